"""What a run uses of the machine: this process's peak memory, a folder's bytes, spawned worker processes."""

from __future__ import annotations

import resource
import sys
from pathlib import Path


def peak_rss_bytes() -> int:
    """This process's peak resident set so far (bytes; ``ru_maxrss`` is KiB on Linux, bytes on macOS)."""
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return int(rss if sys.platform == "darwin" else rss * 1024)


def folder_bytes(path) -> int:
    """Bytes of the files under ``path`` (0 if it is not a folder)."""
    p = Path(path)
    if not p.is_dir():
        return 0
    return sum(f.stat().st_size for f in p.rglob("*") if f.is_file())


def spawn_is_safe() -> bool:
    """Whether a spawned child process can start without running the caller's script again.

    A spawned child imports the main module; a user's script that calls ``clrecon.run`` without
    an ``if __name__ == "__main__":`` guard would then run its whole run again in the child. So
    the automatic choices (the metrics' second process, the figures' second process) use a
    process only under ``python -m clrecon`` or where there is no main script (an interactive
    session, a notebook); their environment variables force it.
    """
    main = sys.modules.get("__main__")
    spec = getattr(main, "__spec__", None)
    return getattr(spec, "name", None) == "clrecon.__main__" or not getattr(main, "__file__", None)


def spawned_pool(n: int):
    """A process pool of ``n`` spawned workers, or None where one cannot start.

    Spawn, not fork: the caller holds OpenCL and HDF5 state and PoCL's threads. Used by the
    metrics' second process, the figure process and the plans made ahead; whether a child is
    safe to start at all is :func:`spawn_is_safe`'s question, asked by each caller.
    """
    try:
        import multiprocessing
        from concurrent.futures import ProcessPoolExecutor

        return ProcessPoolExecutor(n, mp_context=multiprocessing.get_context("spawn"))
    except (OSError, ValueError, ImportError):
        return None
