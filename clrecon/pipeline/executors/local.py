"""``--executor local`` (the default): the graph overlapped on this machine's cores.

The same walk as the serial executor (:mod:`clrecon.pipeline.executors.base`), with four
things done beside it; each computes the same functions on the same inputs, so the run is
the same bit for bit (tests/pipeline/test_executors.py):

- **a helper process** (one spawned worker for the whole run, its imports warm by the time
  they are needed): the nodes a stage offers to compute ahead (``Stage.ahead``: the later
  pitches' plans, made while this process plans the first), the metrics' second group of
  accumulators and the report's figures drawn from ``results`` alone. A spawned child first
  imports NumPy, SciPy, h5py, PyOpenCL and matplotlib (1-2 s of CPU), so one warm child serves
  all three. Started only where a child cannot run the caller's script again
  (:func:`clrecon.core.resources.spawn_is_safe`) and the machine has two or more cores;
- **a writer thread** (:class:`clrecon.core.write_behind.WriteBehind`): each piece a unit makes
  (a slab's volumes, a block's projections) is compressed and written while the next is made
  (h5py releases the GIL while it compresses); one write in flight, in order, each unit file
  atomic as before;
- **a thread beside the run** for a stage that declares ``Stage.beside`` (the truths: they
  depend on the phantom, never on the projections), started once the first node of the named
  stage is done (while the reconstruction often keeps only one core busy), with an OpenCL
  runtime of its own (a kernel object's arguments are not safe to set from two threads). Its
  error is raised in the run's thread before the next unit; an error in the run stops it after
  its current piece. The run waits for it only where a stage needs its product.

Timing: the run's waits are the parts' ``seconds``; the helper's and the threads' own time
their ``beside_seconds``.
"""

from __future__ import annotations

import contextlib
import os
import threading
import time

from clrecon.core import write_behind
from clrecon.core.progress import progress as progress_counter
from clrecon.core.resources import spawn_is_safe, spawned_pool
from clrecon.core.runtime import Runtime, thread_runtime
from clrecon.core.stage_times import StageTimes
from clrecon.outputs import figures
from clrecon.pipeline import evaluate  # noqa: F401 - imported in the helper by unpickling _warm
from clrecon.pipeline.executors.base import Executor, Work, book_times

#: Seconds between the run's checks on a thread beside it while it waits for it.
POLL_S = 0.2


def helper_wanted() -> bool:
    """Whether an overlapping run starts its helper process here (module docstring)."""
    return (os.cpu_count() or 1) >= 2 and spawn_is_safe()


def _warm() -> int:
    """In the helper: import what the metrics and the figures need (this module's imports, and
    matplotlib's pyplot, which the figures load on first use); returns the helper's pid."""
    figures._plt()
    return os.getpid()


def _timed(fn, *args):
    """In the helper: ``fn(*args)`` and its own seconds."""
    t0 = time.perf_counter()
    out = fn(*args)
    return out, time.perf_counter() - t0


class _Stopped(Exception):
    """Raised in a thread beside the run to end it after its current piece."""


class _Beside:
    """A node's work running in a thread of its own, beside the run."""

    def __init__(self, node, work: Work, device_spec: str | None):
        self.node, self.work, self.device_spec = node, work, device_spec
        self.times = StageTimes()
        self.pieces = 0
        self.error: BaseException | None = None
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._run, name=f"clrecon-{node[0].name}", daemon=True)
        self.thread.start()

    def _emit(self, piece) -> None:
        self.work.write(piece)
        self.pieces += self.work.weight(piece)
        if self.stop.is_set():
            raise _Stopped

    def _run(self) -> None:
        try:
            with thread_runtime(Runtime(self.device_spec)):
                for unit in self.work.units:
                    unit.local(self._emit, self.times)
                    if self.stop.is_set():
                        return
        except _Stopped:
            pass
        except BaseException as e:  # noqa: BLE001 - handed to the run's thread, raised there
            self.error = e


