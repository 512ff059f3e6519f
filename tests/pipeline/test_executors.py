"""The run as a graph of stages (clrecon.pipeline.graph) and its executors (clrecon.pipeline.executors):
serial and overlapped give the same run bit for bit; the helper process serves the plans ahead,
the metrics and the figures; the truths run beside the reconstruction on a runtime of their own;
a stage added to the graph runs in its place."""

import dataclasses
import os
import signal
import subprocess
import sys
import threading

import numpy as np
import pytest
from run_compare import QUIET, assert_identical

from clrecon.cli import main
from clrecon.config.scene import load_scene
from clrecon.core import runtime as runtime_mod
from clrecon.core.errors import ClreconError
from clrecon.evaluation import groundtruth
from clrecon.outputs.volumes import open_volumes, pitch_key
from clrecon.pipeline import executors, graph
from clrecon.pipeline import run as run_mod
from clrecon.pipeline import stage as stage_mod
from clrecon.pipeline.executors import local as local_mod
from clrecon.pipeline.executors.base import Unit, Work, serial_order
from clrecon.pipeline.run import run

PITCHES = (0.1, 0.2)


@pytest.fixture(scope="module")
def serial(tmp_path_factory):
    """tiny at two pitches, every stage in this thread, in order."""
    out, cache = tmp_path_factory.mktemp("serial"), tmp_path_factory.mktemp("cache")
    return out, run(load_scene("tiny"), out, cache_dir=cache, pitches=PITCHES, executor="serial", **QUIET)


def test_the_graph_is_in_order():
    """The serial walk goes pitch by pitch through each run of per-pitch stages, the once-per-run
    stages in place: the truths after the reconstruction, before the motion stages that wait for
    them (the graph's own checks: tests/pipeline/test_graph.py)."""
    order = [(st.name, p) for st, p in serial_order(graph.GRAPH, PITCHES)]
    first = ["plan", "simulate", "truth_free", "reconstruct"]
    motion = ["mc_reconstruct", "mcir_reconstruct", "consistency"]
    assert order[:9] == [(n, p) for p in PITCHES for n in first] + [("truth", None)]
    assert order[9:15] == [(n, p) for p in PITCHES for n in motion]
    assert [n for n, _ in order[-4:]] == ["assemble", "metrics", "results", "report"]


def test_overlapped_with_a_helper_is_the_serial_run(tmp_path, serial, monkeypatch):
    """The local executor with its helper process (forced: pytest is no place to spawn by default):
    one child for the later pitch's plan, the metrics' second group and the figures; the truths
    beside the reconstruction; the units written behind; volumes, metrics and figures the same."""
    spawned = []
    real = local_mod.spawned_pool
    monkeypatch.setattr(local_mod, "spawned_pool", lambda n: spawned.append(n) or real(n))
    ex = executors.LocalExecutor(helper=True)
    res = run(load_scene("tiny"), tmp_path, cache_dir=tmp_path / "cache", pitches=PITCHES, executor=ex, **QUIET)
    assert spawned == [1] and ex.pool is None  # one child, closed at the end
    assert_identical(tmp_path, serial)
    st, ref = res["stages"], serial[1]["stages"]
    assert res["executor"] == "local" and serial[1]["executor"] == "serial"
    assert st["metrics"]["processes"] == 2 and ref["metrics"]["processes"] == 1
    assert st["plan"]["beside_seconds"] > 0 and "waited_for" in st["plan"]  # pitch 0.2 planned ahead
    assert st["groundtruth"]["beside_seconds"] > 0 and st["write_volumes"]["beside_seconds"] > 0
    assert not any("beside_seconds" in v for v in ref.values())
    assert set(res["method_plan_seconds"]) == {"p0.100", "p0.200"}
    assert res["units_written"] == serial[1]["units_written"]
    names = sorted(p.name for p in (serial[0] / "figures").glob("*.png"))
    assert names and sorted(p.name for p in (tmp_path / "figures").glob("*.png")) == names
    assert st["unaccounted"]["seconds"] >= -0.01


def test_truths_beside_the_reconstruction_run_on_their_own_runtime(tmp_path, monkeypatch):
    """(Bit identity: test_overlapped_with_a_helper_is_the_serial_run; here: where the truths ran.)"""
    used = []
    real = groundtruth.groundtruth_sinograms

    def spy(*a, **k):
        used.append((threading.current_thread().name, k.get("rt")))
        return real(*a, **k)

    monkeypatch.setattr(groundtruth, "groundtruth_sinograms", spy)
    res = run(load_scene("tiny"), tmp_path, cache_dir=tmp_path / "cache", executor="local", **QUIET)
    st = res["stages"]
    assert st["groundtruth"]["beside_seconds"] > 0 and st["phantom_truth"]["ran"]
    assert "| groundtruth | yes, beside the reconstruction (" in (tmp_path / "report.md").read_text()
    # every target in the thread, on a runtime of its own (not the run's: kernel objects are not thread-safe)
    assert len(used) == 4 and {name for name, _ in used} == {"clrecon-truth"}
    assert {id(rt) for _, rt in used} != {id(runtime_mod.get_runtime())} and used[0][1] is not None


