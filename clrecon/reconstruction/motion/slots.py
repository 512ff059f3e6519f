"""Which rows each (slice, view, target) backprojects, and with what weight, in the motion-compensated FBP.

Once a motion model brings every row to the target state, any candidate of a (slice, view) could
serve it; what still separates them is how far the model has to carry them (its error grows
with the phase distance) and the SSRB data-model error (it grows with the row's distance from
the slice, which the kernel's taper handles per voxel). Two ways to weight:

- :func:`kernel_slots`: a Gaussian in phase space around the target,
  ``w = exp(-d_c^2 / 2 sigma_c^2 - (a - a*)^2 / 2 sigma_a^2)`` (d_c the circular cardiac
  distance), keeping the ``max_slots`` largest per (slice, view, target), normalised; wide
  widths approach the uniform weights of "every projection serves every phase".
- :func:`plan_slots`: an interpolation method's own weights (e.g. barycentric), so that the model
  only corrects the residual phase offset of the rows that method chose.

Outputs are (T, S, V, K) arrays: local projection indices into :class:`PlaneRows` (-1 = empty,
always after the filled slots) and float32 weights. docs/motion-model.md "The method" (step 4).
"""

from __future__ import annotations

import math

import numpy as np

from clrecon.reconstruction.motion.backproject import PlaneRows
from clrecon.reconstruction.rebin import CandidateGroups


def _dense(groups: CandidateGroups):
    """(G, Kc) positions into the CSR arrays (-1 beyond a group's count) and the counts."""
    counts = groups.counts
    kc = int(counts.max()) if counts.size else 0
    pos = groups.offsets[:-1, None] + np.arange(max(kc, 1))[None, :]
    return np.where(np.arange(max(kc, 1))[None, :] < counts[:, None], pos, -1), counts


def kernel_slots(groups: CandidateGroups, cardiac_phase, resp_amplitude, targets, *, sigma_c: float,
                 sigma_a: float, max_slots: int, rows: PlaneRows | None = None):
    """Gaussian phase-space weights of the candidates, the ``max_slots`` largest per (slice, view, target).

    Parameters
    ----------
    groups : CandidateGroups of S slices (slice-major, V views each)
    cardiac_phase, resp_amplitude : (n,) the candidates' recorded c and a (``table.x[groups.row]``)
    targets : (T, 2) (c*, a*) pairs
    sigma_c, sigma_a : kernel widths (cardiac in cycles, amplitude in [0, 1] units); ``inf`` = flat
    max_slots : K, kept per (slice, view, target) (ties: the earlier candidate)
    rows : PlaneRows, optional: return local indices into it (else global projection numbers)

    Returns
    -------
    (slot_proj (T, S, V, K) int, slot_w (T, S, V, K) float32); weights sum to 1 per (t, s, v).
    """
    for name, v in (("sigma_c", sigma_c), ("sigma_a", sigma_a)):
        if not (isinstance(v, (int, float)) and v > 0 and not math.isnan(v)):
            raise ValueError(f"{name} = {v!r}: must be > 0 (inf for a flat kernel)")
    if not (isinstance(max_slots, int) and max_slots >= 1):
        raise ValueError(f"max_slots = {max_slots!r}: must be an integer >= 1")
    tg = np.atleast_2d(np.asarray(targets, np.float64))
    c = np.asarray(cardiac_phase, np.float64)
    a = np.asarray(resp_amplitude, np.float64)
    pos, counts = _dense(groups)
    if np.any(counts == 0):
        raise ValueError(f"{int(np.sum(counts == 0))} (slice, view) groups have no candidate")
    valid = pos >= 0
    pc = np.where(valid, c[np.maximum(pos, 0)], 0.0)
    pa = np.where(valid, a[np.maximum(pos, 0)], 0.0)
    K = min(max_slots, pos.shape[1])
    G = pos.shape[0]
    S = len(groups.slice_z_mm)
    V = groups.views_per_rotation
    out_p = np.full((len(tg), G, K), -1, np.int64)
    out_w = np.zeros((len(tg), G, K), np.float32)
    proj = groups.projection
    for t, (ct, at) in enumerate(tg):
        dc = np.abs((pc - ct + 0.5) % 1.0 - 0.5)
        logw = -0.5 * (dc / sigma_c) ** 2 - 0.5 * ((pa - at) / sigma_a) ** 2
        logw = np.where(valid, logw, -np.inf)
        order = np.argsort(-logw, axis=1, kind="stable")[:, :K]
        lw = np.take_along_axis(logw, order, axis=1)
        w = np.exp(lw - lw[:, :1])          # relative to the largest: no underflow to all-zero
        w = np.where(np.isfinite(lw), w, 0.0)
        w /= w.sum(axis=1, keepdims=True)
        chosen = np.take_along_axis(pos, order, axis=1)
        keep = chosen >= 0
        out_p[t] = np.where(keep, proj[np.maximum(chosen, 0)], -1)
        out_w[t] = np.where(keep, w, 0.0)
    out_p = out_p.reshape(len(tg), S, V, K)
    out_w = out_w.reshape(len(tg), S, V, K)
    if rows is not None:
        out_p = rows.local_index(out_p)
    return out_p, out_w


def plan_slots(proj_index, weight, rows: PlaneRows | None = None):
    """A method plan's weights (S, V, T, K) (``MethodWeights.proj_index``, ``.weight``) as slots (T, S, V, K).

    Zero-weight slots are emptied (-1) and the filled ones moved to the front of each list.
    """
    p = np.asarray(proj_index)
    w = np.asarray(weight, np.float64)
    if p.ndim != 4 or w.shape != p.shape:
        raise ValueError(f"proj_index {p.shape} and weight {w.shape}: expected (S, V, T, K) each")
    p = np.moveaxis(p, 2, 0)
    w = np.moveaxis(w, 2, 0)
    filled = w != 0
    order = np.argsort(~filled, axis=-1, kind="stable")
    p = np.take_along_axis(p, order, axis=-1)
    w = np.take_along_axis(w, order, axis=-1)
    filled = np.take_along_axis(filled, order, axis=-1)
    p = np.where(filled, p, -1).astype(np.int64)
    w = np.where(filled, w, 0.0).astype(np.float32)
    if rows is not None:
        p = rows.local_index(p)
    return p, w
