"""Metrics: pooled MAE/std over all voxels of all targets, per-target MAE, FOV masks, LV volume."""

import numpy as np
import pytest

from clrecon.metrics import abs_error_stats, blood_pool_volume_ml, fov_masks, table2
from clrecon.scene import load_scene


@pytest.fixture(scope="module")
def scene():
    return load_scene("tiny")


def test_table2_matches_a_direct_computation(scene):
    rng = np.random.default_rng(3)
    rc = scene.recon
    shape = (2, 3, rc.nz, rc.ny, rc.nx)
    truth = rng.normal(0, 100, shape).astype(np.float32)
    recon = truth + rng.normal(5, 20, shape).astype(np.float32)
    res = table2(recon, truth, scene)
    for fov, m in fov_masks(scene).items():
        d = np.abs(recon - truth)[..., m].astype(np.float64)       # (2, 3, nz, n_in)
        assert res[fov]["mae_hu"] == pytest.approx(d.mean(), rel=1e-9)
        assert res[fov]["std_hu"] == pytest.approx(d.std(), rel=1e-6)
        assert res[fov]["n_voxels"] == d.size
        per = np.array(res["per_target"][fov])
        assert per.shape == (2, 3)
        assert np.allclose(per, d.mean(axis=(2, 3)))
        assert abs_error_stats(recon, truth, m)["mae_hu"] == pytest.approx(d.mean(), rel=1e-9)


def test_masks(scene):
    m = fov_masks(scene)
    assert m["small"].sum() < m["large"].sum()
    assert not (m["small"] & ~m["large"]).any()


def test_shape_mismatch_is_an_error(scene):
    with pytest.raises(ValueError, match="shape"):
        table2(np.zeros((1, 1, 2, 3, 3)), np.zeros((1, 1, 2, 3, 4)), scene)


def test_blood_pool_volume_of_a_box(scene):
    s = scene.replace(recon={"nx": 32, "ny": 32, "nz": 8, "voxel_mm": 2.0, "slice_mm": 2.0})
    vol = np.zeros((8, 32, 32), np.float32)
    vol[2:6, 10:20, 12:17] = 400.0                     # 4 x 10 x 5 voxels of 8 mm^3
    vol[2:6, 25:28, 25:28] = 400.0                     # a separate bright region: not counted
    z = (np.arange(8) - 3.5) * 2.0
    x = (np.arange(32) - 15.5) * 2.0
    seed = (z[3], x[14], x[13])
    assert blood_pool_volume_ml(vol, seed, s, z) == pytest.approx(4 * 10 * 5 * 8 / 1000)
    assert blood_pool_volume_ml(vol, (z[0], x[0], x[0]), s, z) == 0.0
