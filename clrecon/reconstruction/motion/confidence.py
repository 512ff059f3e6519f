"""Shrink a registered field towards zero where the images cannot show the motion.

A window registration (Lucas-Kanade) solves, per voxel, ``A v = b`` with ``A`` the window mean of
the image gradient's outer product (the structure tensor). Where the window holds no structure
(a texture-poor soft-tissue region, a flat blood pool far from a wall, noise only) ``A`` is the
noise's and the field there is invented: it follows the noise, the streaks, or the coarse levels'
guess. This module replaces each registered displacement by its posterior mean under a Gaussian
prior centred on zero (no motion), the Wiener form of a ridge towards zero::

    v = (A_s + (s_r^2 / N_eff) P^-1)^-1 A_s v_hat

with every quantity measured on the images themselves, nothing tuned:

- ``A_s``: the structure tensor of the fixed image (window of the registration's radius) less
  the noise's own expected contribution (the gradient noise variance per axis), projected onto
  the positive semi-definite matrices: the texture the window really holds;
- ``s_r``: the robust (MAD) standard deviation of the registration's residual ``fixed(x) -
  moving(x + u(x))``, i.e. what the registration cannot explain (noise, streaks, model misfit);
- ``N_eff``: the independent samples in a window, ``s_r^2 / var(window mean of the residual)``
  (correlated noise and streaks give fewer than the window's voxels);
- ``P``: the prior covariance of the displacement, diagonal, the field's own mean square per
  axis over the voxels inside the HU window (an empirical Bayes prior).

Where the texture is strong (``A_s`` much larger than ``s_r^2 / (N_eff P)``) the factor is the
identity and the field is unchanged; where there is none it is zero; in between it shrinks
along the directions the window cannot see (an edge shows motion across it, not along it).
The gradient noise variance per axis is the robust (MAD) variance of the fixed image's gradient
inside the HU window: most of a CT volume is flat tissue, where the gradient is noise, and the MAD
treats the edges as outliers.

The beat step's fields are shrunk under a *local* prior (``unregistered`` of :func:`shrink_voxels`,
:func:`local_prior_scale`): ``P`` times the share of the images' difference that the field explains
in the window, so a field in a textured tissue that the step does not move (the chest wall, whose
cardiac-phase images differ by streaks only) is taken back although the texture could show it.
The beat moves the heart and its neighbours only, so "no motion where none is explained" is the
right fallback for it; breathing moves the whole trunk, and where its beat-averaged images (the
heart blurred by the beat) explain little, zero is the wrong fallback: its step keeps the global prior
(docs/motion-model.md "Knobs": ``shrink``). Fields here are in voxel units per axis (z, y, x) of the registration grid.
Shapes: images (nz, ny, nx); fields (3, nz, ny, nx) as :mod:`clrecon.reconstruction.motion.registration`
returns them (mm, components (dx, dy, dz)).
"""

from __future__ import annotations

import numpy as np
import scipy.ndimage

#: MAD to standard deviation of a normal distribution.
MAD_TO_STD = 1.4826
#: Voxels of one chunk of :func:`shrink_voxels`' per-voxel 3 x 3 algebra (:func:`psd_part`, :func:`shrink_solve`).
CHUNK_VOXELS = 1 << 18
#: Peak bytes of one field's shrinking per voxel beside its inputs (``estimate.shrunk``: the moving
#: image seen through the field, float32, then :func:`shrink_field` in float64: the field in mm and
#: in voxels, the normalised images, the residual and its box mean, the gradients, the (3, 3)
#: structure tensor per voxel, the shrunk field; under the beat's local prior also the unregistered
#: difference, two more box means and the prior's scale), and beside those the bytes per voxel of
#: one chunk of :func:`shrink_voxels`' closed-form solve (:data:`CHUNK_VOXELS`, or the grid where
#: smaller). Both from a spawned process's peak above its baseline while ``estimate.shrunk`` shrinks
#: one of two fields (its copy of the fields taken off): the line through the peaks on two grids of
#: two and eight full chunks, for each prior, rounded up to 10 bytes; one pair for both steps
#: (measured with ``benchmarks/studies/motion-model/registration_memory.py --shrink [--local]``;
#: the figures: docs/results/code-history.md "One Lucas-Kanade registration's memory").
SHRINK_BYTES_PER_VOXEL = 180
SHRINK_CHUNK_BYTES_PER_VOXEL = 420


def _robust_std(x: np.ndarray) -> float:
    x = np.asarray(x, np.float64)
    if x.size == 0:
        return 0.0
    return MAD_TO_STD * float(np.median(np.abs(x - np.median(x))))


