"""Bench section ``interpolation``: output rows/s of the 5DCT interpolation, per method.

One output row is one rebinned row per (slice, view, target). Timed: the neighbour search and
weights (:func:`clrecon.reconstruction.interpolation.weights.batch_weights`) and the kernel that
applies them (:func:`clrecon.reconstruction.interpolation.weights.apply_weights_interleaved`, rows
uploaded once, as the reconstruction does), per method, on the ``demo`` scan (4 middle slices;
``--quick``: 2); reference: the float64 NumPy ``apply_weights_reference`` on the same weights.
"""

from __future__ import annotations

import numpy as np

from clrecon.bench.timing import load1, median_time
from clrecon.config.scene import load_scene
from clrecon.core.runtime import get_runtime
from clrecon.reconstruction import rebin, reconstruct
from clrecon.reconstruction.interpolation import weights as interpolate
from clrecon.scan.table import projection_table


def run(quick: bool = False, repeats: int = 3, log=print, *, scene="demo", pitch: float | None = None,
        n_slices: int | None = None, methods=None, reference_rows: int = 20000) -> dict:
    """Rows/s of neighbour search + weights + ``apply_weights`` per method (see module doc; ``log`` unused)."""

    sc = load_scene(scene) if isinstance(scene, str) else scene
    rt = get_runtime()
    pitch = pitch or sc.scan.pitches[0]
    n_slices = n_slices or (2 if quick else 4)
    nz = sc.recon.nz
    i0 = max(0, nz // 2 - n_slices // 2)
    slices_z = reconstruct.slice_positions(sc, (i0, min(nz, i0 + n_slices)))
    table = projection_table(sc, pitch)
    targets = reconstruct.Targets(tuple(sc.cardiac_targets), tuple(sc.resp_targets))
    load = load1()
    t_groups, _ = median_time(lambda: rebin.candidate_groups(table, slices_z, sc.scanner,
                                                              reconstruct.object_radius_mm(sc)), 1, warmup=False)
    groups = rebin.candidate_groups(table, slices_z, sc.scanner, reconstruct.object_radius_mm(sc))
    c = table.cardiac_phase[groups.row]
    a = table.resp_amplitude[groups.row]
    opts = reconstruct.weight_options(reconstruct.ReconstructionConfig.from_scene(sc), targets)
    rng = np.random.default_rng(0)
    rows = rng.standard_normal((len(groups.row), sc.scanner.n_cols)).astype(np.float32)
    t_up, _ = median_time(lambda: interpolate.DeviceRows(rows, rt=rt).release(), repeats)
    d_rows = interpolate.DeviceRows(rows, rt=rt)
    S, V = len(slices_z), sc.scanner.views_per_rotation
    res = {"scene": sc.name, "pitch": pitch, "slices": S, "views": V,
           "candidates": int(len(groups.row)), "n_cols": sc.scanner.n_cols, "repeats": repeats,
           "load_average_1min_before": load, "candidate_groups_s": t_groups, "upload_rows_s": t_up,
           "kernel": "apply_weights_interleaved16_cols8 (rows uploaded once; output in the backprojector's layout)",
           "methods": {}}
    for m in methods or sc.recon.methods:
        tg, _ = reconstruct.method_targets(m, targets)
        box = {}

        def weights(m=m, tg=tg, box=box):
            box["w"] = interpolate.batch_weights(m, c, a, groups.offsets, tg, rt=rt, dz=groups.dz_mm, **opts)

        t_w, _ = median_time(weights, max(1, repeats - 1), warmup=False)
        G, T, K = box["w"].index.shape
        # sinogram b = s * T + t, (B, V, K): as reconstruct hands them to the kernel
        idx = box["w"].index.reshape(S, V, T, K).transpose(0, 2, 1, 3).reshape(S * T, V, K)
        wgt = box["w"].weight.reshape(S, V, T, K).transpose(0, 2, 1, 3).reshape(S * T, V, K).astype(np.float32)

        def apply(idx=idx, wgt=wgt, box=box):
            buf, n_groups = interpolate.apply_weights_interleaved(d_rows, idx, wgt, rt=rt)
            box["out"] = rt.from_device(buf, (n_groups, V, sc.scanner.n_cols + 2, 16))
            buf.release()

        t_a, _ = median_time(apply, repeats)
        n_sino = max(1, min(S * T, reference_rows // V))  # whole sinograms, about reference_rows rows

        def apply_ref(idx=idx, wgt=wgt, n_sino=n_sino, K=K, box=box):
            box["ref"] = interpolate.apply_weights_reference(
                rows, idx[:n_sino].reshape(-1, K), wgt[:n_sino].reshape(-1, K))

        t_ref, _ = median_time(apply_ref, 1, warmup=False)
        out_rows = G * T
        ref = box["ref"].reshape(n_sino, V, -1)
        got = box["out"].transpose(0, 3, 1, 2).reshape(-1, V, sc.scanner.n_cols + 2)[:n_sino, :, 1:-1]
        diff = float(np.abs(got - ref).max() / max(np.abs(ref).max(), 1e-30))
        n_ref = n_sino * V
        res["methods"][m] = {
            "output_rows": out_rows, "k_slots": K, "weights_s": t_w, "apply_s": t_a,
            "rows_per_s": out_rows / (t_w + t_a), "weights_rows_per_s": out_rows / t_w,
            "apply_rows_per_s": out_rows / t_a,
            "reference_apply_rows_per_s": n_ref / t_ref, "apply_speedup": (out_rows / t_a) / (n_ref / t_ref),
            "max_rel_diff_vs_reference": diff}
    d_rows.release()
    return res


def report_lines(ip: dict) -> list[str]:
    """The section's lines of the bench report."""
    out = [""]
    out.append(f"3. interpolation {ip['scene']} pitch {ip['pitch']}: {ip['slices']} slices x {ip['views']} views, "
               f"{ip['candidates']} candidate rows of {ip['n_cols']}; load {ip['load_average_1min_before']}")
    out.append(f"   {'method':13s} {'rows':>8s} {'K':>3s} {'rows/s':>10s} {'weights/s':>10s} {'apply/s':>10s} "
               f"{'ref apply/s':>11s} {'x ref':>6s} {'max rel diff':>12s}")
    for name, r in ip["methods"].items():
        out.append(f"   {name:13s} {r['output_rows']:>8d} {r['k_slots']:>3d} {r['rows_per_s']:>10.3g} "
                   f"{r['weights_rows_per_s']:>10.3g} {r['apply_rows_per_s']:>10.3g} "
                   f"{r['reference_apply_rows_per_s']:>11.3g} {r['apply_speedup']:>6.1f} "
                   f"{r['max_rel_diff_vs_reference']:>12.1e}")
    return out
