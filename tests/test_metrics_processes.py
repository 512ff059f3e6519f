"""The metrics stage split over processes (clrecon.pipeline.evaluate): bit for bit the one-process numbers."""

import json

import pytest
from run_compare import QUIET, reference_run

from clrecon.config.scene import load_scene
from clrecon.pipeline import evaluate as evaluate_mod
from clrecon.pipeline.run import run

KEYS = ("metrics", "respiratory_only", "motion")


@pytest.fixture(scope="module")
def one_process(tmp_path_factory):
    return reference_run(tmp_path_factory, {"CLRECON_METRICS_PROCESSES": "1"})[1:]


def _same(a, b):
    for k in KEYS:  # exact equality of every float, through the JSON the run writes
        assert json.dumps(a[k], sort_keys=True) == json.dumps(b[k], sort_keys=True), k


@pytest.mark.parametrize("n", [2, 3])
def test_split_over_processes_is_bit_identical(tmp_path, one_process, monkeypatch, n):
    ref, cache = one_process
    monkeypatch.setenv("CLRECON_METRICS_PROCESSES", str(n))
    res = run(load_scene("tiny"), tmp_path, cache_dir=cache, **QUIET)
    assert ref["stages"]["metrics"]["processes"] == 1
    assert res["stages"]["metrics"]["processes"] == n   # the split path was taken
    _same(res, ref)


def test_a_pool_that_cannot_start_runs_every_group_here(tmp_path, one_process, monkeypatch):
    ref, cache = one_process
    monkeypatch.setenv("CLRECON_METRICS_PROCESSES", "2")
    monkeypatch.setattr(evaluate_mod, "spawned_pool", lambda n: None)
    res = run(load_scene("tiny"), tmp_path, cache_dir=cache, **QUIET)
    assert res["stages"]["metrics"]["processes"] == 1
    _same(res, ref)


def test_automatic_choice_and_bad_value(monkeypatch):
    monkeypatch.delenv("CLRECON_METRICS_PROCESSES", raising=False)
    monkeypatch.setattr(evaluate_mod.os, "cpu_count", lambda: 2)
    monkeypatch.setattr(evaluate_mod, "spawn_is_safe", lambda: True)
    assert evaluate_mod.process_count(evaluate_mod.PROCESS_MIN_BYTES - 1) == 1
    assert evaluate_mod.process_count(evaluate_mod.PROCESS_MIN_BYTES) == 2
    monkeypatch.setattr(evaluate_mod.os, "cpu_count", lambda: 1)
    assert evaluate_mod.process_count(10 * evaluate_mod.PROCESS_MIN_BYTES) == 1
    monkeypatch.setenv("CLRECON_METRICS_PROCESSES", "two")
    with pytest.raises(ValueError, match="CLRECON_METRICS_PROCESSES='two'"):
        evaluate_mod.process_count(0)


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
    monkeypatch.setenv("CLRECON_METRICS_PROCESSES", "")
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
