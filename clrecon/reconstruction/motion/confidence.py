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
#: Voxels of one chunk of :func:`shrink_voxels`' per-voxel eigen-solve.
CHUNK_VOXELS = 1 << 18
#: Peak bytes of one field's shrinking per voxel beside its inputs (``estimate.shrunk``: the moving
#: image seen through the field, float32, then :func:`shrink_field` in float64: the field in mm and
#: in voxels, the normalised images, the residual and its box mean, the gradients, the (3, 3)
#: structure tensor per voxel, the shrunk field; under the beat's local prior also the unregistered
#: difference, two more box means and the prior's scale), and beside those the bytes per voxel of
#: one chunk of :func:`shrink_voxels`' eigen-solve (:data:`CHUNK_VOXELS`, or the grid where smaller).
#: Both from a spawned process's peak above its baseline while ``estimate.shrunk`` shrinks one of two
#: fields under the local prior, the larger of the two steps' (its copy of the fields taken off): the
#: line through the peaks on two grids of two and eight full chunks, rounded up; one pair for both
#: steps (measured with ``benchmarks/studies/motion-model/registration_memory.py --shrink --local``;
#: the figures: docs/results/code-history.md "One Lucas-Kanade registration's memory").
SHRINK_BYTES_PER_VOXEL = 210
SHRINK_CHUNK_BYTES_PER_VOXEL = 490


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
    ridge = np.diag(np.maximum(c / np.maximum(prior, 1e-12), floor))
    q = None
    if unregistered is not None:
        q = local_prior_scale(unregistered, r, A, g_noise, prior, size).ravel()
    A = np.moveaxis(A.reshape(3, 3, -1), -1, 0)                      # (N, 3, 3)
    vf = v.reshape(3, -1).T                                          # (N, 3)
    out = np.empty_like(vf)
    trace = np.empty(vf.shape[0])
    for i0 in range(0, vf.shape[0], chunk):
        a = A[i0:i0 + chunk] - np.diag(g_noise)
        w, V = np.linalg.eigh(a)
        a_s = np.einsum("nik,nk,njk->nij", V, np.maximum(w, 0.0), V)
        if q is None:
            S = np.linalg.solve(a_s + ridge, a_s)
        else:  # the prior P q(x): the ridge c / (P q), as large as 1 / floor where nothing is seen
            rq = c / np.maximum(prior[None, :] * q[i0:i0 + chunk, None], c * floor)
            S = np.linalg.solve(a_s + rq[:, :, None] * np.eye(3), a_s)
        out[i0:i0 + chunk] = np.einsum("nij,nj->ni", S, vf[i0:i0 + chunk])
        trace[i0:i0 + chunk] = np.trace(S, axis1=1, axis2=2) / 3.0
    info = {"residual_std": s_r, "n_eff": n_eff, "prior_rms_vox": np.sqrt(prior).tolist(),
            "gradient_noise_var": g_noise.tolist(), "mean_gain": float(trace[m.ravel()].mean())}
    if q is not None:
        info["mean_prior_scale"] = float(q[m.ravel()].mean())
    return out.T.reshape(v.shape), info


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
