"""``clrecon sweep STUDY.toml``: a grid of runs, one run directory per point, and a summary.

A study file (format in docs/distributed.md)::

    name = "kappa"                  # default: the file's stem
    scene = "tiny"                  # base scene: built-in name or TOML path (relative to the study file)
    methods = ["local_linear", "nearest"]   # optional, as `run --methods`; also pitches, slices, targets
    report = false                  # optional: write each point's report.md (default true)

    [set]                           # fixed overrides of every point, SECTION.KEY = value
    "noise.enabled" = false

    [grid]                          # swept: every combination, in this order
    "recon.kappa" = [0.05, 0.1, 0.2]
    "signals.rhythm" = ["periodic", "af"]
    # scene = ["tiny", "demo"]      # the base scene may be swept too

Every point is a normal run directory ``<out>/<point name>/`` (``results.json``,
``volumes.h5``, ...) with ``point.json`` (its parameters). Resumable: a point whose
``results.json`` exists for the same parameters is kept, an unfinished one resumes from its
unit files (:mod:`clrecon.core.units`). Points run one after another, each on the Dask
cluster if a client is given (its units spread over the workers; points sharing a scan share
its projection store). The summary (:mod:`clrecon.outputs.sweep_summary`): ``summary.csv``,
``summary.md`` and, per swept parameter, a figure of MAE and motion metrics against it.
"""

from __future__ import annotations

import itertools
import json
import re
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from clrecon.config import overrides as scene_overrides
from clrecon.core import jsonio
from clrecon.core.errors import ClreconError
from clrecon.core.units import write_json_atomic
from clrecon.outputs import sweep_summary
from clrecon.pipeline.run import run as run_pipeline

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    import tomli as tomllib

_TOP_KEYS = ("name", "scene", "out", "methods", "pitches", "slices", "targets", "report", "set", "grid")


@dataclass(frozen=True)
class Study:
    """A parsed study file: the base run, fixed overrides and the swept grid (``{key: [values]}``)."""

    name: str
    scene: str
    source: str = ""
    out: str | None = None
    methods: tuple | None = None
    pitches: tuple | None = None
    slices: tuple | None = None
    targets: dict | None = None
    report: bool = True
    fixed: dict = field(default_factory=dict)
    grid: dict = field(default_factory=dict)

    def points(self) -> list[dict]:
        """Every combination of the grid, ``{key: value}``, the first key varying slowest."""
        keys = list(self.grid)
        return [dict(zip(keys, combo, strict=True)) for combo in itertools.product(*self.grid.values())]


def _bad(where: str, what: str) -> ClreconError:
    return ClreconError(f"{where}: {what}")


def load_study(path: str | Path) -> Study:
    """Parse and check a study file; :class:`ClreconError` naming the file, key and what is allowed."""
    p = Path(path)
    try:
        raw = tomllib.loads(p.read_text())
    except OSError as e:
        raise _bad(str(p), f"cannot read the study file ({e.strerror or e})") from None
    except tomllib.TOMLDecodeError as e:
        raise _bad(str(p), f"not valid TOML ({e})") from None
    unknown = sorted(set(raw) - set(_TOP_KEYS))
    if unknown:
        raise _bad(f"{p}: {unknown[0]}", f"unknown study key; allowed: {', '.join(_TOP_KEYS)}")
    grid = raw.get("grid", {})
    if not isinstance(grid, dict) or not grid:
        raise _bad(f"{p}: [grid]", "expected a table of swept keys, each a non-empty list, "
                                   "e.g. \"recon.kappa\" = [0.05, 0.1]")
    for key, values in grid.items():
        if not isinstance(values, list) or not values:
            raise _bad(f"{p}: [grid] {key}", f"expected a non-empty list of values, got {values!r}")
        if key != "scene" and "." not in key:
            raise _bad(f"{p}: [grid] {key}", "expected SECTION.KEY (e.g. recon.kappa, signals.rhythm) or scene")
    fixed = raw.get("set", {})
    if not isinstance(fixed, dict):
        raise _bad(f"{p}: [set]", "expected a table of SECTION.KEY = value overrides")
    scene = raw.get("scene")
    if scene is None and "scene" not in grid:
        raise _bad(str(p), "no scene: give scene = \"NAME\" (or sweep scene in [grid])")

    def tup(key):
        v = raw.get(key)
        if v is None:
            return None
        if not isinstance(v, list):
            raise _bad(f"{p}: {key}", f"expected a list, got {v!r}")
        return tuple(v)

    slices = tup("slices")
    if slices is not None and len(slices) != 2:
        raise _bad(f"{p}: slices", f"expected [start, stop] slice indices, got {list(slices)}")
    study = Study(name=str(raw.get("name") or p.stem), scene=str(scene or ""), source=str(p), out=raw.get("out"),
                  methods=tup("methods"), pitches=tup("pitches"), slices=slices, targets=raw.get("targets"),
                  report=bool(raw.get("report", True)), fixed=dict(fixed), grid=dict(grid))
    for point in study.points():  # every point's scene must load: fail before the first run
        point_scene(study, point)
    return study


