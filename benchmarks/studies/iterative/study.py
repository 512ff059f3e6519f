"""Issue 42's first study: the iterative reconstruction through the phantom's TRUE motion (docs/results/iterative-study.md).

    PYTHONPATH=. python benchmarks/studies/iterative/study.py ROW [ROW ...]   -> benchmarks/studies/iterative/study.json

Rows (each measured alone, every other setting at its default):
  static        demo with both motions off: OS-SART on the cone-beam rows (no motion model)
  pull          demo, true motion model, intensity-preserving warp, no density term
  pull+density  ... with the density term (attenuation linear in the amplitude)
  push          mass-preserving warp (W_u^T), no density term
  push+density  mass-preserving warp with the density term
Variants by environment: PITCH (0.1), VAR (noise-free | noisy), EPOCHS (3), DZ (2 mm plane
spacing), FINE (1: the reconstruction's voxel; 2: half of it in-plane), BINS ("20x10"), KEYTAG
(appended to the row's key in study.json, to keep a row of an earlier version of the code).

The true motion model is the one the motion-model study gives `mc` ("mc with the true motion"):
the phantom's own displacement from the reference state (0.8, 0.45) to the 50 targets
(textureless points filled smoothly, clrecon.simulation.phantoms.motion_field), fitted to the
model's basis (amplitude degree 1, two cardiac harmonics), here on the iterative volume's grid.
MAE as clrecon.evaluation.metrics over the run's 16 slices and every target (large FOV = the
reconstruction circle, small FOV = the heart box) against the run's ground truth CT.
Arrays are cached under $ITER_STUDY_CACHE (default /tmp/clrecon-iter-study).
"""

import hashlib
import json
import os
import platform
import sys
import time

import numpy as np
import scipy.ndimage

import clrecon
from clrecon.core.conventions import mu_to_hu, voxel_coords
from clrecon.evaluation.groundtruth import GroundTruthConfig, groundtruth_volumes
from clrecon.evaluation.metrics import MetricsConfig, table2
from clrecon.reconstruction import reconstruct as rc
from clrecon.reconstruction.iterative import geometry as geo
from clrecon.reconstruction.iterative.motion_operator import MotionConeOperator
from clrecon.reconstruction.iterative.operators import ConeOperator
from clrecon.reconstruction.iterative.sart import SARTConfig, os_sart
from clrecon.reconstruction.iterative.state_bins import state_bins
from clrecon.reconstruction.motion import model as mm
from clrecon.scan.table import projection_table
from clrecon.simulation.phantom_sources import phantom_from_config
from clrecon.simulation.phantoms import motion_field
from clrecon.simulation.simulate import simulate

HERE = os.path.dirname(os.path.abspath(__file__))
OUT = os.path.join(HERE, "study.json")
CACHE = os.environ.get("ITER_STUDY_CACHE", "/tmp/clrecon-iter-study")
REFERENCE = (0.8, 0.45)
BASIS = mm.MotionBasis(resp_degree=1, cardiac_harmonics=2)


def env(name, default):
    return type(default)(os.environ.get(name, default))


def cached(name, parts, fn):
    os.makedirs(CACHE, exist_ok=True)
    key = hashlib.sha1(json.dumps(parts, default=str).encode()).hexdigest()[:16]
    path = os.path.join(CACHE, f"{name}-{key}.npy")
    if os.path.exists(path):
        return np.load(path)
    out = fn()
    np.save(path, out)
    return out


def to_slices(vol, grid, z, nx, voxel_mm):
    """Trilinear samples of a grid volume at the run's slice planes and in-plane voxel centres."""
    xo = voxel_coords(nx, voxel_mm)
    iz = (np.asarray(z) - grid.z0_mm) / grid.dz_mm
    ixy = (xo - grid.origin_mm[0]) / grid.voxel_mm
    Z, Y, X = np.meshgrid(iz, ixy, ixy, indexing="ij")
    return scipy.ndimage.map_coordinates(np.asarray(vol, np.float64), [Z, Y, X], order=1, mode="nearest")


def main(rows):
    for row in rows:
        run_row(row)


