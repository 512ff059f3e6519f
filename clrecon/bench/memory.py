"""Bench section ``memory``: peak resident memory of one slab, and its extrapolation to the job.

A child process plans and reconstructs ONE slab of a few slices of ``paper-p002`` for one method
and a few targets (the projections it needs are simulated first, in the same child, and are not
counted: the peak is reset before the plan), with a byte model of the slab's big arrays that
extrapolates to the full job. Goal: < 8 GiB.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from clrecon.bench.timing import load1
from clrecon.config.scene import load_scene
from clrecon.core.runtime import get_runtime
from clrecon.pipeline.variants import noise_variants
from clrecon.reconstruction import fbp, rebin, reconstruct
from clrecon.scan.table import projection_table
from clrecon.simulation import simulate

#: Goal of the issue (the report marks it): the full job's predicted peak, GiB.
GOAL_PEAK_MEMORY_GIB = 8.0


def _status_kib(field_name: str) -> int:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(field_name + ":"):
            return int(line.split()[1])
    return -1


def slab_memory_child(scene_name: str, n_slices: int, cardiac, resp, method: str, cache_dir: str) -> dict:
    """(In a child process) simulate what one slab needs, then plan + reconstruct it; peak RSS.

    The peak (VmHWM) is reset after simulating (``/proc/self/clear_refs``), so it covers
    planning and reconstructing the slab only; the full-process peak is reported as well.
    """

    sc = load_scene(scene_name)
    rt = get_runtime()
    pitch = sc.scan.pitches[0]
    nz = sc.recon.nz
    i0 = max(0, nz // 2 - n_slices // 2)
    slices_z = reconstruct.slice_positions(sc, (i0, i0 + n_slices))
    targets = reconstruct.Targets(tuple(cardiac), tuple(resp))
    table = projection_table(sc, pitch)
    p = reconstruct.plan(reconstruct.ReconstructionConfig.from_scene(sc), table, slices_z, targets, (method,))
    needed = p.needed_projections(len(table))
    t0 = time.perf_counter()
    store = simulate.simulate(sc, pitch, needed=needed, cache_dir=cache_dir, progress=False)
    sim_s = time.perf_counter() - t0
    variants = noise_variants(sc)
    hwm_process = _status_kib("VmHWM")
    try:
        Path("/proc/self/clear_refs").write_text("5")  # reset VmHWM to the current RSS
        reset = True
    except OSError:
        reset = False
    rss_before = _status_kib("VmRSS")
    t0 = time.perf_counter()
    p = reconstruct.plan(reconstruct.ReconstructionConfig.from_scene(sc), table, slices_z, targets, (method,))
    proj, _ = p.needed_pairs()
    vols = reconstruct.reconstruct(reconstruct.ReconstructionConfig.from_scene(sc), store, p, variants=variants,
                                   rt=rt, slab_size=n_slices)
    recon_s = time.perf_counter() - t0
    hwm = _status_kib("VmHWM")
    store.close() if hasattr(store, "close") else None
    groups = rebin.candidate_groups(table, slices_z, sc.scanner, reconstruct.object_radius_mm(sc))
    return {"scene": sc.name, "slices": n_slices, "targets": len(cardiac) * len(resp), "method": method,
            "variants": list(variants), "projections_simulated": int(needed.sum()), "simulate_s": sim_s,
            "reconstruct_s": recon_s, "rebinned_rows": int(len(proj)),
            "candidates_per_slice": float(len(groups.row) / n_slices),
            "volume_bytes": int(sum(v.nbytes for v in vols.values())),
            "rss_before_mib": rss_before / 1024, "peak_rss_mib": hwm / 1024, "peak_reset": reset,
            "process_peak_before_reset_mib": hwm_process / 1024}


def slab_memory_model(scene, slab_slices: int, n_targets: int, n_variants: int, rows_per_slice: float) -> dict:
    """Bytes of the big arrays of one slab (see :func:`clrecon.reconstruction.reconstruct.reconstruct`).

    The rebinned rows of every variant (host; each variant's rows move to the device, which
    on a CPU device is host memory too, when it is reconstructed), one backprojection launch
    (the interleaved sinograms, at most ``fbp.LAUNCH_BYTES``, and its images) and the images
    of the one method being reconstructed (float32, twice: the batch and the returned volume
    it is copied into, since the measuring child passes no ``on_slab``; in a run each (variant,
    method) goes to the writer as soon as it is done, so they do not grow with the number of
    methods).
    """

    sc, rc = scene.scanner, scene.recon
    C, V = sc.n_cols, sc.views_per_rotation
    rows = slab_slices * rows_per_slice * C * 4
    images = 2 * slab_slices * n_targets * rc.ny * rc.nx * 4
    geom = fbp.FanBeamGeometry.from_scene(scene)
    groups = min(fbp.groups_per_launch(geom), -(-slab_slices * n_targets // fbp.BATCH_LANES))
    launch = groups * fbp.BATCH_LANES * (V * (C + 2) * 4 + 2 * rc.ny * rc.nx * 4)
    total = rows * n_variants + images + launch
    return {"rebinned_rows_bytes_per_variant": rows, "images_bytes": images, "launch_bytes": launch,
            "total_bytes": total, "total_gib": total / 2 ** 30}


def run(quick: bool = False, repeats: int = 3, log=print, *, scene: str = "paper-p002", method: str = "nearest",
        n_slices: int | None = None, cardiac=(0.4,), resp=None, cache_dir=None) -> dict:
    """Peak RSS of one slab of ``scene`` in a child process, and its extrapolation to the full job (one child:
    ``repeats`` and ``log`` unused)."""

    sc = load_scene(scene)  # a name or file: the child loads it again
    n_slices = n_slices or (1 if quick else 2)
    resp = resp or ((0.55,) if quick else (0.25, 0.75))
    load = load1()
    with tempfile.TemporaryDirectory(prefix="clrecon-bench-mem-") as tmp:
        code = ("import json, sys; from clrecon.bench.memory import slab_memory_child; "
                "print('RESULT ' + json.dumps(slab_memory_child(*json.loads(sys.argv[1]))))")
        args = json.dumps([str(scene), n_slices, list(cardiac), list(resp), method,
                           str(cache_dir or Path(tmp) / "cache")])
        env = dict(os.environ, CLRECON_NO_PROGRESS="1")
        t0 = time.perf_counter()
        proc = subprocess.run([sys.executable, "-c", code, args], capture_output=True, text=True, env=env)
        wall = time.perf_counter() - t0
    if proc.returncode != 0:
        return {"error": proc.stderr.strip().splitlines()[-1] if proc.stderr.strip() else f"exit {proc.returncode}"}
    line = [x for x in proc.stdout.splitlines() if x.startswith("RESULT ")][-1]
    res = json.loads(line[len("RESULT "):])
    res["wall_s"] = wall
    res["load_average_1min_before"] = load
    # model, checked at the measured size, then at the full job's slab
    n_var = len(noise_variants(sc))
    small = slab_memory_model(sc, n_slices, res["targets"], n_var, res["rebinned_rows"] / n_slices)
    full_targets = len(sc.cardiac_targets) * len(sc.resp_targets)
    full_methods = len(sc.recon.methods)
    rows_per_slice = res["candidates_per_slice"]  # upper bound: every candidate used by some method
    per_slice = reconstruct.slab_bytes_per_slice(rows_per_slice, sc.scanner.n_cols, n_var, full_targets,
                                                 sc.recon.ny, sc.recon.nx,
                                                 volume_itemsize=np.dtype(sc.recon.volume_dtype).itemsize)
    slab = min(sc.recon.nz, reconstruct.slices_per_slab(per_slice))  # the run's rule (its plan not modelled)
    full = slab_memory_model(sc, slab, full_targets, n_var, rows_per_slice)
    base_mib = res["rss_before_mib"]
    res["model_small_mib"] = base_mib + small["total_bytes"] / 2 ** 20
    # extrapolation: the measured peak plus the growth of the modelled arrays (the rest --
    # kernel builds, PoCL's buffer pools, the read chunk, HDF5's cache -- does not grow with
    # slices, targets or methods)
    res["full_job"] = {"slab_slices": slab, "targets": full_targets, "methods": full_methods,
                       "rows_per_slice_upper_bound": rows_per_slice, **full,
                       "predicted_peak_gib": (res["peak_rss_mib"] * 2 ** 20 + full["total_bytes"]
                                              - small["total_bytes"]) / 2 ** 30,
                       "slab_size_rule": "reconstruct.slices_per_slab: rows of every variant + one method's "
                                         "images <= SLAB_BYTES (the plan not modelled)"}
    res["goal_gib"] = GOAL_PEAK_MEMORY_GIB
    return res


def report_lines(mem: dict) -> list[str]:
    """The section's lines of the bench report."""
    out = [""]
    if "error" in mem:
        out.append(f"   memory: child failed: {mem['error']}")
    else:
        fj = mem["full_job"]
        out.append(f"   peak memory, one slab of {mem['scene']}: {mem['slices']} slices x "
                   f"{mem['targets']} targets x "
                   f"{mem['method']} x {len(mem['variants'])} variants ({mem['rebinned_rows']} rebinned rows; "
                   f"{mem['projections_simulated']} projections simulated first in {mem['simulate_s']:.0f} s)")
        out.append(f"   measured peak RSS {mem['peak_rss_mib']:.0f} MiB (process before the slab "
                   f"{mem['rss_before_mib']:.0f} MiB; before + modelled arrays {mem['model_small_mib']:.0f} MiB: "
                   f"the rest is fixed: kernel builds, buffer pools, the read chunk)")
        ok = "met" if fj["predicted_peak_gib"] < GOAL_PEAK_MEMORY_GIB else "NOT met"
        out.append(f"   full job's slab ({fj['slab_slices']} slices x {fj['targets']} targets x "
                   f"{fj['methods']} methods, "
                   f"<= {fj['rows_per_slice_upper_bound']:.0f} rows/slice): measured + modelled growth "
                   f"{fj['predicted_peak_gib']:.1f} GiB "
                   f"(rows {fj['rebinned_rows_bytes_per_variant'] / 2 ** 30:.2f} GiB/variant, images "
                   f"{fj['images_bytes'] / 2 ** 30:.2f} GiB); goal < 8 GiB: {ok}")
    return out
