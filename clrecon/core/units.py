"""Unit files: one finished unit of work per file, written atomically and checksummed.

HDF5 has no journal: a process killed in the middle of an HDF5 write can leave the whole
file unreadable. So the pipeline never writes its results into an HDF5 file as it goes:
each finished unit (a chunk of projections, a slab of one reconstruction, one target's
truth) becomes its own small file in a ``<name>.units/`` folder, and the HDF5 file is
assembled from them at the end under a ``.partial`` name and renamed into place.

A unit file is written as ``.<stem>.<pid>.tmp``, flushed and fsync'd, then renamed to
``<stem>.<digest>.unit`` (and the folder fsync'd): a crash leaves either no unit or a
complete one. ``<digest>`` is the BLAKE2b-128 of the file's bytes, so a unit damaged later
(a torn sector, a flipped bit) is detected when read: :func:`scan_units` drops it with a
warning and the unit is computed again.

Payload: the arrays and a JSON ``meta`` dictionary, in one of two formats, told apart by their
first bytes when read (:func:`read_unit` reads both):

- an uncompressed ``.npz`` (``compress=None``; what every unit was before the compressed
  units, so an interrupted run of an earlier version still resumes);
- an HDF5 file image (``compress={array: chunk shape}``): the named arrays chunked and
  compressed with the filters of the file they are assembled into (LZF + byte shuffle, and
  Fletcher-32 for the projection store: :data:`FILTERS`, :data:`VOLUME_FILTERS`), the others
  stored plain; ``meta`` is the root attribute
  ``meta``. The projection units and the volume units are written so (docs/data-flow.md,
  "Disk"): a unit on disk is about the size of its share of the assembled file instead of its
  raw size, and a volume unit's compressed chunks are copied into the assembled file as they
  are (:func:`open_unit`, ``read_direct_chunk`` / ``write_direct_chunk``: no second
  compression).
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import itertools
import json
import os
import warnings
from pathlib import Path

import h5py
import numpy as np

from clrecon.core import faults
from clrecon.core.errors import StoreError

SUFFIX = ".unit"
#: The HDF5 format signature (first 8 bytes of an HDF5 file image).
H5_MAGIC = b"\x89HDF\r\n\x1a\n"
#: The chunk filters of a compressed projection unit and of the projection store: LZF + byte
#: shuffle + Fletcher-32 chunk checksums.
FILTERS = {"compression": "lzf", "shuffle": True, "fletcher32": True}
#: The chunk filters of a compressed volume unit and of the volume dataset files: LZF + byte
#: shuffle, no Fletcher-32 (HDF5's checksum pass costs about as much as the decompression when
#: the volumes are read, measured on float16 512 x 512 slices; the units carry their BLAKE2b).
VOLUME_FILTERS = {"compression": "lzf", "shuffle": True}
_image_names = itertools.count()


def _digest(data: bytes) -> str:
    return hashlib.blake2b(data, digest_size=16).hexdigest()


def fsync_dir(path: Path) -> None:
    """fsync a folder, so that a rename in it survives a power cut (no-op where unsupported)."""
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def h5_image(arrays: dict, meta: dict, compress: dict, filters: dict | None = None) -> bytes:
    """The bytes of an in-memory HDF5 file holding ``arrays`` (``compress``: name -> chunk shape).

    ``filters``: the HDF5 filters of the compressed arrays (default :data:`FILTERS`).
    """
    filters = FILTERS if filters is None else filters
    f = h5py.File(f"clrecon-unit-{os.getpid()}-{next(_image_names)}", "w", driver="core", backing_store=False,
                  libver="latest")
    try:
        f.attrs["meta"] = json.dumps(meta, sort_keys=True)
        for k, a in arrays.items():
            a = np.asarray(a)
            if k in compress and a.size:
                f.create_dataset(k, data=a, chunks=tuple(int(c) for c in compress[k]), **filters)
            else:
                f.create_dataset(k, data=a)
        f.flush()
        return f.id.get_file_image()
    finally:
        f.close()


def write_unit(folder: Path, stem: str, arrays: dict, meta: dict, fault: str, compress: dict | None = None,
               filters: dict | None = None) -> Path:
    """Write one unit atomically; returns its final path. ``fault`` names its :mod:`faults` point.

    ``compress``: ``{array name: chunk shape}``, the unit is then an HDF5 image with those arrays
    compressed with ``filters`` (default :data:`FILTERS`; module docstring); None: an uncompressed ``.npz``.
    """
    if compress is not None:
        data = h5_image(arrays, meta, compress, filters)
    else:
        buf = io.BytesIO()
        np.savez(buf, meta=np.frombuffer(json.dumps(meta, sort_keys=True).encode(), np.uint8), **arrays)
        data = buf.getvalue()
    folder.mkdir(parents=True, exist_ok=True)
    tmp = folder / f".{stem}.{os.getpid()}.tmp"
    with open(tmp, "wb") as f:
        half = len(data) // 2
        view = memoryview(data)  # the halves written without copies of the image
        f.write(view[:half])
        f.flush()
        faults.point(fault)  # test hook: a SIGKILL in the middle of the write
        f.write(view[half:])
        f.flush()
        os.fsync(f.fileno())
    final = folder / f"{stem}.{_digest(data)}{SUFFIX}"
    os.replace(tmp, final)
    fsync_dir(folder)
    return final


def _checked_bytes(path: Path) -> bytes:
    data = Path(path).read_bytes()
    want = Path(path).name[:-len(SUFFIX)].rsplit(".", 1)[-1]
    if _digest(data) != want:  # StoreError is an OSError: scan_units drops it; elsewhere one line
        raise StoreError(f"{path}: checksum mismatch (damaged unit file); run again: it is computed again")
    return data


@contextlib.contextmanager
def open_unit(path: Path):
    """``(h5py.File or None, arrays or None, meta)`` of a unit whose checksum is checked.

    An HDF5 unit is given open (read-only, in memory), for reading its arrays lazily or copying
    its compressed chunks; an ``.npz`` unit (an earlier version's) as its arrays.
    """
    data = _checked_bytes(path)
    if data[:8] == H5_MAGIC:
        with h5py.File(io.BytesIO(data), "r") as f:
            yield f, None, json.loads(f.attrs["meta"])
    else:
        arrays, meta = _npz(data)
        yield None, arrays, meta


def _npz(data: bytes) -> tuple[dict, dict]:
    with np.load(io.BytesIO(data), allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files if k != "meta"}
        meta = json.loads(z["meta"].tobytes().decode())
    return arrays, meta


def read_unit(path: Path) -> tuple[dict, dict]:
    """(arrays, meta) of a unit file (either format); ValueError if its checksum does not match its name."""
    data = _checked_bytes(path)
    if data[:8] == H5_MAGIC:
        with h5py.File(io.BytesIO(data), "r") as f:
            return {k: f[k][()] for k in f.keys()}, json.loads(f.attrs["meta"])
    return _npz(data)


def read_meta(path: Path) -> dict:
    """The ``meta`` of a unit file, its checksum checked (the arrays are not decompressed)."""
    data = _checked_bytes(path)
    if data[:8] == H5_MAGIC:
        with h5py.File(io.BytesIO(data), "r") as f:
            return json.loads(f.attrs["meta"])
    return _npz(data)[1]


def scan_units(folder: Path) -> list[tuple[Path, dict]]:
    """(path, meta) of every intact unit in ``folder``, sorted by name.

    Removes leftover temporary files (units whose write was interrupted) and damaged units
    (checksum mismatch, unreadable), the latter with a warning: they are computed again.
    """
    out = []
    if not folder.is_dir():
        return out
    for p in sorted(folder.iterdir()):
        if p.name.endswith(".tmp"):
            p.unlink(missing_ok=True)
            continue
        if not p.name.endswith(SUFFIX):
            continue
        try:
            meta = read_meta(p)
        except (OSError, ValueError, KeyError, EOFError) as e:
            warnings.warn(f"{p}: damaged unit file ({str(e).splitlines()[0] if str(e) else type(e).__name__}); "
                          f"it is computed again", stacklevel=2)
            p.unlink(missing_ok=True)
            continue
        out.append((p, meta))
    return out


def write_json_atomic(path: Path, obj) -> None:
    """Write a small JSON file under a temporary name, fsync, rename."""
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        with open(tmp, "w") as f:
            json.dump(obj, f, sort_keys=True, allow_nan=False)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:  # a full disk or a signal: no torn temporary file left behind
        tmp.unlink(missing_ok=True)
        raise
    fsync_dir(path.parent)


def fsync_file(path: Path) -> None:
    with open(path, "rb+") as f:
        os.fsync(f.fileno())
