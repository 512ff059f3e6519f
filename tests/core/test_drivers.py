"""The OpenCL CPU driver choice: registration of wheel drivers, the probe, its cache, the order, the
fallback and the no-driver error (clrecon/core/drivers.py, docs/drivers.md).

The failures are forced through the drivers' own compilers (``CLRECON_PROBE_FAIL`` puts an
``#error`` into the probe's source for the platforms it names), so the fallback and the error are
tested on a machine where every driver works.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys

import numpy as np
import pyopencl as cl
import pytest

from clrecon.core import driver_probe, drivers
from clrecon.core import runtime as cl_runtime
from clrecon.core.runtime import KernelBuildError, Runtime


def _installed(key: str) -> bool:
    drivers.register_wheel_drivers()
    drv = {d.key: d for d in drivers.CPU_DRIVERS}[key]
    return any(drv.matches(p.name) for p in cl.get_platforms())


_verdicts: dict = {}


def _verdict(key: str) -> tuple[bool, str]:
    """Whether driver ``key`` is installed and passes the probe here (in a child: a driver that aborts
    while compiling, as PoCL 3.0 does on some AVX-512 CPUs, must not take the test process with it)."""
    if key not in _verdicts:
        if not _installed(key):
            _verdicts[key] = (False, "not installed")
        else:
            drv = {d.key: d for d in drivers.CPU_DRIVERS}[key]
            name = next(p.name for p in cl.get_platforms() if drv.matches(p.name))
            _verdicts[key] = drivers.run_probe_child(name, 0)
    return _verdicts[key]


def _works(key: str) -> bool:
    return _verdict(key)[0]


def _why_not(*keys: str) -> str:
    return "; ".join(f"{k}: {_verdict(k)[1]}" for k in keys if not _works(k))


needs_both = pytest.mark.skipif(not (_works("intel") and _works("pocl")),
                                reason=f"needs both CPU drivers working on this CPU ({_why_not('intel', 'pocl')})")
needs_intel = pytest.mark.skipif(not _installed("intel"), reason="Intel's CPU runtime is not installed here")
needs_pocl = pytest.mark.skipif(not _works("pocl"), reason=f"PoCL does not run here ({_why_not('pocl')})")


@pytest.fixture
def cache(tmp_path, monkeypatch):
    """A fresh clrecon cache (no remembered verdicts, no kernel binaries) and no CLRECON_DEVICE."""
    monkeypatch.setenv("CLRECON_CACHE", str(tmp_path / "cache"))
    monkeypatch.delenv("CLRECON_DEVICE", raising=False)
    monkeypatch.delenv("CLRECON_PROBE_FAIL", raising=False)
    return tmp_path / "cache"


def test_probe_reference_on_edge_cases():
    x = driver_probe.probe_inputs()
    assert x.dtype == np.float32 and x.size % 16 == 0 and x[:4].tolist() == [0.0, np.float32(1e-30), 1.0, 1e6]
    ref = driver_probe.probe_reference(x)
    # x = 0: sqrt 0 + exp 0 + log 1 + atan2(0, 1) = 1; x = 1: 1 + e^-1 + ln 2 + atan(1/2)
    assert ref[0] == 1.0
    assert ref[2] == pytest.approx(1 + np.exp(-1) + np.log(2) + np.arctan(0.5), rel=1e-15)
    assert np.isfinite(ref).all()


@pytest.mark.parametrize("key", [d.key for d in drivers.CPU_DRIVERS])
def test_the_probe_kernel_matches_its_float64_reference_on_each_installed_cpu_driver(key):
    """Runs kernels/probe.cl in this process on each installed CPU driver (tolerance RTOL 1e-5 |ref| +
    ATOL 1e-6, driver_probe.RTOL/ATOL), and the forced failure makes the driver's compiler fail."""
    if not _works(key):
        pytest.skip(f"{key} does not pass the probe on this CPU ({_verdict(key)[1]})")
    drv = {d.key: d for d in drivers.CPU_DRIVERS}[key]
    name = next(p.name for p in cl.get_platforms() if drv.matches(p.name))
    v = driver_probe.run_probe(name, 0)
    assert v["ok"], v
    os.environ["CLRECON_PROBE_FAIL"] = key if key != "pocl" else "portable"
    try:
        v = driver_probe.run_probe(name, 0)
    finally:
        del os.environ["CLRECON_PROBE_FAIL"]
    assert not v["ok"] and "the kernel build failed" in v["reason"] and "forced failure" in v["reason"], v


def test_verdicts_are_remembered_so_the_second_runtime_probes_nothing(cache, monkeypatch):
    first = Runtime()
    assert first.driver["probes"] and not first.driver["probes"][-1]["cached"]
    assert drivers.verdicts_path().is_file()

    def no_child(*a):
        raise AssertionError("probed again although the verdict was remembered")

    monkeypatch.setattr(drivers, "run_probe_child", no_child)
    second = Runtime()
    assert second.device.platform.name == first.device.platform.name
    assert all(p["cached"] for p in second.driver["probes"])


