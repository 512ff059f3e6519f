"""The later pitches planned in a second process (clrecon.pipeline.plan_ahead): the same run
bit for bit, the plan handed over only for the request it was made for."""

import json

import numpy as np
import pytest
from run_compare import QUIET, assert_identical

from clrecon.config.scene import load_scene
from clrecon.pipeline import plan_ahead, slabs
from clrecon.pipeline.run import resolve_targets, run
from clrecon.reconstruction import reconstruct

PITCHES = (0.1, 0.2)


def _run(tmp_path_factory, monkeypatch, setting: str):
    monkeypatch.setenv(plan_ahead.ENV, setting)
    out, cache = tmp_path_factory.mktemp(f"ahead{setting}"), tmp_path_factory.mktemp("cache")
    return out, run(load_scene("tiny"), out, cache_dir=cache, pitches=PITCHES, **QUIET)


def test_a_run_with_the_later_pitch_planned_ahead_is_identical(tmp_path_factory, monkeypatch):
    ref = _run(tmp_path_factory, monkeypatch, "0")
    out, _ = _run(tmp_path_factory, monkeypatch, "1")
    res = assert_identical(out, ref)
    assert res["stages"]["plan"]["beside_seconds"] > 0 and "waited_for" in res["stages"]["plan"]
    assert "beside_seconds" not in ref[1]["stages"]["plan"]
    # each method's planning seconds are still reported for both pitches (the error-vs-time figure)
    assert set(res["method_plan_seconds"]) == {"p0.100", "p0.200"}
    assert json.loads((out / "results.json").read_text())["request"]["pitches"] == list(PITCHES)


def test_the_plan_is_handed_over_only_for_the_request_it_was_made_for():
    scene = load_scene("tiny")
    cfg = reconstruct.ReconstructionConfig.from_scene(scene)
    z = reconstruct.slice_positions(scene)
    targets = resolve_targets(scene)
    methods = ("nearest", "barycentric")
    every = np.arange(len(z))
    ahead = plan_ahead.PlanAhead(scene, cfg, (0.2, 0.3), z, targets, methods, 1)
    try:
        assert ahead.take(0.2, every[1:], methods) is None        # a resumed run: some slices done
        assert ahead.take(0.3, every, ("nearest",)) is None       # other methods
        assert ahead.take(0.4, every, methods) is None            # a pitch not planned
    finally:
        ahead.close()
    ahead = plan_ahead.PlanAhead(scene, cfg, (0.2,), z, targets, methods, 1)
    try:
        pp = ahead.take(0.2, every, methods)
    finally:
        ahead.close()
    here = slabs.plan_pitch(scene, cfg, 0.2, z, every, targets, methods, 1, False)
    assert np.array_equal(pp.needed, here.needed) and pp.slabs == here.slabs
    for a, b in zip(pp.plans, here.plans, strict=True):
        for m in methods:
            assert np.array_equal(a.methods[m].proj_index, b.methods[m].proj_index)
            assert np.array_equal(a.methods[m].weight.view(np.uint64), b.methods[m].weight.view(np.uint64))
    assert ahead.beside_seconds > 0 and ahead.wait_seconds >= 0


@pytest.mark.parametrize("setting,n,want", [("0", 2, False), ("1", 2, True), ("1", 1, False), ("", 1, False)])
def test_enabled(monkeypatch, setting, n, want):
    monkeypatch.setenv(plan_ahead.ENV, setting)
    assert plan_ahead.enabled(n) is want
