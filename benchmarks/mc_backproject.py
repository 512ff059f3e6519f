"""``python -m benchmarks.mc_backproject``: the motion-compensated backprojection kernel, 8 voxels
per work-item (``kernels/mc_backproject.cl``, with the lanes the device gets: 16 on a CPU with
AVX-512, else 8) against the scalar kernel it replaced (``kernels/reference/mc_backproject_scalar.cl``),
on each OpenCL CPU driver, in the same run; and the kernel's other build (8 lanes where the device
gets 16, else 16).

The case (:func:`clrecon.bench.mc_kernel.synthetic_case`, shared with the bench's ``mc`` section) has
`demo`'s geometry (128^2 voxels of 3 mm, 360 views x 240 columns, flat detector)
and the motion model's basis (NB = 6: constant, amplitude, 2 cardiac harmonics), with synthetic
data of `demo`'s sizes at pitch 0.10: projections every view on 13 turns 2.8 mm apart in z, each
rebinned to the 2-mm planes within its SSRB window (11.9 mm) plus one plane (14 planes), random
rows; per (slice, view) the 3 projections nearest the slice in z with random weights (as
barycentric's 3 slots); smooth random fields of up to 6 mm. The kernels read the same device
buffers (one :class:`MCBackprojector`), their repeats alternate, medians reported; an update is
one (voxel in the FOV, non-empty slot) pair. The outputs are compared (max |new - old| over
max |old|).
"""

from __future__ import annotations

import time

import numpy as np

from clrecon.bench import reference_kernels
from clrecon.bench.mc_kernel import synthetic_case
from clrecon.bench.timing import load1, timed
from clrecon.core.runtime import Runtime
from clrecon.reconstruction.motion import backproject as mcb
from clrecon.reconstruction.motion.backproject import MCBackprojector

#: The drivers measured (``CLRECON_DEVICE`` names): Intel's CPU runtime and PoCL.
DRIVERS = ("intel", "portable")


def bench_mc_backproject(quick: bool = False, repeats: int = 3, drivers=DRIVERS, scene: str = "demo") -> dict:
    """Updates/s of the new and the scalar kernel on each driver, same data, alternating repeats
    (``scene``: whose geometry; the module docstring's case is `demo`'s)."""
    geom, model, rows, pb, sp, sw, zs = synthetic_case(2 if quick else 4, scene=scene)
    target = (0.3, 0.6)
    fov = int(geom.fov_mask().sum())
    updates = fov * int(((sp >= 0) & (sw > 0)).sum())
    res = {"scene": f"{scene} geometry, synthetic rows and fields", "image": [geom.ny, geom.nx], "views": geom.n_views,
           "cols": geom.n_cols, "slices": len(zs), "slots": sp.shape[2], "basis": model.basis.size,
           "rows_mb": rows.rows.nbytes / 1e6, "updates": updates, "repeats": repeats, "drivers": {}}
    for name in drivers:
        try:
            rt = Runtime(name)
        except Exception as e:  # noqa: BLE001 - a driver that is not installed is reported, not fatal
            res["drivers"][name] = {"error": str(e).splitlines()[0]}
            continue
        out = {}
        with MCBackprojector(rows, pb, model, zs, geom, runtime=rt) as bp:
            def new(out=out, bp=bp):
                out["new"] = bp(sp, sw, target)

            def old(out=out, bp=bp):
                out["old"] = reference_kernels.mc_backproject_scalar(bp, sp, sw, target)

            alt = 24 - bp.lanes  # the other build: 8 or 16 lanes
            k_alt = rt.kernel(mcb._KERNEL_FILE, "mc_backproject", **{**bp._defines, "LANES": alt})
            g_alt = mcb._global_size(geom, len(zs), alt, bp.local_size)

            def other(out=out, bp=bp, k_alt=k_alt, g_alt=g_alt):
                out["other"] = bp._launch(k_alt, g_alt, bp.local_size, sp, sw, target)

            fns = {"new": new, "old": old, "other": other}
            for fn in fns.values():  # warm-up: builds, PoCL specialisation
                fn()
            times = {k: [] for k in fns}
            cpu = {k: [] for k in fns}
            loads = []
            for _ in range(max(1, repeats)):
                loads.append(load1())
                for k, fn in fns.items():
                    c0 = time.process_time()
                    times[k].append(timed(fn))
                    cpu[k].append(time.process_time() - c0)
        med = {k: float(np.median(v)) for k, v in times.items()}
        med_cpu = {k: float(np.median(v)) for k, v in cpu.items()}
        scale = float(np.abs(out["old"]).max())
        res["drivers"][name] = {
            "device": rt.description, "seconds": times, "median_s": med,
            "updates_per_s": {k: updates / v for k, v in med.items()}, "speedup": med["old"] / med["new"],
            "lanes": bp.lanes, "other_lanes": alt, "speedup_other": med["old"] / med["other"],
            "cpu_seconds": cpu, "updates_per_cpu_s": {k: updates / v for k, v in med_cpu.items()},
            "cpu_speedup": med_cpu["old"] / med_cpu["new"],
            "max_rel_diff": float(np.abs(out["new"] - out["old"]).max()) / scale if scale else 0.0,
            "max_rel_diff_other": float(np.abs(out["other"] - out["old"]).max()) / scale if scale else 0.0,
            "load_average_1min_repeats": loads}
    return res