def test_a_forced_verdict_is_not_taken_for_a_real_one(cache, monkeypatch):
    """The forced-failure setting is part of a verdict's key: a failure forced once is not remembered
    as the driver's real verdict."""
    rt = Runtime()
    name = rt.device.platform.name
    dev_key = drivers.verdict_key(rt.device)
    monkeypatch.setenv("CLRECON_PROBE_FAIL", name)
    assert drivers.verdict_key(rt.device) != dev_key


@needs_both
def test_default_order_is_intel_then_pocl(cache):
    rt = Runtime()
    assert drivers.INTEL.matches(rt.device.platform.name), rt.driver
    assert [p["platform"] for p in rt.driver["probes"]] == [rt.device.platform.name]


@needs_both
def test_a_driver_whose_builds_fail_is_passed_over_for_the_next(cache, monkeypatch):
    monkeypatch.setenv("CLRECON_PROBE_FAIL", "intel")
    rt = Runtime()
    assert drivers.POCL.matches(rt.device.platform.name)
    probes = rt.driver["probes"]
    assert [p["ok"] for p in probes] == [False, True]
    assert "forced failure" in probes[0]["reason"] and drivers.INTEL.matches(probes[0]["platform"])
    # the kernels run on the driver that was chosen
    x = np.arange(4, dtype=np.int32)
    buf = rt.to_device(x, np.int32)
    assert (rt.from_device(buf, (4,), np.int32) == x).all()


def test_no_working_driver_is_one_line_naming_the_cpu_each_driver_and_the_remedy(cache, monkeypatch):
    monkeypatch.setenv("CLRECON_PROBE_FAIL", "intel,portable,pocl")
    with pytest.raises(drivers.NoWorkingDriver) as e:
        Runtime()
    msg = str(e.value)
    assert "\n" not in msg
    assert drivers.cpu_line() in msg and "Remedy:" in msg
    for d in drivers.CPU_DRIVERS:  # every known driver: tried with its reason, or named as not installed
        assert (d.key in msg) or any(d.matches(part) for part in msg.split(";")), (d, msg)
    assert "forced failure" in msg


def test_clrecon_device_overrides_the_probe(cache, monkeypatch):
    spec, drv = ("portable", drivers.POCL) if _works("pocl") else ("intel", drivers.INTEL)
    if not _works(drv.key):
        pytest.skip(f"no CPU driver passes the probe here ({_why_not('intel', 'pocl')})")
    monkeypatch.setenv("CLRECON_PROBE_FAIL", "intel,portable,pocl")  # no probe runs, so none fails
    rt = Runtime(spec)
    assert drv.matches(rt.device.platform.name) and rt.driver["probes"] == []
    assert rt.driver["chosen_by"] == f"device {spec!r} asked for"
    monkeypatch.setenv("CLRECON_DEVICE", spec)
    assert Runtime().driver["chosen_by"] == f"CLRECON_DEVICE={spec}"


