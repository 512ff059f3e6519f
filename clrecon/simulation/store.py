"""Projection store: noise-free line integrals of one (scene, pitch) on disk (pipeline stage 5).

One HDF5 file per scan, ``<cache_dir>/<scene.scan_hash(pitch)>.h5``, reused by every later
run with the same scan settings. ``cache_dir`` defaults to ``$CLRECON_CACHE`` or
``~/.cache/clrecon``. Why HDF5 (h5py) rather than zarr: one self-describing file (data,
per-projection table and provenance together) that can be renamed atomically, chunked and
compressed, and read by every tool in the CT field (MATLAB, TIGRE, ASTRA users, HDFView).

Layout
------
- ``projections`` (n, R, C) float32: line integrals, ``proj[k, row, col]``; chunked by blocks
  of projections and :data:`ROW_CHUNK` detector rows (about 2 MiB per chunk, a power of two
  projections) and compressed with LZF + byte shuffle. A slab reads only the rows its slices
  use (:meth:`ProjectionStore.read_indices` ``rows=``), and HDF5 decompresses whole chunks, so
  chunks of row blocks keep a slab from decompressing rows it does not use (docs/stages-simulation.md
  "6. Projection store"). LZF is much faster than the projector fills the store and about halves
  the disk use (measured against none and gzip-1: docs/results/code-history.md "The projection store's chunks").
- ``present`` (n,) bool: which projections have been simulated. A run may simulate only the
  projections its slices need; a later run simulates only what is still missing.
- ``table/<column>`` (n,): the :class:`~clrecon.scan.table.ProjectionTable` columns.
- attrs: ``format``, ``scan_hash``, ``pitch``, ``scene_json`` (the scene that created it; a measured
  scene's input paths replaced by their digests, :mod:`clrecon.scan.patient_data`),
  ``clrecon_version``, ``projector_version``, ``views_per_rotation``, ``complete`` (all n
  projections present and the file closed cleanly).

Interruption safety (crash-safe at any instant, SIGKILL included)
-----------------------------------------------------------------
HDF5 has no journal, so nothing is written into an HDF5 file while projecting. Each chunk of
projections (a *unit*) becomes its own file in ``<hash>.h5.units/``, written under a temporary
name, fsync'd and renamed with its BLAKE2b checksum in its name (:mod:`clrecon.core.units`).
When the projecting is done the store is *assembled*: the existing ``<hash>.h5`` (if any) is
copied to ``<hash>.h5.partial`` (or a new file is created there), the units are written into
it with their ``present`` entries, it is fsync'd and renamed to ``<hash>.h5``, and the units
folder is removed.

Disk (docs/data-flow.md, "Disk"): a unit is written compressed with the store's own filters
(an HDF5 image, LZF + shuffle + Fletcher-32), so the units and the assembled store coexist at
about 2 x the compressed projections (raw ``.npz`` units, as written before, were 2.4 x larger
than their share of the store on paper-p002). A contiguous unit is cut on the store's chunk
grid: ``head`` (the projections up to the next multiple of the chunk rows), ``data`` (whole
chunks, chunked like the store) and ``tail``; the assembly copies ``data``'s compressed chunks
into the store as they are (``write_direct_chunk``: no second compression, bit-identical) and
writes only head and tail decoded. Other units (sparse index sets, an earlier version's
``.npz``) are decoded and written. So the finished ``.h5`` is never written in place, a SIGKILL at any
instant can only tear the unit being written (a ``.tmp`` file, deleted on the next open) or
the assembly copy (``.partial``, always discarded and rebuilt on the next open), and a
unit damaged later fails its checksum, is dropped with a warning and simulated again. The
``present`` mask of an open store is the file's mask plus the intact units. A ``.h5`` that
cannot be read raises :class:`~clrecon.core.errors.StoreError`. A store whose table no
longer matches what the current code computes for the scene (signal model changed without a
``PROJECTOR_VERSION`` bump) is stale: it is discarded (with its units) with a warning.

Integrity: every dataset carries HDF5 Fletcher-32 chunk checksums, and :meth:`ProjectionStore.read`
refuses NaN or inf line integrals; both raise :class:`~clrecon.core.errors.StoreError` naming the
file (a corrupt store never yields numbers).

Noise is not stored: :meth:`ProjectionStore.read` adds it on the way out (see
:mod:`clrecon.simulation.noise`), so one store serves the noise-free and the noisy reconstructions.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import warnings
from pathlib import Path

import h5py
import numpy as np

from clrecon.core import faults, units
from clrecon.core.cache import default_cache_dir
from clrecon.core.errors import StoreError
from clrecon.core.versions import PROJECTOR_VERSION, __version__
from clrecon.scan.patient_data import redact_scene_dict  # no patient's path in the shared cache
from clrecon.scan.table import ProjectionTable, cached_projection_table
from clrecon.simulation.config import SimulatedScan
from clrecon.simulation.noise import add_noise

FORMAT = "clrecon-projections"
#: Target size of one HDF5 chunk of the projections dataset (bytes).
CHUNK_BYTES = 2 << 20
#: Detector rows per HDF5 chunk of the projections dataset (all rows when the detector has fewer).
ROW_CHUNK = 8
#: HDF5 raw-chunk cache per open file (bytes): holds the chunks a read or a write straddles.
CACHE_BYTES = 64 << 20
_FLOAT_ATOL = 1e-9


def _one_line(e: BaseException) -> str:
    text = str(e).strip().splitlines()
    return f"{type(e).__name__}: {text[0] if text else ''}"


def chunk_shape(shape: tuple) -> tuple:
    """HDF5 chunk of a projections dataset of ``shape`` (n, R, C): (projections, rows, columns).

    :data:`ROW_CHUNK` rows (all of them on a smaller detector) by the largest power of two of
    projections whose chunk stays within :data:`CHUNK_BYTES`: the simulation's units of 256
    projections, which start on multiples of 256, are then whole chunks."""
    n, r, c = (int(x) for x in shape)
    rows = min(ROW_CHUNK, r)
    per = max(1, CHUNK_BYTES // (rows * c * 4))
    return (max(1, min(1 << (per.bit_length() - 1), n)), rows, c)


class ProjectionStore:
    """Noise-free projections of one (scene, pitch), on disk.

    Use :meth:`open` (or :func:`clrecon.simulation.simulate.simulate`, which fills it).

    Attributes
    ----------
    path : Path
        The finished file, ``<cache_dir>/<scan_hash>.h5``.
    partial_path : Path
        The name the file has while being assembled, ``<scan_hash>.h5.partial``.
    units_path : Path
        Folder of the finished, not yet assembled chunks, ``<scan_hash>.h5.units``.
    shape : tuple
        (n, R, C): projections, detector rows, detector columns.
    n_simulated, n_reused : int
        Set by :meth:`missing` and the filler (:func:`~clrecon.simulation.simulate.simulate`, the
        measured-scan import): needed projections it wrote, and needed projections already present.
    simulate_s : float
        Seconds :func:`~clrecon.simulation.simulate.simulate` spent projecting and writing.
    """

    def __init__(self, scene: SimulatedScan, pitch: float, table: ProjectionTable, cache_dir: Path):
        # Use ProjectionStore.open(); the constructor only sets fields.
        self.scene = scene
        self.pitch = float(pitch)
        self.scan_hash = scene.scan_hash(pitch)
        self.cache_dir = Path(cache_dir)
        self.path = self.cache_dir / f"{self.scan_hash}.h5"
        self.partial_path = self.path.with_name(self.path.name + ".partial")
        self.units_path = self.path.with_name(self.path.name + ".units")
        self._units: list[tuple[Path, dict]] = []
        self._table = table
        self.shape = (len(table), scene.scanner.n_rows, scene.scanner.n_cols)
        self._present = np.zeros(len(table), dtype=bool)
        self._state = "absent"  # absent | partial | final
        self._reader = None
        self._writer = None
        self.n_simulated = 0
        self.n_reused = 0
        self.simulate_s = 0.0
        #: unit files written by this process (chunks of projections)
        self.units_written = 0
        #: HDF5 chunks the last assembly copied from the units without decoding them
        self.chunks_copied = 0

    # -- opening -----------------------------------------------------------------------
    @classmethod
    def open(cls, scene: SimulatedScan, pitch: float, cache_dir=None, table: ProjectionTable | None = None,
             create: bool = True) -> ProjectionStore:
        """Open the store of ``(scene, pitch)``, resuming a ``.partial`` file if one was left.

        Parameters
        ----------
        scene, pitch
            The scan. ``pitch`` should be one of ``scene.scan.pitches``.
        cache_dir : path-like, optional
            Folder of the stores; default :func:`default_cache_dir`.
        table : ProjectionTable, optional
            ``projection_table(scene, pitch)`` if already computed.
        create : bool
            If False, a store with no file on disk raises :class:`StoreError`.

        Raises
        ------
        StoreError
            The ``.h5`` file is corrupt, truncated or belongs to another scan, both the
            ``.h5`` and the ``.partial`` exist, or (``create=False``) there is no store.
        """
        cache_dir = Path(cache_dir).expanduser() if cache_dir is not None else default_cache_dir()
        if table is None:
            table = cached_projection_table(scene, pitch)
        store = cls(scene, pitch, table, cache_dir)
        if store.partial_path.exists():
            # an assembly cut short (or a .partial of an older clrecon): rebuilt from the units
            warnings.warn(f"{store.partial_path}: unfinished assembly of an interrupted run; discarded "
                          f"(kept: {store.path.name} and the finished chunks in {store.units_path.name}/)",
                          stacklevel=2)
            store.partial_path.unlink()
        if store.path.exists():
            if not store._load(store.path):
                shutil.rmtree(store.units_path, ignore_errors=True)
        store._scan_units()
        if store.path.exists():
            store._state = "partial" if store._units else "final"
        elif store._units:
            store._state = "partial"
        if store._state == "absent" and not create:
            raise StoreError(f"{store.path}: no projection store for this scan; run simulate first")
        return store

    def _scan_units(self) -> None:
        """Add the intact unit files to ``present`` (damaged ones are dropped by scan_units)."""
        self._units = []
        for p, meta in units.scan_units(self.units_path):
            if meta.get("scan_hash") != self.scan_hash:
                p.unlink()
                continue
            self._units.append((p, meta))
            self._present[np.asarray(meta["indices"], np.int64)] = True

    def _load(self, path: Path) -> bool:
        """Validate ``path`` and read its present mask. False if it was discarded (stale)."""
        try:
            with h5py.File(path, "r") as f:
                if f.attrs.get("format") != FORMAT:
                    raise ValueError(f"not a {FORMAT} file")
                if f.attrs.get("scan_hash") != self.scan_hash:
                    raise ValueError(f"scan hash {f.attrs.get('scan_hash')!r} != {self.scan_hash!r}")
                ds = f["projections"]
                if ds.shape != self.shape or ds.dtype != np.float32:
                    raise ValueError(f"projections are {ds.dtype}{ds.shape}, expected float32{self.shape}")
                present = f["present"][...]
                if present.shape != (self.shape[0],) or present.dtype != bool:
                    raise ValueError(f"present mask is {present.dtype}{present.shape}")
                stored = {c: f["table"][c][...] for c in ProjectionTable.COLUMNS}
        except (OSError, KeyError, ValueError, TypeError, RuntimeError) as e:
            raise StoreError(f"{path}: corrupt or truncated projection store ({_one_line(e)}); "
                             f"delete it to simulate again") from None
        bad = [c for c in ProjectionTable.COLUMNS if not self._column_matches(c, stored[c])]
        if bad:
            warnings.warn(f"{path}: stale projection store (table columns {', '.join(bad)} differ from "
                          f"what this clrecon computes); simulating again", stacklevel=3)
            path.unlink()
            return False
        self._present = present
        return True

    def _column_matches(self, name: str, stored: np.ndarray) -> bool:
        want = getattr(self._table, name)
        if stored.shape != want.shape:
            return False
        if np.issubdtype(want.dtype, np.floating):
            return bool(np.allclose(stored, want, rtol=0.0, atol=_FLOAT_ATOL))
        return bool(np.array_equal(stored, want))

    def _block(self) -> int:
        """Projections per HDF5 chunk, in the store and in its units (:func:`chunk_shape`)."""
        return chunk_shape(self.shape)[0]

    def _chunks(self) -> tuple:
        """Chunk shape of the projections dataset (:func:`chunk_shape`)."""
        return chunk_shape(self.shape)

    def _create(self, path: Path) -> None:
        n = self.shape[0]
        self.cache_dir.mkdir(parents=True, exist_ok=True)
        with h5py.File(path, "w") as f:
            # fletcher32: every chunk carries a checksum, so a corrupted file fails on read
            # (StoreError) instead of returning wrong numbers
            f.create_dataset("projections", shape=self.shape, dtype=np.float32, chunks=self._chunks(),
                             compression="lzf", shuffle=True, fletcher32=True)
            f.create_dataset("present", data=np.zeros(n, dtype=bool), fletcher32=True)
            g = f.create_group("table")
            for col in ProjectionTable.COLUMNS:
                g.create_dataset(col, data=getattr(self._table, col), fletcher32=True)
            f.attrs.update({
                "format": FORMAT, "scan_hash": self.scan_hash, "pitch": self.pitch,
                "scene_json": json.dumps(redact_scene_dict(self.scene.to_dict()), sort_keys=True),
                "clrecon_version": __version__, "projector_version": PROJECTOR_VERSION,
                "views_per_rotation": self._table.views_per_rotation, "complete": False,
            })
        self._present = np.zeros(n, dtype=bool)

    # -- state -------------------------------------------------------------------------
    @property
    def table(self) -> ProjectionTable:
        """The per-projection table of the scan (n rows)."""
        return self._table

    @property
    def present(self) -> np.ndarray:
        """(n,) bool: projections simulated so far (a copy)."""
        return self._present.copy()

    def missing(self, needed: np.ndarray) -> np.ndarray:
        """Indices of the ``needed`` (n,) bool projections not yet present, for a filler to write.

        Sets :attr:`n_reused` (needed and already present) and resets :attr:`n_simulated`
        (the filler counts what it writes): the bookkeeping the simulation and the measured-scan
        import share.
        """
        present = self._present
        self.n_reused = int(np.count_nonzero(needed & present))
        self.n_simulated = 0
        return np.flatnonzero(needed & ~present)

    @property
    def complete(self) -> bool:
        """All n projections present in a finished (not ``.partial``) file."""
        return self._state == "final" and bool(self._present.all())

    @property
    def state(self) -> str:
        """``absent`` (no file), ``partial`` (interrupted or being written) or ``final``."""
        return self._state

    def __len__(self) -> int:
        return self.shape[0]

    def __repr__(self) -> str:
        return (f"ProjectionStore({str(self.path)!r}, state={self._state}, "
                f"present={int(self._present.sum())}/{self.shape[0]})")

    # -- writing -----------------------------------------------------------------------
    @contextlib.contextmanager
    def writing(self):
        """Context in which :meth:`write` may be called; the store is ``partial`` meanwhile.

        Each :meth:`write` is a durable unit file. On normal exit the store is assembled into
        ``<hash>.h5`` (see the module's *Interruption safety*); on an exception (or interrupt,
        or SIGKILL) the finished units stay for the next run to resume, and the error propagates.
        """
        if self._writer is not None:
            raise RuntimeError("already writing")
        self.close()
        self._state = "partial"
        self._writer = True
        try:
            yield self
        finally:
            self._writer = None
        self._assemble()
        self._state = "final"

    def _assemble(self) -> None:
        """Copy the .h5 (or a new file) to .partial, write the units in, fsync, rename, drop the units."""
        if self.path.exists():
            shutil.copyfile(self.path, self.partial_path)
        else:
            self._create(self.partial_path)
        present = np.zeros(self.shape[0], dtype=bool)
        self.chunks_copied = 0
        with h5py.File(self.partial_path, "r+", rdcc_nbytes=CACHE_BYTES) as f:
            ds = f["projections"]
            present |= f["present"][...]
            for p, _ in self._units:
                with units.open_unit(p) as (uf, arrays, _meta):  # checksum checked again: raises if damaged since
                    idx = (uf if uf is not None else arrays)["indices"][()]
                    if uf is not None and "head" in uf:
                        self.chunks_copied += self._copy_aligned(ds, uf, int(idx[0]))
                    else:  # any index set (or an earlier version's .npz unit): decoded and written
                        arr = uf["data"][()] if uf is not None else arrays["data"]
                        breaks = np.flatnonzero(np.diff(idx) != 1) + 1
                        for lo, hi in zip(np.concatenate([[0], breaks]), np.concatenate([breaks, [idx.size]]),
                                          strict=True):
                            ds[idx[lo]:idx[hi - 1] + 1] = arr[lo:hi]
                present[idx] = True
                faults.point("assemble-store")
            f["present"][...] = present
            f.attrs["complete"] = bool(present.all())
        units.fsync_file(self.partial_path)
        faults.point("rename-store")
        os.replace(self.partial_path, self.path)
        units.fsync_dir(self.cache_dir)
        shutil.rmtree(self.units_path, ignore_errors=True)
        self._units = []
        self._present = present

    @staticmethod
    def _copy_aligned(ds: h5py.Dataset, uf: h5py.File, first: int) -> int:
        """A contiguous unit into the store: head and tail rows decoded, the body's chunks copied as they are.

        Returns the number of chunks copied compressed.

        The body starts on a multiple of the store's chunk length (in projections) and is chunked like the store with
        the same filters, so each of its compressed chunks is a whole chunk of the store
        (``write_direct_chunk``): no second compression, bit-identical.
        """
        h, body, tail = len(uf["head"]), uf["data"], uf["tail"]
        if h:
            ds[first:first + h] = uf["head"][()]
        start = first + h
        copied = 0
        if len(body):
            same = (body.chunks == ds.chunks and body.compression == ds.compression == "lzf" and body.shuffle
                    and ds.shuffle and body.fletcher32 and ds.fletcher32)
            n_chunks = body.id.get_num_chunks()
            per_block = int(np.prod([-(-n // k) for n, k in zip(ds.shape[1:], ds.chunks[1:], strict=True)]))
            if same and len(body) % ds.chunks[0] == 0 and n_chunks == len(body) // ds.chunks[0] * per_block:
                for c in range(n_chunks):
                    off = body.id.get_chunk_info(c).chunk_offset
                    mask, raw = body.id.read_direct_chunk(off)
                    ds.id.write_direct_chunk((start + off[0],) + tuple(off[1:]), raw, mask)
                copied = n_chunks
            else:  # another chunking (CHUNK_BYTES changed since the store was made): decoded
                ds[start:start + len(body)] = body[()]
        if len(tail):
            ds[start + len(body):start + len(body) + len(tail)] = tail[()]
        return copied

    def write(self, indices, data) -> None:
        """Store projections ``indices`` (increasing ints, shape (m,)) = ``data`` (m, R, C).

        Only inside :meth:`writing`. One durable, checksummed unit file; ``present`` is set
        once it is renamed into place.
        """
        if self._writer is None:
            raise RuntimeError("ProjectionStore.write outside `with store.writing():`")
        idx = np.asarray(indices, dtype=np.int64)
        arr = np.asarray(data)
        if not np.issubdtype(arr.dtype, np.floating):
            raise TypeError(f"projections must be floating point, got {arr.dtype}")
        if arr.shape != (idx.size,) + self.shape[1:]:
            raise ValueError(f"data has shape {arr.shape}, expected {(idx.size,) + self.shape[1:]}")
        if idx.size == 0:
            return
        if np.any(np.diff(idx) <= 0) or idx[0] < 0 or idx[-1] >= self.shape[0]:
            raise ValueError(f"indices must increase strictly within [0, {self.shape[0]})")
        arr = np.ascontiguousarray(arr, dtype=np.float32)
        meta = {"scan_hash": self.scan_hash, "indices": idx.tolist()}
        block, det = self._block(), tuple(self.shape[1:])
        if idx[-1] - idx[0] + 1 == idx.size:  # contiguous: cut on the store's chunk grid
            h = min(int(-idx[0] % block), idx.size)
            nb = (idx.size - h) // block
            arrays = {"indices": idx, "head": arr[:h], "data": arr[h:h + nb * block], "tail": arr[h + nb * block:]}
            compress = {k: self._chunks() if k == "data" else (max(len(arrays[k]), 1),) + det
                        for k in ("head", "data", "tail")}
        else:
            arrays, compress = {"indices": idx, "data": arr}, {"data": (min(block, idx.size),) + det}
        p = units.write_unit(self.units_path, f"p{idx[0]:09d}-{idx[-1]:09d}", arrays, meta, fault="simulate",
                             compress=compress)
        self._units.append((p, meta))
        self._present[idx] = True
        self.units_written += 1

    # -- reading -----------------------------------------------------------------------
    def read(self, start: int, stop: int, noisy: bool = False) -> np.ndarray:
        """Projections ``start`` to ``stop - 1`` (contiguous), shape (stop - start, R, C), float32.

        ``noisy=True`` adds Poisson + electronic noise from ``scene.noise`` (seeded per
        projection index, so any split of the range gives the same values).

        Raises
        ------
        StoreError
            The store is not finished or some of the projections were not simulated.
        ValueError
            A bad range, or ``noisy=True`` while the scene's noise is disabled.
        """
        n = self.shape[0]
        if not (0 <= start <= stop <= n):
            raise ValueError(f"range [{start}, {stop}) outside [0, {n}]")
        if start == stop:
            if noisy and not self.scene.noise.enabled:
                raise ValueError("noisy=True but the scene's noise.enabled is false")
            return np.zeros((0,) + tuple(self.shape[1:]), np.float32)
        return self.read_indices(np.arange(start, stop, dtype=np.int64), noisy=noisy)

    def read_indices(self, indices, noisy: bool = False, rows: tuple[int, int] | None = None) -> np.ndarray:
        """Projections ``indices`` (sorted, unique), shape (len(indices), R, C), float32.

        For sparse selections (a run that needs only some projections): reads the covering
        range of the file, requires only the selected projections to be present, and keeps
        only those. Same errors and noise as :meth:`read`. ``rows=(lo, hi)`` reads only
        detector rows ``lo .. hi - 1`` (shape (len(indices), hi - lo, C)); their noise is the
        same as those rows of the whole projections' (:func:`clrecon.simulation.noise.add_noise`).
        """
        idx = np.asarray(indices, dtype=np.int64)
        if idx.size == 0:
            return np.zeros((0,) + tuple(self.shape[1:]), np.float32)
        if np.any(np.diff(idx) <= 0):
            raise ValueError("indices must be sorted and unique")
        n = self.shape[0]
        if idx[0] < 0 or idx[-1] >= n:
            raise ValueError(f"indices outside [0, {n})")
        if noisy and not self.scene.noise.enabled:
            raise ValueError("noisy=True but the scene's noise.enabled is false")
        if self._state != "final":
            raise StoreError(f"{self.path}: the store is {self._state}, not finished; run simulate first")
        missing = idx[~self._present[idx]]
        if missing.size:
            raise StoreError(f"{self.path}: projections {missing[0]}..{missing[-1]} "
                             f"({missing.size} of the requested {idx.size}) were not simulated")
        start, stop = int(idx[0]), int(idx[-1]) + 1
        r_lo, r_hi = (0, self.shape[1]) if rows is None else (int(rows[0]), int(rows[1]))
        if not 0 <= r_lo < r_hi <= self.shape[1]:
            raise ValueError(f"rows {rows}: must satisfy 0 <= lo < hi <= {self.shape[1]} detector rows")
        try:
            if self._reader is None:
                self._reader = h5py.File(self.path, "r", rdcc_nbytes=CACHE_BYTES)
            data = self._reader["projections"][start:stop, r_lo:r_hi]
            if idx.size != stop - start:  # sparse selection: keep only the requested projections
                data = data[idx - start]
        except (OSError, KeyError, RuntimeError) as e:
            self.close()
            raise StoreError(f"{self.path}: corrupt or truncated projection store ({_one_line(e)}); "
                             f"delete it to simulate again") from None
        bad = ~np.isfinite(data)
        if bad.any():
            k = idx[np.flatnonzero(bad.any(axis=(1, 2)))]
            raise StoreError(f"{self.path}: projections {k[0]}..{k[-1]} hold {int(bad.sum())} NaN or inf "
                             f"line integrals (corrupt store); delete it to simulate again")
        if noisy:
            data = add_noise(data, idx, self.scene.noise, first_row=r_lo)
        return data

    def close(self) -> None:
        """Close the read handle (reopened on the next :meth:`read`)."""
        if self._reader is not None:
            self._reader.close()
            self._reader = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
