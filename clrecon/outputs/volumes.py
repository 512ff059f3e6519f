"""The run directory's volume store, ``volumes.h5`` (written by ``run``, read by report/viewer/export).

Layout (HDF5)::

    /axes/cardiac_phase  (n_c,)   target cardiac phases        (absent axis: length 1)
    /axes/resp_amplitude (n_r,)   target respiratory amplitudes
    /axes/z_mm (nz,) /axes/y_mm (ny,) /axes/x_mm (nx,)   voxel centres, LPS, mm
    /groundtruth                  ground-truth CT (exact in-plane projections + same FBP)
    /phantom                      voxelised analytic phantom
    /recon/<pitch>/<variant>/<method>     e.g. /recon/p0.020/noise-free/local_linear
                                  (:func:`recon_path`; <pitch> is :func:`pitch_key`'s)

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
the volumes of a paper-scale run (docs/results/paper-scale.md gives the measured effect).
"""

from __future__ import annotations

import contextlib
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
#: Layout of ``volumes.h5``: 3 = axes + virtual datasets over the unit files in
#: ``volumes.d/<gen>/`` (each block written once, in place: :class:`VolumeWriter`); 2 = virtual
#: datasets over ``volumes.d/<gen>/<name>.h5`` (one compressed file per dataset, copied from the
#: units); 1 = every dataset inside ``volumes.h5`` (clrecon before the per-dataset files). All
#: are read: :data:`READABLE_VERSIONS`.
FORMAT_VERSION = 3
READABLE_VERSIONS = (1, 2, 3)
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


#: The group of every reconstruction in ``volumes.h5``.
RECON = "recon"


def pitch_key(pitch: float) -> str:
    """A pitch's name in ``volumes.h5`` and ``results.json``: ``0.02`` -> ``"p0.020"``."""
    return f"p{pitch:.3f}"


def recon_path(pk: str, variant: str | None = None, method: str | None = None) -> str:
    """The HDF5 path of a reconstruction, ``recon/<pitch key>/<variant>/<method>``; with fewer parts
    the group of its pitch (``recon/<pk>``) or of its variant (``recon/<pk>/<variant>``).
    The one spelling of the layout (module docstring); ``pk`` is :func:`pitch_key`'s."""
    if method is not None and variant is None:
        raise ValueError("recon_path: a method needs its variant")
    return "/".join([RECON, pk] + [x for x in (variant, method) if x is not None])


