"""Is the phantom's true motion a correspondence of its images? Per heart object, on two states.

The registration error of ``mc`` is measured against the analytic phantom's own motion
(:func:`clrecon.simulation.phantoms.motion_field.displacement_fields`: each point moves with the
innermost object holding it, textureless points filled smoothly). This study asks, per object of
the heart, whether that motion maps the target state's image onto the reference's as well as the
registered field does:

- the image residual ``fixed - moving(x + u(x))`` (HU RMS, images clipped to the registration's HU
  window) with u = 0, the registered field (TV-L1, the beat step's registration) and the phantom's
  field;
- the share of the object's points that the phantom's rule carries out of the object at the
  target state (:func:`clrecon.simulation.phantoms.analytic.inside`: another object lies there
  then, e.g. the LV's cut in the RV), and the registration's error on the points it keeps inside
  and on those it carries out;
- the registration's error per object and per component, and the mean displacement, true and
  registered.

    python benchmarks/studies/motion-model/true_field_consistency.py [--voxel 3.0] [--slice 4.0]
        [--nz 16] [--pair 0.8,0.45:0.4,0.45]

Results: docs/results/mc-study.md "Two ground-truth states of the phantom".
"""

from __future__ import annotations

import argparse
import json

import numpy as np
from flow_pairs import phantom_pair

from clrecon.config.overrides import load_scene
from clrecon.core.conventions import voxel_coords
from clrecon.evaluation.motion_model import HEART
from clrecon.reconstruction.motion import flow, registration
from clrecon.reconstruction.motion.estimate import to_reference
from clrecon.reconstruction.motion.model import FieldGrid
from clrecon.simulation.phantom_sources import phantom_from_config
from clrecon.simulation.phantoms.analytic import inside


def rms(a) -> float:
    return round(float(np.sqrt(np.mean(np.square(a)))), 2) if a.size else float("nan")


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--scene", default="demo")
    ap.add_argument("--voxel", type=float, default=3.0)
    ap.add_argument("--slice", type=float, default=4.0)
    ap.add_argument("--nz", type=int, default=16)
    ap.add_argument("--fov", type=float, default=384.0, help="in-plane side of the grid, mm")
    ap.add_argument("--pair", default="0.8,0.45:0.4,0.45", help="reference c,a : target c,a")
    args = ap.parse_args()
    scene = load_scene(args.scene)
    ph = phantom_from_config(scene.phantom)
    n = int(round(args.fov / args.voxel))
    x = voxel_coords(n, args.voxel)
    z = (np.arange(args.nz) - 0.5 * (args.nz - 1)) * args.slice
    (c0, a0), (c1, a1) = (tuple(map(float, s.split(","))) for s in args.pair.split(":"))
    fixed, moving, true, own = phantom_pair(ph, scene.phantom.mu_water_per_mm, x, x, z, (c0, a0), (c1, a1))
    cfg = flow.TVL1Config()
    u = registration.register(fixed, moving, (args.voxel, args.voxel, args.slice), cfg=cfg)
    Z, Y, X = np.meshgrid(z, x, x, indexing="ij")
    pts = np.stack([X, Y, Z], -1)
    objs1 = ph.objects(c1, a1)
    moved = pts + np.moveaxis(true, 0, -1)
    kept = np.zeros(own.shape, bool)
    for i in np.unique(own[own >= 0]):
        m = own == i
        kept[m] = inside(objs1[i], moved[m])
    grid = FieldGrid.of_slices(n, n, args.voxel, z)
    lo, hi = cfg.hu_window
    resid = {name: np.clip(fixed, lo, hi) - np.clip(to_reference(moving, f.astype(np.float32), grid), lo, hi)
             for name, f in (("zero", np.zeros_like(u)), ("registered", u), ("phantom", true))}
    err = np.sqrt(((u - true) ** 2).sum(0))
    rows = []
    names = list(ph.names)
    heart = np.zeros(own.shape, bool)
    for name in HEART:
        if name not in names or not (own == names.index(name)).any():
            continue
        m = own == names.index(name)
        heart |= m
        rows.append({"object": name, "voxels": int(m.sum()),
                     "residual_hu_rms": {k: rms(r[m]) for k, r in resid.items()},
                     "carried_out_share": round(float(1 - kept[m].mean()), 3),
                     "error_mm_rms": rms(err[m]), "error_kept_in_mm": rms(err[m & kept]),
                     "error_carried_out_mm": rms(err[m & ~kept]),
                     "error_xyz_mm_rms": [rms((u - true)[k][m]) for k in range(3)],
                     "mean_true_mm": np.round(true[:, m].mean(1, dtype=np.float64), 2).tolist(),
                     "mean_registered_mm": np.round(u[:, m].mean(1, dtype=np.float64), 2).tolist(),
                     "motion_mm_rms": rms(np.sqrt((true[:, m] ** 2).sum(0)))})
        print(json.dumps(rows[-1]), flush=True)
    print(json.dumps({"heart": {"error_mm_rms": rms(err[heart]), "error_kept_in_mm": rms(err[heart & kept]),
                                "carried_out_share": round(float(1 - kept[heart].mean()), 3),
                                "motion_mm_rms": rms(np.sqrt((true[:, heart] ** 2).sum(0))),
                                "residual_hu_rms": {k: rms(r[heart]) for k, r in resid.items()}},
                      "grid": [args.nz, n, n], "spacing_mm": [args.voxel, args.voxel, args.slice],
                      "pair": args.pair, "registration": str(cfg)}))


if __name__ == "__main__":
    main()
