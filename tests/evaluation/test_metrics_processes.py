"""The metrics stage split over processes (clrecon.pipeline.evaluate): bit for bit the one-process numbers."""

import json

import h5py
import numpy as np
import pytest
from run_compare import reference_run

from clrecon.config.scene import load_scene
from clrecon.evaluation.metrics import MetricsConfig, table2
from clrecon.pipeline import evaluate as evaluate_mod
from clrecon.pipeline.run import resolve_targets
from clrecon.simulation.phantom_sources import phantom_from_config

KEYS = ("metrics", "respiratory_only", "motion")


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    """tiny run by the serial executor: its volumes and its one-process metrics."""
    return reference_run(tmp_path_factory, {}, executor="serial")[:2]


def _evaluate(out, res, **kw):
    scene = load_scene("tiny")
    info: dict = {}
    req = res["request"]
    targets = resolve_targets(scene, req["targets"]["cardiac"], req["targets"]["resp"])
    with h5py.File(out / "volumes.h5", "r") as f:
        got = evaluate_mod.evaluate(scene, f, targets, np.asarray(req["slices_z_mm"]), req["pitches"],
                                    tuple(req["variants"]), tuple(req["methods"]), phantom_from_config(scene.phantom),
                                    info=info, **kw)
    return dict(zip(KEYS, got, strict=True)), info["processes"]


def _same(a, b):
    for k in KEYS:  # exact equality of every float, through the JSON the run writes
        assert json.dumps(a[k], sort_keys=True) == json.dumps(b[k], sort_keys=True), k


@pytest.mark.parametrize("n", [2, 3])
def test_split_over_processes_is_bit_identical(tiny, n):
    out, ref = tiny
    assert ref["stages"]["metrics"]["processes"] == 1
    got, processes = _evaluate(out, ref, processes=n)
    assert processes == n   # the split path was taken
    _same(json.loads(json.dumps(got)), ref)


def test_a_pool_that_cannot_start_runs_every_group_here(tiny, monkeypatch):
    out, ref = tiny
    monkeypatch.setattr(evaluate_mod, "spawned_pool", lambda n: None)
    got, processes = _evaluate(out, ref, processes=2)
    assert processes == 1
    _same(json.loads(json.dumps(got)), ref)


def test_modelled_process_count(monkeypatch):
    """The memory model's count: 2 with a warm helper, else 2 only from PROCESS_MIN_BYTES on a
    machine of >= 2 cores where a child may be spawned."""
    monkeypatch.setattr(evaluate_mod.os, "cpu_count", lambda: 2)
    monkeypatch.setattr(evaluate_mod, "spawn_is_safe", lambda: True)
    assert evaluate_mod.process_count(evaluate_mod.PROCESS_MIN_BYTES - 1) == 1
    assert evaluate_mod.process_count(evaluate_mod.PROCESS_MIN_BYTES) == 2
    assert evaluate_mod.process_count(1, warm=True) == 2
    monkeypatch.setattr(evaluate_mod.os, "cpu_count", lambda: 1)
    assert evaluate_mod.process_count(10 * evaluate_mod.PROCESS_MIN_BYTES) == 1


def test_groups_keep_every_key_once_in_order():
    keys = [(p, v, m) for p in ("a", "b") for v in ("n", "f") for m in "xyz"]
    for n in (1, 2, 5, 40):
        g = evaluate_mod._groups(keys, n)
        assert [k for part in g for k in part] == keys and len(g) == min(n, len(keys))


def test_spawn_is_safe_only_without_a_main_script_to_rerun(monkeypatch):
    import sys
    import types

    script = types.ModuleType("__main__")
    script.__file__ = "/home/user/my_study.py"        # an unguarded script would run again in the child
    monkeypatch.setitem(sys.modules, "__main__", script)
    assert evaluate_mod.spawn_is_safe() is False
    monkeypatch.setattr(evaluate_mod.os, "cpu_count", lambda: 2)
    assert evaluate_mod.process_count(10 * evaluate_mod.PROCESS_MIN_BYTES) == 1
    cli = types.ModuleType("__main__")
    cli.__file__ = "/site-packages/clrecon/__main__.py"
    cli.__spec__ = types.SimpleNamespace(name="clrecon.__main__")
    monkeypatch.setitem(sys.modules, "__main__", cli)
    assert evaluate_mod.spawn_is_safe() is True
    notebook = types.ModuleType("__main__")           # no file: nothing to re-run
    monkeypatch.setitem(sys.modules, "__main__", notebook)
    assert evaluate_mod.spawn_is_safe() is True