class VolumeWriter:
    """Writes ``volumes.h5`` crash-safely, each block once, in place (peak disk: the result).

    Every finished block (a slab of one reconstruction, one target of a truth) is written as
    its own atomic, checksummed unit file (:mod:`clrecon.core.units`) straight into the result's
    folder ``volumes.d/<gen>/``, compressed with the filters of the result (one chunk per slice;
    ``compression = "lzf"``: LZF + byte shuffle, :data:`clrecon.core.units.VOLUME_FILTERS`;
    ``"none"``: chunked, no filter, as :func:`resolve_compression` picks for small runs); nothing
    is written into a shared HDF5 file while computing, so a SIGKILL at any instant can only lose
    the block being written.

    :meth:`assemble` copies no data: it writes ``volumes.h5.partial``, the ``/axes`` and, for every
    dataset, an HDF5 virtual dataset whose mappings place each unit's ``data`` (a slab's slices,
    or one target) at its block of the full grid (paths relative to ``volumes.h5``'s folder,
    which HDF5 resolves against the folder of the file holding the virtual dataset: the run
    folder can be moved or copied whole), with the dataset's attributes; ``f`` is then open on
    it for reading. :meth:`close` fsyncs it, renames it to ``volumes.h5``, removes the units
    folder (which holds only ``run.json``) and any other ``volumes.d/*`` folder (an earlier
    result's). The unit files *are* the result's data: the disk never holds a block twice (the
    format before, 2, copied each dataset's units into one file per dataset and then dropped
    them, so one dataset was on disk twice at a time and the copy took 7 % of demo's run).

    An interrupted run of an earlier version resumes: its units in ``volumes.h5.units/`` are
    moved into ``volumes.d/<gen>/`` (``.npz`` units and units of another dtype are rewritten
    there as HDF5 units, the only data written twice), and a dataset file ``<name>.h5`` its
    assembly had finished is mapped for the blocks its ``done`` mask holds.

    ``<gen>`` is a fresh name per started run (kept in ``volumes.h5.units/run.json``): a
    different request in the same run folder never touches the earlier result's files, which
    stay readable until the new ``volumes.h5`` replaces the old one.

    A later run with the same ``run_key`` (hash of scene and request, kept in
    ``volumes.h5.units/run.json``) keeps the intact units and skips what they hold; a damaged
    unit is dropped with a warning and redone; a leftover ``.partial`` (an assembly cut short)
    is discarded and rebuilt; any other key starts afresh.
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
        self._blocks: dict[str, str] = {}  # name -> "slices" | "targets"
        self._old_files: dict[str, tuple[Path, np.ndarray]] = {}  # name -> (format-2 dataset file, its done)
        #: bytes under the run's volume paths after each step of :meth:`assemble` (peak bookkeeping)
        self.disk_trace: list[tuple[str, int]] = []
        self._made_folder = not self.path.parent.exists()  # removed again by a failed start (abort)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.partial.unlink(missing_ok=True)  # only ever an assembly in progress: rebuilt from the units
        meta_path = self.units_dir / "run.json"
        try:
            meta = json.loads(meta_path.read_text())
        except (OSError, ValueError):
            meta = None
        if (meta and meta.get("run_key") == run_key and meta.get("format_version") == UNITS_FORMAT):
            self.resumed = True
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
        for p in self.datasets_dir.glob("*.partial"):  # a format-2 dataset's assembly cut short
            p.unlink(missing_ok=True)
        if self.resumed:
            moved = False
            for p in self.units_dir.glob(f"*{units.SUFFIX}"):  # an earlier version's units: into place
                os.replace(p, self.datasets_dir / p.name)
                moved = True
            if moved:
                units.fsync_dir(self.datasets_dir)
            for p, m in units.scan_units(self.datasets_dir):
                self._units.setdefault(m["name"], []).append((p, m))

    @staticmethod
    def _new_gen() -> str:
        return f"{time.strftime('%Y%m%dT%H%M%S')}-{secrets.token_hex(3)}"

    def _drop_datasets(self, keep: str | None) -> None:
        if self.datasets_root.is_dir():
            for p in self.datasets_root.iterdir():
                if p.name != keep:
                    shutil.rmtree(p, ignore_errors=True) if p.is_dir() else p.unlink(missing_ok=True)

    def dataset_path(self, name: str) -> Path:
        """Where an earlier version (format 2) put dataset ``name`` assembled: ``volumes.d/<gen>/<name with ~>.h5``."""
        return self.datasets_dir / f"{name.replace('/', '~')}.h5"

    def _dims(self):
        return tuple(d for d, keep in zip(DIMS, self.keep + (True, True, True), strict=True) if keep)

    def _squeeze(self, vol: np.ndarray) -> np.ndarray:
        drop = tuple(i for i, keep in enumerate(self.keep) if not keep)
        return vol.reshape(tuple(s for i, s in enumerate(vol.shape) if i not in drop))

    def _chunks(self, shape: tuple) -> tuple:
        return (1,) * (len(shape) - 2) + tuple(shape[-2:])

    def create(self, name: str, full_shape: tuple, done_size: int, broadcast: tuple = (),
               blocks: str = "slices") -> None:
        """Declare dataset ``name`` with a ``done`` mask of ``done_size`` (slices or flattened targets).

        ``broadcast``: target axes (``"cardiac"``, ``"resp"``) along which the volume is the same
        for every target, stored at length 1 (blocks written to it have length 1 there).
        ``blocks``: ``"slices"`` (written by :meth:`write`, slabs of slices) or ``"targets"``
        (:meth:`write_target`, one target each: the truths).
        """
        if name in self._specs:
            return
        bad = set(broadcast) - {"cardiac", "resp"}
        if bad:
            raise ValueError(f"broadcast axes {sorted(bad)}: only 'cardiac' and 'resp' can be broadcast")
        if blocks not in ("slices", "targets"):
            raise ValueError(f"blocks {blocks!r}: allowed slices, targets")
        self._blocks[name] = blocks
        full_shape = tuple(1 if d in broadcast else n for d, n in zip(DIMS, full_shape, strict=True))
        self._broadcast[name] = tuple(d for d, keep in zip(DIMS[:2], self.keep, strict=True)
                                      if keep and d in broadcast)
        shape = tuple(n for i, n in enumerate(full_shape) if i >= 2 or self.keep[i])
        self._specs[name] = (shape, done_size)
        done = np.zeros(done_size, bool)
        assembled = self._assembled_done(name, shape, done_size)
        if assembled is not None:
            done |= assembled
            self._old_files[name] = (self.dataset_path(name), assembled)
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
        """The done mask of ``name``'s format-2 dataset file of this run (None: none, or unusable: removed)."""
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
        p.unlink(missing_ok=True)  # damaged or from another layout: recomputed
        return None

    def done(self, name: str) -> np.ndarray:
        """Boolean mask of the finished blocks of ``name`` (slices or flattened targets)."""
        return self._done[name].copy()

    def _unit(self, name: str, vol: np.ndarray, meta: dict, fault: str, stem: str) -> None:
        meta = dict(meta, name=name, shape=list(self._specs[name][0]))
        vol = self.as_stored(vol)
        p = units.write_unit(self.datasets_dir, stem, {"data": vol}, meta, fault,
                             compress={"data": self._chunks(vol.shape)}, filters=self.filters)
        self._units[name].append((p, meta))
        self.units_written[fault] += 1

    def as_stored(self, vol: np.ndarray) -> np.ndarray:
        """``vol`` as :meth:`write` stores it: C-contiguous in the volume dtype (a copy unless it
        already is), the same values. Converting before :meth:`write` lets a caller drop its
        float32 images before the write starts (the reconstruction's write behind)."""
        return np.ascontiguousarray(vol, self.dtype)

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

    def read(self, name: str, z_index=None, reduce=None) -> np.ndarray:
        """Slices ``z_index`` (default all) of dataset ``name`` read back from its finished unit files:
        ``(n_c, n_r, s, ny, nx)`` float32, a ``broadcast`` axis at length 1 (as written).

        For a stage that works on an earlier stage's volumes before ``volumes.h5`` exists (``mc``
        on the barycentric first pass). Every slice asked for must be done (ValueError otherwise);
        each unit's checksum is checked (a damaged one raises :class:`~clrecon.core.errors.StoreError`).
        ``reduce``: optional reduction applied to each unit's slices as they are read,
        ``(n_c, n_r, s, ny, nx)`` float32 -> ``(m_c, m_r, s, my, mx)`` float32, slice by slice
        independent (``mc``'s block means onto its registration grid; ``mcir``'s one target): the
        result is ``(m_c, m_r, s, my, mx)`` and the dataset is never held whole (one unit at a time).
        """
        if self._blocks.get(name) != "slices":
            raise ValueError(f"{name}: not a dataset of slabs of slices declared in this run")
        shape, size = self._specs[name]
        z = np.arange(size) if z_index is None else np.asarray(z_index, np.int64)
        if not self._done[name][z].all():
            raise ValueError(f"{name}: slices {z[~self._done[name][z]].tolist()} are not written yet")
        full = tuple(1 if (not keep or d in self._broadcast[name]) else n
                     for d, keep, n in zip(DIMS[:2], self.keep, (len(self.axes["cardiac_phase"]),
                                                                  len(self.axes["resp_amplitude"])), strict=True))
        def fit(v):  # v: (n_c, n_r, s, ny, nx) as read -> float32, reduced where asked
            v = np.asarray(v, np.float32)
            return v if reduce is None else reduce(v)

        kept = fit(np.zeros(full + (0,) + tuple(shape[-2:]), np.float32)).shape  # the reduced shape, no slice
        out = np.empty(kept[:2] + (z.size,) + kept[3:], np.float32)
        pos = {int(k): i for i, k in enumerate(z)}
        got = np.zeros(z.size, bool)
        for p, m in self._units[name]:
            want = [(i, pos[k]) for i, k in enumerate(m["z"]) if k in pos]
            if not want:
                continue
            data = units.read_unit(p)[0]["data"].reshape(full + (len(m["z"]),) + tuple(shape[-2:]))
            src, dst = zip(*want, strict=True)
            whole = list(src) == list(range(len(m["z"])))  # the unit's every slice, in order: no copy
            out[:, :, list(dst)] = fit(data if whole else data[:, :, list(src)])
            del data
            got[list(dst)] = True
        old = self._old_files.get(name)
        if not got.all() and old is not None:  # slices an earlier version's assembled dataset file holds
            with h5py.File(old[0], "r") as f:
                for i in np.flatnonzero(~got):
                    v = np.asarray(f["volume"][(slice(None),) * (len(shape) - 3) + (int(z[i]),)], np.float32)
                    out[:, :, i] = fit(v.reshape(full + (1,) + tuple(shape[-2:])))[:, :, 0]
            got[:] = True
        if not got.all():
            raise ValueError(f"{name}: slices {z[~got].tolist()} have no unit file")
        return out

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
        ``link(path, folder) -> new path`` puts it into the result's folder. Returns whether it
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
        self._units[name].append((link(path, self.datasets_dir), meta))
        self._done[name][k] = True
        self.units_written["adopted"] = self.units_written.get("adopted", 0) + 1
        return True

    # -- assembly ------------------------------------------------------------------------
    def _disk_bytes(self) -> int:
        """Bytes now under the run's volume paths (units folder, result folders, the link file)."""
        total = 0
        for root in (self.units_dir, self.datasets_root):
            total += folder_bytes(root)
        for p in (self.partial, self.path):
            if p.exists():
                total += p.stat().st_size
        return total

    def _as_source(self, p: Path) -> Path:
        """Unit ``p`` as an HDF5 unit (an earlier version's ``.npz`` unit is rewritten once as one,
        the old file removed; the dtype is part of the run key, so an HDF5 unit has the writer's)."""
        with open(p, "rb") as fh:
            if fh.read(8) == units.H5_MAGIC:
                return p
        arrays, meta = units.read_unit(p)
        data = np.ascontiguousarray(arrays["data"], self.dtype)
        stem = p.name[:-len(units.SUFFIX)].rsplit(".", 1)[0]
        new = units.write_unit(self.datasets_dir, stem, {"data": data}, meta, "assemble-volumes",
                               compress={"data": self._chunks(data.shape)}, filters=self.filters)
        p.unlink(missing_ok=True)
        return new

    def _map_blocks(self, layout, rel: str, src_shape: tuple, m: dict) -> None:
        """Map the source ``rel:/data`` (shape ``src_shape``) at its block of ``layout``: runs of
        consecutive slices of a slab (``m["z"]``) or one target (``m["sel"]``)."""
        nt = len(src_shape) - 3
        if "z" in m:
            vs = h5py.VirtualSource(rel, "data", shape=src_shape, dtype=self.dtype)
            z = np.asarray(m["z"], np.int64)
            cut = np.flatnonzero(np.diff(z) != 1) + 1
            for a, b in zip(np.r_[0, cut], np.r_[cut, len(z)], strict=True):
                lead = (slice(None),) * nt
                layout[lead + (slice(int(z[a]), int(z[b - 1]) + 1),)] = vs[lead + (slice(int(a), int(b)),)]
        else:
            vs = h5py.VirtualSource(rel, "data", shape=src_shape, dtype=self.dtype)
            layout[tuple(int(s) for s in m["sel"])] = vs

    def _map_old_file(self, layout, name: str, rel: str, shape: tuple, done: np.ndarray) -> None:
        """Map a format-2 dataset file's finished blocks (slices, or flattened targets)."""
        vs = h5py.VirtualSource(rel, "volume", shape=shape, dtype=self.dtype)
        nt = len(shape) - 3
        lead = (slice(None),) * nt
        if self._blocks[name] == "slices":
            idx = np.flatnonzero(done)
            cut = np.flatnonzero(np.diff(idx) != 1) + 1
            for a, b in zip(np.r_[0, cut], np.r_[cut, len(idx)], strict=True):
                if b > a:
                    s = slice(int(idx[a]), int(idx[b - 1]) + 1)
                    layout[lead + (s,)] = vs[lead + (s,)]
        else:
            n_resp = len(self.axes["resp_amplitude"])
            for k in np.flatnonzero(done):
                i, j = divmod(int(k), n_resp)
                sel = tuple(x for x, keep in zip((i, j), self.keep, strict=True) if keep)
                layout[sel] = vs[sel]

    def assemble(self) -> h5py.File:
        """``volumes.h5.partial``: the axes and a virtual dataset per dataset over its units; returns it open."""
        self.disk_trace.append(("start", self._disk_bytes()))
        root = self.path.parent
        with h5py.File(self.partial, "w") as f:
            f.attrs["format_version"] = FORMAT_VERSION
            f.attrs["datasets_dir"] = self.datasets_dir.relative_to(root).as_posix()
            for k, v in self.axes.items():
                f[f"axes/{k}"] = v
            for name, (shape, _) in self._specs.items():
                layout = h5py.VirtualLayout(shape=shape, dtype=self.dtype)
                sources = []
                if name in self._old_files:
                    old, done = self._old_files[name]
                    rel = old.relative_to(root).as_posix()
                    self._map_old_file(layout, name, rel, shape, done)
                    sources.append(rel)
                for n, (p, m) in enumerate(self._units[name]):
                    p = self._as_source(p)
                    self._units[name][n] = (p, m)
                    rel = p.relative_to(root).as_posix()
                    src_shape = shape[:-3] + (len(m["z"]),) + shape[-2:] if "z" in m else shape[len(m["sel"]):]
                    self._map_blocks(layout, rel, src_shape, m)
                    sources.append(rel)
                faults.point("assemble-volumes")
                ds = f.create_virtual_dataset(name, layout, fillvalue=np.nan)
                ds.attrs["dims"] = list(self._dims())
                ds.attrs["broadcast"] = list(self._broadcast[name])
                ds.attrs["units"] = "HU"
                ds.attrs["done"] = self._done[name].astype(np.uint8)
                ds.attrs["sources"] = np.array(sources, dtype=h5py.string_dtype())
        units.fsync_file(self.partial)
        self.disk_trace.append(("assembled", self._disk_bytes()))
        self.f = h5py.File(self.partial, "r")
        return self.f

    def close(self) -> None:
        """Assemble (if not yet), rename to ``volumes.h5``, remove the units folder and earlier results' files."""
        if self.f is None:
            self.assemble()
        self.f.close()
        faults.point("rename-volumes")
        self.partial.replace(self.path)
        units.fsync_dir(self.path.parent)
        shutil.rmtree(self.units_dir, ignore_errors=True)
        self._drop_datasets(keep=self.datasets_dir.name)

    def abort(self) -> None:
        """Close the assembly file if open; the units stay for the next run.

        A run that fails before any unit is written (a failed start: a kernel that does not build,
        a bad input found late) leaves nothing behind: no ``volumes.h5.units/run.json`` stub, no empty
        ``volumes.d/<gen>/``, and no run folder this writer made, so that nothing looks like a run
        to resume or read."""
        if self.f is not None:
            try:
                self.f.close()
            except Exception:  # noqa: BLE001 - best-effort cleanup on a failing run: the original error matters
                pass
        try:
            self._drop_empty_start()
        except OSError:  # best effort: the original error matters
            pass

    def _drop_empty_start(self) -> None:
        if any(self.datasets_dir.iterdir()):
            return  # units to keep: the next run resumes from them
        self.datasets_dir.rmdir()
        with contextlib.suppress(OSError):
            self.datasets_root.rmdir()  # only when empty: an earlier result's folder stays
        if self.units_dir.is_dir() and {p.name for p in self.units_dir.iterdir()} <= {"run.json"}:
            (self.units_dir / "run.json").unlink(missing_ok=True)
            self.units_dir.rmdir()
        if self._made_folder:
            with contextlib.suppress(OSError):
                self.path.parent.rmdir()  # only when empty


