"""The motion-model study of issue 34, phase 1 (docs/results/mc-study.md): demo and demo-hrv, reported slices.

    python benchmarks/studies/motion-model/study.py            -> benchmarks/studies/motion-model/study.json

Knobs are those chosen on demo's tuning slices by tune.py (tune.json) and fixed here (KNOBS); the
reported slices are the run's own 16 (every metric as clrecon.evaluation.metrics: MAE over all
voxels of all 50 targets, large FOV = the reconstruction circle, small FOV = the heart box).
Rows of study.json: per (scene, pitch, noise variant): the paper methods, the masked
r4DCT/barycentric control, the motion-model variants (A: motion-compensated FBP with barycentric
row weights; A2: A again with the model registered from A's own images; B: the model-based
correction step with the MC image of the reference state as the model), A with the phantom's true motion as the model's input (demo), the registration error
against the phantom's motion, the static-phantom floor (SSRB data-model error), and seconds.
Resumable: finished cells are kept in study.json; intermediate arrays are cached (common.CACHE).
"""

import json
import os
import platform
import subprocess
import sys
import time

import numpy as np
import scipy.ndimage

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)
import common as cm

import clrecon
from clrecon.evaluation.groundtruth import GroundTruthConfig, groundtruth_volumes
from clrecon.evaluation.metrics import MetricsConfig, table2
from clrecon.reconstruction import reconstruct as rc
from clrecon.reconstruction.motion import backproject as mcb
from clrecon.reconstruction.motion import estimate
from clrecon.reconstruction.motion import model as mm
from clrecon.reconstruction.motion import registration as reg
from clrecon.scan.table import projection_table
from clrecon.simulation.phantoms import motion_field
from clrecon.simulation.simulate import simulate

OUT = os.path.join(HERE, "study.json")
#: chosen once on demo's tuning slices (tune.json; docs/motion-model.md "Knobs")
KNOBS = {
    "reference_target": [4, 4],            # (c, a) = (0.8, 0.45): diastasis, mid amplitude
    "basis": {"resp_degree": 1, "cardiac_harmonics": 2},
    "registration": "separable Lucas-Kanade (skimage optical_flow_ilk), radius 7 voxels, 10 warps",
    "plane_dz_mm": 2.0,
    "taper_mm": 2.0,
    "inversion_steps": mcb.INVERSION_STEPS,
    "B_model_image": "A with Gaussian row weights sigma_c 0.1, sigma_a 0.15, 6 rows, at the reference, 2-mm slices",
    "B_state_bins": [20, 10],
    "mask_threshold_hu": None,              # the masked control's, set by masked_threshold() on tuning slices
}
FLOW = reg.FlowConfig(radius=7)
BASIS = mm.MotionBasis(**KNOBS["basis"])
HEART = ("lv_myocardium", "lv_blood", "rv_myocardium", "rv_blood", "left_atrium", "right_atrium", "lesion",
         "aortic_root")


def load():
    return json.load(open(OUT)) if os.path.exists(OUT) else {}


def save(res):
    json.dump(res, open(OUT, "w"), indent=1)


def cardiac_mask(vol, threshold):
    """The masked control's mask: std over cardiac targets (mean over amplitudes) above the threshold, dilated."""
    sd = np.asarray(vol, np.float64).std(axis=0).mean(axis=0)          # (S, ny, nx)
    return scipy.ndimage.binary_dilation(sd > threshold, iterations=1)


def masked_control(fp, threshold):
    m = cardiac_mask(fp["barycentric"], threshold)
    return np.where(m, fp["barycentric"], fp["r4dct"]).astype(np.float32)


def masked_threshold(res):
    """Choose the control's threshold on demo's tuning slices (noise-free), once."""
    if "masked_threshold" in res:
        return res["masked_threshold"]
    ctx = cm.Context("demo", 0.10)
    trt = cm.truth(ctx, ctx.tune_z)
    fpt = cm.first_pass(ctx, "noise-free", ctx.tune_z)
    scores = {str(t): cm.mae(ctx, masked_control(fpt, t), trt) for t in (10.0, 20.0, 40.0, 80.0)}
    best = min(scores, key=lambda k: sum(scores[k]))
    res["masked_threshold"] = {"chosen_hu": float(best), "tuning": scores}
    save(res)
    return res["masked_threshold"]