def normalise(volume, hu_window: tuple) -> np.ndarray:
    """``volume`` clipped to ``hu_window`` and scaled by its width (the registration's intensities), float64."""
    lo, hi = hu_window
    return np.clip(np.asarray(volume, np.float64), lo, hi) / (hi - lo)


def shrink_voxels(fixed, residual, field_vox, radius: int, inside,
                  chunk: int = CHUNK_VOXELS, unregistered=None) -> tuple[np.ndarray, dict]:
    """``field_vox`` times the per-voxel 3 x 3 shrinkage ``(A_s + c P^-1)^-1 A_s`` (module docstring).

    Parameters
    ----------
    fixed : (nz, ny, nx) the fixed image, normalised (:func:`normalise`)
    residual : (nz, ny, nx) ``fixed - moving(x + u(x))``, normalised
    field_vox : (3, nz, ny, nx) the registered field in voxels along (z, y, x)
    radius : the registration window's radius (voxels)
    inside : (nz, ny, nx) bool, the voxels the noise and prior are measured on (inside the HU window)
    chunk : voxels whose 3 x 3 systems are solved at once (memory only: the same bits for any value)
    unregistered : optional (nz, ny, nx) ``fixed - moving``, normalised, without the field: the prior
        becomes local (:func:`local_prior_scale`): the global one times the share of the images'
        difference the field explains at each voxel

    Returns
    -------
    ((3, nz, ny, nx) float64 voxels, info: the measured noise ``residual_std``, ``n_eff``,
    ``prior_rms_vox`` (3,) along (z, y, x), ``gradient_noise_var`` (3,) and ``mean_gain`` (the
    mean of the trace of the shrinkage over 3 inside the HU window: 1 = unchanged, 0 = all shrunk)).
    """
    f = np.asarray(fixed, np.float64)
    r = np.asarray(residual, np.float64)
    v = np.asarray(field_vox, np.float64)
    size = 2 * int(radius) + 1
    m = np.asarray(inside, bool)
    if m.sum() < 2:
        m = np.ones_like(m)
    s_r = _robust_std(r[m])
    var_mean = _robust_std(_box(r, size)[m]) ** 2
    n_eff = float(np.clip(s_r ** 2 / var_mean, 1.0, size ** 3)) if var_mean > 0 else float(size ** 3)
    g = np.gradient(f)
    g_noise = np.array([_robust_std(gr[m]) ** 2 for gr in g])
    A = np.empty((3, 3) + f.shape, np.float64)
    for i in range(3):
        for j in range(i, 3):
            A[i, j] = A[j, i] = _box(g[i] * g[j], size)
    del g
    prior = np.array([float(np.mean(v[k][m] ** 2)) for k in range(3)])
    c = s_r ** 2 / n_eff
    # a floor far below any texture keeps the systems regular where the residual is exactly 0
    # (identical images: nothing to shrink towards but nothing seen where A_s = 0 either)
    scale = float(np.mean((A[0, 0] + A[1, 1] + A[2, 2])[m])) / 3.0
    floor = 1e-12 * (scale if scale > 0 else 1.0)
    ridge = np.maximum(c / np.maximum(prior, 1e-12), floor)          # the global prior's, per axis
    q = None
    if unregistered is not None:
        q = local_prior_scale(unregistered, r, A, g_noise, prior, size).ravel()
    comps = [(A[i, j] - (g_noise[i] if i == j else 0.0)).ravel() for i, j in _UPPER]  # A - diag(noise)
    del A
    vf = v.reshape(3, -1)                                            # (3, N)
    out = np.empty_like(vf)
    trace = np.empty(vf.shape[1])
    for i0 in range(0, vf.shape[1], chunk):
        part = slice(i0, i0 + chunk)
        a_s = psd_part([a[part] for a in comps])
        if q is None:
            ridges = list(ridge)
        elif c > 0:  # the prior P q(x): the ridge c / (P q), as large as 1 / floor where nothing is seen
            ridges = [np.maximum(c / np.maximum(prior[k] * q[part], c * floor), floor) for k in range(3)]
        else:  # a residual of exactly 0 (nothing unexplained): the global prior's floor, not 0 / 0
            ridges = [floor] * 3
        out[:, part], trace[part] = shrink_solve(a_s, ridges, vf[:, part])
    info = {"residual_std": s_r, "n_eff": n_eff, "prior_rms_vox": np.sqrt(prior).tolist(),
            "gradient_noise_var": g_noise.tolist(), "mean_gain": float(trace[m.ravel()].mean())}
    if q is not None:
        info["mean_prior_scale"] = float(q[m.ravel()].mean())
    return out.reshape(v.shape), info


