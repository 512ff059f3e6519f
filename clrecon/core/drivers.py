"""Which OpenCL CPU driver runs the kernels: found, registered, probed once per machine, chosen in order.

clrecon runs on whichever OpenCL CPU driver works on this CPU (docs/drivers.md). Two come from
PyPI with the package on x86-64 Linux:

``intel``
    Intel's CPU OpenCL runtime (``intel-opencl-rt``); runs on Intel and AMD x86-64 CPUs of every
    generation seen here, Zen 5 included.
``pocl``
    PoCL (``pocl-binary-distribution`` 3.0, LLVM 14, through ``pyopencl[pocl]``); its LLVM does
    not know CPUs newer than 2022 (AMD Zen 5: "unknown target CPU 'generic'") and it has no
    setting to name another CPU, so there it cannot build any kernel.

Default choice, with no ``CLRECON_DEVICE``: the CPU platforms in :data:`CPU_DRIVERS` order, then
any other CPU platform; the first whose device passes the probe (:mod:`clrecon.core.driver_probe`,
a small kernel built and run in a child process) runs the kernels. The order puts the faster
driver first where both work (measured by ``python -m clrecon bench --drivers``, docs/drivers.md).
A probe's verdict is kept per CPU, platform, driver version and probe source in
``<cache>/opencl-drivers.json``, so the second run probes nothing. ``CLRECON_DEVICE`` overrides
all of it (GPUs, Oclgrind, a driver by name) and nothing is probed.

Intel's wheel installs an ICD file naming its build machine's prefix
(``/opt/anaconda1anaconda2anaconda3/lib/libintelocl.so``), which the ICD loader cannot open.
:func:`register_wheel_drivers` writes an ICD folder naming the installed library (plus the
system's own ICD files, so GPUs stay visible) and points ``OCL_ICD_VENDORS`` at it for this
process and its children -- before the first platform query, which is when the loader reads it.
A user's own ``OCL_ICD_VENDORS`` is left as it is.
"""

from __future__ import annotations

import dataclasses
import hashlib
import importlib.metadata
import json
import os
import platform
import subprocess
import sys
import tempfile
import threading
from pathlib import Path

from clrecon.core.cache import default_cache_dir
from clrecon.core.errors import OpenCLUnavailable
from clrecon.core.kernel_sources import load_source

#: Seconds a probe child may take (a cold build of the probe takes about 1 s).
PROBE_TIMEOUT_S = 180
#: Bump when the probe's meaning changes (its source is hashed into the verdict's key already).
PROBE_VERSION = 1
#: Where the ICD loader looks when OCL_ICD_VENDORS is unset (Khronos and ocl-icd default).
SYSTEM_ICD_DIR = Path("/etc/OpenCL/vendors")


@dataclasses.dataclass(frozen=True)
class CpuDriver:
    """An OpenCL CPU driver clrecon knows by name."""

    key: str
    #: lower-case substrings of its OpenCL platform name
    platform_match: tuple[str, ...]
    #: PyPI distribution that brings it
    package: str
    #: library its ICD file must name, found in ``package``'s files; None: pyopencl ships the ICD
    icd_library: str | None = None

    def matches(self, platform_name: str) -> bool:
        return any(s in platform_name.lower() for s in self.platform_match)


INTEL = CpuDriver("intel", ("intel(r) opencl",), "intel-opencl-rt", "libintelocl.so")
POCL = CpuDriver("pocl", ("portable computing language", "pocl"), "pocl-binary-distribution")
#: The default order: Intel's runtime first -- it builds on every x86-64 CPU seen here and ran the
#: pipeline's kernels faster than PoCL 3.0 where both work (docs/drivers.md, "Which is faster").
CPU_DRIVERS = (INTEL, POCL)


def driver_of(platform_name: str) -> CpuDriver | None:
    """The known driver whose platform this is, or None."""
    return next((d for d in CPU_DRIVERS if d.matches(platform_name)), None)


# -- the CPU ----------------------------------------------------------------------------------

