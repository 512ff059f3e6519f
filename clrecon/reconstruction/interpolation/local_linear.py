"""``local_linear``: kernel-weighted local linear regression in phase space (the 5DCT paper).

dc = signed circular difference, da = a - a*. Two nearest points in each of the four
quadrants around the target (dc >= 0 counts as right, da >= 0 as up: a point exactly on an
axis, or on the target, belongs to the non-negative side). Weighted least squares
y ~ b0 + b1 dc + b2 da with w = exp(kappa (cos 2 pi dc - 1)) exp(-da^2 / 2 sigma^2); the
weights l^T = e1^T (X^T W X)^-1 X^T W are solved per row by the OpenCL kernel
``local_linear_weights`` (``kernels/interp.cl``, :func:`local_linear_solve`; float64 NumPy
reference :func:`local_linear_solve_reference`). Fewer than 3 selected points (2 in a 1-D
problem) -> nearest point. Kernel weights below ``LL_WEIGHT_FLOOR`` times the row's largest
are zero (narrow kernels, kappa up to 100 and sigma down to 0.01: the far points drop out
instead of underflowing differently in float32 and float64). Ill-conditioned X^T W X
(collinear points, or a thin cloud far from the target: an eigenvalue of the weighted
covariance of (dc, da) below ``LL_RCOND`` times the points' weighted mean squared distance
to the target) -> fit along the principal direction, i.e. the degenerate direction is
dropped; both directions degenerate (coinciding points, duplicates, spread below
``LL_SPREAD``) -> weighted mean.

EXTRAPOLATION (our choice; the paper is silent): when every selected point lies strictly on
one side of the target along an axis (e.g. a target amplitude above every amplitude sampled
at that view), the slope along that axis is dropped and the fit is locally constant along
it, as 1-D interpolation clamps at the ends of its data. An unguarded linear fit
extrapolates there with weights whose sum of magnitudes reached 7-25 on short scans and
amplifies noise and motion error. ``extrapolate=True`` (``recon.local_linear_extrapolate =
true``) gives the paper's plain fit.
"""

from __future__ import annotations

import numpy as np

from clrecon.core.runtime import get_runtime
from clrecon.reconstruction.interpolation._common import LOCAL as _LOCAL
from clrecon.reconstruction.interpolation._common import take as _take
from clrecon.reconstruction.interpolation.registry import register_method

#: Local linear: points per quadrant and slots per row.
LL_PER_QUADRANT = 2
LL_SLOTS = 4 * LL_PER_QUADRANT
#: Local linear: a direction of the weighted (dc, da) covariance whose eigenvalue is below
#: LL_RCOND times the weighted mean squared distance of the points to the target counts as
#: degenerate and is dropped from the fit (std ratio 1e-2: the fit never extrapolates more
#: than ~100 point spreads, which bounds |weights| and the float32 kernel's error).
LL_RCOND = 1e-4
#: Local linear: spread (std, phase units) below which the points count as coinciding.
LL_SPREAD = 1e-6
#: Local linear: kernel weights below this fraction of the largest one in the row are zero
#: (the point lies outside the kernel). Makes the float32 and float64 solves use the same
#: points whatever kappa and sigma (float32 exp underflows near 1e-38).
LL_WEIGHT_FLOOR = 1e-10
LL_LOG_WEIGHT_FLOOR = float(np.log(LL_WEIGHT_FLOOR))


@register_method(name="local_linear", label="local linear", neighbours=LL_SLOTS, target_grid="5d",
                 axes=("cardiac", "resp"), five_d=True, marker="o", rank=0)
def weights(ch, targets, dc, da, d2, opts):
    return _local_linear(dc, da, d2, opts.use_cardiac, opts.use_resp, opts.kappa, opts.sigma, opts.rt,
                         opts.precision, opts.extrapolate)


def _local_linear_select(dc, da, d2, min_points):
    """Two nearest per quadrant -> (g, T, 8) ids, count, packed first; nearest if too few."""
    quad = (dc < 0).astype(np.int8) + 2 * (da < 0).astype(np.int8)
    ids, oks = [], []
    for q in range(4):
        dq = np.where(quad == q, d2, np.inf)
        two = np.argpartition(dq, LL_PER_QUADRANT - 1, axis=-1)[..., :LL_PER_QUADRANT]
        ids.append(two)
        oks.append(np.isfinite(_take(dq, two)))
    ids = np.concatenate(ids, axis=-1)
    oks = np.concatenate(oks, axis=-1)
    pack = np.argsort(~oks, axis=-1, kind="stable")  # selected slots first
    ids = _take(ids, pack)
    count = oks.sum(axis=-1)
    few = count < min_points
    if np.any(few):
        ids[..., 0] = np.where(few, np.argmin(d2, axis=-1), ids[..., 0])
        count = np.where(few, 1, count)
    return ids, count


