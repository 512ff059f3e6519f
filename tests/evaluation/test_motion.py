"""Motion metrics (clrecon.evaluation.motion): edge width, centroid, LV volume error, noise std.

Synthetic images with known answers, then one small run end to end. Tolerances live in ``TOL``.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from scipy.special import ndtr, ndtri

from clrecon.config.scene import load_scene
from clrecon.core.conventions import voxel_coords
from clrecon.evaluation import motion as mo
from clrecon.pipeline.run import run

#: 10-90 % width of a Gaussian edge of std sigma: 2 * Phi^-1(0.9) sigma
K_10_90 = 2.0 * 1.2815515655446004

#: name -> (value, reason)
TOL = {
    "centroid_voxel": (0.1, "the brief's law: a shifted blob recovers its shift within 0.1 voxel"),
    "noise_se": (4.0, "standard errors of a sample std, sigma / sqrt(2N), for seeded Gaussian noise"),
}


def tol(name):
    return TOL[name][0]


def _cfg(n=128, h=1.0, nz=1, **kw):
    x = voxel_coords(n, h)
    return mo.MotionConfig.from_grid(x, x, voxel_coords(nz, h), slice_mm=h, **kw)


def _disc(cfg, centre, radius, sigma=None):
    """HU image (1, ny, nx): myocardium outside, blood inside a disc; a Gaussian edge of std sigma (mm)."""
    xx, yy = np.meshgrid(np.asarray(cfg.x_mm), np.asarray(cfg.y_mm))
    r = np.hypot(xx - centre[0], yy - centre[1])
    inside = (r <= radius).astype(float) if sigma is None else ndtr((radius - r) / sigma)
    return (cfg.hu_myocardium + (cfg.hu_blood - cfg.hu_myocardium) * inside)[None]


# ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize("sigma_vox", [2.0, 3.0])
def test_edge_width_of_a_gaussian_edge_is_2563_sigma(sigma_vox):
    """A disc with a Gaussian edge of std sigma: every radial profile's 10-90 % width is 2.563 sigma.

    Linear interpolation (bilinear in the image, then along the profile) can only widen an edge
    that is concave at its 90 % point and convex at its 10 % point, by at most (to leading
    order) h^2/8 |f''/f'| at each end: relative 0.125 (h^2 + step^2) / sigma^2 in all."""
    h = 1.0
    cfg = _cfg(h=h)
    centre = (3.3, -2.7, 0.0)
    sigma = sigma_vox * h
    w = mo.edge_widths(_disc(cfg, centre, 35.0, sigma), cfg, centre)
    assert np.isfinite(w).all()
    rel = w / (K_10_90 * sigma) - 1.0
    bound = 0.125 * (h * h + cfg.profile_step_mm ** 2) / sigma ** 2
    assert rel.min() >= 0.0 and rel.max() <= bound, (rel.min(), rel.max(), bound)
    med, n = mo.edge_width_summary(w)
    assert n == cfg.n_profiles and med == pytest.approx(K_10_90 * sigma, rel=bound)


def test_sharp_disc_edge_is_at_most_about_one_voxel():
    h = 3.0
    cfg = _cfg(n=64, h=h)
    centre = (1.1, 2.3, 0.0)
    w = mo.edge_widths(_disc(cfg, centre, 40.0), cfg, centre)
    med, n = mo.edge_width_summary(w)
    assert n == cfg.n_profiles and med <= h


def test_edge_width_skips_profiles_without_a_clean_transition():
    cfg = _cfg()
    centre = (0.0, 0.0, 0.0)
    flat = np.full((1, 128, 128), cfg.hu_blood)
    assert mo.edge_width_summary(mo.edge_widths(flat, cfg, centre))[1] == 0
    # an edge that only falls half way (blood -> 245 HU) is not a blood -> myocardium transition
    half = _disc(cfg, centre, 30.0, 2.0)
    half = np.maximum(half, 0.5 * (cfg.hu_blood + cfg.hu_myocardium) - 10.0)
    assert np.isnan(mo.edge_widths(half, cfg, centre)).all()
    # with the true boundary radius given, the edge far from it (here: a second ring) is not taken
    img = _disc(cfg, centre, 20.0, 2.0)
    exp = np.full(cfg.n_profiles, 20.0)
    exp[:4] = 45.0           # nothing within the search window of 45 mm
    exp[4] = np.nan          # not a clean wall crossing in the phantom
    w = mo.edge_widths(img, cfg, centre, exp)
    assert np.isnan(w[:5]).all() and np.isfinite(w[5:]).all()
    assert mo.edge_width_summary(w)[1] == cfg.n_profiles - 5