def cpu_description() -> dict:
    """This CPU: model name, vendor, family/model/stepping (x86) and a hash of its feature flags."""
    info = {"model_name": platform.processor() or platform.machine(), "machine": platform.machine()}
    try:
        text = Path("/proc/cpuinfo").read_text(errors="replace")
    except OSError:
        return info
    fields: dict[str, str] = {}
    for line in text.splitlines():
        if not line.strip():
            break  # the first processor's block describes them all
        k, _, v = line.partition(":")
        fields[k.strip()] = v.strip()
    for src, dst in (("model name", "model_name"), ("vendor_id", "vendor"), ("cpu family", "family"),
                     ("model", "model"), ("stepping", "stepping"), ("CPU part", "arm_part")):
        if src in fields:
            info[dst] = fields[src]
    flags = fields.get("flags") or fields.get("Features") or ""
    info["flags_sha"] = hashlib.sha256(" ".join(sorted(flags.split())).encode()).hexdigest()[:12]
    return info


def cpu_line(cpu: dict | None = None) -> str:
    """One line naming the CPU, e.g. ``AMD EPYC 9R45 (x86_64, AuthenticAMD family 26 model 2)``."""
    c = cpu or cpu_description()
    fam = f", {c.get('vendor', '')} family {c['family']} model {c.get('model', '?')}" if "family" in c else ""
    return f"{c.get('model_name') or '?'} ({c.get('machine', '?')}{fam})"


# -- registering the drivers that come as wheels ------------------------------------------------

_registered: dict | None = None
_reg_lock = threading.Lock()


def wheel_library(drv: CpuDriver) -> Path | None:
    """The installed ``drv.icd_library`` of ``drv.package``, or None where the package is absent."""
    if drv.icd_library is None:
        return None
    try:
        dist = importlib.metadata.distribution(drv.package)
    except importlib.metadata.PackageNotFoundError:
        return None
    for f in dist.files or ():
        if f.name == drv.icd_library:
            path = Path(dist.locate_file(f)).resolve()
            if path.is_file():
                return path
    return None


def register_wheel_drivers(environ=None, cache_dir: Path | None = None) -> dict:
    """Make the wheel-installed drivers visible to the ICD loader, once per process.

    Returns what was done: ``{"icd_dir": str | None, "registered": {key: library}, "note": str}``.
    Must run before the process's first OpenCL platform query (the loader reads
    ``OCL_ICD_VENDORS`` then); :class:`clrecon.core.runtime.Runtime` calls it first thing.
    """
    global _registered
    environ = os.environ if environ is None else environ
    with _reg_lock:
        if _registered is not None and environ is os.environ:
            return _registered
        libs = {d.key: lib for d in CPU_DRIVERS if (lib := wheel_library(d)) is not None}
        if not libs:
            result = {"icd_dir": None, "registered": {}, "note": "no wheel-installed driver needs registering"}
        elif environ.get("OCL_ICD_VENDORS"):
            result = {"icd_dir": None, "registered": {},
                      "note": f"OCL_ICD_VENDORS={environ['OCL_ICD_VENDORS']} set by the user: left as it is"}
        else:
            lines = {f"clrecon-{k}.icd": f"{lib}\n" for k, lib in libs.items()}
            try:  # the system's own drivers (GPUs) stay visible: the loader reads only our folder now
                for f in sorted(SYSTEM_ICD_DIR.glob("*.icd")):
                    lines.setdefault(f.name, f.read_text(errors="replace").strip() + "\n")
            except OSError:
                pass
            tag = hashlib.sha256(json.dumps(lines, sort_keys=True).encode()).hexdigest()[:16]
            folder = _write_icd_folder((cache_dir or default_cache_dir()) / "opencl-vendors" / tag, lines)
            environ["OCL_ICD_VENDORS"] = str(folder)
            result = {"icd_dir": str(folder), "registered": {k: str(v) for k, v in libs.items()},
                      "note": f"OCL_ICD_VENDORS={folder} for this process (wheel drivers: {', '.join(libs)})"}
        if environ is os.environ:
            _registered = result
        return result