@pytest.mark.parametrize("executor", ["serial", "local"])
def test_a_failing_truth_stage_fails_the_run_with_its_error(tmp_path, monkeypatch, executor):
    def broken(*a, **k):
        raise RuntimeError("truth projector broke")

    monkeypatch.setattr(groundtruth, "groundtruth_sinograms", broken)
    with pytest.raises(RuntimeError, match="truth projector broke"):
        run(load_scene("tiny"), tmp_path, cache_dir=tmp_path / "cache", executor=executor, **QUIET)
    assert not (tmp_path / "results.json").exists() and not (tmp_path / "volumes.h5").exists()


def test_thread_runtime_is_per_thread():
    main_rt = runtime_mod.get_runtime()
    other = runtime_mod.Runtime()
    seen = {}

    def body():
        with runtime_mod.thread_runtime(other):
            seen["inside"] = runtime_mod.get_runtime()
        seen["after"] = runtime_mod.get_runtime()

    t = threading.Thread(target=body)
    with runtime_mod.thread_runtime(other):
        t.start()
        t.join()
        seen["main_inside"] = runtime_mod.get_runtime()
    assert seen["inside"] is other and seen["after"] is main_rt
    assert seen["main_inside"] is other and runtime_mod.get_runtime() is main_rt


def _echo(run, pitch, plan):
    """A stage added to the graph: after a pitch's reconstruction, one more per-target volume
    dataset (here the first target's slices, a stand-in for a second pass), as units."""
    name = f"extra/{pitch_key(pitch)}"
    run.writer.create(name, run.full_shape, run.n_targets, blocks="targets")
    n_r = run.targets.shape[1]

    def here(emit, times):
        for k in range(run.n_targets):
            emit((k, np.full(run.full_shape[2:], float(k), np.float32)))
        times.add("echo", 0.0)

    def write(piece):
        k, vol = piece
        run.writer.write_target(name, *divmod(k, n_r), n_r, vol)

    return Work([Unit(here)], write)


def test_a_stage_added_to_the_graph_runs_in_its_place(tmp_path, serial, monkeypatch):
    """One entry in the graph: a per-pitch stage after the reconstruction that writes volume units
    (one of the volume writers) is run after each pitch's reconstruction and before the assembly,
    which maps its units."""
    echo = graph.Stage(name="echo", fn=_echo, needs=("plan",), after=("reconstruct",), per_pitch=True,
                       parts=("echo",), rest="echo")
    at = [st.name for st in graph.GRAPH].index("reconstruct") + 1
    stages = [dataclasses.replace(st, after=st.after + ("echo",)) if st.name == "assemble" else st
              for st in graph.GRAPH[:at] + (echo,) + graph.GRAPH[at:]]
    monkeypatch.setattr(run_mod, "GRAPH", stage_mod.graph(*stages))
    res = run(load_scene("tiny"), tmp_path, cache_dir=tmp_path / "cache", pitches=PITCHES, executor="serial",
              **QUIET)
    assert res["stages"]["echo"]["ran"] and list(res["stages"]).index("echo") > list(res["stages"]).index("fbp")
    with open_volumes(tmp_path) as f:
        for pk in ("p0.100", "p0.200"):
            vol = f[f"extra/{pk}"][()]
            assert vol.shape[:2] == (2, 2) and float(vol[1, 1].max()) == 3.0
    assert res["metrics"] == serial[1]["metrics"]


def test_make_names_the_choices():
    assert executors.make("serial").kind == "serial" and executors.make().kind == "local"
    with pytest.raises(ClreconError, match="must be one of serial, local, dask"):
        executors.make("threads")
    with pytest.raises(ClreconError, match="--executor dask needs a Dask client"):
        executors.make("dask")
    with pytest.raises(ClreconError, match="with --workers/--cluster"):
        executors.make("serial", client=object())


def test_cli_executor_and_workers_conflict(tmp_path, capsys):
    assert main(["run", "--scene", "tiny", "--out", str(tmp_path), "--executor", "serial", "--workers", "2"]) == 2
    err = capsys.readouterr().err
    assert "--executor serial with --workers/--cluster" in err and len(err.strip().splitlines()) == 1


def test_a_killed_run_leaves_no_helper_behind(tmp_path):
    """kill -9 of a run while its helper lives (under ``python -m clrecon`` on >= 2 cores the local
    executor starts one): the helper notices that its parent is gone and ends
    (core.resources._watch_parent), so the run's stdout and stderr close at once, and releases the pool's
    named semaphores: no "leaked semaphore objects" warning from the resource tracker on stderr."""
    env = dict(os.environ, CLRECON_NO_PROGRESS="1", CLRECON_FAULT="recon:5")
    cmd = [sys.executable, "-m", "clrecon", "run", "--scene", "tiny", "--out", str(tmp_path / "out"),
           "--cache", str(tmp_path / "cache"), "--no-progress", "--pitch", "0.1,0.2", "--executor", "local"]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    try:
        proc.wait(timeout=600)
        assert proc.returncode == -signal.SIGKILL
        _, err = proc.communicate(timeout=30)  # EOF on both pipes: no process holds them any more
        assert "leaked semaphore" not in err, err
    finally:
        if proc.poll() is None:
            proc.kill()
