"""Per-target weight diagnostics (clrecon.reconstruction.diagnostics) on the `tiny` scene's plans:
ranges, agreement with the plan's own weights, and the barycentric |dc| limit as a law."""

from __future__ import annotations

import numpy as np
import pytest

from clrecon.config.scene import load_scene
from clrecon.core.conventions import circular_difference
from clrecon.reconstruction import reconstruct
from clrecon.reconstruction.diagnostics import pooled, weight_diagnostics
from clrecon.reconstruction.interpolation import barycentric as ip_bary
from clrecon.scan import table as geometry

# The triangle |dc| limit is tested up to the rounding the method itself allows.
DC_LIMIT = ip_bary.BARY_MAX_DC + ip_bary.BARY_DC_ROUNDING


@pytest.fixture(scope="module", params=[(0.02, ((0.4,), (0.75,))), (0.1, ((0.0, 0.4), (0.25, 0.75)))],
                ids=["p0.02-issue-target", "p0.10-tiny-grid"])
def tiny_plan(request):
    scene = load_scene("tiny")
    pitch, (cardiac, resp) = request.param
    targets = reconstruct.Targets(cardiac=cardiac, resp=resp)
    cfg = reconstruct.ReconstructionConfig.from_scene(scene)
    table = geometry.projection_table(scene, pitch)
    methods = tuple(dict.fromkeys(("barycentric", "local_linear", "nearest") + tuple(scene.recon.methods)))
    p = reconstruct.plan(cfg, table, reconstruct.slice_positions(scene), targets, methods)
    return p, table, targets


def test_diagnostics_exist_for_every_method_and_target_within_their_ranges(tiny_plan):
    p, table, targets = tiny_plan
    diag = weight_diagnostics(p, table, targets)
    n_t = targets.shape[0] * targets.shape[1]
    assert set(diag) == set(p.methods)
    for m, d in diag.items():
        assert d["targets"] == targets.pairs.tolist()
        assert len(d["max_abs_dc"]) == len(d["max_abs_da"]) == n_t, m
        assert all(0.0 <= x <= 0.5 for x in d["max_abs_dc"]), m
        assert all(0.0 <= x <= 1.0 for x in d["max_abs_da"]), m
        if "branch_share" in d:
            shares = np.array(list(d["branch_share"].values()))
            assert np.all((shares >= 0) & (shares <= 1)) and np.allclose(shares.sum(0), 1.0), m
    assert set(diag["barycentric"]["branch_share"]) == set(ip_bary.BRANCH_NAMES)
    assert "branch_share" not in diag["nearest"]
    pb = pooled(diag["barycentric"])
    assert pb["max_abs_dc"] == max(diag["barycentric"]["max_abs_dc"])
    assert sum(pb[nm] for nm in ip_bary.BRANCH_NAMES) == pytest.approx(1.0)


def test_diagnostics_match_the_plan_weights(tiny_plan):
    """Independent recomputation: for every grid target, the largest circular |dc| and |da|
    over the (slice, view, slot) entries of the plan with non-zero weight."""
    p, table, targets = tiny_plan
    diag = weight_diagnostics(p, table, targets)
    pairs = targets.pairs
    for m, mp in p.methods.items():
        n_cs, n_rs = mp.targets_shape
        for t, (cs, as_) in enumerate(pairs):
            i, j = divmod(t, targets.shape[1])
            ts = (i % n_cs) * n_rs + (j % n_rs)
            used = mp.weight[:, :, ts] != 0
            proj = mp.proj_index[:, :, ts][used]
            assert diag[m]["max_abs_dc"][t] == pytest.approx(
                np.abs(circular_difference(table.cardiac_phase[proj], cs)).max(), abs=1e-12)
            assert diag[m]["max_abs_da"][t] == pytest.approx(np.abs(table.resp_amplitude[proj] - as_).max(), abs=1e-12)
        if mp.branch is not None:
            for nm, k in zip(ip_bary.BRANCH_NAMES, range(3), strict=True):
                share = (mp.branch == k).mean(axis=(0, 1))
                np.testing.assert_allclose(diag[m]["branch_share"][nm], share[: len(pairs)], atol=1e-12)


def test_barycentric_uses_no_vertex_beyond_the_cardiac_limit(tiny_plan):
    """The law the triangle |dc| limit makes true: in the triangle and segment branches every
    row with non-zero weight lies within BARY_MAX_DC of the target in circular c. Only the
    nearest branch may use a farther row (the nearest point itself; at pitch 0.1 the target
    (0.4, 0.75) takes it in most (slice, view) pairs), so the per-target diagnostic obeys the
    limit wherever no (slice, view) took the nearest branch."""
    p, table, targets = tiny_plan
    mp = p.methods["barycentric"]
    assert mp.branch is not None and mp.branch.shape == mp.weight.shape[:3]
    pairs = targets.pairs
    dc = np.abs(circular_difference(table.cardiac_phase[mp.proj_index], pairs[None, None, :, 0, None]))
    interp = np.isin(mp.branch, (ip_bary.BRANCH_TRIANGLE, ip_bary.BRANCH_SEGMENT))[..., None] & (mp.weight != 0)
    assert interp.any()
    assert dc[interp].max() <= DC_LIMIT
    diag = weight_diagnostics(p, table, targets)["barycentric"]
    no_nearest = np.array(diag["branch_share"]["nearest"]) == 0.0
    assert no_nearest.any()
    assert np.all(np.array(diag["max_abs_dc"])[no_nearest] <= DC_LIMIT)