def _scene_ref(study: Study, name: str) -> str:
    """A scene name, or a TOML path resolved against the study file's folder."""
    if name.endswith(".toml") and study.source and not Path(name).is_absolute():
        return str(Path(study.source).parent / name)
    return name


def point_scene(study: Study, point: dict):
    """The scene of one grid point: the base (or swept) scene with the fixed and swept overrides."""
    overrides = {**study.fixed, **{k: v for k, v in point.items() if k != "scene"}}
    name = _scene_ref(study, str(point.get("scene", study.scene)))
    where = f"{study.source or study.name}: point {point_name(point)}"
    try:
        return scene_overrides.load_scene(name, **overrides)
    except ClreconError as e:  # SceneError included: the key, the value and what is allowed
        raise ClreconError(f"{where}: {e}") from None


def _fmt(value: Any) -> str:
    if isinstance(value, list):
        return "+".join(_fmt(v) for v in value)
    if isinstance(value, bool):
        return "true" if value else "false"
    return f"{value:g}" if isinstance(value, float) else str(value)


def point_name(point: dict) -> str:
    """The point's folder name, from its values: ``kappa=0.05_rhythm=af`` (stable, so a rerun finds it)."""
    shorts = [k.rsplit(".", 1)[-1] for k in point]
    parts = []
    for (k, v), short in zip(point.items(), shorts, strict=True):
        label = short if shorts.count(short) == 1 else k
        parts.append(f"{label}={_fmt(v)}")
    return re.sub(r"[^A-Za-z0-9._=+-]", "-", "_".join(parts)) or "point"


def run_study(study: Study, out: str | Path | None = None, cache_dir: str | Path | None = None, client=None,
              progress: bool = True, log: Callable[..., Any] = print) -> dict:
    """Run every point not yet finished, then write the summary; returns :func:`sweep_summary.write` 's dict.

    ``client``: a ``distributed.Client``: each point's units run on its workers.
    """
    root = Path(out or study.out or Path("runs") / study.name)
    root.mkdir(parents=True, exist_ok=True)
    targets = study.targets or {}
    rows, kept, ran = [], 0, 0
    points = study.points()
    for n, point in enumerate(points, 1):
        name = point_name(point)
        pdir = root / name
        record = {"study": study.name, "point": point, "fixed": study.fixed, "scene": point.get("scene", study.scene),
                  "methods": study.methods, "pitches": study.pitches, "slices": study.slices, "targets": targets}
        record = json.loads(json.dumps(record))
        results = _finished(pdir, record)
        if results is None:
            log(f"[{n}/{len(points)}] {name}")
            pdir.mkdir(parents=True, exist_ok=True)
            write_json_atomic(pdir / "point.json", record)
            results = run_pipeline(point_scene(study, point), pdir, methods=study.methods,
                                   cardiac=targets.get("cardiac"), resp=targets.get("resp"),
                                   slice_range=study.slices, pitches=study.pitches, cache_dir=cache_dir,
                                   progress=progress, report=study.report, log=lambda *a, **k: None, client=client)
            ran += 1
        else:
            log(f"[{n}/{len(points)}] {name}: kept (finished earlier)")
            kept += 1
        rows.append((name, point, results))
    summary = sweep_summary.write(root, study.grid, rows)
    summary.update(points_run=ran, points_kept=kept)
    return summary


def _finished(pdir: Path, record: dict) -> dict | None:
    """The point's results if it finished for exactly these parameters, else None (run or resume it)."""
    try:
        if json.loads((pdir / "point.json").read_text()) != record:
            return None
        return jsonio.loads((pdir / "results.json").read_text())
    except (OSError, ValueError):
        return None
