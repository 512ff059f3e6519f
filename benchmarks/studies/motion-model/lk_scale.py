"""Lucas-Kanade on OpenCL (``motion.lk``) against scikit-image's ``optical_flow_ilk``: time, memory, fields.

One pair per run: smoothed random texture in HU (std 2 voxels, about -200 +- 300 HU, band-limited)
and its copy moved by a known motion -- ``shift``: (dz, dy, dx) voxels, cubic, periodic; ``deform``:
a smooth field (a sinusoid of amplitude ``--amp`` voxels per axis over the volume) applied with
linear interpolation. Each backend registers it once in this process, one after the other (the
default ``FlowConfig`` / ``LKConfig``: radius 7, 10 warps): scikit-image through
``registration.register`` (as ``mc``'s breathing step runs it), the OpenCL port through
``lk.register_lk`` (its kernels built on a small pair first). Per backend: wall and CPU seconds
(all threads), and the peak resident set above the resident set just before the call
(``/proc/self/status`` VmHWM after ``/proc/self/clear_refs`` reset it to VmRSS), in bytes and per
voxel. Then the fields' difference (mm): max, RMS, 99th percentile and the share of voxels that
differ by more than 0.01 mm, over the whole volume; and each field's median in the inner part
against the known shift. Prints one JSON line; with ``--save`` the fields go to that .npz.

    PYTHONPATH=. nice -n 10 python benchmarks/studies/motion-model/lk_scale.py --shape 110 512 512 \
        --spacing 1 1 1 [--pair shift|deform] [--backends cl,skimage]
"""

from __future__ import annotations

import argparse
import json
import os
import time

import numpy as np
import scipy.ndimage

from clrecon.core.runtime import get_runtime
from clrecon.reconstruction.motion import lk, registration


def _status(key: str) -> int:
    with open("/proc/self/status") as fh:
        for line in fh:
            if line.startswith(key + ":"):
                return int(line.split()[1]) * 1024
    raise KeyError(key)


def measure(fn):
    """(result, wall s, cpu s, peak bytes above the resident set at the call)."""
    with open("/proc/self/clear_refs", "w") as fh:
        fh.write("5")
    base = _status("VmRSS")
    t0, c0 = time.perf_counter(), time.process_time()
    out = fn()
    return out, time.perf_counter() - t0, time.process_time() - c0, _status("VmHWM") - base


def make_pair(shape, kind: str, amp: float, seed: int = 0):
    rng = np.random.default_rng(seed)
    fixed = scipy.ndimage.gaussian_filter(rng.normal(0, 1, shape).astype(np.float32), 2.0, mode="wrap")
    fixed *= np.float32(300.0 / fixed.std())
    fixed -= np.float32(200.0)
    if kind == "shift":
        shift = (0.6, -1.3, 0.8)
        moving = scipy.ndimage.shift(fixed, shift, order=3, mode="grid-wrap")
        truth = np.array(shift)  # moving(x + s) = fixed(x): u = s voxels (z, y, x)
        return fixed, moving.astype(np.float32), truth
    k, j, i = np.meshgrid(*(np.arange(n, dtype=np.float32) for n in shape), indexing="ij", sparse=True)
    d = [amp * np.sin(2 * np.pi * (i / shape[2] + j / shape[1] + c / 3.0)) * np.cos(np.pi * k / shape[0])
         for c in range(3)]
    moving = scipy.ndimage.map_coordinates(fixed, [k - d[0], j - d[1], i - d[2]], order=1, mode="nearest")
    return fixed, moving.astype(np.float32), None


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--shape", type=int, nargs=3, default=[110, 512, 512])
    ap.add_argument("--spacing", type=float, nargs=3, default=[1.0, 1.0, 1.0], help="dx dy dz mm")
    ap.add_argument("--pair", choices=("shift", "deform"), default="shift")
    ap.add_argument("--amp", type=float, default=2.0, help="deform: amplitude (voxels)")
    ap.add_argument("--backends", default="cl,skimage")
    ap.add_argument("--save", default=None)
    args = ap.parse_args()
    shape, h = tuple(args.shape), tuple(args.spacing)
    fixed, moving, truth = make_pair(shape, args.pair, args.amp)
    rt = get_runtime()
    lk.register_lk(fixed[:4, :32, :32], moving[:4, :32, :32], h, runtime=rt)  # build the kernels
    n = fixed.size
    res = {"shape": shape, "spacing_mm": h, "pair": args.pair, "device": rt.description,
           "load_before": os.getloadavg()}
    fields = {}
    runs = {"cl": lambda: lk.register_lk(fixed, moving, h, runtime=rt),
            "skimage": lambda: registration.register(fixed, moving, h)}
    inner = (slice(None),) + tuple(slice(8, s - 8) if s > 24 else slice(None) for s in shape)
    for name in args.backends.split(","):
        u, wall, cpu, peak = measure(runs[name])
        fields[name] = u
        res[name] = {"seconds": round(wall, 2), "cpu_seconds": round(cpu, 1), "peak_above_gb": round(peak / 2**30, 3),
                     "bytes_per_voxel": round(peak / n, 1),
                     "median_u_mm": [round(float(np.median(u[c][inner[1:]])), 4) for c in range(3)]}
    if truth is not None:
        res["truth_mm"] = [truth[2] * h[0], truth[1] * h[1], truth[0] * h[2]]
    if len(fields) == 2:
        d = np.abs(fields["cl"] - fields["skimage"])
        res["diff_mm"] = {"max": float(d.max()), "rms": float(np.sqrt(np.mean(d.astype(np.float64) ** 2))),
                          "p99": float(np.percentile(d, 99)), "share_over_0.01": float(np.mean(d.max(0) > 0.01)),
                          "share_equal": float(np.mean(d == 0))}
    res["load_after"] = os.getloadavg()
    if args.save:
        np.savez(args.save, **fields)
    print(json.dumps(res))


if __name__ == "__main__":
    main()
