"""The run directory's volume store, ``volumes.h5`` (written by ``run``, read by report/viewer/export).

Layout (HDF5)::

    /axes/cardiac_phase  (n_c,)   target cardiac phases        (absent axis: length 1)
    /axes/resp_amplitude (n_r,)   target respiratory amplitudes
    /axes/z_mm (nz,) /axes/y_mm (ny,) /axes/x_mm (nx,)   voxel centres, LPS, mm
    /groundtruth                  ground-truth CT (exact in-plane projections + same FBP)
    /phantom                      voxelised analytic phantom
    /recon/<pitch>/<variant>/<method>     e.g. /recon/p0.020/noise-free/local_linear

Every volume dataset is HU, float32 or (``recon.volume_dtype = "float16"``, the paper-scale
scenes) IEEE half precision, with attribute ``dims``: the axis names of its shape, a subset of
``("cardiac", "resp", "z", "y", "x")`` — a scene without cardiac motion has no cardiac axis
on disk (its 5D volume is 4D), one without breathing no respiratory axis. Attribute
``broadcast`` (possibly empty) names the axes a volume has at length 1 because it stands for
every target along them: the cardiac-blind ``r4dct`` (one volume per amplitude) and the
phase-blind ``helical`` (one volume) are stored once, not once per target.
:func:`read_volume` (and every reader of the run directory) always returns float32 on the
full 5-axis grid (size-1 and broadcast axes restored).

Half precision: 11 significant bits, so a value is stored within 2^-11 of itself relative
(<= 0.25 HU for |HU| < 1024, <= 0.5 HU for |HU| < 2048, <= 1 HU up to 4096); the metrics are
computed from the stored volumes, so they describe exactly what a user reads back. It halves
the volumes of a paper-scale run (docs/reproduction.md gives the measured effect on Table 2).
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import h5py
import numpy as np

from clrecon.core import faults, units
from clrecon.core.errors import StoreError

DIMS = ("cardiac", "resp", "z", "y", "x")
FORMAT_VERSION = 1
#: Allowed on-disk dtypes of the volumes (``recon.volume_dtype``).
VOLUME_DTYPES = ("float32", "float16")


def pitch_key(pitch: float) -> str:
    return f"p{pitch:.3f}"


class VolumeWriter:
    """Writes ``volumes.h5`` crash-safely: unit files first, one HDF5 file assembled at the end.

    Every finished block (a slab of one reconstruction, one target of a truth) is written as
    its own atomic, checksummed unit file in ``volumes.h5.units/`` (:mod:`clrecon.core.units`);
    nothing is written into HDF5 while computing, so a SIGKILL at any instant can only lose
    the block being written. :meth:`assemble` builds ``volumes.h5.partial`` from the units
    (``f`` is then open on it for reading); :meth:`close` fsyncs it, renames it to
    ``volumes.h5`` and removes the units. A later run with the same ``run_key`` (hash of
    scene and request, kept in ``volumes.h5.units/run.json``) keeps the intact units and
    skips what they hold; a damaged unit is dropped with a warning and redone; a leftover
    ``.partial`` (an assembly cut short) is discarded and rebuilt; any other key starts afresh.
    """

    def __init__(self, path: Path, axes: dict, keep_cardiac: bool, keep_resp: bool, run_key: str = "",
                 dtype: str = "float32"):
        if dtype not in VOLUME_DTYPES:
            raise ValueError(f"volume dtype {dtype!r}: allowed {', '.join(VOLUME_DTYPES)}")
        self.dtype = np.dtype(dtype)
        self.path = Path(path)
        self.partial = self.path.with_name(self.path.name + ".partial")
        self.units_dir = self.path.with_name(self.path.name + ".units")
        self.keep = (keep_cardiac, keep_resp)
        self.axes = {k: np.asarray(v, np.float64) for k, v in axes.items()}
        self.resumed = False
        self.f = None
        self.units_written = {"recon": 0, "truth": 0}
        self._specs: dict[str, tuple[tuple, int]] = {}  # name -> (on-disk shape, done size)
        self._broadcast: dict[str, tuple[str, ...]] = {}  # name -> axes stored at length 1 (standing for all)
        self._done: dict[str, np.ndarray] = {}
        self._units: dict[str, list[tuple[Path, dict]]] = {}
        self.partial.unlink(missing_ok=True)  # only ever an assembly in progress: rebuilt from the units
        meta_path = self.units_dir / "run.json"
        try:
            meta = json.loads(meta_path.read_text())
        except (OSError, ValueError):
            meta = None
        if (meta and meta.get("run_key") == run_key and meta.get("format_version") == FORMAT_VERSION):
            self.resumed = True
            for p, m in units.scan_units(self.units_dir):
                self._units.setdefault(m["name"], []).append((p, m))
        else:
            shutil.rmtree(self.units_dir, ignore_errors=True)
            self.units_dir.mkdir(parents=True)
            units.write_json_atomic(meta_path, {"run_key": run_key, "format_version": FORMAT_VERSION})

    def _dims(self):
        return tuple(d for d, keep in zip(DIMS, self.keep + (True, True, True), strict=True) if keep)

    def _squeeze(self, vol: np.ndarray) -> np.ndarray:
        drop = tuple(i for i, keep in enumerate(self.keep) if not keep)
        return vol.reshape(tuple(s for i, s in enumerate(vol.shape) if i not in drop))

    def create(self, name: str, full_shape: tuple, done_size: int, broadcast: tuple = ()) -> None:
        """Declare dataset ``name`` with a ``done`` mask of ``done_size`` (slices or flattened targets).

        ``broadcast``: target axes (``"cardiac"``, ``"resp"``) along which the volume is the same
        for every target, stored at length 1 (blocks written to it have length 1 there).
        """
        if name in self._specs:
            return
        bad = set(broadcast) - {"cardiac", "resp"}
        if bad:
            raise ValueError(f"broadcast axes {sorted(bad)}: only 'cardiac' and 'resp' can be broadcast")
        full_shape = tuple(1 if d in broadcast else n for d, n in zip(DIMS, full_shape, strict=True))
        self._broadcast[name] = tuple(d for d, keep in zip(DIMS[:2], self.keep, strict=True)
                                      if keep and d in broadcast)
        shape = tuple(n for i, n in enumerate(full_shape) if i >= 2 or self.keep[i])
        self._specs[name] = (shape, done_size)
        done = np.zeros(done_size, bool)
        kept = []
        for p, m in self._units.get(name, []):
            sel = np.asarray(m["z"] if "z" in m else [m["target"]], np.int64)
            if tuple(m["shape"]) != shape or sel.max(initial=-1) >= done_size or done[sel].any():
                p.unlink(missing_ok=True)  # from another layout, or overlapping: redo
                continue
            done[sel] = True
            kept.append((p, m))
        self._units[name] = kept
        self._done[name] = done

    def done(self, name: str) -> np.ndarray:
        """Boolean mask of the finished blocks of ``name`` (slices or flattened targets)."""
        return self._done[name].copy()

    def _unit(self, name: str, vol: np.ndarray, meta: dict, fault: str, stem: str) -> None:
        meta = dict(meta, name=name, shape=list(self._specs[name][0]))
        p = units.write_unit(self.units_dir, stem, {"data": np.ascontiguousarray(vol, self.dtype)}, meta, fault)
        self._units[name].append((p, meta))
        self.units_written[fault] += 1

    def write(self, name: str, vol: np.ndarray, z_index) -> None:
        """Write a full-axis block ``(n_c, n_r, s, ny, nx)`` into slice indices ``z_index`` (increasing).

        Along a ``broadcast`` axis of the dataset the block has length 1.

        Slices already done are skipped (a resumed run never writes a unit twice).
        """
        v = self._squeeze(vol)
        z = np.asarray(z_index, np.int64)
        new = ~self._done[name][z]
        if not new.any():
            return
        if not new.all():  # (a resumed run) only the slices not yet written; else no copy
            v, z = v[(slice(None),) * (v.ndim - 3) + (new,)], z[new]
        self._unit(name, v, {"z": z.tolist()}, "recon", f"{name.replace('/', '~')}.z{z[0]:05d}-{z[-1]:05d}")
        self._done[name][z] = True

    @staticmethod
    def target_stem(name: str, k: int) -> str:
        """File-name stem of the unit of flattened target ``k`` of ``name``."""
        return f"{name.replace('/', '~')}.t{k:05d}"

    def write_target(self, name: str, i: int, j: int, n_resp: int, vol: np.ndarray) -> Path | None:
        """Write one target's ``(nz, ny, nx)`` volume at cardiac index ``i``, respiratory index ``j``.

        Returns the unit file written (None if the target was already done).
        """
        k = i * n_resp + j
        if self._done[name][k]:
            return None
        sel = [int(x) for x, keep in zip((i, j), self.keep, strict=True) if keep]
        self._unit(name, vol, {"target": k, "sel": sel}, "truth", self.target_stem(name, k))
        self._done[name][k] = True
        return self._units[name][-1][0]

    def adopt_target(self, name: str, k: int, path: Path, link) -> bool:
        """Take flattened target ``k`` of ``name`` from an existing unit file (e.g. the truth cache).

        The unit must pass its checksum and describe this target of this dataset's shape;
        ``link(path, folder) -> new path`` puts it into the units folder. Returns whether it
        was taken (False: damaged or not this target; the caller computes it).
        """
        if self._done[name][k]:
            return True
        try:
            _, meta = units.read_unit(path)
        except (OSError, ValueError, KeyError, EOFError):
            return False
        if (meta.get("name") != name or meta.get("target") != k
                or tuple(meta.get("shape", ())) != self._specs[name][0]):
            return False
        self._units[name].append((link(path, self.units_dir), meta))
        self._done[name][k] = True
        self.units_written["adopted"] = self.units_written.get("adopted", 0) + 1
        return True

    def assemble(self) -> h5py.File:
        """Build ``volumes.h5.partial`` from the units; returns it open for reading (also ``self.f``)."""
        with h5py.File(self.partial, "w") as f:
            f.attrs["format_version"] = FORMAT_VERSION
            for k, v in self.axes.items():
                f[f"axes/{k}"] = v
            for name, (shape, _) in self._specs.items():
                chunks = tuple(1 for _ in shape[:-3]) + (1,) + tuple(shape[-2:])
                ds = f.create_dataset(name, shape=shape, dtype=self.dtype, chunks=chunks)
                ds.attrs["dims"] = list(self._dims())
                ds.attrs["broadcast"] = list(self._broadcast[name])
                ds.attrs["units"] = "HU"
                ds.attrs["done"] = self._done[name].astype(np.uint8)
                for p, m in self._units[name]:
                    data = units.read_unit(p)[0]["data"]  # checksum checked again
                    if "z" in m:
                        ds[(slice(None),) * (len(shape) - 3) + (list(m["z"]),)] = data
                    else:
                        ds[tuple(m["sel"])] = data
                    faults.point("assemble-volumes")
        units.fsync_file(self.partial)
        self.f = h5py.File(self.partial, "r")
        return self.f

    def close(self) -> None:
        """Assemble (if not yet), rename to ``volumes.h5`` and remove the units."""
        if self.f is None:
            self.assemble()
        self.f.close()
        faults.point("rename-volumes")
        self.partial.replace(self.path)
        units.fsync_dir(self.path.parent)
        shutil.rmtree(self.units_dir, ignore_errors=True)

    def abort(self) -> None:
        """Close the assembly file if open; the units stay for the next run."""
        if self.f is not None:
            try:
                self.f.close()
            except Exception:  # noqa: BLE001 - best-effort cleanup on a failing run: the original error matters
                pass


def open_volumes(path) -> h5py.File:
    """Open a run's ``volumes.h5`` read-only, with one-line errors for missing/old/corrupt files."""
    p = Path(path)
    if p.is_dir():
        p = p / "volumes.h5"
    if not p.exists():
        raise StoreError(f"{p}: no volumes in this run directory (was `clrecon run` finished?)")
    try:
        f = h5py.File(p, "r")
    except OSError as e:
        raise StoreError(f"{p}: not a readable HDF5 file ({e})") from None
    version = f.attrs.get("format_version")
    if version != FORMAT_VERSION:
        f.close()
        raise StoreError(f"{p}: volume format {version!r} is not {FORMAT_VERSION}; "
                         f"re-run `clrecon run` with this version")
    return f


