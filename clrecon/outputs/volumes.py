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
import os
import secrets
import shutil
import time
from pathlib import Path

import h5py
import numpy as np

from clrecon.core import faults, units
from clrecon.core.errors import StoreError
from clrecon.core.resources import folder_bytes

DIMS = ("cardiac", "resp", "z", "y", "x")
#: Layout of ``volumes.h5``: 2 = axes + virtual datasets over ``volumes.d/<gen>/<name>.h5``
#: (one compressed file per dataset); 1 = every dataset inside ``volumes.h5`` (clrecon before
#: the per-dataset files; still read: :data:`READABLE_VERSIONS`).
FORMAT_VERSION = 2
READABLE_VERSIONS = (1, 2)
#: Format of the units folder's ``run.json`` (unchanged by the per-dataset files: an earlier
#: version's interrupted run resumes).
UNITS_FORMAT = 1
#: Allowed on-disk dtypes of the volumes (``recon.volume_dtype``).
VOLUME_DTYPES = ("float32", "float16")
#: ``recon.volume_compression = "auto"`` compresses (LZF + shuffle) a run whose volumes are at least
#: this many bytes raw. Below it the compression costs more time than its disk is worth: on demo
#: (0.99 GB raw, 0.61 GB compressed, 26 datasets) writing the compressed units took 9.2 s of an
#: 80 s run and every read of a volume decompresses it again (docs/data-flow.md, "Disk").
AUTO_COMPRESS_BYTES = 4 * 1024 ** 3
#: Allowed ``recon.volume_compression`` values; the chunk filters of each resolved one.
VOLUME_COMPRESSIONS = ("auto", "lzf", "none")
_FILTERS_OF = {"lzf": units.VOLUME_FILTERS, "none": {}}


def resolve_compression(choice: str, volume_bytes: int) -> str:
    """``"lzf"`` or ``"none"`` for ``recon.volume_compression = choice`` and the run's raw volume bytes."""
    if choice not in VOLUME_COMPRESSIONS:
        raise ValueError(f"volume compression {choice!r}: allowed {', '.join(VOLUME_COMPRESSIONS)}")
    if choice == "auto":
        return "lzf" if volume_bytes >= AUTO_COMPRESS_BYTES else "none"
    return choice


def pitch_key(pitch: float) -> str:
    return f"p{pitch:.3f}"


