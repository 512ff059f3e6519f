"""The iterative operators' throughput: the voxel projector A beside its matched transpose A^T, and the
warp W_u beside W_u^T, on the same data in the same run.

Geometry: as the ``voxel-projector`` section (:mod:`clrecon.bench.voxel_projector`): the scene's
detector (default ``demo``: 240 x 16 cells), views spread over one rotation and +-40 mm of
source z, a cube of ``n_voxels``^3 voxels of ``voxel_mm`` (default 128^3 at 3 mm) holding the
analytic phantom voxelised; the projections backprojected are the phantom's own. The warp
uses a smooth random field of a few mm on the same cube.

Counts: a *ray* is one detector cell of one view; a *voxel update* is one of the four
bilinear weights of a Joseph sample (:func:`clrecon.simulation.voxel_projector.ray_samples`
counts the samples exactly), read by A and scattered by A^T (two 32-bit atomics of the
fixed-point sum for each); the warp's rates are output voxels/s. Times are wall-clock, end to
end (upload, kernel, read-back), after one untimed call (kernel build), median of ``repeats``.
The pair through the warp (``mcir``'s operator for one motion-state bin, pull warp: A W_u x and
W_u^T A^T y) is timed beside the static pair A x, A^T y. The dot-product mismatch
``|<A x, y> - <x, A^T y>| / <|A||x|, |y|>`` of the timed data is reported beside (x the phantom,
y its projection with the sign of a random field).

On a shared machine the figures depend on the other load: the 1-min load average is recorded.
Run as ``python -m clrecon.bench.iterative [--quick] [--repeats 3]`` or ``bench --only iterative``.
"""

from __future__ import annotations

import argparse
import json
import os

import numpy as np

from clrecon.bench.timing import fmt
from clrecon.bench.voxel_projector import _median_time
from clrecon.config.scene import load_scene
from clrecon.core.conventions import detector_coords, detector_frames
from clrecon.core.runtime import get_runtime
from clrecon.reconstruction.iterative.cone_backprojector import backproject_pair, backproject_volume
from clrecon.reconstruction.iterative.cone_gather import gather_backproject
from clrecon.reconstruction.iterative.warp import warp, warp_adjoint
from clrecon.simulation.phantoms.analytic import Phantom
from clrecon.simulation.voxel_projector import project_volume, ray_samples
from clrecon.simulation.voxelise import voxelise_objects


