"""Phase-space interpolation of rebinned rows (pipeline stage after :mod:`clrecon.rebin`).

For one (slice, view) the candidates are points (c_k, a_k) in the (cardiac phase,
respiratory amplitude) plane, each carrying a rebinned row. For every target (c*, a*) a
method gives a handful of weights; the target's row is the weighted sum of candidate rows
(:func:`apply_weights`, OpenCL). Methods (DESIGN.md "Phase-space interpolation", 5DCT paper
section 2.2):

``barycentric``
    Delaunay triangulation of the points with copies at c - 1 and c + 1 (cardiac phase is
    periodic, amplitude is not); the triangle containing the target gives lambda_1..3.
    Otherwise the two nearest points (distance with circular dc) and the target projected
    onto their segment, clamped to it; if one of the two is more than 0.3 away in c, the
    nearest point alone. Qhull failures (fewer than two distinct points, all points at one
    amplitude: collinear) and degenerate triangles take the same fallback.
``local_linear``
    dc = signed circular difference, da = a - a*. Two nearest points in each of the four
    quadrants around the target (dc >= 0 counts as right, da >= 0 as up: a point exactly on
    an axis, or on the target, belongs to the non-negative side). Weighted least squares
    y ~ b0 + b1 dc + b2 da with w = exp(kappa (cos 2 pi dc - 1)) exp(-da^2 / 2 sigma^2);
    the weights l^T = e1^T (X^T W X)^-1 X^T W are solved per row by the OpenCL kernel
    ``local_linear_weights`` (``kernels/interp.cl``). Fewer than 3 selected points (2 in a
    1-D problem) -> nearest point. Kernel weights below ``LL_WEIGHT_FLOOR`` times the row's
    largest are zero (narrow kernels, kappa up to 100 and sigma down to 0.01: the far points
    drop out instead of underflowing differently in float32 and float64). Ill-conditioned
    X^T W X (collinear points, or a thin cloud far from the target: an eigenvalue of the
    weighted covariance of (dc, da) below ``LL_RCOND`` times the points' weighted mean
    squared distance to the target) -> fit along the principal direction, i.e. the
    degenerate direction is dropped; both directions degenerate (coinciding points,
    duplicates, spread below ``LL_SPREAD``) -> weighted mean.
    EXTRAPOLATION (our choice; the paper is silent): when every selected point lies strictly
    on one side of the target along an axis (e.g. a target amplitude above every amplitude
    sampled at that view), the slope along that axis is dropped and the fit is locally
    constant along it, as 1-D interpolation clamps at the ends of its data. An unguarded
    linear fit extrapolates there with weights whose sum of magnitudes reached 7-25 on short
    scans and amplifies noise and motion error. ``extrapolate=True``
    (``recon.local_linear_extrapolate = true``) gives the paper's plain fit.
``r4dct``
    Amplitude only (cardiac ignored): linear between the candidates bracketing a*; outside
    the sampled range, the nearest in amplitude.
``nearest``
    Nearest point (distance with circular dc).
``bin``
    Mean of the points inside the target's bin: cardiac [c* - wc/2, c* + wc/2) circular,
    amplitude [a* - wa/2, a* + wa/2). An empty bin gives the nearest point (so a target
    always gets a row; the bin baseline's artefacts come from motion inside the bin, not
    from missing data).

The respiratory direction (inhale/exhale) is not used: the targets are amplitudes.

Reduced problems: ``use_cardiac=False`` (no cardiac motion) sets every dc to 0 and ignores
the targets' c, ``use_resp=False`` (breath hold, no breathing) sets every da to 0; the
methods then interpolate in 1-D exactly (barycentric = linear between the bracketing
points, the 0.3 rule still applying in c). With both off, every method returns the first
candidate.

Candidate sets come in compressed sparse-row form (``offsets``) so that many (slice, view)
groups are handled at once; everything but the per-group Delaunay triangulation is
vectorised over groups and targets.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from .cl_runtime import get_runtime
from .conventions import circular_difference
from .errors import ClreconError

METHODS = ("barycentric", "local_linear", "r4dct", "nearest", "bin")

#: Barycentric fallback: a second-nearest point farther than this in c is not used (paper).
BARY_MAX_DC = 0.3
#: Barycentric: copies farther than this in c outside the targets' c range are left out of
#: the first triangulation (exactness is checked, see ``_delaunay_locate``).
DELAUNAY_MARGIN = 0.5
#: Barycentric coordinates down to -BARY_EPS count as inside (targets on edges), then clipped.
BARY_EPS = 1e-9
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

_LOCAL = 64  # fixed work-group size (PoCL specialises binaries per local size)


class NoCandidatesError(ClreconError, ValueError):
    """A (slice, view) group has no candidate projection: the pitch is too high for the window."""


@dataclass(frozen=True)
class Weights:
    """Interpolation weights.

    Attributes
    ----------
    index : np.ndarray
        int32 (..., T, K): candidate index (into the group's candidates for
        :func:`method_weights`, into the flat candidate arrays for :func:`batch_weights`).
    weight : np.ndarray
        float64 (..., T, K): weights; each (..., t) sums to one. Unused slots have weight 0
        and index 0. An index may appear twice in a row (barycentric triangles through a
        point and its periodic copy); the weights then add.
    """

    index: np.ndarray
    weight: np.ndarray

    def compact(self) -> tuple[np.ndarray, "Weights"]:
        """Only the candidates that carry weight: ``(used (U,) int64, Weights into 0..U-1)``.

        Rebinning only ``used`` saves the SSRB of candidates no target needs.
        """
        live = self.weight != 0
        used, inv = np.unique(self.index[live], return_inverse=True)
        idx = np.zeros_like(self.index)
        idx[live] = inv.astype(self.index.dtype)
        return used.astype(np.int64), Weights(index=idx, weight=self.weight)


# ---------------------------------------------------------------------------------------
# validation and group padding
def _check_method(method: str) -> None:
    if method not in METHODS:
        raise ValueError(f"method = {method!r}: must be one of {', '.join(METHODS)}")


def _as_targets(targets) -> np.ndarray:
    t = np.asarray(targets, dtype=np.float64)
    if t.ndim == 1 and t.size == 2:
        t = t[None, :]
    if t.ndim != 2 or t.shape[1] != 2 or t.shape[0] == 0:
        raise ValueError(f"targets: expected shape (T, 2) of (cardiac, amplitude), got {np.shape(targets)}")
    if not np.all(np.isfinite(t)):
        raise ValueError("targets: must be finite")
    t = t.copy()
    t[:, 0] %= 1.0
    return t


def _as_points(c, a, offsets):
    c = np.asarray(c, dtype=np.float64).ravel()
    a = np.asarray(a, dtype=np.float64).ravel()
    if c.shape != a.shape:
        raise ValueError(f"c {c.shape} and a {a.shape} must have the same length")
    if not (np.all(np.isfinite(c)) and np.all(np.isfinite(a))):
        raise ValueError("c and a: must be finite")
    off = np.asarray(offsets, dtype=np.int64)
    if off.ndim != 1 or off.size < 2 or off[0] != 0 or off[-1] != c.size or np.any(np.diff(off) < 0):
        raise ValueError(f"offsets: expected non-decreasing (G + 1,) from 0 to {c.size}, got {off!r}")
    return c % 1.0, a, off


@dataclass
class _Chunk:
    """Groups g0..g1 padded to (g, N); candidates first, ``valid`` marks them."""

    c: np.ndarray
    a: np.ndarray
    valid: np.ndarray
    counts: np.ndarray
    start: np.ndarray  # flat offset of each group's first candidate


def _chunk(c, a, off, g0, g1) -> _Chunk:
    counts = np.diff(off[g0:g1 + 1])
    n = max(int(counts.max(initial=0)), 2)  # >= 2: argpartition(kth=1) needs two columns
    j = np.arange(n)
    valid = j[None, :] < counts[:, None]
    flat = np.minimum(off[g0:g1, None] + j[None, :], max(c.size - 1, 0))
    cc = np.where(valid, c[flat] if c.size else 0.0, 0.0)
    aa = np.where(valid, a[flat] if a.size else 0.0, 0.0)
    return _Chunk(c=cc, a=aa, valid=valid, counts=counts, start=off[g0:g1])


def _deltas(ch: _Chunk, targets, use_cardiac: bool, use_resp: bool):
    """dc, da, squared distance (g, T, N); invalid points have distance inf."""
    if use_cardiac:
        dc = circular_difference(ch.c[:, None, :], targets[None, :, 0, None])
    else:
        dc = np.zeros((ch.c.shape[0], targets.shape[0], ch.c.shape[1]))
    if use_resp:
        da = ch.a[:, None, :] - targets[None, :, 1, None]
    else:
        da = np.zeros_like(dc)
    d2 = np.where(ch.valid[:, None, :], dc * dc + da * da, np.inf)
    return dc, da, d2


def _take(x, idx):
    return np.take_along_axis(x, idx, axis=-1)


# ---------------------------------------------------------------------------------------
# the methods on one padded chunk: each returns local (g, T, K) index and float64 weight
def _nearest(d2):
    idx = np.argmin(d2, axis=-1)[..., None]
    return idx, np.ones(idx.shape)


def _bracket(x, valid, max_gap=None):
    """1-D linear interpolation at x = 0 between the bracketing points, (g, T, 2).

    Outside the sampled range (one side empty) or, with ``max_gap``, when a bracketing point
    is farther than ``max_gap``: the nearest point.
    """
    v = valid[:, None, :] if valid.ndim == 2 else valid
    lo_val = np.where(v & (x <= 0), x, -np.inf)
    hi_val = np.where(v & (x >= 0), x, np.inf)
    lo = np.argmax(lo_val, axis=-1)
    hi = np.argmin(hi_val, axis=-1)
    xl = _take(lo_val, lo[..., None])[..., 0]
    xh = _take(hi_val, hi[..., None])[..., 0]
    both = np.isfinite(xl) & np.isfinite(xh)
    if max_gap is not None:
        both &= (-xl <= max_gap) & (xh <= max_gap)
    span = np.where(both, xh - xl, 1.0)
    t = np.where(both & (span > 0), -np.where(both, xl, 0.0) / np.where(span > 0, span, 1.0), 0.0)
    # one side only, or a gap too wide: the nearest of the two (an absent side is at inf)
    near_lo = np.abs(np.where(np.isfinite(xl), xl, np.inf)) <= np.abs(np.where(np.isfinite(xh), xh, np.inf))
    first = np.where(both | near_lo, lo, hi)
    idx = np.stack([first, hi], axis=-1)
    w = np.stack([np.where(both, 1.0 - t, 1.0), np.where(both, t, 0.0)], axis=-1)
    return idx, w


def _two_nearest(dc, da, d2, max_dc=BARY_MAX_DC):
    """Target projected onto the segment of the two nearest points (clamped), (g, T, 2)."""
    two = np.argpartition(d2, 1, axis=-1)[..., :2]
    dd = _take(d2, two)
    swap = dd[..., 1] < dd[..., 0]
    two = np.where(swap[..., None], two[..., ::-1], two)
    dd = _take(d2, two)
    c1, c2 = _take(dc, two[..., :1])[..., 0], _take(dc, two[..., 1:])[..., 0]
    a1, a2 = _take(da, two[..., :1])[..., 0], _take(da, two[..., 1:])[..., 0]
    ec, ea = c2 - c1, a2 - a1
    L2 = ec * ec + ea * ea
    usable = np.isfinite(dd[..., 1]) & (L2 > 0) & (np.abs(c1) <= max_dc) & (np.abs(c2) <= max_dc)
    t = np.where(usable, -(c1 * ec + a1 * ea) / np.where(L2 > 0, L2, 1.0), 0.0)
    t = np.clip(t, 0.0, 1.0)
    w = np.stack([1.0 - t, t], axis=-1)
    return two, w


def _delaunay_one(pts, targets):
    """Vertex ids (T, 3) of the Delaunay triangles of ``pts`` (m, 2) containing ``targets``.

    -1 where a target lies in no triangle; None if Qhull cannot triangulate (fewer than three
    distinct points, or all collinear).
    """
    from scipy.spatial import Delaunay, QhullError
    if pts.shape[0] < 3:
        return None
    try:
        tri = Delaunay(pts)
    except (QhullError, ValueError):
        return None
    # Point location by barycentric coordinates of every target in every triangle, vectorised:
    # Delaunay.find_simplex first builds its per-simplex transforms, which cost ~10x the
    # triangulation itself here (2 ms vs 0.2 ms for 150 points and 50 targets).
    simp = tri.simplices                                          # (n_s, 3)
    p0 = pts[simp[:, 0]]
    e1 = pts[simp[:, 1]] - p0
    e2 = pts[simp[:, 2]] - p0
    det = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]               # twice the signed area
    ok = np.abs(det) > 0
    det = np.where(ok, det, 1.0)
    d = targets[:, None, :] - p0[None]                            # (T, n_s, 2)
    l1 = (d[..., 0] * e2[:, 1] - d[..., 1] * e2[:, 0]) / det
    l2 = (e1[:, 0] * d[..., 1] - e1[:, 1] * d[..., 0]) / det
    eps = 1e-12
    inside = ok & (l1 >= -eps) & (l2 >= -eps) & (l1 + l2 <= 1 + eps)
    s = np.where(inside.any(axis=1), inside.argmax(axis=1), -1)
    v = simp[np.maximum(s, 0)].copy()
    v[s < 0] = -1
    return v


def _circumcircles(pc, pa):
    """Circumcentre (c, a) and squared radius of triangles given by (..., 3) vertex arrays."""
    bc, ba = pc[..., 1] - pc[..., 0], pa[..., 1] - pa[..., 0]
    cc, ca = pc[..., 2] - pc[..., 0], pa[..., 2] - pa[..., 0]
    d = 2.0 * (bc * ca - ba * cc)
    d = np.where(d != 0, d, np.inf)
    b2, c2 = bc * bc + ba * ba, cc * cc + ca * ca
    uc = (ca * b2 - ba * c2) / d
    ua = (bc * c2 - cc * b2) / d
    return pc[..., 0] + uc, pa[..., 0] + ua, uc * uc + ua * ua


def _delaunay_locate(ch: _Chunk, targets, workers: int):
    """Containing Delaunay triangle of every (group, target) in the periodically copied points.

    Returns ``cand`` (g, T, 3) candidate ids (-1: no triangle) and ``shift`` (g, T, 3) the
    c-shift (0, -1 or +1) of the copy used for each vertex.

    Speed-up that keeps the result exact: each group is first triangulated with only the
    copies within ``DELAUNAY_MARGIN`` in c of the targets' range (about 2n points instead
    of 3n). A triangle found there is a Delaunay triangle of the full copied set unless its
    circumcircle holds one of the left-out copies. Groups where that happens (circumcircles
    wider than the margin: slivers along the amplitude edges), or where a target inside the
    points' amplitude range lies in no triangle, are triangulated again with every copy.
    """
    g, n_max = ch.c.shape
    T = targets.shape[0]
    shifts = np.array([0.0, -1.0, 1.0])
    pc = ch.c[:, None, :] + shifts[None, :, None]                      # (g, 3, N)
    pa = np.broadcast_to(ch.a[:, None, :], pc.shape)
    valid3 = np.broadcast_to(ch.valid[:, None, :], pc.shape)
    lo = targets[:, 0].min() - DELAUNAY_MARGIN
    hi = targets[:, 0].max() + DELAUNAY_MARGIN
    keep = valid3 & (pc >= lo) & (pc <= hi)
    flat_c, flat_a = pc.reshape(g, -1), pa.reshape(g, -1)
    ids = np.full((g, T, 3), -1, dtype=np.int64)                        # into the 3N copies
    full_done = np.zeros(g, dtype=bool)

    def run(gi, use_all):
        if use_all and full_done[gi]:
            return
        full_done[gi] = use_all
        m = (valid3[gi] if use_all else keep[gi]).ravel()
        sel = np.flatnonzero(m)
        v = _delaunay_one(np.stack([flat_c[gi, sel], flat_a[gi, sel]], axis=-1), targets)
        if v is None:
            if not use_all:
                run(gi, True)
            return
        ids[gi] = np.where(v >= 0, sel[np.maximum(v, 0)], -1)

    def work(gs, use_all=False):
        for gi in gs:
            run(int(gi), use_all)

    amin = np.where(ch.valid, ch.a, np.inf).min(axis=1)
    amax = np.where(ch.valid, ch.a, -np.inf).max(axis=1)
    # fewer than two points or no amplitude spread: collinear, nothing to triangulate
    todo = np.flatnonzero((ch.counts >= 2) & (amax > amin))
    if workers > 1 and todo.size > 1:
        with ThreadPoolExecutor(workers) as ex:  # Qhull (reentrant) releases the GIL in part
            list(ex.map(work, np.array_split(todo, workers)))
    else:
        work(todo)

    # Exactness checks. (1) A target in no triangle of the cut-down set may still be inside
    # the full set's hull unless its amplitude lies outside the points' range: redo.
    found = ids[..., 0] >= 0
    within_a = (targets[None, :, 1] >= amin[:, None]) & (targets[None, :, 1] <= amax[:, None])
    tried = np.zeros(g, dtype=bool)
    tried[todo] = True
    redo = set(np.flatnonzero(tried & ~full_done & np.any(~found & within_a, axis=1)).tolist())
    # (2) A triangle found is Delaunay in the full set unless a left-out copy lies inside its
    # circumcircle; only circumcircles reaching beyond [lo, hi] in c can hold one.
    gi = np.arange(g)[:, None, None]
    safe = np.maximum(ids, 0)
    cc, ca, r2 = _circumcircles(flat_c[gi, safe], flat_a[gi, safe])
    r = np.sqrt(r2)
    wide = found & ((cc - r < lo) | (cc + r > hi))
    if np.any(wide):
        out3 = (valid3 & ~keep).reshape(g, -1)
        for gw, tw in zip(*np.nonzero(wide)):
            if gw in redo or full_done[gw]:
                continue
            e = out3[gw]
            d2 = (flat_c[gw, e] - cc[gw, tw]) ** 2 + (flat_a[gw, e] - ca[gw, tw]) ** 2
            if np.any(d2 < r2[gw, tw] * (1.0 - 1e-9)):
                redo.add(int(gw))
    work(sorted(redo), use_all=True)

    found = ids[..., 0] >= 0
    safe = np.maximum(ids, 0)
    cand = np.where(found[..., None], safe % n_max, -1)
    shift = shifts[safe // n_max]
    return cand, shift


def _barycentric(ch: _Chunk, targets, dc, da, d2, use_cardiac, use_resp, workers):
    if not (use_cardiac and use_resp):
        if use_resp:
            return _bracket(da, ch.valid)
        return _bracket(dc, ch.valid, max_gap=BARY_MAX_DC)
    g, T = d2.shape[:2]
    cand, shift = _delaunay_locate(ch, targets, workers)
    found = cand[..., 0] >= 0
    cand = np.maximum(cand, 0)
    gi = np.arange(g)[:, None, None]
    pc = ch.c[gi, cand] + shift
    pa = ch.a[gi, cand]
    # barycentric coordinates of the target in triangle (p0, p1, p2)
    e1c, e1a = pc[..., 1] - pc[..., 0], pa[..., 1] - pa[..., 0]
    e2c, e2a = pc[..., 2] - pc[..., 0], pa[..., 2] - pa[..., 0]
    dcq = targets[None, :, 0] - pc[..., 0]
    daq = targets[None, :, 1] - pa[..., 0]
    det = e1c * e2a - e1a * e2c
    scale = (e1c ** 2 + e1a ** 2) * (e2c ** 2 + e2a ** 2)
    ok = found & (np.abs(det) > 1e-12 * np.sqrt(scale)) & (scale > 0)  # no sliver of zero area
    sdet = np.where(ok, det, 1.0)
    l1 = (dcq * e2a - daq * e2c) / sdet
    l2 = (e1c * daq - e1a * dcq) / sdet
    lam = np.stack([1.0 - l1 - l2, l1, l2], axis=-1)
    ok &= np.all(np.isfinite(lam), axis=-1) & np.all(lam >= -BARY_EPS, axis=-1)
    lam = np.clip(lam, 0.0, None)
    lam /= np.where(ok, lam.sum(axis=-1), 1.0)[..., None]
    idx = np.where(ok[..., None], cand, 0)
    w = np.where(ok[..., None], lam, 0.0)
    if not np.all(ok):
        fi, fw = _two_nearest(dc, da, d2)
        idx[..., :2] = np.where(ok[..., None], idx[..., :2], fi)
        w[..., :2] = np.where(ok[..., None], w[..., :2], fw)
    return idx, w


def _bin(ch: _Chunk, dc, da, d2, cardiac_bin_width, resp_bin_width, use_cardiac, use_resp):
    inside = np.isfinite(d2)
    if use_cardiac:
        inside &= (dc >= -0.5 * cardiac_bin_width) & (dc < 0.5 * cardiac_bin_width)
    if use_resp:
        inside &= (da >= -0.5 * resp_bin_width) & (da < 0.5 * resp_bin_width)
    count = inside.sum(axis=-1)
    K = max(int(count.max(initial=0)), 1)
    order = np.argsort(~inside, axis=-1, kind="stable")[..., :K]
    member = _take(inside, order)
    w = np.where(member, 1.0 / np.maximum(count, 1)[..., None], 0.0)
    idx = np.where(member, order, 0)
    empty = count == 0  # empty bin -> nearest point
    if np.any(empty):
        near = np.argmin(d2, axis=-1)
        idx[..., 0] = np.where(empty, near, idx[..., 0])
        w[..., 0] = np.where(empty, 1.0, w[..., 0])
    return idx, w


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


# ---------------------------------------------------------------------------------------
def batch_weights(method: str, c, a, offsets, targets, *, kappa: float = 1.0, sigma: float = 0.15,
                  cardiac_bin_width: float = 0.2, resp_bin_width: float = 0.1,
                  use_cardiac: bool = True, use_resp: bool = True, allow_empty: bool = False,
                  chunk_groups: int = 1024, workers: int | None = None, rt=None,
                  precision: str | None = None, extrapolate: bool = False) -> Weights:
    """Interpolation weights for many (slice, view) groups at once.

    Parameters
    ----------
    method : str
        One of :data:`METHODS`.
    c, a : array_like
        (n,) cardiac phase in [0, 1) (taken mod 1) and respiratory amplitude of all
        candidates of all groups, group after group.
    offsets : array_like of int
        (G + 1,) group g owns candidates ``offsets[g]:offsets[g + 1]``
        (:attr:`clrecon.rebin.CandidateGroups.offsets`).
    targets : array_like
        (T, 2) target (cardiac phase, amplitude), the same for every group.
    kappa, sigma : float
        Local-linear kernel widths (``ReconConfig.kappa``, ``ReconConfig.sigma``).
    cardiac_bin_width, resp_bin_width : float
        ``bin`` widths: the spacing of the cardiac targets (0.2 for 5 phases) and
        1 / resp_bins.
    use_cardiac, use_resp : bool
        False when the scene has no cardiac motion / no breathing (see module docstring).
    allow_empty : bool
        If False (default) a group without candidates raises :class:`NoCandidatesError`;
        if True its weights are all zero (the caller must handle it).
    chunk_groups : int
        Groups processed together (memory ~ chunk_groups * T * max_count * 50 bytes).
    workers : int, optional
        Threads for the per-group Delaunay triangulations (default 1: on a loaded 2-core
        machine extra threads were measured to slow it down; up to 2x on an idle one).
    rt : Runtime, optional
        For the local-linear kernel.
    precision : str, optional
        Local-linear kernel precision, see :func:`local_linear_solve`.

    Returns
    -------
    Weights
        index int32 (G, T, K) into the flat candidate arrays, weight float64 (G, T, K).
        K = 3 barycentric, 8 local_linear, 2 r4dct, 1 nearest, largest bin count for bin.
    """
    _check_method(method)
    c, a, off = _as_points(c, a, offsets)
    targets = _as_targets(targets)
    if not (kappa > 0 and sigma > 0 and cardiac_bin_width > 0 and resp_bin_width > 0):
        raise ValueError(f"kappa = {kappa}, sigma = {sigma}, cardiac_bin_width = {cardiac_bin_width}, "
                         f"resp_bin_width = {resp_bin_width}: must all be > 0")
    G, T = off.size - 1, targets.shape[0]
    counts = np.diff(off)
    if not allow_empty and np.any(counts == 0):
        bad = np.flatnonzero(counts == 0)
        raise NoCandidatesError(f"{bad.size} of {G} (slice, view) groups have no candidate projection "
                                f"(first: group {bad[0]}); lower the pitch or widen the slice window")
    if not (use_cardiac or use_resp):
        method = "nearest"  # no motion: every candidate is as good; take the first
    workers = 1 if workers is None else max(int(workers), 1)
    chunk_groups = max(int(chunk_groups), 1)

    parts = []
    for g0 in range(0, G, chunk_groups):
        g1 = min(G, g0 + chunk_groups)
        ch = _chunk(c, a, off, g0, g1)
        dc, da, d2 = _deltas(ch, targets, use_cardiac, use_resp)
        if method == "nearest":
            idx, w = _nearest(d2)
        elif method == "r4dct":
            da_r = ch.a[:, None, :] - targets[None, :, 1, None]
            idx, w = _bracket(da_r if use_resp else np.zeros_like(da_r), ch.valid)
        elif method == "bin":
            idx, w = _bin(ch, dc, da, d2, cardiac_bin_width, resp_bin_width, use_cardiac, use_resp)
        elif method == "barycentric":
            idx, w = _barycentric(ch, targets, dc, da, d2, use_cardiac, use_resp, workers)
        else:
            idx, w = _local_linear(dc, da, d2, use_cardiac, use_resp, kappa, sigma, rt, precision,
                                   extrapolate)
        empty = ch.counts == 0
        w = np.where(empty[:, None, None], 0.0, w)
        gidx = np.where(w != 0, idx + ch.start[:, None, None], 0)
        parts.append((gidx, w))
    K = max(p[0].shape[-1] for p in parts) if parts else 1
    index = np.zeros((G, T, K), dtype=np.int32)
    weight = np.zeros((G, T, K), dtype=np.float64)
    g0 = 0
    for gidx, w in parts:
        g1 = g0 + gidx.shape[0]
        index[g0:g1, :, :gidx.shape[-1]] = gidx
        weight[g0:g1, :, :w.shape[-1]] = w
        g0 = g1
    return Weights(index=index, weight=weight)


def method_weights(method: str, c, a, targets, *, kappa: float = 1.0, sigma: float = 0.15,
                   cardiac_bin_width: float = 0.2, resp_bin_width: float = 0.1,
                   use_cardiac: bool = True, use_resp: bool = True, rt=None,
                   precision: str | None = None, extrapolate: bool = False) -> Weights:
    """Interpolation weights for one (slice, view): candidates (n,) -> Weights (T, K) into 0..n-1.

    See :func:`batch_weights` for the parameters; raises :class:`NoCandidatesError` for n = 0.
    """
    c = np.asarray(c, dtype=np.float64).ravel()
    w = batch_weights(method, c, a, [0, c.size], targets, kappa=kappa, sigma=sigma,
                      cardiac_bin_width=cardiac_bin_width, resp_bin_width=resp_bin_width,
                      use_cardiac=use_cardiac, use_resp=use_resp, workers=1, rt=rt, precision=precision,
                      extrapolate=extrapolate)
    return Weights(index=w.index[0], weight=w.weight[0])


# ---------------------------------------------------------------------------------------
def _check_apply(rows, index, weight):
    rows = np.asarray(rows)
    if rows.dtype.kind not in "fiu":
        raise TypeError(f"rows: expected a real numeric array, got dtype {rows.dtype}")
    index = np.asarray(index)
    if index.dtype.kind not in "iu":
        raise TypeError(f"index: expected an integer array, got dtype {index.dtype}")
    weight = np.asarray(weight)
    if weight.dtype.kind != "f":
        raise TypeError(f"weight: expected a float array, got dtype {weight.dtype}")
    if rows.ndim != 2 or index.ndim != 2 or weight.shape != index.shape:
        raise ValueError(f"expected rows (P, C), index and weight (B, K) of equal shape, got "
                         f"{rows.shape}, {index.shape}, {weight.shape}")
    live = weight != 0
    if np.any(live) and (index[live].min() < 0 or index[live].max() >= rows.shape[0]):
        raise ValueError(f"index: entries with non-zero weight must lie in [0, {rows.shape[0]})")
    return rows, np.where(live, index, 0), weight


def apply_weights_reference(rows, index, weight) -> np.ndarray:
    """Float64 NumPy reference of :func:`apply_weights`, shape (B, C)."""
    rows, index, weight = _check_apply(rows, index, weight)
    r = rows.astype(np.float64)
    w = weight.astype(np.float64)
    if r.shape[0] == 0:
        return np.zeros((index.shape[0], r.shape[1]))
    # zero weights do not touch their row (a NaN there must not leak through 0 * NaN)
    return np.einsum("bk,bkc->bc", w, np.where((w != 0)[..., None], r[index], 0.0))


def apply_weights(rows, index, weight, rt=None) -> np.ndarray:
    """Weighted sums of rebinned rows on the OpenCL device (``apply_weights`` kernel).

    Parameters
    ----------
    rows : array_like
        (P, C) rebinned rows (converted to float32).
    index : array_like of int
        (B, K) row of ``rows`` for each slot; only slots with non-zero weight are read.
    weight : array_like of float
        (B, K) weights (converted to float32), e.g. ``Weights.weight.reshape(-1, K)``.
    rt : Runtime, optional

    Returns
    -------
    np.ndarray
        float32 (B, C): ``out[b] = sum_k weight[b, k] * rows[index[b, k]]``.
    """
    rows, index, weight = _check_apply(rows, index, weight)
    B, K = index.shape
    C = rows.shape[1]
    if B == 0 or C == 0:
        return np.zeros((B, C), np.float32)
    rt = rt or get_runtime()
    knl = rt.kernel("interp.cl", "apply_weights")
    d_rows = rt.to_device(rows, np.float32, "rows")
    d_idx = rt.to_device(index, np.int32, "index")
    d_w = rt.to_device(weight, np.float32, "weight")
    d_out = rt.empty((B, C), np.float32)
    ev = knl(rt.queue, (-(-C // _LOCAL) * _LOCAL, B), (_LOCAL, 1), d_rows, d_idx, d_w, d_out,
             np.int32(B), np.int32(C), np.int32(K))
    return rt.from_device(d_out, (B, C), np.float32, wait_for=[ev])


class DeviceRows:
    """Rebinned rows uploaded once, for several :func:`apply_weights_interleaved` calls.

    ``rows`` (P, C) is converted to float32; :meth:`release` frees the device copy (on a
    CPU device it is host memory too, so release it as soon as the slab is done).
    """

    def __init__(self, rows, rt=None):
        rows = np.asarray(rows)
        if rows.dtype.kind not in "fiu":
            raise TypeError(f"rows: expected a real numeric array, got dtype {rows.dtype}")
        if rows.ndim != 2:
            raise ValueError(f"rows: expected shape (P, C), got {rows.shape}")
        self.rt = rt or get_runtime()
        self.shape = rows.shape
        self.buf = self.rt.to_device(rows, np.float32, "rows")

    def release(self) -> None:
        if self.buf is not None:
            self.buf.release()
            self.buf = None


def apply_weights_interleaved(rows: DeviceRows, index, weight, rt=None):
    """:func:`apply_weights` for whole sinograms, written in the batched backprojector's layout.

    Parameters
    ----------
    rows : DeviceRows
        (P, C) rows on the device.
    index : array_like of int
        (B, V, K): row of ``rows`` for slot k of view v of sinogram b; only slots with
        non-zero weight are read.
    weight : array_like of float
        (B, V, K) weights (converted to float32).
    rt : Runtime, optional

    Returns
    -------
    (buffer, n_groups)
        Device buffer of (n_groups, V, C + 2, 16) float32, n_groups = ceil(B / 16): the
        layout of :func:`clrecon.fbp.interleave_batch` (sinogram ``16 g + lane`` in lane
        ``lane`` of group ``g``; lanes beyond B are zero), for
        :func:`clrecon.fbp.backproject_interleaved`.
    """
    index = np.asarray(index)
    weight = np.asarray(weight)
    if index.dtype.kind not in "iu":
        raise TypeError(f"index: expected an integer array, got dtype {index.dtype}")
    if weight.dtype.kind != "f":
        raise TypeError(f"weight: expected a float array, got dtype {weight.dtype}")
    if index.ndim != 3 or weight.shape != index.shape:
        raise ValueError(f"expected index and weight (B, V, K) of equal shape, got {index.shape}, {weight.shape}")
    P, C = rows.shape
    B, V, K = index.shape
    live = weight != 0
    if np.any(live) and (index[live].min() < 0 or index[live].max() >= P):
        raise ValueError(f"index: entries with non-zero weight must lie in [0, {P})")
    rt = rt or rows.rt
    G = max(1, -(-B // 16))
    idx = np.zeros((G * 16, V, K), np.int32)
    wgt = np.zeros((G * 16, V, K), np.float32)
    idx[:B] = np.where(live, index, 0)
    wgt[:B] = weight
    d_out = rt.empty((G, V, C + 2, 16), np.float32)
    if B == 0 or P == 0 or C == 0 or V == 0 or K == 0:
        rt.cl.enqueue_fill_buffer(rt.queue, d_out, np.float32(0), 0, G * V * (C + 2) * 16 * 4).wait()
        return d_out, G
    knl = rt.kernel("interp.cl", "apply_weights_interleaved16")
    d_idx = rt.to_device(idx, np.int32, "index")
    d_w = rt.to_device(wgt, np.float32, "weight")
    ev = knl(rt.queue, (-(-(C + 2) // _LOCAL) * _LOCAL, V, G), (_LOCAL, 1, 1), rows.buf, d_idx, d_w, d_out,
             np.int32(V), np.int32(C), np.int32(K))
    ev.wait()
    d_idx.release()
    d_w.release()
    return d_out, G
