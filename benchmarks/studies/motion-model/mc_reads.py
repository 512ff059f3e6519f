"""Where the motion-compensated backprojection's time goes: its row reads against everything else.

Issue 41, item 4 asks the kernel for a quarter of the static backprojector's updates/s. This study
times, on the bench's synthetic case (:func:`clrecon.bench.mc_kernel.synthetic_case`: `demo`'s
geometry, 4 slices, 3 slots per view, NB = 6), builds of the same computation that differ only in
how they read the plane rows, all on the same device buffers, alternating, medians:

- ``lanes``: the production kernel (``kernels/mc_backproject.cl``, 8 or 16 voxels per work-item in
  explicit vectors, its launch shape);
- ``lanes-noread``: the same source with the four taps replaced by the interpolation weights (no row
  is read; everything else computed as before): the time of all but the reads;
- ``lanes-hot``: every slot reads the rows of projection 0 (13 KB, cache-resident): the reads'
  instruction cost without cache misses;
- ``vec``, ``vec-pair``, ``vec-hot``, ``vec-pair-hot``, ``vec-noread``: the study kernel
  ``mc_vec.cl`` beside this file (one voxel per work-item, branches uniform along x, so Intel's CPU
  compiler vectorises it across 16 work-items with gather instructions), plain, with each plane's
  two column taps as one 8-byte load (``PAIR``), and the same two read variants;
- ``static`` and ``static-single``: the fan-beam backprojector of the same geometry on 32 random
  sinograms, as the bench's row times it (16 sinograms per work-item, the column computed once for
  all 16) and the one-sinogram-per-work-item kernel it replaced
  (:func:`clrecon.bench.reference_kernels.backproject_single`), updates (voxel in the FOV, view,
  image): what a read costs where the geometry is not shared by 16 images.

Each variant's image is compared with the production kernel's (max |difference| over max |image|;
the read variants differ by construction). Prints one JSON line: M updates/s per variant (an update
is one (voxel in the FOV, non-empty slot) pair, as the bench counts), the CPU, the load.

    PYTHONPATH=. python benchmarks/studies/motion-model/mc_reads.py [--repeats 5]

Results: docs/results/mc-cost.md "Cost".
"""

from __future__ import annotations

import argparse
import json
import re
import tempfile
from pathlib import Path

import numpy as np

from clrecon.bench import reference_kernels
from clrecon.bench.mc_kernel import STATIC_BATCH, synthetic_case
from clrecon.bench.timing import load1, timed
from clrecon.core import drivers
from clrecon.core.kernel_sources import load_source
from clrecon.core.runtime import get_runtime
from clrecon.reconstruction import fbp
from clrecon.reconstruction.motion.backproject import MCBackprojector, _global_size

HERE = Path(__file__).resolve().parent
#: The production kernel's four taps (one statement) and its row base, which the variants below
#: replace (the script stops if the kernel no longer has them).
TAPS = re.compile(r"const floatL val = \(1\.0f - tg\)[^;]*;")
ROW_BASE = re.compile(re.escape("__global const float *r0 = rows + (size_t)p * np_max * n_cols;"))
#: The production kernel with no row reads, and with every slot reading projection 0's rows.
LANES_VARIANTS = {
    "lanes-noread": (TAPS, "const floatL val = tc * tg;"),
    "lanes-hot": (ROW_BASE, "__global const float *r0 = rows;"),
}
#: The study kernel's variants: build options.
VEC_VARIANTS = {"vec": {}, "vec-pair": {"PAIR": 1}, "vec-hot": {"HOTREAD": 0}, "vec-pair-hot": {"PAIR": 1, "HOTREAD": 0},
                "vec-noread": {"NOREAD": 1}}
#: The study kernel's local size: 16 work-items along x (one AVX-512 vector), 4 rows.
VEC_LOCAL = (16, 4)


def lanes_source(pattern: re.Pattern, new: str) -> str:
    """The production kernel's source with the one match of ``pattern`` replaced by ``new``."""
    src = load_source("mc_backproject.cl")
    if len(pattern.findall(src)) != 1:
        raise SystemExit(f"kernels/mc_backproject.cl: {pattern.pattern!r} does not match once: update this study")
    return pattern.sub(lambda _m: new, src)


def run(repeats: int = 5, scene: str = "demo", n_slices: int = 4) -> dict:
    """The module docstring's measurement on ``scene``'s geometry (``n_slices`` slices)."""
    rt = get_runtime()
    geom, model, rows, pb, sp, sw, zs = synthetic_case(n_slices, scene=scene)
    updates = int(geom.fov_mask().sum()) * int(((sp >= 0) & (sw > 0)).sum())
    target = (0.3, 0.6)
    with MCBackprojector(rows, pb, model, zs, geom, runtime=rt) as bp, tempfile.TemporaryDirectory() as tmp:
        fns = {"lanes": lambda: bp(sp, sw, target)}
        gs = _global_size(geom, len(zs), bp.lanes, bp.local_size)
        for i, (name, (old, new)) in enumerate(LANES_VARIANTS.items()):
            folder = Path(tmp) / str(i)
            folder.mkdir()
            (folder / "mc_backproject.cl").write_text(lanes_source(old, new))
            kern = rt.kernel("mc_backproject.cl", "mc_backproject", _folder=folder, **bp._defines)
            fns[name] = lambda kern=kern: bp._launch(kern, gs, bp.local_size, sp, sw, target)
        base = {k: v for k, v in bp._defines.items() if k not in ("LANES", "LX", "LY", "VCHUNK")}
        vgs = _global_size(geom, len(zs), 1, VEC_LOCAL)  # one voxel per work-item
        for name, opts in VEC_VARIANTS.items():
            kern = rt.kernel("mc_vec.cl", "mc_backproject", _folder=HERE, **base, **opts,
                             LX=VEC_LOCAL[0], LY=VEC_LOCAL[1], VCHUNK=1 << 20)
            fns[name] = lambda kern=kern: bp._launch(kern, vgs, VEC_LOCAL, sp, sw, target)
        sino = np.random.default_rng(1).normal(size=(STATIC_BATCH, geom.n_views, geom.n_cols)).astype(np.float32)
        fns["static"] = lambda: fbp.backproject(sino, geom, runtime=rt)
        fns["static-single"] = lambda: reference_kernels.backproject_single(sino, geom, runtime=rt)
        images = {k: f() for k, f in fns.items()}  # builds and warm-up
        times = {k: [] for k in fns}
        loads = []
        for _ in range(repeats):
            loads.append(load1())
            for k, f in fns.items():
                times[k].append(timed(f))
        ref = images.pop("lanes")
        scale = float(np.abs(ref).max())
        static = images.pop("static")
        single_diff = float(np.abs(images.pop("static-single") - static).max() / np.abs(static).max())
    counts = {k: updates for k in times}
    counts["static"] = counts["static-single"] = int(geom.fov_mask().sum()) * geom.n_views * STATIC_BATCH
    out = {"device": rt.description, "cpu": drivers.cpu_line(), "updates": updates, "repeats": repeats,
           "lanes": bp.lanes, "local_size": list(bp.local_size), "vec_local_size": list(VEC_LOCAL),
           "load_average_1min": loads,
           "m_updates_per_s": {k: round(counts[k] / float(np.median(v)) / 1e6, 1) for k, v in times.items()},
           "max_diff_over_max": {k: float(np.abs(v - ref).max()) / scale for k, v in images.items()},
           "static_single_max_diff_over_max": single_diff}
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=5)
    print(json.dumps(run(ap.parse_args().repeats)))


if __name__ == "__main__":
    main()