def _one_sided(x, live):
    """(...,) True where every live selected value lies strictly on one side of 0."""
    pos = np.where(live, x > 0, True).all(axis=-1)
    neg = np.where(live, x < 0, True).all(axis=-1)
    return pos | neg


def _local_linear(dc, da, d2, use_cardiac, use_resp, kappa, sigma, rt, precision, extrapolate=False):
    min_points = 1 + int(use_cardiac) + int(use_resp)  # 3 in 2-D (the paper), 2 in 1-D
    ids, count = _local_linear_select(dc, da, d2, min_points)
    sel_dc = _take(dc, ids)
    sel_da = _take(da, ids)
    if not extrapolate:
        # No extrapolation along an axis the selected points do not bracket: zero that axis'
        # differences, so the solver's degenerate-direction fallback drops its slope (local
        # constant along it). See EXTRAPOLATION in the module docstring.
        live = np.arange(LL_SLOTS) < count[..., None]
        sel_da = np.where(_one_sided(sel_da, live)[..., None], 0.0, sel_da)
        sel_dc = np.where(_one_sided(sel_dc, live)[..., None], 0.0, sel_dc)
    shape = ids.shape
    l = local_linear_solve(sel_dc.reshape(-1, LL_SLOTS), sel_da.reshape(-1, LL_SLOTS),
                           count.reshape(-1), kappa, sigma, rt=rt, precision=precision)
    l = l.reshape(shape)
    live = np.arange(LL_SLOTS) < count[..., None]
    return np.where(live, ids, 0), np.where(live, l, 0.0)


# ---------------------------------------------------------------------------------------
# local linear solve: OpenCL kernel and its float64 reference
def _check_ll_inputs(dc, da, count):
    dc = np.asarray(dc, dtype=np.float64)
    da = np.asarray(da, dtype=np.float64)
    count = np.asarray(count)
    if dc.ndim != 2 or dc.shape[1] != LL_SLOTS or da.shape != dc.shape or count.shape != dc.shape[:1]:
        raise ValueError(f"expected dc, da of shape (n, {LL_SLOTS}) and count (n,), got "
                         f"{dc.shape}, {da.shape}, {count.shape}")
    if count.size and (count.min() < 0 or count.max() > LL_SLOTS):
        raise ValueError(f"count: must lie in [0, {LL_SLOTS}]")
    return dc, da, count.astype(np.int64)