def _write_icd_folder(folder: Path, files: dict[str, str]) -> Path:
    """``folder`` holding ``files`` (name -> text); written whole under a temporary name, then renamed.

    Falls back to a folder under the system's temporary directory where the cache is read-only."""
    if folder.is_dir() and all((folder / n).is_file() for n in files):
        return folder
    for parent in (folder.parent, Path(tempfile.gettempdir()) / "clrecon-opencl-vendors"):
        try:
            parent.mkdir(parents=True, exist_ok=True)
            tmp = Path(tempfile.mkdtemp(prefix=".icd-", dir=parent))
            for name, text in files.items():
                (tmp / name).write_text(text)
            dst = parent / folder.name
            try:
                os.rename(tmp, dst)
            except OSError:  # another process made it first: theirs holds the same files
                for f in tmp.iterdir():
                    f.unlink()
                tmp.rmdir()
            return dst
        except OSError:
            continue
    raise OpenCLUnavailable(f"cannot write the OpenCL ICD folder {folder} (nor one under the temporary directory)")


# -- probing ----------------------------------------------------------------------------------------

@dataclasses.dataclass(frozen=True)
class Verdict:
    """What the probe said of one device."""

    platform: str
    platform_version: str
    device: str
    driver_version: str
    ok: bool
    reason: str
    cached: bool = False

    def line(self) -> str:
        return f"{self.platform} {self.driver_version}: {self.reason}"


def _probe_source_sha() -> str:
    return hashlib.sha256(load_source("probe.cl").encode()).hexdigest()[:12]


def verdict_key(dev, cpu: dict | None = None) -> str:
    """Key of a device's verdict: CPU, platform, driver version, probe source, forced failures."""
    p = dev.platform
    payload = {"cpu": cpu or cpu_description(), "platform": p.name, "platform_version": p.version,
               "device": dev.name, "driver_version": dev.driver_version, "probe": PROBE_VERSION,
               "probe_source": _probe_source_sha(), "forced": os.environ.get("CLRECON_PROBE_FAIL", ""),
               "python": sys.version_info[:2]}
    return hashlib.sha256(json.dumps(payload, sort_keys=True).encode()).hexdigest()[:24]


def verdicts_path(cache_dir: Path | None = None) -> Path:
    return (cache_dir or default_cache_dir()) / "opencl-drivers.json"


def read_json_dict(path: Path) -> dict:
    """The JSON object in ``path``; {} where it is missing, unreadable or not an object."""
    try:
        data = json.loads(path.read_text())
        return data if isinstance(data, dict) else {}
    except (OSError, ValueError):
        return {}


def remember(path: Path, key: str, entry: dict) -> None:
    """Add one entry to the JSON object in ``path`` (read, merge, write under a temporary name, rename)."""
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        data = read_json_dict(path)
        data[key] = entry
        tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
        tmp.write_text(json.dumps(data, indent=1, sort_keys=True))
        os.replace(tmp, path)
    except OSError:
        pass  # a read-only cache: the probe runs again next time, nothing else is lost


#: The folder holding this ``clrecon`` package: first on a child's ``PYTHONPATH``, so that the child runs the
#: same clrecon as its parent (a checkout beside an older installed copy included).
PACKAGE_ROOT = Path(__file__).resolve().parents[2]


def child_environ() -> dict:
    """This process's environment for a child that runs clrecon's modules: :data:`PACKAGE_ROOT` put first on
    ``PYTHONPATH``."""
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(PACKAGE_ROOT)] + [p for p in env.get("PYTHONPATH", "").split(os.pathsep)
                                                               if p])
    return env


