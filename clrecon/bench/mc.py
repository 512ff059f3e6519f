"""``python -m clrecon bench --only mc``: the cost of the ``mc`` method against the paper methods'
reconstruction of the same run (docs/results/mc-cost.md "Cost").

One run of ``demo`` at pitch 0.10 (the clinical pitch ``mc`` is for; ``--quick``: its 4 middle
slices) with barycentric (``mc``'s first pass), local linear, r4DCT and ``mc``, in a temporary
folder with a fresh projection cache. From its ``results.json``: the paper methods'
reconstruction (read + noise + rebin + interpolate + FBP, every variant and method) against
``mc``'s own parts (registration with the rounds' backprojections, plane rows, the final
motion-compensated backprojection), and ``mc``'s MAE beside min(barycentric, local linear).
Then, on the run's own noisy first pass, one registration round (13 registrations on ``demo``) with
the scene's registrations (``steps``: by default the OpenCL Lucas-Kanade for the breathing
and TV-L1 for the beat, in the run's process), ``repeats`` times; where a step registers in a
process pool (scikit-image's Lucas-Kanade, ``[recon.mc] registration = "lucas_kanade"``) one after
the other and in the pool, alternating: the pool's speed-up, with the fields' bit-identity checked.
Last, the motion-compensated backprojection kernel against the static backprojector on the same
geometry, in the same process (:mod:`clrecon.bench.mc_kernel`: G updates/s, their ratio, medians, the load).
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

import h5py
import numpy as np

from clrecon.bench import mc_kernel
from clrecon.bench.timing import load1
from clrecon.config.scene import load_scene
from clrecon.core.resources import spawned_pool
from clrecon.outputs.volumes import recon_path
from clrecon.pipeline.context import resolve_targets
from clrecon.pipeline.run import run as run_pipeline
from clrecon.reconstruction import reconstruct
from clrecon.reconstruction.motion import mc_fbp
from clrecon.reconstruction.motion import method as mcm
from clrecon.reconstruction.motion.registration import registration_workers

#: The pitch of the section: the clinical one.
PITCH = 0.10
METHODS = ("barycentric", "local_linear", "r4dct", "mc")
#: Stages of the paper methods' reconstruction, and of mc's own work, in ``results.json["stages"]``.
RECON_STAGES = ("read", "noise", "rebin", "interpolate", "fbp")
MC_STAGES = ("registration", "plane_rows", "mc_backproject")


def _first_pass(run_dir: Path, pk: str, variant: str) -> np.ndarray:
    """The run's volumes of ``mc``'s first pass (barycentric) of ``variant``: (n_c, n_r, S, ny, nx) HU."""
    with h5py.File(run_dir / "volumes.h5", "r") as f:
        return np.asarray(f[recon_path(pk, variant, mc_fbp.FIRST_PASS)], np.float32)


def _registration_round(first, sc, slices_z, repeats: int) -> dict:
    """One registration round on ``first`` with ``sc``'s registrations: one after the other, and where a
    step registers in a process pool (:func:`method.uses_pool`) in the pool too, alternating."""
    cfg = reconstruct.ReconstructionConfig.from_scene(sc)
    knobs = sc.recon.mc_knobs
    targets = resolve_targets(sc)
    pairs = targets.pairs
    ref_ij = mcm.reference_index(targets.cardiac, targets.resp, knobs)
    grid = mcm.field_grid(cfg.fbp, slices_z)
    workers = registration_workers(grid.nx * grid.ny * grid.nz) if mcm.uses_pool(knobs) else 1
    pool = spawned_pool(workers) if workers > 1 else None
    serial_s, pooled_s, same = [], [], True
    try:
        if pool is not None:  # warm the workers' imports (skimage) before timing
            mcm.register(first, ref_ij, grid, pairs, knobs, pool=pool)
        for _ in range(repeats):
            t0 = time.perf_counter()
            a, _ = mcm.register(first, ref_ij, grid, pairs, knobs)
            serial_s.append(time.perf_counter() - t0)
            if pool is not None:
                t0 = time.perf_counter()
                b, _ = mcm.register(first, ref_ij, grid, pairs, knobs, pool=pool)
                pooled_s.append(time.perf_counter() - t0)
                same = same and bool(np.array_equal(a.fields, b.fields))
    finally:
        if pool is not None:
            pool.shutdown()
    s = float(np.median(serial_s))
    p = float(np.median(pooled_s)) if pooled_s else None
    return {"registrations": (first.shape[0] - 1) + (first.shape[1] - 1), "steps": mcm.registrations(knobs),
            "grid": [grid.nz, grid.ny, grid.nx],
            "workers": workers, "serial_s": s, "pool_s": p, "speedup": (s / p) if p else None,
            "same_bits": same, "repeats": repeats}


def bench_mc_section(quick: bool = False, repeats: int = 3, scene="demo") -> dict:
    """The section's numbers (module docstring)."""
    sc = load_scene(scene) if isinstance(scene, str) else scene
    sc = sc.replace(scan={"pitches": [PITCH]})
    nz = sc.recon.nz
    slices = (max(0, nz // 2 - 2), min(nz, nz // 2 + 2)) if quick else (0, nz)
    load = load1()
    with tempfile.TemporaryDirectory(prefix="clrecon-bench-mc-") as tmp:
        out = Path(tmp) / "run"
        t0 = time.perf_counter()
        res = run_pipeline(sc, out, slice_range=slices, methods=METHODS, cache_dir=Path(tmp) / "cache",
                           progress=False, report=False, log=lambda *a, **k: None)
        run_s = time.perf_counter() - t0
        pk = next(iter(res["metrics"]))
        variant = "noisy" if "noisy" in res["metrics"][pk] else next(iter(res["metrics"][pk]))
        first = _first_pass(out, pk, variant)
    st = res["stages"]
    recon_s = sum(st[k]["seconds"] for k in RECON_STAGES if k in st)
    parts = {k: st[k]["seconds"] for k in MC_STAGES if k in st}
    mc_s = sum(parts.values())
    mae = {}
    for v, per in res["metrics"][pk].items():
        paper = min(per[m]["large"]["mae_hu"] for m in ("barycentric", "local_linear")), \
            min(per[m]["small"]["mae_hu"] for m in ("barycentric", "local_linear"))
        got = per["mc"]["large"]["mae_hu"], per["mc"]["small"]["mae_hu"]
        mae[v] = {"mc": list(got), "min_bary_ll": list(paper), "ratio": [got[0] / paper[0], got[1] / paper[1]]}
    slices_z = reconstruct.slice_positions(sc, slices)
    reg = _registration_round(first, sc, slices_z, max(1, repeats if not quick else 1))
    kernel = mc_kernel.run(quick, repeats, scene=sc)
    return {"scene": sc.name, "pitch": PITCH, "slices": list(slices), "methods": list(METHODS),
            "variants": list(res["metrics"][pk]), "load_average_1min_before": load, "run_s": run_s,
            "reconstruction_s": recon_s, "mc_s": mc_s, "mc_parts_s": parts,
            "ratio": mc_s / recon_s if recon_s else None, "mae": mae, "registration_round": reg, "kernel": kernel}


def run(quick: bool = False, repeats: int = 3, log=print) -> dict:
    """The bench's ``mc``: :func:`bench_mc_section` on ``demo``."""
    return bench_mc_section(quick, repeats)


def report_lines(r: dict | None) -> list[str]:
    """The section's lines of the bench report."""
    if not r:
        return []
    parts = ", ".join(f"{k} {v:.1f} s" for k, v in r["mc_parts_s"].items())
    out = ["", f"mc ({r['scene']}, pitch {r['pitch']:g}, slices {r['slices'][0]}:{r['slices'][1]}, "
               f"{', '.join(r['variants'])}; load {r['load_average_1min_before']}): run {r['run_s']:.1f} s; "
               f"mc {r['mc_s']:.1f} s ({parts}) against {r['reconstruction_s']:.1f} s of the paper methods' "
               f"reconstruction (x{r['ratio']:.1f})"]
    for v, m in r["mae"].items():
        out.append(f"   {v}: mc MAE {m['mc'][0]:.1f} / {m['mc'][1]:.1f} HU (large / small FOV), "
                   f"x{m['ratio'][0]:.3f} / x{m['ratio'][1]:.3f} min(barycentric, local linear)")
    g = r["registration_round"]
    steps = ", ".join(f"{k} {v}" for k, v in g.get("steps", {}).items())
    what = (f"one registration round ({g['registrations']} registrations on {g['grid'][2]} x {g['grid'][1]} "
            f"x {g['grid'][0]}{'; ' + steps if steps else ''})")
    if g["pool_s"]:
        out.append(f"   {what}: {g['serial_s']:.1f} s one after the other, {g['pool_s']:.1f} s in "
                   f"{g['workers']} processes (x{g['speedup']:.2f}; same bits: {g['same_bits']}; median of "
                   f"{g['repeats']})")
    else:
        out.append(f"   {what}: {g['serial_s']:.1f} s in the run's process (median of {g['repeats']})")
    out.extend(mc_kernel.report_lines(r.get("kernel")))
    return out
