"""The one reader of a run directory (``results.json`` + ``volumes.h5``).

Used by the figures (:mod:`clrecon.outputs.figures`), the viewer (:mod:`clrecon.viewer.app`), the
export (:mod:`clrecon.outputs.export`) and the notebook API (:func:`clrecon.open_run`)::

    with RunDirectory("runs/tiny") as run:
        run.axes["cardiac_phase"]           # target cardiac phases, (n_c,)
        run.sources                         # [Source("groundtruth", ...), ..., Source("recon/p0.100/...")]
        src = run.resolve(method="nearest")  # defaults: best method, smallest pitch, noisy
        vol = run.read(src, (0, 1))         # (nz, ny, nx) float32 HU of one target

Opening reads only the file's header (format version); axes, ``results.json``, the source
list and the scene are read when first asked for, and volumes one target (or one plane) at
a time. Errors are one-line :class:`~clrecon.core.errors.ClreconError` s (``StoreError``
for missing or unreadable files).

The on-disk layout is :mod:`clrecon.outputs.volumes`; a volume dataset has the axes named
in its ``dims`` attribute (a scene without cardiac motion or breathing has no cardiac or
respiratory axis on disk); :meth:`RunDirectory.read` restores them as length-1 axes.

The module-level functions (:func:`sources`, :func:`describe_sources`,
:func:`resolve_source`, :func:`run_axes`) take an open ``h5py.File`` or a
:class:`RunDirectory`; they are what :class:`RunDirectory` uses, kept for older callers.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeAlias

import numpy as np

from clrecon.config.scene import Scene, scene_from_dict
from clrecon.core import jsonio
from clrecon.core.errors import ClreconError, StoreError
from clrecon.outputs.volumes import (
    DIMS,
    FORMAT_VERSION,
    READABLE_VERSIONS,
    RECON,
    list_recons,
    open_volumes,
    read_part,
    read_volume,
    recon_path,
)
from clrecon.reconstruction.interpolation import by_rank

#: Preferred default source, best first (5DCT methods, then baselines).
METHOD_PREFERENCE = by_rank()  # the interpolation methods by their registered ``rank``
VARIANT_PREFERENCE = ("noisy", "noise-free")
REFERENCE_VOLUMES = ("groundtruth", "phantom")
AXIS_NAMES = ("cardiac_phase", "resp_amplitude", "z_mm", "y_mm", "x_mm")

if TYPE_CHECKING:
    import h5py

#: An open ``volumes.h5`` or a :class:`RunDirectory` (the module-level functions take either).
VolumeFile: TypeAlias = "h5py.File | RunDirectory"
#: A pitch as a number (0.02), a number string or a key (``"p0.020"``).
PitchLike: TypeAlias = float | str | None


@dataclass(frozen=True)
class Source:
    """One 5D volume of a run: ``dataset`` is its HDF5 path; ``method`` its name or a reference.

    ``pitch_key``/``variant`` are None for the ground truth and the phantom.
    """

    dataset: str
    method: str
    pitch_key: str | None = None
    variant: str | None = None

    @property
    def label(self) -> str:
        """Human label, e.g. ``"local_linear p0.020 noisy"`` or ``"groundtruth"``."""
        if self.pitch_key is None:
            return self.method
        return f"{self.method} {self.pitch_key} {self.variant}"

    @property
    def pitch(self) -> float | None:
        """The pitch as a number (None for the references)."""
        return None if self.pitch_key is None else float(self.pitch_key[1:])

    @property
    def name(self) -> str:
        """Identifier-like name, e.g. ``"local_linear_p0.020_noisy"`` or ``"groundtruth"``."""
        if self.pitch_key is None:
            return self.method
        return f"{self.method}_{self.pitch_key}_{self.variant}"


# ----------------------------------------------------------------------------------------
# functions over an open volume file (or a RunDirectory)
def _h5(f: VolumeFile) -> h5py.File:
    return f.h5 if isinstance(f, RunDirectory) else f


def open_volume_store(run_dir: str | Path) -> h5py.File:
    """Open a run directory's ``volumes.h5`` (h5py.File) with one-line errors for wrong paths."""
    p = Path(run_dir)
    if not p.exists():
        raise StoreError(f"{p}: no such run directory")
    if p.is_file() and p.name != "volumes.h5":
        raise StoreError(f"{p}: expected a run directory (with volumes.h5), got a file")
    h5 = p / "volumes.h5" if p.is_dir() else p
    if h5.exists():  # check the format here too: open_volumes' own message reads a closed file
        import h5py

        try:
            with h5py.File(h5, "r") as f:
                version = f.attrs.get("format_version")
                version = version.item() if hasattr(version, "item") else version
        except OSError as e:
            raise StoreError(f"{h5}: not a readable HDF5 file ({e})") from None
        if version not in READABLE_VERSIONS:
            raise StoreError(f"{h5}: volume format {version!r} is not {FORMAT_VERSION} (an older or foreign run "
                             f"directory); re-run `clrecon run` with this version")
    return open_volumes(p)


