"""``python -m clrecon bench --drivers``: every CPU driver that passes the probe, side by side.

Each kernel family of the pipeline runs on the same inputs on each driver in one process (one
:class:`~clrecon.core.runtime.Runtime` per driver), the drivers taking turns within every repeat
so that a change of the machine's load between them falls on both; the figure is the median of
the repeats, and the ratio ``<first driver> / <second>`` of the medians is the number to trust.
Rows (sizes are those of the ``demo`` scene, ``--quick`` shrinks them):

``projector``
    :func:`clrecon.simulation.projector.project`: demo projections/s (64 projections per call).
``ssrb``
    :func:`clrecon.reconstruction.rebin.ssrb_rows`: rebinned rows/s (32 768 rows of 900 columns).
``interpolation``
    :func:`clrecon.reconstruction.interpolation.apply.apply_weights_interleaved`: output rows/s for
    K = 8 weights per row (the kernel that applies the 5DCT weights).
``backprojection``
    :func:`clrecon.reconstruction.fbp.backproject`: G voxel updates/s (16 sinograms, 984 views x 900
    columns onto 512^2; --quick 256^2).
``noise``
    :func:`clrecon.simulation.noise.add_noise`: noisy cells/s (a 32 x 64 x 900 chunk).
``demo cold``
    ``python -m clrecon run`` on ``demo`` in a child process per driver, with an empty projection
    cache, an empty PoCL kernel cache and no kept kernel binaries: seconds from start to end, kernel
    builds included (``--quick``: the ``tiny`` scene); beside the wall time, the child's CPU seconds
    (user + system), which the other jobs of a shared machine move less.

Beside the speed, each row gives the largest difference between the drivers' outputs relative to
the output's range: where and by how much their last bits differ.
"""

from __future__ import annotations

import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from clrecon.bench.timing import load1
from clrecon.config.scene import load_scene
from clrecon.core import drivers
from clrecon.core.runtime import Runtime
from clrecon.pipeline import driver_timing


def working_cpu_drivers() -> list[tuple[str, str]]:
    """(driver key, CLRECON_DEVICE spec) of every known CPU driver installed here that passes the probe."""
    import pyopencl as cl

    drivers.register_wheel_drivers()
    out = []
    for dev, idx in drivers.first_device_per_driver(cl.get_platforms()):
        drv = drivers.driver_of(dev.platform.name)
        if drivers.probe_device(dev, idx).ok:
            out.append((drv.key, drv.platform_match[0]))
    return out


def bench_kernels(keys_specs, quick: bool = False, repeats: int = 3) -> dict:
    """Median throughput of each kernel row on each driver (drivers alternating within a repeat)."""
    sc = load_scene("demo")
    work = driver_timing.workloads(sc, driver_timing.inputs(sc, "quick" if quick else "full"))
    rts = {key: Runtime(spec) for key, spec in keys_specs}
    out: dict = {}
    for name in ("projector", "ssrb", "interpolation", "backprojection", "noise"):
        fn, units, unit = work[name].fn, work[name].display_units, work[name].display_unit
        results, times, cpu = {}, {k: [] for k in rts}, {k: [] for k in rts}
        for key, rt in rts.items():  # warm-up: kernel builds, first-touch buffers
            results[key] = np.asarray(fn(rt), np.float64)
        for r in range(repeats):
            order = list(rts) if r % 2 == 0 else list(rts)[::-1]
            for key in order:
                t0, c0 = time.perf_counter(), time.process_time()
                fn(rts[key])
                times[key].append(time.perf_counter() - t0)
                cpu[key].append(time.process_time() - c0)
        med = {k: float(np.median(v)) for k, v in times.items()}
        row = {"unit": unit, "units_per_call": units, "load_average_1min": load1(),
               "seconds": med, "throughput": {k: units / s for k, s in med.items()},
               "cpu_seconds": {k: float(np.median(v)) for k, v in cpu.items()}}
        keys = list(rts)
        if len(keys) >= 2:
            a, b = results[keys[0]], results[keys[1]]
            scale = max(float(np.abs(b).max()), 1e-30)
            row["max_abs_difference_rel_to_range"] = float(np.abs(a - b).max() / scale)
            row["bit_identical"] = bool(np.array_equal(a, b))
            row[f"ratio_{keys[0]}_over_{keys[1]}"] = med[keys[1]] / med[keys[0]]
        out[name] = row
    return out