#: Eigenvalue gap (of a matrix scaled to a largest component of 1) below which :func:`psd_part`
#: hands the matrix to LAPACK: the closed form's eigenvalues err by about eps / gap there (1e-12 at
#: this gap), up to sqrt(eps) where two eigenvalues meet.
NEAR_DEGENERATE = 1e-4
#: The upper triangle of a symmetric 3 x 3 matrix, in the order :func:`psd_part` and
#: :func:`shrink_solve` take its components: (0,0), (0,1), (0,2), (1,1), (1,2), (2,2).
_UPPER = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))
#: Entry (i, j) of the full matrix: its index in :data:`_UPPER`.
_FULL = ((0, 1, 2), (1, 3, 4), (2, 4, 5))


def _eigvals_sym3(a00, a01, a02, a11, a12, a22):
    """Eigenvalues (lo, mid, hi) of symmetric 3 x 3 matrices given by their upper-triangle
    components (arrays of one shape), in closed form (the trigonometric solution of the
    characteristic cubic; Smith, Comm. ACM 4:168, 1961): absolute error a few ulp of the matrix's
    norm where the eigenvalues lie apart, growing as eps / gap where two approach each other (up to
    sqrt(eps) where they meet: :func:`psd_part` hands those matrices to LAPACK)."""
    q = (a00 + a11 + a22) / 3.0
    b00, b11, b22 = a00 - q, a11 - q, a22 - q
    p = np.sqrt((b00 * b00 + b11 * b11 + b22 * b22 + 2.0 * (a01 * a01 + a02 * a02 + a12 * a12)) / 6.0)
    det = b00 * (b11 * b22 - a12 * a12) - a01 * (a01 * b22 - a12 * a02) + a02 * (a01 * a12 - b11 * a02)
    with np.errstate(divide="ignore", invalid="ignore"):
        r = np.where(p > 0, det / (2.0 * p * p * p), 0.0)
    phi = np.arccos(np.clip(r, -1.0, 1.0)) / 3.0
    hi = q + 2.0 * p * np.cos(phi)
    lo = q + 2.0 * p * np.cos(phi + 2.0 * np.pi / 3.0)
    return lo, 3.0 * q - lo - hi, hi


def _eigvec_sym3(a, lam):
    """Unit eigenvectors (3 arrays) of the symmetric matrices ``a`` (6 upper-triangle components)
    for their eigenvalues ``lam``: the largest of the three cross products of the rows of
    ``a - lam I`` (stable to about eps |a| / the gap to the other eigenvalues; where every cross
    product vanishes the vector is (1, 0, 0), a case the callers weight by a vanishing amount)."""
    a00, a01, a02, a11, a12, a22 = a
    r0 = (a00 - lam, a01, a02)
    r1 = (a01, a11 - lam, a12)
    r2 = (a02, a12, a22 - lam)

    def cross(u, w):
        return (u[1] * w[2] - u[2] * w[1], u[2] * w[0] - u[0] * w[2], u[0] * w[1] - u[1] * w[0])

    cands = [cross(r0, r1), cross(r0, r2), cross(r1, r2)]
    norms = np.stack([c[0] * c[0] + c[1] * c[1] + c[2] * c[2] for c in cands])
    pick = np.argmax(norms, axis=0)
    n2 = np.take_along_axis(norms, pick[None], 0)[0]
    vec = [np.choose(pick, [c[k] for c in cands]) for k in range(3)]
    ok = n2 > 0
    inv = np.where(ok, 1.0 / np.sqrt(np.where(ok, n2, 1.0)), 0.0)
    return vec[0] * inv + np.where(ok, 0.0, 1.0), vec[1] * inv, vec[2] * inv


