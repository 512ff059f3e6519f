"""``python -m clrecon bench``: throughput figures, each beside a reference measured in the same run.

The machine may be shared (here: 2 CPU cores and other engineers' jobs), so an absolute
figure alone means little; every section therefore times a reference on the same data in
the same process, and the ratio is the number to trust. Times are medians of ``repeats``
runs after one untimed warm-up (kernel builds, PoCL specialisation, first-touch buffers),
unless a section says otherwise. The 1-minute load average is recorded before each section.

Sections (``--only`` picks some):

``backprojection``
    G voxel-updates/s of :func:`clrecon.reconstruction.fbp.backproject` (512^2 from 984 views x 900
    columns, 64 sinograms per call, from host sinograms: interleave, upload, kernel, read
    back; the reconstruction itself interleaves on the device and launches two groups of
    16 at a time, :func:`clrecon.reconstruction.fbp.groups_per_launch`)
    on ramp-filtered sinograms of analytic disk phantoms; references: the one-sinogram-per-
    work-item reference kernel (:func:`clrecon.bench.reference_kernels.backproject_single`) and the ASTRA Toolbox CPU
    fan-beam backprojector (``line_fanflat``, optional: ``pip install 'clrecon[bench]'``),
    with the agreement of the images after a least-squares scale. Goal: >= 4 G updates/s.
``projector``
    :func:`clrecon.bench.projector.bench_projector` on ``paper-p002`` (900 x 64 cells):
    rays/s, ray-object pairs/s, projections/s, the whole simulation's projected time (goal
    < 10 minutes) against the same kernel without culling.
``voxel-projector``
    :func:`clrecon.bench.voxel_projector.bench_voxel_projector`: rays/s and Joseph plane
    samples/s of the voxel projector (the path of ``[phantom] kind = "voxel"``) on the demo
    detector and a 128^3 volume (``--quick``: tiny, 32^3), against its float64 NumPy
    reference and the analytic projector on the same rays.
``interpolation``
    Output rows/s (one rebinned row per (slice, view, target)) through the neighbour search
    and weights (:func:`clrecon.reconstruction.interpolation.weights.batch_weights`) and the kernel that applies
    them (:func:`clrecon.reconstruction.interpolation.weights.apply_weights_interleaved`, rows uploaded once, as the
    reconstruction does), per method, on the demo scan; reference: the float64 NumPy
    ``apply_weights_reference`` on the same weights.
``end-to-end``
    :func:`clrecon.pipeline.run.run` on ``demo`` into a temporary folder with a fresh projection
    cache: total seconds and the per-stage seconds of its ``results.json``.
``memory``
    Peak resident memory of a child process that plans and reconstructs ONE slab of a few
    slices of ``paper-p002`` for one method and a few targets (the projections it needs are
    simulated first, in the same child, and are not counted: the peak is reset before the
    plan), with a byte model of the slab's big arrays that extrapolates to the full job.
``scaling``
    Plan and reconstruct seconds of demo-sized scenes against slices, targets and
    projections (via :meth:`clrecon.config.scene.Scene.replace`).
``measured``
    :func:`clrecon.bench.measured.bench_measured_section`: DICOM-CT-PD import views/s (header pass +
    pixel import into a fresh store) against reading the same files' bytes; goal >= 200 views/s.
``paper-projector``, ``noise``, ``paper-fbp``, ``groundtruth``
    The paper-p002 job's stages at the job's own sizes, each with the time it projects for
    the whole job (:mod:`clrecon.bench.paper`): simulation projections/s over 512 projections
    spread over the scan in the simulation's 256-projection chunks (projector alone and
    ``simulate`` end to end, against the unculled kernel on a subset; the per-call fixed cost
    that made the old 16-projection figure low), noise cells/s on a 256 x 64 x 900 chunk (against
    NumPy's ``Generator(Philox)``), FBP images/s (filter + interleaved backprojection, against
    the one-sinogram kernel and a float64 NumPy filter), ground-truth and phantom-truth
    slice-targets/s at 110 slices per target (against the unculled projector + one-sinogram
    kernel, and float64 NumPy point samples).
``truth_free`` (only when named): the cost of ``recon.truth_free`` against the reconstruction it
    accompanies (demo, 4 middle slices; :func:`bench_truth_free_section`).
``mc`` (only when named): :mod:`clrecon.bench.mc`, the cost of the ``mc`` method against the paper
    methods' reconstruction of the same ``demo`` run at pitch 0.10 (``--quick``: 4 slices), its MAE
    ratio, and one registration round one after the other against the run's process pool.
``drivers`` (only when named, or ``--drivers``): :mod:`clrecon.bench.drivers`, every CPU driver that passes
    the probe side by side (projector, SSRB, interpolation, backprojection, noise, the demo cold).
``tradeoff`` (only with ``--only tradeoff``: not in the default set, about 20 minutes)
    :func:`clrecon.bench.tradeoff.run_tradeoff`: per method, the knobs that trade seconds for
    error (local-linear neighbours, kappa, sigma; candidate turns; views; grid) swept on demo
    at pitch 0.02, small/large-FOV MAE against the method's seconds, each method's Pareto
    front; ``tradeoff.json`` and ``tradeoff.png`` in a kept temporary folder (the report says where).

The A/B benchmarks of the code's own levers and options, and the studies (levers, backprojector
options, detectors, Dask scaling, truth-free trust), live in a checkout's ``benchmarks/`` folder,
outside the wheel (:data:`MOVED`; ``python -m benchmarks.levers`` and so on).

``--json FILE`` writes every number and the machine (CPU model, cores, load averages,
OpenCL device). ``--quick`` shrinks every section (about a minute on an idle 2-core machine).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import platform
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from clrecon.bench import paper
from clrecon.bench.drivers import bench_drivers
from clrecon.bench.drivers import report_lines as drivers_report_lines
from clrecon.bench.fbp import bench_backprojection
from clrecon.bench.mc import bench_mc_section
from clrecon.bench.mc import report_lines as mc_report_lines
from clrecon.bench.measured import bench_measured_section
from clrecon.bench.measured import report_lines as measured_report_lines
from clrecon.bench.projector import bench_projector
from clrecon.bench.timing import load1, median_time
from clrecon.bench.tradeoff import format_table as tradeoff_table
from clrecon.bench.tradeoff import run_tradeoff
from clrecon.bench.voxel_projector import bench_voxel_projector
from clrecon.config.scene import load_scene
from clrecon.core import atomic, machine_speed
from clrecon.core.errors import ClreconError
from clrecon.core.runtime import get_runtime
from clrecon.core.versions import __version__
from clrecon.pipeline.run import run
from clrecon.pipeline.variants import noise_variants
from clrecon.reconstruction import fbp, rebin, reconstruct
from clrecon.reconstruction.interpolation import weights as interpolate
from clrecon.scan.table import projection_table
from clrecon.simulation import simulate

SECTIONS = ("backprojection", "projector", "voxel-projector", "interpolation", "end-to-end", "memory", "scaling",
            "measured")
#: Paper-scale sections (:mod:`clrecon.bench.paper`): the paper-p002 job's stages at the job's sizes.
SECTIONS = SECTIONS + paper.SECTIONS
#: Sections run only when ``--only`` names them (long).
EXTRA_SECTIONS = ("tradeoff", "truth_free", "drivers", "mc")
#: Former sections, now A/B benchmarks of a checkout's ``benchmarks/`` folder (not in the wheel).
MOVED = {"levers": "benchmarks.levers", "backprojector": "benchmarks.backprojector",
         "detectors": "benchmarks.detectors", "distributed": "benchmarks.dask_scaling",
         "truth_free_trust": "benchmarks.truth_free_trust"}

#: Goals of the issue (bench output marks them).
GOAL_BACKPROJECTION_GUPS = 4.0
GOAL_SIMULATION_S = 600.0
GOAL_PEAK_MEMORY_GIB = 8.0

#: Sinograms per backprojection call in the benchmark (the former FBP batch of the reconstruction).
RECON_FBP_BATCH = 64


# ---------------------------------------------------------------------------------------
# helpers
def machine() -> dict:
    """CPU model, core count, load averages, memory, OpenCL device and library versions."""
    cpu = platform.processor() or "unknown"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    mem_gib = None
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemTotal"):
                mem_gib = round(int(line.split()[1]) / 2 ** 20, 1)
    except OSError:
        pass
    import pyopencl


    return {"cpu_model": cpu, "logical_cores": os.cpu_count(), "memory_gib": mem_gib,
            "load_average": [round(x, 2) for x in os.getloadavg()], "device": get_runtime().description,
            "driver": get_runtime().driver,
            "platform": platform.platform(), "python": platform.python_version(), "numpy": np.__version__,
            "pyopencl": pyopencl.VERSION_TEXT, "clrecon": __version__}


# ---------------------------------------------------------------------------------------
# 1. backprojection
def disk_phantom_sinograms(geom, n: int, seed: int = 0, n_phantoms: int = 8) -> np.ndarray:
    """(n, V, C) float32 exact fan-beam line integrals of random disk phantoms in the FOV.

    ``n_phantoms`` phantoms (a water body disk, five random inserts of +-0.5..1 x water),
    each repeated with its views rolled (= the phantom rotated by a multiple of the view step).
    """
    rng = np.random.default_rng(seed)
    beta = geom.view_angles_rad()
    u = geom.col_coords_mm()
    R, D = geom.sid_mm, geom.sdd_mm
    cb, sb = np.cos(beta)[:, None], np.sin(beta)[:, None]
    sx, sy = R * cb, R * sb                                     # source
    px, py = (R - D) * cb - u * sb, (R - D) * sb + u * cb       # detector cell centre
    dx, dy = px - sx, py - sy
    norm = np.hypot(dx, dy)
    dx, dy = dx / norm, dy / norm
    rmax = 0.9 * geom.fov_radius_mm
    base = []
    mu_w = 0.0193
    for _ in range(max(1, min(n_phantoms, n))):
        disks = [(0.0, 0.0, rmax, mu_w)]
        for _ in range(5):
            r = rng.uniform(0.05, 0.25) * rmax
            rho = rng.uniform(0.0, rmax - r)
            phi = rng.uniform(0, 2 * np.pi)
            disks.append((rho * np.cos(phi), rho * np.sin(phi), r, rng.choice([-1, 1]) * rng.uniform(0.5, 1.0) * mu_w))
        sino = np.zeros((geom.n_views, geom.n_cols))
        for cx, cy, r, mu in disks:
            ox, oy = cx - sx, cy - sy
            t = ox * dx + oy * dy
            d2 = ox * ox + oy * oy - t * t
            sino += mu * 2.0 * np.sqrt(np.maximum(r * r - d2, 0.0))
        base.append(sino.astype(np.float32))
    out = np.empty((n, geom.n_views, geom.n_cols), np.float32)
    step = max(1, geom.n_views // max(1, -(-n // len(base))))
    for i in range(n):
        out[i] = np.roll(base[i % len(base)], (i // len(base)) * step, axis=0)
    return out


def _astra_backprojection(filtered0: np.ndarray, geom, repeats: int) -> dict:
    """Time ASTRA's CPU ``line_fanflat`` backprojection (``BP``) of one sinogram in our geometry."""
    try:
        import astra
    except ImportError:
        return {"skipped": "astra-toolbox is not installed (pip install 'clrecon[bench]' or astra-toolbox)"}
    b = geom.view_angles_rad()
    R, D, p = geom.sid_mm, geom.sdd_mm, geom.col_pitch_mm
    # fanflat_vec rows: source, detector centre, vector between neighbouring cells (our
    # conventions: source at R(cos b, sin b), columns along (-sin b, cos b)).
    vec = np.stack([R * np.cos(b), R * np.sin(b), (R - D) * np.cos(b), (R - D) * np.sin(b),
                    -p * np.sin(b), p * np.cos(b)], axis=1)
    hx, hy = 0.5 * geom.nx * geom.voxel_mm, 0.5 * geom.ny * geom.voxel_mm
    vol = astra.create_vol_geom(geom.ny, geom.nx, -hx, hx, -hy, hy)
    pg = astra.create_proj_geom("fanflat_vec", geom.n_cols, vec)
    pid = astra.create_projector("line_fanflat", pg, vol)
    sino_id = astra.data2d.create("-sino", pg, filtered0.astype(np.float32))
    vol_id = astra.data2d.create("-vol", vol, 0.0)
    cfg = astra.astra_dict("BP")
    cfg.update(ProjectorId=pid, ProjectionDataId=sino_id, ReconstructionDataId=vol_id)
    alg = astra.algorithm.create(cfg)
    cpu = []

    def once():
        astra.data2d.store(vol_id, 0.0)
        c0 = time.process_time()
        astra.algorithm.run(alg)
        cpu.append(time.process_time() - c0)

    try:
        sec, all_s = median_time(once, repeats)
        img = np.flipud(astra.data2d.get(vol_id)).astype(np.float64)  # ASTRA's row 0 is the largest y
    finally:
        astra.algorithm.delete(alg)
        astra.data2d.delete([sino_id, vol_id])
        astra.projector.delete(pid)
    updates = geom.nx * geom.ny * geom.n_views
    return {"version": astra.__version__, "projector": "line_fanflat (fanflat_vec), BP, CPU", "seconds": sec,
            "all_seconds": all_s, "cpu_seconds": float(np.median(cpu)), "gups": updates / sec / 1e9,
            "image": img}


