"""Files that appear whole or not at all: written under a temporary name beside the final one, then renamed.

Every output a user opens by name -- ``results.json``, ``report.md``/``report.html``, the
figures, sweep tables, export indexes -- goes through here. The bytes are written to
``<name>.partial`` in the same folder (same file system, so the rename is atomic), flushed and
``fsync``-ed, then ``os.replace``-d onto the final name. A failure on the way (disk full, a
signal, an exception in the code that makes the bytes) removes the temporary file and leaves
the final name as it was: absent, or the previous complete version. A SIGKILL can leave only
a ``.partial`` file, never a torn file under the final name (docs/run-directory.md "Resumability").

The fault point ``write:<file name>`` (:mod:`clrecon.core.faults`) sits half-way through the
bytes of every write, so tests inject a full disk or a kill there.
"""

from __future__ import annotations

import contextlib
import io
import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from clrecon.core import faults, jsonio

SUFFIX = ".partial"


def partial_path(path: Path, keep_suffix: bool | str = False) -> Path:
    """The temporary name of ``path``: ``name.partial``, or ``stem.partial.ext`` for writers that
    infer the format from the extension (``keep_suffix``: True keeps the last extension, a string
    such as ``".nii.gz"`` that whole ending)."""
    path = Path(path)
    ending = keep_suffix if isinstance(keep_suffix, str) else (path.suffix if keep_suffix else "")
    if ending and path.name.endswith(ending) and len(path.name) > len(ending):
        return path.with_name(path.name[:-len(ending)] + SUFFIX + ending)
    return path.with_name(path.name + SUFFIX)


def _fsync_dir(folder: Path) -> None:
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:  # pragma: no cover - a platform without directory handles
        return
    try:
        os.fsync(fd)
    except OSError:  # pragma: no cover - some file systems refuse fsync on a directory
        pass
    finally:
        os.close(fd)


def stage_bytes(path, data: bytes) -> Path:
    """Write ``data`` whole under ``path``'s temporary name (:func:`partial_path`), flushed and
    ``fsync``-ed, and leave it there for :func:`commit`: for a file that must not appear under its
    name before another one is whole (a run's report before its ``results.json``). Returns the
    temporary path; a failure on the way removes it."""
    path = Path(path)
    tmp = partial_path(path)
    try:
        with open(tmp, "wb") as f:
            half = len(data) // 2
            f.write(data[:half])
            faults.point(f"write:{path.name}", str(path))
            f.write(data[half:])
            f.flush()
            os.fsync(f.fileno())
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return tmp


def commit(path) -> Path:
    """Rename the file :func:`stage_bytes` left for ``path`` onto ``path``; returns ``path``."""
    path = Path(path)
    os.replace(partial_path(path), path)
    _fsync_dir(path.parent)
    return path


def discard(path) -> None:
    """Remove what :func:`stage_bytes` left for ``path`` (nothing if there is none)."""
    partial_path(Path(path)).unlink(missing_ok=True)


def write_bytes(path, data: bytes) -> Path:
    """Write ``data`` to ``path`` whole or not at all; returns ``path``."""
    path = Path(path)
    stage_bytes(path, data)
    try:
        os.replace(partial_path(path), path)
    except BaseException:
        discard(path)
        raise
    _fsync_dir(path.parent)
    return path


def write_text(path, text: str, staged: bool = False) -> Path:
    """:func:`write_bytes` of ``text`` in UTF-8; ``staged``: :func:`stage_bytes` instead (returns the
    temporary path, for :func:`commit`)."""
    return (stage_bytes if staged else write_bytes)(path, text.encode("utf-8"))


def write_json(path, obj: Any, **kw) -> Path:
    """Strict JSON (:mod:`clrecon.core.jsonio`: non-finite values as null with their reason), whole or not at all."""
    return write_text(path, jsonio.dumps(obj, **kw))


def save_figure(fig, path, **savefig_kw) -> Path:
    """A matplotlib figure as a file, whole or not at all (rendered in memory, then :func:`write_bytes`)."""
    path = Path(path)
    buf = io.BytesIO()
    fig.savefig(buf, format=savefig_kw.pop("format", path.suffix.lstrip(".") or "png"), **savefig_kw)
    return write_bytes(path, buf.getvalue())


@contextlib.contextmanager
def replacing(path, keep_suffix: bool | str = False) -> Iterator[Path]:
    """For writers that need a file name (nibabel, a CSV writer, a renderer): yields the temporary
    path; when the block ends without error the file replaces ``path``, else it is removed.

    ``keep_suffix``: the temporary name keeps the extension (:func:`partial_path`) for writers that
    pick the format from it."""
    path = Path(path)
    tmp = partial_path(path, keep_suffix)
    try:
        yield tmp
        faults.point(f"write:{path.name}", str(path))
        with open(tmp, "rb+") as f:
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    _fsync_dir(path.parent)