def test_edge_width_ignores_a_profile_leaving_the_grid():
    cfg = _cfg(n=32)
    centre = (10.0, 0.0, 0.0)
    w = mo.edge_widths(_disc(cfg, centre, 12.0, 2.0), cfg, centre)
    assert np.isfinite(w[[4, 8, 12]]).all()   # +y, -x, -y: inside the grid
    assert np.isnan(w[0])                       # +x: the grid ends (x <= 15.5 mm) before the 10 % point


# ---------------------------------------------------------------------------------------------
def _blob_cfg(**kw):
    g = voxel_coords(32, 1.0)
    return mo.MotionConfig.from_grid(g, g, voxel_coords(20, 1.0), lesion_box_mm=7.0, lesion_threshold_hu=500.0,
                                     lesion_radius_mm=3.0, **kw)


def _grid(cfg):
    return np.meshgrid(np.asarray(cfg.z_mm), np.asarray(cfg.y_mm), np.asarray(cfg.x_mm), indexing="ij")


def test_centroid_recovers_a_shift_within_a_tenth_of_a_voxel():
    cfg = _blob_cfg()
    Z, Y, X = _grid(cfg)
    rng = np.random.default_rng(7)
    centre = np.array([0.2, -0.3, 0.4])
    for _ in range(20):
        s = rng.uniform(-1.5, 1.5, 3)
        p = centre + s
        blob = 1000.0 * np.exp(-((X - p[0]) ** 2 + (Y - p[1]) ** 2 + (Z - p[2]) ** 2) / (2 * 1.5 ** 2))
        err = mo.target_error(blob, cfg, centre)
        np.testing.assert_allclose(err, s, atol=tol("centroid_voxel"))
        # a bright neighbour below the threshold (a blood pool at 400 HU) weighs nothing
        with_pool = np.where(X > 3.5, np.maximum(blob, 400.0), blob)
        np.testing.assert_allclose(mo.target_error(with_pool, cfg, centre), err, atol=1e-12)


def test_centroid_not_measured_when_absent_or_outside_the_slab():
    cfg = _blob_cfg()
    vol = np.full((20, 32, 32), 90.0)
    assert np.isnan(mo.target_error(vol, cfg, np.zeros(3))).all()           # nothing above the threshold
    z_top = max(cfg.z_mm)
    assert not mo.lesion_in_slab(cfg, np.array([0.0, 0.0, z_top - 1.0]))
    assert np.isnan(mo.target_error(vol + 1000.0, cfg, np.array([0.0, 0.0, z_top - 1.0]))).all()


# ---------------------------------------------------------------------------------------------
def _geometry(cfg, vol):
    mask = np.zeros(vol.shape, bool)
    mask[:, 40:90, 40:90] = True
    return mo.TargetGeometry(lv_centre_mm=np.array([0.0, 0.0, 0.0]), lesion_centre_mm=np.full(3, np.nan),
                             edge_expected_mm=np.full(cfg.n_profiles, 20.0), lv_region=mo.crop_to_mask(mask),
                             lv_true_ml=math.nan)


def test_truth_against_itself_has_no_volume_error_and_no_noise():
    cfg = _cfg(nz=3)
    vol = np.repeat(_disc(cfg, (0.0, 0.0), 20.0, 1.5), 3, axis=0)
    geom = _geometry(cfg, vol)
    ref, same = mo.MotionMetrics(cfg, 1, 1), mo.MotionMetrics(cfg, 1, 1)
    ref.add(0, 0, vol, None, geom)
    same.add(0, 0, vol, vol, geom, ref.lv_ml[0, 0])
    r, s = ref.result(), same.result()
    assert s["lv_volume_error_ml"]["mean"] == 0.0 and s["lv_volume_error_ml"]["per_target"] == [[0.0]]
    assert s["noise_std_hu"]["mean"] == 0.0
    assert s["edge_width_mm"] == r["edge_width_mm"]
    # the volume is the disc's inside the 220 HU contour (radius 20 mm + 1.5 mm * Phi^-1(1 - q), q the
    # threshold's fraction of the edge), 1 mm^3 voxels over 3 slices; counting pixel centres in a
    # disc of ~1300 pixels errs by a few pixels (Gauss circle problem): 1 %
    q = (cfg.lv_threshold_hu - cfg.hu_myocardium) / (cfg.hu_blood - cfg.hu_myocardium)
    r220 = 20.0 - 1.5 * ndtri(q)
    assert s["lv_volume_error_ml"]["volume_ml_per_target"][0][0] == pytest.approx(3 * np.pi * r220 ** 2 / 1000,
                                                                                rel=0.01)
    assert r["noise_std_hu"] is None and r["lv_volume_error_ml"]["mean"] is None
    assert s["target_error_mm"]["found"] == 0 and s["target_error_mm"]["mean"] is None   # no lesion given
    json.dumps(s, allow_nan=False)