def psd_part(a):
    """The nearest positive semi-definite matrices (in the Frobenius norm) to the symmetric 3 x 3
    matrices ``a``: their eigen-decompositions with the negative eigenvalues set to 0.

    ``a``: the 6 upper-triangle components (:data:`_UPPER`'s order), float64 arrays of one shape;
    returns the same for the result. Closed form per voxel, vectorised (the per-matrix LAPACK call
    of ``numpy.linalg.eigh`` on millions of 3 x 3 matrices was most of a registration round's
    shrinking): with no negative eigenvalue the matrix itself; with all three, zero; with one, the
    matrix less ``lam_lo v_lo v_lo^T``; with two, ``lam_hi v_hi v_hi^T`` -- the eigenvector used is
    always that of an eigenvalue separated from the others by at least its own magnitude, so its
    error is at most a few ulp of the matrix's norm. Where that eigenvalue lies within
    :data:`NEAR_DEGENERATE` of another (there the closed form's eigenvalues lose half their digits),
    ``numpy.linalg.eigh`` does those matrices. Tested against ``eigh`` on random and degenerate
    matrices to 1e-12 of the norm (tests/reconstruction/test_motion_confidence.py)."""
    a = [np.asarray(x, np.float64) for x in a]
    big = np.maximum.reduce([np.abs(x) for x in a])
    unit = [x / np.where(big > 0, big, 1.0) for x in a]               # scale-free: no under- or overflow
    lo, mid, hi = _eigvals_sym3(*unit)
    n_neg = (lo < 0).astype(np.int8) + (mid < 0) + (hi < 0)
    # the closed form's eigenvalues err by up to sqrt(eps) where two of them meet: LAPACK where the
    # eigenvalue whose vector is used lies that close to another (a pair at 0 of exactly repeated
    # eigenvalues: zeros, diagonal blocks; rare in images)
    near = ((n_neg == 1) & (mid - lo < NEAR_DEGENERATE)) | ((n_neg == 2) & (hi - mid < NEAR_DEGENERATE))
    n_neg[near] = -1
    out = [x.copy() for x in a]
    if near.any():
        w, vec = np.linalg.eigh(np.stack([np.stack([unit[_FULL[i][j]][near] for j in range(3)], -1)
                                          for i in range(3)], -2))
        fixed = np.einsum("nik,nk,njk->nij", vec, np.maximum(w, 0.0), vec) * big[near][:, None, None]
        for k, (i, j) in enumerate(_UPPER):
            out[k][near] = fixed[:, i, j]
    one = n_neg == 1
    if one.any():
        v = _eigvec_sym3([x[one] for x in unit], lo[one])
        for k, (i, j) in enumerate(_UPPER):
            out[k][one] -= (lo[one] * big[one]) * v[i] * v[j]
    two = n_neg == 2
    if two.any():
        v = _eigvec_sym3([x[two] for x in unit], hi[two])
        for k, (i, j) in enumerate(_UPPER):
            out[k][two] = (hi[two] * big[two]) * v[i] * v[j]
    three = n_neg == 3
    for x in out:
        x[three] = 0.0
    return out


def shrink_solve(a_s, ridge, v):
    """``S v`` and ``trace(S) / 3`` of the shrinkage ``S = (a_s + R)^-1 a_s`` per voxel.

    ``a_s``: 6 upper-triangle components of positive semi-definite 3 x 3 matrices (arrays of N);
    ``ridge``: the diagonal of R (3 arrays of N, or broadcastable), positive; ``v``: (3, N).
    With ``M = a_s + R`` (symmetric positive definite), solved by a Cholesky factorisation of ``M``
    scaled to a unit diagonal (the ridge may exceed the texture by 12 orders of magnitude where
    nothing is seen): ``S v = M^-1 (a_s v)`` (exactly 0 where ``a_s`` is), and, as ``S = I - M^-1 R``,
    ``trace(S) = 3 - sum_k R_kk (M^-1)_kk``. Returns ((3, N), (N,))."""
    m = [np.asarray(x, np.float64).copy() for x in a_s]
    r = [np.broadcast_to(np.asarray(x, np.float64), m[0].shape) for x in ridge]
    m[0] += r[0]
    m[3] += r[1]
    m[5] += r[2]
    d = [1.0 / np.sqrt(m[0]), 1.0 / np.sqrt(m[3]), 1.0 / np.sqrt(m[5])]   # M' = D M D, unit diagonal
    b01, b02, b12 = m[1] * d[0] * d[1], m[2] * d[0] * d[2], m[4] * d[1] * d[2]
    tiny = np.finfo(np.float64).tiny
    l11 = np.sqrt(np.maximum(1.0 - b01 * b01, tiny))                 # M' = L L^T, l00 = 1
    l21 = (b12 - b02 * b01) / l11
    l22 = np.sqrt(np.maximum(1.0 - b02 * b02 - l21 * l21, tiny))
    # L^-1 (lower triangular): its column norms squared are the diagonal of M'^-1
    i10 = -b01 / l11
    i20 = (b01 * l21 / l11 - b02) / l22
    i21 = -l21 / (l11 * l22)
    i11, i22 = 1.0 / l11, 1.0 / l22
    minv_diag = [(1.0 + i10 * i10 + i20 * i20) * d[0] ** 2, (i11 * i11 + i21 * i21) * d[1] ** 2,
                 (i22 * i22) * d[2] ** 2]
    av = [sum(a_s[_FULL[i][j]] * v[j] for j in range(3)) for i in range(3)]
    rhs = [av[k] * d[k] for k in range(3)]                            # D (a_s v)
    y0 = rhs[0]                                                       # L y = D a_s v
    y1 = i10 * rhs[0] + i11 * rhs[1]
    y2 = i20 * rhs[0] + i21 * rhs[1] + i22 * rhs[2]
    x2 = y2 * i22                                                     # L^T x = y
    x1 = (y1 - l21 * x2) * i11
    x0 = y0 - b01 * x1 - b02 * x2
    out = np.stack([x0 * d[0], x1 * d[1], x2 * d[2]])
    trace = (3.0 - (r[0] * minv_diag[0] + r[1] * minv_diag[1] + r[2] * minv_diag[2])) / 3.0
    return out, trace