def read_part(f: h5py.File, name: str, index: dict | None = None, full: bool = True) -> np.ndarray:
    """Part of a volume as float32 HU, by axis name: ``index`` maps axis names to an int or slice.

    The one place that reads volume datasets: an axis the dataset lacks on disk (length 1) or
    stores at length 1 for every target (attribute ``broadcast``) takes any index, and with
    ``full=True`` the result has every one of the five axes at the run's length (from
    ``/axes``) except those indexed by an int; with ``full=False`` the axes the dataset lacks
    on disk are left out (its own shape).
    """
    index = dict(index or {})
    ds = f[name]
    dims = [str(d) for d in ds.attrs["dims"]]
    bc = {str(d) for d in ds.attrs.get("broadcast", [])}
    sel = []
    for d in dims:
        k = index.get(d, slice(None))
        if d in bc:
            k = 0 if isinstance(k, (int, np.integer)) else slice(0, 1)
        sel.append(k)
    arr = np.asarray(ds[tuple(sel)], np.float32)
    picked = lambda d: isinstance(index.get(d, slice(None)), (int, np.integer))  # noqa: E731
    kept = [d for d in dims if not picked(d)]
    if full:  # every axis not picked by an int, length 1 where the dataset lacks it
        out_dims = [d for d in DIMS if not picked(d)]
        arr = arr.reshape([arr.shape[kept.index(d)] if d in kept else 1 for d in out_dims])
    else:
        out_dims = kept
    if bc:  # the broadcast axes restored to the run's length (or the slice of it asked for)
        want = [len(range(_axis_len(f, d))[index.get(d, slice(None))]) if d in bc else n
                for d, n in zip(out_dims, arr.shape, strict=True)]
        arr = np.ascontiguousarray(np.broadcast_to(arr, want))
    return arr


def _axis_len(f: h5py.File, dim: str) -> int:
    return int(f[f"axes/{_AXIS_NAME[dim]}"].shape[0])


_AXIS_NAME = dict(zip(DIMS, ("cardiac_phase", "resp_amplitude", "z_mm", "y_mm", "x_mm"), strict=True))


def read_volume(f: h5py.File, name: str, index=None) -> np.ndarray:
    """A volume as a full 5-axis float32 array ``(n_c, n_r, nz, ny, nx)``.

    ``index`` optionally picks (cardiac_index, resp_index) and returns ``(nz, ny, nx)``.
    """
    if index is not None:
        return read_part(f, name, {"cardiac": int(index[0]), "resp": int(index[1])})
    return read_part(f, name)


def list_recons(f: h5py.File) -> list[tuple[str, str, str]]:
    """(pitch_key, variant, method) of every reconstruction in the file."""
    out = []
    if "recon" not in f:
        return out
    for p in f["recon"]:
        for v in f["recon"][p]:
            for m in f["recon"][p][v]:
                out.append((p, v, m))
    return out
