"""``mc``: motion-compensated FBP with a registered (c, a) motion model (docs/motion-model.md).

Not made by the ``reconstruct`` stage: the pipeline stage ``mc_reconstruct``
(:mod:`clrecon.pipeline.stages.mc_reconstruct`) reads the barycentric first pass back, registers
it, fits the motion model and backprojects every row along the model into each target
(:mod:`clrecon.reconstruction.motion`). The rows of a (slice, view) and their weights are
barycentric's, so this entry's ``weights`` are barycentric's: what the interpolation API
returns for ``mc`` is the weighting the motion-compensated backprojection uses, before each row
is moved. Opt-in: not in the ``recon.methods`` default (it costs several times the paper methods).
"""

from __future__ import annotations

from clrecon.reconstruction.interpolation import barycentric
from clrecon.reconstruction.interpolation.registry import register_method


@register_method(name="mc", label="MC-FBP", neighbours=3, target_grid="5d", axes=("cardiac", "resp"),
                 five_d=True, marker="P", rank=7, opt_in=True, stage="mc_reconstruct")
def weights(ch, targets, dc, da, d2, opts):
    return barycentric.weights(ch, targets, dc, da, d2, opts)
