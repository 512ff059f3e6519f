"""Stage ``metrics`` (once per run, not for a measured scan): Table 2, the respiratory-only
comparison and the motion metrics of every reconstruction against the ground truth
(:func:`clrecon.pipeline.evaluate.evaluate`), its second group of accumulators in the
executor's helper process where there is one."""

from __future__ import annotations

from clrecon.evaluation import groundtruth
from clrecon.pipeline.evaluate import evaluate
from clrecon.pipeline.stages.truth import MEASURED
from clrecon.simulation.phantom_sources import phantom_from_config


def skip(run) -> str | None:
    return MEASURED if run.scene.measured else None


def stage(run, pitch=None, volumes=None):
    run.log("metrics")
    phantom = phantom_from_config(run.scene.phantom)
    info: dict = {}
    met, resp_only, motion_res = evaluate(run.scene, volumes, run.targets, run.slices_z, run.pitches, run.variants,
                                          run.methods, phantom, progress=run.progress, info=info, pool=run.pool)
    run.records.update(metrics=met, respiratory_only=resp_only, motion=motion_res)
    run.note("metrics", processes=info["processes"])
    if not groundtruth.offers_lv_region(phantom):
        run.note("metrics", respiratory_only_skipped_because=(
            f"phantom.kind = {run.scene.phantom.kind!r} has no LV blood-pool model (the LV volume needs it)"))
    return met