def bench_demo_cold(keys_specs, quick: bool = False, repeats: int = 1) -> dict:
    """Seconds of ``python -m clrecon run`` per driver with every cache empty (child processes, alternating)."""
    scene = "tiny" if quick else "demo"
    times: dict = {k: [] for k, _ in keys_specs}
    cpu: dict = {k: [] for k, _ in keys_specs}
    for r in range(repeats):
        order = keys_specs if r % 2 == 0 else keys_specs[::-1]
        for key, spec in order:
            with tempfile.TemporaryDirectory(prefix=f"clrecon-bench-{key}-") as tmp:
                env = dict(os.environ, CLRECON_DEVICE=spec, CLRECON_CACHE=str(Path(tmp) / "cache"),
                           POCL_CACHE_DIR=str(Path(tmp) / "pocl"))
                t0, c0 = time.perf_counter(), _children_cpu_s()
                cp = subprocess.run([sys.executable, "-m", "clrecon", "run", "--scene", scene, "--out",
                                     str(Path(tmp) / "run"), "--no-progress"], capture_output=True, text=True, env=env)
                dt = time.perf_counter() - t0
                cpu[key].append(_children_cpu_s() - c0)
                if cp.returncode != 0:
                    tail = (cp.stderr.strip().splitlines() or ["?"])[-1]
                    raise RuntimeError(f"bench --drivers: the {scene} run on {key} failed: {tail}")
                times[key].append(dt)
    med = {k: float(np.median(v)) for k, v in times.items()}
    med_cpu = {k: float(np.median(v)) for k, v in cpu.items()}
    row = {"scene": scene, "unit": "s", "seconds": med, "all_seconds": times, "cpu_seconds": med_cpu,
           "all_cpu_seconds": cpu, "load_average_1min": load1()}
    keys = [k for k, _ in keys_specs]
    if len(keys) >= 2:
        row[f"ratio_{keys[0]}_over_{keys[1]}"] = med[keys[1]] / med[keys[0]]
        row[f"cpu_ratio_{keys[0]}_over_{keys[1]}"] = med_cpu[keys[1]] / med_cpu[keys[0]]
    return row


def _children_cpu_s() -> float:
    """User + system CPU seconds of this process's finished children: less sensitive to the other jobs on
    a shared machine than the wall time (both are reported)."""
    ru = resource.getrusage(resource.RUSAGE_CHILDREN)
    return ru.ru_utime + ru.ru_stime


def bench_drivers(quick: bool = False, repeats: int = 3, demo: bool = True) -> dict:
    """The ``drivers`` section: kernel rows and the cold demo on every working CPU driver."""
    keys_specs = working_cpu_drivers()
    res = {"drivers": [k for k, _ in keys_specs], "cpu": drivers.cpu_line(), "repeats": repeats}
    if not keys_specs:
        res["skipped_because"] = "no CPU driver passes the probe"
        return res
    res["kernels"] = bench_kernels(keys_specs, quick, repeats)
    if demo:
        res["demo_cold"] = bench_demo_cold(keys_specs, quick, 1 if quick else max(1, repeats // 2))
    return res


def run(quick: bool = False, repeats: int = 3, log=print) -> dict:
    """The bench's ``drivers``: :func:`bench_drivers`, the cold demo included."""
    return bench_drivers(quick, repeats)


def report_lines(res: dict) -> list[str]:
    """The section as text lines for the bench report."""
    head = ["", "drivers: each CPU driver that passes the probe, same inputs, same process (clrecon.bench.drivers)"]
    keys = res.get("drivers", [])
    if not keys:
        return head + [f"  drivers: skipped ({res.get('skipped_because', 'none')})"]
    lines = head + [f"  drivers on {res['cpu']}: {', '.join(keys)} (median of {res['repeats']}, alternating)"]
    ratio_key = f"ratio_{keys[0]}_over_{keys[1]}" if len(keys) >= 2 else None
    for name, row in res.get("kernels", {}).items():
        figs = ", ".join(f"{k} {row['throughput'][k]:.4g}" for k in keys)
        extra = ""
        if ratio_key:
            diff = row["max_abs_difference_rel_to_range"]
            same = "bit-identical" if row["bit_identical"] else f"differ by {diff:.1e} of their range"
            extra = f"; {keys[0]}/{keys[1]} {row[ratio_key]:.2f}x; outputs {same}"
        lines.append(f"    {name:<15} {row['unit']}: {figs}{extra} (load {row['load_average_1min']:.2f})")
    if "demo_cold" in res:
        row = res["demo_cold"]
        figs = ", ".join(f"{k} {row['seconds'][k]:.1f} s ({row['cpu_seconds'][k]:.1f} CPU s)" for k in keys)
        extra = (f"; {keys[0]}/{keys[1]} speed {row[ratio_key]:.2f}x wall, "
                 f"{row['cpu_' + ratio_key]:.2f}x CPU" if ratio_key else "")
        lines.append(f"    {row['scene'] + ' cold':<15} {figs}{extra} (load {row['load_average_1min']:.2f})")
    return lines
