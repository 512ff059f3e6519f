"""How fast the machine was while a run or a bench ran: a fixed probe, and who used the CPUs.

Why: on the shared 2-core machine the same code took 60.8 s for the demo one morning and
80.9–101.6 s that afternoon, with stages whose code had not changed 25–55 % slower, and the
load average did not show it (a run that keeps both cores busy reads load 2 by itself).
Cross-run figures are only comparable with a measure of the machine beside them, so a run
records two:

- **probe seconds**: a fixed single-threaded NumPy workload (sort, FFT, exp/log of seeded
  float64 data), the fastest of five tries after one untimed one, once before the run and
  once after it. The fastest, because a try that a context switch hit says nothing about
  the machine; what slows all five (a busier host, a lower clock) is what the probe is for.
  Only differences well beyond ~15 % mean a different machine (the spread measured idle:
  docs/results/code-history.md "The machine-speed probe"). Single-threaded on
  purpose: it measures the speed of one core as the run would get it, not how many cores are
  free. A run whose probe took 1.3 × another's ran on a machine about that much slower.
- **CPU time of the machine during the run** from ``/proc/stat`` (Linux): the whole machine's
  busy core-seconds, the part of them that was not this process or its children (other
  tenants, other jobs), and the hypervisor's *steal* (core-seconds the VM was runnable but
  not running). ``None`` where ``/proc/stat`` is absent (macOS, Windows).

:func:`start` before the work, :meth:`Sample.finish` after it; the dict goes into
``results.json`` as ``machine_speed`` and into the bench's output.
"""

from __future__ import annotations

import os
import resource
import time
from dataclasses import dataclass

import numpy as np

#: Size of the probe's data (float64 values) and how often it is timed (the fastest counts).
PROBE_VALUES = 1 << 18
PROBE_REPEATS = 5

_STAT_FIELDS = ("user", "nice", "system", "idle", "iowait", "irq", "softirq", "steal")
#: Clock ticks per second of /proc's CPU times.
_TICK = os.sysconf("SC_CLK_TCK") if hasattr(os, "sysconf") else 100


def probe_seconds(repeats: int = PROBE_REPEATS) -> float:
    """Fastest wall seconds of ``repeats`` tries of one fixed single-threaded workload (same
    data every call), after one untimed try."""
    x = np.random.default_rng(20261203).standard_normal(PROBE_VALUES)
    times = []
    for _ in range(repeats + 1):
        t0 = time.perf_counter()
        s = np.sort(x)
        f = np.fft.rfft(s)
        y = np.log1p(np.exp(-np.abs(x[: PROBE_VALUES // 2]))) + np.abs(f[: PROBE_VALUES // 2])
        float(y.sum())
        times.append(time.perf_counter() - t0)
    return float(min(times[1:]))


def machine_cpu_seconds() -> dict | None:
    """Cumulative core-seconds of the whole machine by kind (``/proc/stat``), or None."""
    try:
        with open("/proc/stat") as f:
            parts = f.readline().split()
    except OSError:
        return None
    if not parts or parts[0] != "cpu":
        return None
    vals = [int(v) / _TICK for v in parts[1:1 + len(_STAT_FIELDS)]]
    vals += [0.0] * (len(_STAT_FIELDS) - len(vals))
    return dict(zip(_STAT_FIELDS, vals, strict=True))


def _live_children_cpu_seconds() -> float:
    """CPU seconds (user + system) of this process's children still running (``/proc``; 0 elsewhere).

    ``RUSAGE_CHILDREN`` counts a child only once it has been waited for; the run's helper and
    metrics processes are still alive when the machine's record is taken."""
    me, total = str(os.getpid()), 0.0
    try:
        entries = os.listdir("/proc")
    except OSError:
        return 0.0
    for pid in entries:
        if not pid.isdigit():
            continue
        try:
            with open(f"/proc/{pid}/stat") as f:
                fields = f.read().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if fields[1] == me:  # fields after the name: state, ppid, ..., utime (12), stime (13)
            total += (int(fields[11]) + int(fields[12])) / _TICK
    return total


def own_cpu_seconds() -> float:
    """CPU seconds (user + system) of this process and its children so far (waited-for and live)."""
    s, c = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return s.ru_utime + s.ru_stime + c.ru_utime + c.ru_stime + _live_children_cpu_seconds()


@dataclass
class Sample:
    """The machine at the start of a piece of work (see :func:`start`)."""

    wall0: float
    own0: float
    stat0: dict | None
    probe_start_s: float | None

    def finish(self, probe: bool = True) -> dict:
        """The machine over the work: probe seconds before and after, and its CPU time.

        Returns a JSON-ready dict: ``probe_seconds`` {start, end} (s; end is None with
        ``probe=False``), ``wall_s``, ``cores``, and where ``/proc/stat`` exists
        ``machine_busy_core_s`` (all busy core-seconds), ``others_core_s`` (busy minus this
        process and its children: other jobs on the machine), ``steal_core_s`` and their
        fractions of ``wall_s x cores``.
        """
        own = own_cpu_seconds() - self.own0
        stat1 = machine_cpu_seconds()
        wall = time.perf_counter() - self.wall0
        cores = os.cpu_count() or 1
        start_s = None if self.probe_start_s is None else round(self.probe_start_s, 4)
        out = {"probe_seconds": {"start": start_s,
                                 "end": round(probe_seconds(), 4) if probe else None},
               "wall_s": round(wall, 2), "cores": cores, "own_core_s": round(own, 1)}
        if self.stat0 is not None and stat1 is not None:
            d = {k: stat1[k] - self.stat0[k] for k in _STAT_FIELDS}
            busy = d["user"] + d["nice"] + d["system"] + d["irq"] + d["softirq"]
            capacity = max(wall * cores, 1e-9)
            out.update({
                "machine_busy_core_s": round(busy, 1),
                "others_core_s": round(max(busy - own, 0.0), 1),
                "steal_core_s": round(d["steal"], 1),
                "others_fraction": round(max(busy - own, 0.0) / capacity, 3),
                "steal_fraction": round(d["steal"] / capacity, 3),
            })
        return out


def start(probe: bool = True) -> Sample:
    """Record the machine before a piece of work (runs the probe first unless ``probe=False``)."""
    p = probe_seconds() if probe else None
    return Sample(wall0=time.perf_counter(), own0=own_cpu_seconds(), stat0=machine_cpu_seconds(), probe_start_s=p)


def describe(ms: dict) -> str:
    """One line for logs and the report: probe seconds and the other jobs' and steal share."""
    ps = ms.get("probe_seconds", {})
    start, end = ps.get("start"), ps.get("end")
    txt = (f"probe {start * 1e3:.1f} ms" if start is not None else "no probe") + (
        f" -> {end * 1e3:.1f} ms" if end is not None else "")
    if "others_fraction" in ms:
        txt += (f"; other jobs {100 * ms['others_fraction']:.0f} % and steal {100 * ms['steal_fraction']:.0f} %"
                f" of {ms['cores']} cores")
    return txt
