"""Metrics: pooled MAE/std over all voxels of all targets, per-target MAE, FOV masks, LV volume."""

import numpy as np
import pytest

from benchmarks.levers import _table2_fresh
from clrecon.config.scene import load_scene
from clrecon.evaluation.metrics import (
    MetricsConfig,
    Table2,
    abs_error_stats,
    blood_pool_volume_ml,
    fov_masks,
    table2,
)


@pytest.fixture(scope="module")
def scene():
    return load_scene("tiny")


def test_table2_matches_a_direct_computation(scene):
    rng = np.random.default_rng(3)
    rc = scene.recon
    shape = (2, 3, rc.nz, rc.ny, rc.nx)
    truth = rng.normal(0, 100, shape).astype(np.float32)
    recon = truth + rng.normal(5, 20, shape).astype(np.float32)
    res = table2(recon, truth, MetricsConfig.from_scene(scene))
    for fov, m in fov_masks(MetricsConfig.from_scene(scene)).items():
        d = np.abs(recon - truth)[..., m].astype(np.float64)       # (2, 3, nz, n_in)
        assert res[fov]["mae_hu"] == pytest.approx(d.mean(), rel=1e-9)
        assert res[fov]["std_hu"] == pytest.approx(d.std(), rel=1e-6)
        assert res[fov]["n_voxels"] == d.size
        per = np.array(res["per_target"][fov])
        assert per.shape == (2, 3)
        assert np.allclose(per, d.mean(axis=(2, 3)))
        assert abs_error_stats(recon, truth, m)["mae_hu"] == pytest.approx(d.mean(), rel=1e-9)


def test_table2_kept_arrays_give_the_same_sums_bit_for_bit(scene):
    """Table2.add with a kept scratch dictionary, shared by two accumulators and reused across
    targets, float16 and float32 inputs and two shapes, gives the float64 sums of the fresh-array
    formula it replaced (``x = |recon - truth|[:, idx].astype(float64)``; ``x.sum()``, ``(x * x).sum()``)."""
    rng = np.random.default_rng(11)
    cfg = MetricsConfig.from_scene(scene)
    rc = scene.recon
    sc: dict = {}
    accs = [Table2(cfg, 2, 2), Table2(cfg, 2, 2)]
    for nz, dtype in ((rc.nz, np.float32), (rc.nz + 3, np.float16), (rc.nz, np.float32)):
        for i in range(2):
            for j in range(2):
                truth = rng.normal(0, 300, (nz, rc.ny, rc.nx)).astype(dtype)
                for acc in accs:
                    recon = (truth + rng.normal(0, 40, truth.shape)).astype(dtype)
                    acc.add(i, j, recon, truth, sc)
                    ref = Table2(cfg, 2, 2)
                    _table2_fresh(ref, i, j, recon, truth)  # the bench's same-run reference: the old formula
                    for fov in acc.flat:
                        want = ref.sums[fov][i, j]
                        assert np.array_equal(acc.sums[fov][i, j].view(np.int64), want.view(np.int64)), (fov, nz, dtype)
                        assert acc.count[fov][i, j] == ref.count[fov][i, j] == nz * acc.flat[fov].size
    assert len(sc) == 5  # one difference array and two per FOV, reused (resized when the shape changed)


def test_masks(scene):
    m = fov_masks(MetricsConfig.from_scene(scene))
    assert m["small"].sum() < m["large"].sum()
    assert not (m["small"] & ~m["large"]).any()


def test_shape_mismatch_is_an_error(scene):
    with pytest.raises(ValueError, match="shape"):
        table2(np.zeros((1, 1, 2, 3, 3)), np.zeros((1, 1, 2, 3, 4)), MetricsConfig.from_scene(scene))


def test_blood_pool_volume_counts_only_inside_the_region():
    vol = np.zeros((8, 32, 32), np.float32)
    vol[2:6, 10:20, 12:17] = 400.0                     # 4 x 10 x 5 voxels above threshold
    vol[2:6, 20:28, 12:17] = 400.0                     # touching bright neighbour: outside the region
    region = np.zeros(vol.shape, bool)
    region[1:7, 8:20, 10:20] = True
    assert blood_pool_volume_ml(vol, region, 0.008) == pytest.approx(4 * 10 * 5 * 0.008)
    with pytest.raises(ValueError, match="shape"):
        blood_pool_volume_ml(vol, region[:-1], 0.008)


def test_lv_region_follows_the_phantom():
    from clrecon.evaluation.groundtruth import lv_region_mask
    from clrecon.simulation.phantoms.analytic import Phantom
    ph = Phantom()
    x = y = (np.arange(96) - 47.5) * 2.0
    z = (np.arange(60) - 29.5) * 2.0
    cav = lv_region_mask(ph, 0.0, 0.5, x, y, z, margin_mm=0.0)
    vol_ml = cav.sum() * 8 / 1000
    # the phantom's voxelised LV cavity at end-diastole matches its volume curve within 10 %
    # (2 mm voxels, the part inside the 120 mm slab)
    assert vol_ml == pytest.approx(ph.lv_blood_volume_ml(0.0), rel=0.10)
    grown = lv_region_mask(ph, 0.0, 0.5, x, y, z, margin_mm=6.0)
    assert grown.sum() > cav.sum() and not (cav & ~grown).any()
    inhale = lv_region_mask(ph, 0.0, 1.0, x, y, z, margin_mm=0.0)
    zc = lambda m: (m.sum(axis=(1, 2)) * z).sum() / m.sum()   # noqa: E731
    assert zc(inhale) < zc(cav) - 3.0                   # the heart moves down on inhale