def registration_error(ctx, fields, tf, ref):
    """RMS and 95th percentile of |u_est - u_true| (mm) in the heart and the body outside the lungs."""
    g = cm.field_grid(ctx)
    x, y, z = g.coords()
    Z, Y, X = np.meshgrid(z, y, x, indexing="ij")
    own = motion_field.owner(ctx.phantom, np.stack([X, Y, Z], -1), *ref)
    names = ctx.phantom.names
    heart = np.isin(own, [names.index(n) for n in HEART if n in names])
    body = (own >= 0) & ~np.isin(own, [names.index(n) for n in ("lung_left", "lung_right", "trachea")])
    e = np.sqrt(((np.asarray(fields) - tf) ** 2).sum(1))
    t = np.sqrt((tf ** 2).sum(1))
    out = {}
    for k, m in (("heart", heart), ("body_outside_lungs", body)):
        out[k] = {"rms_mm": round(float(np.sqrt((e[:, m] ** 2).mean())), 2),
                  "p95_mm": round(float(np.percentile(e[:, m], 95)), 2),
                  "true_motion_rms_mm": round(float(np.sqrt((t[:, m] ** 2).mean())), 2)}
    return out


def static_floor(res):
    """The SSRB data-model floor: demo's phantom frozen (no motion), the first candidate per view."""
    if "static_floor" in res:
        return res["static_floor"]
    out = {}
    sc = clrecon.load_scene("demo", **{"phantom.cardiac_motion": False, "phantom.respiratory_motion": False,
                                       "name": "demo-static"})
    cfg = rc.ReconstructionConfig.from_scene(sc)
    tg = rc.Targets(cardiac=(0.0,), resp=(0.05,))
    z = rc.slice_positions(sc)
    gt = next(groundtruth_volumes(GroundTruthConfig.from_scene(sc), z, tg))[2][None, None]
    for pitch in (0.1, 0.02):
        table = projection_table(sc, pitch)
        store = simulate(sc, pitch, progress=False)
        plan = rc.plan(cfg, table, z, tg, ("nearest",))
        for var in ("noise-free", "noisy"):
            v = rc.reconstruct(cfg, store, plan, variants=(var,))[(var, "nearest")]
            r = table2(v, gt, MetricsConfig.from_scene(sc))
            out[f"{pitch:g} {var}"] = [round(r["large"]["mae_hu"], 2), round(r["small"]["mae_hu"], 2)]
    res["static_floor"] = out
    save(res)
    return out


