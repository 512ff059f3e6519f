"""A small fake run directory (``volumes.h5`` + ``results.json``) for the viewer/figure/export tests.

It has the exact on-disk format of :mod:`clrecon.pipeline.run` but volumes made from a cheap analytic
"thorax" (body, lungs, spine, a heart that moves with breathing and beats) instead of a
simulation, so the tests of the consumers of a run directory need no OpenCL and run in well
under a second. Reconstructions are the ground truth plus method-dependent errors: ``nearest``
has axial misalignment (slices from other targets), ``barycentric`` and ``local_linear`` small
noise, ``r4dct`` the cardiac average.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from clrecon.config.scene import load_scene
from clrecon.core.conventions import voxel_coords
from clrecon.evaluation import metrics, motion
from clrecon.outputs.volumes import VolumeWriter, pitch_key, recon_path

METHODS = ("nearest", "barycentric", "local_linear", "r4dct")
PITCHES = (0.02, 0.1)
VARIANTS = ("noisy", "noise-free")


def fake_scene(nx=40, ny=36, nz=10):
    """The ``tiny`` scene resized: 8 mm voxels, 6 mm slices, 3 x 3 targets, pitches 0.02 and 0.1."""
    return load_scene("tiny").replace(recon={"nx": nx, "ny": ny, "nz": nz, "voxel_mm": 8.0, "slice_mm": 6.0,
                                             "cardiac_phases": [0.0, 0.4, 0.8], "resp_bins": 3},
                                      scan={"pitches": list(PITCHES)})


def anatomy_hu(c: float, a: float, z, y, x) -> np.ndarray:
    """HU of the fake thorax at cardiac phase ``c``, amplitude ``a`` on the grid (z, y, x) mm (LPS)."""
    Z, Y, X = np.meshgrid(z, y, x, indexing="ij")
    hu = np.full(Z.shape, -1000.0)
    body = (X / 150.0) ** 2 + ((Y - 10) / (110.0 + 10 * a)) ** 2 <= 1
    hu[body] = 40.0
    for sx in (-75.0, 75.0):
        lung = ((X - sx) / 55.0) ** 2 + ((Y - 10) / 75.0) ** 2 <= 1
        hu[lung & body] = -800.0
    spine = (X / 20.0) ** 2 + ((Y - 85) / 20.0) ** 2 <= 1
    hu[spine] = 700.0
    hz = 12.0 * a  # heart rides on the diaphragm
    r = 30.0 * (1.0 - 0.25 * np.sin(np.pi * c) ** 2)  # end-systole near c = 0.5
    heart = ((X - 20) / 50.0) ** 2 + ((Y + 30) / 45.0) ** 2 + ((Z - hz) / 40.0) ** 2 <= 1
    hu[heart] = 90.0
    lv = ((X - 30) ** 2 + (Y + 30) ** 2 + (Z - hz) ** 2) <= r * r
    hu[lv] = 400.0
    return hu.astype(np.float32)


def make_fake_run(out: Path, methods=METHODS, pitches=PITCHES, variants=VARIANTS, seed: int = 0,
                  scene=None) -> dict:
    """Write ``out/volumes.h5`` and ``out/results.json``; returns the results dictionary."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    scene = scene or fake_scene()
    rc = scene.recon
    cardiac = tuple(scene.cardiac_targets)
    resp = tuple(scene.resp_targets)
    z = voxel_coords(rc.nz, rc.slice_mm)
    y = voxel_coords(rc.ny, rc.voxel_mm)
    x = voxel_coords(rc.nx, rc.voxel_mm)
    shape = (len(cardiac), len(resp), len(z), len(y), len(x))
    gt = np.empty(shape, np.float32)
    for i, c in enumerate(cardiac):
        for j, a in enumerate(resp):
            gt[i, j] = anatomy_hu(c, a, z, y, x)
    rng = np.random.default_rng(seed)
    axes = {"cardiac_phase": cardiac, "resp_amplitude": resp, "z_mm": z, "y_mm": y, "x_mm": x}
    w = VolumeWriter(out / "volumes.h5", axes, keep_cardiac=scene.has_cardiac, keep_resp=scene.has_respiratory)
    nz = shape[2]
    w.create("groundtruth", shape, nz)
    w.write("groundtruth", gt, np.arange(nz))
    w.create("phantom", shape, nz)
    w.write("phantom", gt, np.arange(nz))
    met, secs, mot = {}, {}, {}
    mcfg = motion.MotionConfig.from_scene(scene, z)
    for pitch in pitches:
        pk = pitch_key(pitch)
        met[pk], secs[pk], mot[pk] = {}, {}, {}
        for v in variants:
            met[pk][v], secs[pk][v] = {}, {}
            mot[pk][v] = {"groundtruth": fake_motion(mcfg, shape[:2], 0.0, 0.0, reference=True)}
            noise = 25.0 if v == "noisy" else 3.0
            for k, m in enumerate(methods):
                if m == "nearest":  # axial misalignment: every other slice from a neighbouring target
                    vol = gt.copy()
                    vol[:, :, 1::2] = np.roll(gt, 1, axis=1)[:, :, 1::2]
                elif m == "r4dct":
                    vol = np.broadcast_to(gt.mean(axis=0, keepdims=True), shape).copy()
                else:
                    vol = gt.copy()
                vol = vol + rng.normal(0.0, noise * (1 + k) * (1 + 5 * pitch), shape).astype(np.float32)
                name = recon_path(pk, v, m)
                w.create(name, shape, nz)
                w.write(name, vol, np.arange(nz))
                met[pk][v][m] = metrics.table2(vol, gt, metrics.MetricsConfig.from_scene(scene))
                secs[pk][v][m] = 0.5 + k + 3 * pitch
                mot[pk][v][m] = fake_motion(mcfg, shape[:2], 1.0 + k + 10 * pitch, noise * (1 + k))
    w.close()
    results = {
        "format_version": 1, "scene": scene.to_dict(), "scene_source": "fake", "versions": {"clrecon": "test"},
        "device": "fake", "request": {"methods": list(methods), "pitches": list(pitches), "variants": list(variants),
                                      "targets": {"cardiac": list(cardiac), "resp": list(resp)},
                                      "slices": [0, rc.nz], "slices_z_mm": z.tolist()},
        "dimensions": {"cardiac": scene.has_cardiac, "resp": scene.has_respiratory},
        "stages": {"simulate": {"ran": False, "seconds": 0.0, "skipped_because": "fake run"}},
        "metrics": met, "method_seconds": secs, "respiratory_only": {}, "motion": mot,
        "motion_definitions": motion.definitions(mcfg),
        "outputs": {"volumes": "volumes.h5", "report": "report.md"},
    }
    (out / "results.json").write_text(json.dumps(results, indent=1))
    return results


def fake_motion(cfg, targets_shape, blur: float, noise: float, reference: bool = False) -> dict:
    """A ``results.json["motion"]`` entry (:class:`clrecon.evaluation.motion.MotionMetrics`) with made-up
    numbers: edges ``blur`` mm wider than 3 mm, lesions ``blur / 2`` mm off, noise std ``noise`` HU."""
    acc = motion.MotionMetrics(cfg, *targets_shape)
    acc.edge[:] = 3.0 + blur
    acc.n_prof[:] = cfg.n_profiles - 2
    acc.lv_ml[:] = 100.0 - 2.0 * blur
    acc.vec[:] = (0.5 * blur, 0.0, 0.1)
    acc.reference = reference
    if not reference:
        acc.lv_err[:] = -2.0 * blur
        acc.noise[:] = noise
    return acc.result()
