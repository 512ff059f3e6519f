"""The data-consistency residual (clrecon/evaluation/consistency.py, docs/consistency.md "Did it
help? A truth-free check"): its lattice weights against a brute-force reference, its projector's
geometry against the FBP, zero for rows made from the volumes it is given, larger for wrong
volumes, a rigid-motion negative control, and the comparison's verdict."""

import numpy as np
import pytest

from clrecon.config.scene import load_scene
from clrecon.evaluation import consistency as cs
from clrecon.reconstruction import fbp as fbp_mod
from clrecon.reconstruction import reconstruct as rc


@pytest.fixture(scope="module")
def tiny_cfg():
    return rc.ReconstructionConfig.from_scene(load_scene("tiny").replace(recon={"nx": 64, "ny": 64, "voxel_mm": 6.0}))


def _bilinear_reference(c, a, cardiac, resp):
    """Dense (p, n_c * n_r) weights from NumPy's interpolation of each target's indicator
    (``np.interp`` with ``period=1`` in c; it clamps a at the ends)."""
    ec, er = np.eye(len(cardiac)), np.eye(len(resp))
    wc = np.stack([np.interp(c, cardiac, ec[i], period=1.0) for i in range(len(cardiac))], axis=1)
    wr = np.stack([np.interp(a, resp, er[j]) for j in range(len(resp))], axis=1)
    return (wc[:, :, None] * wr[:, None, :]).reshape(len(c), -1)


def test_lattice_weights_match_a_brute_force_reference():
    rng = np.random.default_rng(3)
    cardiac, resp = [0.0, 0.15, 0.4, 0.6, 0.85], [0.05, 0.15, 0.45, 0.95]  # uneven lattices
    c = np.concatenate([rng.uniform(-0.5, 1.5, 200), [0.0, 0.85, 0.9, 0.999, 0.2]])
    a = np.concatenate([rng.uniform(-0.2, 1.2, 200), [0.05, 0.95, 0.5, -1.0, 2.0]])
    c[-3] = 0.925  # halfway between 0.85 and 1.0 (= 0.0)
    idx, w = cs.lattice_weights(c, a, cardiac, resp)
    dense = np.zeros((c.size, 20))
    np.add.at(dense, (np.repeat(np.arange(c.size), 4), idx.ravel()), w.ravel())
    assert np.allclose(dense, _bilinear_reference(c, a, cardiac, resp), atol=1e-12)
    assert np.allclose(w.sum(axis=1), 1.0)
    # at a lattice node the weight is all on that target; c = 0.925 wraps halfway between 0.85 and 0.0
    assert dense[-5, 0] == pytest.approx(1.0) and dense[-4, 4 * 4 + 3] == pytest.approx(1.0)
    assert dense[-3, 16:20].sum() == pytest.approx(0.5) and dense[-3, 0:4].sum() == pytest.approx(0.5)


def test_lattice_weights_of_a_single_target_axis_and_bad_lattices():
    idx, w = cs.lattice_weights([0.3, 0.7], [0.5, 0.1], [0.0], [0.1, 0.9])
    assert np.allclose(w.sum(axis=1), 1) and set(idx[w > 0].tolist()) <= {0, 1}
    with pytest.raises(ValueError, match="distinct"):
        cs.lattice_weights([0.3], [0.5], [0.2, 0.2], [0.5])


def test_projections_have_the_fbp_geometry(tiny_cfg):
    """FBP of the projections of an off-centre image at every view gives that image back, not a mirror."""
    g = tiny_cfg.fbp
    yy, xx = np.mgrid[:g.ny, :g.nx]
    img = np.zeros((g.ny, g.nx))
    img[(xx - 40) ** 2 + (yy - 22) ** 2 < 36] = 0.02
    img[(xx - 20) ** 2 + (yy - 36) ** 2 < 16] = 0.01
    sino = cs.inplane_projections(img[None], g.voxel_mm, tiny_cfg.scanner.detector_model, g, np.zeros(g.n_views, int),
                                  np.arange(g.n_views))
    rec = fbp_mod.fbp(sino[None], g, tiny_cfg.filter)[0]
    assert np.corrcoef(rec.ravel(), img.ravel())[0, 1] > 0.9
    for wrong in (rec[::-1], rec[:, ::-1], rec.T):
        assert abs(np.corrcoef(wrong.ravel(), img.ravel())[0, 1]) < 0.3