def cell(res, scene, pitch, var, with_true):
    key = f"{scene} p{pitch:g} {var}"
    row = res.get(key, {})
    ctx = cm.Context(scene, pitch)
    z = ctx.report_z
    tr = cm.truth(ctx, z)
    fp = cm.first_pass(ctx, var, z)
    row["seconds_first_pass_4_methods"] = round(float(fp["seconds"]), 1)
    row["paper"] = {m: cm.mae(ctx, fp[m], tr) for m in cm.FIRST_PASS}
    row["masked_control"] = cm.mae(ctx, masked_control(fp, res["masked_threshold"]["chosen_hu"]), tr)
    save_row(res, key, row)
    ref_ij = tuple(KNOBS["reference_target"])
    ref = tuple(ctx.pairs[ref_ij[0] * ctx.targets.shape[1] + ref_ij[1]])
    models = {}
    models["registered"], fields, reg_s = cm.separable_model(ctx, var, fp["barycentric"], ref_ij, FLOW, BASIS)
    row["seconds_registration"] = round(reg_s, 1)
    tf = cm.true_fields(ctx, ref, ctx.pairs)
    row["registration_error"] = registration_error(ctx, fields, tf, ref)
    model_fields = np.stack([models["registered"].displacement(c, a) for c, a in ctx.pairs])
    row["registered_model_error"] = registration_error(ctx, model_fields, tf, ref)
    if with_true:
        models["true"] = cm.true_model(ctx, ref, BASIS)[0]
    save_row(res, key, row)
    margin = 20.0
    t0 = time.perf_counter()
    g = cm.groups_for(ctx, z, 0.0)
    rows = cm.plane_rows(ctx, var, g.projection, z.min() - margin, z.max() + margin, KNOBS["plane_dz_mm"])
    row["seconds_plane_rows"] = round(time.perf_counter() - t0, 1)
    row["plane_rows"] = {"rows": int(rows.plane_count.sum()), "MB": round(rows.rows.nbytes / 1e6, 1)}
    bary = cm.bary_slots(ctx, z, rows)
    cfg = mcb.MCConfig(taper_mm=KNOBS["taper_mm"])
    for src, model in models.items():
        name = f"A {src}"
        if name not in row:
            t0 = time.perf_counter()
            v = cm.mc_volumes(ctx, rows, model, bary[0], bary[1], z, cfg)
            row[name] = {"mae": cm.mae(ctx, v, tr), "seconds": round(time.perf_counter() - t0, 1)}
            np.save(os.path.join(cm.CACHE, f"A-{src}-{scene}-{pitch:g}-{var}.npy"), v)
            save_row(res, key, row)
            print(key, name, row[name], flush=True)
    if "A2 registered" not in row:
        # a second round: the registration repeated on round 1's motion-compensated images (fewer
        # streaks, motion nearer the truth), the model refitted, A again (chosen on the tuning slices)
        a1 = np.load(os.path.join(cm.CACHE, f"A-registered-{scene}-{pitch:g}-{var}.npy"))
        t0 = time.perf_counter()
        f2, _ = estimate.separable_fields(a1, ref_ij, cm.field_grid(ctx), FLOW)
        t_reg = time.perf_counter() - t0
        model2, _ = mm.fit_motion_model(f2, ctx.pairs, BASIS, cm.field_grid(ctx), ref)
        v = cm.mc_volumes(ctx, rows, model2, bary[0], bary[1], z, cfg)
        np.save(os.path.join(cm.CACHE, f"A2-registered-{scene}-{pitch:g}-{var}.npy"), v)
        row["A2 registered"] = {"mae": cm.mae(ctx, v, tr), "seconds": round(time.perf_counter() - t0, 1),
                                "seconds_registration": round(t_reg, 1),
                                "registration_error": registration_error(ctx, f2, tf, ref)}
        save_row(res, key, row)
        print(key, "A2", row["A2 registered"], flush=True)
    if pitch >= 0.1 and "B registered" not in row:
        t0 = time.perf_counter()
        # the model image's slices: 2 mm apart over the reported range (beyond it the scan does not
        # cover every view; the warp extends the end slices)
        fine_z = np.arange(z.min(), z.max() + 0.01, 2.0)
        rg = mm.FieldGrid.of_slices(ctx.geom.nx, ctx.geom.ny, ctx.geom.voxel_mm, fine_z)
        mref = cm.mc_reference_image(ctx, var, models["registered"], ref, fine_z, 0.1, 0.15, 6, 8.0,
                                     KNOBS["plane_dz_mm"], KNOBS["taper_mm"])
        t_ref = time.perf_counter() - t0
        v, info = cm.correction_volumes(ctx, var, z, models["registered"], mref, rg, bins=tuple(KNOBS["B_state_bins"]))
        row["B registered"] = {"mae": cm.mae(ctx, v, tr), "seconds": round(time.perf_counter() - t0, 1),
                               "seconds_model_image": round(t_ref, 1), **info}
        save_row(res, key, row)
        print(key, "B", row["B registered"], flush=True)
    return row


def save_row(res, key, row):
    res[key] = row
    save(res)


def main():
    res = load()
    res["knobs"] = KNOBS
    res["machine"] = {"cpu": subprocess.run("lscpu | grep 'Model name'", shell=True, capture_output=True,
                                            text=True).stdout.strip(), "platform": platform.platform()}
    loads = res.setdefault("loadavg", [])
    res.setdefault("started", time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()))
    masked_threshold(res)
    KNOBS["mask_threshold_hu"] = res["masked_threshold"]["chosen_hu"]
    static_floor(res)
    cells = [("demo", 0.10, "noise-free", True), ("demo", 0.10, "noisy", True),
             ("demo-hrv", 0.10, "noise-free", False), ("demo-hrv", 0.10, "noisy", False),
             ("demo", 0.02, "noise-free", False), ("demo", 0.02, "noisy", False)]
    for scene, pitch, var, with_true in cells:
        loads.append(open("/proc/loadavg").read().split()[:3])
        cell(res, scene, pitch, var, with_true)
    res["finished"] = time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())
    loads.append(open("/proc/loadavg").read().split()[:3])
    save(res)


if __name__ == "__main__":
    main()
