"""How far the measured rows are from ideal in-plane rows of the phantom at the row's own state (the
data model every reconstruction inherits and the ground truth does not): RMS of y_k - ideal_k in
HU mm over the channels through the reconstruction circle, by the row's axial distance |dz|.
docs/consistency.md "Did it help? A truth-free check".

    python benchmarks/studies/consistency/data_model.py /tmp/run --scene demo
"""

import argparse
import json

import numpy as np

from clrecon.config.scene import load_scene
from clrecon.evaluation import consistency as cs
from clrecon.evaluation import groundtruth as gt
from clrecon.evaluation import truth_free
from clrecon.reconstruction import reconstruct as rc
from clrecon.scan import table as geometry
from clrecon.simulation import projector
from clrecon.simulation.store import ProjectionStore, default_cache_dir


def ideal_rows(ph, detector, geom, groups, flat, table, zs):
    """Ideal in-plane rows (p, C) line integrals of the phantom ``ph`` for the candidate rows ``flat`` of
    ``groups`` (the check's sampling of slices ``zs``), each at its own state (c, a) in ``table``, its
    group's view and its slice's z; returns (rows, view (p,))."""
    gof = np.repeat(np.arange(groups.n_groups), np.diff(groups.offsets))[flat]
    view, z = groups.group_view[gof], np.asarray(zs)[gof // groups.views_per_rotation]
    c, a = table.cardiac_phase[groups.row[flat]], table.resp_amplitude[groups.row[flat]]
    (src, centre, eu, ev), u, vs = cs.inplane_frames(detector, geom, view, z)
    objs = np.stack([ph.objects(ck, ak) for ck, ak in zip(c, a, strict=True)])
    return projector.project_views(objs, src, centre, eu, ev, u, np.zeros(1), v_scale=vs)[:, 0, :], view


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("run")
    ap.add_argument("--scene", default="demo")
    ap.add_argument("--view-step", type=int, default=16)
    args = ap.parse_args()
    scene = load_scene(args.scene)
    cfg = rc.ReconstructionConfig.from_scene(scene)
    g, det = cfg.fbp, cfg.scanner.detector_model
    res = json.load(open(f"{args.run}/results.json"))
    ph = gt.GroundTruthConfig.from_scene(scene).source()
    zs = truth_free.sample_slices(np.array(res["request"]["slices_z_mm"]), 4)
    scale = 1000 / cfg.mu_water_per_mm
    for pk in res["metrics"]:
        pitch = float(pk[1:])
        table = geometry.projection_table(scene, pitch)
        tab = geometry.usable_table(scene, table)[0]
        store = ProjectionStore.open(scene, pitch, cache_dir=default_cache_dir(), table=table)
        groups = rc.candidate_groups_of(cfg, tab, zs)
        gsel = np.flatnonzero(groups.group_view % args.view_step == 0)
        flat = np.concatenate([np.arange(groups.offsets[x], groups.offsets[x + 1]) for x in gsel])
        y = truth_free.read_rows(store, groups, flat, cfg.scanner, ("noise-free",), cfg.noise)["noise-free"][0]
        ideal, view = ideal_rows(ph, det, g, groups, flat, tab, zs)
        circ = cs.channels_through_circle(det, g, view, cfg.object_radius_mm)
        e = (y - ideal) * scale
        dz = np.abs(groups.dz_mm[flat])
        print(f"{pk}: {flat.size} rows, RMS(y - ideal) {np.sqrt((e[circ] ** 2).mean()):.0f} HU mm, "
              f"row RMS {np.sqrt(((ideal * scale)[circ] ** 2).mean()):.0f} HU mm")
        for lo, hi in ((0, 2), (2, 6), (6, 50)):
            s = (dz >= lo) & (dz < hi)
            print(f"   |dz| in [{lo}, {hi}) mm: {s.sum()} rows, {np.sqrt((e[s][circ[s]] ** 2).mean()):.0f} HU mm")


if __name__ == "__main__":
    main()
