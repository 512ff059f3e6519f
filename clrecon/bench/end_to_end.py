"""Bench section ``end-to-end``: :func:`clrecon.pipeline.run.run` on ``demo``.

Into a temporary folder with a fresh projection cache (``--quick``: the 4 middle slices): the
total seconds and the per-stage seconds of its ``results.json``.
"""

from __future__ import annotations

import resource
import tempfile
import time
from pathlib import Path

from clrecon.bench.timing import load1
from clrecon.config.scene import load_scene
from clrecon.pipeline.run import run as run_pipeline


def run(quick: bool = False, repeats: int = 3, log=print, *, scene="demo") -> dict:
    """:func:`clrecon.pipeline.run.run` on a scene (demo; quick: its 4 middle slices) into a temp dir with a
    fresh cache (one run: ``repeats`` and ``log`` unused)."""

    sc = load_scene(scene) if isinstance(scene, str) else scene
    slices = None
    if quick:
        nz = sc.recon.nz
        slices = (max(0, nz // 2 - 2), min(nz, nz // 2 + 2))
    load = load1()
    with tempfile.TemporaryDirectory(prefix="clrecon-bench-") as tmp:
        t0 = time.perf_counter()
        c0 = resource.getrusage(resource.RUSAGE_SELF)
        res = run_pipeline(sc, Path(tmp) / "run", slice_range=slices, cache_dir=Path(tmp) / "cache", progress=False,
                           log=lambda *a, **k: None)
        c1 = resource.getrusage(resource.RUSAGE_SELF)
        wall = time.perf_counter() - t0
    stages = {k: v.get("seconds", 0.0) for k, v in res["stages"].items() if v.get("ran", True)}
    return {"scene": sc.name, "slices": list(slices) if slices else [0, sc.recon.nz],
            "load_average_1min_before": load, "total_seconds": res["total_seconds"], "wall_s": wall,
            "cpu_s": (c1.ru_utime - c0.ru_utime) + (c1.ru_stime - c0.ru_stime), "stages": stages,
            "method_seconds": res.get("method_seconds", {})}


def report_lines(e2: dict) -> list[str]:
    """The section's lines of the bench report."""
    out = [""]
    st = e2["stages"]
    out.append(f"4. end to end: run {e2['scene']} slices {e2['slices'][0]}:{e2['slices'][1]}, fresh cache: "
               f"{e2['total_seconds']:.1f} s wall ({e2['cpu_s']:.0f} s CPU of this process), "
               f"load {e2['load_average_1min_before']}")
    items = sorted(st.items(), key=lambda kv: -kv[1])
    out.append("   " + ", ".join(f"{k} {v:.1f}" for k, v in items))
    return out