def _linked_gen(path: Path) -> str | None:
    """The ``volumes.d/<gen>`` folder name a finished ``volumes.h5`` reads from (None: none or old layout)."""
    try:
        with h5py.File(path, "r") as f:
            rel = f.attrs.get("datasets_dir")
    except OSError:
        return None
    return Path(str(rel)).name if rel else None


def check_sources(f: h5py.File, p: Path) -> None:
    """Raise a one-line :class:`StoreError` when a file a ``volumes.h5`` reads from is missing.

    Format 2 names one dataset file per dataset (attribute ``source``), format 3 the unit files
    of each dataset (attribute ``sources``).
    """
    if f.attrs.get("format_version") not in (2, 3):
        return
    rel = f.attrs.get("datasets_dir")
    folder = p.parent / str(rel)
    present = {q.name for q in folder.iterdir()} if folder.is_dir() else set()
    missing = []

    def visit(name, obj):
        if not isinstance(obj, h5py.Dataset):
            return
        srcs = obj.attrs.get("sources")
        if srcs is None:
            srcs = [obj.attrs["source"]] if "source" in obj.attrs else []
        for src in srcs:
            src = src.decode() if isinstance(src, bytes) else str(src)
            q = p.parent / src
            if not (q.name in present if q.parent == folder else q.is_file()):
                missing.append(name)
                return
    f.visititems(visit)
    if missing:
        raise StoreError(f"{p}: {len(missing)} of its datasets read from files missing from {folder} "
                         f"(first: {missing[0]}); copy or move the run folder whole, volumes.h5 with its "
                         f"{p.stem}.d/ folder")


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
    if RECON not in f:
        return out
    for p in f[RECON]:
        for v in f[RECON][p]:
            for m in f[RECON][p][v]:
                out.append((p, v, m))
    return out
