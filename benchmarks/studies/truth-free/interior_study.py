"""Adds the interior scheme's CV errors to the trust study's cases (same scans, slices, targets, store)."""

import json
import os
import time

import numpy as np

import clrecon
from benchmarks.truth_free_trust import CASES
from clrecon.evaluation import truth_free as tf
from clrecon.pipeline.run import resolve_targets
from clrecon.pipeline.variants import noise_variants
from clrecon.reconstruction import reconstruct as rc
from clrecon.scan.table import projection_table
from clrecon.simulation import simulate

cfgtf = tf.TruthFreeConfig(schemes=("interior",), image_fold=False, choose_by=("interior", "heart"))
out = {}
for name in ("demo", "demo-hrv", "paper-p010"):
    scene_name, sl, card, resp = CASES[name]
    sc = clrecon.load_scene(scene_name)
    cfg = rc.ReconstructionConfig.from_scene(sc)
    targets = resolve_targets(sc, card, resp)
    zs = rc.slice_positions(sc, sl)
    for pitch in sc.scan.pitches:
        t0 = time.time()
        table = projection_table(sc, pitch)
        need = np.zeros(len(table), bool)
        need[tf.needed_projections(cfg, table, zs, cfgtf)] = True
        store = simulate.simulate(sc, pitch, needed=need, cache_dir="/tmp/tf/cache", progress=False)
        r = tf.cross_validate(store, table, zs, cfg, targets, noise_variants(sc), tuple(sc.recon.small_fov_mm), cfgtf)
        out[f"{name}/p{pitch:.3f}".replace("p0.1", "p0.1").replace("p0.0", "p0.0")] = r
        print(name, pitch, round(time.time() - t0), r["folds"], flush=True)
json.dump(
    {"cases": out, "load": os.getloadavg(), "date": time.strftime("%Y-%m-%d %H:%M", time.gmtime())},
    open("benchmarks/studies/truth-free/interior.json", "w"),
    indent=1,
)
