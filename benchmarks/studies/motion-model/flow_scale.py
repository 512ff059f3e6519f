"""Time and peak memory of one TV-L1 registration of a clinical-size volume (default 512 x 512 x 110).

Smoothed random texture and its copy shifted by a few voxels (the work does not depend on the
content: fixed levels, warps and iterations). Prints wall and CPU seconds (all threads), peak RSS and the load.

    nice -n 10 python benchmarks/studies/motion-model/flow_scale.py [--shape 110 512 512]
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import time

import numpy as np
import scipy.ndimage

from clrecon.core.runtime import get_runtime
from clrecon.reconstruction.motion import flow


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--shape", type=int, nargs=3, default=[110, 512, 512])
    args = ap.parse_args()
    shape = tuple(args.shape)
    rng = np.random.default_rng(0)
    fixed = scipy.ndimage.gaussian_filter(rng.normal(0, 300, shape).astype(np.float32), 2.0)
    moving = np.roll(fixed, (2, -3, 4), axis=(0, 1, 2))
    rt = get_runtime()
    flow.register_tvl1(fixed[:8, :64, :64], moving[:8, :64, :64], (1.0, 1.0, 1.0), runtime=rt)  # build the kernels
    rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20
    load0 = os.getloadavg()
    t0 = time.perf_counter()
    cpu0 = time.process_time()
    u = flow.register_tvl1(fixed, moving, (1.0, 1.0, 1.0), runtime=rt)
    dt = time.perf_counter() - t0
    cpu = time.process_time() - cpu0
    inner = tuple(slice(8, n - 8) for n in shape)
    print(json.dumps({"shape": shape, "device": rt.description, "seconds": round(dt, 1), "cpu_seconds": round(cpu, 1),
                      "peak_rss_gb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20, 2),
                      "rss_before_gb": round(rss0, 2), "inputs_gb": round(2 * fixed.nbytes / 2**30, 2),
                      "median_u_mm": [float(np.median(u[k][inner])) for k in range(3)], "expected_mm": [4, -3, 2],
                      "load_before": load0, "load_after": os.getloadavg(), "cfg": str(flow.TVL1Config())}))


if __name__ == "__main__":
    main()