def run_row(row):
    pitch, var, epochs, dz, fine = env("PITCH", 0.1), env("VAR", "noise-free"), env("EPOCHS", 3), env("DZ", 2.0), \
        env("FINE", 1)
    nbc, nbr = (int(v) for v in env("BINS", "20x10").split("x"))
    res = json.load(open(OUT)) if os.path.exists(OUT) else {}
    static = row == "static"
    over = {"phantom.cardiac_motion": False, "phantom.respiratory_motion": False, "name": "demo-static"} \
        if static else {}
    sc = clrecon.load_scene("demo", **over)
    cfg = rc.ReconstructionConfig.from_scene(sc)
    tg = rc.Targets(cardiac=(0.0,), resp=(0.05,)) if static else \
        rc.Targets(cardiac=sc.cardiac_targets, resp=sc.resp_targets)
    z = rc.slice_positions(sc)
    gcfg = GroundTruthConfig.from_scene(sc)
    nc, nr = tg.shape

    def truth():
        out = np.empty((nc, nr, len(z), sc.recon.ny, sc.recon.nx), np.float32)
        for i, j, v in groundtruth_volumes(gcfg, z, tg):
            out[i, j] = v
        return out
    gt = cached("truth", (sc.name, list(map(float, z)), tg.pairs.tolist()), truth)
    table = projection_table(sc, pitch)
    store = simulate(sc, pitch, progress=False)
    proj = store.read(0, len(table), noisy=(var == "noisy"))
    r = sc.recon
    grid = geo.volume_grid(sc.scanner, r.nx * fine, r.ny * fine, r.voxel_mm / fine, table.source_z_mm,
                           cfg.object_radius_mm, dz)
    groups = geo.view_groups(sc.scanner, table)
    t0 = time.perf_counter()
    if static:
        op = ConeOperator(grid, groups, env("NSUB", 120))
    else:
        # the true fields on the reconstruction's in-plane grid and the volume's planes (the
        # operator resamples the model to a finer volume)
        fg = mm.FieldGrid(nx=r.nx, ny=r.ny, nz=grid.nz, voxel_mm=r.voxel_mm, z0_mm=grid.z0_mm, dz_mm=grid.dz_mm)
        x, y, zz = fg.coords()
        ph = phantom_from_config(sc.phantom)
        tf = cached("truefield", (sc.name, fg.shape, fg.voxel_mm, fg.z0_mm, fg.dz_mm, REFERENCE),
                    lambda: motion_field.displacement_fields(ph, x, y, zz, REFERENCE, tg.pairs))
        model, _ = mm.fit_motion_model(tf, tg.pairs, BASIS, fg, REFERENCE)
        del tf
        bins = state_bins(table.state_cardiac, table.state_resp, nbc, nbr)
        warp_mode = row.split("+")[0]
        op = MotionConeOperator(grid, groups, bins, model, warp_mode=warp_mode, density=row.endswith("+density"),
                                mu_water_per_mm=sc.phantom.mu_water_per_mm)
    t_setup = time.perf_counter() - t0
    x0 = np.zeros(op.unknown_shape, np.float32)
    X, hist = os_sart(op, lambda s: proj[op.subset_rows(s)], x0, SARTConfig(epochs=epochs, decay=0.3), log=print)
    t_solve = time.perf_counter() - t0 - t_setup
    out = np.empty((nc, nr, len(z), r.ny, r.nx), np.float32)
    for i, c in enumerate(tg.cardiac):
        for j, a in enumerate(tg.resp):
            vol = X if static else op.state_volume(X, c, a)
            out[i, j] = mu_to_hu(to_slices(vol, grid, z, r.nx, r.voxel_mm), sc.phantom.mu_water_per_mm)
    m = table2(out, gt, MetricsConfig.from_scene(sc))
    key = f"{row} p{pitch:g} {var} e{epochs} dz{dz:g} fine{fine}" + ("" if static else f" bins{nbc}x{nbr}") \
        + os.environ.get("KEYTAG", "")
    res[key] = {"mae_hu": [round(m["large"]["mae_hu"], 2), round(m["small"]["mae_hu"], 2)],
                "setup_s": round(t_setup, 1), "solve_s": round(t_solve, 1), "history": hist.as_dict(),
                "grid": list(grid.shape), "voxel_mm": grid.voxel_mm, "dz_mm": dz,
                "cpu": platform.processor() or platform.machine(), "load_1min": os.getloadavg()[0],
                "date": time.strftime("%Y-%m-%d")}
    print(key, res[key]["mae_hu"], f"setup {t_setup:.0f} s solve {t_solve:.0f} s")
    json.dump(res, open(OUT, "w"), indent=1)
    np.save(os.path.join(CACHE, f"X-{row}.npy"), X)


if __name__ == "__main__":
    main(sys.argv[1:])
