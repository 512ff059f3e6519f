"""Dask scale-out (clrecon.pipeline.distributed): a 2-worker local cluster gives the single-process
run's volumes and metrics bit for bit; a worker killed mid-unit costs only that unit; a client
killed mid-run (``python -m clrecon run --workers 2``) resumes; a sweep runs its points on the cluster;
a tls:// cluster (certificates made here) runs ``clrecon run`` and ``sweep`` bit-identically."""

import json
import logging
import os
import re
import signal
import subprocess
import sys

import dask
import h5py
import pytest
from run_compare import assert_identical
from tls_certs import make_certs

from clrecon.cli import main
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


# ----------------------------------------------------------------------------------------
# a tls:// cluster (issue 18: patient data on a cluster)
@pytest.fixture(scope="module")
def certs(tmp_path_factory):
    return {k: str(v) for k, v in make_certs(tmp_path_factory.mktemp("certs")).items()}


@pytest.fixture(scope="module")
def tls_cluster(certs):
    """A scheduler and one single-threaded worker process on 127.0.0.1 that speak only TLS (one CA)."""
    import distributed as d

    node = dict(tls_ca_file=certs["ca"], tls_scheduler_cert=certs["cert"], tls_scheduler_key=certs["key"],
                tls_worker_cert=certs["cert"], tls_worker_key=certs["key"], tls_client_cert=certs["cert"],
                tls_client_key=certs["key"])
    cluster = d.LocalCluster(n_workers=1, threads_per_worker=1, processes=True, protocol="tls",
                             security=d.Security(require_encryption=True, **node), dashboard_address="127.0.0.1:0",
                             silence_logs=logging.ERROR, env={"CLRECON_NO_PROGRESS": "1"})
    try:
        yield cluster.scheduler_address
    finally:
        cluster.close()


def _tls_args(certs):
    return ["--tls-ca-file", certs["ca"], "--tls-cert", certs["cert"], "--tls-key", certs["key"]]


def test_tls_cluster_run_and_sweep_bit_identical(tmp_path, tls_cluster, certs, reference):
    assert tls_cluster.startswith("tls://127.0.0.1:")
    term = signal.getsignal(signal.SIGTERM)  # main() installs its SIGTERM handler; this process keeps its own
    try:
        out, cache = tmp_path / "run", tmp_path / "cache"
        argv = ["run", "--scene", "tiny", "--out", str(out), "--cache", str(cache), "--no-progress",
                "--cluster", tls_cluster, *_tls_args(certs)]
        assert main(argv) == 0
        res = assert_identical(out, reference)
        d = res["distributed"]
        assert d["encrypted"] is True and d["scheduler"] == tls_cluster and d["workers"] == 1
        assert d["units"] == {"simulate": 2, "reconstruct": 1, "truth": 4}
        # a sweep (one noise-free point at the default kappa) on the same cluster, its store reused
        study = tmp_path / "study.toml"
        study.write_text('name = "t"\nscene = "tiny"\nmethods = ["nearest"]\nreport = false\n'
                         '[set]\n"noise.enabled" = false\n[grid]\n"recon.kappa" = [1.0]\n')
        assert main(["sweep", str(study), "--out", str(tmp_path / "study"), "--cache", str(cache), "--no-progress",
                     "--cluster", tls_cluster, *_tls_args(certs)]) == 0
    finally:
        signal.signal(signal.SIGTERM, term)
    point = tmp_path / "study" / "kappa=1"
    pres = json.loads((point / "results.json").read_text())
    assert pres["distributed"]["encrypted"] is True and pres["distributed"]["units"]["simulate"] == 0
    name = "recon/p0.100/noise-free/nearest"
    with h5py.File(point / "volumes.h5") as a, h5py.File(reference[0] / "volumes.h5") as b:
        assert a[name][()].tobytes() == b[name][()].tobytes()
    assert pres["metrics"]["p0.100"]["noise-free"]["nearest"] == reference[1]["metrics"]["p0.100"]["noise-free"][
        "nearest"]


def test_tls_certificates_from_dask_config(tls_cluster, certs):
    """No --tls-* options: a tls:// address takes the client's certificates from Dask's config."""
    conf = {"distributed.comm.tls.ca-file": certs["ca"], "distributed.comm.tls.client.cert": certs["cert"],
            "distributed.comm.tls.client.key": certs["key"]}
    with dask.config.set(conf), distributed.connect(cluster=tls_cluster) as c:
        assert c.submit(sum, [1, 2], pure=False).result() == 3
        assert all(w.startswith("tls://") for w in c.scheduler_info()["workers"])


