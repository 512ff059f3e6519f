"""Stage ``truth_free`` (per pitch, with ``recon.truth_free`` or the ``cv_tuned`` method): quality
without ground truth by cross-validation in sinogram space (:func:`clrecon.evaluation.truth_free.cross_validate`;
docs/truth-free.md). Its product, the per-variant choice of kernel, is what ``cv_tuned`` reconstructs with.
"""

from __future__ import annotations

from clrecon.evaluation import truth_free
from clrecon.outputs.volumes import pitch_key
from clrecon.pipeline.executors.base import Idle


def skip(run) -> str | None:
    return None if run.want_truth_free else "recon.truth_free is off and no cv_tuned method was asked for"


def stage(run, pitch: float, plan, store):
    pk = pitch_key(pitch)
    if plan.pp is None:
        run.records["truth_free"][pk] = {"skipped_because": "this pitch was reconstructed by an earlier run "
                                         "(resumed): run into a fresh output folder to cross-validate it"}
        return Idle()
    run.log(f"[{pk}] truth-free cross-validation")
    res = truth_free.cross_validate(store, plan.pp.plan_table, run.slices_z[plan.todo], run.recon_cfg, run.targets,
                                    run.variants, tuple(run.scene.recon.small_fov_mm), rt=run.rt)
    run.records["truth_free"][pk] = res
    return res
