"""Bench section ``backprojection``: the batched backprojector against two references.

G voxel-updates/s of :func:`clrecon.reconstruction.fbp.backproject` (512^2 from 984 views x 900
columns, 64 sinograms per call, from host sinograms: interleave, upload, kernel, read back; the
reconstruction itself interleaves on the device and launches two groups of 16 at a time,
:func:`clrecon.reconstruction.fbp.groups_per_launch`) on ramp-filtered sinograms of analytic disk
phantoms; references: the one-sinogram-per-work-item reference kernel
(:func:`clrecon.bench.reference_kernels.backproject_single`) and the ASTRA Toolbox CPU fan-beam
backprojector (``line_fanflat``, optional: ``pip install 'clrecon[bench]'``), with the agreement
of the images after a least-squares scale. Goal: >= 4 G updates/s. ``--quick``: 256^2 from
492 views x 450 columns.
"""

from __future__ import annotations

import dataclasses
import time

import numpy as np

from clrecon.bench.fbp import bench_backprojection
from clrecon.bench.timing import fmt, load1, median_time
from clrecon.reconstruction import fbp

#: Goal of the issue (the report marks it), G voxel updates/s.
GOAL_BACKPROJECTION_GUPS = 4.0
#: Sinograms per backprojection call in the benchmark (the former FBP batch of the reconstruction).
RECON_FBP_BATCH = 64


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


def run(quick: bool = False, repeats: int = 3, log=print, *, nx: int | None = None, n_views: int | None = None,
        n_cols: int | None = None, batch: int = RECON_FBP_BATCH, reference_batch: int = 4, astra: bool = True) -> dict:
    """Batched backprojection vs the one-sinogram kernel and ASTRA, on filtered disk phantoms (``log`` unused)."""

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


def report_lines(bp: dict) -> list[str]:
    """The section's lines of the bench report."""
    out = [""]
    out.append(f"1. backprojection {bp['nx']}^2 from {bp['n_views']} views x {bp['n_cols']} columns, "
               f"{bp['batch']} sinograms per call ({bp['fov_fraction']:.0%} of voxels in the FOV), "
               f"load {bp['load_average_1min_before']}")
    out.append(f"   {'kernel':34s} {'G upd/s':>8s} {'in FOV':>8s} {'s':>8s}  notes")
    goal = "goal >= 4: " + ("met" if bp["batched_gups"] >= GOAL_BACKPROJECTION_GUPS else "NOT met")
    out.append(f"   {'batched float16 (clrecon)':34s} {fmt(bp['batched_gups']):>8s} "
               f"{fmt(bp['batched_gups_in_fov']):>8s} {fmt(bp['batched_s'], 3):>8s}  {goal}")
    if "single_gups" in bp:
        out.append(f"   {'one sinogram / work-item (ref)':34s} {fmt(bp['single_gups']):>8s} "
                   f"{fmt(bp['single_gups_in_fov']):>8s} {fmt(bp['single_s'], 3):>8s}  "
                   f"{bp['reference_batch']} sinograms; "
                   f"batched {bp['speedup']:.1f}x; max rel diff {bp['max_rel_diff']:.1e}")
    a = bp.get("astra", {})
    if "gups" in a:
        ag = a["agreement"]
        out.append(f"   {'ASTRA ' + a['version'] + ' line_fanflat BP (CPU)':34s} {fmt(a['gups']):>8s} "
                   f"{fmt(a['gups'] * bp['fov_fraction']):>8s} {fmt(a['seconds'], 3):>8s}  1 sinogram; "
                   f"batched {a['speedup_ours_vs_astra']:.0f}x; after scale: "
                   f"rel RMS diff {ag['rel_rms_diff']:.1%}, "
                   f"corr {ag['correlation']:.4f}")
    else:
        out.append(f"   ASTRA: skipped: {a.get('skipped', a.get('error', '?'))}")
    return out
