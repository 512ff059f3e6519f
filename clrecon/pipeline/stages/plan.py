"""Stage ``plan`` (per pitch): the projection table, the slab-by-slab interpolation plans and
the projections they need (:func:`clrecon.pipeline.slabs.plan_pitch`).

A resumed run plans only the slices and methods it still lacks (:func:`todo`). The plan is a
pure function of the scene, the pitch, the slices, the targets and the methods, so an executor
may make it ahead in a helper process (:func:`ahead`) and hand it to :func:`stage`.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from clrecon.evaluation import consistency, truth_free
from clrecon.outputs.volumes import pitch_key
from clrecon.pipeline import slabs as slabs_mod
from clrecon.pipeline.context import TUNED
from clrecon.pipeline.executors.base import Idle
from clrecon.pipeline.stages import consistency as consistency_stage
from clrecon.reconstruction import reconstruct
from clrecon.reconstruction.iterative import method as mcir


@dataclass
class PitchTodo:
    """The product of ``plan`` (the ``plan`` the later stages take): what one pitch still has to do
    (its unfinished methods and slices, the projections they read) and its slabs (``pp``)."""

    pitch: float
    methods: tuple                  # the methods with an unfinished unit
    todo: np.ndarray                # slice indices one of them lacks
    pp: slabs_mod.PitchSlabs | None  # its planned slabs; None: nothing to do (a resumed run's finished pitch)
    needed: np.ndarray | None = None  # (n,) bool: the projections the reconstruction (and the folds) read
    plan_seconds: dict = field(default_factory=dict)  # method -> planning seconds

    @property
    def fixed_methods(self) -> tuple:
        """The methods ``reconstruct`` makes with the plan (not cv_tuned, planned apart; not a second-pass method)."""
        return slabs_mod.fixed_methods(self.methods)


def todo(run, pitch: float) -> tuple[tuple, np.ndarray]:
    """(methods with an unfinished unit, slice indices one of them lacks); declares the pitch's datasets."""
    pk = pitch_key(pitch)
    got = run.unfinished
    if pk not in got:
        slabs_mod.declare_recon(run.writer, pk, run.methods, run.variants, run.full_shape, len(run.slices_z))
        got[pk] = slabs_mod.unfinished(run.writer, pk, run.variants, run.methods)
    return got[pk]


def ahead(run, pitch: float):
    """``(fn, args)`` of this pitch's planning for a helper process, or None where it is planned here
    (a measured scan, the truth-free folds, nothing to do)."""
    if run.scene.measured or run.want_truth_free:
        return None
    methods, slices = todo(run, pitch)
    fixed = slabs_mod.planned_methods(methods)
    if not slices.size or not fixed:
        return None
    return slabs_mod.plan_pitch, (run.scene, run.recon_cfg, pitch, run.slices_z, slices, run.targets, fixed,
                                  len(run.variants), False)


def stage(run, pitch: float, ahead=None) -> PitchTodo | Idle:
    pk = pitch_key(pitch)
    methods, slices = todo(run, pitch)
    if slices.size == 0:
        run.log(f"[{pk}] already reconstructed (resumed run)")
        return Idle(PitchTodo(pitch, methods, slices, None))
    run.log(f"[{pk}] planning {slices.size} slices x {run.n_targets} targets x {len(methods)} methods")
    fixed = slabs_mod.planned_methods(methods)
    pp = ahead
    if pp is None:
        pp = slabs_mod.plan_pitch(run.scene, run.recon_cfg, pitch, run.slices_z, slices, run.targets, fixed,
                                  len(run.variants), run.progress)
        run.clock.add("signals", pp.signals_seconds)
    needed = pp.needed
    if run.want_truth_free:  # the folds read every candidate of the sampled slices; cv_tuned may choose any kernel
        t0 = time.perf_counter()
        needed = needed.copy()
        needed[truth_free.needed_projections(run.recon_cfg, pp.plan_table, run.slices_z[slices])] = True
        if TUNED in methods:
            needed[np.unique(reconstruct.candidate_groups_of(run.recon_cfg, pp.plan_table,
                                                             run.slices_z[slices]).projection)] = True
        run.clock.add("plan", time.perf_counter() - t0)
    if consistency_stage.METHOD in run.methods:  # the consistency check reads every candidate of its sampled slices
        t0 = time.perf_counter()
        needed = needed.copy()
        needed[consistency.needed_projections(run.recon_cfg, pp.plan_table, run.slices_z)] = True
        run.clock.add("plan", time.perf_counter() - t0)
    if mcir.NAME in methods:  # mcir reads every view that sees a slice (its slabs' cone-beam rows)
        needed = needed.copy()
        needed[mcir.needed_projections(run.scene.scanner, run.scene.recon, run.scene.recon.mcir,
                                       run.recon_cfg.object_radius_mm, pp.plan_table, run.slices_z)] = True
    run.records["diagnostics"][pk] = pp.diagnostics
    run.records["sampling"][pk] = pp.sampling
    if pp.excluded:
        run.records["recorded_signals"][pk] = {
            "views_total": len(pp.table), "views_used": len(pp.plan_table),
            "views_excluded": int(len(pp.table) - len(pp.plan_table)), "excluded_by_reason": dict(pp.excluded)}
    return PitchTodo(pitch, methods, slices, pp, needed, dict(pp.method_plan_seconds))
