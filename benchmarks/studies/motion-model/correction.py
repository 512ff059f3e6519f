"""Model-based correction step: the model at the target plus the interpolated residual of the rows.

Study code, outside the wheel (the variant B of docs/motion-model.md; the shipped ``mc`` method
is the motion-compensated backprojection, variant A). Imported by ``common.py`` here.

For a target t, with M(s) the model image at state s (a reference-frame image warped by the motion
model, :mod:`warp` here) and P_k the in-plane projection of row k (its
slice, its view):

    image_t = M(t) + FBP( sum_k w_k (y_k - P_k M(s_k)) )

w_k an interpolation method's weights (barycentric), y_k the SSRB rows. Equivalently the method's
own image minus the error the model predicts for it, ``FBP(sum_k w_k P_k M(s_k)) - M(t)``: a model
error that does not change with the state cancels to first order, and what the model cannot hold
(the lungs' density change with breathing, sliding, anything the warp gets wrong) stays in the
residual and is interpolated as before. docs/motion-model.md "The method" (step 6).

The residual needs P_k M(s_k) for every row the weights use. Rows are grouped by state into a
(cardiac x amplitude) grid of bins (``state_bins``); each bin's model volume is warped once at the
slices, and all (bin, slice) images are projected together by the voxel projector
(:mod:`clrecon.simulation.voxel_projector`, Joseph's method) as the slices of one stack: each row's
rays lie in its image's plane, in the geometry of the ground truth's in-plane rows
(``clrecon.evaluation.groundtruth.groundtruth_sinograms``: flat or cylindrical cells, a flying
focal spot's source angle and radius).
"""

from __future__ import annotations

import math

import numpy as np
from warp import warp

from clrecon.evaluation.consistency import STACK_DZ_MM, inplane_frames
from clrecon.reconstruction.fbp import FanBeamGeometry
from clrecon.reconstruction.motion.model import FieldGrid, MotionModel
from clrecon.simulation.voxel_projector import project_volume


def state_bins(cardiac_phase, resp_amplitude, n_cardiac: int, n_resp: int):
    """Bin index of each state (n,) and the bins' centre states (n_cardiac * n_resp, 2).

    Cardiac bins are periodic, of width 1/n_cardiac, centred on i/n_cardiac (so the lattice of the
    targets is on bin centres); amplitude bins of width 1/n_resp over [0, 1] centred on
    (j + 1/2)/n_resp. ``n_cardiac = 1`` or ``n_resp = 1`` collapses that axis.
    """
    for name, v in (("n_cardiac", n_cardiac), ("n_resp", n_resp)):
        if not (isinstance(v, (int, np.integer)) and v >= 1):
            raise ValueError(f"{name} = {v!r}: must be an integer >= 1")
    c = np.asarray(cardiac_phase, np.float64)
    a = np.asarray(resp_amplitude, np.float64)
    ic = np.round(np.mod(c, 1.0) * n_cardiac).astype(np.int64) % n_cardiac
    ia = np.clip(np.floor(np.clip(a, 0.0, 1.0) * n_resp), 0, n_resp - 1).astype(np.int64)
    cc, aa = np.meshgrid(np.arange(n_cardiac) / n_cardiac, (np.arange(n_resp) + 0.5) / n_resp, indexing="ij")
    return ic * n_resp + ia, np.stack([cc.ravel(), aa.ravel()], axis=1)


def model_rows(model_volume_mu, model: MotionModel, detector, geom: FanBeamGeometry, pair_view, pair_slice_z,
               pair_state, *, bins: tuple = (20, 10), volume_grid: FieldGrid | None = None,
               rt=None) -> np.ndarray:
    """In-plane projections of the model at each row's (binned) state, (p, C) float32.

    Parameters
    ----------
    model_volume_mu : (nz, ny, nx) attenuation (1/mm) in the model's reference frame, on ``volume_grid``
        (default the model's grid; finer z planes are better: docs/motion-model.md)
    model : MotionModel
    detector : the scanner's detector model (``scanner.detector_model``)
    geom : FanBeamGeometry of the reconstruction
    pair_view : (p,) int view index j of each row; pair_slice_z : (p,) its slice z (mm)
    pair_state : (p, 2) its recorded (c, a)
    bins : (n_cardiac, n_resp) of :func:`state_bins`
    """
    view = np.asarray(pair_view, np.int64)
    z = np.asarray(pair_slice_z, np.float64)
    st = np.asarray(pair_state, np.float64)
    if view.ndim != 1 or z.shape != view.shape or st.shape != view.shape + (2,):
        raise ValueError(f"pair_view {view.shape}, pair_slice_z {z.shape}, pair_state {st.shape}: "
                         "expected (p,), (p,), (p, 2)")
    if view.size and (view.min() < 0 or view.max() >= geom.n_views):
        raise ValueError(f"pair_view: views must lie in [0, {geom.n_views})")
    b, centres = state_bins(st[:, 0], st[:, 1], *bins)
    zs, zi = np.unique(z, return_inverse=True)
    used_bins, bi = np.unique(b, return_inverse=True)
    images = warp(model_volume_mu, model, centres[used_bins], zs, runtime=rt, volume_grid=volume_grid)
    stack = images.reshape((-1,) + images.shape[2:])                             # q = bin * S + slice
    q = bi * len(zs) + zi
    g = model.grid
    origin = (-0.5 * (g.nx - 1) * g.voxel_mm, -0.5 * (g.ny - 1) * g.voxel_mm, 0.0)
    (src, centre, eu, ev), u, vs = inplane_frames(detector, geom, view, q * STACK_DZ_MM)
    out = project_volume(stack, origin, (g.voxel_mm, g.voxel_mm, STACK_DZ_MM), src, centre, eu, ev, u,
                         np.zeros(1), rt=rt, v_scale=vs)
    return out[:, 0, :]


def interpolate_rows(rows, pair_index, weight) -> np.ndarray:
    """Sinograms (B, V, C) = sum_k weight[b, v, k] rows[pair_index[b, v, k]] (float64 sums, float32 out).

    ``pair_index`` (B, V, K) int into ``rows`` (p, C) (any value where the weight is 0).
    """
    r = np.asarray(rows, np.float32)
    idx = np.asarray(pair_index, np.int64)
    w = np.asarray(weight, np.float64)
    if idx.shape != w.shape or idx.ndim != 3:
        raise ValueError(f"pair_index {idx.shape} and weight {w.shape}: expected (B, V, K) each")
    out = np.zeros(idx.shape[:2] + (r.shape[1],), np.float64)
    for k in range(idx.shape[2]):
        wk = w[..., k]
        nz = wk != 0
        out[nz] += wk[nz, None] * r[idx[..., k][nz]]
    return out.astype(np.float32)


def corrected_images(residual_fbp_mu, model_at_target_mu, fov_mask, mu_water: float) -> np.ndarray:
    """HU of ``M(t) + FBP(residual)`` (both mu, (..., ny, nx)); -1000 outside the FOV like the FBP."""
    if not math.isfinite(mu_water) or mu_water <= 0:
        raise ValueError(f"mu_water = {mu_water!r}: must be > 0")
    mu = np.where(fov_mask, np.asarray(model_at_target_mu) + np.asarray(residual_fbp_mu), 0.0)
    return (1000.0 * (mu - mu_water) / mu_water).astype(np.float32)
