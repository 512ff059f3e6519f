"""With the truth: each method's image at a target reprojected against the ideal in-plane sinogram of
the phantom at that target's state (the projection-domain error the truth-free check cannot see), on
one slice and every 4th view. docs/consistency.md "Did it help? A truth-free check".

    python benchmarks/studies/consistency/reprojection.py /tmp/run --scene demo
"""

import argparse
import json

import h5py
import numpy as np

from clrecon.config.scene import load_scene
from clrecon.evaluation import consistency as cs
from clrecon.evaluation import groundtruth as gt
from clrecon.outputs.volumes import recon_path
from clrecon.reconstruction import reconstruct as rc


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("run")
    ap.add_argument("--scene", default="demo")
    ap.add_argument("--slice", type=int, default=5)
    args = ap.parse_args()
    scene = load_scene(args.scene)
    res = json.load(open(f"{args.run}/results.json"))
    cfg = rc.ReconstructionConfig.from_scene(scene)
    g, det = cfg.fbp, cfg.scanner.detector_model
    gcfg = gt.GroundTruthConfig.from_scene(scene)
    ph = gcfg.source()
    req = res["request"]
    z = np.array(req["slices_z_mm"])[args.slice:args.slice + 1]
    C, R = req["targets"]["cardiac"], req["targets"]["resp"]
    views = np.arange(0, g.n_views, 4)
    circle = cs.channels_through_circle(det, g, views, cfg.object_radius_mm)
    scale = 1000 / cfg.mu_water_per_mm
    names = ["groundtruth"] + [recon_path(pk, "noise-free", m) for pk in res["metrics"]
                               for m in ("barycentric", "local_linear", "nearest", "mc") if m in req["methods"]]
    picks = [(0, len(R) // 4), (len(C) // 2, len(R) // 2), (len(C) - 1, 3 * len(R) // 4)]
    with h5py.File(f"{args.run}/volumes.h5", "r") as f:
        print(f"slice z {z[0]:g} mm; targets (c, a): " + ", ".join(f"({C[i]:g}, {R[j]:g})" for i, j in picks))
        for name in names:
            out = []
            for i, j in picks:
                ideal = gt.groundtruth_sinograms(gcfg, ph, C[i], R[j], z)[0][views]
                mu = cfg.mu_water_per_mm * (1 + np.asarray(f[name][i, j, args.slice], np.float64) / 1000)
                p = cs.inplane_projections(mu[None], g.voxel_mm, det, g, np.zeros(views.size, int), views)
                out.append(np.sqrt(((ideal - p)[circle] ** 2).mean()) * scale)
            print(f"{name:42s} " + " ".join(f"{x:7.0f}" for x in out) + " HU mm")


if __name__ == "__main__":
    main()
