"""Registration of pairs with known motion: Lucas-Kanade (scikit-image) against TV-L1 (OpenCL).

Two ground-truth states of the analytic phantom (voxelised, noise-free) on a scene's grid (or a
finer one), registered fixed = reference state, moving = target state; the error against the
phantom's own motion (:func:`clrecon.simulation.phantoms.motion_field.displacement_fields`, the
definition of ``clrecon.evaluation.motion_model.registration_error``) in the heart and in the body
outside the lungs: RMS and 95th percentile (mm), beside the true motion's RMS.

    python benchmarks/studies/motion-model/flow_pairs.py [--scene demo] [--voxel 3.0] [--slice 4.0]
        [--nz 16] [--nxy 128] [--pairs 0.8,0.45:0.3,0.95 ...] [--methods lk,tvl1]
"""

from __future__ import annotations

import argparse
import json
import resource
import time

import numpy as np

from clrecon.config.overrides import load_scene
from clrecon.core.conventions import mu_to_hu, voxel_coords
from clrecon.evaluation.motion_model import HEART, LUNGS
from clrecon.reconstruction.motion import flow, registration
from clrecon.simulation.phantom_sources import phantom_from_config
from clrecon.simulation.phantoms import motion_field


def errors(u, true, heart, body):
    e = np.sqrt(((u - true) ** 2).sum(0))
    t = np.sqrt((true.astype(np.float64) ** 2).sum(0))
    out = {}
    for name, m in (("heart", heart), ("body_outside_lungs", body)):
        out[name] = {"rms_mm": round(float(np.sqrt((e[m] ** 2).mean())), 3),
                     "p95_mm": round(float(np.percentile(e[m], 95)), 3),
                     "true_motion_rms_mm": round(float(np.sqrt((t[m] ** 2).mean())), 3)}
    return out


def phantom_pair(phantom, mu_water_per_mm, x, y, z, state0, state1):
    """Two noise-free states of ``phantom`` voxelised on the grid (x, y, z) mm (3^3 sub-samples):
    (fixed at ``state0``, moving at ``state1``, HU float32 (nz, ny, nx); the phantom's own motion from
    the first to the second, (3, nz, ny, nx) mm; the owner of each voxel centre at ``state0``)."""
    fixed, moving = (mu_to_hu(phantom.voxelise(c, a, x, y, z, supersample=3), mu_water_per_mm).astype(np.float32)
                     for c, a in (state0, state1))
    true = motion_field.displacement_fields(phantom, x, y, z, state0, [state1])[0]
    Z, Y, X = np.meshgrid(z, y, x, indexing="ij")
    return fixed, moving, true, motion_field.owner(phantom, np.stack([X, Y, Z], -1), *state0)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--scene", default="demo")
    ap.add_argument("--nxy", type=int, default=128)
    ap.add_argument("--voxel", type=float, default=3.0)
    ap.add_argument("--nz", type=int, default=16)
    ap.add_argument("--slice", type=float, default=4.0)
    ap.add_argument("--pairs", nargs="+", default=["0.8,0.45:0.3,0.95", "0.8,0.45:0.0,0.05", "0.8,0.45:0.4,0.45"])
    ap.add_argument("--methods", default="lk,tvl1")
    ap.add_argument("--tvl1", default="{}", help="TVL1Config keys as JSON")
    args = ap.parse_args()
    scene = load_scene(args.scene)
    phantom = phantom_from_config(scene.phantom)
    x = voxel_coords(args.nxy, args.voxel)
    y = voxel_coords(args.nxy, args.voxel)
    z = (np.arange(args.nz) - 0.5 * (args.nz - 1)) * args.slice
    spacing = (args.voxel, args.voxel, args.slice)
    cfgs = {"lk": registration.FlowConfig(radius=7), "tvl1": flow.TVL1Config(**json.loads(args.tvl1))}
    rows = []
    for pair in args.pairs:
        (c0, a0), (c1, a1) = (tuple(map(float, s.split(","))) for s in pair.split(":"))
        *vols, true, own = phantom_pair(phantom, scene.phantom.mu_water_per_mm, x, y, z, (c0, a0), (c1, a1))
        names = phantom.names
        heart = np.isin(own, [names.index(n) for n in HEART if n in names])
        body = (own >= 0) & ~np.isin(own, [names.index(n) for n in LUNGS if n in names])
        row = {"pair": pair, "zero_field": errors(np.zeros_like(true), true, heart, body)}
        for name in args.methods.split(","):
            t0 = time.perf_counter()
            u = registration.register(vols[0], vols[1], spacing, cfg=cfgs[name])
            row[name] = errors(u, true, heart, body) | {"seconds": round(time.perf_counter() - t0, 2)}
        rows.append(row)
        print(json.dumps(row), flush=True)
    print(json.dumps({"grid": [args.nz, args.nxy, args.nxy], "spacing_mm": spacing, "tvl1": str(cfgs["tvl1"]),
                      "peak_rss_gb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20, 2)}))


if __name__ == "__main__":
    main()
