"""How densely a scan samples cardiac phase space at each (slice, view).

For one (slice, view) the SSRB candidates (:func:`clrecon.reconstruction.rebin.candidate_groups`)
are the projections of the same view angle from every turn whose rows cover the slice; their
recorded cardiac phases are the points a phase-space method interpolates between. With a
periodic rhythm the phase advances by exactly T_rot / RR per turn, so for T_rot / RR = p / q in
lowest terms a view sees at most q distinct cardiac phases however many turns cover it (demo
and Table 1: 0.3 s / 0.75 s = 2/5, five phases 0.2 apart); heart-rate variability breaks that
lattice. The numbers here report it (``results.json`` ``"sampling"``, docs/algorithms.md
"Candidate selection").

Groups are taken duck-typed (``offsets`` (G + 1,) CSR bounds and ``row`` (n,) rows of the
table), so this module needs only the table.
"""

from __future__ import annotations

import numpy as np

#: Two cardiac phases closer than this (circular distance, fraction of the R-R interval)
#: count as the same phase. Phases of one lattice point of a periodic rhythm differ by rounding
#: only (~1e-15); 1e-3 of a 0.75 s R-R interval is 0.75 ms, far below the 0.2 spacing of the
#: cardiac targets, so "distinct" means a genuinely different cardiac state.
DISTINCT_PHASE_TOL = 1e-3


def distinct_cardiac_phases(table, groups, tol: float = DISTINCT_PHASE_TOL) -> np.ndarray:
    """Number of distinct cardiac phases among each group's candidates, shape (G,) int64.

    Parameters
    ----------
    table : ProjectionTable
        The table the groups index (``cardiac_phase`` (n_table,), fraction of R-R in [0, 1)).
    groups : CandidateGroups
        ``offsets`` (G + 1,) and ``row`` (n,) into ``table``; G = slices x views.
    tol : float
        Phases are sorted round the circle; a new phase starts wherever the gap to the
        previous one (circularly, including the gap across c = 0) exceeds ``tol``
        (single-linkage: a chain of phases each within ``tol`` of the next is one phase).

    Returns
    -------
    np.ndarray
        (G,) int64; 0 for a group without candidates.
    """
    off = np.asarray(groups.offsets, dtype=np.int64)
    c = np.asarray(table.cardiac_phase, dtype=np.float64)[np.asarray(groups.row, dtype=np.int64)] % 1.0
    G = off.size - 1
    counts = np.diff(off)
    out = np.zeros(G, dtype=np.int64)
    if c.size == 0:
        return out
    gid = np.repeat(np.arange(G), counts)
    order = np.lexsort((c, gid))                    # by group, then by phase
    cs = c[order]
    start = off[:-1]
    last = off[1:] - 1
    gap = np.empty_like(cs)
    gap[1:] = np.diff(cs)
    has = counts > 0
    # the gap before each group's first phase is the one across c = 0 from its last phase
    gap[start[has]] = cs[start[has]] + 1.0 - cs[last[has]]
    big = (gap > tol).astype(np.int64)
    out[has] = np.add.reduceat(big, start[has])
    # every gap within tol (more than 1/tol phases packed round the circle): one phase
    out[has] = np.maximum(out[has], 1)
    return out


def _stats(x: np.ndarray) -> dict:
    if x.size == 0:
        return {"median": 0.0, "min": 0, "max": 0}
    return {"median": float(np.median(x)), "min": int(x.min()), "max": int(x.max())}


def sampling_summary(table, groups, tol: float = DISTINCT_PHASE_TOL) -> dict:
    """Median / min / max over (slice, view) groups of the distinct cardiac phases and of the
    candidates per group: ``{"distinct_cardiac_phases_per_view": {"median", "min", "max"},
    "candidates_per_view": {...}}`` (plain Python numbers, for ``results.json``)."""
    counts = np.diff(np.asarray(groups.offsets, dtype=np.int64))
    return {"distinct_cardiac_phases_per_view": _stats(distinct_cardiac_phases(table, groups, tol)),
            "candidates_per_view": _stats(counts)}
