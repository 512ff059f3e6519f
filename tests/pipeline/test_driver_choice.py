"""The run's CPU driver chosen by timing (clrecon/pipeline/driver_choice.py, driver_timing.py; docs/drivers.md)."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pyopencl as cl
import pytest

from clrecon.config.overrides import load_scene
from clrecon.core import drivers
from clrecon.core.runtime import Runtime
from clrecon.pipeline import driver_choice, driver_timing
from clrecon.pipeline.driver_choice import Decision, DriverTiming
from clrecon.pipeline.run import run


def _timing(key, **per_unit):
    base = dict.fromkeys(driver_timing.FAMILIES, 1e-9)
    base.update(per_unit)
    return DriverTiming(key, key, key, "1", base, True)


@pytest.fixture
def cache(tmp_path, monkeypatch):
    monkeypatch.setenv("CLRECON_CACHE", str(tmp_path / "cache"))
    monkeypatch.delenv("CLRECON_DEVICE", raising=False)
    monkeypatch.delenv("CLRECON_PROBE_FAIL", raising=False)
    monkeypatch.delenv(drivers.PREFERENCE_ENV, raising=False)
    return tmp_path / "cache"


def test_the_choice_follows_the_run_mix():
    """Intel backprojects 1.5x faster, PoCL interpolates 4.5x and draws noise 2x faster (the issue's Zen 3
    figures): an interpolation-heavy run takes PoCL, a backprojection-heavy one Intel."""
    intel = _timing("intel", backprojection=1.0e-9, interpolation=4.5e-8, noise=2e-7)
    pocl = _timing("pocl", backprojection=1.5e-9, interpolation=1.0e-8, noise=1e-7)
    interp_heavy = {"interpolation": 1e9, "noise": 1e8, "backprojection": 1e9}
    fbp_heavy = {"interpolation": 1e9, "noise": 1e8, "backprojection": 1e11}
    d = driver_choice.decide(interp_heavy, [intel, pocl])
    assert d.key == "pocl" and "pocl" in d.reason and "intel" in d.reason
    assert d.predicted["intel"]["total"] == pytest.approx(1.0 + 45 + 20, rel=1e-3)
    assert driver_choice.decide(fbp_heavy, [intel, pocl]).key == "intel"


def test_a_later_driver_must_win_by_the_margin():
    first = _timing("intel", backprojection=1.0e-9)
    close = _timing("pocl", backprojection=(1 - driver_choice.MARGIN / 2) * 1.0e-9)
    clear = _timing("pocl", backprojection=(1 - 2 * driver_choice.MARGIN) * 1.0e-9)
    work = {"backprojection": 1e10}
    assert driver_choice.decide(work, [first, close]).key == "intel"
    assert driver_choice.decide(work, [first, clear]).key == "pocl"


def test_one_driver_is_taken_without_timing_comparison():
    d = driver_choice.decide({"noise": 1.0}, [_timing("intel")])
    assert d.key == "intel" and d.reason == "the only CPU driver that passes the probe"
    assert driver_choice.decide({}, []).key is None


def test_run_work_counts_what_the_run_does():
    demo = load_scene("demo")
    w = driver_choice.run_work(demo)
    assert set(w) == set(driver_timing.FAMILIES) and all(v > 0 for v in w.values())
    # fewer slices: less rebinning and backprojection, the same projections within the window's reach
    narrow = driver_choice.run_work(demo, slices_z=[0.0, 1.0])
    assert narrow["backprojection"] < w["backprojection"] and narrow["ssrb"] < w["ssrb"]
    # one method of the five 5D-like ones: a quarter or less of the images
    one = driver_choice.run_work(demo, methods=("barycentric",))
    assert one["backprojection"] < 0.3 * w["backprojection"] and one["noise"] == w["noise"]
    # without noise, no noise work
    quiet = load_scene("demo", noise={"enabled": False})
    assert driver_choice.run_work(quiet)["noise"] == 0.0
    # the paper's scan is backprojection-heavier than the demo
    paper = driver_choice.run_work(load_scene("paper-p010"))
    share = {k: x["backprojection"] / x["interpolation"] for k, x in (("demo", w), ("paper", paper))}
    assert share["paper"] > share["demo"]


def test_timings_are_kept_per_machine_and_no_child_runs_the_second_time(cache, monkeypatch):
    drivers.register_wheel_drivers()
    devs = drivers.first_device_per_driver(cl.get_platforms())
    dev, idx = next(((d, i) for d, i in devs if drivers.probe_device(d, i).ok), (None, None))
    if dev is None:
        pytest.skip("no CPU driver passes the probe here")
    t = driver_choice.time_driver(dev, idx)
    assert t is not None and not t.cached and t.child_seconds > 0
    assert all(t.seconds_per_unit[f] > 0 for f in driver_timing.FAMILIES), t
    kept = json.loads(driver_choice.timings_path().read_text())
    assert len(kept) == 1 and next(iter(kept.values()))["cpu"] == drivers.cpu_line()

    def no_child(*a):
        raise AssertionError("timed again although the timings were kept")

    monkeypatch.setattr(driver_choice, "run_timing_child", no_child)
    again = driver_choice.time_driver(dev, idx)
    assert again.cached and again.seconds_per_unit == pytest.approx(t.seconds_per_unit)


def test_a_driver_known_to_fail_the_probe_is_not_timed(cache, monkeypatch):
    drivers.register_wheel_drivers()
    dev, idx = drivers.first_device_per_driver(cl.get_platforms())[0]
    drivers.remember_verdict(dev, False, "failed for the test")

    def no_child(*a):
        raise AssertionError("a failing driver was timed")

    monkeypatch.setattr(driver_choice, "run_timing_child", no_child)
    assert driver_choice.time_driver(dev, idx) is None


def test_the_timing_child_reports_a_failed_probe_as_a_verdict(cache, monkeypatch):
    drivers.register_wheel_drivers()
    dev, idx = drivers.first_device_per_driver(cl.get_platforms())[0]
    monkeypatch.setenv("CLRECON_PROBE_FAIL", "intel,portable,pocl")
    res = driver_choice.run_timing_child(dev.platform.name, idx)
    assert not res["ok"] and "seconds_per_unit" not in res
    assert "forced failure" in res["reason"] or "probe process" in res["reason"], res


def test_the_preferred_driver_comes_first_and_says_why(cache, monkeypatch):
    drivers.register_wheel_drivers()
    ok = [d for d, i in drivers.first_device_per_driver(cl.get_platforms()) if drivers.probe_device(d, i).ok]
    if not ok:
        pytest.skip("no CPU driver passes the probe here")
    key = drivers.driver_of(ok[-1].platform.name).key  # the last working one: preferring it changes the order
    drivers.prefer(key, "predicted fastest for the test")
    assert os.environ[drivers.PREFERENCE_ENV] == key
    first = drivers.candidates(cl.get_platforms())[0][1]
    assert drivers.driver_of(first.platform.name).key == key
    rt = Runtime()
    assert drivers.driver_of(rt.device.platform.name).key == key
    assert rt.driver["chosen_by"] == "predicted fastest for the test"
    with pytest.raises(ValueError, match="unknown CPU driver 'nvidia'"):
        drivers.prefer("nvidia", "no")


def test_a_run_records_the_timed_choice(cache, monkeypatch, tmp_path):
    """With two working drivers the run logs and records its choice; here the decision is given (this CPU may
    have one working driver), the rest is the real run."""
    drivers.register_wheel_drivers()
    ok = [d for d, i in drivers.first_device_per_driver(cl.get_platforms()) if drivers.probe_device(d, i).ok]
    if not ok:
        pytest.skip("no CPU driver passes the probe here")
    key = drivers.driver_of(ok[0].platform.name).key
    dec = Decision(key, f"predicted fastest for this run's kernels by timing: {key} 1 s against other 2 s",
                   {key: {"total": 1.0}, "other": {"total": 2.0}})
    monkeypatch.setattr(driver_choice, "choose_for_run", lambda *a, **k: dec)
    lines = []
    res = run(load_scene("tiny"), tmp_path / "run", methods=["barycentric"], slice_range=(0, 1), progress=False,
              report=False, log=lambda *a, **k: lines.append(" ".join(map(str, a))))
    assert res["driver"]["timing"]["driver"] == key and res["driver"]["chosen_by"] == dec.reason
    assert any(ln.startswith(f"OpenCL driver: {key}, predicted fastest") for ln in lines), lines


def test_devices_shows_the_timings(cache):
    cp = subprocess.run([sys.executable, "-m", "clrecon", "devices"], capture_output=True, text=True,
                        env=dict(os.environ), timeout=600)
    assert cp.returncode == 0, cp.stderr
    assert "Driver timings (seconds per unit of work" in cp.stdout
    assert ("one CPU driver passes the probe" in cp.stdout) or ("predicted kernel seconds" in cp.stdout), cp.stdout


def test_a_timing_that_dies_after_the_probe_leaves_the_driver_working_and_the_order_decides(cache, monkeypatch):
    drivers.register_wheel_drivers()
    dev, idx = drivers.first_device_per_driver(cl.get_platforms())[0]
    monkeypatch.setattr(driver_choice, "run_timing_child", lambda *a: {
        "ok": True, "reason": "builds and runs the probe kernel", "died": "the probe process died on signal 11"})
    assert driver_choice.time_driver(dev, idx) is None
    assert drivers.cached_verdict(dev).ok
    d = driver_choice.choose_for_run(load_scene("tiny"))
    assert d.key is None and "could not be timed" in d.reason
    driver_choice.apply(d)
    assert drivers.PREFERENCE_ENV not in os.environ


def test_a_timing_child_without_a_verdict_leaves_it_to_the_plain_probe(cache, monkeypatch):
    drivers.register_wheel_drivers()
    dev, idx = drivers.first_device_per_driver(cl.get_platforms())[0]
    monkeypatch.setattr(driver_choice, "run_timing_child", lambda *a: {
        "ok": False, "reason": "the probe process exited with status 1 (ImportError)", "no_output": True})
    monkeypatch.setattr(drivers, "run_probe_child", lambda *a: (True, "probed by the plain probe"))
    assert driver_choice.time_driver(dev, idx) is None
    assert drivers.cached_verdict(dev).reason == "probed by the plain probe"


def test_children_run_this_checkout_of_clrecon(tmp_path, monkeypatch):
    """A child started from another folder imports the same clrecon as its parent (not an older installed copy)."""
    monkeypatch.chdir(tmp_path)
    res = drivers.run_json_child("clrecon.pipeline.driver_timing", ["no such platform", "0"], 120)
    assert res == {"ok": False, "reason": "platform 'no such platform' not found in the child process"}
