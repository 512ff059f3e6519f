"""Peak memory of one Lucas-Kanade registration in a spawned process, as ``mc``'s pool runs it.

For each volume shape: a fresh pool of one spawned worker (``core.resources.spawned_pool``, the
run's), a warm-up registration of a small volume (imports scikit-image), then the worker's resident
set as its baseline (``/proc/<pid>/status`` VmRSS, its high-water mark reset through
``/proc/<pid>/clear_refs``), then one ``registration.register`` of the shape with the default
``FlowConfig`` and the worker's VmHWM after it, its VmRSS then (an idle worker of the pool), and
its VmHWM after a second registration in the same worker (the run's pool repeats them). Prints
per shape: voxels, the baseline, the peak above it and that per voxel, the idle resident set,
the second peak, the wall seconds; and ``resource.getrusage(RUSAGE_CHILDREN)`` (the largest
child's peak, baseline included) as a cross-check. The volumes are smoothed random texture in HU
and its copy shifted by a few voxels (the work does not depend on the content: fixed pyramid
levels and warps). One registration runs at a time. The pool's workers import the worktree's
``clrecon`` only with it on ``PYTHONPATH`` (the script's folder is ``sys.path[0]``). With
``--shrink``: the same for ``estimate.shrunk`` shrinking one of two fields (:func:`measure_shrink`;
``confidence.SHRINK_BYTES_PER_VOXEL``).

    PYTHONPATH=. nice -n 10 python benchmarks/studies/motion-model/registration_memory.py [--shrink] [--shape NZ NY NX ...]
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import time

import numpy as np
import scipy.ndimage

from clrecon.core.resources import spawned_pool
from clrecon.reconstruction.config import ReconConfig
from clrecon.reconstruction.motion import estimate, registration
from clrecon.reconstruction.motion import method as mcm
from clrecon.reconstruction.motion.model import FieldGrid

#: demo's registration grid at downsample 1 and 2, a paper-p010 slab's (8 slices) and 40 slices at both.
SHAPES = [(16, 64, 64), (16, 128, 128), (8, 512, 512), (40, 256, 256), (40, 512, 512)]


def _status(pid: int) -> dict[str, int]:
    """VmRSS and VmHWM of ``pid`` (bytes)."""
    out = {}
    with open(f"/proc/{pid}/status") as f:
        for line in f:
            k, _, v = line.partition(":")
            if k in ("VmRSS", "VmHWM"):
                out[k] = int(v.split()[0]) * 1024
    return out


def _pair(shape, rng):
    fixed = scipy.ndimage.gaussian_filter(rng.normal(0, 300, shape), 2.0).astype(np.float32) - 200
    moving = np.roll(fixed, (1, 3, -2), axis=(0, 1, 2))
    return fixed, moving


def measure(shape, spacing_mm=(0.98, 0.98, 1.0)) -> dict:
    rng = np.random.default_rng(0)
    fixed, moving = _pair(shape, rng)
    pool = spawned_pool(1)
    try:
        small = _pair((8, 32, 32), rng)
        pool.submit(registration.register, *small, spacing_mm).result()
        (pid,) = list(pool._processes)
        with open(f"/proc/{pid}/clear_refs", "w") as f:
            f.write("5")  # reset VmHWM to the current resident set
        base = _status(pid)["VmRSS"]
        t = time.perf_counter()
        pool.submit(registration.register, fixed, moving, spacing_mm).result()
        wall = time.perf_counter() - t
        peak, idle = _status(pid)["VmHWM"], _status(pid)["VmRSS"]
        pool.submit(registration.register, moving, fixed, spacing_mm).result()
        again = _status(pid)["VmHWM"]
    finally:
        pool.shutdown()
    n = int(np.prod(shape))
    return {"shape": list(shape), "voxels": n, "baseline_bytes": base, "peak_bytes": peak,
            "above_baseline_bytes": peak - base, "bytes_per_voxel": round((peak - base) / n, 1),
            "second_peak_bytes": again, "idle_bytes": idle, "wall_s": round(wall, 1)}


def _shrink(fields, images, grid, local=False):
    """``estimate.shrunk`` as ``method.register`` calls it (the default knobs' window), in the worker;
    ``local``: the beat step's (the local prior)."""
    estimate.shrunk(fields, images, 0, grid, mcm.shrink_of(ReconConfig().mc), local=local)


def measure_shrink(shape, n: int = 2, local: bool = False) -> dict:
    """The worker's peak above its baseline while ``estimate.shrunk`` shrinks ``n`` - 1 fields (the run's
    process does this after each step's registrations, ``knobs.shrink``): the copy of the ``n`` fields
    and one field's :func:`confidence.shrink_field`, with the moving image seen through it."""
    rng = np.random.default_rng(0)
    images = np.stack(_pair(shape, rng))[np.arange(n) % 2]
    fields = scipy.ndimage.gaussian_filter(rng.normal(0, 2, (n, 3) + shape), (0, 0, 1, 4, 4)).astype(np.float32)
    grid = FieldGrid(nx=shape[2], ny=shape[1], nz=shape[0], voxel_mm=0.98, z0_mm=0.0, dz_mm=1.0)
    pool = spawned_pool(1)
    try:
        small = (8, 32, 32)
        sg = FieldGrid(nx=32, ny=32, nz=8, voxel_mm=0.98, z0_mm=0.0, dz_mm=1.0)
        pool.submit(_shrink, fields[:, :, :8, :32, :32].copy(), images[:, :8, :32, :32].copy(), sg).result()
        (pid,) = list(pool._processes)
        with open(f"/proc/{pid}/clear_refs", "w") as f:
            f.write("5")
        base = _status(pid)["VmRSS"]
        t = time.perf_counter()
        pool.submit(_shrink, fields, images, grid, local).result()
        wall = time.perf_counter() - t
        peak = _status(pid)["VmHWM"]
    finally:
        pool.shutdown()
    vox = int(np.prod(shape))
    inputs = fields.nbytes + images.nbytes  # the call's arrays, unpickled in the worker
    return {"shrink_shape": list(shape), "fields": n, "voxels": vox, "baseline_bytes": base, "peak_bytes": peak,
            "above_baseline_less_inputs_bytes": peak - base - inputs,
            "bytes_per_voxel_less_inputs": round((peak - base - inputs) / vox, 1), "wall_s": round(wall, 1),
            "small": list(small), "local_prior": local}


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--shape", type=int, nargs=3, action="append", help="NZ NY NX (repeatable)")
    ap.add_argument("--shrink", action="store_true", help="measure estimate.shrunk instead of a registration")
    ap.add_argument("--local", action="store_true", help="with --shrink: the beat step's local prior")
    args = ap.parse_args()
    for shape in (args.shape or SHAPES):
        print(json.dumps(measure_shrink(tuple(shape), local=args.local) if args.shrink else measure(tuple(shape))), flush=True)
    print(json.dumps({"children_maxrss_bytes": resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss * 1024,
                      "load": os.getloadavg()}))


if __name__ == "__main__":
    main()
