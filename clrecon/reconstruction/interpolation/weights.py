"""Phase-space interpolation of rebinned rows (pipeline stage after :mod:`clrecon.reconstruction.rebin`).

For one (slice, view) the candidates are points (c_k, a_k) in the (cardiac phase,
respiratory amplitude) plane, each carrying a rebinned row. For every target (c*, a*) a
method gives a handful of weights; the target's row is the weighted sum of candidate rows
(:func:`apply_weights_interleaved`, OpenCL). This module is the dispatcher: validation, chunking of the
groups, the differences to the targets, then the method's ``weights`` function from the
registry (:mod:`clrecon.reconstruction.interpolation.registry`), then flat indices and
padding. The methods live one per module (docs/algorithms.md "Phase-space interpolation", 5DCT paper
section 2.2): :mod:`~clrecon.reconstruction.interpolation.barycentric`,
:mod:`~clrecon.reconstruction.interpolation.local_linear`,
:mod:`~clrecon.reconstruction.interpolation.r4dct`,
:mod:`~clrecon.reconstruction.interpolation.nearest`,
:mod:`~clrecon.reconstruction.interpolation.bin`,
:mod:`~clrecon.reconstruction.interpolation.helical`; adding one is described in
``docs/extending.md``.

The respiratory direction (inhale/exhale) is not used: the targets are amplitudes.

Reduced problems: ``use_cardiac=False`` (no cardiac motion) sets every dc to 0 and ignores
the targets' c, ``use_resp=False`` (breath hold, no breathing) sets every da to 0; the
methods then interpolate in 1-D exactly (barycentric = linear between the bracketing
points, the 0.3 rule still applying in c). With both off, every phase-space method returns
the first candidate; ``helical``, which uses no phase axis, keeps its own rule (the turn
nearest in z) whatever moves.

Candidate sets come in compressed sparse-row form (``offsets``) so that many (slice, view)
groups are handled at once; everything but the per-group Delaunay triangulation is
vectorised over groups and targets.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from clrecon.core.errors import ClreconError
from clrecon.reconstruction.interpolation import registry as _registry
from clrecon.reconstruction.interpolation._common import chunk as _chunk
from clrecon.reconstruction.interpolation._common import deltas as _deltas
from clrecon.reconstruction.interpolation.apply import (  # noqa: F401
    DeviceRows,
    apply_padded_interleaved,
    apply_weights_interleaved,
    apply_weights_reference,
    pad_interleaved,
)
from clrecon.reconstruction.interpolation.barycentric import (  # noqa: F401
    BARY_EPS,
    BARY_MAX_DC,
    DELAUNAY_MARGIN,
    _delaunay_one,
)
from clrecon.reconstruction.interpolation.base import Options
from clrecon.reconstruction.interpolation.local_linear import (  # noqa: F401
    LL_GUARD_CARDIAC,
    LL_GUARD_RESP,
    LL_LOG_WEIGHT_FLOOR,
    LL_PER_QUADRANT,
    LL_RCOND,
    LL_SLOTS,
    LL_SPREAD,
    LL_WEIGHT_FLOOR,
    local_linear_solve,
    local_linear_solve_reference,
    slot_count,
)

#: Registered method names, in registration order (the ``recon.methods`` default).
METHODS = _registry.METHODS.names


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
    branch : np.ndarray or None
        int8 (..., T): which branch of the method each (group, target) took, for methods
        that report it (barycentric: ``BRANCH_NAMES`` triangle 0, segment 1, nearest 2;
        -1 for an empty group), else None. Diagnostic only: the weights do not depend on it.
    """

    index: np.ndarray
    weight: np.ndarray
    branch: np.ndarray | None = None

    def compact(self) -> tuple[np.ndarray, Weights]:
        """Only the candidates that carry weight: ``(used (U,) int64, Weights into 0..U-1)``.

        Rebinning only ``used`` saves the SSRB of candidates no target needs.
        """
        live = self.weight != 0
        used, inv = np.unique(self.index[live], return_inverse=True)
        idx = np.zeros_like(self.index)
        idx[live] = inv.astype(self.index.dtype)
        return used.astype(np.int64), Weights(index=idx, weight=self.weight, branch=self.branch)