def test_noise_std_of_pure_gaussian_noise_recovers_sigma():
    cfg = _cfg(n=64, nz=8, noise_centre_mm=(5.0, -4.0), noise_radius_mm=15.0)
    mask = mo.noise_region_mask(cfg)
    n = int(mask.sum()) * 8
    assert n > 5000
    truth = np.zeros((8, 64, 64), np.float32)
    truth[:, :32] = 400.0      # structure in the truth does not matter: the std is of recon - truth
    rng = np.random.default_rng(11)
    for sigma in (5.0, 30.0):
        recon = truth + rng.normal(0.0, sigma, truth.shape).astype(np.float32)
        est = mo.noise_std(recon, truth, mask)
        assert abs(est - sigma) <= tol("noise_se") * sigma / math.sqrt(2 * n)
    assert mo.noise_std(truth + 7.0, truth, mask) == pytest.approx(0.0, abs=1e-9)  # an offset is not noise


# ---------------------------------------------------------------------------------------------
#: a tiny-sized scene whose slab and grid hold the lesion: 4 mm voxels, 10 slices of 4 mm, one target
SCENE_OVERRIDES = {"recon": {"nx": 96, "ny": 96, "voxel_mm": 4.0, "nz": 10, "slice_mm": 4.0},
                   "scan": {"coverage_mm": 70.0}}


@pytest.fixture(scope="module")
def small_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("motion_run")
    scene = load_scene("tiny").replace(**SCENE_OVERRIDES)
    res = run(scene, out, methods=["local_linear", "nearest"], cardiac=[0.0], resp=[0.75],
              cache_dir=tmp_path_factory.mktemp("motion_cache"), progress=False, log=lambda *a: None)
    return out, res


def test_run_has_the_motion_block_with_finite_numbers(small_run):
    out, res = small_run
    on_disk = json.loads((out / "results.json").read_text())
    mot = on_disk["motion"]
    assert set(mot) == {"p0.100"} and set(mot["p0.100"]) == {"noisy", "noise-free"}
    for bym in mot["p0.100"].values():
        assert set(bym) == {"groundtruth", "local_linear", "nearest"}
        for m, e in bym.items():
            assert math.isfinite(e["edge_width_mm"]["mean"])
            assert e["edge_width_mm"]["valid_profiles_per_target"][0][0] > 0
            t = e["target_error_mm"]
            assert t["found"] == 1 and math.isfinite(t["mean"])
            assert t["per_target"][0][0] == pytest.approx(np.linalg.norm(t["vector_per_target"][0][0]))
            assert e["lv_volume_error_ml"]["volume_ml_per_target"][0][0] > 0
            if m == "groundtruth":
                assert e["noise_std_hu"] is None
                assert t["mean"] < 4.0   # the grid's own localisation floor: under one voxel
            else:
                assert math.isfinite(e["lv_volume_error_ml"]["mean"]) and math.isfinite(e["noise_std_hu"]["mean"])
    std = {v: {m: mot["p0.100"][v][m]["noise_std_hu"]["mean"] for m in ("local_linear", "nearest")}
           for v in ("noisy", "noise-free")}
    for m in ("local_linear", "nearest"):   # independent noise adds variance
        assert std["noisy"][m] > std["noise-free"][m]
    assert on_disk["motion_definitions"]["noise"]["radius_mm"] > 0
    md = (out / "report.md").read_text()
    assert "## Motion metrics" in md and "(figures/motion_metrics.png)" in md
    assert (out / "figures" / "motion_metrics.png").stat().st_size > 10_000
