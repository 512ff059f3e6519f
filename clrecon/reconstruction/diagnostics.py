"""Per-target diagnostics of a reconstruction plan's interpolation weights.

How far from a target, in phase space, are the rows that make its volume? For every method of
a :class:`clrecon.reconstruction.reconstruct.SlabWeights` and every target of the grid (cardiac-major,
:attr:`clrecon.reconstruction.reconstruct.Targets.pairs`), over all (slice, view) pairs of the
plan and the candidates with a non-zero weight:

- ``max_abs_dc``: the largest circular |c_k - c*| (cardiac phase, cycles, in [0, 0.5]);
- ``max_abs_da``: the largest |a_k - a*| (respiratory amplitude, in [0, 1] for amplitudes in
  [0, 1]);
- ``branch_share`` (methods that report their branch, ``MethodWeights.branch``: barycentric):
  the share of (slice, view) pairs that took each branch (``triangle``, ``segment`` = the
  two-point fallback, ``nearest``), each in [0, 1], summing to one per target.

A method solved on a coarser target grid (``target_grid = "resp"``: one cardiac-blind target
per amplitude, ``"none"``: one target) stands for every grid target; its rows are compared
with each grid target's (c*, a*), i.e. with the phase its volume is reported at.
"""

from __future__ import annotations

import numpy as np

from clrecon.core.conventions import circular_difference
from clrecon.reconstruction.interpolation.barycentric import BRANCH_NAMES as _BARY_BRANCHES

#: Names of the branch codes of the methods that report one (``Weights.branch``).
BRANCH_NAMES = {"barycentric": _BARY_BRANCHES}


def weight_diagnostics(plan, table, targets) -> dict:
    """Per method, per target: the phase-space reach of the rows with non-zero weight.

    Parameters
    ----------
    plan : SlabWeights
        :func:`clrecon.reconstruction.reconstruct.plan` result; per method a ``MethodWeights``
        with ``proj_index`` and ``weight`` (S, V, T, K), ``targets_shape`` (n_c, n_r) of the
        targets it was solved for, and ``branch`` (S, V, T) int8 or None.
    table : ProjectionTable
        The projection table the plan was made from (``cardiac_phase``, ``resp_amplitude``
        per projection).
    targets : Targets
        The target grid (n_c x n_r); the lists below follow ``targets.pairs`` (cardiac-major).

    Returns
    -------
    dict
        ``{method: {"targets": [[c*, a*], ...], "max_abs_dc": [...], "max_abs_da": [...]}}``
        with one entry per grid target, plus ``"branch_share": {name: [...]}`` for methods
        that report their branch. Plain floats (JSON-ready).
    """
    pairs = np.asarray(targets.pairs, dtype=np.float64)
    n_c, n_r = targets.shape
    phase = np.asarray(table.cardiac_phase, dtype=np.float64)
    amp = np.asarray(table.resp_amplitude, dtype=np.float64)
    out = {}
    for name, mp in plan.methods.items():
        n_cs, n_rs = mp.targets_shape
        ci, rj = np.divmod(np.arange(n_c * n_r), n_r)
        src = (ci % n_cs) * n_rs + (rj % n_rs)           # solved target standing for each grid target
        max_dc = np.zeros(n_c * n_r)
        max_da = np.zeros(n_c * n_r)
        for t in range(n_c * n_r):
            used = mp.weight[:, :, src[t], :] != 0
            proj = mp.proj_index[:, :, src[t], :][used]
            if proj.size:
                max_dc[t] = np.abs(circular_difference(phase[proj], pairs[t, 0])).max()
                max_da[t] = np.abs(amp[proj] - pairs[t, 1]).max()
        d = {"targets": pairs.tolist(), "max_abs_dc": max_dc.tolist(), "max_abs_da": max_da.tolist()}
        branch = getattr(mp, "branch", None)
        if branch is not None:
            names = BRANCH_NAMES.get(name) or tuple(f"branch{k}" for k in range(int(branch.max(initial=0)) + 1))
            per = branch.reshape(-1, branch.shape[-1])[:, src]  # (S V, grid targets)
            n = max(per.shape[0], 1)
            d["branch_share"] = {nm: ((per == k).sum(axis=0) / n).tolist() for k, nm in enumerate(names)}
        out[name] = d
    return out


def pooled(diag: dict) -> dict:
    """One method's diagnostics pooled over targets: largest |dc|, |da|; mean branch shares
    (every target has the same number of (slice, view) pairs, so the mean is the pooled share)."""
    p = {"max_abs_dc": max(diag["max_abs_dc"], default=0.0), "max_abs_da": max(diag["max_abs_da"], default=0.0)}
    for nm, v in diag.get("branch_share", {}).items():
        p[nm] = float(np.mean(v)) if v else 0.0
    return p


def combine(parts) -> dict:
    """:func:`weight_diagnostics` of a plan made slab by slab, from ``[(diagnostics, n_slices), ...]``.

    The largest |dc|, |da| over the slabs; branch shares averaged with the slabs' slice counts
    as weights (every slice has the same views), so the result equals the diagnostics of one
    plan over all the slices.
    """
    parts = [(d, n) for d, n in parts if d]
    if not parts:
        return {}
    total = sum(n for _, n in parts)
    out = {}
    for name, first in parts[0][0].items():
        ds = [(d[name], n) for d, n in parts]
        c = {"targets": first["targets"],
             "max_abs_dc": np.max([d["max_abs_dc"] for d, _ in ds], axis=0).tolist(),
             "max_abs_da": np.max([d["max_abs_da"] for d, _ in ds], axis=0).tolist()}
        if "branch_share" in first:
            names = list(dict.fromkeys(nm for d, _ in ds for nm in d.get("branch_share", {})))
            n_t = len(first["targets"])
            c["branch_share"] = {nm: (sum(np.asarray(d["branch_share"].get(nm, np.zeros(n_t))) * n for d, n in ds)
                                      / total).tolist() for nm in names}
        out[name] = c
    return out