def test_the_cli_says_no_driver_in_one_line_with_exit_code_2_and_writes_nothing(cache, tmp_path):
    env = dict(os.environ, CLRECON_PROBE_FAIL="intel,portable,pocl", CLRECON_CACHE=str(cache))
    env.pop("CLRECON_DEVICE", None)
    out = tmp_path / "run"
    cp = subprocess.run([sys.executable, "-m", "clrecon", "run", "--scene", "tiny", "--out", str(out)],
                        capture_output=True, text=True, env=env, timeout=300)
    assert cp.returncode == 2, cp.stderr
    lines = [ln for ln in cp.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("clrecon: error: no OpenCL CPU driver"), cp.stderr
    assert "Traceback" not in cp.stderr
    assert not out.exists()  # no run.json stub, no empty volumes.d/


def test_register_writes_an_icd_folder_naming_the_installed_library_and_keeps_the_system_ones(tmp_path,
                                                                                              monkeypatch):
    lib = tmp_path / "lib" / "libintelocl.so"
    lib.parent.mkdir()
    lib.write_bytes(b"")
    system = tmp_path / "etc-vendors"
    system.mkdir()
    (system / "nvidia.icd").write_text("libnvidia-opencl.so.1\n")
    monkeypatch.setattr(drivers, "SYSTEM_ICD_DIR", system)
    monkeypatch.setattr(drivers, "wheel_library", lambda d: lib if d.key == "intel" else None)
    env: dict = {}
    reg = drivers.register_wheel_drivers(env, cache_dir=tmp_path / "c")
    folder = env["OCL_ICD_VENDORS"]
    assert reg["icd_dir"] == folder and reg["registered"] == {"intel": str(lib)}
    files = {e.name: open(e.path).read() for e in os.scandir(folder)}
    assert files == {"clrecon-intel.icd": f"{lib}\n", "nvidia.icd": "libnvidia-opencl.so.1\n"}
    # a user's own OCL_ICD_VENDORS is left as it is
    user = {"OCL_ICD_VENDORS": "/opt/my-vendors"}
    reg = drivers.register_wheel_drivers(user, cache_dir=tmp_path / "c")
    assert user == {"OCL_ICD_VENDORS": "/opt/my-vendors"} and reg["icd_dir"] is None and "left as it is" in reg["note"]


@needs_intel
def test_intel_wheel_is_found_and_its_icd_names_the_installed_library():
    lib = drivers.wheel_library(drivers.INTEL)
    assert lib is not None and lib.name == "libintelocl.so" and lib.is_file()
    reg = drivers.register_wheel_drivers()
    if reg["icd_dir"]:  # (not when the user set OCL_ICD_VENDORS)
        with open(os.path.join(reg["icd_dir"], "clrecon-intel.icd")) as f:
            assert f.read().strip() == str(lib)


@needs_intel
def test_intel_kernels_are_built_once_per_machine_not_once_per_process(cache, monkeypatch):
    """Intel's runtime keeps no build cache of its own: the runtime keeps the binaries (one per program),
    and a later runtime loads them instead of compiling; a damaged binary is rebuilt from source."""
    rt = Runtime("intel")
    rt.program("ssrb.cl")
    bins = list((cache / "kernels").glob("*.bin"))
    assert len(bins) == 1

    def no_compile(*a):
        raise AssertionError("compiled again although the binary was kept")

    rt2 = Runtime("intel")
    monkeypatch.setattr(rt2, "_keep_binary", no_compile)
    assert rt2.kernel("ssrb.cl", "ssrb_rows").function_name == "ssrb_rows"
    monkeypatch.undo()
    monkeypatch.setenv("CLRECON_CACHE", str(cache))
    bins[0].write_bytes(b"not a binary")
    rt3 = Runtime("intel")
    assert rt3.kernel("ssrb.cl", "ssrb_rows").function_name == "ssrb_rows"
    assert bins[0].read_bytes() != b"not a binary"


@needs_pocl
def test_pocl_keeps_no_binaries_of_ours(cache):
    """PoCL caches its builds itself (POCL_CACHE_DIR): nothing is written twice."""
    rt = Runtime("portable")
    rt.program("ssrb.cl")
    assert not (cache / "kernels").exists()


def test_a_failed_build_is_a_kernel_build_error(cache):
    rt = cl_runtime.get_runtime()
    with pytest.raises(KernelBuildError):
        rt._build("x.cl", "__kernel void k() { nope; }", [])


def test_devices_lists_every_platform_and_whether_it_builds(cache):
    cp = subprocess.run([sys.executable, "-m", "clrecon", "devices", "--json"], capture_output=True, text=True,
                        env=dict(os.environ, CLRECON_CACHE=str(cache)), timeout=300)
    assert cp.returncode == 0, cp.stderr
    rows = json.loads(cp.stdout)
    names = {p.name for p in cl.get_platforms()}
    assert {r["platform"] for r in rows["devices"]} == names
    for r in rows["devices"]:
        assert set(r) >= {"platform", "driver_version", "device", "type", "probe_ok", "probe_reason", "default"}
    assert sum(r["default"] for r in rows["devices"]) == 1
    assert rows["cpu"] == drivers.cpu_line()


ZEN5 = "EPYC-Milan,family=26,model=2"  # an AMD CPU of family 26 (Zen 5), as qemu's CPUID presents it


@pytest.mark.skipif(shutil.which("qemu-x86_64") is None,
                    reason="needs qemu-x86_64 (Debian's qemu-user) to present a Zen 5 CPU to the drivers")
def test_on_an_emulated_zen5_cpu_pocl_cannot_build_and_intel_can():
    """The failure this module exists for, not forced: PoCL 3.0's LLVM 14 names a family-26 AMD CPU
    "generic" and its clang rejects that; Intel's runtime builds and runs the probe on it. The probes
    run in one process under qemu's user-mode emulator with the CPUID of a Zen 5."""
    if not (_installed("intel") and _installed("pocl")):
        pytest.skip("needs both CPU drivers installed")
    code = ("import json; from clrecon.core import drivers, driver_probe; import pyopencl as cl; "
            "drivers.register_wheel_drivers(); "
            "print(json.dumps({p.name: driver_probe.run_probe(p.name, 0) for p in cl.get_platforms() "
            "if drivers.driver_of(p.name)}))")
    cp = subprocess.run(["qemu-x86_64", "-cpu", ZEN5, sys.executable, "-c", code], capture_output=True, text=True,
                        timeout=600, env=dict(os.environ, PYTHONPATH=os.pathsep.join(sys.path)))
    assert cp.returncode == 0, cp.stderr[-2000:]
    verdicts = json.loads(cp.stdout.strip().splitlines()[-1])
    pocl = next(v for k, v in verdicts.items() if drivers.POCL.matches(k))
    intel = next(v for k, v in verdicts.items() if drivers.INTEL.matches(k))
    assert not pocl["ok"] and "unknown target CPU 'generic'" in pocl["reason"], pocl
    assert intel["ok"], intel
