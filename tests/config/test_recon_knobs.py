"""Reconstruction knobs that trade time for error: local-linear neighbours (quadrants / nearest,
count), ``max_turns``; defaults equal today's behaviour, the selections do what they say, the
kernel agrees with its float64 reference for other slot counts."""

from __future__ import annotations

import numpy as np
import pytest

from clrecon.config.scene import load_scene
from clrecon.core.conventions import circular_difference
from clrecon.core.errors import SceneError
from clrecon.reconstruction import rebin, reconstruct
from clrecon.reconstruction.interpolation import local_linear as ll
from clrecon.reconstruction.interpolation import weights as ip
from clrecon.scan.table import projection_table

# local_linear_weights kernel vs float64 reference, max |dl| / max(1, sum |l_ref|): the same
# bounds as tests/reconstruction/test_interpolate.py (double: rounding; single: cond(C) <= 1/LL_RCOND x eps)
TOL = {"ll_kernel_double": 1e-9, "ll_kernel_single": 1e-3, "weights_f64": 1e-9}

TARGETS = np.array([[c, a] for c in (0.0, 0.2, 0.4, 0.6, 0.8) for a in np.arange(0.05, 1.0, 0.1)])


# ---------------------------------------------------------------------------------------
# scene keys
@pytest.mark.parametrize("key,value,fragment", [
    ("local_linear_points", "fifth", "one of quadrants, nearest"),
    ("local_linear_count", 0, "an integer in 1..32"),
    ("local_linear_count", 2.0, "an integer in 1..32"),
    ("local_linear_count", 9, "at most 8"),       # quadrants: 4 x 9 > 32 slots
    ("max_turns", -1, "an integer in 0..10000"),
])
def test_scene_rejects_bad_knobs(key, value, fragment):
    with pytest.raises(SceneError, match=f"recon.{key}") as e:
        load_scene("tiny").replace(recon={key: value})
    assert fragment in str(e.value)


def test_scene_knob_defaults_are_todays_behaviour():
    rc = load_scene("tiny").recon
    assert (rc.local_linear_points, rc.local_linear_count, rc.max_turns) == ("quadrants", 2, 0)
    assert load_scene("tiny").replace(recon={"local_linear_points": "nearest", "local_linear_count": 9}) \
        .recon.local_linear_count == 9


# ---------------------------------------------------------------------------------------
# defaults: explicit values give the arrays of the implicit defaults
def _plan(scene, methods):
    cfg = reconstruct.ReconstructionConfig.from_scene(scene)
    table = projection_table(scene, scene.scan.pitches[0])
    targets = reconstruct.Targets(tuple(scene.cardiac_targets), tuple(scene.resp_targets))
    return reconstruct.plan(cfg, table, reconstruct.slice_positions(scene), targets, methods), table


def test_explicit_defaults_give_identical_plans():
    s = load_scene("tiny")
    methods = s.recon.methods
    implicit, _ = _plan(s, methods)
    explicit, _ = _plan(s.replace(recon={"local_linear_points": "quadrants", "local_linear_count": 2,
                                         "max_turns": 0}), methods)
    for m in methods:
        np.testing.assert_array_equal(implicit.methods[m].proj_index, explicit.methods[m].proj_index)
        np.testing.assert_array_equal(implicit.methods[m].weight, explicit.methods[m].weight)
    assert implicit.methods["local_linear"].weight.shape[-1] == ll.LL_SLOTS == 8
    # per-method plan seconds: one entry per method, together within the whole plan's time
    assert set(implicit.method_seconds) == set(methods)
    assert 0 < sum(implicit.method_seconds.values()) <= implicit.seconds + 1e-9


def test_explicit_defaults_give_identical_weights():
    rng = np.random.default_rng(3)
    c, a = rng.random(300), rng.random(300)
    off = np.array([0, 40, 41, 43, 120, 300])
    W0 = ip.batch_weights("local_linear", c, a, off, TARGETS)
    W1 = ip.batch_weights("local_linear", c, a, off, TARGETS, local_linear_points="quadrants", local_linear_count=2)
    np.testing.assert_array_equal(W0.index, W1.index)
    np.testing.assert_array_equal(W0.weight, W1.weight)