def normalise_pitch(pitch: PitchLike) -> str | None:
    """``0.02``, ``"0.02"`` or ``"p0.020"`` -> ``"p0.020"`` (None stays None)."""
    if pitch is None:
        return None
    text = str(pitch).strip()
    try:
        return f"p{float(text.lstrip('pP')):.3f}"
    except ValueError:
        raise ClreconError(f"--pitch {pitch!r}: expected a number such as 0.02 or a key such as p0.020") from None


def sources(f: VolumeFile) -> list[Source]:
    """Every volume of the run: ground truth, phantom, then each (pitch, variant, method)."""
    f = _h5(f)
    out = [Source(name, name) for name in REFERENCE_VOLUMES if name in f]
    out += [Source(recon_path(p, v, m), m, p, v) for p, v, m in list_recons(f)]
    return out


def describe_sources(f: VolumeFile) -> str:
    """One line naming what a run holds, e.g. ``groundtruth, phantom; p0.020/noisy: local_linear, nearest``."""
    f = _h5(f)
    refs = [n for n in REFERENCE_VOLUMES if n in f]
    groups: dict = {}
    for p, v, m in list_recons(f):
        groups.setdefault(f"{p}/{v}", []).append(m)
    parts = [", ".join(refs) if refs else "no reference volumes"]
    parts += [f"{k}: {', '.join(ms)}" for k, ms in groups.items()]
    return "; ".join(parts) if groups else parts[0] + "; no reconstructions"


def resolve_source(f: VolumeFile, method: str | None = None, pitch: PitchLike = None,
                   variant: str | None = None) -> Source:
    """The source asked for, with defaults filled in; a ClreconError naming what exists otherwise.

    ``method``: a reconstruction method, ``groundtruth`` or ``phantom``; default the best
    method present (:data:`METHOD_PREFERENCE`), else the ground truth. ``pitch``: number or
    key, default the smallest pitch present. ``variant``: default ``noisy`` if present.
    """
    f = _h5(f)
    if method in REFERENCE_VOLUMES:
        if method not in f:
            raise ClreconError(f"this run has no {method} volume; it has {describe_sources(f)}")
        return Source(method, method)
    recons = list_recons(f)
    pk = normalise_pitch(pitch)
    cands = [r for r in recons if (pk is None or r[0] == pk) and (variant is None or r[1] == variant)
             and (method is None or r[2] == method)]
    if not cands:
        if method is None and pk is None and variant is None:
            for name in REFERENCE_VOLUMES:
                if name in f:
                    return Source(name, name)
        want = ", ".join(f"{k} {v}" for k, v in (("method", method), ("pitch", pk), ("variant", variant)) if v)
        raise ClreconError(f"no volume with {want or 'any name'} in this run; it has {describe_sources(f)}")

    def rank(r):
        p, v, m = r
        mi = METHOD_PREFERENCE.index(m) if m in METHOD_PREFERENCE else len(METHOD_PREFERENCE)
        vi = VARIANT_PREFERENCE.index(v) if v in VARIANT_PREFERENCE else len(VARIANT_PREFERENCE)
        return (mi, float(p[1:]), vi, m)

    p, v, m = min(cands, key=rank)
    return Source(recon_path(p, v, m), m, p, v)


