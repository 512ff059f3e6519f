"""SIGKILL at any instant: a real ``python -m clrecon run`` subprocess kills itself (``kill -9``)
at a chosen point (``CLRECON_FAULT``, :mod:`clrecon.core.faults`); the rerun resumes, writes
only the unfinished units, and ends bit-identical to an uninterrupted run."""

import os
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from run_compare import assert_identical

from clrecon.config.scene import load_scene
from clrecon.pipeline.run import run


def _cli(out, cache, fault=None, executor="serial"):
    # serial: the truths after the reconstruction, so that the units each fault leaves are fixed
    # (CASES); the truth thread's own case is test_sigkill_in_the_truth_thread_then_resume
    env = dict(os.environ, CLRECON_NO_PROGRESS="1")
    env.pop("CLRECON_FAULT", None)
    if fault:
        env["CLRECON_FAULT"] = fault
    cmd = [sys.executable, "-m", "clrecon", "run", "--scene", "tiny", "--out", str(out), "--cache", str(cache),
           "--no-progress", "--executor", executor]
    return subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=600)


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    out = tmp_path_factory.mktemp("ref")
    res = run(load_scene("tiny"), out, cache_dir=tmp_path_factory.mktemp("cache"), progress=False,
              log=lambda *a: None)
    return out, res


# (fault, unit files the rerun writes: projections, recon, truth); with the reference run's
# totals P, R, T: tiny has 384 projections = 2 chunks of 256, 6 methods x 2 variants x 1 slab, 4 targets x 2 truths
CASES = {
    "simulate:2": lambda P, R, T: (P - 1, R, T),     # mid-write of the 2nd chunk of projections
    "assemble-store:1": lambda P, R, T: (0, R, T),   # store .partial torn mid-assembly
    "rename-store:1": lambda P, R, T: (0, R, T),     # store assembled, not yet renamed
    "recon:5": lambda P, R, T: (0, R - 4, T),        # mid-write of the 5th reconstruction unit
    "truth:3": lambda P, R, T: (0, 0, T - 2),        # mid-write of the 3rd truth target
    "assemble-volumes:1": lambda P, R, T: (0, 0, 0),  # volumes.h5.partial open, the 1st dataset's mappings made
    "assemble-volumes:3": lambda P, R, T: (0, 0, 0),  # ... the 3rd's
    "assemble-volumes:14": lambda P, R, T: (0, 0, 0),  # ... the last dataset's (phantom), not yet fsync'd
    "rename-volumes:1": lambda P, R, T: (0, 0, 0),   # right before the final rename
}


@pytest.mark.parametrize("fault", list(CASES))
def test_sigkill_then_resume_is_bit_identical(tmp_path, reference, fault):
    out, cache = tmp_path / "run", tmp_path / "cache"
    killed = _cli(out, cache, fault)
    assert killed.returncode == -signal.SIGKILL, killed.stderr
    assert not (out / "results.json").exists() and not (out / "volumes.h5").exists()
    again = _cli(out, cache)
    assert again.returncode == 0, again.stderr
    assert "Traceback" not in again.stderr
    res = assert_identical(out, reference, ("metrics", "respiratory_only", "motion"))
    total = reference[1]["units_written"]
    P, R, T = total["projections"], total["recon"], total["truth"]
    assert (P, R, T) == (2, 12, 8)
    want = CASES[fault](P, R, T)
    got = res["units_written"]
    assert (got["projections"], got["recon"], got["truth"]) == want
    assert not list(cache.glob("*.units")) and not list(cache.glob("*.partial"))
    assert [p.name for p in (out / "volumes.d").iterdir()] == [Path(str(_attr(out, "datasets_dir"))).name]
    assert not list((out / "volumes.d").rglob("*.partial"))


def test_sigkill_in_the_truth_thread_then_resume_is_bit_identical(tmp_path, reference):
    out, cache = tmp_path / "run", tmp_path / "cache"
    killed = _cli(out, cache, "truth:3", "local")   # the 3rd truth unit, mid-write, beside the reconstruction
    assert killed.returncode == -signal.SIGKILL, killed.stderr
    again = _cli(out, cache, executor="local")
    assert again.returncode == 0, again.stderr
    res = assert_identical(out, reference, ("metrics", "respiratory_only", "motion"))
    P, R, T = (reference[1]["units_written"][k] for k in ("projections", "recon", "truth"))
    got = res["units_written"]
    assert got["truth"] == T - 2 and got["recon"] <= R and got["projections"] <= P  # nothing done twice


def _attr(out, key):
    import h5py

    with h5py.File(out / "volumes.h5", "r") as f:
        return f.attrs[key]


def test_damaged_unit_file_is_detected_and_redone(tmp_path, reference):
    out, cache = tmp_path / "run", tmp_path / "cache"
    assert _cli(out, cache, "truth:3").returncode == -signal.SIGKILL
    unit = sorted((out / "volumes.d").rglob("recon~*~noisy~local_linear.*.unit"))[0]
    raw = bytearray(unit.read_bytes())
    for k in range(len(raw) // 2, len(raw) // 2 + 8):   # flip 8 bytes in the middle of the volume
        raw[k] ^= 0x5A
    unit.write_bytes(bytes(raw))
    again = _cli(out, cache)
    assert again.returncode == 0, again.stderr
    assert "damaged unit file" in again.stderr
    res = assert_identical(out, reference, ("metrics", "respiratory_only", "motion"))
    got = res["units_written"]
    assert (got["projections"], got["recon"], got["truth"]) == (0, 1, 6)


def test_fault_hook_is_inert_without_the_variable(monkeypatch):
    from clrecon.core import faults

    monkeypatch.delenv("CLRECON_FAULT", raising=False)
    for _ in range(3):
        faults.point("simulate")
    monkeypatch.setenv("CLRECON_FAULT", "recon:2")
    faults.point("simulate")  # another point: nothing
    assert np.isfinite(1.0)