# ---------------------------------------------------------------------------------------
# validation
def _check_method(method: str) -> None:
    if method not in _registry.METHODS:
        names = _registry.METHODS.names
        raise ValueError(f"method = {method!r}: must be one of {', '.join(names)}")


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


def _as_dz(dz, n: int):
    if dz is None:
        return None
    d = np.asarray(dz, dtype=np.float64).ravel()
    if d.shape != (n,):
        raise ValueError(f"dz: expected ({n},) like c, got {np.shape(dz)}")
    if not np.all(np.isfinite(d)):
        raise ValueError("dz: must be finite")
    return np.abs(d)


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


# ---------------------------------------------------------------------------------------
def batch_weights(method: str, c, a, offsets, targets, *, kappa: float = 1.0, sigma: float = 0.15,
                  cardiac_bin_width: float = 0.2, resp_bin_width: float = 0.1,
                  use_cardiac: bool = True, use_resp: bool = True, allow_empty: bool = False,
                  chunk_groups: int = 1024, workers: int | None = None, rt=None,
                  precision: str | None = None, extrapolate: bool = False, dz=None,
                  local_linear_points: str = "quadrants", local_linear_count: int = 2,
                  cardiac_distance_scale: float = 1.0, tuned: tuple | None = None) -> Weights:
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
        (:attr:`clrecon.reconstruction.rebin.CandidateGroups.offsets`).
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
    extrapolate : bool
        Local linear: the paper's plain fit (no extrapolation guard).
    local_linear_points, local_linear_count : str, int
        Local-linear neighbours: ``"quadrants"`` (``count`` nearest per quadrant, K = 4 count;
        default 2, K = 8) or ``"nearest"`` (the ``count`` nearest, K = count), see
        :mod:`~clrecon.reconstruction.interpolation.local_linear`.
    cardiac_distance_scale : float
        s > 0, dimensionless (amplitude units per cardiac cycle; ``recon.cardiac_distance_scale``):
        the phase-space distance is sqrt((s dc)^2 + da^2) wherever a method picks points by
        distance (local_linear's neighbours, nearest, barycentric's two-nearest fallback and its
        segment projection), and barycentric triangulates (s c, a). Kernel weights, the 0.3 rule
        and barycentric coordinates use the unscaled dc (the coordinates are affine-invariant, so
        only the choice of triangle changes). Default 1: unscaled.
    dz : array_like, optional
        (n,) like ``c``: each candidate's z distance from its group's slice, |z_slice - z_k|
        in mm (a sign is dropped; :attr:`clrecon.reconstruction.rebin.CandidateGroups.dz_mm`).
        Only the phase-blind methods read it (``helical``, which requires it); the phase
        methods' weights do not depend on it.
    tuned : tuple, optional
        ``cv_tuned`` only: the fixed kernel it uses, ``(method, ((knob, value), ...))``
        (:mod:`~clrecon.reconstruction.interpolation.cv_tuned`).

    Returns
    -------
    Weights
        index int32 (G, T, K) into the flat candidate arrays, weight float64 (G, T, K).
        K = the method's ``neighbours``: 3 barycentric, 8 local_linear (4 x count or count:
        ``local_linear_points``), 2 r4dct, 1 nearest,
        largest bin count for bin, 1 helical. ``branch`` int8 (G, T) for methods that report
        their branch (barycentric), else None.
    """
    _check_method(method)
    c, a, off = _as_points(c, a, offsets)
    dz = _as_dz(dz, c.size)
    targets = _as_targets(targets)
    if not (cardiac_distance_scale > 0 and np.isfinite(cardiac_distance_scale)):
        raise ValueError(f"cardiac_distance_scale = {cardiac_distance_scale}: must be finite and > 0")
    if not (kappa > 0 and sigma > 0 and cardiac_bin_width > 0 and resp_bin_width > 0):
        raise ValueError(f"kappa = {kappa}, sigma = {sigma}, cardiac_bin_width = {cardiac_bin_width}, "
                         f"resp_bin_width = {resp_bin_width}: must all be > 0")
    slot_count(local_linear_points, local_linear_count)  # raises ValueError naming a bad rule or count
    G, T = off.size - 1, targets.shape[0]
    counts = np.diff(off)
    if not allow_empty and np.any(counts == 0):
        bad = np.flatnonzero(counts == 0)
        raise NoCandidatesError(f"{bad.size} of {G} (slice, view) groups have no candidate projection "
                                f"(first: group {bad[0]}); lower the pitch or widen the slice window")
    if not (use_cardiac or use_resp) and _registry.METHODS[method].axes:
        method = "nearest"  # no motion: every phase-space method sees one point; take the first
    workers = 1 if workers is None else max(int(workers), 1)
    chunk_groups = max(int(chunk_groups), 1)

    m = _registry.METHODS[method]
    opts = Options(kappa=kappa, sigma=sigma, cardiac_bin_width=cardiac_bin_width, resp_bin_width=resp_bin_width,
                   use_cardiac=use_cardiac, use_resp=use_resp, workers=workers, rt=rt, precision=precision,
                   extrapolate=extrapolate, local_linear_points=local_linear_points,
                   local_linear_count=int(local_linear_count),
                   cardiac_distance_scale=float(cardiac_distance_scale), tuned=tuned)
    # differences along an axis the method does not use are left at zero (not computed)
    use_c, use_r = use_cardiac and "cardiac" in m.axes, use_resp and "resp" in m.axes

    parts = []
    for g0 in range(0, G, chunk_groups):
        g1 = min(G, g0 + chunk_groups)
        ch = _chunk(c, a, off, g0, g1, dz)
        dc, da, d2 = _deltas(ch, targets, use_c, use_r, opts.cardiac_distance_scale)
        res = m.weights(ch, targets, dc, da, d2, opts)
        idx, w = res[0], res[1]
        br = res[2] if len(res) > 2 else None  # optional branch report (g, T)
        empty = ch.counts == 0
        w = np.where(empty[:, None, None], 0.0, w)
        gidx = np.where(w != 0, idx + ch.start[:, None, None], 0)
        if br is not None:
            br = np.where(empty[:, None], -1, br).astype(np.int8)
        parts.append((gidx, w, br))
    K = max(p[0].shape[-1] for p in parts) if parts else 1
    index = np.zeros((G, T, K), dtype=np.int32)
    weight = np.zeros((G, T, K), dtype=np.float64)
    branch = np.full((G, T), -1, dtype=np.int8) if parts and all(p[2] is not None for p in parts) else None
    g0 = 0
    for gidx, w, br in parts:
        g1 = g0 + gidx.shape[0]
        index[g0:g1, :, :gidx.shape[-1]] = gidx
        weight[g0:g1, :, :w.shape[-1]] = w
        if branch is not None:
            branch[g0:g1] = br
        g0 = g1
    return Weights(index=index, weight=weight, branch=branch)


def method_weights(method: str, c, a, targets, *, kappa: float = 1.0, sigma: float = 0.15,
                   cardiac_bin_width: float = 0.2, resp_bin_width: float = 0.1,
                   use_cardiac: bool = True, use_resp: bool = True, rt=None,
                   precision: str | None = None, extrapolate: bool = False, dz=None,
                   local_linear_points: str = "quadrants", local_linear_count: int = 2,
                   cardiac_distance_scale: float = 1.0, tuned: tuple | None = None) -> Weights:
    """Interpolation weights for one (slice, view): candidates (n,) -> Weights (T, K) into 0..n-1.

    See :func:`batch_weights` for the parameters (``dz`` (n,) mm); raises
    :class:`NoCandidatesError` for n = 0.
    """
    c = np.asarray(c, dtype=np.float64).ravel()
    w = batch_weights(method, c, a, [0, c.size], targets, kappa=kappa, sigma=sigma,
                      cardiac_bin_width=cardiac_bin_width, resp_bin_width=resp_bin_width,
                      use_cardiac=use_cardiac, use_resp=use_resp, workers=1, rt=rt, precision=precision,
                      extrapolate=extrapolate, dz=dz, local_linear_points=local_linear_points,
                      local_linear_count=local_linear_count, cardiac_distance_scale=cardiac_distance_scale,
                      tuned=tuned)
    return Weights(index=w.index[0], weight=w.weight[0], branch=None if w.branch is None else w.branch[0])