def _disc(g, centre_x_mm, radius_mm=40.0, mu=0.02):
    x = (np.arange(g.nx) - (g.nx - 1) / 2) * g.voxel_mm
    y = (np.arange(g.ny) - (g.ny - 1) / 2) * g.voxel_mm
    return np.where((x[None, :] - centre_x_mm) ** 2 + y[:, None] ** 2 < radius_mm ** 2, mu, 0.0)


def _hu(mu, mu_w):
    return 1000.0 * (mu - mu_w) / mu_w


def _rows_setup(g, n=300, seed=0):
    rng = np.random.default_rng(seed)
    return (rng.integers(0, 2, n), rng.integers(0, g.n_views, n), rng.uniform(0, 1, n), rng.uniform(0, 1, n))


def test_rows_made_from_the_volumes_have_zero_residual(tiny_cfg):
    """Rows made exactly from the lattice's images (blended at each row's state) are predicted to
    float32 rounding; a static image at every target is the special case."""
    g, det, mu_w = tiny_cfg.fbp, tiny_cfg.scanner.detector_model, tiny_cfg.mu_water_per_mm
    cardiac, resp = [0.0, 0.5], [0.25, 0.75]
    vols = np.stack([np.stack([np.stack([_disc(g, 30.0 * np.sin(2 * np.pi * c) + 10 * a, 40 + 5 * s)
                                         for s in range(2)]) for a in resp]) for c in cardiac])
    sl, vw, c, a = _rows_setup(g)
    idx, w = cs.lattice_weights(c, a, cardiac, resp)
    flat = vols.reshape(4, 2, g.ny, g.nx)
    want = np.zeros((sl.size, g.n_cols))
    for k in range(4):
        proj = cs.inplane_projections(flat[idx[:, k], sl], g.voxel_mm, det, g, np.arange(sl.size), vw)
        want += w[:, k, None] * proj
    got = cs.predicted_rows(_hu(vols, mu_w), cardiac, resp, sl, vw, c, a, geom=g, detector=det, mu_water=mu_w)
    scale = np.abs(want).max()
    assert scale > 1.0 and np.abs(got - want).max() < 1e-5 * scale
    static = np.broadcast_to(vols[:1, :1], vols.shape)
    rows = cs.inplane_projections(static[0, 0], g.voxel_mm, det, g, sl, vw)
    pred = cs.predicted_rows(_hu(static, mu_w), cardiac, resp, sl, vw, c, a, geom=g, detector=det, mu_water=mu_w)
    r = cs.residual(rows, pred, {"all": np.ones(rows.shape, bool)}, np.zeros(sl.size, int), 1)
    assert r.rms("all") < 1e-5 * np.sqrt((rows.astype(float) ** 2).mean())


def test_rigid_motion_control_the_right_states_beat_one_state_and_a_wrong_image(tiny_cfg):
    """A disc moving rigidly with the cardiac phase (rows at its exact position at each row's state):
    the volumes at the right states leave a smaller residual than the same images all at one state
    (a method that ignores motion) and than a wrong image (the disc shrunk)."""
    g, det, mu_w = tiny_cfg.fbp, tiny_cfg.scanner.detector_model, tiny_cfg.mu_water_per_mm
    cardiac, resp = [0.0, 0.2, 0.4, 0.6, 0.8], [0.5]
    pos = lambda c: 36.0 * np.sin(2 * np.pi * c)  # noqa: E731
    sl, vw, c, _ = _rows_setup(g, 400, seed=1)
    sl = np.zeros_like(sl)
    a = np.full(c.size, 0.5)
    rows = np.concatenate([cs.inplane_projections(_disc(g, pos(ck))[None], g.voxel_mm, det, g, [0], [v])
                           for ck, v in zip(c, vw, strict=True)])
    right = np.stack([_disc(g, pos(ci)) for ci in cardiac])[:, None, None]
    one = np.broadcast_to(right[:1], right.shape)
    shrunk = np.stack([_disc(g, pos(ci), radius_mm=30.0) for ci in cardiac])[:, None, None]
    mask = {"all": np.ones(rows.shape, bool)}
    blocks = np.arange(sl.size) % 8
    res = {}
    for name, vols in (("right", right), ("one state", one), ("shrunk", shrunk)):
        pred = cs.predicted_rows(_hu(vols, mu_w), cardiac, resp, sl, vw, c, a, geom=g, detector=det, mu_water=mu_w)
        res[name] = cs.residual(rows, pred, mask, blocks, 8, scale=1000.0 / mu_w)
    assert res["right"].rms("all") < 0.5 * res["one state"].rms("all")
    assert res["right"].rms("all") < 0.5 * res["shrunk"].rms("all")
    assert cs.compare(res["right"], res["one state"], "all")["says"] == "lower"
    assert cs.compare(res["one state"], res["right"], "all")["says"] == "higher"