def local_prior_scale(unregistered, registered, A, g_noise, prior, size: int) -> np.ndarray:
    """q(x) in [0, 1]: the share of the global prior ``prior`` (per axis, voxels squared) that the
    field explains at x, by the method of moments on the registration's window.

    In the window, the difference ``r0 = fixed - moving`` without the field holds the motion's own
    intensity change and what no field explains; with the field, ``r1 = fixed - moving(x + u(x))``
    holds only the latter. So ``mean_w(r0^2) - mean_w(r1^2) ~ sum_k A_s,kk P_k q`` (linearised;
    ``A_s`` the window's structure tensor less the gradient noise, ``P`` the global prior), and
    ``q = (mean_w(r0^2) - mean_w(r1^2)) / sum_k A_s,kk P_k``, clipped to [0, 1]: 0 where the field
    explains nothing of the images' difference (a tissue the step does not move, whose images
    differ by streaks only), 1 where it explains at least the global prior's share (the global
    prior is never exceeded). Shapes: ``unregistered``, ``registered`` (nz, ny, nx) normalised
    intensities; ``A`` (3, 3, nz, ny, nx) window means of the gradient's outer product; ``g_noise``,
    ``prior`` (3,). Returns (nz, ny, nx) float64."""
    seen = _box(np.asarray(unregistered, np.float64) ** 2, size)
    seen -= _box(np.asarray(registered, np.float64) ** 2, size)
    expected = sum(np.maximum(A[k, k] - g_noise[k], 0.0) * prior[k] for k in range(3))
    with np.errstate(divide="ignore", invalid="ignore"):
        q = np.where(expected > 0, np.maximum(seen, 0.0) / expected, 0.0)
    return np.minimum(q, 1.0)


def _box(a, size: int) -> np.ndarray:
    """The registration window's mean (a flat (size,)*3 window, mirrored at the edges, as Lucas-Kanade's)."""
    return scipy.ndimage.uniform_filter(a, size=size, mode="mirror")


def shrink_field(fixed, moving_at_ref, field, spacing_mm: tuple, radius: int,
                 hu_window: tuple, moving=None) -> tuple[np.ndarray, dict]:
    """``field`` shrunk towards zero where ``fixed`` holds too little structure to show it (module docstring).

    Parameters
    ----------
    fixed : (nz, ny, nx) HU, the registration's fixed image
    moving_at_ref : (nz, ny, nx) HU, the moving image seen through the field: ``moving(x + u(x))``
    field : (3, nz, ny, nx) mm, components (dx, dy, dz)
    spacing_mm : (dx, dy, dz) voxel spacing
    radius : the registration window's radius (voxels)
    hu_window : (lo, hi) the HU the registration clips to
    moving : optional (nz, ny, nx) HU, the moving image itself: the prior becomes local
        (:func:`local_prior_scale`)

    Returns
    -------
    ((3, nz, ny, nx) float32 mm, info of :func:`shrink_voxels`)
    """
    u = np.asarray(field, np.float64)
    sp = np.asarray(spacing_mm, np.float64)
    f = normalise(fixed, hu_window)
    r = f - normalise(moving_at_ref, hu_window)
    lo, hi = hu_window
    fx = np.asarray(fixed, np.float64)
    inside = (fx > lo) & (fx < hi)
    vox = np.stack([u[2] / sp[2], u[1] / sp[1], u[0] / sp[0]])        # (z, y, x) voxels
    r0 = None if moving is None else f - normalise(moving, hu_window)
    out, info = shrink_voxels(f, r, vox, radius, inside, unregistered=r0)
    return np.stack([out[2] * sp[0], out[1] * sp[1], out[0] * sp[2]]).astype(np.float32), info