def run_json_child(module: str, args: list[str], timeout_s: float, what: str = "the probe") -> dict:
    """Run ``python -m module args...`` in a child process and return the JSON lines it prints, merged.

    A child that times out, cannot start, dies or prints no JSON gives ``{"ok": False, "reason": one line}``
    (a driver that aborts the process while compiling costs a verdict, not the run; ``"no_output": True``
    where it printed nothing); one that died after
    printing a JSON line gives that line with ``"died": reason`` added."""
    cmd = [sys.executable, "-m", module, *args]
    try:
        cp = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout_s, env=child_environ())
    except subprocess.TimeoutExpired:
        return {"ok": False, "reason": f"{what} did not finish in {timeout_s:g} s"}
    except OSError as e:
        return {"ok": False, "reason": f"{what} could not start: {e}"}
    lines = [ln for ln in cp.stdout.splitlines() if ln.startswith("{")]
    merged: dict = {}
    for ln in lines:
        merged.update(json.loads(ln))
    if cp.returncode != 0 or not lines:
        sig = -cp.returncode if cp.returncode < 0 else None
        how = f"died on signal {sig}" if sig else f"exited with status {cp.returncode}"
        err = [ln.strip() for ln in cp.stderr.splitlines() if ln.strip()]
        reason = f"the probe process {how} while building or running the kernel" + (f" ({err[-1][:200]})" if err
                                                                                      else "")
        if not lines:
            return {"ok": False, "reason": reason, "no_output": True}
        merged["died"] = reason
    return merged


def run_probe_child(platform_name: str, device_index: int) -> tuple[bool, str]:
    """Run :mod:`clrecon.core.driver_probe` in a child process: (ok, one-line reason)."""
    v = run_json_child("clrecon.core.driver_probe", [platform_name, str(device_index)], PROBE_TIMEOUT_S)
    return bool(v.get("ok")), str(v.get("reason", ""))


def cached_verdict(dev, cache_dir: Path | None = None) -> Verdict | None:
    """The probe's kept verdict on ``dev``, or None where it was never probed (with this key)."""
    p = dev.platform
    hit = read_json_dict(verdicts_path(cache_dir)).get(verdict_key(dev))
    if isinstance(hit, dict) and "ok" in hit:
        return Verdict(p.name, p.version, dev.name, dev.driver_version, bool(hit["ok"]), str(hit["reason"]),
                       cached=True)
    return None


def remember_verdict(dev, ok: bool, reason: str, cache_dir: Path | None = None) -> Verdict:
    """Keep a verdict on ``dev`` (from :func:`run_probe_child` or a child that probes and times)."""
    p = dev.platform
    remember(verdicts_path(cache_dir), verdict_key(dev), {"ok": ok, "reason": reason, "platform": p.name,
                                                          "driver_version": dev.driver_version, "device": dev.name,
                                                          "cpu": cpu_line()})
    return Verdict(p.name, p.version, dev.name, dev.driver_version, ok, reason)


def probe_device(dev, index: int, cache_dir: Path | None = None, use_cache: bool = True) -> Verdict:
    """The probe's verdict on ``dev`` (the ``index``-th device of its platform), cached on disk."""
    if use_cache and (hit := cached_verdict(dev, cache_dir)) is not None:
        return hit
    ok, reason = run_probe_child(dev.platform.name, index)
    return remember_verdict(dev, ok, reason, cache_dir)


# -- choosing -----------------------------------------------------------------------------------

def _is_cpu(dev) -> bool:
    import pyopencl as cl

    return dev.type == cl.device_type.CPU


# -- the run's preference -------------------------------------------------------------------------

#: Names the CPU driver (a :class:`CpuDriver` key) that this process and its children prefer: set by
#: :func:`prefer` (the run's timed choice, :mod:`clrecon.pipeline.driver_choice`), inherited by the
#: process pools and local Dask workers a run starts, so all of them use one driver.
PREFERENCE_ENV = "CLRECON_DRIVER_PREFERENCE"
_preference_reasons: dict[str, str] = {}


def prefer(key: str, reason: str) -> None:
    """Make driver ``key`` the first CPU driver in this process's (and its later children's) order."""
    if key not in {d.key for d in CPU_DRIVERS}:
        raise ValueError(f"unknown CPU driver {key!r}; known: {', '.join(d.key for d in CPU_DRIVERS)}")
    os.environ[PREFERENCE_ENV] = key
    _preference_reasons[key] = reason


def preferred() -> str | None:
    """The preferred driver's key (from :data:`PREFERENCE_ENV`), or None (an unknown value is ignored)."""
    key = os.environ.get(PREFERENCE_ENV, "").strip().lower()
    return key if key in {d.key for d in CPU_DRIVERS} else None