class LocalExecutor(Executor):
    """The graph overlapped on this machine (module docstring).

    ``helper``: start the helper process (None: where :func:`helper_wanted`); ``beside``: run
    the stages that declare it in a thread beside the run (False: in the walk, in order);
    ``write_behind``: write pieces in the writer thread. ``device_spec``: the beside threads'
    OpenCL device (``CLRECON_DEVICE`` form; None: the default).
    """

    kind = "local"

    def __init__(self, helper: bool | None = None, beside: bool = True, write_behind: bool = True,
                 device_spec: str | None = None):
        super().__init__()
        self.want_helper = helper_wanted() if helper is None else bool(helper)
        self.want_beside, self.want_write_behind = bool(beside), bool(write_behind)
        self.device_spec = device_spec
        self.ahead: dict = {}
        self.beside_jobs: dict = {}

    @contextlib.contextmanager
    def session(self, run):
        self.pool = spawned_pool(1) if self.want_helper else None
        self.writer = write_behind.WriteBehind(background=self.want_write_behind)
        try:
            self._send_ahead(run)
            if self.pool is not None:
                try:
                    self.pool.submit(_warm)  # queued behind the work sent ahead
                except RuntimeError:  # the pool broke: every part runs here
                    self._close_pool()
            yield
        except BaseException:
            for job in self.beside_jobs.values():
                job.stop.set()
            for job in self.beside_jobs.values():
                job.thread.join()
            raise
        finally:
            self.writer.close()  # the piece in flight finished (it is atomic either way)
            for fut in self.ahead.values():
                fut.cancel()
            self._close_pool()

    def _close_pool(self) -> None:
        if self.pool is not None:
            self.pool.shutdown(wait=True, cancel_futures=True)
            self.pool = None
            self.run_ctx.pool = None

    def _send_ahead(self, run) -> None:
        """Send the nodes a stage offers to compute ahead (every pitch's but the first) to the helper."""
        if self.pool is None:
            return
        for st, pitch in self.nodes:
            if st.ahead is None or pitch is None or pitch == run.pitches[0]:
                continue
            call = st.ahead(run, pitch)
            if call is not None:
                try:
                    self.ahead[(st, pitch)] = self.pool.submit(_timed, call[0], *call[1])
                except RuntimeError:  # the pool broke while starting: the walk makes them itself
                    return

    def take_ahead(self, node):
        fut = self.ahead.pop(node, None)
        if fut is None:
            return None
        try:
            out, own = fut.result()
        except Exception:  # noqa: BLE001 - the helper died or failed: the node is made here
            return None
        self.clock.beside(node[0].rest or node[0].parts[0], own)
        return out

    # ---- beside
    def startable(self, node) -> bool:
        return node not in self.beside_jobs and super().startable(node)

    def start(self, node) -> None:
        super().start(node)
        if not self.want_beside:
            return
        for other in list(self.todo):
            st = other[0]
            if st.beside == node[0].name and self.ready(other) and not (st.skip and st.skip(self.run_ctx)):
                self.todo.remove(other)
                out = st.fn(self.run_ctx, other[1], **self.inputs(other))
                if isinstance(out, Work):
                    self.beside_jobs[other] = _Beside(other, out, self.device_spec)
                else:
                    self.done[other] = out

    def check(self) -> None:
        for job in self.beside_jobs.values():
            if job.error is not None:
                raise job.error

    def wait(self) -> None:
        """Wait for the threads beside the run (the walk needs one's product), with a progress counter."""
        if not self.beside_jobs:
            super().wait()
        for node, job in list(self.beside_jobs.items()):
            self._finish_beside(node, job)

    def wait_all(self) -> None:
        for node, job in list(self.beside_jobs.items()):
            self._finish_beside(node, job)

    def _finish_beside(self, node, job: _Beside) -> None:
        st = node[0]
        t0 = time.perf_counter()
        total = job.work.progress[1] if job.work.progress else 0
        left = total - job.pieces
        bar = None
        if job.thread.is_alive() and left > 0 and job.work.progress:
            bar = progress_counter(left, job.work.progress[0], self.run_ctx.progress, job.work.progress[2])
        seen = job.pieces
        while job.thread.is_alive():
            job.thread.join(POLL_S)
            if bar is not None and job.pieces > seen:
                bar.update(job.pieces - seen)
                seen = job.pieces
        if bar is not None:
            bar.close()
        del self.beside_jobs[node]
        if job.error is not None:
            job.work.abort(job.error)
            raise job.error
        self.clock.add(st.parts[0], time.perf_counter() - t0)
        book_times(self.clock, job.times, beside=True)
        self.done[node] = job.work.finish(job.times)
