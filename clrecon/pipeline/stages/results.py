"""Stage ``results`` (once per run, untimed; ``after`` ``assemble`` and ``metrics``): ``volumes.h5``
closed, the ``results.json`` dictionary built from the stages' records and the executor's clock (schema:
docs/run-directory.md "results.json"); :func:`finish` adds what is known only at the very end
and :func:`write_json_atomic` writes it."""

from __future__ import annotations

import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

from clrecon.core import atomic
from clrecon.core.resources import peak_child_rss_bytes, peak_rss_bytes
from clrecon.core.versions import __version__
from clrecon.evaluation import claims, motion
from clrecon.outputs import measured_record
from clrecon.pipeline.context import RESULTS_FORMAT
from clrecon.pipeline.stages import assemble


def load_average() -> float | None:
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


def write_json_atomic(path: Path, results: dict) -> None:
    """``results.json`` as it goes to disk: no patient's path in it
    (:func:`clrecon.outputs.measured_record.for_disk`)."""
    _write_json_atomic(path, measured_record.for_disk(results))

#: What ``waited_for`` says of a part computed beside the run.
BESIDE = ("the seconds are the run's own time on it and its wait for what was done beside it; beside_seconds the "
          "time spent on it elsewhere (the helper process, a thread) while the run went on")


def stage_table(run, skipped: set) -> dict:
    """``results.json["stages"]``: every part of every stage in the graph's order, with its seconds."""
    clock, out = run.clock, {}
    for st in run.graph:
        if st.optional and st.name in skipped:
            continue
        for part in st.parts:
            ran = part in clock.seconds or part in clock.beside_seconds
            out[part] = {"ran": ran, "seconds": round(clock.seconds.get(part, 0.0), 3)}
            if st.name in skipped:
                out[part]["skipped_because"] = st.skip(run)
            if clock.beside_seconds.get(part, 0.0) > 0:
                out[part].update(beside_seconds=round(clock.beside_seconds[part], 3), waited_for=BESIDE)
    scene, rec = run.scene, run.records
    if scene.measured:  # a measured scan: "simulate" imports its projections, and they carry their own noise
        out["noise"]["skipped_because"] = "a measured scan: the projections carry their own noise"
        out["simulate"]["does"] = "imports the measured projections into the projection store"
    elif not scene.noise.enabled:
        out["noise"]["skipped_because"] = "scene has noise.enabled = false"
    if sum(v["projections_simulated"] for v in rec["sim_info"].values()) == 0:
        out["simulate"].update(ran=False, skipped_because="every needed projection was already in the projection store")
    out["simulate"]["per_pitch"] = rec["sim_info"]
    out["groundtruth"]["targets_from_cache"] = int(run.writer.units_written.get("adopted", 0))
    out["read"]["cells"] = int(rec["counts"].get("read_cells", 0))
    out["noise"]["cells"] = int(rec["counts"].get("noise_cells", 0))
    for part, notes in run.notes.items():
        out.setdefault(part, {"ran": False, "seconds": 0.0}).update(notes)
    return out


def stage(run, pitch=None) -> dict:
    assemble.close(run)
    scene, rec, targets = run.scene, run.records, run.targets
    skipped = {st.name for st in run.graph if st.skip is not None and st.skip(run)}
    results = {
        "format_version": RESULTS_FORMAT,
        "scene": scene.to_dict(),
        "scene_source": scene.source,
        "versions": _versions(),
        "device": run.rt.description,
        "driver": run.rt.driver,
        "request": {"methods": list(run.methods), "pitches": list(run.pitches), "variants": list(run.variants),
                    "targets": {"cardiac": list(targets.cardiac), "resp": list(targets.resp)},
                    "slices": list(run.slice_range) if run.slice_range else [0, scene.recon.nz],
                    "slices_z_mm": run.slices_z.tolist()},
        "dimensions": {"cardiac": scene.has_cardiac, "resp": scene.has_respiratory},
        "resumed": run.writer.resumed,
        "preflight": {"forced": bool(run.force), "needs_bytes": run.need},
        "units_written": dict(rec["units_written"], **run.writer.units_written),
        "executor": run.executor_kind,
        "stages": stage_table(run, skipped),
        "metrics": rec["metrics"],
        "method_seconds": rec["method_seconds"],
        "method_plan_seconds": rec["method_plan_seconds"],
        "diagnostics": rec["diagnostics"],
        "sampling": rec["sampling"],
        "respiratory_only": rec["respiratory_only"],
        "motion": rec["motion"],
        "motion_definitions": motion.definitions(motion.MotionConfig.from_scene(scene, run.slices_z)),
        "outputs": {"volumes": "volumes.h5", "report": "report.md" if run.report else None,
                    "volume_compression": run.writer.compression},
        "measured": bool(scene.measured),
        "ground_truth": {"available": not scene.measured,
                         "why": "measured scan: error against truth is unavailable" if scene.measured else ""},
        "recorded_signals": rec["recorded_signals"],
    }
    if scene.measured:  # the reading, the orientation check, the calibration's sources, the patient frame
        measured_record.annotate_results(results, scene, run.log)
    if run.want_truth_free:
        results["truth_free"] = rec["truth_free"]
    if "mc" in run.methods:  # the truth-free check of mc (stage consistency)
        results["consistency"] = rec["consistency"]
    summary = run.executor_summary()
    if summary is not None:
        results["distributed"] = summary
    results["claims"] = claims.evaluate_claims(results)  # the paper's claims, measured
    # how fast the machine was over the work (before the report, which shows it): cross-run
    # seconds on a shared machine are comparable only beside this (core/machine_speed.py)
    results["machine_speed"] = run.machine_speed.finish()
    return results


def finish(run, results: dict, t_start: float, load_start) -> dict:
    """The report's seconds, the total, what no stage accounts for (pre-flight, scene checks, the
    claims, closing files: named so that the stage table sums to the wall time), peak memory, load."""
    st = results["stages"]
    if "report" in run.clock.seconds:
        st["report"] = {"ran": True, "seconds": round(run.clock.seconds["report"], 3)}
    results["total_seconds"] = round(time.perf_counter() - t_start, 3)
    st.pop("unaccounted", None)
    st["unaccounted"] = {"ran": True, "seconds": round(
        results["total_seconds"] - sum(s.get("seconds", 0.0) for s in st.values()), 3)}
    results["peak_rss_bytes"] = peak_rss_bytes()
    results["peak_child_rss_bytes"] = peak_child_rss_bytes()
    results["load_average"] = {"start": load_start, "end": load_average()}
    return results
