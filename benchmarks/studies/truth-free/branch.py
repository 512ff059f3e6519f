import numpy as np

import clrecon
from clrecon.evaluation import truth_free as tf
from clrecon.reconstruction import reconstruct as rc
from clrecon.reconstruction.interpolation import weights as iw
from clrecon.scan.table import projection_table

for name in ("demo", "demo-hrv"):
    sc = clrecon.load_scene(name)
    cfg = rc.ReconstructionConfig.from_scene(sc)
    targets = rc.Targets(cardiac=sc.cardiac_targets, resp=sc.resp_targets)
    for pitch in sc.scan.pitches:
        table = projection_table(sc, pitch)
        zs = tf.sample_slices(rc.slice_positions(sc, (6, 10)), 4)
        g = rc.candidate_groups_of(cfg, table, zs)
        gsel = np.flatnonzero(g.group_view % 4 == 0)
        c, a = table.cardiac_phase[g.row], table.resp_amplitude[g.row]
        opts = rc.weight_options(cfg, targets)
        # targets: barycentric branch over the sampled groups
        sub = np.concatenate([np.arange(g.offsets[i], g.offsets[i + 1]) for i in gsel])
        off = np.concatenate([[0], np.cumsum(g.counts[gsel])])
        wt = iw.batch_weights("barycentric", c[sub], a[sub], off, targets.pairs, **opts)
        bt = np.bincount(wt.branch.ravel(), minlength=3) / wt.branch.size
        nd = tf.target_nearest_distances(c, a, g.offsets, targets.pairs)
        nd_c = tf.target_nearest_distances(c, a, g.offsets, targets.pairs, True, False)
        out = {"targets": np.round(bt, 3).tolist()}
        for s in tf.SCHEMES:
            f = tf.make_folds(c, a, g.offsets, g.dz_mm, gsel, s, nd_c if s == "nndm_c" else nd)
            w = iw.batch_weights("barycentric", f.c, f.a, f.offsets, np.array([[0.5, 0.5]]), allow_empty=True, **opts)
            out[s] = np.round(
                np.bincount(w.branch.ravel()[w.branch.ravel() >= 0], minlength=3) / (w.branch >= 0).sum(), 3
            ).tolist()
        print(name, pitch, "barycentric branch shares (triangle, segment, nearest):", out)
