"""``clrecon run``: simulate (or reuse) -> reconstruct -> evaluate -> report, into a run directory.

The run directory holds ``results.json`` (schema in README.md), ``volumes.h5``
(:mod:`clrecon.outputs.volumes`) and ``report.md`` with its figures. Outputs are written under
temporary names and renamed when complete, so an interrupted run never leaves files that
look finished.

Only what the scene and the request ask for is computed: no noise stage without noise, no
cardiac axis without cardiac motion, no respiratory axis without breathing, only the
projections the requested slices use, only the requested methods and targets; a second run
with the same scan reuses the stored projections. ``results.json["stages"]`` says which
stages ran, which were skipped and why.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import platform
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from clrecon.config.scene import Scene
from clrecon.core import atomic, machine_speed, write_behind
from clrecon.core.errors import ClreconError
from clrecon.core.progress import progress as progress_counter
from clrecon.core.resources import peak_rss_bytes
from clrecon.core.runtime import get_runtime
from clrecon.core.versions import __version__
from clrecon.evaluation import claims, groundtruth, motion, truth_free
from clrecon.evaluation.truth_cache import TruthCache, truth_key
from clrecon.outputs import measured_record
from clrecon.outputs import report as report_mod
from clrecon.outputs.volumes import VolumeWriter, pitch_key
from clrecon.pipeline import costs as costs_mod
from clrecon.pipeline import distributed, helper_process, plan_ahead, preflight, truth_worker
from clrecon.pipeline import slabs as slabs_mod
from clrecon.pipeline.evaluate import evaluate
from clrecon.pipeline.variants import noise_variants
from clrecon.reconstruction import interpolation, reconstruct
from clrecon.reconstruction.reconstruct import StageTimes, Targets
from clrecon.simulation import simulate
from clrecon.simulation.phantom_sources import phantom_from_config
from clrecon.simulation.store import default_cache_dir

RESULTS_FORMAT = 1
#: From the interpolation-method registry: the 5DCT methods, and those compared in the
#: respiratory-only study (5DCT + the cardiac-blind, respiratory-grid methods such as r4dct).
#: The self-tuning method: planned after the truth-free cross-validation chose its kernel.
TUNED = "cv_tuned"
#: recon keys added after run directories existed: left out of the run key at these defaults.
_RECON_LATER = {"candidate_window_mm": 0.0, "truth_free": False, "volume_compression": "auto",
                "cardiac_distance_scale": 1.0}


def _progress(total: int, desc: str, enabled: bool, unit: str = "it"):
    return progress_counter(total, desc, enabled, unit)


def resolve_targets(scene: Scene, cardiac: Sequence[float] | None = None,
                    resp: Sequence[float] | None = None) -> Targets:
    """Targets of the run: the scene's, narrowed by ``cardiac``/``resp`` lists if given."""
    c = tuple(scene.cardiac_targets)
    r = tuple(scene.resp_targets)
    if cardiac:
        if not scene.has_cardiac:
            raise ClreconError("--targets: the scene has no cardiac motion, so there is no cardiac axis to select")
        bad = [x for x in cardiac if not 0 <= x < 1]
        if bad:
            raise ClreconError(f"--targets: cardiac phase {bad[0]} outside [0, 1)")
        c = tuple(float(x) for x in cardiac)
    if resp:
        if not scene.has_respiratory:
            raise ClreconError("--targets: the scene has no breathing, so there is no respiratory axis to select")
        bad = [x for x in resp if not 0 <= x <= 1]
        if bad:
            raise ClreconError(f"--targets: respiratory amplitude {bad[0]} outside [0, 1]")
        r = tuple(float(x) for x in resp)
    return Targets(cardiac=c, resp=r)


def _load_average() -> float | None:
    """1-minute load average of the machine (None where the OS does not say)."""
    try:
        return round(os.getloadavg()[0], 2)
    except (OSError, AttributeError):
        return None


