"""``helical``: the conventional free-breathing helical reconstruction, phase ignored.

What a standard scanner gives without gating: for each (slice, view) the single-slice
rebinning of the candidate projection whose source is nearest the slice in z (the turn
nearest in z, smallest ``|z_slice - z_k|``), whatever its cardiac phase and respiratory
amplitude; the same fan-beam FBP. One slot, weight 1. Ties (a slice exactly half-way between
two turns) go to the earlier projection (group order is turn order).

Phase-blind: ``target_grid = "none"`` (one volume, broadcast over every (c*, a*) target) and
no phase axes; it reads the candidates' z distance ``ch.dz`` (mm), which
:func:`clrecon.reconstruction.interpolation.weights.batch_weights` takes as ``dz`` and
:func:`clrecon.reconstruction.reconstruct.plan` fills from the SSRB candidate groups. It is
the "without phase-space interpolation" reconstruction of the paper's Figure 3 (choice:
docs/choices-reconstruction.md "helical baseline").
"""

from __future__ import annotations

import numpy as np

from clrecon.reconstruction.interpolation.registry import register_method


@register_method(name="helical", label="helical (no gating)", neighbours=1, target_grid="none", axes=(),
                 five_d=False, marker="X", rank=5)
def weights(ch, targets, dc, da, d2, opts):
    if ch.dz is None:
        raise ValueError("method 'helical' needs each candidate's z distance: pass dz (mm, like c) to "
                         "batch_weights / method_weights")
    # padding has dz = inf, so an empty group's argmin is 0 (the dispatcher zeroes its weights)
    near = np.argmin(ch.dz, axis=-1)                                   # (g,)
    idx = np.broadcast_to(near[:, None, None], (near.shape[0], targets.shape[0], 1)).copy()
    return idx, np.ones(idx.shape)
