"""The shrinkage's prior made local: does it keep the beat's fields out of the chest wall?

`mc`'s fields are shrunk towards zero where the images cannot show motion
(``clrecon/reconstruction/motion/confidence.py``) under one prior per field: the field's own mean
square. With TV-L1 registering the beat, the beat's fields reach into the chest wall, which the
heart does not move (docs/results/mc-study.md "Which registration for which step": large FOV 0.09 HU
worse, body muscle 24.68 -> 25.04 HU). The local prior (``confidence.local_prior_scale``) scales the
prior by what the unregistered images show at each voxel. One run per variant of a scene at one
pitch with ``barycentric,mc``, measured as ``step_registrations.py`` measures (MAE per object, the
model's error against the phantom's motion and its steps):

- ``global``: the shrinkage as it is (the default);
- ``local``: the local prior in both steps;
- ``local-beat``: the local prior in the beat step only;
- ``oracle-mask``: the global prior, and the beat's fields multiplied by a mask taken from the
  phantom (the heart and epicardial fat over the cardiac cycle at amplitude 0.45, dilated by 6 mm,
  tapered over a 3-mm Gaussian): what confining the beat to the heart could gain at most.

    python benchmarks/studies/motion-model/local_prior.py --out /tmp/lp [--scene demo] [--pitch 0.1]
        [--variants global,local,local-beat] [--noise]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import scipy.ndimage

from clrecon.config.overrides import load_scene
from clrecon.evaluation.motion_model import HEART
from clrecon.reconstruction.motion import confidence, estimate, persist
from clrecon.simulation.phantom_sources import phantom_from_config
from clrecon.simulation.phantoms import motion_field

sys.path.insert(0, str(Path(__file__).resolve().parent))
from step_registrations import _keeping, measure_run

VARIANTS = ("global", "local", "local-beat", "oracle-mask", "gain", "gain-beat")


def _noise_floor(unregistered, registered, A, g_noise, prior, size):
    """The first local prior tried: the registered residual's *global* robust variance as the floor
    (``mean_w(r0^2) - s_r^2``) instead of its window mean square."""
    s_r = confidence._robust_std(registered)
    return confidence.local_prior_scale(unregistered, np.full_like(registered, s_r), A, g_noise, prior, size)


def _steps_local(shrunk, which: str):
    """``estimate.shrunk`` with the local prior in ``which`` steps ("both", "beat", "none"); the
    separable scheme shrinks the breathing step's fields first, then the beat's, once per round."""
    calls = [0]

    def wrapped(fields, images, reference, grid, shrink, local=False):
        step = "breathing" if calls[0] % 2 == 0 else "beat"
        calls[0] += 1
        return shrunk(fields, images, reference, grid, shrink, local=which == "both" or which == step)
    return wrapped


def _heart_mask(scene, grid) -> np.ndarray:
    """(nz, ny, nx) float32 in [0, 1]: the phantom's heart and epicardial fat at any cardiac phase
    (amplitude 0.45), dilated by 6 mm and tapered (module docstring)."""
    phantom = phantom_from_config(scene.phantom)
    x, y, z = grid.coords()
    Z, Y, X = np.meshgrid(z, y, x, indexing="ij")
    pts = np.stack([X, Y, Z], -1)
    ids = [phantom.names.index(n) for n in HEART + ("epicardial_fat",) if n in phantom.names]
    inside = np.zeros(grid.shape, bool)
    for c in np.linspace(0.0, 0.9, 10):
        inside |= np.isin(motion_field.owner(phantom, pts, float(c), 0.45), ids)
    sp = np.array([grid.dz_mm, grid.voxel_mm, grid.voxel_mm])
    dist = scipy.ndimage.distance_transform_edt(~inside, sampling=sp)
    return scipy.ndimage.gaussian_filter((dist <= 6.0).astype(np.float64), 3.0 / sp).astype(np.float32)


def _masked_beat(shrunk, scene):
    calls = [0]

    def wrapped(fields, images, reference, grid, shrink, local=False):
        beat = calls[0] % 2 == 1
        calls[0] += 1
        out, infos = shrunk(fields, images, reference, grid, shrink, local=False)
        if beat:
            out = out * _heart_mask(scene, grid)[None, None]
        return out, infos
    return wrapped


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--out", required=True)
    ap.add_argument("--scene", default="demo")
    ap.add_argument("--pitch", type=float, default=0.1)
    ap.add_argument("--variants", default=",".join(VARIANTS))
    ap.add_argument("--noise", action="store_true")
    args = ap.parse_args()
    persist.save_model = _keeping(persist.save_model)
    original, prior_scale = estimate.shrunk, confidence.local_prior_scale
    out = Path(args.out)
    rows = []
    for variant_name in args.variants.split(","):
        if variant_name not in VARIANTS:
            raise SystemExit(f"--variants: {variant_name!r} is not one of {VARIANTS}")
        over = {} if args.noise else {"noise__enabled": False}
        scene = load_scene(args.scene, **over)
        confidence.local_prior_scale = prior_scale
        if variant_name == "oracle-mask":
            estimate.shrunk = _masked_beat(original, scene)
        else:
            if variant_name.startswith("local"):
                confidence.local_prior_scale = _noise_floor
            estimate.shrunk = _steps_local(original, {"global": "none", "local": "both", "local-beat": "beat",
                                                      "gain": "both", "gain-beat": "beat"}[variant_name])
        rows += measure_run(scene, args.scene, args.pitch, out / variant_name, prior=variant_name)
    (out / "local_prior.json").write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
