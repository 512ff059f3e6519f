"""The truths beside the reconstruction (clrecon.pipeline.truth_worker): the same bytes as the
foreground path, their own OpenCL runtime, errors raised in the run's thread."""

import threading

import pytest
from run_compare import QUIET, assert_identical, reference_run

from clrecon.config.scene import load_scene
from clrecon.core import runtime as runtime_mod
from clrecon.evaluation import groundtruth
from clrecon.pipeline.run import run


@pytest.fixture(scope="module")
def foreground(tmp_path_factory):
    """tiny with the truths after the reconstruction, in the run's thread (CLRECON_TRUTH_THREAD=0)."""
    return reference_run(tmp_path_factory, {"CLRECON_TRUTH_THREAD": "0"})[:2]


def test_truths_beside_the_reconstruction_are_bit_identical(tmp_path, foreground, monkeypatch):
    monkeypatch.setenv("CLRECON_TRUTH_THREAD", "1")
    used = []
    real = groundtruth.groundtruth_sinograms

    def spy(*a, **k):
        used.append((threading.current_thread().name, k.get("rt")))
        return real(*a, **k)

    monkeypatch.setattr(groundtruth, "groundtruth_sinograms", spy)
    res = run(load_scene("tiny"), tmp_path, cache_dir=tmp_path / "cache", **QUIET)
    assert_identical(tmp_path, foreground, ("metrics", "respiratory_only", "motion", "diagnostics", "sampling"))
    st = res["stages"]
    assert "beside_seconds" in st["groundtruth"] and st["groundtruth"]["beside_seconds"] > 0
    assert "beside_seconds" not in foreground[1]["stages"]["groundtruth"]
    assert "| groundtruth | yes, beside the reconstruction (" in (tmp_path / "report.md").read_text()
    # every target in the worker thread, on a runtime of its own (not the run's: kernel objects are not thread-safe)
    assert len(used) == 4 and {name for name, _ in used} == {"clrecon-truths"}
    assert {id(rt) for _, rt in used} != {id(runtime_mod.get_runtime())} and used[0][1] is not None


def test_a_failing_truth_thread_fails_the_run_with_its_error(tmp_path, monkeypatch):
    monkeypatch.setenv("CLRECON_TRUTH_THREAD", "1")

    def broken(*a, **k):
        raise RuntimeError("truth projector broke")

    monkeypatch.setattr(groundtruth, "groundtruth_sinograms", broken)
    with pytest.raises(RuntimeError, match="truth projector broke"):
        run(load_scene("tiny"), tmp_path, cache_dir=tmp_path / "cache", **QUIET)
    assert not (tmp_path / "results.json").exists() and not (tmp_path / "volumes.h5").exists()


def test_thread_runtime_is_per_thread():
    main = runtime_mod.get_runtime()
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
    assert seen["inside"] is other and seen["after"] is main
    assert seen["main_inside"] is other and runtime_mod.get_runtime() is main
