"""The projector tests' one tolerance table (tests/simulation/test_projector.py, test_cylindrical.py):
name -> (value, reason). Nothing else in those files is a tolerance."""

import numpy as np

EPS32 = float(np.finfo(np.float32).eps)

#: The one tolerance table: name -> (value, reason).
TOL = {
    # |p - p_ref| <= atol + rtol |p_ref| per ray. rtol: float32 rounding of the record and
    # the sums (a few eps per object). atol: a ray that grazes an object of radius r has a
    # chord 2 r sqrt(1 - rho^2); float32 rho^2 costs ~ r eps / sqrt(1 - rho^2) of chord, at
    # most ~ r sqrt(eps) exactly at tangency ("tangent_atol"). On sampled detectors the
    # measured maximum over 12 random scenes of 10 objects (r <= 60 mm, |mu| <= 0.03) is
    # 1.3e-5; 3e-5 leaves a factor 2.4.
    "kernel_rtol": (2e-5, "float32 records and sums, a few eps per object"),
    "kernel_atol": (3e-5, "grazing rays, measured max 1.3e-5 over 12 random scenes"),
    "tangent_atol": (60.0 * np.sqrt(EPS32) * 0.03 * 2, "worst case at exact tangency: r sqrt(eps) mu"),
    # the phantom: grazing rays on the body outline (r = 160 mm): measured 7e-5; 2e-4 is
    # still 1/10 of the quantum noise of a line integral at 2e5 photons (~2.2e-3)
    "phantom_atol": (2e-4, "grazing rays on the 160 mm body outline"),
    # typical (not worst-case) agreement: root-mean-square over all rays
    "phantom_rms": (2e-6, "float32 accumulation over ~40 objects of line integrals <= 6"),
    # exact chord of a water cylinder: far from its edge only float32 rounding
    "water_rtol": (2e-6, "float32 rounding, rays away from the edge"),
    # the record kernel and its NumPy reference evaluate the same float64 formulas in a
    # different order, then round to float32: a couple of float32 ulps
    "record_rtol": (4 * EPS32, "float64 -> float32 rounding of the same formulas"),
    "record_atol": (1e-9, "o, W0, B0: zero up to float64 rounding (|o| ~ 1e-14, |dc| ~ 1e3)"),
    # culling only removes exact zeros and keeps the summation order
    "culling": (0.0, "culled objects add +0.0; the order of the sum is unchanged"),
    # analytic vs ray marching through the voxelised phantom (3x3x3 supersampled pixels,
    # bilinear, steps of h/4): measured relative RMS 0.71 %, 0.34 %, 0.14 %, 0.064 % at
    # h = 2, 1, 0.5, 0.25 mm (first order in h, as partial-volume edges are)
    "voxel_rel_rms": (0.003, "voxelisation + interpolation error at h = 0.5 mm (measured 0.14 %)"),
    "voxel_convergence": (0.6, "halving h must shrink the error (measured ratio 0.41)"),
    # voxeliser vs float64 point samples: decisions differ only for samples within float32
    # rounding of a surface
    "voxelise_mismatch_fraction": (2e-4, "float32 inside tests of samples on a surface"),
}


def tol(name):
    return TOL[name][0]
