"""Same-run A/B of ``python -m clrecon run`` wall time: this tree against another source tree.

    python -m benchmarks.ab_run --ref /path/to/other/tree [--pairs 3] [--cases tiny,demo,paper-slab]

Each case runs alternately from the reference tree (``PYTHONPATH=<ref>``) and from this tree,
``--pairs`` times, into fresh run folders; both share one projection cache, warmed by a first run of
each case, and the truth cache is emptied before every run (the truths are computed each time; the
simulation is reused). Reports per case the median wall seconds of each side, their ratio (this /
reference: below 1 is faster), the runs' own CPU core-seconds (from their ``results.json``; much
less sensitive to other jobs on a shared machine), the 1-minute load before each run, the CPU model,
and whether every ``volumes.h5`` dataset is bit-identical between the two sides' last runs. Cases:
``tiny``, ``demo`` (the default scene, whole) and ``paper-slab`` (``paper-p010``, slices 54:56, all
50 targets, at the paper's 512^2 / 900 x 64 sizes).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import h5py

HERE = Path(__file__).resolve().parent.parent
CASES = {"tiny": ["--scene", "tiny"], "demo": ["--scene", "demo"],
         "paper-slab": ["--scene", "paper-p010", "--slices", "54:56"]}


def _cpu() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return "unknown"


def _load() -> float:
    return round(os.getloadavg()[0], 2)


def _own_core_s(out: Path) -> float | None:
    """The run's own CPU core-seconds (``results.json`` ``machine_speed``): less sensitive to other
    jobs than wall time."""
    return _speed(out, "own_core_s")


def _speed(out: Path, key: str) -> float | None:
    try:
        return json.loads((out / "results.json").read_text())["machine_speed"][key]
    except (OSError, KeyError, ValueError):
        return None


def _run(tree: Path, args: list, out: Path, cache: Path, extra: list) -> float:
    shutil.rmtree(cache / "truth", ignore_errors=True)
    env = dict(os.environ, PYTHONPATH=str(tree), CLRECON_NO_PROGRESS="1")
    t0 = time.perf_counter()
    done = subprocess.run([sys.executable, "-m", "clrecon", "run", *args, "--out", str(out), "--cache", str(cache),
                           "--no-progress", *extra], env=env, capture_output=True, text=True, cwd=str(tree))
    wall = time.perf_counter() - t0
    if done.returncode != 0:
        raise SystemExit(f"{tree}: {' '.join(args)} failed: {done.stderr.strip().splitlines()[-1:]}")
    return wall


def _datasets(path: Path) -> dict:
    out = {}
    with h5py.File(path / "volumes.h5", "r") as f:
        f.visititems(lambda n, o: out.__setitem__(n, o[()].tobytes()) if isinstance(o, h5py.Dataset) else None)
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--ref", required=True, help="the other source tree (a checkout with clrecon/ and kernels/)")
    p.add_argument("--this", default=str(HERE), help="this side's source tree (default: the one holding this script)")
    p.add_argument("--pairs", type=int, default=3)
    p.add_argument("--cases", default="demo,paper-slab")
    p.add_argument("--work", help="folder for the runs and the shared cache (default: a temporary one)")
    p.add_argument("--json", help="write the numbers here too")
    a = p.parse_args(argv)
    ref, this = Path(a.ref).resolve(), Path(a.this).resolve()
    work = Path(a.work) if a.work else Path(tempfile.mkdtemp(prefix="clrecon-ab-"))
    cache = work / "cache"
    res = {"cpu": _cpu(), "cores": os.cpu_count(), "ref": str(ref), "this": str(this), "cases": {}}
    for case in a.cases.split(","):
        args = CASES[case]
        _run(this, args, work / f"{case}-warm", cache, [])  # fills the shared projection cache
        walls: dict = {"ref": [], "this": []}
        cpu: dict = {"ref": [], "this": []}
        others: dict = {"ref": [], "this": []}
        loads: list = []
        for i in range(a.pairs):
            for side, tree in (("ref", ref), ("this", this)) if i % 2 == 0 else (("this", this), ("ref", ref)):
                loads.append(_load())
                walls[side].append(_run(tree, args, work / f"{case}-{side}", cache, []))
                cpu[side].append(_own_core_s(work / f"{case}-{side}"))
                others[side].append(_speed(work / f"{case}-{side}", "others_core_s"))
                print(f"{case} {side} {walls[side][-1]:.1f} s, own {cpu[side][-1]} core-s, other jobs "
                      f"{others[side][-1]} core-s (load {loads[-1]})", flush=True)
        same = _datasets(work / f"{case}-ref") == _datasets(work / f"{case}-this")
        med = {k: statistics.median(v) for k, v in walls.items()}
        mcpu = {k: statistics.median(v) if all(x is not None for x in v) else None for k, v in cpu.items()}
        res["cases"][case] = {"walls": walls, "median": med, "ratio_this_over_ref": med["this"] / med["ref"],
                              "own_core_s": cpu, "median_own_core_s": mcpu, "others_core_s": others,
                              "load_1min": loads,
                              "volumes_bit_identical": same}
        cpu_ratio = mcpu["this"] / mcpu["ref"] if mcpu["this"] and mcpu["ref"] else float("nan")
        print(f"{case}: this {med['this']:.1f} s, reference {med['ref']:.1f} s, ratio {med['this'] / med['ref']:.3f}; "
              f"own core-s ratio {cpu_ratio:.3f}; load {min(loads)}-{max(loads)}, volumes bit-identical: {same}",
              flush=True)
    if a.json:
        Path(a.json).write_text(json.dumps(res, indent=2))
    if not a.work:
        shutil.rmtree(work, ignore_errors=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
