"""``local_linear``: kernel-weighted local linear regression in phase space (the 5DCT paper).

dc = signed circular difference, da = a - a*. Two nearest points in each of the four
quadrants around the target (dc >= 0 counts as right, da >= 0 as up: a point exactly on an
axis, or on the target, belongs to the non-negative side); ``recon.local_linear_count`` sets
the points per quadrant (K = 4 count slots), and ``recon.local_linear_points = "nearest"``
takes the ``count`` nearest points overall instead (K = count; the paper's Figure 2B caption
speaks of the five nearest, its text of two per quadrant). Weighted least squares
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
it, as 1-D interpolation clamps at the ends of its data. Only that axis' column of the design
matrix goes: the kernel weights w still come from the true (dc, da), so the fit keeps
favouring the points nearest the target along the guarded axis, and the fit becomes
y ~ b0 + b1 dc (amplitude guarded), y ~ b0 + b2 da (cardiac guarded) or the weighted mean
(both). The solver receives the guard as a per-row flag (``guard``: bit ``LL_GUARD_CARDIAC``,
bit ``LL_GUARD_RESP``); the remaining columns keep the LL_RCOND / LL_SPREAD fallbacks. An
unguarded linear fit extrapolates there with weights whose sum of magnitudes reached 7-25 on
short scans and amplifies noise and motion error. ``extrapolate=True``
(``recon.local_linear_extrapolate = true``) gives the paper's plain fit (every flag 0).
"""

from __future__ import annotations

import numpy as np

from clrecon.core.runtime import get_runtime
from clrecon.reconstruction.interpolation._common import LOCAL as _LOCAL
from clrecon.reconstruction.interpolation._common import take as _take
from clrecon.reconstruction.interpolation.registry import register_method

#: Local linear: points per quadrant and slots per row, by default (the paper's text: two
#: nearest per quadrant); ``recon.local_linear_points`` / ``local_linear_count`` change them.
LL_PER_QUADRANT = 2
LL_SLOTS = 4 * LL_PER_QUADRANT
#: Local linear neighbour rules: ``count`` nearest per quadrant (K = 4 count slots), or the
#: ``count`` nearest overall (K = count; the paper's Figure 2B caption: the five nearest).
LL_POINT_RULES = ("quadrants", "nearest")
#: Local linear: most slots per row (the kernel keeps three private arrays of K_SLOTS reals).
LL_MAX_SLOTS = 32
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
#: Local linear ``guard`` flag bits (per row): drop the dc slope / the da slope from the fit
#: (the extrapolation guard; the kernel weights still use the true differences).
LL_GUARD_CARDIAC = 1
LL_GUARD_RESP = 2


@register_method(name="local_linear", label="local linear", neighbours=LL_SLOTS, target_grid="5d",
                 axes=("cardiac", "resp"), five_d=True, marker="o", rank=0)
def weights(ch, targets, dc, da, d2, opts):
    return _local_linear(dc, da, d2, opts.use_cardiac, opts.use_resp, opts.kappa, opts.sigma, opts.rt,
                         opts.precision, opts.extrapolate, opts.local_linear_points, opts.local_linear_count)


def slot_count(points: str = "quadrants", count: int = LL_PER_QUADRANT) -> int:
    """K, the slots per row of the neighbour rule ``points`` with ``count`` (see :data:`LL_POINT_RULES`)."""
    if points not in LL_POINT_RULES:
        raise ValueError(f"local_linear_points = {points!r}: must be one of {', '.join(LL_POINT_RULES)}")
    k = 4 * count if points == "quadrants" else count
    if not (isinstance(count, (int, np.integer)) and count >= 1 and k <= LL_MAX_SLOTS):
        raise ValueError(f"local_linear_count = {count!r}: must be an integer >= 1 with "
                         f"{'4 x count' if points == 'quadrants' else 'count'} <= {LL_MAX_SLOTS}")
    return int(k)