def report_lines(res: dict | None) -> list[str]:
    """Report lines of a :func:`bench_mc_backproject` result."""
    if not res:
        return []
    out = [f"motion-compensated backprojection: {res['slices']} slices {res['image'][1]}^2, {res['views']} views x "
           f"{res['cols']} columns, {res['slots']} slots, NB = {res['basis']}, {res['rows_mb']:.0f} MB of plane rows "
           f"({res['scene']}); {res['updates'] / 1e6:.1f} M updates per launch",
           f"   {'driver':10s} {'lanes':>5s} {'new M upd/s':>12s} {'scalar M upd/s':>15s} {'speedup':>8s} "
           f"{'max |diff|':>11s} {'other lanes':>12s} {'speedup':>8s} {'per CPU s: new':>15s} {'scalar':>7s} "
           f"{'ratio':>6s}  load (1 min)"]
    for name, d in res["drivers"].items():
        if "error" in d:
            out.append(f"   {name:10s} not measured: {d['error']}")
            continue
        u = d["updates_per_s"]
        out.append(f"   {name:10s} {d['lanes']:>5d} {u['new'] / 1e6:>12.1f} {u['old'] / 1e6:>15.1f} "
                   f"{d['speedup']:>7.2f}x "
                   f"{d['max_rel_diff']:>11.1e} {d['other_lanes']:>3d}: {u['other'] / 1e6:>7.1f} "
                   f"{d['speedup_other']:>7.2f}x "
                   f"{d['updates_per_cpu_s']['new'] / 1e6:>15.1f} {d['updates_per_cpu_s']['old'] / 1e6:>7.1f} "
                   f"{d['cpu_speedup']:>5.2f}x  {d['load_average_1min_repeats']}")
    out.append("   (M updates/s: (voxel in the FOV, non-empty slot) pairs per wall second, medians; per CPU s: per "
               "second of this process's CPU time; max |diff|: max |new - scalar| / max |scalar|)")
    return out


def _bench(quick: bool = False, repeats: int = 3) -> dict:
    """Motion-compensated backprojection kernel, 8 voxels per work-item against scalar, both CPU drivers."""
    return bench_mc_backproject(quick=quick, repeats=repeats)


if __name__ == "__main__":  # pragma: no cover - run by hand: python -m benchmarks.mc_backproject
    from benchmarks._cli import main

    raise SystemExit(main(_bench, report_lines))
