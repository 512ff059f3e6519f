"""What a run uses of the machine: this process's peak memory, a folder's bytes, spawned worker processes."""

from __future__ import annotations

import math
import os
import resource
import sys
import threading
import time
from pathlib import Path


def peak_rss_bytes() -> int:
    """This process's peak resident set so far (bytes; ``ru_maxrss`` is KiB on Linux, bytes on macOS)."""
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return int(rss if sys.platform == "darwin" else rss * 1024)


def peak_child_rss_bytes() -> int:
    """The largest peak resident set of this process's children that have ended and been waited for
    (bytes; ``RUSAGE_CHILDREN``: the largest one, not a sum; a child still running is not in it)."""
    rss = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    return int(rss if sys.platform == "darwin" else rss * 1024)


def rss_bytes() -> int:
    """This process's resident set now (bytes; ``VmRSS`` of ``/proc/self/status``), or its peak so far
    (:func:`peak_rss_bytes`) where ``/proc`` has none."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return peak_rss_bytes()


#: Binary units above bytes, for :func:`format_bytes`.
BYTE_UNITS = ("KiB", "MiB", "GiB", "TiB", "PiB", "EiB")


def format_bytes(n: float) -> str:
    """``n`` bytes with the binary unit that shows it in 3 significant figures: ``0 B``, ``1000 B``,
    ``1.50 KiB``, ``900 KiB``, ``64.0 GiB`` (1000-1023 of a unit keep their 4 digits: ``1023 KiB``)."""
    v = float(n)
    if not math.isfinite(v) or abs(v) < 1024:
        return f"{v:.0f} B"
    unit = BYTE_UNITS[0]
    for unit in BYTE_UNITS:  # noqa: B007 - the unit the loop stops at is the one shown
        v /= 1024
        if abs(v) < 1024:
            break
    text = f"{v:.0f}" if abs(v) >= 999.5 else f"{v:#.3g}".rstrip(".")
    return f"{text} {unit}"


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


#: Seconds between a pool worker's checks that the process that spawned it is still there.
PARENT_CHECK_S = 0.5


def _release_semaphores(names) -> None:
    """Unlink the named semaphores ``names`` of a pool whose parent is gone and tell the resource tracker.

    A spawned pool's queues hold named POSIX semaphores, registered with Python's resource tracker
    (a process of its own). When the run is killed (kill -9, the OOM killer) nobody closes them: the
    tracker unlinks them once the last worker has ended and prints "There appear to be N leaked
    semaphore objects to clean up at shutdown", which was the terminal's last line after a kill. The
    worker that unlinks a name first unregisters it (the others find it gone: a name unregistered
    twice would make the tracker print a KeyError), so the tracker has nothing left to report."""
    try:
        from _multiprocessing import sem_unlink
        from multiprocessing import resource_tracker
    except ImportError:  # pragma: no cover - a platform without named semaphores
        return
    for name in names:
        try:
            sem_unlink(name)
        except OSError:  # another worker was first, or the name was never made
            continue
        try:
            resource_tracker.unregister(name, "semaphore")
        except Exception:  # noqa: BLE001 - best effort on the way out; the tracker then unlinks nothing
            pass


def _release_own_semaphores() -> None:
    """Run this process's multiprocessing at-exit finalizers (exit priority >= 0), as a normal exit would.

    A spawned worker runs with the spawn start method as its default, so a ``multiprocessing``
    lock made in it without a context (tqdm's write lock, made by the first progress counter)
    is a named semaphore registered with the resource tracker; its finalizer unlinks it at a
    normal exit, which ``os._exit`` skips: the tracker then reports it leaked. This is the
    first step of multiprocessing's own exit handler (``util._exit_function``)."""
    try:
        from multiprocessing import util
        run_finalizers = util._run_finalizers
    except (ImportError, AttributeError):  # pragma: no cover - a Python without it
        return
    try:
        run_finalizers(0)
    except Exception:  # noqa: BLE001 - best effort on the way out
        pass


def _watch_parent(parent_pid: int, semaphores=()) -> None:
    """Pool worker initializer: a daemon thread that ends this worker once its parent is gone.

    A worker blocks on its task queue and does not notice that the run which spawned it was
    killed (SIGKILL, or the OOM killer): it would live on, an orphan holding the run's stdout
    and stderr open, so that whatever waits for the run's output (a shell pipe, a batch
    system, a test) waited for ever. So each worker checks its parent's pid every
    :data:`PARENT_CHECK_S` and exits when it has changed, releasing the pool's named
    ``semaphores`` first (:func:`_release_semaphores`) and those it made itself
    (:func:`_release_own_semaphores`)."""
    def watch():
        while os.getppid() == parent_pid:
            time.sleep(PARENT_CHECK_S)
        _release_semaphores(semaphores)
        _release_own_semaphores()
        os._exit(0)

    threading.Thread(target=watch, name="clrecon-parent-watch", daemon=True).start()


def pool_semaphore_names(pool) -> list[str]:
    """The names of the named POSIX semaphores of ``pool``'s queues (a ``ProcessPoolExecutor`` of a
    spawn context: its call queue's and result queue's locks), as the resource tracker knows them."""
    from multiprocessing.synchronize import SemLock

    names = []
    for q in (getattr(pool, "_call_queue", None), getattr(pool, "_result_queue", None)):
        for v in (vars(q).values() if q is not None else ()):
            name = getattr(getattr(v, "_semlock", None), "name", None) if isinstance(v, SemLock) else None
            if name:
                names.append(name)
    return names


def spawned_pool(n: int):
    """A process pool of ``n`` spawned workers, or None where one cannot start.

    Spawn, not fork: the caller holds OpenCL and HDF5 state and PoCL's threads. Used by the
    run's helper process (the plans made ahead, the metrics' second group, the figures);
    whether a child is safe to start at all is :func:`spawn_is_safe`'s question, asked by each
    caller. Each worker ends itself when this process dies (:func:`_watch_parent`), and releases
    the pool's named semaphores and its own then, so that a kill -9 leaves none for the resource tracker.
    """
    try:
        import multiprocessing
        from concurrent.futures import ProcessPoolExecutor

        names: list[str] = []  # filled below: the workers are spawned (and their arguments pickled) on submit
        pool = ProcessPoolExecutor(n, mp_context=multiprocessing.get_context("spawn"),
                                   initializer=_watch_parent, initargs=(os.getpid(), names))
        names.extend(pool_semaphore_names(pool))
        return pool
    except (OSError, ValueError, ImportError):
        return None


#: Environment variable: set to a file path, :func:`rss_mark` appends one line per call to it
#: (a debug aid for locating a run's memory peak; unset: :func:`rss_mark` does nothing).
RSS_TRACE_ENV = "CLRECON_RSS_TRACE"
#: Seconds between the trace's samples of this process's resident set.
RSS_TRACE_INTERVAL_S = 0.05


def _rss_now() -> tuple[int, int]:
    """(this process's resident bytes, the resident bytes of its live descendants) from ``/proc``."""
    def rss(pid) -> int:
        try:
            with open(f"/proc/{pid}/status") as f:
                for line in f:
                    if line.startswith("VmRSS:"):
                        return int(line.split()[1]) * 1024
        except OSError:
            pass
        return 0

    def children(pid) -> list[int]:
        out = []
        try:
            for t in os.listdir(f"/proc/{pid}/task"):
                with open(f"/proc/{pid}/task/{t}/children") as f:
                    out += [int(c) for c in f.read().split()]
        except OSError:
            pass
        return out + [g for c in out for g in children(c)]

    return rss("self"), sum(rss(c) for c in children(os.getpid()))


class _RssTrace:
    """A daemon thread sampling :func:`_rss_now` every :data:`RSS_TRACE_INTERVAL_S`, keeping the
    largest samples since the last :meth:`mark`."""

    def __init__(self, path: str):
        self.path, self.t0 = path, time.perf_counter()
        self.lock = threading.Lock()
        self.peak = self.peak_total = 0
        threading.Thread(target=self._run, name="clrecon-rss-trace", daemon=True).start()

    def _run(self) -> None:
        while True:
            own, kids = _rss_now()
            with self.lock:
                self.peak, self.peak_total = max(self.peak, own), max(self.peak_total, own + kids)
            time.sleep(RSS_TRACE_INTERVAL_S)

    def mark(self, label: str) -> None:
        own, kids = _rss_now()
        with self.lock:
            peak, total = max(self.peak, own), max(self.peak_total, own + kids)
            self.peak = self.peak_total = 0
        with open(self.path, "a") as f:
            f.write(f"{time.perf_counter() - self.t0:9.2f} s  rss {own / 1e9:7.3f} GB  children {kids / 1e9:6.3f} GB"
                    f"  peak since last mark {peak / 1e9:7.3f} GB (with children {total / 1e9:7.3f})  {label}\n")


_trace: _RssTrace | None = None


def rss_mark(label: str) -> None:
    """Debug aid: with ``CLRECON_RSS_TRACE=<file>`` set, append to that file this process's resident
    set now, its descendants', and the largest sampled since the previous mark, then ``label``
    (what the process did since that mark). Costs nothing when the variable is unset."""
    global _trace
    path = os.environ.get(RSS_TRACE_ENV)
    if not path:
        return
    if _trace is None:
        _trace = _RssTrace(path)
    _trace.mark(label)
