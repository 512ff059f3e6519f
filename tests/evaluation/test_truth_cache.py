"""The truth cache: a second run with the same truths (another pitch, other methods) takes them
from the cache, bit for bit; a damaged cached unit is computed again."""

import numpy as np

from clrecon.config.scene import load_scene
from clrecon.evaluation.truth_cache import truth_key
from clrecon.outputs.volumes import open_volumes, read_volume
from clrecon.pipeline.run import run
from clrecon.reconstruction.reconstruct import Targets, slice_positions

QUIET = dict(progress=False, report=False, log=lambda *a, **k: None)


def _truths(out):
    with open_volumes(out) as f:
        return {n: read_volume(f, n) for n in ("groundtruth", "phantom")}


def test_second_run_takes_the_truths_from_the_cache(tmp_path):
    scene = load_scene("tiny")
    cache = tmp_path / "cache"
    a = run(scene, tmp_path / "a", methods=["nearest"], cache_dir=cache, **QUIET)
    n_t = len(scene.cardiac_targets) * len(scene.resp_targets)
    assert a["stages"]["groundtruth"]["targets_from_cache"] == 0
    key = truth_key(scene, slice_positions(scene), Targets(tuple(scene.cardiac_targets), tuple(scene.resp_targets)))
    cached = sorted((cache / "truth" / key).glob("*.unit"))
    assert len(cached) == 2 * n_t  # ground truth and phantom truth, every target
    # another method and the noise-free variant only: same truths
    b = run(scene.replace(noise={"enabled": False}), tmp_path / "b", methods=["barycentric"], cache_dir=cache,
            **QUIET)
    assert b["stages"]["groundtruth"]["targets_from_cache"] == 2 * n_t
    assert b["units_written"]["truth"] == 0
    ta, tb = _truths(tmp_path / "a"), _truths(tmp_path / "b")
    for n in ta:
        np.testing.assert_array_equal(ta[n], tb[n])
    # the run's own copy is gone with its units folder, the cache keeps its file
    assert all(p.exists() for p in cached)
    # a damaged cached unit: dropped and computed again, the result unchanged
    raw = bytearray(cached[0].read_bytes())
    raw[len(raw) // 2] ^= 0xFF
    cached[0].write_bytes(bytes(raw))
    c = run(scene, tmp_path / "c", methods=["nearest"], cache_dir=cache, **QUIET)
    assert c["stages"]["groundtruth"]["targets_from_cache"] == 2 * n_t - 1
    assert c["units_written"]["truth"] == 1
    tc = _truths(tmp_path / "c")
    for n in ta:
        np.testing.assert_array_equal(ta[n], tc[n])


def test_the_key_follows_what_the_truths_depend_on():
    scene = load_scene("tiny")
    z = slice_positions(scene)
    t = Targets((0.0, 0.4), (0.25, 0.75))
    k = truth_key(scene, z, t)
    assert k == truth_key(scene.replace(scan={"pitches": [0.05]}), z, t)  # not the pitch
    assert k == truth_key(scene.replace(recon={"methods": ["nearest"]}), z, t)  # nor the methods
    assert k != truth_key(scene, z[:1], t)
    assert k != truth_key(scene, z, Targets((0.0,), (0.25, 0.75)))
    assert k != truth_key(scene.replace(recon={"nx": 16}), z, t)
    assert k != truth_key(scene.replace(phantom={"mu_water_per_mm": 0.02}), z, t)