def test_tls_foreign_certificates_refused(tmp_path, tls_cluster):
    """A client whose certificates another CA signed is refused by the scheduler: one line."""
    other = {k: str(v) for k, v in make_certs(tmp_path / "other").items()}
    sec = distributed.tls_security(other["ca"], other["cert"], other["key"], address=tls_cluster)
    with pytest.raises(ClreconError, match="no TLS connection to a Dask scheduler there") as e:
        with distributed.connect(cluster=tls_cluster, security=sec):
            pass
    assert "\n" not in str(e.value)


def test_tls_errors_are_one_line(tmp_path, certs, capsys):
    """Bad TLS settings fail before any connection, with one line naming the option and the file."""
    other = {k: str(v) for k, v in make_certs(tmp_path / "other").items()}
    (tmp_path / "notes.txt").write_text("not a certificate")
    addr = "tls://127.0.0.1:1"  # nothing listens: each case must fail before connecting
    cases = [
        ([], "tls:// scheduler needs certificates and none are given"),
        (["--tls-ca-file", certs["ca"]], "--tls-cert missing"),
        (["--tls-ca-file", str(tmp_path / "nope.pem"), "--tls-cert", certs["cert"], "--tls-key", certs["key"]],
         "--tls-ca-file .*nope.pem: cannot read the CA certificate file \\(No such file"),
        (["--tls-ca-file", certs["ca"], "--tls-cert", str(tmp_path / "notes.txt"), "--tls-key", certs["key"]],
         "--tls-cert .*notes.txt: not a PEM file"),
        (["--tls-ca-file", certs["ca"], "--tls-cert", certs["cert"], "--tls-key", other["key"]],
         "--tls-cert .*node.pem / --tls-key .*node.key: not a PEM certificate with its matching private key"),
        (["--tls-ca-file", certs["key"], "--tls-cert", certs["cert"], "--tls-key", certs["key"]],
         "--tls-ca-file .*node.key: not a usable CA certificate"),
    ]
    (tmp_path / "unreadable.pem").write_text(open(certs["cert"]).read())
    (tmp_path / "unreadable.pem").chmod(0)
    if not os.access(tmp_path / "unreadable.pem", os.R_OK):  # root reads any file
        cases.append((["--tls-ca-file", certs["ca"], "--tls-cert", str(tmp_path / "unreadable.pem"),
                       "--tls-key", certs["key"]], "--tls-cert .*unreadable.pem: cannot read the client certificate"))
    base = ["run", "--scene", "tiny", "--out", str(tmp_path / "run"), "--no-progress"]
    term = signal.getsignal(signal.SIGTERM)
    try:
        for extra, pattern in cases:
            assert main(base + ["--cluster", addr, *extra]) == 2, extra
            err = capsys.readouterr().err
            assert err.count("\n") == 1 and re.search(pattern, err), (extra, err)
        for argv in (base + ["--cluster", "tcp://127.0.0.1:1", *_tls_args(certs)], base + _tls_args(certs),
                     base + ["--workers", "1", *_tls_args(certs)]):
            assert main(argv) == 2
            err = capsys.readouterr().err
            assert err.count("\n") == 1 and "the certificates are for a tls:// scheduler" in err, err
    finally:
        signal.signal(signal.SIGTERM, term)
    assert not (tmp_path / "run").exists()
    with pytest.raises(ClreconError, match="TLS certificates .* are for a tls:// scheduler address"):
        with distributed.connect(cluster="tcp://127.0.0.1:1", security=distributed.tls_security(
                certs["ca"], certs["cert"], certs["key"], address="tls://x")):
            pass


def test_bench_tls_round_trips():
    """``python -m benchmarks.dask_scaling``'s tls:// vs tcp:// figure runs and reports both protocols."""
    from benchmarks.dask_scaling import _tls_lines, tls_overhead

    t = tls_overhead(1)
    assert set(t["trivial_round_trip_s"]) == {"tcp", "tls"} and t["round_trips"] == 10
    assert all(v > 0 for v in (*t["trivial_round_trip_s"].values(), *t["payload_round_trip_s"].values()))
    (line,) = _tls_lines(t)
    assert "tls:// vs tcp://" in line and "MB/s over TLS" in line
