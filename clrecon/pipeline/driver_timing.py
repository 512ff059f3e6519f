"""The pipeline's kernel families timed on one OpenCL device: the workloads and the timing child.

Five kernel families do nearly all of a run's device work; each has one workload here, built on
the ``demo`` scene's detector and grid from seeded random inputs (the same inputs on every
driver):

========================  ==================================================  ===============
family                    function                                             unit of work
========================  ==================================================  ===============
``projector``             :func:`clrecon.simulation.projector.project`         one ray (R x C per projection)
``noise``                 :func:`clrecon.simulation.noise.add_noise`           one detector cell
``ssrb``                  :func:`clrecon.reconstruction.rebin.ssrb_rows`       one rebinned cell (C per row)
``interpolation``         :func:`~clrecon.reconstruction.interpolation.apply.apply_weights_interleaved`
                                                                               one output cell, K = 8 weights
``backprojection``        :func:`clrecon.reconstruction.fbp.backproject`       one voxel update
========================  ==================================================  ===============

:func:`workloads` builds them at three sizes: ``"timing"`` (about 20-60 ms a call on a 2-core
CPU: the driver choice of :mod:`clrecon.pipeline.driver_choice`), ``"quick"`` and ``"full"`` (the
sizes of ``python -m clrecon bench --drivers``, which uses the same workloads).

``python -m clrecon.pipeline.driver_timing PLATFORM_NAME DEVICE_INDEX`` is the child the driver
choice runs once per driver and machine: it probes the device as
:mod:`clrecon.core.driver_probe` does (a driver that aborts costs a verdict, not the run), and
prints its verdict as a JSON line ``{"ok", "reason"}``; when the probe passes it times every family
(one warm-up call, which builds the kernels, then the median of :data:`REPEATS` calls) and prints
a second line ``{"seconds_per_unit": {family: s}, "build_seconds", "seconds"}`` (or
``{"timing_error"}``): a timing that fails or dies leaves the probe's verdict standing.
"""

from __future__ import annotations

import dataclasses
import json
import sys
import time

import numpy as np

from clrecon.config.scene import load_scene
from clrecon.core import driver_probe
from clrecon.core.errors import first_error_line
from clrecon.core.runtime import Runtime
from clrecon.reconstruction import rebin
from clrecon.reconstruction.fbp import FanBeamGeometry, backproject
from clrecon.reconstruction.interpolation.apply import DeviceRows, apply_weights_interleaved
from clrecon.scan.table import projection_table
from clrecon.simulation import noise, projector

#: The kernel families, in the order they are timed and shown.
FAMILIES = ("projector", "noise", "ssrb", "interpolation", "backprojection")
#: Timed calls per family after the warm-up (the median is kept).
REPEATS = 3
#: Bump when a workload or its unit changes: cached timings of another version are timed again.
TIMING_VERSION = 1
#: Weights per interpolated output row in the interpolation workload (the 5D methods' neighbours).
K_WEIGHTS = 8

#: (projections, SSRB pairs, sinograms, views, grid, noise projections) per size. "timing" fills the
#: backprojector's 16 lanes and calls each kernel on batches like a run's, so that a call's fixed cost
#: weighs about as in a run; "quick" and "full" are bench --drivers' sizes.
_SIZES = {"timing": (32, 16384, 16, 246, 256, 16), "quick": (16, 4096, 4, 492, 256, 8),
          "full": (64, 32768, 16, 984, 512, 32)}


@dataclasses.dataclass(frozen=True)
class Workload:
    """One kernel family's call on a runtime: ``fn(rt)`` returns its output; ``units`` of work per call."""

    fn: object
    units: float
    unit: str
    #: what bench shows: ``units`` scaled to its display unit (e.g. G updates) and that unit's name
    display_units: float
    display_unit: str


def inputs(sc, size: str) -> dict:
    """Seeded inputs shared by every driver, for the ``demo``-like scene ``sc`` at ``size``."""
    n_proj, n_pairs, n_sino, V, nx, n_noise = _SIZES[size]
    rng = np.random.default_rng(0)
    pitch = sc.scan.pitches[-1]
    table = projection_table(sc, pitch)
    idx = np.linspace(0, len(table) - 1, n_proj).round().astype(np.int64)
    R, C = sc.scanner.n_rows, sc.scanner.n_cols
    proj = rng.uniform(0, 4, (n_proj, R, C)).astype(np.float32)
    slot = rng.integers(0, n_proj, n_pairs).astype(np.int32)
    half = 0.4 * R * sc.scanner.row_pitch_mm * sc.scanner.sid_mm / sc.scanner.sdd_mm
    dz = rng.uniform(-half, half, n_pairs).astype(np.float32)
    rows = rng.standard_normal((4096, C)).astype(np.float32)
    index = rng.integers(0, rows.shape[0], (n_sino * 4, V, K_WEIGHTS)).astype(np.int32)
    weight = rng.uniform(0, 1, (n_sino * 4, V, K_WEIGHTS)).astype(np.float32)
    weight /= weight.sum(-1, keepdims=True)
    geom = FanBeamGeometry(sid_mm=595.0, sdd_mm=1085.6, n_cols=900, col_pitch_mm=0.8, n_views=V, nx=nx, ny=nx,
                           voxel_mm=1.0)
    geom = dataclasses.replace(geom, voxel_mm=2.0 * geom.fov_radius_mm / nx)
    sino = rng.standard_normal((n_sino, V, geom.n_cols)).astype(np.float32)
    line_integrals = rng.uniform(0, 6, (n_noise, R, C)).astype(np.float32)
    return dict(table=table.take(idx), proj=proj, slot=slot, dz=dz, rows=rows, index=index, weight=weight,
                geom=geom, sino=sino, line_integrals=line_integrals, noise_idx=idx[:n_noise])