class VolumeWriter:
    """Writes ``volumes.h5`` crash-safely, one dataset file at a time (peak disk: result + one dataset).

    Every finished block (a slab of one reconstruction, one target of a truth) is written as
    its own atomic, checksummed unit file in ``volumes.h5.units/`` (:mod:`clrecon.core.units`),
    compressed with the filters of the final files (one chunk per slice; ``compression = "lzf"``:
    LZF + byte shuffle, :data:`clrecon.core.units.VOLUME_FILTERS`; ``"none"``: chunked, no filter,
    as :func:`resolve_compression` picks for small runs); nothing is written into HDF5 while computing,
    so a SIGKILL at any instant can only lose the block being written.

    :meth:`assemble` then builds the datasets one by one: ``volumes.d/<gen>/<name>.h5.partial``
    from that dataset's units (their compressed chunks copied as they are, no recompression),
    fsync, rename to ``<name>.h5``, and only then that dataset's units are deleted; so at any
    instant the disk holds the finished datasets, the units of the others and at most one
    dataset twice, never the whole result twice. Last it writes ``volumes.h5.partial``: the
    ``/axes`` and, for every dataset, an HDF5 virtual dataset mapping the whole of
    ``volumes.d/<gen>/<name>.h5:/volume`` (a path relative to ``volumes.h5``'s folder, which
    HDF5 resolves against the folder of the file holding the virtual dataset: the run folder can
    be moved or copied whole), with the dataset's attributes; ``f`` is then open on it for
    reading. :meth:`close` fsyncs it, renames it to ``volumes.h5``, removes the units folder
    and any other ``volumes.d/*`` folder (an earlier result's).

    ``<gen>`` is a fresh name per started run (kept in ``volumes.h5.units/run.json``): a
    different request in the same run folder never touches the earlier result's files, which
    stay readable until the new ``volumes.h5`` replaces the old one.

    A later run with the same ``run_key`` (hash of scene and request, kept in
    ``volumes.h5.units/run.json``) keeps the intact units and the finished dataset files and
    skips what they hold; a damaged unit is dropped with a warning and redone; a leftover
    ``.partial`` (an assembly cut short) is discarded and rebuilt; any other key starts afresh.
    """

    def __init__(self, path: Path, axes: dict, keep_cardiac: bool, keep_resp: bool, run_key: str = "",
                 dtype: str = "float32", compression: str = "lzf"):
        if dtype not in VOLUME_DTYPES:
            raise ValueError(f"volume dtype {dtype!r}: allowed {', '.join(VOLUME_DTYPES)}")
        if compression not in _FILTERS_OF:
            raise ValueError(f"volume compression {compression!r}: allowed {', '.join(_FILTERS_OF)}")
        self.dtype = np.dtype(dtype)
        self.compression = compression
        self.filters = _FILTERS_OF[compression]
        self.path = Path(path)
        self.partial = self.path.with_name(self.path.name + ".partial")
        self.units_dir = self.path.with_name(self.path.name + ".units")
        self.datasets_root = self.path.with_name(self.path.stem + ".d")
        self.keep = (keep_cardiac, keep_resp)
        self.axes = {k: np.asarray(v, np.float64) for k, v in axes.items()}
        self.resumed = False
        self.f = None
        self.run_key = run_key
        self.units_written = {"recon": 0, "truth": 0}
        self._specs: dict[str, tuple[tuple, int]] = {}  # name -> (on-disk shape, done size)
        self._broadcast: dict[str, tuple[str, ...]] = {}  # name -> axes stored at length 1 (standing for all)
        self._done: dict[str, np.ndarray] = {}
        self._units: dict[str, list[tuple[Path, dict]]] = {}
        #: bytes under the run's volume paths after each step of :meth:`assemble` (peak bookkeeping)
        self.disk_trace: list[tuple[str, int]] = []
        self.partial.unlink(missing_ok=True)  # only ever an assembly in progress: rebuilt from the units
        meta_path = self.units_dir / "run.json"
        try:
            meta = json.loads(meta_path.read_text())
        except (OSError, ValueError):
            meta = None
        if (meta and meta.get("run_key") == run_key and meta.get("format_version") == UNITS_FORMAT):
            self.resumed = True
            for p, m in units.scan_units(self.units_dir):
                self._units.setdefault(m["name"], []).append((p, m))
            gen = meta.get("datasets")
            if not gen:  # units of an earlier version's interrupted run: a folder for its datasets
                gen = self._new_gen()
                units.write_json_atomic(meta_path, dict(meta, datasets=gen))
        else:
            shutil.rmtree(self.units_dir, ignore_errors=True)
            self.units_dir.mkdir(parents=True)
            gen = self._new_gen()
            self._drop_datasets(keep=_linked_gen(self.path))  # folders of interrupted runs; not the result's
            units.write_json_atomic(meta_path, {"run_key": run_key, "format_version": UNITS_FORMAT,
                                                "datasets": gen})
        self.datasets_dir = self.datasets_root / gen
        self.datasets_dir.mkdir(parents=True, exist_ok=True)
        for p in self.datasets_dir.glob("*.partial"):  # a dataset's assembly cut short
            p.unlink(missing_ok=True)

    @staticmethod
    def _new_gen() -> str:
        return f"{time.strftime('%Y%m%dT%H%M%S')}-{secrets.token_hex(3)}"

    def _drop_datasets(self, keep: str | None) -> None:
        if self.datasets_root.is_dir():
            for p in self.datasets_root.iterdir():
                if p.name != keep:
                    shutil.rmtree(p, ignore_errors=True) if p.is_dir() else p.unlink(missing_ok=True)

    def dataset_path(self, name: str) -> Path:
        """The file that holds dataset ``name`` once assembled: ``volumes.d/<gen>/<name with ~>.h5``."""
        return self.datasets_dir / f"{name.replace('/', '~')}.h5"

    def _dims(self):
        return tuple(d for d, keep in zip(DIMS, self.keep + (True, True, True), strict=True) if keep)

    def _squeeze(self, vol: np.ndarray) -> np.ndarray:
        drop = tuple(i for i, keep in enumerate(self.keep) if not keep)
        return vol.reshape(tuple(s for i, s in enumerate(vol.shape) if i not in drop))

    def _chunks(self, shape: tuple) -> tuple:
        return (1,) * (len(shape) - 2) + tuple(shape[-2:])

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
        assembled = self._assembled_done(name, shape, done_size)
        if assembled is not None:
            done |= assembled
        kept = []
        for p, m in self._units.get(name, []):
            sel = np.asarray(m["z"] if "z" in m else [m["target"]], np.int64)
            if tuple(m["shape"]) != shape or sel.max(initial=-1) >= done_size or done[sel].any():
                p.unlink(missing_ok=True)  # from another layout, overlapping or already assembled: redo/drop
                continue
            done[sel] = True
            kept.append((p, m))
        self._units[name] = kept
        self._done[name] = done

    def _assembled_done(self, name: str, shape: tuple, done_size: int) -> np.ndarray | None:
        """The done mask of ``name``'s finished dataset file of this run (None: none, or unusable: removed)."""
        p = self.dataset_path(name)
        if not p.exists():
            return None
        try:
            with h5py.File(p, "r") as f:
                ds = f["volume"]
                ok = (f.attrs.get("run_key") == self.run_key and ds.shape == shape and ds.dtype == self.dtype)
                done = np.asarray(ds.attrs["done"], bool)
            if ok and done.shape == (done_size,):
                return done
        except (OSError, KeyError, ValueError):
            pass
        p.unlink(missing_ok=True)  # damaged or from another layout: rebuilt from units / recomputed
        return None

    def done(self, name: str) -> np.ndarray:
        """Boolean mask of the finished blocks of ``name`` (slices or flattened targets)."""
        return self._done[name].copy()

    def _unit(self, name: str, vol: np.ndarray, meta: dict, fault: str, stem: str) -> None:
        meta = dict(meta, name=name, shape=list(self._specs[name][0]))
        vol = np.ascontiguousarray(vol, self.dtype)
        p = units.write_unit(self.units_dir, stem, {"data": vol}, meta, fault,
                             compress={"data": self._chunks(vol.shape)}, filters=self.filters)
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
            meta = units.read_meta(path)
        except (OSError, ValueError, KeyError, EOFError):
            return False
        if (meta.get("name") != name or meta.get("target") != k
                or tuple(meta.get("shape", ())) != self._specs[name][0]):
            return False
        self._units[name].append((link(path, self.units_dir), meta))
        self._done[name][k] = True
        self.units_written["adopted"] = self.units_written.get("adopted", 0) + 1
        return True

    # -- assembly ------------------------------------------------------------------------
    def _disk_bytes(self) -> int:
        """Bytes now under the run's volume paths (units, dataset files, the link file)."""
        total = 0
        for root in (self.units_dir, self.datasets_root):
            total += folder_bytes(root)
        for p in (self.partial, self.path):
            if p.exists():
                total += p.stat().st_size
        return total

    def _copy_unit(self, ds: h5py.Dataset, p: Path, m: dict) -> None:
        """Write unit ``p`` into ``ds``: its compressed chunks as they are where they match, else decoded."""
        nt = ds.ndim - 3
        with units.open_unit(p) as (uf, arrays, _):  # checksum checked again
            src = uf["data"] if uf is not None else None
            if "z" in m:
                z = np.asarray(m["z"], np.int64)
                place = lambda off: off[:nt] + (int(z[off[nt]]),) + off[nt + 1:]  # noqa: E731
            else:
                place = lambda off: tuple(m["sel"]) + off  # noqa: E731
            if (src is not None and src.chunks == ds.chunks and src.dtype == ds.dtype
                    and (src.compression, src.shuffle, src.fletcher32) == (ds.compression, ds.shuffle, ds.fletcher32)
                    and src.id.get_num_chunks() == int(np.prod(src.shape[:-2]))):
                for c in range(src.id.get_num_chunks()):
                    info = src.id.get_chunk_info(c)
                    mask, raw = src.id.read_direct_chunk(info.chunk_offset)
                    ds.id.write_direct_chunk(place(tuple(info.chunk_offset)), raw, mask)
                return
            data = arrays["data"] if src is None else src[()]
            if "z" in m:
                ds[(slice(None),) * nt + (z.tolist(),)] = data
            else:
                ds[tuple(m["sel"])] = data

    def _assemble_dataset(self, name: str) -> None:
        """``volumes.d/<gen>/<name>.h5`` from its units (and its earlier file, if any); then drop the units."""
        shape, _ = self._specs[name]
        final = self.dataset_path(name)
        pending = self._units[name]
        if final.exists() and not pending:
            return
        part = final.with_name(final.name + ".partial")
        if final.exists():  # an assembled dataset that a resumed run extends (rare): copied, then added to
            shutil.copyfile(final, part)
        with h5py.File(part, "r+" if final.exists() else "w") as f:
            if "volume" not in f:
                f.attrs.update({"format_version": FORMAT_VERSION, "run_key": self.run_key, "name": name})
                ds = f.create_dataset("volume", shape=shape, dtype=self.dtype, chunks=self._chunks(shape),
                                      **self.filters)
                ds.attrs["dims"] = list(self._dims())
                ds.attrs["broadcast"] = list(self._broadcast[name])
                ds.attrs["units"] = "HU"
            ds = f["volume"]
            for p, m in pending:
                self._copy_unit(ds, p, m)
                faults.point("assemble-volumes")
            ds.attrs["done"] = self._done[name].astype(np.uint8)
        units.fsync_file(part)
        faults.point("rename-dataset")
        os.replace(part, final)
        units.fsync_dir(final.parent)
        self.disk_trace.append((f"renamed {name}", self._disk_bytes()))
        faults.point("drop-units")
        for p, _ in pending:  # in the fsync'd, renamed file now: the units go
            p.unlink(missing_ok=True)
        units.fsync_dir(self.units_dir)
        self._units[name] = []
        self.disk_trace.append((f"dropped units of {name}", self._disk_bytes()))

    def assemble(self) -> h5py.File:
        """Assemble every dataset file, then ``volumes.h5.partial`` over them; returns it open for reading."""
        self.disk_trace.append(("start", self._disk_bytes()))
        for name in self._specs:
            self._assemble_dataset(name)
        rel = self.datasets_dir.relative_to(self.path.parent).as_posix()
        with h5py.File(self.partial, "w") as f:
            f.attrs["format_version"] = FORMAT_VERSION
            f.attrs["datasets_dir"] = rel
            for k, v in self.axes.items():
                f[f"axes/{k}"] = v
            for name, (shape, _) in self._specs.items():
                layout = h5py.VirtualLayout(shape=shape, dtype=self.dtype)
                layout[...] = h5py.VirtualSource(f"{rel}/{self.dataset_path(name).name}", "volume", shape=shape,
                                                 dtype=self.dtype)
                ds = f.create_virtual_dataset(name, layout, fillvalue=np.nan)
                ds.attrs["dims"] = list(self._dims())
                ds.attrs["broadcast"] = list(self._broadcast[name])
                ds.attrs["units"] = "HU"
                ds.attrs["done"] = self._done[name].astype(np.uint8)
                ds.attrs["source"] = f"{rel}/{self.dataset_path(name).name}"
        units.fsync_file(self.partial)
        self.disk_trace.append(("assembled", self._disk_bytes()))
        self.f = h5py.File(self.partial, "r")
        return self.f

    def close(self) -> None:
        """Assemble (if not yet), rename to ``volumes.h5``, remove the units and earlier results' files."""
        if self.f is None:
            self.assemble()
        self.f.close()
        faults.point("rename-volumes")
        self.partial.replace(self.path)
        units.fsync_dir(self.path.parent)
        shutil.rmtree(self.units_dir, ignore_errors=True)
        self._drop_datasets(keep=self.datasets_dir.name)

    def abort(self) -> None:
        """Close the assembly file if open; the units stay for the next run."""
        if self.f is not None:
            try:
                self.f.close()
            except Exception:  # noqa: BLE001 - best-effort cleanup on a failing run: the original error matters
                pass