def candidates(platforms) -> list[tuple[int, object, int]]:
    """CPU devices in the default order: (rank, device, index in its platform).

    The preferred driver (:func:`preferred`) first, then the known drivers in :data:`CPU_DRIVERS`
    order, then any other CPU platform (Oclgrind, a simulator whose devices are not CPUs, is never
    a candidate)."""
    out = []
    pref = preferred()
    for p in platforms:
        drv = driver_of(p.name)
        rank = CPU_DRIVERS.index(drv) + 1 if drv else len(CPU_DRIVERS) + 1
        if drv is not None and drv.key == pref:
            rank = 0
        try:
            devs = p.get_devices()
        except Exception:  # noqa: BLE001 - a platform with no usable device is simply not a candidate
            continue
        for i, d in enumerate(devs):
            if _is_cpu(d):
                out.append((rank, d, i))
    return sorted(out, key=lambda t: t[0])


def first_device_per_driver(platforms) -> list[tuple[object, int]]:
    """(device, index in its platform) of the first CPU device of every known driver installed, in the
    order of :func:`candidates` (probed or not: :func:`probe_device` says whether it works)."""
    out, seen = [], set()
    for _rank, dev, idx in candidates(platforms):
        drv = driver_of(dev.platform.name)
        if drv is None or drv.key in seen:
            continue
        seen.add(drv.key)
        out.append((dev, idx))
    return out


def missing_drivers(platforms) -> list[CpuDriver]:
    """Known drivers with no platform installed (or not registered)."""
    names = [p.name for p in platforms]
    return [d for d in CPU_DRIVERS if not any(d.matches(n) for n in names)]


def remedy(machine: str | None = None) -> str:
    """What to do when no driver works, for this kind of machine."""
    machine = machine or platform.machine()
    if machine in ("x86_64", "AMD64"):
        return ("reinstall clrecon so that Intel's CPU runtime comes with it (`pip install --force-reinstall "
                "clrecon`, or `pip install intel-opencl-rt intel-cmplr-lib-rt`), or install a PoCL >= 7 for this "
                "CPU (Debian/Ubuntu `pocl-opencl-icd`, conda-forge `pocl`) and set CLRECON_DEVICE=portable")
    return ("install an OpenCL driver for this CPU -- PoCL from your distribution (`pocl-opencl-icd`) or conda-forge "
            "(`pocl`) -- and set CLRECON_DEVICE to its platform name (`python -m clrecon devices` lists them)")


class NoWorkingDriver(OpenCLUnavailable):
    """No OpenCL CPU driver on this machine builds and runs the probe kernel."""


@dataclasses.dataclass
class Choice:
    """The device the runtime uses and how it came to be chosen (results.json's ``driver``)."""

    device: object
    chosen_by: str
    verdicts: list[Verdict]
    registration: dict
    #: the run's timed choice among the working drivers (:mod:`clrecon.pipeline.driver_choice`), if any
    timing: dict | None = None

    def as_dict(self) -> dict:
        d = self.device
        p = d.platform
        return {"platform": p.name, "platform_version": p.version, "driver_version": d.driver_version,
                "device": d.name, "device_type": "cpu" if _is_cpu(d) else "other",
                "compute_units": int(d.max_compute_units), "chosen_by": self.chosen_by,
                "probes": [{"platform": v.platform, "driver_version": v.driver_version, "ok": v.ok,
                            "reason": v.reason, "cached": v.cached} for v in self.verdicts],
                "cpu": cpu_line(), **({"timing": self.timing} if self.timing else {})}


def choose_cpu_device(platforms, cache_dir: Path | None = None) -> Choice:
    """The first CPU device in the default order that passes the probe; :class:`NoWorkingDriver` if none."""
    reg = register_wheel_drivers()
    verdicts = []
    for _rank, dev, idx in candidates(platforms):
        v = probe_device(dev, idx, cache_dir)
        verdicts.append(v)
        if v.ok:
            drv = driver_of(dev.platform.name)
            if drv is not None and drv.key == preferred():
                how = _preference_reasons.get(drv.key, "the run's choice, made by timing in a parent process")
            else:
                how = "the first CPU driver in clrecon's order that passes the probe"
            return Choice(dev, how, verdicts, reg)
    raise NoWorkingDriver(no_driver_message(verdicts, missing_drivers(platforms)))


