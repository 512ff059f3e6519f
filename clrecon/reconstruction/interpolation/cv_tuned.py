"""``cv_tuned``: the fixed kernel with the smallest truth-free cross-validated error, chosen per scan.

Not a new estimator: the run cross-validates the fixed kernels on the scan's own rebinned rows
(:mod:`clrecon.evaluation.truth_free`, no ground truth), picks the one with the smallest
error (by default the NNDM folds, heart channels) and hands it here as ``Options.tuned`` =
``(method, ((knob, value), ...))``; these weights are then exactly that method's weights with
those knobs, so the reconstruction (same OpenCL kernels) is bit for bit the chosen method's
(tests/evaluation/test_truth_free.py). Without a choice (the interpolation API called directly) it is
``barycentric``. Opt-in: not in the ``recon.methods`` default.
"""

from __future__ import annotations

from dataclasses import replace

from clrecon.reconstruction.interpolation.registry import METHODS, register_method

#: The method's name (the run plans it apart, after the cross-validation: ``clrecon.pipeline.context.TUNED``).
NAME = "cv_tuned"
#: The kernel used when no cross-validation chose one.
FALLBACK = ("barycentric", ())


@register_method(name=NAME, label="CV-tuned", neighbours=None, target_grid="5d", axes=("cardiac", "resp"),
                 five_d=True, marker="*", rank=6, opt_in=True)
def weights(ch, targets, dc, da, d2, opts):
    name, knobs = opts.tuned if opts.tuned is not None else FALLBACK
    if name == NAME or METHODS[name].target_grid != "5d" or set(METHODS[name].axes) != {"cardiac", "resp"}:
        raise ValueError(f"cv_tuned: cannot use {name!r} (a 5-D method with both axes other than cv_tuned)")
    sub = replace(opts, tuned=None, **dict(knobs))
    return METHODS[name].weights(ch, targets, dc, da, d2, sub)
