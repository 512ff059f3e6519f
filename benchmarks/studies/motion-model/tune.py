"""Knob choice for the motion-model study on demo, pitch 0.10, noise-free, on the TUNING slices only
(z = -12, -4, 4, 12 mm: midway between the run's reported slices, never reported).

    python benchmarks/studies/motion-model/tune.py          -> benchmarks/studies/motion-model/tune.json
    python benchmarks/studies/motion-model/tune.py rounds   (after study.py: rounds 2 and 3 of registration)

Each line: a variant (motion source x reconstruction x knobs), its MAE (large, small FOV) on the
tuning slices beside barycentric's, and its seconds. docs/motion-model.md "Knobs".
"""

import json
import os
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)
import common as cm
from demons import DemonsConfig

from clrecon.reconstruction.motion import backproject as mcb
from clrecon.reconstruction.motion import model as mm
from clrecon.reconstruction.motion import registration as reg

OUT = os.path.join(HERE, "tune.json")


def rounds(res):
    """Rounds of registration on the motion-compensated images (A), measured on the tuning slices.

    Round k registers round k-1's A images of the reported slices (made by study.py, cached) and
    reconstructs the tuning slices with the refitted model; round 1 is tune's "registered-ilk A-bary".
    """
    from clrecon.reconstruction.motion import estimate
    ctx = cm.Context("demo", 0.10)
    var, z = "noise-free", ctx.tune_z
    trt = cm.truth(ctx, z)
    g = cm.field_grid(ctx)
    ref = tuple(ctx.pairs[44])
    basis = mm.MotionBasis(resp_degree=1, cardiac_harmonics=2)
    gg = cm.groups_for(ctx, z, 0.0)
    rows = cm.plane_rows(ctx, var, gg.projection, z.min() - 20, z.max() + 20, 2.0)
    bary = cm.bary_slots(ctx, z, rows)
    for k, src in ((2, "A"), (3, "A2")):
        key = f"registered-ilk A-bary round {k}"
        if key in res:
            continue
        prev = np.load(os.path.join(cm.CACHE, f"{src}-registered-demo-0.1-{var}.npy"))
        t0 = time.perf_counter()
        f, _ = estimate.separable_fields(prev, (4, 4), g, reg.FlowConfig(radius=7))
        model, _ = mm.fit_motion_model(f, ctx.pairs, basis, g, ref)
        v = cm.mc_volumes(ctx, rows, model, bary[0], bary[1], z, mcb.MCConfig(taper_mm=2.0))
        res[key] = {"mae": cm.mae(ctx, v, trt), "seconds": round(time.perf_counter() - t0, 1)}
        print(key, res[key], flush=True)
        json.dump(res, open(OUT, "w"), indent=1)


def main():
    ctx = cm.Context("demo", 0.10)
    var = "noise-free"
    z = ctx.tune_z
    trt = cm.truth(ctx, z)
    fp = cm.first_pass(ctx, var, ctx.report_z)
    fpt = cm.first_pass(ctx, var, z)
    res = json.load(open(OUT)) if os.path.exists(OUT) else {}
    res["first_pass"] = {m: cm.mae(ctx, fpt[m], trt) for m in cm.FIRST_PASS}
    ref_ij = (4, 4)
    ref = tuple(ctx.pairs[ref_ij[0] * 10 + ref_ij[1]])
    basis = mm.MotionBasis(resp_degree=1, cardiac_harmonics=2)
    dcfg = DemonsConfig(iterations=(60, 30), shrink=(2, 1), max_step_mm=2.0, field_sigma_mm=4.0, image_sigma_mm=2.0)
    margin, plane_dz, taper = 8.0, 2.0, 2.0
    models = {"true": cm.true_model(ctx, ref, basis)[0]}
    t0 = time.perf_counter()
    models["registered"] = cm.separable_model(ctx, var, fp["barycentric"], ref_ij, dcfg, basis)[0]
    models["registered-ilk"] = cm.separable_model(ctx, var, fp["barycentric"], ref_ij, reg.FlowConfig(radius=7),
                                                  basis)[0]
    res["registration_s"] = time.perf_counter() - t0
    g = cm.groups_for(ctx, z, margin)
    rows = cm.plane_rows(ctx, var, g.projection, z.min() - 20, z.max() + 20, plane_dz)
    bary = cm.bary_slots(ctx, z, rows)
    cand = cm.candidate_rows(ctx, var, z)
    fine_z = np.arange(z.min() - 16, z.max() + 16.01, 2.0)
    rg = mm.FieldGrid.of_slices(ctx.geom.nx, ctx.geom.ny, ctx.geom.voxel_mm, fine_z)
    if sys.argv[1:] == ["rounds"]:
        return rounds(res)
    want = sys.argv[1:] or ["A-bary", "A-k", "B"]
    for src, model in models.items():
        for name in want:
            key = f"{src} {name}"
            if key in res:
                print(key, res[key])
                continue
            t0 = time.perf_counter()
            if name == "A-bary":
                v = cm.mc_volumes(ctx, rows, model, bary[0], bary[1], z, mcb.MCConfig(taper_mm=taper))
            elif name.startswith("A-k"):
                sc, sa, K = {"A-k": (0.1, 0.15, 6), "A-k2": (0.2, 0.3, 9), "A-k3": (0.07, 0.1, 4)}[name]
                sl = cm.kernel_slots(ctx, z, rows, sc, sa, K, margin)
                v = cm.mc_volumes(ctx, rows, model, sl[0], sl[1], z, mcb.MCConfig(taper_mm=taper))
            elif name.startswith("B"):
                sc, sa, K = 0.1, 0.15, 6
                mref = cm.mc_reference_image(ctx, var, model, ref, fine_z, sc, sa, K, margin, plane_dz, taper)
                v, _ = cm.correction_volumes(ctx, var, z, model, mref, rg, bins=(20, 10), cand=cand)
            res[key] = {"mae": cm.mae(ctx, v, trt), "seconds": round(time.perf_counter() - t0, 1)}
            print(key, res[key], "bary", res["first_pass"]["barycentric"], flush=True)
            json.dump(res, open(OUT, "w"), indent=1)


if __name__ == "__main__":
    main()
