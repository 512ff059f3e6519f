"""Which registration for which step of the separable scheme: Lucas-Kanade and TV-L1 crossed.

For each (breathing step, beat step) registration (``[recon.mc] registration``,
``beat_registration``) one ``clrecon`` run of a scene at one pitch with ``barycentric,mc``; then,
from the run's volumes and its fitted motion model (kept by wrapping ``persist.save_model``: a
finished run deletes its unit files):

- ``mc``'s MAE against the ground truth per object of the phantom (the innermost object holding
  each voxel at each target's state), large FOV, pooled over the targets -- where the two
  registrations differ in the image;
- the model's error against the phantom's motion (RMS, mm) in the heart, the lungs and the rest of
  the body, and the error of its *steps*: ``u(c_i) - u(c_{i-1})`` (neighbouring cardiac targets) and
  ``u(a_j) - u(a_{j-1})`` (neighbouring amplitudes) against the phantom's -- what the
  backprojection uses, since it moves each row by the difference between the row's state and
  the target's.

    python benchmarks/studies/motion-model/step_registrations.py --out /tmp/steps [--scene demo]
        [--pitch 0.1] [--combos lucas_kanade:lucas_kanade,tvl1:tvl1,lucas_kanade:tvl1,tvl1:lucas_kanade]
        [--noise]

Prints one JSON line per combination (and writes ``steps.json`` in ``--out``). Noise-free only
unless ``--noise`` (the scene's variants).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import h5py
import numpy as np

import clrecon
from clrecon.config.overrides import load_scene
from clrecon.evaluation.metrics import MetricsConfig, fov_masks
from clrecon.evaluation.motion_model import HEART, LUNGS
from clrecon.reconstruction.motion import method, persist
from clrecon.simulation.phantom_sources import phantom_from_config
from clrecon.simulation.phantoms import motion_field

KEPT: dict = {}


def _keeping(save):
    def save_model(folder, stem, model, info, fault):
        KEPT[stem] = model
        return save(folder, stem, model, info, fault)
    return save_model


def per_object_mae(run_dir: Path, scene, pk: str, variant: str) -> dict:
    """{object: {method: MAE HU, "share": fraction of the large FOV's voxels}} over every target."""
    phantom = phantom_from_config(scene.phantom)
    with h5py.File(run_dir / "volumes.h5") as f:
        truth = f["groundtruth"]
        ax = {k: f["axes/" + k][...] for k in ("cardiac_phase", "resp_amplitude", "x_mm", "y_mm", "z_mm")}
        methods = list(f[f"recon/{pk}/{variant}"].keys())
        vols = {m: f[f"recon/{pk}/{variant}/{m}"] for m in methods}
        Z, Y, X = np.meshgrid(ax["z_mm"], ax["y_mm"], ax["x_mm"], indexing="ij")
        large = np.broadcast_to(fov_masks(MetricsConfig.from_scene(scene))["large"], Z.shape)
        acc: dict = {}
        for i, c in enumerate(ax["cardiac_phase"]):
            for j, a in enumerate(ax["resp_amplitude"]):
                own = motion_field.owner(phantom, np.stack([X, Y, Z], -1), float(c), float(a))
                t = truth[i, j].astype(np.float64)
                errs = {m: np.abs(vols[m][i, j] - t) for m in methods}
                for k in np.unique(own[large]):
                    sel = large & (own == k)
                    name = "air" if k < 0 else phantom.names[k]
                    row = acc.setdefault(name, {"n": 0, **{m: 0.0 for m in methods}})
                    row["n"] += int(sel.sum())
                    for m in methods:
                        row[m] += float(errs[m][sel].sum())
    total = sum(r["n"] for r in acc.values())
    return {name: {"share": round(r["n"] / total, 4), **{m: round(r[m] / r["n"], 2) for m in methods}}
            for name, r in sorted(acc.items(), key=lambda kv: -kv[1]["n"])}


def model_errors(model, scene, pairs, n_c: int, n_r: int, stride: int = 2) -> dict:
    """RMS error (mm) of ``model`` against the phantom's motion, and of its cardiac and breathing
    steps, in the heart, the lungs and the rest of the body (inside the large FOV), beside the motion's."""
    phantom = phantom_from_config(scene.phantom)
    g = model.grid
    x, y, z = g.coords()
    x, y = x[::stride], y[::stride]
    true = motion_field.displacement_fields(phantom, x, y, z, tuple(model.reference), pairs)
    Z, Y, X = np.meshgrid(z, y, x, indexing="ij")
    own = motion_field.owner(phantom, np.stack([X, Y, Z], -1), *model.reference)
    names = phantom.names
    heart = np.isin(own, [names.index(n) for n in HEART if n in names])
    lungs = np.isin(own, [names.index(n) for n in LUNGS if n in names])
    inside = X ** 2 + Y ** 2 <= MetricsConfig.from_scene(scene).large_radius_mm ** 2
    regions = {"heart": heart & inside, "lungs": lungs & inside, "body": (own >= 0) & ~heart & ~lungs & inside}
    u = np.stack([model.displacement(float(c), float(a))[:, :, ::stride, ::stride] for c, a in pairs])
    u = u.reshape((n_c, n_r) + true.shape[1:])
    t = true.reshape(u.shape)
    out = {}
    for name, (du, dt) in {"state": (u, t), "cardiac_step": (u - np.roll(u, 1, 0), t - np.roll(t, 1, 0)),
                           "breathing_step": (u[:, 1:] - u[:, :-1], t[:, 1:] - t[:, :-1])}.items():
        e2, t2 = ((du - dt) ** 2).sum(2), (dt.astype(np.float64) ** 2).sum(2)
        out[name] = {r: [round(float(np.sqrt(e2[..., m].mean())), 2), round(float(np.sqrt(t2[..., m].mean())), 2)]
                     for r, m in regions.items()}
    return out


def measure_run(scene, scene_name: str, pitch: float, run_dir: Path, **labels) -> list[dict]:
    """One ``barycentric,mc`` run of ``scene`` at ``pitch`` in ``run_dir`` (in this process, so that
    a study's patches apply), and one row per noise variant: ``labels``, each step's registration,
    ``mc``'s MAE (against the ground truth and the phantom), the kept model's errors
    (:func:`model_errors`) and the MAE per object (:func:`per_object_mae`); each row printed as a JSON
    line (without the per-object MAE)."""
    KEPT.clear()
    res = clrecon.run(scene, run_dir, methods=["barycentric", "mc"], pitches=[pitch], progress=False,
                      executor="serial").results
    pk = next(iter(res["metrics"]))
    rows = []
    for variant, ms in res["metrics"][pk].items():
        model = KEPT[f"model~{pk}~{variant}"]
        with h5py.File(run_dir / "volumes.h5") as f:
            cs, rs = f["axes/cardiac_phase"][...], f["axes/resp_amplitude"][...]
        pairs = np.array([(c, a) for c in cs for a in rs])
        row = {"scene": scene_name, "pitch": pitch, "variant": variant, **labels,
               "registrations": method.registrations(scene.recon.mc),
               "mae_hu": {m: [round(v["large"]["mae_hu"], 2), round(v["small"]["mae_hu"], 2)] for m, v in ms.items()},
               "mae_phantom_hu": {m: [round(v["large"]["mae_phantom_hu"], 2), round(v["small"]["mae_phantom_hu"], 2)]
                                  for m, v in ms.items()},
               "model_error_mm": model_errors(model, scene, pairs, len(cs), len(rs)),
               "per_object_mae_hu": per_object_mae(run_dir, scene, pk, variant)}
        rows.append(row)
        print(json.dumps({k: v for k, v in row.items() if k != "per_object_mae_hu"}), flush=True)
    return rows


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--out", required=True)
    ap.add_argument("--scene", default="demo")
    ap.add_argument("--pitch", type=float, default=0.1)
    ap.add_argument("--combos", default="lucas_kanade:lucas_kanade,tvl1:tvl1,lucas_kanade:tvl1,tvl1:lucas_kanade")
    ap.add_argument("--noise", action="store_true")
    args = ap.parse_args()
    persist.save_model = _keeping(persist.save_model)
    out = Path(args.out)
    rows = []
    for combo in args.combos.split(","):
        breathing, beat = combo.split(":")
        over = {"recon__mc__registration": breathing, "recon__mc__beat_registration": beat}
        if not args.noise:
            over["noise__enabled"] = False
        scene = load_scene(args.scene, **over)
        rows += measure_run(scene, args.scene, args.pitch, out / f"{breathing}-{beat}")
    (out / "steps.json").write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
