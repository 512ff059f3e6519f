"""Backprojection throughput: the batched float16 kernel against a one-sinogram reference.

Both kernels run in the same process on the same random filtered sinograms, so the ratio
is meaningful even on a shared machine; the absolute numbers are not (2 cores here, shared).
Throughput is counted in voxel updates, voxels x views x sinograms, per second, using the
median of ``repeats`` timed runs after one warm-up (which also builds the kernels). Times
are end to end: host interleave, upload, kernel and read-back.

Pixels outside the scanner's FOV circle are skipped (set to 0), so the count matters:
``*_gups`` counts every voxel of the image (the usual definition), ``*_gups_in_fov`` only
those really backprojected. By default the pixel size makes the image's inscribed circle
the FOV circle (78.5 % of the voxels inside); at the paper's 1 mm only 42 % of a 512^2
image lies inside the 187 mm FOV of Table 1 and the nominal figure is 2.4x the real work.

Run as ``python -m clrecon.bench.fbp [--nx 512 --views 984 --cols 900 --batch 16]``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time

import numpy as np

from clrecon.bench.reference_kernels import backproject_single
from clrecon.core.runtime import get_runtime
from clrecon.reconstruction.fbp import BATCH_LANES, FanBeamGeometry, backproject, interleave_batch


def _median_seconds(fn, repeats: int) -> float:
    fn()  # warm-up: kernel build, PoCL specialisation for the local size, first-touch buffers
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times))


def bench_backprojection(nx: int = 512, n_views: int = 984, n_cols: int = 900, batch: int = 16,
                         repeats: int = 3, *, voxel_mm: float | None = None, reference: bool = True,
                         seed: int = 0, filtered: np.ndarray | None = None,
                         reference_batch: int | None = None) -> dict:
    """Time :func:`clrecon.reconstruction.fbp.backproject` and the one-sinogram-per-work-item kernel.

    Parameters
    ----------
    nx : int
        Image size nx = ny (Table 1 of the paper: 512).
    n_views, n_cols : int
        Views over 2 pi and detector columns (Table 1: 984 x 900, 0.8 mm at SDD 1085.6).
    batch : int
        Sinograms backprojected together.
    repeats : int
        Timed runs per kernel; the median is reported.
    voxel_mm : float, optional
        Pixel size; default ``2 * fov_radius / nx`` (image inscribed in the FOV, 0.73 mm).
    reference : bool
        Also time the reference kernel (about 10x slower).
    filtered : ndarray, optional
        (batch, n_views, n_cols) filtered sinograms to backproject (default: standard normal
        noise from ``seed``); :mod:`clrecon.bench.backprojection` passes filtered phantom sinograms.
    reference_batch : int, optional
        Sinograms given to the reference kernel, the first ones (default: all ``batch``);
        its G updates/s count only those, and ``max_rel_diff`` compares only those.

    Returns
    -------
    dict
        ``device``, the sizes, ``fov_fraction`` (voxels inside the FOV), ``updates``
        (voxels x views x batch), ``batched_s``, ``batched_gups`` and
        ``batched_gups_in_fov`` (G updates/s), ``interleave_s`` (the host part of
        ``batched_s``), and with ``reference``: ``single_s``, ``single_gups``,
        ``single_gups_in_fov``, ``speedup`` and ``max_rel_diff`` =
        max |batched - single| / max |single|.
    """
    geom = FanBeamGeometry(sid_mm=595.0, sdd_mm=1085.6, n_cols=n_cols, col_pitch_mm=0.8,
                           n_views=n_views, nx=nx, ny=nx, voxel_mm=1.0)
    if voxel_mm is None:
        voxel_mm = 2.0 * geom.fov_radius_mm / nx
    geom = dataclasses.replace(geom, voxel_mm=float(voxel_mm))
    rt = get_runtime()
    if filtered is None:
        filtered = np.random.default_rng(seed).standard_normal((batch, n_views, n_cols), dtype=np.float32)
    elif filtered.shape != (batch, n_views, n_cols):
        raise ValueError(f"filtered: expected shape {(batch, n_views, n_cols)}, got {filtered.shape}")
    n_ref = batch if reference_batch is None else max(1, min(int(reference_batch), batch))
    updates = nx * nx * n_views * batch
    fov_fraction = float(geom.fov_mask().mean())
    res = {"device": rt.description, "nx": nx, "ny": nx, "voxel_mm": geom.voxel_mm, "n_views": n_views,
           "n_cols": n_cols, "batch": batch, "lanes": BATCH_LANES, "repeats": repeats,
           "fov_fraction": fov_fraction, "updates": updates}

    out = {}
    res["batched_s"] = _median_seconds(lambda: out.__setitem__("b", backproject(filtered, geom, runtime=rt)), repeats)
    res["batched_gups"] = updates / res["batched_s"] / 1e9
    res["batched_gups_in_fov"] = res["batched_gups"] * fov_fraction
    res["interleave_s"] = _median_seconds(lambda: interleave_batch(filtered), repeats)
    if reference:
        res["reference_batch"] = n_ref
        res["single_s"] = _median_seconds(
            lambda: out.__setitem__("s", backproject_single(filtered[:n_ref], geom, runtime=rt)), repeats)
        res["single_gups"] = nx * nx * n_views * n_ref / res["single_s"] / 1e9
        res["single_gups_in_fov"] = res["single_gups"] * fov_fraction
        res["speedup"] = res["batched_gups"] / res["single_gups"]
        res["max_rel_diff"] = float(np.max(np.abs(out["b"][:n_ref] - out["s"])) / np.max(np.abs(out["s"])))
    return res


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--nx", type=int, default=512)
    p.add_argument("--views", type=int, default=984)
    p.add_argument("--cols", type=int, default=900)
    p.add_argument("--batch", type=int, default=16)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--voxel-mm", type=float, default=None, help="default: image inscribed in the FOV")
    p.add_argument("--no-reference", action="store_true", help="skip the slow one-sinogram kernel")
    a = p.parse_args(argv)
    res = bench_backprojection(a.nx, a.views, a.cols, a.batch, a.repeats, voxel_mm=a.voxel_mm,
                               reference=not a.no_reference)
    print(json.dumps(res, indent=2))
    return res


if __name__ == "__main__":
    main()
