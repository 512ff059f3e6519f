"""How well the forward model can explain the data: the residual of the phantom itself through it.

    PYTHONPATH=. python benchmarks/studies/iterative/forward_model.py   -> prints, and adds "forward_model" to study.json

The voxelised phantom at the model's reference state (2x2x2 sub-samples per voxel) is pushed
through mcir's forward model with the phantom's true motion (pull warp by the inverse of the
model fitted to the true fields, the study's model) and projected on every view of demo p0.10
(noise-free), and its relative residual ||p - A W f|| / ||p|| is compared with
- the static scene: the static phantom voxelised and projected (no warp): the voxel basis alone;
- per-view states voxelised exactly (no warp, no model, no bins): each bin's own phantom;
- the warp with 20 x 10 and 40 x 20 bins, and with the phantom's lung density change added as
  the density term (lung voxels of the reference, -80 HU per unit of amplitude);
and (FINE=2) all of it on half the reconstruction's voxel in-plane; (FILL=0) with the phantom's own
rule everywhere (each point moves with the object that holds it, air stays) instead of the smooth
fill of its textureless regions.
What this separates: the voxel basis, the warp's interpolation and model, the binning.
"""

import json
import os
import time

import numpy as np

import clrecon
from clrecon.reconstruction import reconstruct as rc
from clrecon.reconstruction.iterative import geometry as geo
from clrecon.reconstruction.iterative.motion_operator import MotionConeOperator
from clrecon.reconstruction.iterative.operators import project_groups, split_groups
from clrecon.reconstruction.iterative.state_bins import state_bins
from clrecon.reconstruction.motion import model as mm
from clrecon.scan.table import projection_table
from clrecon.simulation.phantom_sources import phantom_from_config
from clrecon.simulation.phantoms import motion_field
from clrecon.simulation.simulate import simulate

HERE = os.path.dirname(os.path.abspath(__file__))
OUT = os.path.join(HERE, "study.json")
REFERENCE = (0.8, 0.45)


def rel(p, q):
    return float(np.sqrt(np.sum((p.astype(np.float64) - q) ** 2) / np.sum(p.astype(np.float64) ** 2)))


def main():
    fine = int(os.environ.get("FINE", 1))
    fill = os.environ.get("FILL", "1") != "0"
    out = {}
    for static in (True, False):
        over = {"phantom.cardiac_motion": False, "phantom.respiratory_motion": False, "name": "demo-static"} \
            if static else {}
        sc = clrecon.load_scene("demo", **over)
        cfg = rc.ReconstructionConfig.from_scene(sc)
        table = projection_table(sc, 0.1)
        proj = simulate(sc, 0.1, progress=False).read(0, len(table))
        r = sc.recon
        grid = geo.volume_grid(sc.scanner, r.nx * fine, r.ny * fine, r.voxel_mm / fine, table.source_z_mm,
                               cfg.object_radius_mm, 2.0)
        groups = geo.view_groups(sc.scanner, table)
        ph = phantom_from_config(sc.phantom)
        x, y, z = grid.coords()
        if static:
            f = ph.voxelise(0.0, 0.0, x, y, z, supersample=2).astype(np.float32)
            out["static voxelised"] = rel(proj, project_groups(f, grid, groups))
            print(out)
            continue
        tg = rc.Targets(cardiac=sc.cardiac_targets, resp=sc.resp_targets)
        # the true fields on the reconstruction's in-plane grid (the operator resamples the model)
        fg = mm.FieldGrid(nx=r.nx, ny=r.ny, nz=grid.nz, voxel_mm=r.voxel_mm, z0_mm=grid.z0_mm, dz_mm=grid.dz_mm)
        tf = motion_field.displacement_fields(ph, *fg.coords(), REFERENCE, tg.pairs, fill_textureless=fill)
        model, _ = mm.fit_motion_model(tf, tg.pairs, mm.MotionBasis(resp_degree=1, cardiac_harmonics=2), fg,
                                       REFERENCE)
        del tf
        fref = ph.voxelise(*REFERENCE, x, y, z, supersample=2).astype(np.float32)
        mw = sc.phantom.mu_water_per_mm
        # lung parenchyma of the reference (-900..-700 HU: the phantom's lung is -760..-840) darkens
        # by 80 HU per unit of amplitude (phantom-and-signals: -760 HU at end-exhale, -840 at end-inhale)
        lung, dmu = (mw * 0.1, mw * 0.3), -mw * 0.080
        for nb in ((20, 10), (40, 20)) if fine == 1 else ((20, 10),):
            t0 = time.perf_counter()
            bins = state_bins(table.state_cardiac, table.state_resp, *nb)
            op = MotionConeOperator(grid, groups, bins, model, warp_mode="pull", density=False)
            pred = np.empty_like(proj)
            exact = np.empty_like(proj) if nb == (20, 10) else None
            for b in range(len(bins)):
                rows = bins.members[b]
                parts = split_groups(groups, rows)
                ff = op.to_state(fref, op.field(*bins.states[b]))
                pred[rows] = project_groups(ff, grid, parts)
                if exact is not None:   # the phantom posed at the bin's state: no warp, no model
                    fb = ph.voxelise(*bins.states[b], x, y, z, supersample=2).astype(np.float32)
                    exact[rows] = project_groups(fb, grid, parts)
            out[f"pull warp of the reference, true-motion model, bins {nb[0]}x{nb[1]}"] = rel(proj, pred)
            if nb == (20, 10):   # with the phantom's own lung density change as the density term
                d = np.where((fref > lung[0]) & (fref < lung[1]), dmu, 0.0).astype(np.float32)
                for b in range(len(bins)):
                    rows = bins.members[b]
                    ff = op.to_state(fref + (bins.states[b][1] - REFERENCE[1]) * d, op.field(*bins.states[b]))
                    pred[rows] = project_groups(ff, grid, split_groups(groups, rows))
                out["pull warp + the phantom's lung density change, bins 20x10"] = rel(proj, pred)
            if exact is not None:
                out["each bin's state voxelised (no warp), bins 20x10"] = rel(proj, exact)
            print(out, f"{time.perf_counter() - t0:.0f} s")
    res = json.load(open(OUT)) if os.path.exists(OUT) else {}
    key = f"forward_model voxel {sc.recon.voxel_mm / fine:g} mm" + ("" if fill else " unfilled fields")
    res[key] = {k: round(v, 5) for k, v in out.items()}
    json.dump(res, open(OUT, "w"), indent=1)


if __name__ == "__main__":
    main()
