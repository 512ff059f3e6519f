"""``clrecon run``: simulate (or reuse) -> reconstruct -> evaluate -> report, into a run directory.

The run is the graph of stages of :mod:`clrecon.pipeline.graph`, run by an executor
(:mod:`clrecon.pipeline.executors`: ``serial``, ``local`` (default: overlapped on this
machine's cores) or ``dask``); whichever runs it, the volumes and numbers are the same bit
for bit. The run directory holds ``results.json`` (schema: docs/run-directory.md "results.json"),
``volumes.h5`` (:mod:`clrecon.outputs.volumes`) and ``report.md`` with its figures. Outputs
are written under temporary names and renamed when complete, so an interrupted run never
leaves files that look finished (``report.md``/``report.html`` are renamed last, once
``results.json`` is whole: a run that fails at ``results.json`` leaves no report); the next run
of the same request resumes it.

Only what the scene and the request ask for is computed: no noise stage without noise, no
cardiac axis without cardiac motion, no respiratory axis without breathing, only the
projections the requested slices use, only the requested methods and targets; a second run
with the same scan reuses the stored projections. ``results.json["stages"]`` says which
stages ran, which were skipped and why.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from clrecon.config.scene import Scene
from clrecon.core import drivers, machine_speed
from clrecon.core.errors import ClreconError
from clrecon.core.runtime import get_runtime
from clrecon.outputs import report as report_mod
from clrecon.pipeline import distributed, driver_choice, executors
from clrecon.pipeline.context import RESULTS_FORMAT, TUNED, open_run, resolve_targets
from clrecon.pipeline.graph import GRAPH
from clrecon.pipeline.stages import results as results_mod
from clrecon.reconstruction import interpolation, reconstruct

__all__ = ["RESULTS_FORMAT", "TUNED", "reconstruct_methods", "resolve_targets", "run"]


def run(scene: Scene, out_dir: str | Path, methods: Sequence[str] | None = None,
        cardiac: Sequence[float] | None = None, resp: Sequence[float] | None = None,
        slice_range: tuple[int, int] | None = None, pitches: Sequence[float] | None = None,
        cache_dir: str | Path | None = None, progress: bool = True, report: bool = True,
        log: Callable[..., Any] = print, force: bool = False, client=None,
        executor: str | executors.Executor | None = None) -> dict[str, Any]:
    """Run the whole job; returns the ``results.json`` dictionary.

    ``executor``: ``"serial"`` (every stage in this thread, in order), ``"local"`` (the
    default: the same stages overlapped on this machine's cores) or ``"dask"`` (the units on
    the workers of ``client``, a ``distributed.Client``; a client alone implies it), or an
    :class:`~clrecon.pipeline.executors.Executor`.

    Before any work, :func:`clrecon.pipeline.preflight.check` compares the run's modelled peak
    memory and disk need with the machine and raises a one-line :class:`ClreconError` if it
    will not fit; ``force=True`` skips that check.
    """
    machine0 = machine_speed.start()  # the probe runs before the clock starts (~0.1 s)
    t_start = time.perf_counter()
    load_start = results_mod.load_average()
    out = Path(out_dir)  # made by the volume writer: a run refused before it leaves no folder behind
    decision = _choose_driver(scene, methods, cardiac, resp, slice_range, pitches)
    rt = get_runtime()  # first: a machine with no working OpenCL driver gets its one line before any file
    ran = drivers.driver_of(rt.device.platform.name)
    if decision is not None and decision.predicted and ran is not None and ran.key == decision.key:  # compared
        rt.choice.chosen_by, rt.choice.timing = decision.reason, decision.as_dict()
        log(f"OpenCL driver: {decision.key}, {decision.reason}")
    ex = executors.make(executor, client)
    if client is not None and decision is not None and decision.key and decision.predicted:  # the workers too
        client.register_plugin(distributed.preference_plugin(decision.key, decision.reason))
    ctx = open_run(scene, out, methods, cardiac, resp, slice_range, pitches, cache_dir, rt=rt,
                   executor_kind=ex.kind, distributed=ex.fine_units, force=force, report=report, progress=progress,
                   log=log, graph=GRAPH, executor_summary=ex.summary, machine_speed=machine0)
    try:
        products = ex.run(GRAPH, ctx)
    except BaseException:
        ctx.writer.abort()
        report_mod.discard_report(out)  # a report staged for this run must not outlive its failure
        raise
    try:
        results = results_mod.finish(ctx, products[("results", None)], t_start, load_start)
        results_mod.write_json_atomic(out / "results.json", results)
    except BaseException:  # a full disk at results.json: no report that reads as a finished run
        report_mod.discard_report(out)
        raise
    if products.get(("report", None)) is not None:  # the report appears once results.json is whole
        report_mod.commit_report(out)
    return results


def _choose_driver(scene, methods, cardiac, resp, slice_range, pitches) -> driver_choice.Decision | None:
    """The run's CPU driver, chosen by timing for its mix of kernel work and made this process's preference
    (:mod:`clrecon.pipeline.driver_choice`); None with ``CLRECON_DEVICE`` or a request ``open_run`` refuses."""
    try:
        targets = resolve_targets(scene, cardiac, resp)
        nz = scene.recon.nz
        ok_range = slice_range is None or 0 <= slice_range[0] < slice_range[1] <= nz
        slices_z = reconstruct.slice_positions(scene, slice_range if ok_range else None)
    except ClreconError:
        return None  # open_run says what is wrong, in its one line
    known = [m for m in (methods or scene.recon.methods) if m in interpolation.METHODS]
    decision = driver_choice.choose_for_run(scene, known or None, len(targets.cardiac), len(targets.resp),
                                            slices_z, pitches, targets=targets)
    driver_choice.apply(decision)
    return decision


def reconstruct_methods():
    return interpolation.method_names()