def bench_iterative(repeats: int = 3, quick: bool = False, *, scene="demo", n_voxels: int | None = None,
                    voxel_mm: float | None = None, n_views: int | None = None, rt=None) -> dict:
    """Time A, A^T, W_u and W_u^T on one geometry (see the module docstring).

    Returns a dict with ``rays``, ``samples``, the seconds and rates of each operator
    (``project_rays_per_s``, ``backproject_rays_per_s``, ``*_updates_per_s``, ``warp_voxels_per_s``,
    ``warp_adjoint_voxels_per_s``), ``backproject_over_project`` (time ratio), the dot-product
    mismatches ``dot_rel_projector`` and ``dot_rel_warp``, the sizes and ``load_average_1min``.
    """
    rt = rt or get_runtime()
    sc = load_scene("tiny" if quick and scene == "demo" else scene) if isinstance(scene, str) else scene
    s = sc.scanner
    n = int(n_voxels or (32 if quick else 128))
    h = float(voxel_mm or (10.0 if quick else 3.0))
    m = int(n_views or (2 if quick else 24))
    u, v = detector_coords(s.n_cols, s.col_pitch_mm), detector_coords(s.n_rows, s.row_pitch_mm)
    beta = np.linspace(0.0, 2 * np.pi, m, endpoint=False) + 0.3
    src, det, eu, ev = detector_frames(beta, np.linspace(-40.0, 40.0, m), s.sid_mm, s.sdd_mm)
    axis = (np.arange(n) - (n - 1) / 2.0) * h
    mu = voxelise_objects(Phantom(sc.phantom).objects(0.3, 0.5), axis, axis, axis, supersample=1, rt=rt)
    origin, spacing, shape = (axis[0],) * 3, (h,) * 3, mu.shape
    rng = np.random.default_rng(0)
    geo = (src, det, eu, ev, u, v)
    proj = project_volume(mu, origin, spacing, *geo, rt=rt)                        # builds the kernel
    y = (proj * np.sign(rng.normal(size=proj.shape))).astype(np.float32)
    backproject_volume(y, shape, origin, spacing, *geo, rt=rt)
    field = np.stack([np.sin(np.linspace(0, 3, n))[None, None, :] * np.ones(shape) * a for a in (3.0, -2.0, 4.0)])
    field = field.astype(np.float32)
    warp(mu, field, spacing, rt=rt)
    warp_adjoint(mu, field, spacing, rt=rt)
    load = os.getloadavg()[0]
    _, t_a = _median_time(lambda: project_volume(mu, origin, spacing, *geo, rt=rt), repeats)
    aty, t_at = _median_time(lambda: backproject_volume(y, shape, origin, spacing, *geo, rt=rt), repeats)
    wx, t_w = _median_time(lambda: warp(mu, field, spacing, rt=rt), repeats)
    g = rng.normal(size=shape).astype(np.float32)
    wtg, t_wt = _median_time(lambda: warp_adjoint(g, field, spacing, rt=rt), repeats)

    # the pair through the warp (mcir's operator for one motion-state bin: A W_v and W_v^T A^T, pull warp)
    _, t_aw = _median_time(lambda: project_volume(warp(mu, field, spacing, rt=rt), origin, spacing, *geo, rt=rt),
                           repeats)
    _, t_wat = _median_time(lambda: warp_adjoint(backproject_volume(y, shape, origin, spacing, *geo, rt=rt), field,
                                                 spacing, rt=rt), repeats)

    # SART's backprojections: the voxel-driven B beside A^T, and a subset's first visit (the update and the
    # column sums from one pass: the matched pair kernel, the gather's pair)
    mask = (rng.uniform(size=y.shape) > 0.1).astype(np.float32)
    gather_backproject(y, shape, origin, spacing, *geo, rt=rt, proj2=mask)            # builds the kernels
    backproject_pair(y, mask, shape, origin, spacing, *geo, rt=rt)
    by, t_b = _median_time(lambda: gather_backproject(y, shape, origin, spacing, *geo, rt=rt), repeats)
    _, t_b2 = _median_time(lambda: gather_backproject(y, shape, origin, spacing, *geo, rt=rt, proj2=mask), repeats)
    _, t_at2 = _median_time(lambda: backproject_pair(y, mask, shape, origin, spacing, *geo, rt=rt), repeats)
    b1 = gather_backproject(np.ones_like(y), shape, origin, spacing, *geo, rt=rt).astype(np.float64)
    a1 = backproject_volume(np.ones_like(y), shape, origin, spacing, *geo, rt=rt).astype(np.float64)
    seen = a1 > 0.5 * a1.max()

    rays = proj.size
    samples = int(ray_samples(origin, spacing, shape, *geo).sum())
    x64, y64 = mu.astype(np.float64), y.astype(np.float64)
    dot_a = abs(float(np.sum(proj * y64)) - float(np.sum(x64 * aty))) / float(np.sum(np.abs(proj * y64)))
    dot_w = abs(float(np.sum(wx * g.astype(np.float64))) - float(np.sum(x64 * wtg))) \
        / float(np.sum(np.abs(warp(np.abs(mu), field, spacing, rt=rt) * g.astype(np.float64))))
    return {
        "device": rt.description, "load_average_1min": load, "scene": sc.name, "detector": [s.n_rows, s.n_cols],
        "volume": [n, n, n], "voxel_mm": h, "views": m, "repeats": repeats, "rays": rays, "samples": samples,
        "project_seconds": t_a, "backproject_seconds": t_at,
        "project_rays_per_s": rays / t_a, "backproject_rays_per_s": rays / t_at,
        "project_updates_per_s": 4.0 * samples / t_a, "backproject_updates_per_s": 4.0 * samples / t_at,
        "backproject_over_project": t_at / t_a,
        "warp_seconds": t_w, "warp_adjoint_seconds": t_wt,
        "warp_voxels_per_s": mu.size / t_w, "warp_adjoint_voxels_per_s": mu.size / t_wt,
        "dot_rel_projector": dot_a, "dot_rel_warp": dot_w,
        "warped_pair_seconds": t_aw + t_wat, "static_pair_seconds": t_a + t_at,
        "warped_over_static_pair": (t_aw + t_wat) / (t_a + t_at),
        "gather_seconds": t_b, "gather_voxel_views_per_s": mu.size * m / t_b, "gather_over_backproject": t_b / t_at,
        "gather_pair_seconds": t_b2, "matched_pair_seconds": t_at2,
        "gather_ones_over_matched_ones_mean": float(np.mean(b1[seen] / a1[seen])),
        "gather_ones_over_matched_ones_std": float(np.std(b1[seen] / a1[seen])),
    }


