"""Paper-scale throughput: each stage of the ``paper-p002`` job at the job's own sizes.

The smaller sections of :mod:`clrecon.bench.suite` time kernels; these time the stages the
way the job runs them, so that a figure can be multiplied by the job's counts and mean the
job's time. Each stands beside a reference timed in the same process on the same data
(the machine is shared: the ratio is what to trust), times are medians of ``repeats`` runs
after an untimed warm-up unless said otherwise, and the 1-min load average is recorded.

``paper-projector`` (:func:`bench_paper_projector`)
    512 projections of ``paper-p002`` (900 x 64 cells) spread evenly over the whole helical
    scan (every z, cardiac phase and breathing amplitude the scan sees), in the simulation's
    256-projection chunks: (a) the projector alone, one :func:`clrecon.simulation.projector.project`
    call per chunk; (b) end to end, :func:`clrecon.simulation.simulate.simulate` into a fresh
    projection store (table, store, projector, unit files, assembly) of as many projections in
    runs of 256 consecutive ones (as the simulation writes them), the runs spread over the scan.
    Reference: the same kernel without culling on a subset (every 16th of the set, one call),
    scaled per projection. Also the per-call fixed cost (a straight-line fit of one call's
    seconds against its projections), the first call at a new chunk size, and the old
    16-projection figure measured in the same run, to show why it was low.
``noise`` (:func:`bench_noise`)
    Cells/s of :func:`clrecon.simulation.noise.add_noise` (Philox4x64-10 per cell, Poisson +
    Gaussian, clamp, log) on a paper chunk of real line integrals (256 x 64 x 900). Reference:
    NumPy ``Generator(Philox(seed))`` (also Philox4x64-10, but one sequential stream) drawing
    ``poisson(I0 exp(-p))`` then ``normal(0, sigma_e)`` for the same cells, float64, the same
    clamp and log; plus the bitwise check against the float64 reference of our own streams
    (:func:`clrecon.simulation.noise.add_noise_reference`) on one projection.
``paper-fbp`` (:func:`bench_paper_fbp`)
    512^2 images from 984 views x 900 columns of real in-plane thorax sinograms, as
    :func:`clrecon.reconstruction.reconstruct.reconstruct` runs them: rows ramp-filtered in
    place (:func:`clrecon.reconstruction.fbp.filter_rows`), interleaved sinograms already on the
    device, one :func:`clrecon.reconstruction.fbp.backproject_interleaved` launch per 32 images.
    References: the one-sinogram-per-work-item kernel (from host sinograms) and a float64
    NumPy FFT filter (one row per FFT), each on a subset, scaled per image / per row.
``groundtruth`` (:func:`bench_groundtruth`)
    Slice-targets/s of :func:`clrecon.evaluation.groundtruth.groundtruth_volumes` (exact in-plane
    sinograms + FBP, HU) and :func:`~clrecon.evaluation.groundtruth.phantom_truth_volumes`
    (voxelisation, 2^3 samples per voxel) at 512^2, one target with all the job's 110 slices (the
    ground truth runs a target at a time; its FBP launches take 32 images, so a few slices
    would pay for 32 and misstate the job); one timed run after a warm-up (one slice, and the
    sinograms at the full size). References:
    one slice-target by the
    unculled projector + one-sinogram backprojector, and the float64 NumPy point sampler
    (:meth:`clrecon.simulation.phantoms.analytic.Phantom.mu_at`) on one slice at 1 sample/voxel.

Every section also gives the time it projects for the whole paper job (``projected_*``).
``--quick`` (:data:`SIZES`): 256 projections in one chunk, a 64-projection noise chunk, 32
images, 32 slices; about 85 s at load 4 on the 2-core machine (the default sizes: 152 s at load 3).
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

import numpy as np

from clrecon.bench import reference_kernels
from clrecon.bench.projector import bench_projector
from clrecon.bench.timing import load1, median_time
from clrecon.config.scene import load_scene
from clrecon.core.conventions import mu_to_hu, voxel_coords
from clrecon.core.runtime import get_runtime
from clrecon.evaluation import groundtruth
from clrecon.pipeline.variants import noise_variants
from clrecon.reconstruction import fbp, rebin, reconstruct
from clrecon.scan.table import projection_table
from clrecon.simulation import noise, projector, simulate

#: Projections in the paper scenes' scans (Table 1): the projected whole-scan times use these.
PAPER_SCANS = ("paper-p002", "paper-p010")


def _timed(fn) -> tuple:
    t0 = time.perf_counter()
    out = fn()
    return out, time.perf_counter() - t0


def _scene(scene):
    return load_scene(scene) if isinstance(scene, str) else scene


def spread_indices(n_total: int, n: int) -> np.ndarray:
    """``n`` projection indices spread evenly over ``[0, n_total)``, first and last included."""
    return np.unique(np.linspace(0, n_total - 1, max(1, min(n, n_total))).round().astype(np.int64))


def scan_projections(names=PAPER_SCANS) -> dict:
    """Projections of the first pitch of each scene (from its table: what the simulation would run)."""
    out = {}
    for name in names:
        sc = load_scene(name)
        out[name] = len(projection_table(sc, sc.scan.pitches[0]))
    return out


# ---------------------------------------------------------------------------------------
# projector
def bench_paper_projector(n_projections: int = 512, scene="paper-p002", *, chunk: int = 256,
                          reference_every: int = 16, repeats: int = 3, old_style: bool = True, rt=None) -> dict:
    """Projections/s of the simulation at paper scale (see the module docstring)."""
    sc = _scene(scene)
    rt = rt or get_runtime()
    pitch = sc.scan.pitches[0]
    table = projection_table(sc, pitch)
    n_total = len(table)
    idx = spread_indices(n_total, n_projections)
    chunks = [idx[i:i + chunk] for i in range(0, len(idx), chunk)]
    rays_per_proj = sc.scanner.n_rows * sc.scanner.n_cols
    load = load1()

    projector.project(sc, table.take(idx[:2]), rt=rt)      # kernel builds
    # the first call at the chunk size, then the same call again (warm)
    _, t_first = _timed(lambda: projector.project(sc, table.take(chunks[0]), rt=rt))
    _, t_again = _timed(lambda: projector.project(sc, table.take(chunks[0]), rt=rt))
    one = idx[len(idx) // 2:len(idx) // 2 + 1]
    # seconds of one warm call against its projections (medians): a straight line, fixed + slope * n
    fit_sizes = sorted({1, min(16, len(chunks[0])), len(chunks[0])})
    fit_s = [median_time(lambda k=k: projector.project(sc, table.take(chunks[0][:k]), rt=rt), 3)[0]
             for k in fit_sizes]
    per_proj_s, overhead_s = (float(v) for v in np.polyfit(fit_sizes, fit_s, 1)) if len(fit_sizes) > 1 \
        else (fit_s[0], 0.0)
    t_one = fit_s[0]

    box = {}

    def project_all():
        box["out"] = [projector.project(sc, table.take(c), rt=rt) for c in chunks]

    cpu0 = time.process_time()
    t_proj, all_proj = median_time(project_all, repeats, warmup=False)
    cpu_proj = (time.process_time() - cpu0) / max(1, repeats)
    culled = np.concatenate(box["out"])

    def simulate_once(which) -> float:
        needed = np.zeros(n_total, bool)
        needed[which] = True
        with tempfile.TemporaryDirectory(prefix="clrecon-bench-sim-") as tmp:
            t0 = time.perf_counter()
            store = simulate.simulate(sc, pitch, needed=needed, cache_dir=Path(tmp), chunk=chunk, progress=False)
            t = time.perf_counter() - t0
            store.close()
        return t

    # the simulation projects (and stores) runs of consecutive projections, chunk by chunk: as many
    # whole chunks as the spread set has projections, their starts spread evenly over the scan
    # (spread single projections would cost the store one HDF5 chunk write each, ~2x the real cost)
    n_blocks = max(1, len(idx) // chunk)
    starts = np.linspace(0, max(0, n_total - chunk), n_blocks).round().astype(np.int64)
    blocks = np.unique(np.concatenate([np.arange(s0, min(n_total, s0 + chunk)) for s0 in starts]))
    sim_times = [simulate_once(blocks) for _ in range(max(1, repeats))]
    t_sim = float(np.median(sim_times))
    # the same for one projection: the fixed cost of a simulation (table, store file, assembly)
    t_sim1 = float(np.median([simulate_once(one) for _ in range(max(1, repeats - 1))]))
    sim_per_proj = max(t_sim - t_sim1, 1e-9) / max(1, len(blocks) - 1)

    # reference: the unculled kernel on every reference_every-th projection of the set, one call
    ref_pos = np.arange(0, len(idx), max(1, reference_every))
    ref_table = table.take(idx[ref_pos])
    ref_out = {}
    t_ref, all_ref = median_time(
        lambda: ref_out.__setitem__("x", projector.project(sc, ref_table, rt=rt, cull=False)), max(1, repeats - 1))

    res = {
        "device": rt.description, "load_average_1min_before": load, "scene": sc.name, "pitch": pitch,
        "detector": [sc.scanner.n_rows, sc.scanner.n_cols], "projections": len(idx), "chunk": chunk,
        "chunks": len(chunks), "total_projections": n_total, "repeats": repeats,
        "projector_s": t_proj, "projector_all_s": all_proj, "projector_cpu_s": cpu_proj,
        "projector_projections_per_s": len(idx) / t_proj, "rays_per_s": len(idx) * rays_per_proj / t_proj,
        "simulate_projections": len(blocks), "simulate_blocks": [int(b) for b in starts],
        "simulate_s": t_sim, "simulate_all_s": [round(t, 4) for t in sim_times],
        "simulate_projections_per_s": len(blocks) / t_sim,
        "simulate_one_projection_s": t_sim1, "simulate_per_projection_s": sim_per_proj,
        "simulate_marginal_projections_per_s": 1.0 / sim_per_proj,
        "simulate_note": f"simulate() of {n_blocks} runs of {chunk} consecutive projections starting at "
                         "simulate_blocks, into a fresh store; simulate_one_projection_s: the same for one "
                         "projection (projection table, store file, one unit, assembly), the fixed cost of a run; "
                         "per projection: the rest / (n - 1)",
        "store_share_estimate": max(0.0, 1.0 - len(blocks) / (len(idx) / t_proj) / t_sim),
        "per_call": {"one_projection_s": t_one, "fixed_s": overhead_s, "per_projection_s": per_proj_s,
                     "fit_projections": fit_sizes, "fit_seconds": fit_s,
                     "first_call_at_chunk_size_s": t_first, "same_call_again_s": t_again,
                     "first_call_extra_s": t_first - t_again,
                     "note": "fixed_s and per_projection_s: least-squares line through the median seconds of warm "
                             "calls of fit_projections projections; first_call_extra_s: the first call at a launch "
                             "size this process has not run, minus the same call again: up to ~0.7 s where PoCL "
                             "builds a binary for a launch size not yet in its on-disk kernel cache, ~0 once cached"},
        "reference": {"what": "same kernel without culling (every ray visits every object), one call, on every "
                              f"{reference_every}th projection of the set, scaled per projection",
                      "projections": len(ref_pos), "seconds": t_ref, "all_seconds": all_ref,
                      "projections_per_s": len(ref_pos) / t_ref},
        "max_abs_diff_vs_reference": float(np.abs(culled[ref_pos] - ref_out["x"]).max()),
    }
    res["speedup_vs_reference"] = res["projector_projections_per_s"] / res["reference"]["projections_per_s"]
    scans = scan_projections() if sc.name in PAPER_SCANS else {sc.name: n_total}
    res["projected_whole_scan_s"] = {
        name: {"projections": n, "simulate_s": t_sim1 + (n - 1) * sim_per_proj,
               "projector_only_s": n / res["projector_projections_per_s"],
               "unculled_reference_s": n / res["reference"]["projections_per_s"]}
        for name, n in scans.items()}
    res["projected_note"] = ("at this scene's per-projection rate; paper-p010 has the same detector and phantom, "
                             "only the pitch (hence the count) differs")
    if old_style:
        old = bench_projector(16, sc, repeats=1, rt=rt)
        res["old_16_projection_figure"] = {
            "projections_per_s": old["projections_per_s"], "seconds": old["seconds"],
            "predicted_by_per_call_fit_s": overhead_s + 16 * per_proj_s,
            "what": "clrecon.bench.projector.bench_projector(16): one call of 16 projections, fastest of 1"}
    return res


# ---------------------------------------------------------------------------------------
# noise
def numpy_philox_noise(p: np.ndarray, cfg) -> np.ndarray:
    """Reference noise: NumPy ``Generator(Philox(seed))`` for all cells at once, float64.

    N = poisson(I0 exp(-p)) + normal(0, sigma_e); p_noisy = -log(max(N, 1) / I0), float32.
    One sequential stream (not keyed per projection and cell as ours), so the numbers differ
    and only the distributions agree.
    """
    gen = np.random.Generator(np.random.Philox(int(cfg.seed)))
    lam = float(cfg.i0_photons) * np.exp(-p.astype(np.float64))
    counts = gen.poisson(lam).astype(np.float64)
    if cfg.electronic_sigma > 0:
        counts += gen.normal(0.0, float(cfg.electronic_sigma), size=lam.shape)
    return (-np.log(np.maximum(counts, noise.N_FLOOR) / float(cfg.i0_photons))).astype(np.float32)


def bench_noise(n_projections: int = 256, scene="paper-p002", *, repeats: int = 3, check_projections: int = 1,
                rt=None) -> dict:
    """Cells/s of the Philox noise stage on a paper chunk (see the module docstring)."""
    sc = _scene(scene)
    rt = rt or get_runtime()
    cfg = sc.noise
    pitch = sc.scan.pitches[0]
    table = projection_table(sc, pitch)
    idx = spread_indices(len(table), n_projections)
    clean = projector.project(sc, table.take(idx), rt=rt)
    cells = clean.size
    load = load1()
    box = {}
    t_ours, all_ours = median_time(lambda: box.__setitem__("o", noise.add_noise(clean, idx, cfg, rt=rt)), repeats)
    t_np, all_np = median_time(lambda: box.__setitem__("n", numpy_philox_noise(clean, cfg)), max(1, repeats - 1),
                                warmup=False)
    k = max(1, min(check_projections, len(idx)))
    t_ref, _ = median_time(lambda: box.__setitem__("r", noise.add_noise_reference(clean[:k], idx[:k], cfg)), 1,
                            warmup=False)
    d_ours = (box["o"] - clean).astype(np.float64)
    d_np = (box["n"] - clean).astype(np.float64)
    per_proj = int(np.prod(clean.shape[1:]))
    res = {
        "device": rt.description, "load_average_1min_before": load, "scene": sc.name,
        "chunk_shape": list(clean.shape), "cells": cells, "i0_photons": cfg.i0_photons,
        "electronic_sigma": cfg.electronic_sigma, "repeats": repeats,
        "line_integral_range": [float(clean.min()), float(clean.max())],
        "seconds": t_ours, "all_seconds": all_ours, "cells_per_s": cells / t_ours,
        "reference": {"what": "NumPy Generator(Philox(seed)).poisson(I0 exp(-p)) + .normal(0, sigma_e) for the same "
                              "cells, float64, same clamp at 1 count and log; one sequential stream",
                      "seconds": t_np, "all_seconds": all_np, "cells_per_s": cells / t_np},
        "speedup_vs_reference": t_np / t_ours,
        "noise_mean_std": {"ours": [float(d_ours.mean()), float(d_ours.std())],
                           "numpy": [float(d_np.mean()), float(d_np.std())]},
        "own_reference": {"what": "add_noise_reference (float64 NumPy, our Philox streams step for step)",
                          "projections": k, "cells_per_s": k * per_proj / t_ref,
                          "max_abs_diff": float(np.abs(box["o"][:k] - box["r"]).max())},
    }
    scans = scan_projections() if sc.name in PAPER_SCANS else {sc.name: len(table)}
    res["projected_whole_scan_s"] = {name: {"projections": n, "cells": n * per_proj,
                                            "noise_s": n * per_proj / res["cells_per_s"],
                                            "numpy_reference_s": n * per_proj / res["reference"]["cells_per_s"]}
                                     for name, n in scans.items()}
    res["projected_note"] = ("every projection noised once, all rows (the noisy variant; a projection read by two "
                             "slabs is noised twice)")
    return res


# ---------------------------------------------------------------------------------------
# FBP
def _thorax_sinograms(sc, n: int, rt, n_slices: int = 8) -> np.ndarray:
    """(n, V, C) in-plane fan-beam sinograms of the phantom (``n_slices`` middle slices, repeated)."""
    cfg = groundtruth.GroundTruthConfig.from_scene(sc)
    nz = sc.recon.nz
    k = max(1, min(n_slices, n, nz))
    i0 = max(0, nz // 2 - k // 2)
    z = reconstruct.slice_positions(sc, (i0, i0 + k))
    sino = groundtruth.groundtruth_sinograms(cfg, cfg.source(), 0.4, 0.5, z, rt=rt)
    return np.ascontiguousarray(sino[np.arange(n) % len(z)])


def filter_rows_numpy(rows: np.ndarray, geom, window: str = "ram-lak") -> np.ndarray:
    """Float64 NumPy reference of :func:`clrecon.reconstruction.fbp.filter_rows`: one row per FFT."""
    n_pad = fbp.padded_length(geom.n_cols)
    resp = fbp.ramp_filter_response(geom, window, n_pad).astype(np.float64)
    w = rows.astype(np.float64) * fbp.cosine_weights(geom)
    return np.fft.ifft(np.fft.fft(w, n=n_pad, axis=1) * resp, axis=1).real[:, :geom.n_cols]


def full_job_images(sc) -> dict:
    """Images the reconstruction backprojects for the whole scene: slices x method targets x variants."""
    targets = reconstruct.Targets(tuple(sc.cardiac_targets), tuple(sc.resp_targets))
    per_method = {m: len(reconstruct.method_targets(m, targets)[0]) for m in sc.recon.methods}
    variants = noise_variants(sc)
    return {"slices": sc.recon.nz, "variants": len(variants), "targets_per_method": per_method,
            "images": sc.recon.nz * sum(per_method.values()) * len(variants)}


def bench_paper_fbp(scene="paper-p002", *, n_images: int = 64, reference_images: int = 2, repeats: int = 3,
                    rt=None) -> dict:
    """512^2 images/s of filter + interleaved backprojection as the reconstruction runs them."""
    sc = _scene(scene)
    rt = rt or get_runtime()
    geom = fbp.FanBeamGeometry.from_scene(sc)
    window = sc.recon.filter
    sino = _thorax_sinograms(sc, n_images, rt)
    B, V, C = sino.shape
    load = load1()
    rows = sino.reshape(-1, C).copy()

    def filt():
        work = rows.copy()
        t0 = time.perf_counter()
        fbp.filter_rows(work, geom, window, out=work)
        box["f"] = work
        return time.perf_counter() - t0

    box = {}
    filt()
    t_filter = float(np.median([filt() for _ in range(max(1, repeats))]))
    filtered = box["f"].reshape(B, V, C)
    step = fbp.groups_per_launch(geom) * fbp.BATCH_LANES
    bufs = []
    for b0 in range(0, B, step):
        group = fbp.interleave_batch(filtered[b0:b0 + step])
        bufs.append((rt.to_device(group), group.shape[0], min(step, B - b0)))

    def bp():
        box["img"] = np.concatenate([fbp.backproject_interleaved(buf, g, geom, runtime=rt)[:n] for buf, g, n in bufs])

    t_bp, all_bp = median_time(bp, repeats)
    for buf, _, _ in bufs:
        buf.release()
    n_ref = max(1, min(reference_images, B))
    t_single, all_single = median_time(
        lambda: box.__setitem__("s", reference_kernels.backproject_single(filtered[:n_ref], geom, runtime=rt)),
        max(1, repeats - 1))
    ref_rows = rows[:V]
    t_np, _ = median_time(lambda: box.__setitem__("nf", filter_rows_numpy(ref_rows, geom, window)), 1,
                           warmup=False)
    bp_per_img = t_bp / B
    filt_per_row = t_filter / (B * V)
    res = {
        "device": rt.description, "load_average_1min_before": load, "scene": sc.name,
        "image": [geom.ny, geom.nx], "voxel_mm": geom.voxel_mm, "views": V, "cols": C, "images": B,
        "images_per_launch": step, "repeats": repeats, "fov_fraction": float(geom.fov_mask().mean()),
        "data": "in-plane fan-beam sinograms of the phantom at (0.4, 0.5), middle slices, repeated",
        "filter_s": t_filter, "filter_rows_per_s": B * V / t_filter,
        "backproject_s": t_bp, "backproject_all_s": all_bp, "backproject_images_per_s": B / t_bp,
        "backproject_gups": geom.nx * geom.ny * V * B / t_bp / 1e9,
        "images_per_s_own_rows": 1.0 / (bp_per_img + V * filt_per_row),
        "reference": {"what": f"one-sinogram-per-work-item kernel on {n_ref} of the sinograms (from host), per image",
                      "images": n_ref, "seconds": t_single, "all_seconds": all_single,
                      "images_per_s": n_ref / t_single,
                      "max_rel_diff": float(np.abs(box["img"][:n_ref] - box["s"]).max() / np.abs(box["s"]).max())},
        "filter_reference": {"what": f"float64 NumPy FFT, one row per FFT, on {V} rows (one sinogram)",
                             "rows_per_s": V / t_np,
                             "max_rel_diff": float(np.abs(filtered[0] - box["nf"]).max() / np.abs(box["nf"]).max())},
    }
    res["speedup_vs_reference"] = res["backproject_images_per_s"] / res["reference"]["images_per_s"]
    res["filter_speedup_vs_reference"] = res["filter_rows_per_s"] / res["filter_reference"]["rows_per_s"]
    # the whole job: every image backprojected; every rebinned row filtered once per variant
    job = full_job_images(sc)
    table = projection_table(sc, sc.scan.pitches[0])
    nz = sc.recon.nz
    z = reconstruct.slice_positions(sc, (nz // 2, nz // 2 + 1))
    groups = rebin.candidate_groups(table, z, sc.scanner, reconstruct.object_radius_mm(sc))
    rows_job = job["slices"] * len(groups.row) * job["variants"]
    job.update({"rebinned_rows_upper_bound": rows_job,
                "rows_note": "candidate rows of the middle slice x slices x variants: every candidate used by "
                             "some method (an upper bound)",
                "backproject_s": job["images"] * bp_per_img, "filter_s": rows_job * filt_per_row,
                "reference_backproject_s": job["images"] * t_single / n_ref,
                "reference_filter_s": rows_job * t_np / V})
    job["fbp_s"] = job["backproject_s"] + job["filter_s"]
    job["reference_fbp_s"] = job["reference_backproject_s"] + job["reference_filter_s"]
    res["projected_full_job"] = job
    return res


# ---------------------------------------------------------------------------------------
# ground truth
def bench_groundtruth(scene="paper-p002", *, n_slices: int | None = None, cardiac=(0.4,), resp=(0.25,),
                      repeats: int = 2, rt=None) -> dict:
    """Slice-targets/s of the ground-truth CT and the phantom truth (see the module docstring).

    ``n_slices`` defaults to the scene's ``nz``: the ground truth goes one target at a time
    with all its slices (FBP launches of 32 images; 2 slices would pay for 32), so the
    figure means the job's only at the job's slices per target.
    """
    sc = _scene(scene)
    rt = rt or get_runtime()
    cfg = groundtruth.GroundTruthConfig.from_scene(sc)
    nz = sc.recon.nz
    n_slices = max(1, min(n_slices or nz, nz))
    i0 = max(0, nz // 2 - n_slices // 2)
    z = reconstruct.slice_positions(sc, (i0, i0 + n_slices))
    targets = reconstruct.Targets(tuple(cardiac), tuple(resp))
    n_st = n_slices * len(cardiac) * len(resp)
    load = load1()
    box = {}
    one = reconstruct.Targets(tuple(cardiac[:1]), tuple(resp[:1]))
    # warm-up: kernel builds on one slice, and the projector's launch at the full size
    list(groundtruth.groundtruth_volumes(cfg, z[:1], one, rt=rt))
    list(groundtruth.phantom_truth_volumes(cfg, z[:1], one, rt=rt))
    groundtruth.groundtruth_sinograms(cfg, cfg.source(), float(cardiac[0]), float(resp[0]), z, rt=rt)
    t_gt, all_gt = median_time(
        lambda: box.__setitem__("gt", list(groundtruth.groundtruth_volumes(cfg, z, targets, rt=rt))), repeats,
        warmup=False)
    t_pt, all_pt = median_time(
        lambda: box.__setitem__("pt", list(groundtruth.phantom_truth_volumes(cfg, z, targets, rt=rt))), repeats,
        warmup=False)
    phantom = cfg.source()
    c0, a0 = float(cardiac[0]), float(resp[0])
    t_sino, _ = median_time(lambda: groundtruth.groundtruth_sinograms(cfg, phantom, c0, a0, z, rt=rt), 1,
                             warmup=False)

    # reference CT of one slice-target: unculled projector + one-sinogram backprojector
    det, V, geom = cfg.detector, cfg.views, cfg.fbp
    beta = np.deg2rad(cfg.start_angle_deg) + 2 * np.pi * np.arange(V) / V
    src, centre, e_u, e_v = det.frames(beta, np.full(V, float(z[0])))
    objs = np.broadcast_to(phantom.objects(c0, a0), (V,) + phantom.objects(c0, a0).shape)

    def ref_ct():
        s = projector.project_views(objs, src, centre, e_u, e_v, det.u_mm(), np.zeros(1), rt=rt, cull=False)
        f = fbp.filter_sinograms(s.reshape(1, V, det.n_cols), geom, cfg.filter)
        box["ref"] = mu_to_hu(reference_kernels.backproject_single(f, geom, runtime=rt)[0], cfg.mu_water_per_mm)

    t_ref, _ = median_time(ref_ct, 1)
    mask = geom.fov_mask()
    gt0 = box["gt"][0][2][0]
    # reference phantom truth: float64 NumPy point samples at the voxel centres of one slice
    x = voxel_coords(geom.nx, geom.voxel_mm)
    y = voxel_coords(geom.ny, geom.voxel_mm)
    pts = np.stack(list(np.meshgrid(x, y, indexing="xy")) + [np.full((geom.ny, geom.nx), float(z[0]))], axis=-1)
    t_np, _ = median_time(lambda: box.__setitem__("np", phantom.mu_at(pts, c0, a0)), 1, warmup=False)
    ours1, t_vox1 = _timed(lambda: phantom.voxelise(c0, a0, x, y, z[:1], supersample=1, rt=rt))
    ours1, t_vox1 = _timed(lambda: phantom.voxelise(c0, a0, x, y, z[:1], supersample=1, rt=rt))
    differ = np.abs(ours1[0].astype(np.float64) - box["np"]) > 1e-6
    ss = cfg.supersample
    res = {
        "device": rt.description, "load_average_1min_before": load, "scene": sc.name,
        "image": [geom.ny, geom.nx], "views": V, "cols": det.n_cols, "slices": n_slices,
        "targets": len(cardiac) * len(resp), "slice_targets": n_st, "repeats": repeats,
        "groundtruth_s": t_gt, "groundtruth_all_s": all_gt, "groundtruth_slice_targets_per_s": n_st / t_gt,
        "sinograms_share": min(1.0, t_sino * len(cardiac) * len(resp) / t_gt),
        "phantom_truth_s": t_pt, "phantom_truth_all_s": all_pt, "phantom_truth_slice_targets_per_s": n_st / t_pt,
        "supersample": ss, "phantom_truth_samples_per_s": n_st * geom.nx * geom.ny * ss ** 3 / t_pt,
        "reference": {"what": "one slice-target: the same projector without culling + filter + the "
                              "one-sinogram-per-work-item backprojector",
                      "seconds": t_ref, "slice_targets_per_s": 1.0 / t_ref,
                      "max_abs_diff_hu_in_fov": float(np.abs(gt0 - box["ref"])[mask].max())},
        "phantom_truth_reference": {
            "what": "Phantom.mu_at (float64 NumPy) at the voxel centres of one slice, 1 sample per voxel, "
                    "against voxelise(supersample=1) on the same points",
            "samples_per_s": geom.nx * geom.ny / t_np, "ours_samples_per_s_at_1": geom.nx * geom.ny / t_vox1,
            "voxels_differing": int(differ.sum()), "voxels": int(differ.size)},
    }
    res["speedup_vs_reference"] = res["groundtruth_slice_targets_per_s"] / res["reference"]["slice_targets_per_s"]
    res["phantom_truth_speedup_vs_reference"] = (res["phantom_truth_samples_per_s"]
                                                 / res["phantom_truth_reference"]["samples_per_s"])
    n_job = sc.recon.nz * len(sc.cardiac_targets) * len(sc.resp_targets)
    res["projected_full_job"] = {
        "slice_targets": n_job, "slices": sc.recon.nz, "targets": len(sc.cardiac_targets) * len(sc.resp_targets),
        "groundtruth_s": n_job / res["groundtruth_slice_targets_per_s"],
        "phantom_truth_s": n_job / res["phantom_truth_slice_targets_per_s"],
        "reference_groundtruth_s": n_job * t_ref,
        "reference_phantom_truth_s": (n_job * geom.nx * geom.ny * ss ** 3
                                      / res["phantom_truth_reference"]["samples_per_s"]),
    }
    return res


# ---------------------------------------------------------------------------------------
# sections of ``python -m clrecon bench``
SECTIONS = ("paper-projector", "noise", "paper-fbp", "groundtruth")

#: Keyword arguments of each section: (default, ``--quick``).
SIZES = {
    "paper-projector": (dict(n_projections=512, chunk=256), dict(n_projections=256, chunk=256)),
    "noise": (dict(n_projections=256), dict(n_projections=64)),
    "paper-fbp": (dict(n_images=64, reference_images=2), dict(n_images=32, reference_images=1)),
    "groundtruth": (dict(), dict(n_slices=32)),
}
_FUNCS = {"paper-projector": bench_paper_projector, "noise": bench_noise, "paper-fbp": bench_paper_fbp,
          "groundtruth": bench_groundtruth}


def run_section(name: str, quick: bool = False, repeats: int = 3, scene="paper-p002", **overrides) -> dict:
    """One paper-scale section at its default (or ``--quick``) sizes; ``overrides`` replace them."""
    kw = dict(SIZES[name][1 if quick else 0])
    kw.update(overrides)
    if name == "groundtruth":
        repeats = 1  # one timed run after a 1-slice warm-up: ~15-40 s per call at 110 slices
    return _FUNCS[name](scene=scene, repeats=1 if quick else repeats, **kw)


def _min(s: float) -> str:
    return f"{s / 60:.1f} min" if s < 3600 else f"{s / 3600:.1f} h"


def paper_projector_lines(pj: dict) -> list[str]:
    """Report lines of the ``paper-projector`` section (P1, the simulation at paper scale)."""
    out = []
    pc, ref = pj["per_call"], pj["reference"]
    out += ["", f"P1. simulation at paper scale: {pj['projections']} projections of {pj['scene']} "
                f"({pj['detector'][1]}x{pj['detector'][0]}) spread over the scan, {pj['chunks']} chunk(s) of "
                f"{pj['chunk']}; load {pj['load_average_1min_before']}",
            f"   {'':34s} {'proj/s':>8s}  whole scan: " + ", ".join(pj["projected_whole_scan_s"]),
            f"   {'simulate() end to end (store too)':34s} {pj['simulate_projections_per_s']:>8.1f}  "
            + ", ".join(_min(v["simulate_s"]) for v in pj["projected_whole_scan_s"].values())
            + f"  ({pj['simulate_projections']} in runs of {pj['chunk']}; marginal "
              f"{pj['simulate_marginal_projections_per_s']:.0f}/s, fixed {pj['simulate_one_projection_s']:.2f} s"
              f" per run; store ~{pj['store_share_estimate']:.0%})",
            f"   {'projector, one call per chunk':34s} {pj['projector_projections_per_s']:>8.1f}  "
            + ", ".join(_min(v["projector_only_s"]) for v in pj["projected_whole_scan_s"].values()),
            f"   {'unculled kernel (ref, subset)':34s} {ref['projections_per_s']:>8.1f}  "
            + ", ".join(_min(v["unculled_reference_s"]) for v in pj["projected_whole_scan_s"].values())
            + f"  ({ref['projections']} projections; culled {pj['speedup_vs_reference']:.1f}x; "
              f"max abs diff {pj['max_abs_diff_vs_reference']:.1e})",
            f"   per call: fixed {1e3 * pc['fixed_s']:.0f} ms + {1e3 * pc['per_projection_s']:.2f} ms/projection; "
            f"first call at a new size +{pc['first_call_extra_s']:.2f} s"]
    old = pj.get("old_16_projection_figure")
    if old:
        out.append(f"   old 16-projection figure, this run: {old['projections_per_s']:.0f} proj/s "
                   f"({old['seconds']:.3f} s; the per-call fit predicts {old['predicted_by_per_call_fit_s']:.3f} s,"
                   f" {pc['fixed_s'] / old['predicted_by_per_call_fit_s']:.0%} of it the fixed cost)")
    return out


def noise_lines(nz: dict) -> list[str]:
    """Report lines of the ``noise`` section (P2, the noise)."""
    ref, own = nz["reference"], nz["own_reference"]
    sh = nz["chunk_shape"]
    return ["", f"P2. noise {sh[0]} x {sh[1]} x {sh[2]} cells (I0 {nz['i0_photons']:g}, sigma_e "
                f"{nz['electronic_sigma']:g}); load {nz['load_average_1min_before']}",
            f"   {'':34s} {'M cells/s':>9s}  whole scan: " + ", ".join(nz["projected_whole_scan_s"]),
            f"   {'add_noise (OpenCL Philox)':34s} {nz['cells_per_s'] / 1e6:>9.1f}  "
            + ", ".join(_min(v["noise_s"]) for v in nz["projected_whole_scan_s"].values())
            + f"  (bitwise vs own float64 reference: max diff {own['max_abs_diff']:.1e})",
            f"   {'NumPy Generator(Philox) (ref)':34s} {ref['cells_per_s'] / 1e6:>9.1f}  "
            + ", ".join(_min(v["numpy_reference_s"]) for v in nz["projected_whole_scan_s"].values())
            + f"  (ours {nz['speedup_vs_reference']:.1f}x; noise std {nz['noise_mean_std']['ours'][1]:.4f} "
              f"vs {nz['noise_mean_std']['numpy'][1]:.4f})"]


def paper_fbp_lines(fb: dict) -> list[str]:
    """Report lines of the ``paper-fbp`` section (P3, the FBP at paper scale)."""
    job, ref = fb["projected_full_job"], fb["reference"]
    return ["", f"P3. FBP {fb['image'][1]}^2 from {fb['views']} views x {fb['cols']} columns, {fb['images']} "
                f"images, {fb['images_per_launch']} per launch; load {fb['load_average_1min_before']}",
            f"   backprojection {fb['backproject_images_per_s']:.1f} images/s ({fb['backproject_gups']:.1f} G "
            f"upd/s); filter {fb['filter_rows_per_s'] / 1e3:.0f} k rows/s; an image with its own "
            f"{fb['views']} rows {fb['images_per_s_own_rows']:.1f} images/s",
            f"   ref: one-sinogram kernel {ref['images_per_s']:.2f} images/s (ours "
            f"{fb['speedup_vs_reference']:.1f}x, max rel diff {ref['max_rel_diff']:.0e}); float64 NumPy filter "
            f"{fb['filter_reference']['rows_per_s'] / 1e3:.0f} k rows/s "
            f"(ours {fb['filter_speedup_vs_reference']:.1f}x)",
            f"   full job ({job['images']} images, <= {job['rebinned_rows_upper_bound'] / 1e6:.1f} M rows): "
            f"{_min(job['fbp_s'])} (backprojection {_min(job['backproject_s'])}, filter {_min(job['filter_s'])}); "
            f"with the references {_min(job['reference_fbp_s'])}"]


def groundtruth_lines(gt: dict) -> list[str]:
    """Report lines of the ``groundtruth`` section (P4, the ground truth)."""
    job, ref, pref = gt["projected_full_job"], gt["reference"], gt["phantom_truth_reference"]
    return ["", f"P4. ground truth {gt['image'][1]}^2, {gt['slices']} slices x {gt['targets']} target(s); "
                f"load {gt['load_average_1min_before']}",
            f"   ground-truth CT {gt['groundtruth_slice_targets_per_s']:.1f} slice-targets/s "
            f"(sinograms {gt['sinograms_share']:.0%} of it); ref (unculled + one-sinogram kernel, 1 slice) "
            f"{ref['slice_targets_per_s']:.2f} ({gt['speedup_vs_reference']:.1f}x, max diff "
            f"{ref['max_abs_diff_hu_in_fov']:.1e} HU)",
            f"   phantom truth {gt['phantom_truth_slice_targets_per_s']:.1f} slice-targets/s "
            f"({gt['phantom_truth_samples_per_s'] / 1e6:.0f} M samples/s at {gt['supersample']}^3); ref float64 "
            f"NumPy {pref['samples_per_s'] / 1e6:.2f} M samples/s ({gt['phantom_truth_speedup_vs_reference']:.0f}x;"
            f" {pref['voxels_differing']} of {pref['voxels']} voxels differ at 1 sample)",
            f"   full job ({job['slice_targets']} slice-targets): ground truth {_min(job['groundtruth_s'])}, "
            f"phantom truth {_min(job['phantom_truth_s'])}; with the references "
            f"{_min(job['reference_groundtruth_s'])} and {_min(job['reference_phantom_truth_s'])}"]


#: The report lines of each section, for the bench's registry (:data:`clrecon.bench.suite.REGISTRY`).
REPORT_LINES = {"paper-projector": paper_projector_lines, "noise": noise_lines, "paper-fbp": paper_fbp_lines,
                "groundtruth": groundtruth_lines}


def section_run(name: str):
    """The ``run(quick, repeats, log)`` of the paper section ``name`` (:func:`run_section` at the
    scene's default sizes), for the bench's registry."""
    def run(quick: bool = False, repeats: int = 3, log=print) -> dict:
        return run_section(name, quick, repeats)
    return run