# ---------------------------------------------------------------------------------------
# the selections
def test_nearest_5_selects_exactly_the_5_nearest_with_circular_dc():
    rng = np.random.default_rng(11)
    for _ in range(20):
        n = int(rng.integers(6, 40))
        c, a = rng.random(n), rng.random(n)
        t = np.array([[rng.random(), rng.random()]])
        dc = circular_difference(c, t[0, 0])
        d2 = dc ** 2 + (a - t[0, 1]) ** 2
        want = set(np.argsort(d2)[:5].tolist())
        ids, count = ll._local_linear_select(dc[None, None], (a - t[0, 1])[None, None], d2[None, None], 3,
                                             "nearest", 5)
        assert ids.shape[-1] == 5 and int(count[0, 0]) == 5
        assert set(ids[0, 0].tolist()) == want
        W = ip.method_weights("local_linear", c, a, t, local_linear_points="nearest", local_linear_count=5)
        assert W.index.shape == (1, 5)
        live = W.weight[0] != 0
        assert set(W.index[0][live].tolist()) <= want
        assert abs(W.weight[0].sum() - 1) < TOL["weights_f64"] * max(1.0, np.abs(W.weight[0]).sum())


def test_nearest_with_fewer_candidates_than_slots_uses_them_all():
    c, a = np.array([0.1, 0.95, 0.5]), np.array([0.2, 0.4, 0.9])
    W = ip.method_weights("local_linear", c, a, [[0.0, 0.3]], local_linear_points="nearest", local_linear_count=8)
    assert W.index.shape == (1, 8)
    assert set(W.index[0][W.weight[0] != 0].tolist()) <= {0, 1, 2}
    assert abs(W.weight[0].sum() - 1) < TOL["weights_f64"] * max(1.0, np.abs(W.weight[0]).sum())


def test_one_per_quadrant_gives_at_most_four_slots_one_per_quadrant():
    rng = np.random.default_rng(5)
    c, a = rng.random(60), rng.random(60)
    W = ip.method_weights("local_linear", c, a, TARGETS, local_linear_count=1)
    assert W.index.shape == (len(TARGETS), 4)
    for t, (c0, a0) in enumerate(TARGETS):
        used = W.index[t][W.weight[t] != 0]
        assert len(used) <= 4
        dc, da = circular_difference(c[used], c0), a[used] - a0
        quad = (dc < 0).astype(int) + 2 * (da < 0).astype(int)
        assert len(set(quad.tolist())) == len(used)     # at most one point per quadrant
        # and it is that quadrant's nearest
        dca, daa = circular_difference(c, c0), a - a0
        qa = (dca < 0).astype(int) + 2 * (daa < 0).astype(int)
        d2 = dca ** 2 + daa ** 2
        for i, q in zip(used, quad, strict=True):
            assert d2[i] == d2[qa == q].min()


def test_three_per_quadrant_in_a_sparse_chunk():
    # groups with fewer candidates than 3 per quadrant (even fewer than 3 in all) still work
    c = np.array([0.1, 0.3, 0.7, 0.1, 0.9])
    a = np.array([0.2, 0.8, 0.5, 0.5, 0.1])
    W = ip.batch_weights("local_linear", c, a, [0, 2, 5], TARGETS, local_linear_count=3)
    assert W.index.shape == (2, len(TARGETS), 12)
    sums = W.weight.sum(-1)
    assert np.all(np.abs(sums - 1) < TOL["weights_f64"] * np.maximum(1.0, np.abs(W.weight).sum(-1)))
    assert np.all((W.index[0] < 2) | (W.weight[0] == 0)) and np.all((W.index[1] >= 2) | (W.weight[1] == 0))


def test_bad_rule_or_count_is_a_value_error():
    with pytest.raises(ValueError, match="local_linear_points"):
        ip.method_weights("local_linear", [0.1], [0.2], TARGETS, local_linear_points="fifth")
    with pytest.raises(ValueError, match="local_linear_count"):
        ip.method_weights("local_linear", [0.1], [0.2], TARGETS, local_linear_count=9)