def test_cropped_lv_regions_count_what_the_full_masks_count():
    """The metrics keep each target's LV region as its bounding box and the mask inside it: the
    blood-pool volumes are those of the full-size masks (every target of the demo grid, volumes
    with contrast around the LV and noise everywhere)."""
    import numpy as np

    from clrecon.evaluation import groundtruth, metrics
    from clrecon.pipeline.run import resolve_targets
    from clrecon.reconstruction import reconstruct
    from clrecon.simulation.phantom_sources import phantom_from_config

    scene = load_scene("demo")
    targets = resolve_targets(scene, None, None)
    slices_z = reconstruct.slice_positions(scene, None)
    phantom = phantom_from_config(scene.phantom)
    ctx = evaluate_mod._context(scene, targets, slices_z, tuple(scene.recon.methods), phantom)
    assert ctx.want_ro
    rc = scene.recon
    x, y = reconstruct.voxel_coords(rc.nx, rc.voxel_mm), reconstruct.voxel_coords(rc.ny, rc.voxel_mm)
    rng = np.random.default_rng(5)
    for i, c in enumerate(targets.cardiac[:3]):
        for j, a in enumerate(targets.resp):
            full = groundtruth.lv_region_mask(phantom, c, a, x, y, slices_z)
            sl, sub = ctx.regions[i][j]
            assert sub.sum() == full.sum() > 0 and sub.size < full.size
            vol = rng.normal(200.0, 60.0, full.shape).astype(np.float32)
            assert ctx.lv(vol, i, j) == metrics.blood_pool_volume_ml(vol, full, ctx.voxel_ml)


def test_each_fov_has_its_mae_against_the_phantom_itself(tiny, tmp_path):
    """``mae_phantom_hu``: a reconstruction replaced by the phantom truth scores 0 against it (and
    the phantom's own distance from the ground-truth CT against the CT); the others keep their
    Table-2 numbers, with a non-zero phantom MAE of their own."""
    out, ref = tiny
    name = "recon/p0.100/noise-free/barycentric"
    with h5py.File(out / "volumes.h5", "r") as src, h5py.File(tmp_path / "volumes.h5", "w") as f:
        def copy(key, obj):  # every dataset as a plain one (the run's are virtual, over its unit files)
            if isinstance(obj, h5py.Dataset):
                f.create_dataset(key, data=obj[()])
                f[key].attrs.update(dict(obj.attrs))
        src.visititems(copy)
        f.attrs.update(dict(src.attrs))
        assert f[name].shape == f["phantom"].shape, (f[name].shape, f["phantom"].shape)
        f[name][...] = f["phantom"][()]
        ph = f["phantom"][()].astype(np.float64)
        gt = f["groundtruth"][()].astype(np.float64)
    got, _ = _evaluate(tmp_path, ref)
    met = got["metrics"]["p0.100"]["noise-free"]
    for fov in ("large", "small"):
        assert met["barycentric"][fov]["mae_phantom_hu"] == pytest.approx(0.0, abs=1e-9)
        assert met["barycentric"][fov]["mae_hu"] > 1.0
        for m in ("local_linear", "r4dct"):
            assert met[m][fov]["mae_hu"] == ref["metrics"]["p0.100"]["noise-free"][m][fov]["mae_hu"]
            assert met[m][fov]["mae_phantom_hu"] > 1.0
    direct = table2(ph, gt, MetricsConfig.from_scene(load_scene("tiny")))
    for fov in ("large", "small"):
        assert met["barycentric"][fov]["mae_hu"] == pytest.approx(direct[fov]["mae_hu"], rel=1e-6)
