"""Bench section ``scaling``: plan, simulate and reconstruct seconds against the job's sizes.

Demo-sized scenes (via :meth:`clrecon.config.scene.Scene.replace`), one method, noise-free,
along three axes from a small base: slices, targets and projections (the pitch).
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

from clrecon.bench.timing import load1
from clrecon.config.scene import load_scene
from clrecon.core.runtime import get_runtime
from clrecon.reconstruction import reconstruct
from clrecon.scan.table import projection_table
from clrecon.simulation import simulate


def run(quick: bool = False, repeats: int = 3, log=print, *, scene="demo", method: str = "local_linear") -> dict:
    """Plan / simulate / reconstruct seconds of demo-sized variants: slices, targets, projections (one run
    per size: ``repeats`` and ``log`` unused)."""

    base = load_scene(scene) if isinstance(scene, str) else scene
    rt = get_runtime()
    nz0, bins0, pitch0 = (2, 2, 0.10) if quick else (4, 5, 0.10)
    series = {
        "slices": [dict(recon={"nz": n}) for n in ((2, 4) if quick else (2, 4, 8))],
        "targets": [dict(recon={"resp_bins": b}) for b in ((2, 4) if quick else (2, 5, 10))],
        "projections": [dict(scan={"pitches": [p]}) for p in ((0.10, 0.05) if quick else (0.10, 0.05, 0.025))],
    }
    load = load1()
    rows = []
    with tempfile.TemporaryDirectory(prefix="clrecon-bench-scale-") as tmp:
        for axis, variants in series.items():
            for change in variants:
                recon = {"nz": nz0, "resp_bins": bins0, "methods": [method], **change.get("recon", {})}
                scan = {"pitches": [pitch0], **change.get("scan", {})}
                sc = base.replace(recon=recon, scan=scan, noise={"enabled": False})
                pitch = sc.scan.pitches[0]
                slices_z = reconstruct.slice_positions(sc)
                targets = reconstruct.Targets(tuple(sc.cardiac_targets), tuple(sc.resp_targets))
                table = projection_table(sc, pitch)
                p = reconstruct.plan(reconstruct.ReconstructionConfig.from_scene(sc), table, slices_z, targets,
                                     (method,))
                needed = p.needed_projections(len(table))
                t0 = time.perf_counter()
                store = simulate.simulate(sc, pitch, needed=needed, cache_dir=Path(tmp), progress=False)
                t_sim = time.perf_counter() - t0
                t0 = time.perf_counter()
                reconstruct.reconstruct(reconstruct.ReconstructionConfig.from_scene(sc), store, p,
                                        variants=("noise-free",), rt=rt)
                t_rec = time.perf_counter() - t0
                store.close() if hasattr(store, "close") else None
                proj, _ = p.needed_pairs()
                rows.append({"axis": axis, "slices": len(slices_z), "targets": len(targets.pairs), "pitch": pitch,
                             "projections_needed": int(needed.sum()), "rebinned_rows": int(len(proj)),
                             "plan_s": p.seconds, "simulate_s": t_sim, "reconstruct_s": t_rec,
                             "sinograms": len(slices_z) * len(targets.pairs)})
    return {"scene": base.name, "method": method, "variant": "noise-free", "load_average_1min_before": load,
            "rows": rows}


def report_lines(scl: dict) -> list[str]:
    """The section's lines of the bench report."""
    out = [""]
    out.append(f"5. scaling ({scl['scene']} variants, {scl['method']}, noise-free; "
               f"load {scl['load_average_1min_before']})")
    out.append(f"   {'axis':12s} {'slices':>6s} {'targets':>7s} {'pitch':>6s} {'proj':>6s} {'rows':>8s} "
               f"{'plan s':>7s} {'sim s':>7s} {'recon s':>7s} {'ms/sino':>8s}")
    for r in scl["rows"]:
        out.append(f"   {r['axis']:12s} {r['slices']:>6d} {r['targets']:>7d} {r['pitch']:>6.3f} "
                   f"{r['projections_needed']:>6d} {r['rebinned_rows']:>8d} {r['plan_s']:>7.2f} "
                   f"{r['simulate_s']:>7.2f} {r['reconstruct_s']:>7.2f} "
                   f"{1e3 * r['reconstruct_s'] / r['sinograms']:>8.1f}")
    return out
