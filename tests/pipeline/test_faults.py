"""Faults: an interrupted `run` leaves nothing that looks complete and resumes to the same result;
a failed write (disk full) says so and keeps the earlier outputs."""

import errno
import hashlib
import os
import shutil
import signal
import subprocess
import sys

import h5py
import numpy as np
import pytest

from clrecon.cli import main
from clrecon.config.scene import load_scene
from clrecon.evaluation import groundtruth
from clrecon.outputs.volumes import VolumeWriter
from clrecon.pipeline.run import run

QUIET = dict(progress=False, log=lambda *a: None)


def _volumes(path):
    with h5py.File(path / "volumes.h5", "r") as f:
        out = {}
        f.visititems(lambda n, o: out.__setitem__(n, o[()]) if isinstance(o, h5py.Dataset) else None)
    return out


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """An uninterrupted tiny run (its store is reused by the interrupted runs)."""
    out = tmp_path_factory.mktemp("ref")
    cache = tmp_path_factory.mktemp("cache")
    run(load_scene("tiny"), out, cache_dir=cache, **QUIET)
    return out, cache


def _assert_same(a, b):
    va, vb = _volumes(a), _volumes(b)
    assert va.keys() == vb.keys()
    for k in va:
        np.testing.assert_array_equal(va[k], vb[k], err_msg=k)


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_signal_mid_run_then_resume(tmp_path, sig):
    out, cache = tmp_path / "run", tmp_path / "cache"   # fresh cache: the signal lands in simulate/reconstruct
    env = dict(os.environ, CLRECON_NO_PROGRESS="1", PYTHONUNBUFFERED="1")
    cmd = [sys.executable, "-m", "clrecon", "run", "--scene", "tiny", "--out", str(out), "--cache", str(cache)]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    for line in proc.stdout:
        if "planning" in line:
            proc.send_signal(sig)
            break
    _, err = proc.communicate(timeout=300)
    assert proc.returncode == 130, err
    assert "interrupted" in err and "Traceback" not in err
    assert not (out / "results.json").exists() and not (out / "volumes.h5").exists()
    assert not (out / "volumes.h5.partial").exists()
    # resume: same command, completes
    done = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=600)
    assert done.returncode == 0, done.stderr
    assert (out / "results.json").exists() and not list(out.glob("*.partial")) and not list(out.glob("*.units"))
    ref_out = tmp_path / "ref"
    run(load_scene("tiny"), ref_out, cache_dir=tmp_path / "cache2", **QUIET)
    _assert_same(out, ref_out)


@pytest.mark.parametrize("executor", ["serial", "local"])
def test_interrupt_during_ground_truth_resumes_only_the_rest(tmp_path, reference, monkeypatch, executor):
    # serial: the truths after the reconstruction; local: beside it (the interrupt may then come
    # before the reconstruction is done, and the resumed run does what is left of it)
    ref_out, cache = reference
    calls = {"n": 0}
    real = groundtruth.groundtruth_sinograms

    def flaky(*a, **k):
        calls["n"] += 1
        if calls["n"] == 3:
            raise KeyboardInterrupt
        return real(*a, **k)

    monkeypatch.setattr(groundtruth, "groundtruth_sinograms", flaky)
    shutil.rmtree(cache / "truth", ignore_errors=True)  # the truths must be computed, not taken from the cache
    with pytest.raises(KeyboardInterrupt):
        run(load_scene("tiny"), tmp_path, cache_dir=cache, executor=executor, **QUIET)
    assert (tmp_path / "volumes.h5.units").is_dir() and not (tmp_path / "results.json").exists()
    assert not (tmp_path / "volumes.h5").exists()
    done = sorted(p.name.split(".")[1] for p in (tmp_path / "volumes.d").rglob("groundtruth.*.unit"))
    assert done == ["t00000", "t00001"]
    calls["n"] = 100                                     # no more interruptions
    res = run(load_scene("tiny"), tmp_path, cache_dir=cache, executor=executor, **QUIET)
    assert res["resumed"] is True
    assert calls["n"] == 102                             # only the two missing targets were redone
    if executor == "serial":
        assert res["stages"]["plan"]["ran"] is False     # every slice was already reconstructed
    _assert_same(tmp_path, ref_out)


def test_a_different_request_does_not_resume_a_stale_partial(tmp_path, reference):
    _, cache = reference
    w = VolumeWriter(tmp_path / "volumes.h5", {"z_mm": [0.0]}, True, True, run_key="another run")
    w.abort()
    res = run(load_scene("tiny"), tmp_path, methods=["nearest"], cache_dir=cache, **QUIET)
    assert res["resumed"] is False


def _digest(p):
    return hashlib.sha256(p.read_bytes()).hexdigest()


def test_disk_full_says_so_and_keeps_earlier_outputs(tmp_path, reference, monkeypatch, capsys):
    _, cache = reference
    out = tmp_path / "run"
    argv = ["run", "--scene", "tiny", "--methods", "nearest", "--out", str(out), "--cache", str(cache),
            "--no-progress"]
    assert main(argv) == 0
    before = {n: _digest(out / n) for n in ("results.json", "volumes.h5", "report.md")}
    capsys.readouterr()

    def full(*a, **k):
        raise OSError(errno.ENOSPC, "No space left on device", str(out / "volumes.h5.partial"))

    monkeypatch.setattr(VolumeWriter, "write_target", full)
    shutil.rmtree(cache / "truth", ignore_errors=True)  # the truths must be written, not taken from the cache
    assert main(argv[:4] + ["nearest,bin"] + argv[5:]) == 2
    err = capsys.readouterr().err
    assert err.startswith("clrecon: error: disk full") and err.count("\n") == 1
    assert {n: _digest(out / n) for n in before} == before
