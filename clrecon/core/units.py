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
warning and the unit is computed again. The payload is an uncompressed ``.npz`` (the arrays
and a JSON ``meta`` dictionary).
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import warnings
from pathlib import Path

import numpy as np

from clrecon.core import faults
from clrecon.core.errors import StoreError

SUFFIX = ".unit"


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


def write_unit(folder: Path, stem: str, arrays: dict, meta: dict, fault: str) -> Path:
    """Write one unit atomically; returns its final path. ``fault`` names its :mod:`faults` point."""
    buf = io.BytesIO()
    np.savez(buf, meta=np.frombuffer(json.dumps(meta, sort_keys=True).encode(), np.uint8), **arrays)
    data = buf.getvalue()
    folder.mkdir(parents=True, exist_ok=True)
    tmp = folder / f".{stem}.{os.getpid()}.tmp"
    with open(tmp, "wb") as f:
        half = len(data) // 2
        f.write(data[:half])
        f.flush()
        faults.point(fault)  # test hook: a SIGKILL in the middle of the write
        f.write(data[half:])
        f.flush()
        os.fsync(f.fileno())
    final = folder / f"{stem}.{_digest(data)}{SUFFIX}"
    os.replace(tmp, final)
    fsync_dir(folder)
    return final


def read_unit(path: Path) -> tuple[dict, dict]:
    """(arrays, meta) of a unit file; ValueError if its checksum does not match its name."""
    data = Path(path).read_bytes()
    want = Path(path).name[:-len(SUFFIX)].rsplit(".", 1)[-1]
    if _digest(data) != want:  # StoreError is an OSError: scan_units drops it; elsewhere one line
        raise StoreError(f"{path}: checksum mismatch (damaged unit file); run again: it is computed again")
    with np.load(io.BytesIO(data), allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files if k != "meta"}
        meta = json.loads(z["meta"].tobytes().decode())
    return arrays, meta


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
            _, meta = read_unit(p)
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
    with open(tmp, "w") as f:
        json.dump(obj, f, sort_keys=True)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)
    fsync_dir(path.parent)


def fsync_file(path: Path) -> None:
    with open(path, "rb+") as f:
        os.fsync(f.fileno())