def _residual(sq, cells=10, n_slices=1):
    sq = np.asarray(sq, float)
    z = np.zeros_like(sq)
    return cs.Residual({"all": sq, "heart": sq / 2}, {"all": np.full(sq.size, cells), "heart": np.full(sq.size, cells)},
                       {"all": z, "heart": z}, n_slices)


BLOCKS = np.array([100, 120, 90, 110, 105, 95], float)  # one slice's six blocks


def _slices(*factors):
    """Residual of len(factors) slices, slice s the six BLOCKS times factors[s] (a mean-square factor)."""
    return _residual(np.concatenate([BLOCKS * f for f in factors]), n_slices=len(factors))


def test_verdict_says_helped_only_when_most_slices_are_consistently_lower():
    """Per slice a consistent difference over its blocks decides; over slices a sign test: 12 slices
    all 10 % lower in mean square help, all higher do not, 5 lower and 5 higher decide nothing."""
    base = _slices(*[1.0] * 12)
    better = _slices(*[0.9] * 12)
    assert cs.verdict({"mc": better, "barycentric": base})["helped"] is True
    assert cs.verdict({"mc": base, "barycentric": better})["helped"] is False
    half = _slices(*[0.9] * 5, *[1.1] * 5, 1.0, 1.0)
    v = cs.verdict({"mc": half, "barycentric": base})
    assert v["helped"] is None and v["regions"]["all"]["says"] == "no clear difference"
    e = v["regions"]["all"]
    assert (e["slices_lower"], e["slices_higher"], e["slices"]) == (5, 5, 12) and e["sign_test_p"] == 1.0
    assert cs.verdict({"barycentric": base})["helped"] is None


def test_within_a_slice_a_difference_must_be_consistent_over_its_blocks():
    base = _slices(*[1.0] * 8)
    mixed = np.concatenate([np.array([60, 150, 50, 140, 105, 95.0])] * 8)  # lower on average, not consistently
    v = cs.verdict({"mc": _residual(mixed, n_slices=8), "barycentric": base})
    assert v["regions"]["all"]["ratio"] < 1 and v["regions"]["all"]["slices_lower"] == 0
    assert v["helped"] is None and v["regions"]["all"]["says"] == "no clear difference"


def test_one_slice_with_a_large_residual_does_not_carry_the_verdict():
    """The whole-paper-p010 case (docs/results/mc-consistency.md): mc lower at most slices and twice
    barycentric's residual at one slice whose residual is large. Pooled over every block the one slice
    wins ("higher", z > 2); slice by slice mc is lower at 11 of 12 (sign test p 2 x 13 / 4096 = 0.006) and helped."""
    ref = [1.0] * 11 + [4.0]            # the last slice's residual is twice the others' RMS
    base = _slices(*ref)
    mc = _slices(*[0.81] * 11, 4.0 * 2.0 ** 2)
    v = cs.verdict({"mc": mc, "barycentric": base})
    e = v["regions"]["all"]
    assert e["pooled_says"] == "higher" and e["ratio"] > 1 and e["z"] > cs.Z_DECIDES
    assert (e["slices_lower"], e["slices_higher"]) == (11, 1) and e["sign_test_p"] == pytest.approx(2 * 13 / 4096)
    assert e["says"] == "lower" and v["helped"] is True
    assert "lower at 11, higher at 1 of 12 slices" in v["text"]