def _agreement(ours: np.ndarray, other: np.ndarray, mask: np.ndarray) -> dict:
    """Least-squares scale s (ours ~ s * other) and the agreement after it, inside ``mask``."""
    o = ours[mask].astype(np.float64)
    a = other[mask].astype(np.float64)
    s = float(a @ o / (a @ a)) if np.any(a) else float("nan")
    return {"scale": s, "rel_rms_diff": float(np.linalg.norm(o - s * a) / np.linalg.norm(o)),
            "correlation": float(np.corrcoef(o, a)[0, 1])}


def bench_backprojection_section(quick: bool = False, repeats: int = 3, *, nx: int | None = None,
                                 n_views: int | None = None, n_cols: int | None = None, batch: int = RECON_FBP_BATCH,
                                 reference_batch: int = 4, astra: bool = True) -> dict:
    """Batched backprojection vs the one-sinogram kernel and ASTRA, on filtered disk phantoms."""

    nx = nx or (256 if quick else 512)
    n_views = n_views or (492 if quick else 984)
    n_cols = n_cols or (450 if quick else 900)
    geom = fbp.FanBeamGeometry(sid_mm=595.0, sdd_mm=1085.6, n_cols=n_cols, col_pitch_mm=0.8,
                               n_views=n_views, nx=nx, ny=nx, voxel_mm=1.0)
    geom = dataclasses.replace(geom, voxel_mm=2.0 * geom.fov_radius_mm / nx)  # image inscribed in the FOV
    load = load1()
    sino = disk_phantom_sinograms(geom, batch)
    filtered = fbp.filter_sinograms(sino, geom)
    res = bench_backprojection(nx, n_views, n_cols, batch, repeats, voxel_mm=geom.voxel_mm,
                               filtered=filtered, reference_batch=reference_batch)
    res["load_average_1min_before"] = load
    res["data"] = "ramp-filtered exact sinograms of disk phantoms"
    res["col_pitch_mm"] = geom.col_pitch_mm
    if astra:
        a = _astra_backprojection(filtered[0], geom, max(1, min(repeats, 2)))
        if "image" in a:
            ours = fbp.backproject(filtered[:1], geom)[0]
            a["agreement"] = _agreement(ours, a.pop("image"), geom.fov_mask())
            a["agreement"]["note"] = ("ASTRA's BP is the adjoint of its line projector: each view weighs a pixel "
                                      "by ~1/U (ray density), ours by the FBP distance weight (R/U)^2, so the "
                                      "images agree to a few per cent after one scale, not to rounding")
            a["speedup_ours_vs_astra"] = res["batched_gups"] / a["gups"]
        res["astra"] = a
    else:
        res["astra"] = {"skipped": "not requested"}
    return res