def _smallest(x, k):
    """Positions of the k smallest of x along the last axis, (..., k); x padded with inf if shorter."""
    n = x.shape[-1]
    if n < k:
        x = np.concatenate([x, np.full(x.shape[:-1] + (k - n,), np.inf)], axis=-1)
    return np.argpartition(x, k - 1, axis=-1)[..., :k]


def _local_linear_select(dc, da, d2, min_points, points="quadrants", count=LL_PER_QUADRANT):
    """Neighbours -> (g, T, K) ids, count, selected first; the nearest point if too few.

    ``points = "quadrants"``: the ``count`` nearest in each quadrant (K = 4 count);
    ``"nearest"``: the ``count`` nearest overall (K = count). Distances are ``d2`` (inf for
    padding); a slot past the candidates (a group with fewer than K) is unselected.
    """
    K = slot_count(points, count)
    if points == "nearest":
        ids = _smallest(d2, K)
        oks = ids < d2.shape[-1]
        ids = np.where(oks, ids, 0)
        oks &= np.isfinite(_take(d2, ids))
    else:
        quad = (dc < 0).astype(np.int8) + 2 * (da < 0).astype(np.int8)
        ids, oks = [], []
        for q in range(4):
            dq = np.where(quad == q, d2, np.inf)
            near = _smallest(dq, count)
            ok = near < dq.shape[-1]
            near = np.where(ok, near, 0)
            ids.append(near)
            oks.append(ok & np.isfinite(_take(dq, near)))
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


def _local_linear(dc, da, d2, use_cardiac, use_resp, kappa, sigma, rt, precision, extrapolate=False,
                  points="quadrants", n_points=LL_PER_QUADRANT):
    min_points = 1 + int(use_cardiac) + int(use_resp)  # 3 in 2-D (the paper), 2 in 1-D
    ids, count = _local_linear_select(dc, da, d2, min_points, points, n_points)
    K = ids.shape[-1]
    sel_dc = _take(dc, ids)
    sel_da = _take(da, ids)
    guard = np.zeros(count.shape, np.int32)
    if not extrapolate:
        # No extrapolation along an axis the selected points do not bracket: the solver drops
        # that axis' slope column (local constant along it) but keeps the kernel weights of
        # the true differences. See EXTRAPOLATION in the module docstring.
        live = np.arange(K) < count[..., None]
        guard = np.where(_one_sided(sel_dc, live), LL_GUARD_CARDIAC, 0) \
            | np.where(_one_sided(sel_da, live), LL_GUARD_RESP, 0)
    shape = ids.shape
    l = local_linear_solve(sel_dc.reshape(-1, K), sel_da.reshape(-1, K),
                           count.reshape(-1), kappa, sigma, rt=rt, precision=precision,
                           guard=guard.reshape(-1))
    l = l.reshape(shape)
    live = np.arange(K) < count[..., None]
    return np.where(live, ids, 0), np.where(live, l, 0.0)


# ---------------------------------------------------------------------------------------
# local linear solve: OpenCL kernel and its float64 reference
def _check_ll_inputs(dc, da, count, guard=None):
    dc = np.asarray(dc, dtype=np.float64)
    da = np.asarray(da, dtype=np.float64)
    count = np.asarray(count)
    if (dc.ndim != 2 or not 1 <= dc.shape[1] <= LL_MAX_SLOTS or da.shape != dc.shape
            or count.shape != dc.shape[:1]):
        raise ValueError(f"expected dc, da of shape (n, K) with 1 <= K <= {LL_MAX_SLOTS} and count (n,), got "
                         f"{dc.shape}, {da.shape}, {count.shape}")
    if count.size and (count.min() < 0 or count.max() > dc.shape[1]):
        raise ValueError(f"count: must lie in [0, K = {dc.shape[1]}]")
    guard = np.zeros(count.shape, np.int64) if guard is None else np.asarray(guard)
    if guard.shape != count.shape:
        raise ValueError(f"guard: expected shape {count.shape}, got {guard.shape}")
    all_bits = LL_GUARD_CARDIAC | LL_GUARD_RESP
    if guard.size and (not np.issubdtype(guard.dtype, np.integer) or np.any((guard & ~all_bits) != 0)):
        raise ValueError(f"guard: integer flags made of bits {LL_GUARD_CARDIAC} (cardiac) and {LL_GUARD_RESP} (resp)")
    return dc, da, count.astype(np.int64), guard.astype(np.int64)


