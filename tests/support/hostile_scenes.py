"""Hostile scene values: every key of every scene section x :data:`VALUES`, on the ``tiny`` scene.

Used twice:

- ``tests/config/test_fuzz.py`` validates the whole grid (fast, no kernels) and asserts: no exception
  but a one-line :class:`~clrecon.core.errors.SceneError` naming the key and the value; a refusal
  for every case not in :data:`ACCEPTED`; acceptance for every case in it. A few accepted edge
  cases also run end to end there.
- ``python tests/support/hostile_scenes.py --out FILE.jsonl`` measures the grid end to end (each accepted
  scene run in its own process, with a time and memory limit): refusals, runs that finish, and
  what a user would see otherwise (a traceback, non-finite voxels, non-strict JSON). It imports
  only clrecon's public entry points, so it measures any version of clrecon on the path
  (``PYTHONPATH=/some/checkout``): the before/after figures of docs/results/hostile-grid.md come from it.

:data:`ACCEPTED` is the declaration of which hostile values are legitimate settings in this scene
(a seed of 10^12, a table position of -1 mm, ``truth_free = true``); every other case is absurd or
invalid in the tiny scene and must be refused where it enters.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import time
from dataclasses import fields
from pathlib import Path

BASE_SCENE = "tiny"
#: (label, value) of the hostile values tried in every key; ints where the value is integral so
#: integer keys see them as integers (a float for an int key is refused by its type alone).
VALUES = (("nan", math.nan), ("inf", math.inf), ("-inf", -math.inf), ("0", 0), ("-1", -1), ("1e-300", 1e-300),
          ("1e-6", 1e-6), ("1e6", 10 ** 6), ("1e12", 10 ** 12), ("2^63", 2 ** 63), ("true", True), ('"x"', "x"),
          ("[]", []))

_SMALL = {"0", "1e-300", "1e-6"}           # harmless where 0 is a legal value (a fraction, a std, a drift)
_POSITION = {"0", "-1", "1e-300", "1e-6"}  # positions and offsets: any small number is legitimate
#: key -> labels of the hostile values that are legitimate settings of that key in the tiny scene.
ACCEPTED: dict[str, set[str]] = {
    "scanner.central_col": {"-1"},           # -1: the middle (any other value: the flat detector is centred)
    "scanner.central_row": {"-1"},
    "scanner.ffs_angle_rad": {"0"},          # non-zero: only with a flying focal spot
    "scanner.ffs_radial_mm": {"0"},
    "scanner.ffs_z_mm": {"0"},
    "scan.n_projections": {"0"},             # 0: the length from coverage_mm
    "scan.z_centre_mm": _POSITION,
    "scan.start_angle_deg": _POSITION,
    "signals.seed": {"0", "1e6", "1e12"},
    "signals.resp_period_cv": _SMALL,
    "signals.resp_depth_cv": _SMALL,
    "signals.resp_drift": _SMALL,
    "signals.breath_hold": {"true"},
    "signals.breath_hold_amplitude": _SMALL,
    "signals.rr_cv": _SMALL,
    "signals.ectopic_rate": _SMALL,
    "signals.frame_time_s": {"0"},           # > 0: a frame of at least 1 ms
    "signals.trace_offset_s": _POSITION,
    "signals.ecg_offset_s": _POSITION,
    "phantom.cardiac_motion": {"true"},
    "phantom.respiratory_motion": {"true"},
    "phantom.metal_insert": {"true"},
    "phantom.diaphragm_si_mm": _SMALL,
    "phantom.chest_ap_mm": _SMALL,
    "phantom.heart_si_fraction": _SMALL,
    "noise.enabled": {"true"},
    "noise.i0_photons": {"1e6", "1e12"},
    "noise.electronic_sigma": _SMALL,
    "noise.seed": {"0", "1e6", "1e12"},
    "noise.also_noise_free": {"true"},
    "recon.cardiac_phases": _SMALL,
    "recon.local_linear_extrapolate": {"true"},
    "recon.max_turns": {"0"},
    "recon.candidate_window_mm": {"0"},
    "recon.truth_free": {"true"},
    "recon.small_fov_mm": _POSITION,         # x_min of the heart box
}


def grid_keys() -> list[tuple[str, str]]:
    """(section, key) of every key of every section (``[phantom]``: the analytic phantom's)."""
    from clrecon.config.scene import SECTIONS

    return [(sec, f.name) for sec, cls in SECTIONS.items() for f in fields(cls)]


def base_dict() -> dict:
    from clrecon.config.scene import load_scene

    return load_scene(BASE_SCENE).to_dict()


def case_dict(base: dict, sec: str, key: str, value) -> dict:
    """The base scene with ``sec.key`` = ``value`` (in a list key: its first element, or ``[]``)."""
    d = json.loads(json.dumps(base))
    old = d[sec][key]
    if isinstance(old, list) and not isinstance(value, list):
        value = [value] + old[1:]
    d[sec][key] = value
    return d


def edge_cases() -> list[tuple[str, str, str, object]]:
    """(section, key, label, value): every key with a declared range (``value_ranges``) at both ends.

    Each is either refused by a check across keys (an end of one key's range can clash with the
    tiny scene's other values) or accepted, and an accepted one must run to finite outputs."""
    from clrecon.config.scene import SECTIONS
    from clrecon.core.config import value_ranges

    out = []
    for sec, cls in SECTIONS.items():
        for key, (lo, hi) in value_ranges(cls).items():
            out += [(sec, key, "min", lo), (sec, key, "max", hi)]
    return out


def expected_accepted(sec: str, key: str, label: str) -> bool:
    return label in ACCEPTED.get(f"{sec}.{key}", ())


def validate(d: dict):
    """``("refused", message)``, ``("accepted", scene)`` or ``("traceback", "Type: message")``."""
    from clrecon.config.scene import scene_from_dict
    from clrecon.core.errors import SceneError

    try:
        return "accepted", scene_from_dict(d)
    except SceneError as e:
        return "refused", str(e)
    except Exception as e:  # noqa: BLE001 - what the grid measures
        return "traceback", f"{type(e).__name__}: {str(e)[:200]}"


# ---------------------------------------------------------------------------------------
# end to end (one accepted case per process)
def strict_json(text: str):
    """``json.loads`` refusing NaN/Infinity tokens (what a strict parser does)."""
    def bad(token):
        raise ValueError(f"non-strict JSON token {token}")
    return json.loads(text, parse_constant=bad)


def non_finite_voxels(vol_path: Path) -> int:
    import h5py
    import numpy as np

    n = 0
    with h5py.File(vol_path, "r") as f:
        def visit(name, obj):
            nonlocal n
            if isinstance(obj, h5py.Dataset) and obj.dtype.kind == "f":
                n += int((~np.isfinite(obj[()])).sum())
        f.visititems(visit)
    return n


def run_one(sec: str, key: str, value, out: Path, cache: Path, report: bool = True,
            extra: dict | None = None) -> dict:
    """Run the case end to end as ``clrecon run`` would; what a user sees. ``extra``: ``{section: {key:
    value}}`` set too (e.g. no electronic noise with one photon per cell)."""
    import contextlib
    import io

    from clrecon.config.scene import scene_from_dict
    from clrecon.pipeline.run import run

    d = case_dict(base_dict(), sec, key, value)
    for s2, kv in (extra or {}).items():
        d[s2].update(kv)
    err = io.StringIO()
    rec: dict = {}
    try:
        scene = scene_from_dict(d)
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
            run(scene, out / "run", cache_dir=cache, progress=False, log=lambda *a, **k: None, report=report)
        rec["outcome"] = "ran"
    except Exception as e:  # noqa: BLE001 - classified as the CLI would show it
        from clrecon.core.errors import ClreconError

        one_line = isinstance(e, (ClreconError, OSError, MemoryError)) and "\n" not in str(e)
        rec["outcome"] = "refused_at_run" if isinstance(e, ClreconError) and one_line else (
            "failed_one_line" if one_line else "traceback")
        rec["message"] = f"{type(e).__name__}: {str(e)[:300]}"
        return rec
    res = out / "run" / "results.json"
    try:
        strict_json(res.read_text())
        rec["strict_json"] = True
    except ValueError as e:
        rec["strict_json"] = False
        rec["json_error"] = str(e)[:200]
        rec["nan_tokens"] = res.read_text().count("NaN") + res.read_text().count("Infinity")
    rec["non_finite_voxels"] = non_finite_voxels(out / "run" / "volumes.h5")
    return rec


def _child(args) -> None:
    import resource

    limit = int(args.memory_gib * 2 ** 30)
    resource.setrlimit(resource.RLIMIT_AS, (limit, limit))
    out = Path(args.workdir)
    out.mkdir(parents=True, exist_ok=True)
    rec = run_one(args.sec, args.key, json.loads(args.value_json), out, Path(args.cache))
    print("RESULT " + json.dumps(rec))


def measure(out_file: Path, workdir: Path, cache: Path, timeout_s: float, memory_gib: float,
            only: set | None = None, grids: tuple = ("hostile",)) -> dict:
    """The whole grid: validation of every case, and every accepted case run end to end
    (``grids``: ``hostile`` (:data:`VALUES` in every key) and/or ``edge`` (:func:`edge_cases`))."""
    import shutil

    base = base_dict()
    totals: dict = {}
    cases = [("hostile", sec, key, label, value) for sec, key in grid_keys() for label, value in VALUES
             if "hostile" in grids]
    if "edge" in grids:
        cases += [("edge", sec, key, label, value) for sec, key, label, value in edge_cases()]
    with open(out_file, "w") as fh:
        for grid, sec, key, label, value in cases:
            name = f"{sec}.{key}"
            if only and name not in only:
                continue
            t0 = time.perf_counter()
            status, detail = validate(case_dict(base, sec, key, value))
            rec = {"grid": grid, "key": name, "value": label,
                   "absurd": grid == "hostile" and not expected_accepted(sec, key, label), "validation": status}
            if status == "refused":
                rec["message"] = detail
                rec["one_line"] = "\n" not in detail
            elif status == "traceback":
                rec["message"] = detail
            else:
                wd = workdir / f"{name}={label}".replace("/", "_")
                shutil.rmtree(wd, ignore_errors=True)
                cmd = [sys.executable, __file__, "--child", "--sec", sec, "--key", key, "--value-json",
                       json.dumps(value), "--workdir", str(wd), "--cache", str(cache), "--memory-gib", str(memory_gib)]
                try:
                    p = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout_s,
                                       env=dict(os.environ))
                    line = [x for x in p.stdout.splitlines() if x.startswith("RESULT ")]
                    if line:
                        rec.update(json.loads(line[-1][7:]))
                    else:
                        tail = (p.stderr.strip().splitlines() or [""])[-1]
                        rec.update(outcome="traceback", message=f"rc {p.returncode}: {tail[:300]}")
                except subprocess.TimeoutExpired:
                    rec.update(outcome="timeout", message=f"no result in {timeout_s:.0f} s")
                shutil.rmtree(wd, ignore_errors=True)
            rec["seconds"] = round(time.perf_counter() - t0, 2)
            fh.write(json.dumps(rec) + "\n")
            fh.flush()
            k = f"{grid}:{classify(rec)}"
            totals[k] = totals.get(k, 0) + 1
    return totals


