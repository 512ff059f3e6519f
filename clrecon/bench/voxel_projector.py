"""Voxel projector throughput: the OpenCL Joseph kernel beside its float64 NumPy reference and
the analytic projector on the same rays.

Geometry: a scene's detector and SID/SDD (default ``demo``: 240 x 16 cells) and views spread
over one rotation and +-40 mm of source z; the volume is the analytic phantom voxelised
(one sample per voxel; the content does not change the kernel's cost) on a cube of
``n_voxels``^3 voxels of ``voxel_mm`` (default 128^3 at 3 mm, the demo's in-plane grid).

Counts: a *ray* is one detector cell of one view; a *sample* is one plane of Joseph's method
(one bilinear interpolation, four voxel reads), counted exactly on the host
(:func:`clrecon.simulation.voxel_projector.ray_samples`). Times are wall-clock, end to end
(upload, kernel, read-back; the analytic projector includes its host-side records), the first
call (kernel build) is not timed, and the median of ``repeats`` runs is reported. The NumPy
reference runs on a subset of the rays (one view, a few rows) and is compared per ray.

On a shared machine the figures depend on the other load: the 1-min load average is printed
and returned. Run as ``python -m clrecon.bench.voxel_projector [--quick] [--repeats 3]``.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import time

import numpy as np

from clrecon.bench.timing import fmt
from clrecon.config.scene import load_scene
from clrecon.core.conventions import detector_coords, detector_frames
from clrecon.core.runtime import get_runtime
from clrecon.simulation.phantoms.analytic import Phantom
from clrecon.simulation.projector import project_views
from clrecon.simulation.voxel_projector import project_volume, project_volume_reference, ray_samples
from clrecon.simulation.voxelise import voxelise_objects


def _median_time(fn, repeats: int):
    """(last result, median wall seconds) of ``repeats`` calls."""
    times, out = [], None
    for _ in range(max(1, repeats)):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return out, statistics.median(times)


def bench_voxel_projector(repeats: int = 3, quick: bool = False, *, scene="demo", n_voxels: int | None = None,
                          voxel_mm: float | None = None, n_views: int | None = None, rt=None) -> dict:
    """Time :func:`clrecon.simulation.voxel_projector.project_volume` on a realistic geometry.

    Parameters
    ----------
    repeats : int
        Timed runs of each projector; the median is reported.
    quick : bool
        Small sizes (the ``tiny`` scene's 96 x 8 detector, 32^3 voxels of 10 mm, 2 views) for
        smoke tests; else the ``scene``'s detector, 128^3 voxels of 3 mm and 24 views.
    scene, n_voxels, voxel_mm, n_views
        Override the geometry (scene name or object; cube edge in voxels; voxel size in mm;
        number of views).

    Returns
    -------
    dict with ``rays_per_s``, ``samples_per_s`` (Joseph plane samples), ``voxel_reads_per_s``
    (4 per sample), the reference's ``reference_rays_per_s`` and ``speedup_vs_reference``, the
    analytic projector's ``analytic_rays_per_s`` on the same rays, the agreement figures
    ``max_abs_diff_vs_reference`` and ``rel_rms_vs_analytic`` (voxelisation error at this voxel
    size), the sizes behind them and ``load_average_1min``.
    """
    rt = rt or get_runtime()
    sc = load_scene("tiny" if quick and scene == "demo" else scene) if isinstance(scene, str) else scene
    s = sc.scanner
    n = int(n_voxels or (32 if quick else 128))
    h = float(voxel_mm or (10.0 if quick else 3.0))
    m = int(n_views or (2 if quick else 24))
    u, v = detector_coords(s.n_cols, s.col_pitch_mm), detector_coords(s.n_rows, s.row_pitch_mm)
    beta = np.linspace(0.0, 2 * np.pi, m, endpoint=False) + 0.3
    z_src = np.linspace(-40.0, 40.0, m)
    src, det, eu, ev = detector_frames(beta, z_src, s.sid_mm, s.sdd_mm)
    axis = (np.arange(n) - (n - 1) / 2.0) * h
    phantom = Phantom(sc.phantom)
    objs = phantom.objects(0.3, 0.5)
    mu = voxelise_objects(objs, axis, axis, axis, supersample=1, rt=rt)
    origin, spacing = (axis[0],) * 3, (h,) * 3
    objs_m = np.broadcast_to(objs, (m,) + objs.shape)

    run = lambda: project_volume(mu, origin, spacing, src, det, eu, ev, u, v, rt=rt)  # noqa: E731
    run_analytic = lambda: project_views(objs_m, src, det, eu, ev, u, v, rt=rt)  # noqa: E731
    rows = v[:: max(1, len(v) // 4)][:4]
    run_ref = lambda: project_volume_reference(mu, origin, spacing, src[:1], det[:1], eu[:1], ev[:1], u, rows)  # noqa: E731
    run()                                                          # kernel builds, not timed
    run_analytic()
    load = os.getloadavg()[0]
    print(f"bench_voxel_projector: load average (1 min) {load:.2f} on {os.cpu_count()} CPUs")
    proj, t_vox = _median_time(run, repeats)
    ana, t_ana = _median_time(run_analytic, repeats)
    ref, t_ref = _median_time(run_ref, max(1, min(repeats, 2)))

    rays = proj.size
    samples = int(ray_samples(origin, spacing, mu.shape, src, det, eu, ev, u, v).sum())
    rays_ref = ref.size
    sub = project_volume(mu, origin, spacing, src[:1], det[:1], eu[:1], ev[:1], u, rows, rt=rt)
    a64 = ana.astype(np.float64)
    res = {
        "device": rt.description,
        "load_average_1min": load,
        "scene": sc.name,
        "detector": [s.n_rows, s.n_cols],
        "volume": [n, n, n],
        "voxel_mm": h,
        "views": m,
        "repeats": repeats,
        "rays": rays,
        "samples": samples,
        "samples_per_ray": samples / rays,
        "seconds": t_vox,
        "rays_per_s": rays / t_vox,
        "samples_per_s": samples / t_vox,
        "voxel_reads_per_s": 4.0 * samples / t_vox,
        "reference_rays": rays_ref,
        "reference_seconds": t_ref,
        "reference_rays_per_s": rays_ref / t_ref,
        "analytic_seconds": t_ana,
        "analytic_rays_per_s": rays / t_ana,
        "max_abs_diff_vs_reference": float(np.abs(sub - ref).max()),
        "rel_rms_vs_analytic": float(np.sqrt(np.mean((proj - a64) ** 2) / max(np.mean(a64 ** 2), 1e-300))),
    }
    res["speedup_vs_reference"] = res["rays_per_s"] / res["reference_rays_per_s"]
    res["speed_vs_analytic"] = res["rays_per_s"] / res["analytic_rays_per_s"]
    return res


def run(quick: bool = False, repeats: int = 3, log=print) -> dict:
    """The bench's ``voxel-projector``: :func:`bench_voxel_projector` on ``demo``."""
    return bench_voxel_projector(repeats, quick)


def report_lines(vp: dict) -> list[str]:
    """The section's lines of the bench report."""
    out = [""]
    nz = vp["volume"]
    out.append(f"2b. voxel projector (Joseph) {vp['scene']} ({vp['detector'][1]}x{vp['detector'][0]} cells, "
               f"{vp['views']} views), {nz[0]}^3 voxels of {vp['voxel_mm']:g} mm, "
               f"load {vp['load_average_1min']:.2f}")
    out.append(f"   {'':22s} {'Mrays/s':>8s} {'Msamples/s':>11s}  notes")
    out.append(f"   {'OpenCL (clrecon)':22s} {fmt(vp['rays_per_s'] / 1e6):>8s} "
               f"{fmt(vp['samples_per_s'] / 1e6):>11s}  {vp['samples_per_ray']:.0f} samples/ray; "
               f"max abs diff vs reference {vp['max_abs_diff_vs_reference']:.1e}")
    out.append(f"   {'float64 NumPy (ref)':22s} {fmt(vp['reference_rays_per_s'] / 1e6, 3):>8s} {'':>11s}  "
               f"OpenCL {vp['speedup_vs_reference']:.0f}x")
    out.append(f"   {'analytic projector':22s} {fmt(vp['analytic_rays_per_s'] / 1e6):>8s} {'':>11s}  "
               f"voxel/analytic speed {vp['speed_vs_analytic']:.2f}; rel RMS vs analytic "
               f"{vp['rel_rms_vs_analytic']:.1%} (voxelisation at {vp['voxel_mm']:g} mm)")
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m clrecon.bench.voxel_projector", description=__doc__.split("\n")[0])
    p.add_argument("--quick", action="store_true")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--scene", default="demo")
    a = p.parse_args(argv)
    print(json.dumps(bench_voxel_projector(a.repeats, a.quick, scene=a.scene), indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
