"""Dask scale-out (clrecon.pipeline.distributed): a 2-worker local cluster gives the single-process
run's volumes and metrics bit for bit; a worker killed mid-unit costs only that unit; a client
killed mid-run (``python -m clrecon run --workers 2``) resumes; a sweep runs its points on the cluster."""

import json
import os
import signal
import subprocess
import sys

import pytest
from run_compare import assert_identical

from clrecon.config.scene import load_scene
from clrecon.core.errors import ClreconError
from clrecon.pipeline import distributed
from clrecon.pipeline.run import run
from clrecon.pipeline.sweep import load_study, run_study

QUIET = dict(progress=False, log=lambda *a, **k: None)


@pytest.fixture(scope="module")
def client():
    with distributed.connect(workers=2) as c:
        yield c


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    out = tmp_path_factory.mktemp("ref")
    return out, run(load_scene("tiny"), out, cache_dir=tmp_path_factory.mktemp("cache"), **QUIET)


def test_two_workers_bit_identical(tmp_path, client, reference):
    res = run(load_scene("tiny"), tmp_path / "run", cache_dir=tmp_path / "cache", client=client, **QUIET)
    assert_identical(tmp_path / "run", reference)
    d = res["distributed"]
    # tiny: 384 projections = 2 chunks of 256, one slab (2 slices x 6 methods x 2 variants), 4 targets
    assert d["workers"] == 2 and d["units"] == {"simulate": 2, "reconstruct": 1, "truth": 4}
    assert res["units_written"] == reference[1]["units_written"]
    sim = res["stages"]["simulate"]
    assert sim["ran"] and sim["per_pitch"]["p0.100"]["projections_simulated"] == 384
    assert set(res["method_seconds"]["p0.100"]["noisy"]) == set(reference[1]["method_seconds"]["p0.100"]["noisy"])


def test_killed_worker_costs_only_its_unit(tmp_path, client, reference):
    before = client.run(os.getpid)
    victim = sorted(before)[0]
    # that worker SIGKILLs itself at the start of its next unit; the nanny restarts it (without
    # the fault: a fresh process) and the scheduler hands the unit to a worker again
    client.run(lambda: os.environ.__setitem__("CLRECON_FAULT", "worker-unit:1"), workers=[victim])
    res = run(load_scene("tiny"), tmp_path / "run", cache_dir=tmp_path / "cache", client=client, **QUIET)
    assert_identical(tmp_path / "run", reference)
    client.wait_for_workers(2, timeout=60)
    after = client.run(os.getpid)
    assert before[victim] not in after.values()  # it did die ...
    assert len(set(before.values()) & set(after.values())) == 1  # ... and only it
    # every unit's result was written once: the lost unit was computed again, nothing else
    assert res["distributed"]["units"] == {"simulate": 2, "reconstruct": 1, "truth": 4}
    assert res["units_written"] == reference[1]["units_written"]


def _cli(out, cache, fault=None):
    env = dict(os.environ, CLRECON_NO_PROGRESS="1")
    env.pop("CLRECON_FAULT", None)
    if fault:
        env["CLRECON_FAULT"] = fault
    cmd = [sys.executable, "-m", "clrecon", "run", "--scene", "tiny", "--out", str(out), "--cache", str(cache),
           "--no-progress", "--workers", "2"]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env,
                            start_new_session=True)
    try:
        stdout, stderr = proc.communicate(timeout=600)
    finally:
        # the client's workers outlive a SIGKILLed client: end its process group (ours alone)
        try:
            os.killpg(proc.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
    return proc.returncode, stdout, stderr


def test_cli_client_killed_then_resumes(tmp_path, reference):
    out, cache = tmp_path / "run", tmp_path / "cache"
    rc, _, err = _cli(out, cache, "truth:3")  # the client dies mid-write of its 3rd truth unit
    assert rc == -signal.SIGKILL, err
    assert not (out / "results.json").exists() and not (out / "volumes.h5").exists()
    rc, stdout, err = _cli(out, cache)
    assert rc == 0, err
    assert "Traceback" not in err
    res = assert_identical(out, reference)
    assert res["resumed"] and res["units_written"]["truth"] == reference[1]["units_written"]["truth"] - 2


def test_sweep_on_the_cluster_resumes(tmp_path, client):
    study_file = tmp_path / "study.toml"
    study_file.write_text('name = "k"\nscene = "tiny"\nmethods = ["local_linear", "nearest"]\nreport = false\n'
                          '[set]\n"noise.enabled" = false\n[grid]\n"recon.kappa" = [0.05, 0.2]\n')
    study = load_study(study_file)
    out = tmp_path / "study"
    summary = run_study(study, out=out, cache_dir=tmp_path / "cache", client=client, **QUIET)
    assert summary["points_run"] == 2 and summary["points_kept"] == 0
    for name in ("kappa=0.05", "kappa=0.2"):
        res = json.loads((out / name / "results.json").read_text())
        assert res["distributed"]["workers"] == 2 and res["scene"]["recon"]["kappa"] == float(name.split("=")[1])
    lines = (out / "summary.csv").read_text().splitlines()
    assert lines[0].startswith("point,recon.kappa,pitch,variant,method,mae_small_hu")
    assert len(lines) == 1 + 2 * 2  # 2 points x 2 methods x 1 variant x 1 pitch
    assert (out / "sweep_recon_kappa.png").stat().st_size > 0 and (out / "summary.md").exists()
    # the second point left unfinished: a rerun keeps the first and resumes the second
    (out / "kappa=0.2" / "results.json").unlink()
    again = run_study(study, out=out, cache_dir=tmp_path / "cache", client=client, **QUIET)
    assert again["points_run"] == 1 and again["points_kept"] == 1
    def metrics_only(text):  # the rerun point's run_seconds (last column) differs
        return [line.rsplit(",", 1)[0] for line in text.splitlines()]
    assert metrics_only((out / "summary.csv").read_text()) == metrics_only("\n".join(lines))


def test_connect_errors():
    with pytest.raises(ClreconError, match="give one of them"):
        with distributed.connect(workers=2, cluster="tcp://127.0.0.1:1"):
            pass
    with pytest.raises(ClreconError, match="whole number of worker processes"):
        with distributed.connect(workers=0):
            pass