def run(quick: bool = False, repeats: int = 3, log=print) -> dict:
    """The bench's ``iterative``: :func:`bench_iterative` on ``demo``."""
    return bench_iterative(repeats, quick)


def report_lines(r: dict) -> list[str]:
    """The section's lines of the bench report."""
    nz = r["volume"]
    return [
        "",
        f"2c. iterative operators {r['scene']} ({r['detector'][1]}x{r['detector'][0]} cells, {r['views']} views), "
        f"{nz[0]}^3 voxels of {r['voxel_mm']:g} mm, load {r['load_average_1min']:.2f}",
        f"   {'':26s} {'Mrays/s':>8s} {'Mupdates/s':>11s}  notes",
        f"   {'projector A (Joseph)':26s} {fmt(r['project_rays_per_s'] / 1e6):>8s} "
        f"{fmt(r['project_updates_per_s'] / 1e6):>11s}  {r['samples'] / r['rays']:.0f} samples/ray",
        f"   {'backprojector A^T':26s} {fmt(r['backproject_rays_per_s'] / 1e6):>8s} "
        f"{fmt(r['backproject_updates_per_s'] / 1e6):>11s}  {r['backproject_over_project']:.1f}x A's time; "
        f"dot test {r['dot_rel_projector']:.1e}",
        f"   {'warp W_u / W_u^T':26s} {'':>8s} {'':>11s}  {fmt(r['warp_voxels_per_s'] / 1e6)} / "
        f"{fmt(r['warp_adjoint_voxels_per_s'] / 1e6)} Mvoxels/s; dot test {r['dot_rel_warp']:.1e}",
        f"   {'pair A W + W^T A^T':26s} {'':>8s} {'':>11s}  {r['warped_pair_seconds']:.3f} s against the static "
        f"pair's {r['static_pair_seconds']:.3f} s: {r['warped_over_static_pair']:.2f}x",
        f"   {'voxel-driven B ~ A^T':26s} {'':>8s} {'':>11s}  {r['gather_seconds']:.3f} s: "
        f"{r['gather_over_backproject']:.2f}x A^T's time ({fmt(r['gather_voxel_views_per_s'] / 1e6)} M voxel-views/s); "
        f"B 1 / A^T 1 {r['gather_ones_over_matched_ones_mean']:.3f} +- {r['gather_ones_over_matched_ones_std']:.3f}",
        f"   {'first visit (update + C_s)':26s} {'':>8s} {'':>11s}  B pair {r['gather_pair_seconds']:.3f} s, "
        f"A^T pair {r['matched_pair_seconds']:.3f} s",
    ]


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m clrecon.bench.iterative", description=__doc__.split("\n")[0])
    p.add_argument("--quick", action="store_true")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--scene", default="demo")
    a = p.parse_args(argv)
    print(json.dumps(bench_iterative(a.repeats, a.quick, scene=a.scene), indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
