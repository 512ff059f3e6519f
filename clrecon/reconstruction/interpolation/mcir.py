"""``mcir``: OS-SART on the cone-beam rows through ``mc``'s motion model, with a density term (docs/iterative.md).

Not made by the ``reconstruct`` stage: the pipeline stage ``mcir_reconstruct``
(:mod:`clrecon.pipeline.stages.mcir_reconstruct`) takes ``mc``'s motion model (fitted from the
barycentric first pass, ``first_pass`` below) and solves one reference volume and a density term
from every cone-beam row (:mod:`clrecon.reconstruction.iterative.method`). It has no per-row
interpolation weights of its own: what the interpolation API returns for ``mcir`` is its first
pass's weighting (the images its motion model is registered from). Opt-in: not in the
``recon.methods`` default (it costs several times ``mc``).
"""

from __future__ import annotations

from clrecon.reconstruction.interpolation import barycentric
from clrecon.reconstruction.interpolation.registry import register_method


@register_method(name="mcir", label="MC-SART", neighbours=None, target_grid="5d", axes=("cardiac", "resp"),
                 five_d=True, marker="h", rank=8, opt_in=True, stage="mcir_reconstruct",
                 first_pass="barycentric")
def weights(ch, targets, dc, da, d2, opts):
    return barycentric.weights(ch, targets, dc, da, d2, opts)