# ---------------------------------------------------------------------------------------
# 2. projector
def bench_projector_section(quick: bool = False, repeats: int = 2, scene="paper-p002") -> dict:

    res = bench_projector(16 if quick else 96, scene, repeats=1 if quick else repeats)
    res["goal_total_s"] = GOAL_SIMULATION_S
    return res


# ---------------------------------------------------------------------------------------
# 3. interpolation
def bench_interpolation_section(quick: bool = False, repeats: int = 3, scene="demo", pitch: float | None = None,
                                n_slices: int | None = None, methods=None, reference_rows: int = 20000) -> dict:
    """Rows/s of neighbour search + weights + ``apply_weights`` per method (see module doc)."""

    sc = load_scene(scene) if isinstance(scene, str) else scene
    rt = get_runtime()
    pitch = pitch or sc.scan.pitches[0]
    n_slices = n_slices or (2 if quick else 4)
    nz = sc.recon.nz
    i0 = max(0, nz // 2 - n_slices // 2)
    slices_z = reconstruct.slice_positions(sc, (i0, min(nz, i0 + n_slices)))
    table = projection_table(sc, pitch)
    targets = reconstruct.Targets(tuple(sc.cardiac_targets), tuple(sc.resp_targets))
    load = load1()
    t_groups, _ = median_time(lambda: rebin.candidate_groups(table, slices_z, sc.scanner,
                                                              reconstruct.object_radius_mm(sc)), 1, warmup=False)
    groups = rebin.candidate_groups(table, slices_z, sc.scanner, reconstruct.object_radius_mm(sc))
    c = table.cardiac_phase[groups.row]
    a = table.resp_amplitude[groups.row]
    opts = reconstruct.weight_options(reconstruct.ReconstructionConfig.from_scene(sc), targets)
    rng = np.random.default_rng(0)
    rows = rng.standard_normal((len(groups.row), sc.scanner.n_cols)).astype(np.float32)
    t_up, _ = median_time(lambda: interpolate.DeviceRows(rows, rt=rt).release(), repeats)
    d_rows = interpolate.DeviceRows(rows, rt=rt)
    S, V = len(slices_z), sc.scanner.views_per_rotation
    res = {"scene": sc.name, "pitch": pitch, "slices": S, "views": V,
           "candidates": int(len(groups.row)), "n_cols": sc.scanner.n_cols, "repeats": repeats,
           "load_average_1min_before": load, "candidate_groups_s": t_groups, "upload_rows_s": t_up,
           "kernel": "apply_weights_interleaved16_cols8 (rows uploaded once; output in the backprojector's layout)",
           "methods": {}}
    for m in methods or sc.recon.methods:
        tg, _ = reconstruct.method_targets(m, targets)
        box = {}

        def weights(m=m, tg=tg, box=box):
            box["w"] = interpolate.batch_weights(m, c, a, groups.offsets, tg, rt=rt, dz=groups.dz_mm, **opts)

        t_w, _ = median_time(weights, max(1, repeats - 1), warmup=False)
        G, T, K = box["w"].index.shape
        # sinogram b = s * T + t, (B, V, K): as reconstruct hands them to the kernel
        idx = box["w"].index.reshape(S, V, T, K).transpose(0, 2, 1, 3).reshape(S * T, V, K)
        wgt = box["w"].weight.reshape(S, V, T, K).transpose(0, 2, 1, 3).reshape(S * T, V, K).astype(np.float32)

        def apply(idx=idx, wgt=wgt, box=box):
            buf, n_groups = interpolate.apply_weights_interleaved(d_rows, idx, wgt, rt=rt)
            box["out"] = rt.from_device(buf, (n_groups, V, sc.scanner.n_cols + 2, 16))
            buf.release()

        t_a, _ = median_time(apply, repeats)
        n_sino = max(1, min(S * T, reference_rows // V))  # whole sinograms, about reference_rows rows

        def apply_ref(idx=idx, wgt=wgt, n_sino=n_sino, K=K, box=box):
            box["ref"] = interpolate.apply_weights_reference(
                rows, idx[:n_sino].reshape(-1, K), wgt[:n_sino].reshape(-1, K))

        t_ref, _ = median_time(apply_ref, 1, warmup=False)
        out_rows = G * T
        ref = box["ref"].reshape(n_sino, V, -1)
        got = box["out"].transpose(0, 3, 1, 2).reshape(-1, V, sc.scanner.n_cols + 2)[:n_sino, :, 1:-1]
        diff = float(np.abs(got - ref).max() / max(np.abs(ref).max(), 1e-30))
        n_ref = n_sino * V
        res["methods"][m] = {
            "output_rows": out_rows, "k_slots": K, "weights_s": t_w, "apply_s": t_a,
            "rows_per_s": out_rows / (t_w + t_a), "weights_rows_per_s": out_rows / t_w,
            "apply_rows_per_s": out_rows / t_a,
            "reference_apply_rows_per_s": n_ref / t_ref, "apply_speedup": (out_rows / t_a) / (n_ref / t_ref),
            "max_rel_diff_vs_reference": diff}
    d_rows.release()
    return res


# ---------------------------------------------------------------------------------------
# 4. end to end and memory
def bench_end_to_end_section(quick: bool = False, scene="demo") -> dict:
    """``run`` on a scene (demo; quick: its 4 middle slices) into a temp dir with a fresh cache."""

    sc = load_scene(scene) if isinstance(scene, str) else scene
    slices = None
    if quick:
        nz = sc.recon.nz
        slices = (max(0, nz // 2 - 2), min(nz, nz // 2 + 2))
    load = load1()
    with tempfile.TemporaryDirectory(prefix="clrecon-bench-") as tmp:
        t0 = time.perf_counter()
        c0 = resource.getrusage(resource.RUSAGE_SELF)
        res = run(sc, Path(tmp) / "run", slice_range=slices, cache_dir=Path(tmp) / "cache", progress=False,
                  log=lambda *a, **k: None)
        c1 = resource.getrusage(resource.RUSAGE_SELF)
        wall = time.perf_counter() - t0
    stages = {k: v.get("seconds", 0.0) for k, v in res["stages"].items() if v.get("ran", True)}
    return {"scene": sc.name, "slices": list(slices) if slices else [0, sc.recon.nz],
            "load_average_1min_before": load, "total_seconds": res["total_seconds"], "wall_s": wall,
            "cpu_s": (c1.ru_utime - c0.ru_utime) + (c1.ru_stime - c0.ru_stime), "stages": stages,
            "method_seconds": res.get("method_seconds", {})}


def bench_truth_free_section(quick: bool = False, scene="demo") -> dict:
    """Cost of ``recon.truth_free`` against the reconstruction it accompanies: ``run`` on the scene's
    4 middle slices (quick: 2) with it on, the truth_free stage's seconds next to the
    reconstruction's (read + noise + rebin + interpolate + fbp), same run, same cache."""
    sc = load_scene(scene) if isinstance(scene, str) else scene
    nz = sc.recon.nz
    half = 1 if quick else 2
    slices = (max(0, nz // 2 - half), min(nz, nz // 2 + half))
    load = load1()
    with tempfile.TemporaryDirectory(prefix="clrecon-bench-tf-") as tmp:
        res = run(sc.replace(recon={"truth_free": True}), Path(tmp) / "run", slice_range=slices,
                  cache_dir=Path(tmp) / "cache", progress=False, report=False, log=lambda *a, **k: None)
    st = res["stages"]
    recon_s = sum(st[k]["seconds"] for k in ("read", "noise", "rebin", "interpolate", "fbp") if k in st)
    tf_s = st["truth_free"]["seconds"]
    per_pitch = {pk: e["seconds"] for pk, e in res["truth_free"].items()}
    return {"scene": sc.name, "slices": list(slices), "methods": list(res["request"]["methods"]),
            "variants": list(res["request"]["variants"]), "load_average_1min_before": load,
            "truth_free_s": tf_s, "reconstruction_s": recon_s, "ratio": tf_s / recon_s if recon_s else None,
            "per_pitch": per_pitch, "folds": {pk: e["folds"] for pk, e in res["truth_free"].items()}}


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
    of the one method being reconstructed (float32, twice: the batch and its reordered copy;
    each (variant, method) goes to ``on_slab`` as soon as it is done, so they do not grow
    with the number of methods).
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


def bench_memory_section(quick: bool = False, scene: str = "paper-p002", method: str = "nearest",
                         n_slices: int | None = None, cardiac=(0.4,), resp=None, cache_dir=None) -> dict:
    """Peak RSS of one slab of ``scene`` in a child process, and its extrapolation to the full job."""

    sc = load_scene(scene)  # a name or file: the child loads it again
    n_slices = n_slices or (1 if quick else 2)
    resp = resp or ((0.55,) if quick else (0.25, 0.75))
    load = load1()
    with tempfile.TemporaryDirectory(prefix="clrecon-bench-mem-") as tmp:
        code = ("import json, sys; from clrecon.bench.suite import slab_memory_child; "
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
                                                 sc.recon.ny, sc.recon.nx)
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


# ---------------------------------------------------------------------------------------
# 5. scaling
def bench_scaling_section(quick: bool = False, scene="demo", method: str = "local_linear") -> dict:
    """Plan / simulate / reconstruct seconds of demo-sized variants: slices, targets, projections."""

    base = load_scene(scene) if isinstance(scene, str) else scene
    rt = get_runtime()
    nz0, bins0, pitch0 = (2, 2, 0.10) if quick else (4, 5, 0.10)
    series = {
        "slices": [dict(recon={"nz": n}) for n in ((2, 4) if quick else (2, 4, 8))],
        "targets": [dict(recon={"resp_bins": b}) for b in ((2, 4) if quick else (2, 5, 10))],
        "projections": [dict(scan={"pitches": [p]}) for p in ((0.10, 0.05) if quick else (0.10, 0.05, 0.025))],
    }
    load = load1()
    rows = []
    with tempfile.TemporaryDirectory(prefix="clrecon-bench-scale-") as tmp:
        for axis, variants in series.items():
            for change in variants:
                recon = {"nz": nz0, "resp_bins": bins0, "methods": [method], **change.get("recon", {})}
                scan = {"pitches": [pitch0], **change.get("scan", {})}
                sc = base.replace(recon=recon, scan=scan, noise={"enabled": False})
                pitch = sc.scan.pitches[0]
                slices_z = reconstruct.slice_positions(sc)
                targets = reconstruct.Targets(tuple(sc.cardiac_targets), tuple(sc.resp_targets))
                table = projection_table(sc, pitch)
                p = reconstruct.plan(reconstruct.ReconstructionConfig.from_scene(sc), table, slices_z, targets,
                                     (method,))
                needed = p.needed_projections(len(table))
                t0 = time.perf_counter()
                store = simulate.simulate(sc, pitch, needed=needed, cache_dir=Path(tmp), progress=False)
                t_sim = time.perf_counter() - t0
                t0 = time.perf_counter()
                reconstruct.reconstruct(reconstruct.ReconstructionConfig.from_scene(sc), store, p,
                                        variants=("noise-free",), rt=rt)
                t_rec = time.perf_counter() - t0
                store.close() if hasattr(store, "close") else None
                proj, _ = p.needed_pairs()
                rows.append({"axis": axis, "slices": len(slices_z), "targets": len(targets.pairs), "pitch": pitch,
                             "projections_needed": int(needed.sum()), "rebinned_rows": int(len(proj)),
                             "plan_s": p.seconds, "simulate_s": t_sim, "reconstruct_s": t_rec,
                             "sinograms": len(slices_z) * len(targets.pairs)})
    return {"scene": base.name, "method": method, "variant": "noise-free", "load_average_1min_before": load,
            "rows": rows}


# ---------------------------------------------------------------------------------------
# report
def _f(x, nd=2) -> str:
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "-"
    if abs(x) >= 1e6:
        return f"{x:.3g}"
    return f"{x:.{nd}f}"


def format_report(res: dict) -> str:
    """Readable tables of a :func:`run_bench` result."""
    out = []
    m = res["machine"]
    out.append(f"machine: {m['cpu_model']}, {m['logical_cores']} logical cores, {m['memory_gib']} GiB; "
               f"load average {m['load_average']}; device {m['device']}")
    if m.get("speed"):
        out.append(f"machine over the bench: {machine_speed.describe(m['speed'])}")
    bp = res.get("backprojection")
    if bp:
        out.append("")
        out.append(f"1. backprojection {bp['nx']}^2 from {bp['n_views']} views x {bp['n_cols']} columns, "
                   f"{bp['batch']} sinograms per call ({bp['fov_fraction']:.0%} of voxels in the FOV), "
                   f"load {bp['load_average_1min_before']}")
        out.append(f"   {'kernel':34s} {'G upd/s':>8s} {'in FOV':>8s} {'s':>8s}  notes")
        goal = "goal >= 4: " + ("met" if bp["batched_gups"] >= GOAL_BACKPROJECTION_GUPS else "NOT met")
        out.append(f"   {'batched float16 (clrecon)':34s} {_f(bp['batched_gups']):>8s} "
                   f"{_f(bp['batched_gups_in_fov']):>8s} {_f(bp['batched_s'], 3):>8s}  {goal}")
        if "single_gups" in bp:
            out.append(f"   {'one sinogram / work-item (ref)':34s} {_f(bp['single_gups']):>8s} "
                       f"{_f(bp['single_gups_in_fov']):>8s} {_f(bp['single_s'], 3):>8s}  "
                       f"{bp['reference_batch']} sinograms; "
                       f"batched {bp['speedup']:.1f}x; max rel diff {bp['max_rel_diff']:.1e}")
        a = bp.get("astra", {})
        if "gups" in a:
            ag = a["agreement"]
            out.append(f"   {'ASTRA ' + a['version'] + ' line_fanflat BP (CPU)':34s} {_f(a['gups']):>8s} "
                       f"{_f(a['gups'] * bp['fov_fraction']):>8s} {_f(a['seconds'], 3):>8s}  1 sinogram; "
                       f"batched {a['speedup_ours_vs_astra']:.0f}x; after scale: "
                       f"rel RMS diff {ag['rel_rms_diff']:.1%}, "
                       f"corr {ag['correlation']:.4f}")
        else:
            out.append(f"   ASTRA: skipped: {a.get('skipped', a.get('error', '?'))}")
    pj = res.get("projector")
    if pj:
        ref = pj["reference"]
        out.append("")
        out.append(f"2. projector {pj['scene']} ({pj['detector'][1]}x{pj['detector'][0]} cells, "
                   f"{pj['n_objects']} objects), "
                   f"{pj['projections']} projections over the scan, load {pj['load_average_1min_before']:.2f}")
        out.append(f"   {'':22s} {'proj/s':>8s} {'Mrays/s':>8s} {'M ray.obj/s':>12s} {'whole scan':>12s}")
        ok = "met" if pj["projected_total_s"] < GOAL_SIMULATION_S else "NOT met"
        out.append(f"   {'culled (clrecon)':22s} {_f(pj['projections_per_s'], 1):>8s} {_f(pj['rays_per_s'] / 1e6):>8s} "
                   f"{_f(pj['intersections_per_s'] / 1e6, 1):>12s} {pj['projected_total_s'] / 60:>9.1f} min"
                   f"  goal < 10 min: {ok} (2 idle cores: {pj['projected_total_s_if_2_idle_cores'] / 60:.1f} min)")
        out.append(f"   {'unculled (ref)':22s} {_f(ref['projections'] / ref['seconds'], 1):>8s} "
                   f"{_f(ref['rays_per_s'] / 1e6):>8s} {_f(ref['intersections_per_s'] / 1e6, 1):>12s} "
                   f"{ref['projected_total_s'] / 60:>9.1f} min  culled {pj['speedup']:.1f}x; "
                   f"max abs diff {pj['max_abs_diff_vs_reference']:.1e}")
    vp = res.get("voxel-projector")
    if vp:
        out.append("")
        nz = vp["volume"]
        out.append(f"2b. voxel projector (Joseph) {vp['scene']} ({vp['detector'][1]}x{vp['detector'][0]} cells, "
                   f"{vp['views']} views), {nz[0]}^3 voxels of {vp['voxel_mm']:g} mm, "
                   f"load {vp['load_average_1min']:.2f}")
        out.append(f"   {'':22s} {'Mrays/s':>8s} {'Msamples/s':>11s}  notes")
        out.append(f"   {'OpenCL (clrecon)':22s} {_f(vp['rays_per_s'] / 1e6):>8s} "
                   f"{_f(vp['samples_per_s'] / 1e6):>11s}  {vp['samples_per_ray']:.0f} samples/ray; "
                   f"max abs diff vs reference {vp['max_abs_diff_vs_reference']:.1e}")
        out.append(f"   {'float64 NumPy (ref)':22s} {_f(vp['reference_rays_per_s'] / 1e6, 3):>8s} {'':>11s}  "
                   f"OpenCL {vp['speedup_vs_reference']:.0f}x")
        out.append(f"   {'analytic projector':22s} {_f(vp['analytic_rays_per_s'] / 1e6):>8s} {'':>11s}  "
                   f"voxel/analytic speed {vp['speed_vs_analytic']:.2f}; rel RMS vs analytic "
                   f"{vp['rel_rms_vs_analytic']:.1%} (voxelisation at {vp['voxel_mm']:g} mm)")
    ip = res.get("interpolation")
    if ip:
        out.append("")
        out.append(f"3. interpolation {ip['scene']} pitch {ip['pitch']}: {ip['slices']} slices x {ip['views']} views, "
                   f"{ip['candidates']} candidate rows of {ip['n_cols']}; load {ip['load_average_1min_before']}")
        out.append(f"   {'method':13s} {'rows':>8s} {'K':>3s} {'rows/s':>10s} {'weights/s':>10s} {'apply/s':>10s} "
                   f"{'ref apply/s':>11s} {'x ref':>6s} {'max rel diff':>12s}")
        for name, r in ip["methods"].items():
            out.append(f"   {name:13s} {r['output_rows']:>8d} {r['k_slots']:>3d} {r['rows_per_s']:>10.3g} "
                       f"{r['weights_rows_per_s']:>10.3g} {r['apply_rows_per_s']:>10.3g} "
                       f"{r['reference_apply_rows_per_s']:>11.3g} {r['apply_speedup']:>6.1f} "
                       f"{r['max_rel_diff_vs_reference']:>12.1e}")
    e2 = res.get("end-to-end")
    if e2:
        out.append("")
        st = e2["stages"]
        out.append(f"4. end to end: run {e2['scene']} slices {e2['slices'][0]}:{e2['slices'][1]}, fresh cache: "
                   f"{e2['total_seconds']:.1f} s wall ({e2['cpu_s']:.0f} s CPU of this process), "
                   f"load {e2['load_average_1min_before']}")
        items = sorted(st.items(), key=lambda kv: -kv[1])
        out.append("   " + ", ".join(f"{k} {v:.1f}" for k, v in items))
    mem = res.get("memory")
    if mem:
        out.append("")
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
    scl = res.get("scaling")
    if scl:
        out.append("")
        out.append(f"5. scaling ({scl['scene']} variants, {scl['method']}, noise-free; "
                   f"load {scl['load_average_1min_before']})")
        out.append(f"   {'axis':12s} {'slices':>6s} {'targets':>7s} {'pitch':>6s} {'proj':>6s} {'rows':>8s} "
                   f"{'plan s':>7s} {'sim s':>7s} {'recon s':>7s} {'ms/sino':>8s}")
        for r in scl["rows"]:
            out.append(f"   {r['axis']:12s} {r['slices']:>6d} {r['targets']:>7d} {r['pitch']:>6.3f} "
                       f"{r['projections_needed']:>6d} {r['rebinned_rows']:>8d} {r['plan_s']:>7.2f} "
                       f"{r['simulate_s']:>7.2f} {r['reconstruct_s']:>7.2f} "
                       f"{1e3 * r['reconstruct_s'] / r['sinograms']:>8.1f}")
    out.extend(paper.format_report(res))
    tfc = res.get("truth_free")
    if tfc:
        out.append(f"truth-free CV ({tfc['scene']}, slices {tfc['slices'][0]}:{tfc['slices'][1]}, "
                   f"{', '.join(tfc['methods'])}; {', '.join(tfc['variants'])}): {tfc['truth_free_s']:.1f} s "
                   f"against {tfc['reconstruction_s']:.1f} s of reconstruction (x{tfc['ratio']:.2f}), "
                   f"load {tfc['load_average_1min_before']}")
    tr = res.get("tradeoff")
    if tr:
        ld = tr["load_average_1min"]
        out.append("")
        out.append(f"6. error against run time: {tr['scene']} pitch {tr['pitch']:g}, slices "
                   f"{tr['slices'][0]}:{tr['slices'][1]}, {len(tr['points'])} points in {tr['sweep_seconds']:.0f} s "
                   f"(load {ld['min']:.2f}..{ld['max']:.2f}, median {ld['median']:.2f}); "
                   f"{tr['out_dir']}/tradeoff.png; * = on the method's Pareto front")
        out.extend("   " + line for line in tradeoff_table(tr).splitlines())
    if res.get("drivers"):
        out += ["", "drivers: each CPU driver that passes the probe, same inputs, same process (clrecon.bench.drivers)"]
        out.extend(drivers_report_lines(res["drivers"]))
    out.extend(measured_report_lines(res.get("measured")))
    out.extend(mc_report_lines(res.get("mc")))
    return "\n".join(out)


def run_bench(quick: bool = False, only=None, repeats: int | None = None, log=print) -> dict:
    """Run the selected sections; returns every number (see the module docstring)."""
    only = tuple(only or SECTIONS)
    moved = [s for s in only if s in MOVED]
    if moved:
        raise ClreconError(f"--only {moved[0]}: an A/B benchmark of the code itself, now in a checkout's benchmarks/ "
                           f"folder (not installed with the package): python -m {MOVED[moved[0]]} from the checkout")
    bad = [s for s in only if s not in SECTIONS + EXTRA_SECTIONS]
    if bad:
        raise ClreconError(f"--only {bad[0]!r}: sections are {', '.join(SECTIONS + EXTRA_SECTIONS)}")
    repeats = repeats or (1 if quick else 3)
    res = {"quick": quick, "repeats": repeats, "machine": machine()}
    machine0 = machine_speed.start()
    t_all = time.perf_counter()
    fns = {
        "backprojection": lambda: bench_backprojection_section(quick, repeats),
        "projector": lambda: bench_projector_section(quick, max(1, repeats - 1)),
        "voxel-projector": lambda: bench_voxel_projector(repeats, quick),
        "interpolation": lambda: bench_interpolation_section(quick, repeats),
        "end-to-end": lambda: bench_end_to_end_section(quick),
        "memory": lambda: bench_memory_section(quick),
        "scaling": lambda: bench_scaling_section(quick),
        "measured": lambda: bench_measured_section(quick, repeats),
        **{name: (lambda name=name: paper.run_section(name, quick, repeats)) for name in paper.SECTIONS},
        "tradeoff": lambda: run_tradeoff(quick, log=lambda *a, **k: log(*a, file=sys.stderr)),
        "truth_free": lambda: bench_truth_free_section(quick),
        "drivers": lambda: bench_drivers(quick, repeats),
        "mc": lambda: bench_mc_section(quick, repeats),
    }
    for name in SECTIONS + EXTRA_SECTIONS:
        if name in only:
            log(f"bench: {name} ...", file=sys.stderr)
            t0 = time.perf_counter()
            res[name] = fns[name]()
            res[name]["section_s"] = time.perf_counter() - t0
    res["bench_s"] = time.perf_counter() - t_all
    res["machine"]["load_average_after"] = [round(x, 2) for x in os.getloadavg()]
    res["machine"]["speed"] = machine0.finish()
    return res


def _json_default(o):
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(type(o))


def write_json(res: dict, path) -> None:
    atomic.write_json(path, res, indent=2)  # strict JSON, whole or not at all


def main(argv=None) -> int:  # pragma: no cover - the CLI's bench command is the entry point
    p = argparse.ArgumentParser(prog="python -m clrecon.bench.suite", description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true")
    p.add_argument("--json", metavar="FILE")
    p.add_argument("--only", help="comma list from " + ",".join(SECTIONS + EXTRA_SECTIONS))
    a = p.parse_args(argv)
    res = run_bench(a.quick, a.only.split(",") if a.only else None)
    print(format_report(res))
    if a.json:
        write_json(res, a.json)
    return 0


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
