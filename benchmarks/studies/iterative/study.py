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
(appended to the row's key in study.json, to keep a row of an earlier version of the code),
CORR (0: none; n: the per-bin residual correction below with n SART iterations per bin),
CORR_WIDTH (1.0: the correction kernel's width in bins), CORR_SMOOTH (0: voxels of Gaussian
smoothing of each bin's correction).

The per-bin residual correction (rows with CORR > 0; McKinnon-Bates in spirit, with the motion-
compensated reference as the prior): what the warped reference leaves unexplained in each
motion-state bin's own views, r_b = p_b - A_b W_b f, is reconstructed in that bin's frame by CORR
static SART iterations on the bin's views alone, e_b; a target's volume is W_t f plus the
Gaussian-weighted mean of the e_b of the bins near it in phase space (cardiac distance on the
circle, width CORR_WIDTH bins in each axis; no correction where no bin is near). Each row then
reports both MAEs: without (the plain row) and with the correction.

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
from clrecon.reconstruction.iterative.operators import ConeOperator, backproject_groups, project_groups
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


def bin_corrections(op, proj, X, tg, iters, sc_w, sa_w, smooth):
    """Per target (n_c, n_r, nz, ny, nx) float32 1/mm: the Gaussian-weighted mean of the bins' residual
    images e_b (module docstring; kernel widths ``sc_w`` in cardiac phase, ``sa_w`` in amplitude),
    and the weights' sum per target."""
    grid, nb = op.grid, len(op.bins)
    nc, nr = tg.shape
    acc = np.zeros((nc, nr) + grid.shape, np.float32)
    wsum = np.zeros((nc, nr))
    ref = np.ascontiguousarray(X[0], np.float32)
    t0 = time.perf_counter()
    for b in range(nb):
        parts = op._parts[b]
        rows = np.concatenate([p.rows for p in parts])
        r = proj[rows] - project_groups(op.to_state(ref, op._bin_field(b)), grid, parts, op.rt)
        R = project_groups(np.ones(grid.shape, np.float32), grid, parts, op.rt)
        rinv = np.where(R > 1.0, 1.0 / np.maximum(R, 1e-30), 0.0).astype(np.float32)
        C = backproject_groups((rinv > 0).astype(np.float32), grid, parts, op.rt)
        cinv = np.where(C > 0, 1.0 / np.maximum(C, 1e-30), 0.0).astype(np.float32)
        e = np.zeros(grid.shape, np.float32)
        for k in range(iters):
            d = r - project_groups(e, grid, parts, op.rt) if k else r
            e += cinv * backproject_groups(d * rinv, grid, parts, op.rt)
        if smooth:
            e = scipy.ndimage.gaussian_filter(e, smooth, mode="nearest").astype(np.float32)
        cb, ab = op.bins.states[b]
        for i, c in enumerate(tg.cardiac):
            for j, a in enumerate(tg.resp):
                dc = (cb - c + 0.5) % 1.0 - 0.5
                k = float(np.exp(-0.5 * ((dc / sc_w) ** 2 + ((ab - a) / sa_w) ** 2)))
                if k > 1e-3:
                    acc[i, j] += k * e
                    wsum[i, j] += k
        if b % 20 == 0:
            print(f"correction: bin {b + 1}/{nb}, {time.perf_counter() - t0:.0f} s")
    for i in range(nc):
        for j in range(nr):
            acc[i, j] = acc[i, j] / wsum[i, j] if wsum[i, j] > 0.1 else 0.0
    return acc, wsum


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
    hist = None

    def solve():
        nonlocal hist
        x, hist = os_sart(op, lambda s: proj[op.subset_rows(s)], x0, SARTConfig(epochs=epochs, decay=0.3), log=print)
        return x
    # the solution is cached with the row's settings (a CORR row reuses its plain row's solve)
    X = cached("X", (row, pitch, var, epochs, dz, fine, nbc, nbr, clrecon.__version__), solve)
    t_solve = time.perf_counter() - t0 - t_setup
    corr, width, smooth = env("CORR", 0), env("CORR_WIDTH", 1.0), env("CORR_SMOOTH", 0.0)
    E = None
    if corr and not static:
        t1 = time.perf_counter()
        E, wsum = bin_corrections(op, proj, X, tg, corr, width / nbc, width / nbr, smooth)
        t_corr = time.perf_counter() - t1
    out = np.empty((nc, nr, len(z), r.ny, r.nx), np.float32)
    out_c = np.empty_like(out) if E is not None else None
    for i, c in enumerate(tg.cardiac):
        for j, a in enumerate(tg.resp):
            vol = X if static else op.state_volume(X, c, a)
            out[i, j] = mu_to_hu(to_slices(vol, grid, z, r.nx, r.voxel_mm), sc.phantom.mu_water_per_mm)
            if E is not None:
                out_c[i, j] = mu_to_hu(to_slices(vol + E[i, j], grid, z, r.nx, r.voxel_mm),
                                       sc.phantom.mu_water_per_mm)
    m = table2(out, gt, MetricsConfig.from_scene(sc))
    key = f"{row} p{pitch:g} {var} e{epochs} dz{dz:g} fine{fine}" + ("" if static else f" bins{nbc}x{nbr}") \
        + os.environ.get("KEYTAG", "")
    if hist is None and key in res:  # a cached solve: the row's own entry (with its history) stays
        res[key] = dict(res[key], mae_hu=[round(m["large"]["mae_hu"], 2), round(m["small"]["mae_hu"], 2)])
    else:
        res[key] = {"mae_hu": [round(m["large"]["mae_hu"], 2), round(m["small"]["mae_hu"], 2)],
                    "setup_s": round(t_setup, 1), "solve_s": round(t_solve, 1), "history": hist.as_dict() if hist else "cached solve",
                    "grid": list(grid.shape), "voxel_mm": grid.voxel_mm, "dz_mm": dz,
                    "cpu": platform.processor() or platform.machine(), "load_1min": os.getloadavg()[0],
                    "date": time.strftime("%Y-%m-%d")}
    if E is not None:
        mc_ = table2(out_c, gt, MetricsConfig.from_scene(sc))
        ckey = key + f" corr{corr} w{width:g} s{smooth:g}"
        res[ckey] = dict(res[key], mae_hu=[round(mc_["large"]["mae_hu"], 2), round(mc_["small"]["mae_hu"], 2)],
                         plain_mae_hu=res[key]["mae_hu"], correction_s=round(t_corr, 1),
                         weight_sum=[round(float(wsum.min()), 3), round(float(wsum.max()), 3)])
        print(ckey, res[ckey]["mae_hu"], f"correction {t_corr:.0f} s")
    print(key, res[key]["mae_hu"], f"setup {t_setup:.0f} s solve {t_solve:.0f} s")
    json.dump(res, open(OUT, "w"), indent=1)


if __name__ == "__main__":
    main(sys.argv[1:])
