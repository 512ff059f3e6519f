"""``mc``: motion-compensated FBP with a registered (c, a) motion model (docs/motion-model.md).

Not made by the ``reconstruct`` stage: the pipeline stage ``mc_reconstruct``
(:mod:`clrecon.pipeline.stages.mc_reconstruct`) reads its first pass back (``first_pass`` below:
barycentric, the one place that says so), registers it, fits the motion model and backprojects
every row along the model into each target (:mod:`clrecon.reconstruction.motion.mc_fbp`). The
rows of a (slice, view) and their weights are barycentric's, so this entry's ``weights`` are
barycentric's: what the interpolation API returns for ``mc`` is the weighting the
motion-compensated backprojection uses, before each row is moved. Opt-in: not in the
``recon.methods`` default (it costs several times the paper methods).
"""

from __future__ import annotations

from clrecon.reconstruction.interpolation import barycentric
from clrecon.reconstruction.interpolation.registry import register_method


@register_method(name="mc", label="MC-FBP", neighbours=3, target_grid="5d", axes=("cardiac", "resp"),
                 five_d=True, marker="P", rank=7, opt_in=True, stage="mc_reconstruct",
                 first_pass="barycentric")
def weights(ch, targets, dc, da, d2, opts):
    return barycentric.weights(ch, targets, dc, da, d2, opts)