def classify(rec: dict) -> str:
    """One word per case, as the issue counts them."""
    if rec["validation"] == "traceback":
        return "traceback"
    if rec["validation"] == "refused":
        return "refused" if rec.get("one_line", True) else "refused_multiline"
    out = rec.get("outcome")
    if out == "ran":
        if rec.get("non_finite_voxels") or not rec.get("strict_json", True):
            return "non_finite_output"
        return "absurd_accepted" if rec["absurd"] else "accepted"
    return {"refused_at_run": "refused", "failed_one_line": "failed_one_line"}.get(out, out)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="hostile-grid.jsonl")
    ap.add_argument("--workdir", default="/tmp/clrecon-hostile")
    ap.add_argument("--cache", default="/tmp/clrecon-hostile-cache")
    ap.add_argument("--timeout", type=float, default=300.0)
    ap.add_argument("--memory-gib", type=float, default=6.0)
    ap.add_argument("--only", help="comma list of section.key")
    ap.add_argument("--grids", default="hostile", help="hostile (VALUES in every key), edge (every ranged key at "
                    "both ends of its range) or hostile,edge")
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--sec", help=argparse.SUPPRESS)
    ap.add_argument("--key", help=argparse.SUPPRESS)
    ap.add_argument("--value-json", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        _child(args)
        return
    only = set(args.only.split(",")) if args.only else None
    totals = measure(Path(args.out), Path(args.workdir), Path(args.cache), args.timeout, args.memory_gib, only,
                     grids=tuple(args.grids.split(",")))
    print(json.dumps(totals, sort_keys=True))


if __name__ == "__main__":
    main()
