"""The consistency check (clrecon/evaluation/consistency.py) again on a finished run folder, with the
ground truth's volumes as a pseudo-method beside the run's, and the study's variants: rows band-limited
along the channels (``--sigma``, Gaussian, in channels), only rows near their slice (``--max-dz``), only
rows barycentric did not use (``--unused``), and the measured rows replaced by ideal in-plane rows of
the phantom at each row's own state (``--ideal``: the check without the rows' data model, which every
method shares; the volumes are still the ones made from the measured rows), and only rows whose state
(c, a) lies within a share of the target lattice's spacing of a target (``--near F``: the prediction of
such a row is nearly one target's image, so the lattice's bilinear interpolation between targets,
whose images a method may have made sharp, plays no part), and other slices than the check's
evenly spread ones (``--slices 30,50,80,100``: indices into the run's slices). Prints each method's
residual beside its MAE. docs/consistency.md "Did it help? A truth-free check".

    python benchmarks/studies/consistency/rerun.py /tmp/run --scene demo [--sigma 2] [--max-dz 2] [--unused] [--ideal] [--near 0.1] [--slices 30,50] [--max-slices 4]
"""

import argparse
import json
import time

import data_model  # this folder's study (on sys.path when run as a script): the ideal rows
import h5py
import numpy as np
from scipy.ndimage import gaussian_filter1d

from clrecon.config.scene import load_scene
from clrecon.evaluation import consistency as cs
from clrecon.evaluation import groundtruth as gt
from clrecon.evaluation import truth_free
from clrecon.outputs.volumes import recon_path
from clrecon.reconstruction import reconstruct as rc
from clrecon.scan import table as geometry
from clrecon.simulation.store import ProjectionStore, default_cache_dir