def local_linear_solve_reference(dc, da, count, kappa: float, sigma: float, guard=None) -> np.ndarray:
    """Float64 NumPy reference of the ``local_linear_weights`` kernel (same algorithm).

    Parameters
    ----------
    dc, da : array_like
        (n, K) signed circular cardiac difference and amplitude difference of the selected
        points to the target (K slots, 1..``LL_MAX_SLOTS``: 8 for the paper's two per
        quadrant); only the first ``count[i]`` slots of row i are used.
    count : array_like of int
        (n,) number of selected points.
    kappa, sigma : float
        Kernel widths (paper: 1 and 0.15).
    guard : array_like of int, optional
        (n,) extrapolation-guard flags (default 0): bit ``LL_GUARD_CARDIAC`` drops the dc
        slope column, bit ``LL_GUARD_RESP`` the da slope column from the fit (both: the
        weighted mean). The kernel weights always use the true dc, da.

    Returns
    -------
    np.ndarray
        float64 (n, K): weights l, zero beyond ``count``; each row sums to one (count >= 1).
    """
    x, y, count, guard = _check_ll_inputs(dc, da, count, guard)
    live = np.arange(x.shape[1])[None, :] < count[:, None]
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
    # guarded axis: its slope column leaves the fit (coordinate 0 for every point), the
    # weights above keep the true differences
    x = np.where((guard & LL_GUARD_CARDIAC)[:, None] != 0, 0.0, x)
    y = np.where((guard & LL_GUARD_RESP)[:, None] != 0, 0.0, y)
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
    except Exception:  # noqa: BLE001 # pragma: no cover - a driver query may raise any type (cl.Error, ...)
        return False


def local_linear_solve(dc, da, count, kappa: float, sigma: float, rt=None,
                       precision: str | None = None, guard=None) -> np.ndarray:
    """Local linear weights per row on the OpenCL device (``local_linear_weights`` kernel).

    Same inputs (``guard`` (n,) flags, default 0) and output as
    :func:`local_linear_solve_reference`. ``precision`` is ``"double"`` (default where the
    device has cl_khr_fp64) or ``"single"``.
    """
    dc, da, count, guard = _check_ll_inputs(dc, da, count, guard)
    n, K = dc.shape
    if n == 0:
        return np.zeros((0, K))
    rt = rt or get_runtime()
    if precision is None:
        precision = "double" if _has_fp64(rt) else "single"
    if precision not in ("double", "single"):
        raise ValueError(f"precision = {precision!r}: must be 'double' or 'single'")
    real = np.float64 if precision == "double" else np.float32
    defines = {"K_SLOTS": K}
    if precision == "double":
        defines["USE_DOUBLE"] = 1
    knl = rt.kernel("interp.cl", "local_linear_weights", **defines)
    d_dc = rt.to_device(dc.T, real, "dc")  # (K, n): row index fastest for the work-items
    d_da = rt.to_device(da.T, real, "da")
    d_cnt = rt.to_device(count, np.int32, "count")
    d_guard = rt.to_device(guard, np.int32, "guard")
    d_l = rt.empty((K, n), real)
    ev = knl(rt.queue, (-(-n // _LOCAL) * _LOCAL,), (_LOCAL,), d_dc, d_da, d_cnt, d_guard, d_l, np.int32(n),
             real(kappa), real(1.0 / (2.0 * sigma * sigma)), real(LL_RCOND), real(LL_SPREAD ** 2),
             real(LL_LOG_WEIGHT_FLOOR))
    l = rt.from_device(d_l, (K, n), real, wait_for=[ev])
    return np.ascontiguousarray(l.T, dtype=np.float64)

