"""The run's one helper process (clrecon.pipeline.helper_process): the plans ahead, the metrics'
second group and the results-only figures in one warm child, and the run the same bit for bit."""

import os
import signal
import subprocess
import sys

import pytest
from run_compare import QUIET, assert_identical

from clrecon.config.scene import load_scene
from clrecon.core import resources
from clrecon.outputs import figures
from clrecon.pipeline import evaluate as evaluate_mod
from clrecon.pipeline import helper_process, plan_ahead
from clrecon.pipeline.run import resolve_targets, run
from clrecon.reconstruction import reconstruct

PITCHES = (0.1, 0.2)


def _run(tmp_path_factory, monkeypatch, helper: str):
    monkeypatch.setenv(helper_process.ENV, helper)
    for env in (plan_ahead.ENV, evaluate_mod.PROCESSES_ENV, figures.FIGURE_PROCESS_ENV):
        monkeypatch.delenv(env, raising=False)
    out, cache = tmp_path_factory.mktemp(f"helper{helper}"), tmp_path_factory.mktemp("cache")
    return out, run(load_scene("tiny"), out, cache_dir=cache, pitches=PITCHES, **QUIET)


def test_one_helper_serves_the_plans_the_metrics_and_the_figures(tmp_path_factory, monkeypatch):
    """With the helper, the run spawns exactly one child (not one per part), the metrics run in
    two processes (a warm child: whatever the size), the later pitch is planned there, and
    volumes, metrics and figures equal those of a run without any second process."""
    spawned = []
    real = resources.spawned_pool

    def counting(n):
        spawned.append(n)
        return real(n)

    for mod in (helper_process, plan_ahead, evaluate_mod, figures):
        monkeypatch.setattr(mod, "spawned_pool", counting)
    monkeypatch.setenv(plan_ahead.ENV, "0")  # the reference: no second process at all
    monkeypatch.setenv(evaluate_mod.PROCESSES_ENV, "1")
    monkeypatch.setenv(figures.FIGURE_PROCESS_ENV, "0")
    monkeypatch.setenv(helper_process.ENV, "0")
    out0, cache0 = tmp_path_factory.mktemp("helper0"), tmp_path_factory.mktemp("cache")
    ref = (out0, run(load_scene("tiny"), out0, cache_dir=cache0, pitches=PITCHES, **QUIET))
    assert spawned == []
    assert ref[1]["stages"]["metrics"]["processes"] == 1
    out, res = _run(tmp_path_factory, monkeypatch, "1")
    assert spawned == [1]  # one child for the three parts
    assert res["stages"]["metrics"]["processes"] == 2
    assert res["stages"]["plan"]["beside_seconds"] > 0
    assert_identical(out, ref)
    names = sorted(p.name for p in (out0 / "figures").glob("*.png"))
    assert names and sorted(p.name for p in (out / "figures").glob("*.png")) == names


def test_switches(monkeypatch):
    monkeypatch.setenv(helper_process.ENV, "0")
    assert helper_process.enabled() is False and helper_process.start() is None
    monkeypatch.setenv(helper_process.ENV, "1")
    assert helper_process.enabled() is True
    monkeypatch.delenv(helper_process.ENV)
    # automatic: not under pytest (a spawned child would import pytest's main module again)
    assert helper_process.enabled() == ((os.cpu_count() or 1) >= 2 and resources.spawn_is_safe())
    assert evaluate_mod.process_count(1, warm=True) == 2 and evaluate_mod.process_count(1) == 1
    monkeypatch.setenv(evaluate_mod.PROCESSES_ENV, "1")
    assert evaluate_mod.process_count(1, warm=True) == 1  # the metrics' own switch still applies


def test_parts_leave_the_shared_pool_running(monkeypatch):
    """PlanAhead.close and a figure pool given by the run do not shut the run's helper down."""
    monkeypatch.setenv(helper_process.ENV, "1")
    helper = helper_process.start()
    assert helper is not None
    try:
        helper.warm()
        scene = load_scene("tiny")
        cfg = reconstruct.ReconstructionConfig.from_scene(scene)
        ahead = plan_ahead.PlanAhead(scene, cfg, (0.2,), reconstruct.slice_positions(scene), resolve_targets(scene),
                                     ("nearest",), 1, pool=helper.pool)
        ahead.close()
        assert figures._figure_pool(helper.pool) is helper.pool
        assert helper.pool.submit(os.getpid).result(timeout=60) != os.getpid()
    finally:
        helper.close()
    assert helper.pool is None


@pytest.mark.parametrize("choice", ["0"])
def test_figure_switch_wins_over_the_helper(monkeypatch, choice):
    monkeypatch.setenv(figures.FIGURE_PROCESS_ENV, choice)
    assert figures._figure_pool(object()) is None


def test_a_killed_run_leaves_no_helper_behind(tmp_path):
    """kill -9 of a run while its helper lives: the helper notices that its parent is gone and
    ends (core.resources._watch_parent), so the run's stdout and stderr close at once. An
    orphaned helper kept them open, and whatever read the run's output waited for ever."""
    env = dict(os.environ, CLRECON_NO_PROGRESS="1", CLRECON_FAULT="recon:5", CLRECON_TRUTH_THREAD="0")
    env[helper_process.ENV] = "1"
    cmd = [sys.executable, "-m", "clrecon", "run", "--scene", "tiny", "--out", str(tmp_path / "out"),
           "--cache", str(tmp_path / "cache"), "--no-progress", "--pitch", "0.1,0.2"]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    try:
        proc.wait(timeout=600)
        assert proc.returncode == -signal.SIGKILL
        proc.communicate(timeout=30)  # EOF on both pipes: no process holds them any more
    finally:
        if proc.poll() is None:
            proc.kill()