def _versions() -> dict:
    import h5py
    import pyopencl
    import scipy

    return {"clrecon": __version__, "python": sys.version.split()[0], "numpy": np.__version__,
            "scipy": scipy.__version__, "pyopencl": pyopencl.VERSION_TEXT, "h5py": h5py.__version__,
            "platform": platform.platform()}


def _write_json_atomic(path: Path, obj) -> None:
    atomic.write_json(path, obj, indent=2)  # strict JSON, whole or not at all (clrecon.core.atomic)


def _json_default(o):
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, tuple):
        return list(o)
    raise TypeError(type(o))


def run(scene: Scene, out_dir: str | Path, methods: Sequence[str] | None = None,
        cardiac: Sequence[float] | None = None, resp: Sequence[float] | None = None,
        slice_range: tuple[int, int] | None = None, pitches: Sequence[float] | None = None,
        cache_dir: str | Path | None = None, progress: bool = True, report: bool = True,
        log: Callable[..., Any] = print, force: bool = False, client=None) -> dict[str, Any]:
    """Run the whole job; returns the ``results.json`` dictionary.

    ``client``: a ``distributed.Client``; the run's units are then computed on its workers
    first (:mod:`clrecon.pipeline.distributed`) and this process only assembles and evaluates.

    Before any work, :func:`clrecon.pipeline.preflight.check` compares the run's modelled peak
    memory and disk need with the machine and raises a one-line :class:`ClreconError` if it
    will not fit; ``force=True`` skips that check.
    """
    machine0 = machine_speed.start()  # the probe runs before the clock starts (~0.1 s)
    t_start = time.perf_counter()
    load_start = _load_average()
    out = Path(out_dir)  # made by the volume writer: a run refused before it leaves no folder behind
    rt = get_runtime()  # first: a machine with no working OpenCL driver gets its one line before any file
    methods = tuple(methods or scene.recon.methods)
    unknown = [m for m in methods if m not in scene.recon.methods and m not in reconstruct_methods()]
    if unknown:
        raise ClreconError(f"--methods: unknown method {unknown[0]!r}; allowed: {', '.join(reconstruct_methods())}")
    pitches = tuple(pitches or scene.scan.pitches)
    targets = resolve_targets(scene, cardiac, resp)
    nz = scene.recon.nz
    if slice_range is not None:
        i0, i1 = slice_range
        if not (0 <= i0 < i1 <= nz):
            raise ClreconError(f"--slices {i0}:{i1}: must satisfy 0 <= start < stop <= recon.nz = {nz}")
    slices_z = reconstruct.slice_positions(scene, slice_range)
    run_costs = costs_mod.run_costs(scene, methods, len(targets.cardiac), len(targets.resp), slices_z, pitches)
    cache_path = Path(cache_dir).expanduser() if cache_dir is not None else default_cache_dir()
    need = (preflight.needs(scene, run_costs, cache_path, out) if force
            else preflight.check(scene, run_costs, cache_path, out, rt=rt))
    recon_cfg = reconstruct.ReconstructionConfig.from_scene(scene)
    variants = noise_variants(scene)
    times = StageTimes()
    stages: dict = {}
    rc = scene.recon
    axes = {"cardiac_phase": targets.cardiac, "resp_amplitude": targets.resp, "z_mm": slices_z,
            "y_mm": reconstruct.voxel_coords(rc.ny, rc.voxel_mm), "x_mm": reconstruct.voxel_coords(rc.nx, rc.voxel_mm)}
    full_shape = targets.shape + (len(slices_z), rc.ny, rc.nx)
    scene_d = scene.to_dict()
    for k, v in _RECON_LATER.items():  # keys added later hash only away from their defaults
        if scene_d["recon"].get(k) == v:
            scene_d["recon"].pop(k)
    run_key = hashlib.sha256(json.dumps(
        {"scene": scene_d, "methods": methods, "pitches": pitches, "variants": variants,
         "targets": [targets.cardiac, targets.resp], "slices": slices_z.tolist(), "format": RESULTS_FORMAT,
         **({"driver": rt.cache_tag} if rt.cache_tag else {})},  # no resumption across drivers
        sort_keys=True, default=_json_default).encode()).hexdigest()
    writer = VolumeWriter(out / "volumes.h5", axes, keep_cardiac=scene.has_cardiac, keep_resp=scene.has_respiratory,
                          run_key=run_key, dtype=rc.volume_dtype, compression=run_costs["volume_compression"])
    if writer.resumed:
        log("resuming an interrupted run: finished slices and targets are kept")
    n_t = targets.shape[0] * targets.shape[1]
    sim_info = {}
    method_seconds: dict = {}
    method_plan_seconds: dict = {}  # pitch key -> method -> planning seconds (in method_seconds too)
    diagnostics: dict = {}  # pitch key -> method -> per-target weight diagnostics (cardiac-major)
    sampling: dict = {}  # per pitch: distinct cardiac phases and candidates per (slice, view)
    units_written = {"projections": 0}  # unit files written by this process (a resumed run: only the rest)
    recorded_summary: dict = {}  # per pitch: views left out by the recorded traces (lost / invalid stretches)
    stage_counts: dict = {}  # work counts of the reconstruction: detector cells read, noise cells drawn
    dist = None
    tuned = TUNED in methods
    want_tf = bool(rc.truth_free) or tuned
    truth_free_res: dict = {}
    if client is not None and want_tf:
        raise ClreconError("recon.truth_free and the cv_tuned method run in one process: drop --workers/--cluster")
    if client is not None and scene.measured:
        raise ClreconError("a measured scan (scan.source = 'dicom-ct-pd') runs in one process: "
                           "drop --workers/--cluster")
    truth_job = None  # the truths beside the reconstruction (clrecon.pipeline.truth_worker)
    beside = None  # its thread's seconds per truth dataset
    metrics_info: dict = {}  # the metrics stage's processes (clrecon.pipeline.evaluate)
    wb = write_behind.WriteBehind()  # the volume units written behind the reconstruction
    ahead = None  # the later pitches' plans, made in a second process (clrecon.pipeline.plan_ahead)
    # one spawned helper for the plans ahead, the metrics' second group and the report's figures,
    # warm by the time the last two need it (clrecon.pipeline.helper_process)
    helper = helper_process.start()
    helper_pool = helper.pool if helper is not None else None
    try:
        if (client is None and not scene.measured and not want_tf
                and plan_ahead.enabled(len(pitches), helper is not None)):
            ahead = plan_ahead.PlanAhead(scene, recon_cfg, pitches[1:], slices_z, targets,
                                         tuple(m for m in methods if m != TUNED), len(variants), pool=helper_pool)
        if helper is not None:
            helper.warm()  # queued behind the plans ahead
        if not scene.measured and client is None and truth_worker.enabled():
            gt_cfg = groundtruth.GroundTruthConfig.from_scene(scene)
            truths = TruthCache(cache_path, truth_key(scene, slices_z, targets))
            slabs_mod.declare_truths(writer, full_shape, n_t, truths)  # taking those an earlier run computed
            # started once the first pitch's projections are there (below): during the planning and
            # the simulation both cores are already busy, during the reconstruction often only one
            truth_job = truth_worker.TruthWorker(writer, truths, gt_cfg, slices_z, targets)
        # ---- distributed (docs/distributed.md): the workers compute every missing unit and this
        # process writes them; the serial path below then finds them done and only assembles
        if client is not None:
            dist = distributed.compute_units(client, writer, scene, recon_cfg, methods=methods, pitches=pitches,
                                             variants=variants, targets=targets, slices_z=slices_z,
                                             full_shape=full_shape, cache_dir=cache_path, progress=progress,
                                             log=log)
        # ---- end distributed
        for pitch in pitches:
            pk = pitch_key(pitch)
            slabs_mod.declare_recon(writer, pk, methods, variants, full_shape, len(slices_z))
            run_methods, todo = slabs_mod.unfinished(writer, pk, variants, methods)
            if todo.size == 0:
                log(f"[{pk}] already reconstructed (resumed run)")
                if want_tf:
                    truth_free_res[pk] = {"skipped_because": "this pitch was reconstructed by an earlier run "
                                          "(resumed): run into a fresh output folder to cross-validate it"}
                sim_info[pk] = {"projections_total": scene.scan.projection_count(scene.scanner, pitch),
                                "projections_needed": 0, "projections_simulated": 0, "projections_reused": 0,
                                "store": ""}
                continue
            log(f"[{pk}] planning {todo.size} slices x {n_t} targets x {len(run_methods)} methods")
            fixed_methods = tuple(m for m in run_methods if m != TUNED)
            run_tuned = TUNED in run_methods
            pp = ahead.take(pitch, todo, fixed_methods) if ahead is not None else None
            planned_here = pp is None
            if planned_here:
                pp = slabs_mod.plan_pitch(scene, recon_cfg, pitch, slices_z, todo, targets, fixed_methods,
                                          len(variants), progress)
            table, slabs, plans, needed, plan_s = pp.table, pp.slabs, pp.plans, pp.needed, pp.method_plan_seconds
            if want_tf:  # the folds read every candidate of the sampled slices; cv_tuned may choose any kernel
                t0 = time.perf_counter()
                needed = needed.copy()
                needed[truth_free.needed_projections(recon_cfg, pp.plan_table, slices_z[todo])] = True
                if run_tuned:
                    needed[np.unique(reconstruct.candidate_groups_of(recon_cfg, pp.plan_table,
                                                                     slices_z[todo]).projection)] = True
                times.add("plan", time.perf_counter() - t0)
            if planned_here:
                times.add("signals", pp.signals_seconds)
                times.add("plan", pp.plan_seconds)
            diagnostics[pk] = pp.diagnostics
            sampling[pk] = pp.sampling
            if pp.excluded:
                recorded_summary[pk] = {"views_total": len(table), "views_used": len(pp.plan_table),
                                        "views_excluded": int(len(table) - len(pp.plan_table)),
                                        "excluded_by_reason": dict(pp.excluded)}
            t0 = time.perf_counter()
            store = simulate.simulate(scene, pitch, needed=needed, cache_dir=cache_dir, progress=progress)
            times.add("simulate", time.perf_counter() - t0)
            sim_info[pk] = {"projections_total": len(table), "projections_needed": int(needed.sum()),
                            "projections_simulated": int(getattr(store, "n_simulated", 0)),
                            "projections_reused": int(getattr(store, "n_reused", 0)),
                            "store": str(getattr(store, "path", "")), "slabs": len(slabs),
                            "slab_slices": [int(b - a) for a, b in slabs]}
            units_written["projections"] += int(getattr(store, "units_written", 0))
            if truth_job is not None and not truth_job.started:
                truth_job.start()
            if want_tf:
                log(f"[{pk}] truth-free cross-validation")
                t0 = time.perf_counter()
                truth_free_res[pk] = truth_free.cross_validate(store, pp.plan_table, slices_z[todo], recon_cfg,
                                                               targets, variants, tuple(rc.small_fov_mm), rt=rt)
                times.add("truth_free", time.perf_counter() - t0)

            bar = _progress(todo.size * len(variants) * len(run_methods), f"reconstruct {pk}", progress,
                            "slice-volumes")
            ptimes = StageTimes()
            for k, (a, b) in enumerate(slabs):
                sel = todo[a:b]

                def on_slab(zs, slab, pk=pk, sel=sel):
                    for (v, m), vol in slab.items():  # r4dct (1, n_r), helical (1, 1): stored as they are
                        wb.submit(writer.write, f"recon/{pk}/{v}/{m}", vol, sel[zs])

                plan = plans[k]
                if plan is None:  # not kept (the plans of the whole scan were over the budget): made again
                    t0 = time.perf_counter()
                    plan = reconstruct.plan(recon_cfg, pp.plan_table, slices_z[sel], targets, run_methods)
                    times.add("plan", time.perf_counter() - t0)
                    for m, sec in plan.method_seconds.items():
                        plan_s[m] = plan_s.get(m, 0.0) + sec
                plans[k] = None
                if truth_job is not None:
                    truth_job.check()  # a failed truth thread stops the run now, not after the reconstruction
                if fixed_methods:
                    reconstruct.reconstruct(recon_cfg, store, plan, variants=variants, rt=rt, times=ptimes,
                                            progress=bar, on_slab=on_slab, slab_size=len(sel))
                del plan
                for v in variants if run_tuned else ():  # cv_tuned: the kernel chosen for this variant
                    t0 = time.perf_counter()
                    kern = truth_free.Kernel.from_dict(truth_free_res[pk]["choice"][v]["kernel"])
                    cfg_v = dataclasses.replace(recon_cfg, tuned=(kern.method, tuple(sorted(
                        (k, x) for k, x in kern.to_dict().items() if k != "method"))))
                    plan_v = reconstruct.plan(cfg_v, pp.plan_table, slices_z[sel], targets, (TUNED,))
                    times.add("plan", time.perf_counter() - t0)
                    plan_s[TUNED] = plan_s.get(TUNED, 0.0) + plan_v.method_seconds[TUNED]
                    reconstruct.reconstruct(cfg_v, store, plan_v, variants=(v,), rt=rt, times=ptimes,
                                            progress=bar, on_slab=on_slab, slab_size=len(sel))
                    del plan_v
            wb.drain()  # this pitch's units on disk before its store closes and the next pitch begins
            stage_counts.update({k: stage_counts.get(k, 0) + n for k, n in ptimes.counts.items()})
            bar.close()
            method_seconds[pk] = {}
            # a method's cost per variant: its interpolation + FBP of that variant plus its whole
            # plan (made once for every variant: a run of one variant pays it in full)
            for key, sec in ptimes.seconds.items():
                if key.startswith("plan:"):
                    m = key.split(":", 1)[1]
                    plan_s[m] = plan_s.get(m, 0.0) + sec
            method_plan_seconds[pk] = {m: round(sec, 3) for m, sec in plan_s.items()}
            for key, sec in ptimes.seconds.items():
                if key.startswith("method:"):
                    _, m, v = key.split(":")
                    method_seconds[pk].setdefault(v, {})[m] = round(sec + plan_s.get(m, 0.0), 3)
                elif not key.startswith("plan:"):
                    times.add(key, sec)
            if hasattr(store, "close"):
                store.close()

        if scene.measured:  # no ground truth exists: every reconstruction, no error against truth
            t0 = time.perf_counter()
            vol_file = writer.assemble()
            times.add("assemble_volumes", time.perf_counter() - t0)
            met, resp_only, motion_res = {}, {}, {}
        elif truth_job is not None:
            log("ground truth")
            t0 = time.perf_counter()
            truth_job.finish(lambda n: _progress(n, "ground truth", progress, "targets"))
            times.add("groundtruth", time.perf_counter() - t0)
            beside = truth_job.seconds
            truth_job = None
        else:
            log("ground truth")
            gt_cfg = groundtruth.GroundTruthConfig.from_scene(scene)
            truths = TruthCache(cache_path, truth_key(scene, slices_z, targets))
            n_r = targets.shape[1]
            slabs_mod.declare_truths(writer, full_shape, n_t, truths)  # taking those an earlier run computed
            t0 = time.perf_counter()
            skip = set(np.flatnonzero(writer.done("groundtruth")))
            bar = _progress(n_t - len(skip), "ground truth", progress, "targets")
            for i, j, vol in groundtruth.groundtruth_volumes(gt_cfg, slices_z, targets, rt=rt, progress=bar, skip=skip):
                truths.put(writer.write_target("groundtruth", i, j, n_r, vol))
            bar.close()
            times.add("groundtruth", time.perf_counter() - t0)
            t0 = time.perf_counter()
            skip = set(np.flatnonzero(writer.done("phantom")))
            for i, j, vol in groundtruth.phantom_truth_volumes(gt_cfg, slices_z, targets, rt=rt, skip=skip):
                truths.put(writer.write_target("phantom", i, j, n_r, vol))
            times.add("phantom_truth", time.perf_counter() - t0)
        if not scene.measured:
            t0 = time.perf_counter()
            vol_file = writer.assemble()
            times.add("assemble_volumes", time.perf_counter() - t0)
            log("metrics")
            t0 = time.perf_counter()
            phantom = phantom_from_config(scene.phantom)
            met, resp_only, motion_res = evaluate(scene, vol_file, targets, slices_z, pitches, variants, methods,
                                                  phantom, progress=progress, info=metrics_info,
                                                  pool=helper.pool if helper is not None else None)
            times.add("metrics", time.perf_counter() - t0)
        # the previous run's results and report must not describe the new volumes, even for a moment
        for name in ("results.json", "report.md", "report.html"):
            (out / name).unlink(missing_ok=True)
        t0 = time.perf_counter()
        writer.close()
        times.add("assemble_volumes", time.perf_counter() - t0)
    except BaseException:
        if ahead is not None:
            ahead.close()
        if helper is not None:
            helper.close()
        wb.close()  # the unit in flight finished (it is atomic either way) before the writer lets go
        if truth_job is not None:
            truth_job.stop()
        writer.abort()
        raise
    wb.close()
    if wb.wait_seconds or wb.beside_seconds:
        times.add("write_volumes", wb.wait_seconds)
    if ahead is not None:
        ahead.close()
        if ahead.beside_seconds:
            times.add("plan", ahead.wait_seconds)

    if dist is not None:  # what the workers computed, in place of this process's (empty) records
        distributed.merge_records(dist, times, sim_info, method_seconds, method_plan_seconds, diagnostics, sampling,
                                  units_written)
    for name in (("signals", "plan", "simulate", "read", "noise", "rebin", "interpolate", "fbp", "write_volumes")
                 + (("truth_free",) if want_tf else ())
                 + ("groundtruth", "phantom_truth", "assemble_volumes", "metrics")):
        stages[name] = {"ran": name in times.seconds, "seconds": round(times.seconds.get(name, 0.0), 3)}
    if not scene.noise.enabled:
        stages["noise"]["skipped_because"] = "scene has noise.enabled = false"
    total_sim = sum(v["projections_simulated"] for v in sim_info.values())
    if total_sim == 0:
        stages["simulate"]["ran"] = False
        stages["simulate"]["skipped_because"] = "every needed projection was already in the projection store"
    stages["simulate"].update(per_pitch=sim_info)
    stages["groundtruth"]["targets_from_cache"] = int(writer.units_written.get("adopted", 0))
    if metrics_info:
        stages["metrics"]["processes"] = metrics_info["processes"]
    if beside is not None:  # computed in a thread beside the reconstruction: its own seconds apart
        stages["phantom_truth"]["ran"] = True
        for name, key in (("groundtruth", "groundtruth"), ("phantom_truth", "phantom")):
            stages[name]["beside_seconds"] = round(beside[key], 3)
        stages["groundtruth"]["waited_for"] = ("the seconds are the run's wait for the truths after the "
                                               "reconstruction; beside_seconds their thread's own time")
    if ahead is not None and ahead.beside_seconds:  # later pitches planned in a second process
        stages["plan"]["beside_seconds"] = round(ahead.beside_seconds, 3)
        stages["plan"]["waited_for"] = ("the seconds are the run's own planning plus its wait for the later "
                                        "pitches' plans; beside_seconds the second process's time on them")
    if wb.background and "write_volumes" in times.seconds:  # the units written in a thread
        stages["write_volumes"]["beside_seconds"] = round(wb.beside_seconds, 3)
        stages["write_volumes"]["waited_for"] = ("the seconds are the run's wait for the writer thread; "
                                                 "beside_seconds its own time writing the units")
    stages["read"]["cells"] = int(stage_counts.get("read_cells", 0))
    stages["noise"]["cells"] = int(stage_counts.get("noise_cells", 0))
    if scene.measured:
        for name in ("groundtruth", "phantom_truth", "metrics"):
            stages[name]["skipped_because"] = "measured scan: no ground truth exists, so no error against truth"
    elif not groundtruth.offers_lv_region(phantom):
        stages["metrics"]["respiratory_only_skipped_because"] = (
            f"phantom.kind = {scene.phantom.kind!r} has no LV blood-pool model (the LV volume needs it)")
    results = {
        "format_version": RESULTS_FORMAT,
        "scene": scene.to_dict(),
        "scene_source": scene.source,
        "versions": _versions(),
        "device": rt.description,
        "driver": rt.driver,
        "request": {"methods": list(methods), "pitches": list(pitches), "variants": list(variants),
                    "targets": {"cardiac": list(targets.cardiac), "resp": list(targets.resp)},
                    "slices": list(slice_range) if slice_range else [0, nz], "slices_z_mm": slices_z.tolist()},
        "dimensions": {"cardiac": scene.has_cardiac, "resp": scene.has_respiratory},
        "resumed": writer.resumed,
        "preflight": {"forced": bool(force), "needs_bytes": need},
        "units_written": dict(units_written, **writer.units_written),
        "stages": stages,
        "metrics": met,
        "method_seconds": method_seconds,
        "method_plan_seconds": method_plan_seconds,
        "diagnostics": diagnostics,
        "sampling": sampling,
        "respiratory_only": resp_only,
        "motion": motion_res,
        "motion_definitions": motion.definitions(motion.MotionConfig.from_scene(scene, slices_z)),
        "outputs": {"volumes": "volumes.h5", "report": "report.md" if report else None,
                    "volume_compression": writer.compression},
        "measured": bool(scene.measured),
        "ground_truth": {"available": not scene.measured,
                         "why": "measured scan: error against truth is unavailable" if scene.measured else ""},
        "recorded_signals": recorded_summary,
    }
    if scene.measured:  # the reading, the orientation check, the calibration's sources, the patient frame
        measured_record.annotate_results(results, scene, log)
    if want_tf:
        results["truth_free"] = truth_free_res
    if dist is not None:
        results["distributed"] = dist.summary
    results["claims"] = claims.evaluate_claims(results)  # the paper's claims, measured
    # how fast the machine was over the work (before the report, which shows it): cross-run
    # seconds on a shared machine are comparable only beside this (core/machine_speed.py)
    results["machine_speed"] = machine0.finish()
    if report:
        t0 = time.perf_counter()
        try:
            report_mod.write_report(out, results, pool=helper.pool if helper is not None else None)
        finally:
            if helper is not None:
                helper.close()
        stages["report"] = {"ran": True, "seconds": round(time.perf_counter() - t0, 3)}
    elif helper is not None:
        helper.close()
    results["total_seconds"] = round(time.perf_counter() - t_start, 3)
    # what no stage accounts for (pre-flight, scene checks, the report's claims, closing files):
    # named so that a run's stage table sums to its wall time
    stages["unaccounted"] = {"ran": True, "seconds": round(
        results["total_seconds"] - sum(st.get("seconds", 0.0) for st in stages.values()), 3)}
    results["peak_rss_bytes"] = peak_rss_bytes()
    results["load_average"] = {"start": load_start, "end": _load_average()}
    _write_json_atomic(out / "results.json", measured_record.for_disk(results))  # no patient's path on disk
    return results


def reconstruct_methods():
    return interpolation.method_names()