def no_driver_message(verdicts: list[Verdict], missing: list[CpuDriver]) -> str:
    """One line: the CPU, each driver tried with its reason, each known driver absent, the remedy."""
    tried = [v.line() for v in verdicts]
    tried += [f"{d.key} ({d.package}): not installed" for d in missing]
    return (f"no OpenCL CPU driver can run clrecon's kernels on this CPU, {cpu_line()}: "
            f"{'; '.join(tried) or 'no OpenCL CPU platform is installed'}. Remedy: {remedy()}; "
            f"a GPU or another platform: CLRECON_DEVICE=NAME (`python -m clrecon devices` lists them)")


def list_devices(probe_again: bool = False) -> dict:
    """Every OpenCL platform and device, each with the probe's verdict, and which one runs by default.

    Returns ``{"cpu": str, "registration": dict, "clrecon_device": str, "devices": [row, ...]}``; a row
    has platform, platform_version, driver_version, device, type, compute_units, global_mem_gib,
    probe_ok, probe_reason, probe_cached and default (the device a run without ``CLRECON_DEVICE``
    takes). Every device is probed, GPUs and simulators included (``CLRECON_DEVICE`` can name them)."""
    import pyopencl as cl

    reg = register_wheel_drivers()
    try:
        platforms = cl.get_platforms()
    except cl.Error:
        platforms = []
    rows = []
    for p in platforms:
        for i, d in enumerate(p.get_devices()):
            v = probe_device(d, i, use_cache=not probe_again)
            kind = {cl.device_type.CPU: "cpu", cl.device_type.GPU: "gpu",
                    cl.device_type.ACCELERATOR: "accelerator"}.get(d.type, "other")  # Oclgrind: ALL
            rows.append({"platform": p.name, "platform_version": p.version, "driver_version": d.driver_version,
                         "device": d.name, "index": i, "type": kind, "compute_units": int(d.max_compute_units),
                         "global_mem_gib": round(d.global_mem_size / 2**30, 1), "probe_ok": v.ok,
                         "probe_reason": v.reason, "probe_cached": v.cached, "default": False,
                         "_key": (p.name, i)})
    by_key = {r["_key"]: r for r in rows}
    for _rank, d, i in candidates(platforms):
        row = by_key[(d.platform.name, i)]
        if row["probe_ok"]:
            row["default"] = True
            break
    for r in rows:
        del r["_key"]
    return {"cpu": cpu_line(), "registration": reg, "clrecon_device": os.environ.get("CLRECON_DEVICE", ""),
            "devices": rows}


def format_devices(listing: dict) -> str:
    """The listing of :func:`list_devices` as a table for a terminal."""
    out = [f"CPU: {listing['cpu']}"]
    if listing["registration"].get("note"):
        out.append(f"ICD: {listing['registration']['note']}")
    out.append("")
    for r in listing["devices"]:
        mark = "*" if r["default"] else " "
        verdict = "builds and runs the probe" if r["probe_ok"] else f"NO: {r['probe_reason']}"
        out.append(f"{mark} {r['platform']} {r['driver_version']} / {r['device']} [{r['type']}, "
                   f"{r['compute_units']} units, {r['global_mem_gib']} GiB]: {verdict}")
    if not listing["devices"]:
        out.append("  no OpenCL platform is installed")
    out.append("")
    if listing["clrecon_device"]:
        out.append(f"CLRECON_DEVICE={listing['clrecon_device']} is set: runs use that platform.")
    elif any(r["default"] for r in listing["devices"]):
        out.append("* = the first CPU driver in clrecon's order that passes the probe: the default where it is the "
                   "only one; where several pass, each run takes the one its timings predict fastest for its own "
                   "kernel work (below). CLRECON_DEVICE=NAME[:INDEX] picks another.")
    else:
        out.append(f"No CPU driver passes the probe. Remedy: {remedy()}")
    return "\n".join(out)