# ---------------------------------------------------------------------------------------
# the kernel for other slot counts
@pytest.mark.parametrize("K", [4, 5])
@pytest.mark.parametrize("precision", ["double", "single"])
def test_local_linear_kernel_matches_reference_for_other_slot_counts(K, precision):
    rng = np.random.default_rng(100 + K)
    n = 1500
    dc, da = rng.normal(0, 0.1, (n, K)), rng.normal(0, 0.2, (n, K))
    count = rng.integers(0, K + 1, n)
    dc[:20] = 0.1                   # coinciding
    da[20:40] = 0.3                 # one amplitude
    dc[40:60] = da[40:60] = np.linspace(-0.3, 0.3, K)  # collinear
    guard = np.arange(n) % 4
    ref = ip.local_linear_solve_reference(dc, da, count, 1.0, 0.15, guard=guard)
    got = ip.local_linear_solve(dc, da, count, 1.0, 0.15, precision=precision, guard=guard)
    assert got.shape == (n, K)
    scale = np.maximum(1.0, np.abs(ref).sum(1))
    assert np.all(np.isfinite(got))
    assert np.all(np.abs(got - ref).max(1) / scale < TOL[f"ll_kernel_{precision}"])
    live = count > 0
    assert np.all(np.abs(ref[live].sum(1) - 1) < TOL["weights_f64"] * scale[live])
    assert np.all(ref[~live] == 0)


# ---------------------------------------------------------------------------------------
# max_turns
def test_max_turns_1_keeps_only_the_nearest_in_z():
    s = load_scene("tiny")
    table = projection_table(s, s.scan.pitches[0])
    g = rebin.candidate_groups(table, reconstruct.slice_positions(s), s.scanner, reconstruct.object_radius_mm(s))
    assert g.counts.max() > 1   # something to drop
    one = reconstruct.limit_turns(g, 1)
    assert np.all(one.counts == np.minimum(g.counts, 1))
    for k in range(g.n_groups):
        lo, hi = g.offsets[k], g.offsets[k + 1]
        best = lo + int(np.argmin(np.abs(g.dz_mm[lo:hi])))
        assert one.projection[one.offsets[k]] == g.projection[best]
        assert one.dz_mm[one.offsets[k]] == g.dz_mm[best]
    two = reconstruct.limit_turns(g, 2)      # kept in projection order, the two nearest
    for k in range(g.n_groups):
        lo, hi = g.offsets[k], g.offsets[k + 1]
        near = np.sort(g.projection[lo + np.argsort(np.abs(g.dz_mm[lo:hi]), kind="stable")[:2]])
        np.testing.assert_array_equal(two.projection[two.offsets[k]:two.offsets[k + 1]], near)
    # enough turns for every group: unchanged
    same = reconstruct.limit_turns(g, int(g.counts.max()))
    np.testing.assert_array_equal(same.projection, g.projection)
    np.testing.assert_array_equal(same.offsets, g.offsets)


def test_max_turns_1_plan_uses_only_the_nearest_turn():
    s = load_scene("tiny").replace(recon={"max_turns": 1})
    p, table = _plan(s, ("nearest", "barycentric", "local_linear"))
    g = rebin.candidate_groups(table, p.slices_z, s.scanner, reconstruct.object_radius_mm(s))
    nv = s.scanner.views_per_rotation
    for mp in p.methods.values():
        S, V, T, K = mp.proj_index.shape
        for si in range(S):
            for v in range(V):
                k = si * nv + v
                lo, hi = g.offsets[k], g.offsets[k + 1]
                best = g.projection[lo + int(np.argmin(np.abs(g.dz_mm[lo:hi])))]
                used = mp.proj_index[si, v][mp.weight[si, v] != 0]
                assert np.all(used == best)


# ---------------------------------------------------------------------------------------
# results.json["sampling"] counts the candidates the plan uses (candidate window, max_turns)
def test_sampling_summary_follows_the_candidate_window_and_max_turns():
    from clrecon.pipeline import slabs

    s = load_scene("demo").replace(scan={"pitches": [0.02]})
    targets = reconstruct.Targets((0.0, 0.4), (0.25, 0.75))
    z = reconstruct.slice_positions(s)[8:9]  # mid-scan: a wider window adds turns

    def cands(scene):
        cfg = reconstruct.ReconstructionConfig.from_scene(scene)
        pp = slabs.plan_pitch(scene, cfg, scene.scan.pitches[0], z, np.arange(1), targets, ["nearest"], 1, False)
        return pp.sampling["candidates_per_view"]["median"]

    n0 = cands(s)
    assert cands(s.replace(recon={"candidate_window_mm": 2.0 * s.scanner.collimation_iso_mm})) > n0
    assert cands(s.replace(recon={"max_turns": 1})) == 1
