"""The machine-speed record of runs and benches (clrecon/core/machine_speed.py)."""

from __future__ import annotations

import math
import os
import subprocess
import sys

import pytest

from clrecon.core import machine_speed as ms


def test_probe_is_a_fixed_positive_workload():
    a, b = ms.probe_seconds(repeats=1), ms.probe_seconds(repeats=3)
    assert 0 < a < 10 and 0 < b < 10 and math.isfinite(a)


def test_proc_stat_is_read_in_core_seconds(tmp_path, monkeypatch):
    """The first line of /proc/stat, in clock ticks, becomes core-seconds by kind; a file that
    does not start with the aggregate "cpu" line, or none, gives None."""
    stat = tmp_path / "stat"
    stat.write_text("cpu  1000 20 300 5000 40 0 6 70 0 0\ncpu0 500 10 150 2500 20 0 3 35 0 0\n")
    real_open = open
    monkeypatch.setattr(ms.os, "sysconf", lambda name: 100, raising=False)
    monkeypatch.setattr("builtins.open", lambda p, *a, **k: real_open(stat if p == "/proc/stat" else p, *a, **k))
    got = ms.machine_cpu_seconds()
    assert got == {"user": 10.0, "nice": 0.2, "system": 3.0, "idle": 50.0, "iowait": 0.4, "irq": 0.0,
                   "softirq": 0.06, "steal": 0.7}
    stat.write_text("intr 1 2 3\n")
    assert ms.machine_cpu_seconds() is None
    stat.unlink()
    assert ms.machine_cpu_seconds() is None


def test_finish_splits_the_machine_into_this_run_others_and_steal(monkeypatch):
    """Over 10 s of wall on 2 cores: the machine was busy 15 core-s, this process 9 of them, so
    other jobs 6 (30 % of the 20 core-s), and the hypervisor stole 2 (10 %)."""
    zero = dict.fromkeys(("user", "nice", "system", "idle", "iowait", "irq", "softirq", "steal"), 0.0)
    later = dict(zero, user=12.0, nice=1.0, system=1.5, softirq=0.5, idle=3.0, steal=2.0)
    stats, own, clock = iter([zero, later]), iter([100.0, 109.0]), iter([50.0, 60.0])
    monkeypatch.setattr(ms, "machine_cpu_seconds", lambda: next(stats))
    monkeypatch.setattr(ms, "own_cpu_seconds", lambda: next(own))
    monkeypatch.setattr(ms.time, "perf_counter", lambda: next(clock))
    monkeypatch.setattr(ms.os, "cpu_count", lambda: 2)
    monkeypatch.setattr(ms, "probe_seconds", lambda repeats=ms.PROBE_REPEATS: 0.02)
    out = ms.start().finish()
    assert out["wall_s"] == 10.0 and out["cores"] == 2 and out["own_core_s"] == 9.0
    assert out["machine_busy_core_s"] == 15.0 and out["others_core_s"] == 6.0 and out["steal_core_s"] == 2.0
    assert out["others_fraction"] == pytest.approx(0.3) and out["steal_fraction"] == pytest.approx(0.1)
    assert out["probe_seconds"] == {"start": 0.02, "end": 0.02}
    assert ms.describe(out) == "probe 20.0 ms -> 20.0 ms; other jobs 30 % and steal 10 % of 2 cores"


def test_finish_without_proc_stat_keeps_the_probe(monkeypatch):
    monkeypatch.setattr(ms, "machine_cpu_seconds", lambda: None)
    out = ms.start(probe=False).finish(probe=False)
    assert "others_fraction" not in out and out["probe_seconds"] == {"start": None, "end": None}
    assert ms.describe(out) == "no probe"


@pytest.mark.skipif(not os.path.isdir("/proc/self"), reason="reads /proc")
def test_live_children_count_as_this_run():
    """A child still running (the run's helper process) counts as this run's CPU, not as another
    job's: 0.5 s of its CPU show while it lives and, once waited for, through RUSAGE_CHILDREN."""
    before = ms.own_cpu_seconds()
    child = subprocess.Popen([sys.executable, "-c", "import sys, time\nwhile time.process_time() < 0.5: pass\n"
                              "print('done', flush=True)\ntime.sleep(30)"], stdout=subprocess.PIPE, text=True)
    try:
        assert child.stdout.readline().strip() == "done"
        assert ms._live_children_cpu_seconds() >= 0.45
        assert ms.own_cpu_seconds() - before >= 0.45
    finally:
        child.kill()
        child.wait()
    assert ms.own_cpu_seconds() - before >= 0.45  # now a waited-for child