def _linked_gen(path: Path) -> str | None:
    """The ``volumes.d/<gen>`` folder name a finished ``volumes.h5`` reads from (None: none or old layout)."""
    try:
        with h5py.File(path, "r") as f:
            rel = f.attrs.get("datasets_dir")
    except OSError:
        return None
    return Path(str(rel)).name if rel else None


def check_sources(f: h5py.File, p: Path) -> None:
    """Raise a one-line :class:`StoreError` when a dataset file a ``volumes.h5`` reads from is missing."""
    if f.attrs.get("format_version") != FORMAT_VERSION:
        return
    rel = f.attrs.get("datasets_dir")
    folder = p.parent / str(rel)
    missing = []

    def visit(name, obj):
        src = obj.attrs.get("source") if isinstance(obj, h5py.Dataset) else None
        if src is not None and not (p.parent / str(src)).is_file():
            missing.append(name)
    f.visititems(visit)
    if missing:
        raise StoreError(f"{p}: {len(missing)} of its dataset files are missing from {folder} (first: {missing[0]}); "
                         f"copy or move the run folder whole, volumes.h5 with its {p.stem}.d/ folder")


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
    if version not in READABLE_VERSIONS:
        f.close()
        raise StoreError(f"{p}: volume format {version!r} is not {FORMAT_VERSION}; "
                         f"re-run `clrecon run` with this version")
    try:
        check_sources(f, p)
    except StoreError:
        f.close()
        raise
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