def test_a_sign_test_needs_six_slices_that_differ():
    """5 of 5 slices lower give p = 0.0625 (two-sided): no decision; 6 of 6 give 0.031: helped."""
    for n, helped in ((5, None), (6, True)):
        v = cs.verdict({"mc": _slices(*[0.9] * n), "barycentric": _slices(*[1.0] * n)})
        assert v["regions"]["all"]["sign_test_p"] == pytest.approx(2 * 0.5 ** n)
        assert v["helped"] is helped, (n, v["text"])
    assert "cannot decide" in cs.verdict({"mc": _slices(*[0.9] * 4), "barycentric": _slices(*[1.0] * 4)})["text"]


def test_a_difference_within_the_minimum_effect_is_no_clear_difference_whatever_z():
    """The static case (issue 41): mc equal to barycentric up to rounding has a residual lower or
    higher in every block by the same sliver, so the jackknife's SE is tiny and |z| large (z +8.9
    was reported as "did not help"); within MIN_EFFECT of 1 the comparison says no clear difference,
    at every slice and pooled. Just outside it, a consistent difference still decides."""
    base = _slices(*[1.0] * 8)
    for ratio in (1 + 1e-6, 1 - 1e-6, 1 + 0.9 * cs.MIN_EFFECT, 1 - 0.9 * cs.MIN_EFFECT):  # of the RMS
        sliver = _slices(*[ratio ** 2] * 8)
        c = cs.compare(sliver, base, "all")
        assert c["ratio"] == pytest.approx(ratio, abs=1e-12)
        assert abs(c["z"]) > 10 * cs.Z_DECIDES  # consistent over the blocks: z alone would decide
        assert c["says"] == "no clear difference" and c["below_min_effect"] is True, (ratio, c)
        v = cs.verdict({"mc": sliver, "barycentric": base})
        assert v["helped"] is None and "below the smallest effect" in v["text"], v
        assert v["regions"]["all"]["slices_lower"] == v["regions"]["all"]["slices_higher"] == 0
    for ratio, says, helped in ((1 + 1.2 * cs.MIN_EFFECT, "higher", False), (1 - 1.2 * cs.MIN_EFFECT, "lower", True)):
        outside = _slices(*[ratio ** 2] * 8)
        c = cs.compare(outside, base, "all")
        assert c["says"] == says and "below_min_effect" not in c, (ratio, c)
        v = cs.verdict({"mc": outside, "barycentric": base})
        assert v["helped"] is helped and v["regions"]["all"]["says"] == says


def test_residuals_split_into_slices_of_their_blocks():
    r = _residual(np.arange(12.0), n_slices=3)
    assert r.slice(1).sq["all"].tolist() == [4.0, 5.0, 6.0, 7.0] and r.slice(1).n_slices == 1
    assert r.per_slice_rms("all") == pytest.approx(np.sqrt(np.arange(12.0).reshape(3, 4).sum(1) / 40))
    with pytest.raises(ValueError, match="12 blocks do not split into 5 slices"):
        cs.residual(np.zeros((2, 3)), np.zeros((2, 3)), {"all": np.ones((2, 3), bool)}, [0, 1], 12, n_slices=5)


def test_channels_through_the_circle_on_a_flat_detector(tiny_cfg):
    """On a centred flat detector channel u passes within R of the axis iff |u| SID / sqrt(SDD^2 + u^2) <= R."""
    sc = load_scene("tiny").scanner
    g = tiny_cfg.fbp
    det = sc.detector_model
    m = cs.channels_through_circle(det, g, np.arange(0, g.n_views, 7), 150.0)
    u = det.ray_cells()[0]
    want = np.abs(u) * sc.sid_mm / np.sqrt(sc.sdd_mm ** 2 + u ** 2) <= 150.0
    assert 0 < want.sum() < u.size
    assert (m == want[None, :]).all()


def test_identical_methods_compare_as_no_difference_without_warnings():
    """A static scene gives every method the same volumes: z is 0, not NaN."""
    base = _residual([100, 120, 90, 110])
    with np.errstate(all="raise"):
        c = cs.compare(base, base, "all")
    assert c["z"] == 0.0 and c["says"] == "no clear difference" and c["ratio"] == 1.0
