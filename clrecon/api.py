"""The Python API for notebooks: ``clrecon.load_scene``, ``clrecon.run``, ``clrecon.open_run``.

See ``docs/api.md`` for a worked example. In short::

    import clrecon

    scene = clrecon.load_scene("tiny", recon={"nz": 2}, noise__enabled=False)
    result = clrecon.run(scene, out="runs/tiny", methods=["nearest"], targets=([0.4], [0.25]))
    ds = clrecon.open_run(result.path)          # lazy xarray.Dataset, dims (cardiac, resp, z, y, x)
    err = ds["nearest_p0.100_noise-free"] - ds["groundtruth"]

Errors a user can act on are :class:`clrecon.core.errors.ClreconError` (``SceneError`` for
scene values, ``StoreError`` for run directories) with a one-line message.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import xarray

from clrecon.config import overrides as _overrides
from clrecon.config.scene import Scene
from clrecon.core.errors import ClreconError
from clrecon.outputs.dataset import open_dataset
from clrecon.outputs.stacked import open_stacked
from clrecon.pipeline.run import run as run_pipeline

__all__ = ["RunResult", "load_scene", "open_run", "run"]

PathLike = str | Path
#: ``(cardiac_list, resp_list)`` (either may be None: the scene's) or ``{"cardiac": [...], "resp": [...]}``.
TargetsLike = Sequence[Any] | Mapping[str, Any] | None
#: ``(start, stop)`` slice indices or a ``slice`` (step 1).
SlicesLike = Sequence[int] | slice | None


# ----------------------------------------------------------------------------------------
# scenes
def load_scene(name_or_path: PathLike | Scene, **overrides: Any) -> Scene:
    """A scene by built-in name or TOML path, with overrides: :func:`clrecon.config.overrides.load_scene`.

    ``recon={"nz": 4}``, ``recon__nz=4``, ``**{"recon.nz": 4}``, ``name=...``; validated as in
    a scene file (:class:`~clrecon.core.errors.SceneError`); a :class:`Scene` is accepted too.
    """
    return _overrides.load_scene(name_or_path, **overrides)


# ----------------------------------------------------------------------------------------
# runs
@dataclass(frozen=True)
class RunResult:
    """What :func:`run` returns: the run directory ``path`` and its ``results`` (``results.json``)."""

    path: Path
    results: dict

    def open(self, stacked: bool = False) -> xarray.Dataset | xarray.DataArray:
        """:func:`open_run` of this run."""
        return open_run(self.path, stacked=stacked)

    def __repr__(self) -> str:
        return f"RunResult(path={str(self.path)!r}, total_seconds={self.results.get('total_seconds')})"


def _floats(values, what: str) -> list[float] | None:
    if values is None:
        return None
    if isinstance(values, (int, float)) and not isinstance(values, bool):
        return [float(values)]
    try:
        return [float(v) for v in values]
    except (TypeError, ValueError):
        raise ClreconError(f"targets: {what} {values!r}: expected a list of numbers") from None


def _targets(targets: TargetsLike) -> tuple[list[float] | None, list[float] | None]:
    if targets is None:
        return None, None
    if isinstance(targets, Mapping):
        unknown = set(targets) - {"cardiac", "resp"}
        if unknown:
            raise ClreconError(f"targets: unknown key {sorted(unknown)[0]!r}; use 'cardiac' and 'resp'")
        return _floats(targets.get("cardiac"), "cardiac"), _floats(targets.get("resp"), "resp")
    if isinstance(targets, (str, bytes)) or len(targets) != 2:
        raise ClreconError(f"targets {targets!r}: expected (cardiac_list, resp_list) or "
                           f"{{'cardiac': [...], 'resp': [...]}}")
    return _floats(targets[0], "cardiac"), _floats(targets[1], "resp")


def _slices(slices: SlicesLike, nz: int) -> tuple[int, int] | None:
    if slices is None:
        return None
    if isinstance(slices, slice):
        if slices.step not in (None, 1):
            raise ClreconError(f"slices {slices!r}: only step 1 is supported")
        start, stop, _ = slices.indices(nz)
        return start, stop
    try:
        start, stop = slices
        return int(start), int(stop)
    except (TypeError, ValueError):
        raise ClreconError(f"slices {slices!r}: expected (start, stop) slice indices or a slice") from None


def run(scene: Scene | PathLike, out: PathLike | None = None, *, methods: Sequence[str] | str | None = None,
        targets: TargetsLike = None, slices: SlicesLike = None, pitches: Sequence[float] | float | None = None,
        progress: bool = False, cache: PathLike | None = None, report: bool = True,
        log: Callable[[str], Any] | None = None, force: bool = False, client: Any = None,
        executor: str | None = None) -> RunResult:
    """Simulate (or reuse) -> reconstruct -> evaluate -> report, like ``clrecon run``.

    ``scene``: a :class:`Scene` or a built-in name / TOML path. ``out``: the run directory
    (default ``runs/<scene name>``). ``methods``: list (or comma string) of methods, default
    the scene's. ``targets``: ``(cardiac_list, resp_list)`` or ``{"cardiac": ..., "resp": ...}``,
    either part None for the scene's. ``slices``: ``(start, stop)`` indices or ``slice(start,
    stop)`` into the scene's ``recon.nz`` slices. ``pitches``: a number or list, default the
    scene's. ``progress``: tqdm bars. ``cache``: the projection store folder (default
    ``$CLRECON_CACHE`` or ``~/.cache/clrecon``). ``report``: write ``report.md`` and figures.
    ``log``: called with each status line (default: silent). ``force``: run even if the
    pre-flight check (modelled peak memory and disk need against the machine) says it will not fit.
    ``client``: a ``distributed.Client`` (e.g. ``Client(LocalCluster(n_workers=2, threads_per_worker=1))``
    or ``clrecon.pipeline.distributed.connect(workers=2)``): the units are computed on its
    workers, with the same results bit for bit (docs/distributed.md). ``executor``: ``"serial"``,
    ``"local"`` (default) or ``"dask"`` (docs/data-flow.md "Executors").

    Returns a :class:`RunResult` (``.path``, ``.results``, ``.open()``). Wraps
    :func:`clrecon.pipeline.run.run`.
    """

    if not isinstance(scene, Scene):
        scene = load_scene(scene)
    if isinstance(methods, str):
        methods = [m.strip() for m in methods.split(",") if m.strip()]
    if isinstance(pitches, (int, float)) and not isinstance(pitches, bool):
        pitches = [float(pitches)]
    cardiac, resp = _targets(targets)
    slice_range = _slices(slices, scene.recon.nz)
    path = Path(out) if out is not None else Path("runs") / scene.name
    results = run_pipeline(scene, path, methods=list(methods) if methods else None, cardiac=cardiac, resp=resp,
                           slice_range=slice_range, pitches=list(pitches) if pitches else None,
                           cache_dir=None if cache is None else str(cache), progress=progress, report=report,
                           log=log if log is not None else (lambda *a, **k: None), force=force,
                           client=client, executor=executor)
    return RunResult(path=path, results=results)


# ----------------------------------------------------------------------------------------
# reading
def open_run(path: PathLike | RunResult, stacked: bool = False) -> xarray.Dataset | xarray.DataArray:
    """A run directory as a lazily loaded :class:`xarray.Dataset` (nothing but axes read on open).

    ``stacked=True``: instead one lazy :class:`xarray.DataArray` of every reconstruction, on
    ``method, pitch, variant, cardiac, resp, z, y, x`` (``da.sel(method="local_linear",
    variant="noisy")``), NaN where the run lacks a combination; r4dct and helical broadcast
    along the axes they do not vary on; ground truth and phantom stay in the Dataset. Layout:
    :mod:`clrecon.outputs.stacked`.

    Dimensions ``cardiac``, ``resp``, ``z``, ``y``, ``x`` (coordinates: cardiac phase,
    respiratory amplitude, voxel centres in mm, LPS); one float32 HU variable per
    reconstruction, named ``<method>_<pitch key>_<variant>`` (``local_linear_p0.020_noisy``;
    attrs ``method``, ``pitch``, ``pitch_key``, ``variant``, ``units``, pooled ``mae_hu_small``
    / ``mae_hu_large``), plus ``groundtruth`` and ``phantom``. ``ds.attrs["results"]`` and
    ``ds.attrs["metrics"]`` are ``results.json`` (and its metrics) as JSON strings. A scene
    without cardiac motion or breathing has that dimension with length 1
    (``ds.attrs["has_cardiac"]`` / ``["has_resp"]`` = 0). Close with ``ds.close()`` or ``with``.
    Layout details: :mod:`clrecon.outputs.dataset`.
    """
    if isinstance(path, RunResult):
        path = path.path
    return open_stacked(path) if stacked else open_dataset(path)
