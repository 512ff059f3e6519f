"""``python -m clrecon bench``: throughput figures, each beside a reference measured in the same run.

The machine may be shared (here: 2 CPU cores and other engineers' jobs), so an absolute
figure alone means little; every section therefore times a reference on the same data in
the same process, and the ratio is the number to trust. Times are medians of ``repeats``
runs after one untimed warm-up (kernel builds, PoCL specialisation, first-touch buffers),
unless a section says otherwise. The 1-minute load average is recorded before each section.

Each section is a module of :mod:`clrecon.bench` with ``run(quick, repeats, log) -> dict`` and
``report_lines(result) -> list[str]`` (its docstring says what it times and against what); this
module runs the sections of :data:`REGISTRY` that ``--only`` picks, in the registry's order, and
prints their report lines in the same order. Adding a section: one module, one registry line.

Sections (``--only`` picks some):

``backprojection`` (:mod:`clrecon.bench.backprojection`)
    G voxel-updates/s of the batched backprojector against the one-sinogram reference kernel
    and ASTRA's CPU fan-beam backprojector (optional). Goal: >= 4 G updates/s.
``projector`` (:mod:`clrecon.bench.projector`)
    The culled projector on ``paper-p002``: rays/s, ray-object pairs/s, projections/s, the whole
    simulation's projected time (goal < 10 minutes) against the same kernel without culling.
``voxel-projector`` (:mod:`clrecon.bench.voxel_projector`)
    The voxel projector (the path of ``[phantom] kind = "voxel"``) against its float64 NumPy
    reference and the analytic projector on the same rays.
``iterative`` (only when named; :mod:`clrecon.bench.iterative`)
    The iterative operators: the voxel projector A beside its matched transpose A^T (rays/s,
    voxel-updates/s, the dot-product test of the timed data), the warp W_u beside W_u^T.
``interpolation`` (:mod:`clrecon.bench.interpolation`)
    Output rows/s of the neighbour search, weights and weight-applying kernel, per method, on
    the demo scan, against the float64 NumPy reference.
``end-to-end`` (:mod:`clrecon.bench.end_to_end`)
    :func:`clrecon.pipeline.run.run` on ``demo`` with a fresh projection cache: total and per-stage seconds.
``memory`` (:mod:`clrecon.bench.memory`)
    Peak resident memory of one slab of ``paper-p002`` in a child process, with a byte model
    that extrapolates to the full job (goal < 8 GiB).
``scaling`` (:mod:`clrecon.bench.scaling`)
    Plan and reconstruct seconds of demo-sized scenes against slices, targets and projections.
``paper-projector``, ``noise``, ``paper-fbp``, ``groundtruth`` (:mod:`clrecon.bench.paper`)
    The paper-p002 job's stages at the job's own sizes, each with the time it projects for the
    whole job: simulation projections/s, noise cells/s, FBP images/s, ground-truth and
    phantom-truth slice-targets/s, each against its reference.
``truth_free`` (only when named; :mod:`clrecon.bench.truth_free`)
    The cost of ``recon.truth_free`` against the reconstruction it accompanies (demo, 4 middle slices).
``tradeoff`` (only when named, about 50 minutes; :mod:`clrecon.bench.tradeoff`)
    Per method, the knobs that trade seconds for error swept on demo at pitch 0.02: MAE against
    seconds, each method's Pareto front; ``tradeoff.json`` and ``tradeoff.png`` in a kept
    temporary folder (the report says where).
``drivers`` (only when named, or ``--drivers``; :mod:`clrecon.bench.drivers`)
    Every CPU driver that passes the probe side by side (projector, SSRB, interpolation,
    backprojection, noise, the demo cold).
``measured`` (:mod:`clrecon.bench.measured`)
    DICOM-CT-PD import views/s (header pass + pixel import into a fresh store) against reading
    the same files' bytes; goal >= 200 views/s.
``mc`` (only when named; :mod:`clrecon.bench.mc`, :mod:`clrecon.bench.mc_kernel`)
    The cost of the ``mc`` method against the paper methods' reconstruction of the same ``demo``
    run at pitch 0.10 (``--quick``: 4 slices), its MAE ratio, one registration round with the
    scene's registrations (in the run's process by default; one after the other against the process
    pool where a step uses scikit-image's Lucas-Kanade), and the motion-compensated backprojection
    kernel's G updates/s against the static backprojector's on the same geometry (goal >= 1/4).

The A/B benchmarks of the code's own levers and options, and the studies (levers, backprojector
options, detectors, Dask scaling, truth-free trust), live in a checkout's ``benchmarks/`` folder,
outside the wheel (:data:`MOVED`; ``python -m benchmarks.levers`` and so on).

``--json FILE`` writes every number and the machine (CPU model, cores, load averages,
OpenCL device). ``--quick`` shrinks every section (about a minute on an idle 2-core machine).
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from clrecon.bench import (
    backprojection,
    drivers,
    end_to_end,
    interpolation,
    iterative,
    mc,
    measured,
    memory,
    paper,
    projector,
    scaling,
    tradeoff,
    truth_free,
    voxel_projector,
)
from clrecon.core import atomic, machine_speed
from clrecon.core.errors import ClreconError
from clrecon.core.runtime import get_runtime
from clrecon.core.versions import __version__


@dataclass(frozen=True)
class Section:
    """One section of the bench: its ``--only`` name (also the key of its result), how to run it
    and how to report it."""

    name: str
    #: ``run(quick=..., repeats=..., log=...) -> dict``: the section's numbers.
    run: Callable[..., dict]
    #: ``report_lines(result) -> list[str]``: its lines of the report (called only for a non-empty result).
    report_lines: Callable[[dict], list[str]]
    #: In the default set; False: run only when ``--only`` names it (long, or needs extras).
    default: bool = True


#: Every section, in the order they run and appear in the report.
REGISTRY = (
    Section("backprojection", backprojection.run, backprojection.report_lines),
    Section("projector", projector.run, projector.report_lines),
    Section("voxel-projector", voxel_projector.run, voxel_projector.report_lines),
    Section("iterative", iterative.run, iterative.report_lines, default=False),
    Section("interpolation", interpolation.run, interpolation.report_lines),
    Section("end-to-end", end_to_end.run, end_to_end.report_lines),
    Section("memory", memory.run, memory.report_lines),
    Section("scaling", scaling.run, scaling.report_lines),
    *(Section(name, paper.section_run(name), paper.REPORT_LINES[name]) for name in paper.SECTIONS),
    Section("truth_free", truth_free.run, truth_free.report_lines, default=False),
    Section("tradeoff", tradeoff.run, tradeoff.report_lines, default=False),
    Section("drivers", drivers.run, drivers.report_lines, default=False),
    Section("measured", measured.run, measured.report_lines),
    Section("mc", mc.run, mc.report_lines, default=False),
)
#: Sections run when ``--only`` is not given.
SECTIONS = tuple(s.name for s in REGISTRY if s.default)
#: Sections run only when ``--only`` names them (long).
EXTRA_SECTIONS = tuple(s.name for s in REGISTRY if not s.default)
#: Former sections, now A/B benchmarks of a checkout's ``benchmarks/`` folder (not in the wheel).
MOVED = {"levers": "benchmarks.levers", "backprojector": "benchmarks.backprojector",
         "detectors": "benchmarks.detectors", "distributed": "benchmarks.dask_scaling",
         "truth_free_trust": "benchmarks.truth_free_trust"}


# ---------------------------------------------------------------------------------------
# helpers
def machine() -> dict:
    """CPU model, core count, load averages, memory, OpenCL device and library versions."""
    cpu = platform.processor() or "unknown"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    mem_gib = None
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemTotal"):
                mem_gib = round(int(line.split()[1]) / 2 ** 20, 1)
    except OSError:
        pass
    import pyopencl


    return {"cpu_model": cpu, "logical_cores": os.cpu_count(), "memory_gib": mem_gib,
            "load_average": [round(x, 2) for x in os.getloadavg()], "device": get_runtime().description,
            "driver": get_runtime().driver,
            "platform": platform.platform(), "python": platform.python_version(), "numpy": np.__version__,
            "pyopencl": pyopencl.VERSION_TEXT, "clrecon": __version__}


def format_report(res: dict) -> str:
    """Readable tables of a :func:`run_bench` result: the machine, then each section present."""
    out = []
    m = res["machine"]
    out.append(f"machine: {m['cpu_model']}, {m['logical_cores']} logical cores, {m['memory_gib']} GiB; "
               f"load average {m['load_average']}; device {m['device']}")
    if m.get("speed"):
        out.append(f"machine over the bench: {machine_speed.describe(m['speed'])}")
    for section in REGISTRY:
        if res.get(section.name):
            out.extend(section.report_lines(res[section.name]))
    return "\n".join(out)


def run_bench(quick: bool = False, only=None, repeats: int | None = None, log=print) -> dict:
    """Run the selected sections; returns every number (see the module docstring)."""
    only = tuple(only or SECTIONS)
    moved = [s for s in only if s in MOVED]
    if moved:
        raise ClreconError(f"--only {moved[0]}: an A/B benchmark of the code itself, now in a checkout's benchmarks/ "
                           f"folder (not installed with the package): python -m {MOVED[moved[0]]} from the checkout")
    bad = [s for s in only if s not in SECTIONS + EXTRA_SECTIONS]
    if bad:
        raise ClreconError(f"--only {bad[0]!r}: sections are {', '.join(SECTIONS + EXTRA_SECTIONS)}")
    repeats = repeats or (1 if quick else 3)
    res = {"quick": quick, "repeats": repeats, "machine": machine()}
    machine0 = machine_speed.start()
    t_all = time.perf_counter()
    for section in REGISTRY:
        if section.name in only:
            log(f"bench: {section.name} ...", file=sys.stderr)
            t0 = time.perf_counter()
            res[section.name] = section.run(quick=quick, repeats=repeats, log=log)
            res[section.name]["section_s"] = time.perf_counter() - t0
    res["bench_s"] = time.perf_counter() - t_all
    res["machine"]["load_average_after"] = [round(x, 2) for x in os.getloadavg()]
    res["machine"]["speed"] = machine0.finish()
    return res


def _json_default(o):
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(type(o))


def write_json(res: dict, path) -> None:
    atomic.write_json(path, res, indent=2)  # strict JSON, whole or not at all


def main(argv=None) -> int:  # pragma: no cover - the CLI's bench command is the entry point
    p = argparse.ArgumentParser(prog="python -m clrecon.bench.suite", description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true")
    p.add_argument("--json", metavar="FILE")
    p.add_argument("--only", help="comma list from " + ",".join(SECTIONS + EXTRA_SECTIONS))
    a = p.parse_args(argv)
    res = run_bench(a.quick, a.only.split(",") if a.only else None)
    print(format_report(res))
    if a.json:
        write_json(res, a.json)
    return 0


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