def ideal_read(scene, cfg, table, zs):
    """A stand-in for ``truth_free.read_rows`` that returns, for every variant, the ideal in-plane
    rows of the phantom at each sampled row's own state (:func:`data_model.ideal_rows`; no noise: no
    variance)."""
    ph = gt.GroundTruthConfig.from_scene(scene).source()

    def read(store, groups, flat, sc, variants, noise, rt=None):
        ideal = data_model.ideal_rows(ph, cfg.scanner.detector_model, cfg.fbp, groups, flat, table, zs)[0]
        return {v: (ideal, None) for v in variants}

    return read


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("run")
    ap.add_argument("--scene", default="demo")
    ap.add_argument("--sigma", type=float, default=0.0)
    ap.add_argument("--max-dz", type=float, default=None)
    ap.add_argument("--unused", action="store_true")
    ap.add_argument("--ideal", action="store_true", help="ideal in-plane rows of the phantom instead of the measured rows")
    ap.add_argument("--slices", default=None, help="comma list of slice indices to sample instead of the check's")
    ap.add_argument("--max-slices", type=int, default=cs.ConsistencyConfig.max_slices,
                    help="how many evenly spread slices the check samples")
    ap.add_argument("--near", type=float, default=None,
                    help="only rows within this share of the lattice spacing of a target, in c and in a")
    args = ap.parse_args()
    scene = load_scene(args.scene)
    res = json.load(open(f"{args.run}/results.json"))
    cfg = rc.ReconstructionConfig.from_scene(scene)
    req = res["request"]
    targets = rc.Targets(cardiac=tuple(req["targets"]["cardiac"]), resp=tuple(req["targets"]["resp"]))
    slices_z = np.array(req["slices_z_mm"])
    if args.sigma > 0:  # the same Gaussian on the rows and on the predictions
        plain = cs.residual

        def residual(rows, pred, *a, **k):
            smooth = lambda x: gaussian_filter1d(np.asarray(x, np.float64), args.sigma, axis=1, mode="nearest")  # noqa: E731
            return plain(smooth(rows), smooth(pred), *a, **k)

        cs.residual = residual
    if args.near is not None:  # the rows' states, seen by the prediction; the masks keep the near ones
        plain_pred, plain_res = cs.predicted_rows, cs.residual
        C, R = np.asarray(targets.cardiac), np.asarray(targets.resp)
        dc = np.min(np.diff(np.sort(np.r_[C, C[0] + 1]))) if C.size > 1 else 1.0
        da = np.min(np.diff(np.sort(R))) if R.size > 1 else 1.0
        near = {}

        def predicted(vol, cardiac, resp, row_slice, row_view, row_c, row_a, **k):
            gc = np.abs((np.asarray(row_c)[:, None] - C[None] + 0.5) % 1.0 - 0.5).min(1) <= args.near * dc
            ga = np.abs(np.asarray(row_a)[:, None] - R[None]).min(1) <= args.near * da
            near["rows"] = gc & ga
            return plain_pred(vol, cardiac, resp, row_slice, row_view, row_c, row_a, **k)

        def residual(rows, pred, masks, *a, **k):
            return plain_res(rows, pred, {r: m & near["rows"][:, None] for r, m in masks.items()}, *a, **k)

        cs.predicted_rows, cs.residual = predicted, residual
    if args.slices:
        chosen = slices_z[[int(x) for x in args.slices.split(",")]]
        truth_free.sample_slices = lambda z, n: np.asarray(chosen, np.float64)
    f = h5py.File(f"{args.run}/volumes.h5", "r")
    methods = [m for m in req["methods"] if m in ("barycentric", "local_linear", "nearest", "mc")] + ["groundtruth"]
    ccfg = cs.ConsistencyConfig(max_slices=args.max_slices, max_dz_mm=args.max_dz, unused_only=args.unused)
    for pk in res["metrics"]:
        pitch = float(pk[1:])
        table = geometry.projection_table(scene, pitch)
        store = ProjectionStore.open(scene, pitch, cache_dir=default_cache_dir(), table=table)
        if args.ideal:
            cs.truth_free.read_rows = ideal_read(scene, cfg, geometry.usable_table(scene, table)[0],
                                                 truth_free.sample_slices(slices_z, ccfg.max_slices))

        def volumes(v, m, s, pk=pk):
            d = f["groundtruth" if m == "groundtruth" else recon_path(pk, v, m)]
            if d.ndim == 3:  # one target (a motionless scene): (S, ny, nx)
                return np.asarray(d[list(s)], np.float32)[None, None]
            return np.asarray(d[:, :, list(s)], np.float32)

        t = time.time()
        ent = cs.check(store, geometry.usable_table(scene, table)[0], slices_z, cfg, targets, req["variants"],
                       tuple(scene.recon.small_fov_mm), volumes, methods, ccfg)
        n_near = "" if args.near is None else f" ({int(near['rows'].sum())} near a target)"
        print(f"== {pk} sigma {args.sigma} max_dz {args.max_dz} unused {args.unused} ideal {args.ideal} near {args.near} slices {args.slices}: "
              f"{ent['n_rows']} rows{n_near}, "
              f"{time.time() - t:.0f} s")
        for v, bym in ent["residual"].items():
            met = res["metrics"][pk][v]
            for m, e in bym.items():
                ab = e.get("against_barycentric")
                z = (f"z {ab['all']['z']:+6.1f} / {ab['heart']['z']:+6.1f} slices -{ab['all']['slices_lower']}"
                     f"/+{ab['all']['slices_higher']}" if ab else " " * 29)
                mae = f"{met[m]['large']['mae_hu']:.1f} / {met[m]['small']['mae_hu']:.1f}" if m in met else "--"
                print(f"{v:10s} {m:13s} all {e['rms_hu_mm']:7.1f} heart {e['heart_rms_hu_mm']:7.1f} {z}  "
                      f"noise floor {e.get('noise_floor_hu_mm', 0):5.1f}  MAE {mae}  per slice "
                      + " ".join(f"{x:.0f}" for x in e["per_slice_rms_hu_mm"]))
            print("  ", ent["verdict"][v]["text"])


if __name__ == "__main__":
    main()