def local_linear_solve_reference(dc, da, count, kappa: float, sigma: float) -> np.ndarray:
    """Float64 NumPy reference of the ``local_linear_weights`` kernel (same algorithm).

    Parameters
    ----------
    dc, da : array_like
        (n, 8) signed circular cardiac difference and amplitude difference of the selected
        points to the target; only the first ``count[i]`` slots of row i are used.
    count : array_like of int
        (n,) number of selected points.
    kappa, sigma : float
        Kernel widths (paper: 1 and 0.15).

    Returns
    -------
    np.ndarray
        float64 (n, 8): weights l, zero beyond ``count``; each row sums to one (count >= 1).
    """
    x, y, count = _check_ll_inputs(dc, da, count)
    live = np.arange(LL_SLOTS)[None, :] < count[:, None]
    x = np.where(live, x, 0.0)
    y = np.where(live, y, 0.0)
    # kappa (cos 2 pi x - 1) written as -2 kappa sin^2(pi x): no cancellation near x = 0
    sx = np.sin(np.pi * x)
    lw = -2.0 * kappa * sx * sx - y * y / (2.0 * sigma * sigma)
    lw = np.where(live, lw, -np.inf)
    lmax = np.max(lw, axis=1, keepdims=True)
    rel = lw - np.where(np.isfinite(lmax), lmax, 0.0)
    # relative weights below LL_WEIGHT_FLOOR are zero (the point is outside the kernel)
    w = np.where(live & (rel >= LL_LOG_WEIGHT_FLOOR), np.exp(np.where(live, rel, 0.0)), 0.0)
    s0 = w.sum(axis=1)
    s0s = np.where(s0 > 0, s0, 1.0)
    mx, my = (w * x).sum(1) / s0s, (w * y).sum(1) / s0s
    ex, ey = x - mx[:, None], y - my[:, None]
    cxx, cxy, cyy = (w * ex * ex).sum(1) / s0s, (w * ex * ey).sum(1) / s0s, (w * ey * ey).sum(1) / s0s
    half = 0.5 * (cxx - cyy)
    lam1 = 0.5 * (cxx + cyy) + np.sqrt(half * half + cxy * cxy)
    det = cxx * cyy - cxy * cxy
    lam2 = np.where(lam1 > 0, det / np.where(lam1 > 0, lam1, 1.0), 0.0)
    # conditioning relative to the weighted mean squared distance of the points to the target
    thresh = np.maximum(LL_RCOND * (cxx + cyy + mx * mx + my * my), LL_SPREAD ** 2)
    full = lam2 > thresh
    rank1 = (lam1 > thresh) & ~full
    sdet = np.where(full, det, 1.0)
    gx = np.where(full, (cyy * mx - cxy * my) / sdet, 0.0)
    gy = np.where(full, (-cxy * mx + cxx * my) / sdet, 0.0)
    # principal eigenvector, the better-conditioned of the two formulas
    e1x, e1y = cxy, lam1 - cxx
    f1x, f1y = lam1 - cyy, cxy
    use_f = f1x * f1x + f1y * f1y > e1x * e1x + e1y * e1y
    vx, vy = np.where(use_f, f1x, e1x), np.where(use_f, f1y, e1y)
    nrm = np.sqrt(vx * vx + vy * vy)
    nrm = np.where(nrm > 0, nrm, 1.0)
    vx, vy = vx / nrm, vy / nrm
    proj = (vx * mx + vy * my) / np.where(lam1 > 0, lam1, 1.0)
    gx = np.where(rank1, proj * vx, gx)
    gy = np.where(rank1, proj * vy, gy)
    l = w / s0s[:, None] * (1.0 - gx[:, None] * ex - gy[:, None] * ey)
    return np.where(live, l, 0.0)


def _has_fp64(rt) -> bool:
    d = rt.device
    try:
        return "cl_khr_fp64" in d.extensions or bool(d.double_fp_config)
    except Exception:  # pragma: no cover - a driver that does not answer the query
        return False


def local_linear_solve(dc, da, count, kappa: float, sigma: float, rt=None,
                       precision: str | None = None) -> np.ndarray:
    """Local linear weights per row on the OpenCL device (``local_linear_weights`` kernel).

    Same inputs and output as :func:`local_linear_solve_reference`. ``precision`` is
    ``"double"`` (default where the device has cl_khr_fp64) or ``"single"``.
    """
    dc, da, count = _check_ll_inputs(dc, da, count)
    n = dc.shape[0]
    if n == 0:
        return np.zeros((0, LL_SLOTS))
    rt = rt or get_runtime()
    if precision is None:
        precision = "double" if _has_fp64(rt) else "single"
    if precision not in ("double", "single"):
        raise ValueError(f"precision = {precision!r}: must be 'double' or 'single'")
    real = np.float64 if precision == "double" else np.float32
    defines = {"K_SLOTS": LL_SLOTS}
    if precision == "double":
        defines["USE_DOUBLE"] = 1
    knl = rt.kernel("interp.cl", "local_linear_weights", **defines)
    d_dc = rt.to_device(dc.T, real, "dc")  # (K, n): row index fastest for the work-items
    d_da = rt.to_device(da.T, real, "da")
    d_cnt = rt.to_device(count, np.int32, "count")
    d_l = rt.empty((LL_SLOTS, n), real)
    ev = knl(rt.queue, (-(-n // _LOCAL) * _LOCAL,), (_LOCAL,), d_dc, d_da, d_cnt, d_l, np.int32(n),
             real(kappa), real(1.0 / (2.0 * sigma * sigma)), real(LL_RCOND), real(LL_SPREAD ** 2),
             real(LL_LOG_WEIGHT_FLOOR))
    l = rt.from_device(d_l, (LL_SLOTS, n), real, wait_for=[ev])
    return np.ascontiguousarray(l.T, dtype=np.float64)