def run_axes(f: VolumeFile) -> dict[str, np.ndarray]:
    """``{cardiac_phase, resp_amplitude, z_mm, y_mm, x_mm}`` as float64 arrays."""
    f = _h5(f)
    return {k: np.asarray(f[f"axes/{k}"][()], np.float64) for k in AXIS_NAMES}


# ----------------------------------------------------------------------------------------
class RunDirectory:
    """A run directory opened read-only: ``results.json``, ``volumes.h5``, axes and sources.

    ``path``: the run directory (or its ``volumes.h5``). ``results``: the results dictionary
    if the caller already has it (a run writing its report), else ``results.json`` is read
    when first needed. Use as a context manager or call :meth:`close`.

    Attributes and lazy properties: ``dir`` (the directory), ``h5`` (the open ``h5py.File``),
    ``results``, ``scene``, ``axes`` (``cardiac_phase``, ``resp_amplitude``, ``z_mm``,
    ``y_mm``, ``x_mm``; float64, LPS mm), ``sources`` (:class:`Source` list).
    """

    def __init__(self, path: str | Path, results: dict[str, Any] | None = None) -> None:
        p = Path(path)
        self.h5 = open_volume_store(p)
        self.dir = p.parent if p.is_file() else p
        self._results = results
        self._axes: dict | None = None
        self._sources: list[Source] | None = None
        self._scene = None

    @property
    def f(self) -> h5py.File:
        """The open ``h5py.File`` (alias of :attr:`h5`)."""
        return self.h5

    # -- life cycle ------------------------------------------------------------------------
    def close(self) -> None:
        self.h5.close()

    def __enter__(self) -> RunDirectory:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"RunDirectory({str(self.dir)!r})"

    # -- results.json and the scene ------------------------------------------------------
    @property
    def results_path(self) -> Path:
        return self.dir / "results.json"

    @property
    def has_results(self) -> bool:
        return self._results is not None or self.results_path.exists()

    @property
    def results(self) -> dict[str, Any]:
        """The ``results.json`` dictionary (StoreError if missing or unreadable)."""
        if self._results is None:
            p = self.results_path
            if not p.exists():
                raise StoreError(f"{p}: no results.json in this run directory (was `clrecon run` finished?)")
            try:
                res = jsonio.loads(p.read_text())  # null_values back to the floats they were
            except (OSError, ValueError) as e:
                raise StoreError(f"{p}: not a readable results.json ({e})") from None
            if not isinstance(res, dict):
                raise StoreError(f"{p}: not a results.json (expected a JSON object)")
            self._results = res
        return self._results

    @property
    def scene(self) -> Scene:
        """The run's :class:`~clrecon.config.scene.Scene` (from ``results["scene"]``)."""
        if self._scene is None:

            self._scene = scene_from_dict(self.results["scene"])
        return self._scene

    # -- axes ----------------------------------------------------------------------------
    @property
    def axes(self) -> dict[str, np.ndarray]:
        if self._axes is None:
            self._axes = run_axes(self.h5)
        return self._axes

    @property
    def cardiac(self) -> np.ndarray:
        return self.axes["cardiac_phase"]

    @property
    def resp(self) -> np.ndarray:
        return self.axes["resp_amplitude"]

    @property
    def z(self) -> np.ndarray:
        return self.axes["z_mm"]

    @property
    def y(self) -> np.ndarray:
        return self.axes["y_mm"]

    @property
    def x(self) -> np.ndarray:
        return self.axes["x_mm"]

    @property
    def shape(self) -> tuple[int, int, int, int, int]:
        """Full 5-axis shape ``(n_c, n_r, nz, ny, nx)`` of every volume."""
        return tuple(int(self.axes[k].size) for k in AXIS_NAMES)

    def spacing(self) -> tuple[float, float, float]:
        """(dx, dy, dz) in mm (1 along an axis of length 1)."""
        out = []
        for k in ("x_mm", "y_mm", "z_mm"):
            v = self.axes[k]
            out.append(float(v[1] - v[0]) if v.size > 1 else 1.0)
        return tuple(out)

    def origin(self) -> tuple[float, float, float]:
        """Centre (x, y, z) of the first voxel, mm."""
        return (float(self.axes["x_mm"][0]), float(self.axes["y_mm"][0]), float(self.axes["z_mm"][0]))

    # -- what the run holds --------------------------------------------------------------
    def has(self, name: str) -> bool:
        return name in self.h5

    @property
    def has_groundtruth(self) -> bool:
        return "groundtruth" in self.h5

    @property
    def sources(self) -> list[Source]:
        if self._sources is None:
            self._sources = sources(self.h5)
        return self._sources

    def describe(self) -> str:
        return describe_sources(self.h5)

    def resolve(self, method: str | None = None, pitch: PitchLike = None, variant: str | None = None) -> Source:
        """:func:`resolve_source` on this run."""
        return resolve_source(self.h5, method, pitch, variant)

    @staticmethod
    def recon_name(pk: str, variant: str, method: str) -> str:
        """:func:`clrecon.outputs.volumes.recon_path` (kept for callers of the run directory)."""
        return recon_path(pk, variant, method)

    def pitches(self) -> list[str]:
        """Pitch keys present, smallest pitch first."""
        return sorted(self.h5[RECON].keys(), key=lambda k: float(k[1:])) if RECON in self.h5 else []

    def variants(self, pk: str) -> list[str]:
        return list(self.h5[recon_path(pk)].keys())

    def methods(self, pk: str, variant: str) -> list[str]:
        return list(self.h5[recon_path(pk, variant)].keys())

    def preferred_variant(self, pk: str) -> str:
        vs = self.variants(pk)
        return "noisy" if "noisy" in vs else vs[0]

    def dims(self, source: Source | str) -> tuple[str, ...]:
        """The axes a volume has on disk (a subset of ``cardiac, resp, z, y, x``)."""
        return tuple(str(d) for d in self.h5[_dataset(source)].attrs["dims"])

    # -- volumes -------------------------------------------------------------------------
    def read(self, source: Source | str, index: tuple[int, int] | None = None) -> np.ndarray:
        """A volume (:class:`Source` or dataset name) as ``(n_c, n_r, nz, ny, nx)``, or one target.

        ``index``: (cardiac_index, resp_index) -> ``(nz, ny, nx)`` (only that target is read).
        """
        return read_volume(self.h5, _dataset(source), index)

    def read_target(self, source: Source | str, ci: int, ri: int) -> np.ndarray:
        """``(nz, ny, nx)`` float32 HU of target (ci, ri)."""
        return np.asarray(self.read(source, (ci, ri)), np.float32)

    def read_part(self, source: Source | str, **index: int | slice) -> np.ndarray:
        """Part of a volume by axis name, e.g. ``read_part(src, cardiac=0, resp=1, y=12)`` -> (nz, nx).

        Axes not named are read whole; an index for an axis the volume lacks on disk (length 1)
        is ignored.
        """
        unknown = set(index) - set(DIMS)
        if unknown:
            raise ClreconError(f"read_part: unknown axis {sorted(unknown)[0]!r}; axes: {', '.join(DIMS)}")
        return read_part(self.h5, _dataset(source), index, full=False)


def _dataset(source: Source | str) -> str:
    return source.dataset if isinstance(source, Source) else str(source)