def workloads(sc, inp: dict) -> dict[str, Workload]:
    """family -> :class:`Workload` on the inputs of :func:`inputs`."""
    R, C = sc.scanner.n_rows, sc.scanner.n_cols
    g = inp["geom"]

    def interp(rt):
        dr = DeviceRows(inp["rows"], rt=rt)
        buf, n_groups = apply_weights_interleaved(dr, inp["index"], inp["weight"], rt=rt)
        out = rt.from_device(buf, (n_groups, inp["index"].shape[1], C + 2, 16))
        buf.release()
        dr.release()
        return out

    n_rows_out = int(np.prod(inp["index"].shape[:2]))
    updates = g.nx * g.ny * g.n_views * inp["sino"].shape[0]
    n_table = len(inp["table"])
    return {
        "projector": Workload(lambda rt: projector.project(sc, inp["table"], rt=rt), n_table * R * C, "ray",
                              n_table, "projections/s"),
        "noise": Workload(lambda rt: noise.add_noise(inp["line_integrals"], inp["noise_idx"], sc.noise, rt=rt),
                          inp["line_integrals"].size, "cell", inp["line_integrals"].size, "cells/s"),
        "ssrb": Workload(lambda rt: rebin.ssrb_rows(inp["proj"], inp["slot"], inp["dz"], sc.scanner, rt=rt),
                         inp["slot"].size * C, "cell", inp["slot"].size, "rows/s"),
        "interpolation": Workload(interp, n_rows_out * C, "cell", n_rows_out, "rows/s"),
        "backprojection": Workload(lambda rt: backproject(inp["sino"], g, runtime=rt), updates, "voxel update",
                                   updates / 1e9, "G updates/s"),
    }


def time_families(rt, size: str = "timing", repeats: int = REPEATS) -> dict:
    """Seconds per unit of work of every family on runtime ``rt`` (median of ``repeats`` after a warm-up).

    Returns ``{"seconds_per_unit": {family: s}, "build_seconds": s}``: the warm-up calls' seconds
    (kernel builds and first-touch buffers), reported apart from the timings."""
    sc = load_scene("demo")
    work = workloads(sc, inputs(sc, size))
    per_unit, build = {}, 0.0
    for name in FAMILIES:
        w = work[name]
        t0 = time.perf_counter()
        w.fn(rt)
        build += time.perf_counter() - t0
        times = []
        for _ in range(max(1, repeats)):
            t0 = time.perf_counter()
            w.fn(rt)
            times.append(time.perf_counter() - t0)
        per_unit[name] = float(np.median(times)) / w.units
    return {"seconds_per_unit": per_unit, "build_seconds": round(build, 3)}


def probe_and_time(platform_name: str, device_index: int) -> dict:
    """The probe's verdict on the device and, where it passes, :func:`time_families` on it; each printed as a
    JSON line as soon as it is known."""
    import pyopencl as cl

    t0 = time.perf_counter()
    plats = [p for p in cl.get_platforms() if p.name == platform_name]
    if not plats:
        verdict = {"ok": False, "reason": f"platform {platform_name!r} not found in the child process"}
        print(json.dumps(verdict), flush=True)
        return verdict
    dev = plats[0].get_devices()[device_index]
    verdict = driver_probe.probe_on(cl.Context([dev]), dev, force_fail=driver_probe.forced_failure(platform_name))
    print(json.dumps(verdict), flush=True)  # the verdict stands even if the timing dies after it
    if not verdict["ok"]:
        return verdict
    try:
        timing = time_families(Runtime(f"{platform_name}:{device_index}"))
    except Exception as e:  # noqa: BLE001 - a timing that fails leaves the driver working, untimed
        timing = {"timing_error": f"{type(e).__name__}: {first_error_line(e)}"}
    timing["seconds"] = round(time.perf_counter() - t0, 3)
    print(json.dumps(timing), flush=True)
    return {**verdict, **timing}


def main(argv=None) -> int:
    """Print the probe's verdict as one JSON line, then (where it passes) the timings as another."""
    argv = sys.argv[1:] if argv is None else argv
    try:
        probe_and_time(argv[0], int(argv[1]))
    except Exception as e:  # noqa: BLE001 - any failure of a driver is a verdict, reported in one line
        print(json.dumps({"ok": False, "reason": f"{type(e).__name__}: {first_error_line(e)}"}), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
