"""Where, in the image, a method's error adds up along rays: the study behind "a few slices carry
the pooled verdict" (docs/results/mc-consistency.md).

For each chosen slice and target of a finished run, the error image E = V - G of a method's volume V
against the run's ground-truth CT G (HU) is projected in-plane (the consistency check's geometry,
:func:`clrecon.evaluation.consistency.inplane_projections`, every ``--view-step``-th view): the RMS
of these line integrals (HU mm) is what the truth-free residual sees of the method's error. E is
split by the ground truth's own HU into regions (outside the body, lung, soft tissue, dense: bone
and contrast) and each part is projected alone (projection is linear, so the parts add up to the
whole): which region's error makes a slice's line integrals large. Beside it the MAE and the mean
error (bias) per region: a bias adds up along a ray, a zero-mean error mostly cancels.

    python benchmarks/studies/consistency/where.py /tmp/run --scene paper-p010 --slices 50,100 [--methods barycentric,mc] [--pitch p0.100]
"""

import argparse
import json

import h5py
import numpy as np

from clrecon.config.scene import load_scene
from clrecon.evaluation import consistency as cs
from clrecon.outputs.volumes import recon_path
from clrecon.reconstruction import reconstruct as rc

#: Regions by the ground truth's HU: (name, low, high), low <= G < high.
REGIONS = (("outside", -np.inf, -900.0), ("lung", -900.0, -300.0), ("soft", -300.0, 300.0), ("dense", 300.0, np.inf))


def image(d, i: int, j: int, s: int) -> np.ndarray:
    """Slice ``s`` of target (i, j) of a volumes dataset, float64 (ny, nx): (n_c, n_r, S, ny, nx), an
    axis of length 1 serving every target of it, or (S, ny, nx), a motionless scene's one target."""
    if d.ndim == 3:
        return np.asarray(d[s], np.float64)
    return np.asarray(d[min(i, d.shape[0] - 1), min(j, d.shape[1] - 1), s], np.float64)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("run")
    ap.add_argument("--scene", default="demo")
    ap.add_argument("--slices", required=True, help="comma list of slice indices")
    ap.add_argument("--methods", default="barycentric,mc")
    ap.add_argument("--variant", default=None, help="noise variant (default: the run's first)")
    ap.add_argument("--pitch", default=None, help="pitch key, e.g. p0.100 (default: the run's first)")
    ap.add_argument("--view-step", type=int, default=8)
    ap.add_argument("--targets", type=int, default=10, help="every n-th target of the lattice (cardiac-major)")
    args = ap.parse_args()
    scene = load_scene(args.scene)
    res = json.load(open(f"{args.run}/results.json"))
    cfg = rc.ReconstructionConfig.from_scene(scene)
    g, det = cfg.fbp, cfg.scanner.detector_model
    pk = args.pitch or next(iter(res["metrics"]))
    v = args.variant or res["request"]["variants"][0]
    views = np.arange(0, g.n_views, args.view_step)
    f = h5py.File(f"{args.run}/volumes.h5", "r")
    gt = f["groundtruth"]
    nc, nr = gt.shape[:2] if gt.ndim == 5 else (1, 1)
    pick = [(i, j) for k, (i, j) in enumerate((i, j) for i in range(nc) for j in range(nr)) if k % args.targets == 0]
    img = np.repeat(np.arange(len(pick)), views.size)  # every picked target's image at every view
    vw = np.tile(views, len(pick))
    print(f"{pk} {v}: {len(pick)} targets, {views.size} views, regions by the ground truth's HU")
    for s in (int(x) for x in args.slices.split(",")):
        G = np.stack([image(gt, i, j, s) for i, j in pick])          # (T, ny, nx)
        masks = {name: (G >= lo) & (G < hi) for name, lo, hi in REGIONS}
        line = f"slice {s}:"
        for m in args.methods.split(","):
            d = f[recon_path(pk, v, m)]
            E = np.stack([image(d, i, j, s) for i, j in pick]) - G
            parts = {"all": E, **{name: E * mk for name, mk in masks.items()}}
            out = []
            for name, part in parts.items():
                p = cs.inplane_projections(part.astype(np.float32), g.voxel_mm, det, g, img, vw).astype(np.float64)
                rms = np.sqrt((p ** 2).mean())
                if name == "all":
                    out.append(f"line-integral RMS {rms:7.0f} HU mm, MAE {np.abs(E).mean():5.1f} HU")
                else:
                    mk = masks[name]
                    out.append(f"{name} {rms:6.0f} (MAE {np.abs(E[mk]).mean():5.1f}, mean {E[mk].mean():+6.1f}, "
                               f"{100 * mk.mean():4.1f} % of pixels)")
            line += f"\n  {m:12s} " + "; ".join(out)
        print(line, flush=True)


if __name__ == "__main__":
    main()
