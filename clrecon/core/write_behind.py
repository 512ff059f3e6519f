"""Unit files written behind the work that makes them, in one writer thread.

Used by the local executor (:mod:`clrecon.pipeline.executors.local`) for the pieces a run's
units make (a slab's volumes, below; a block's projections, two blocks of at most
``BLOCK_BYTES`` then held), and by :func:`clrecon.simulation.simulate.simulate` on its own.

Writing a finished (variant, method) slab is a single-core job: its float32 HU images are
converted to ``recon.volume_dtype``, compressed (LZF + shuffle, one chunk per slice), hashed
(BLAKE2b) and written and fsync'd as one unit file (:mod:`clrecon.core.units`); written in line,
the backprojector, which keeps both cores busy, would wait for it. h5py releases the GIL while
it compresses, so the unit can be written while the next method's slab is interpolated and
backprojected (the figures on paper-p010: docs/results/code-history.md "Writing volume units behind the work").

One write is in flight at a time: :meth:`WriteBehind.submit` first waits for the previous one,
so at most one finished slab is held beside the one being reconstructed. The executors convert
it to the volume dtype in the run's thread before submitting it
(:class:`clrecon.pipeline.executors.base.Work` ``prepare``), so what the thread holds is that
copy and its compressed image, not the float32 images; the slab rule counts both
(:func:`clrecon.reconstruction.reconstruct.slab_bytes_per_slice`). The writes run in submission
order, each unit is atomic as before, and the writer's done mask is set only after a unit is on
disk: a SIGKILL at any instant loses at most the slabs not yet written, which a resumed run
reconstructs again. The units hold the same values as written in the foreground (same arrays,
same filters; not always the same bytes: h5py's LZF leaves liblzf's hash table uninitialised, so
its output, though always decoded to the same values, can differ between two writes of the same
array). An error in the thread is raised again in the run's thread at the next :meth:`submit` or
at :meth:`drain`.

``WriteBehind(background=False)`` writes in the caller's thread (the same files; the serial
executor, :mod:`clrecon.pipeline.executors.base`, and the A/B benchmarks use it).
"""

from __future__ import annotations

import time
from concurrent.futures import Future, ThreadPoolExecutor


class WriteBehind:
    """Runs ``fn(*args)`` calls in order in one thread, one in flight; see the module docstring.

    ``wait_seconds``: the run's time spent waiting for the thread (stage ``write_volumes``);
    ``beside_seconds``: the thread's own time in the calls. With ``background=False`` each call
    runs at once in the caller's thread (both times then the call's).
    """

    def __init__(self, background: bool = True):
        self.background = bool(background)
        self._pool = ThreadPoolExecutor(1, thread_name_prefix="clrecon-write") if self.background else None
        self._pending: Future | None = None
        self.wait_seconds = 0.0
        self.beside_seconds = 0.0

    def _timed(self, fn, args) -> None:
        t0 = time.perf_counter()
        try:
            fn(*args)
        finally:
            # one writer at a time (the thread, or the caller in foreground mode); read after a wait
            self.beside_seconds += time.perf_counter() - t0

    def submit(self, fn, *args) -> None:
        """Run ``fn(*args)`` after the previous call (waiting for that one first); errors of the
        previous call are raised here."""
        if self._pool is None:
            t0 = time.perf_counter()
            self._timed(fn, args)
            self.wait_seconds += time.perf_counter() - t0
            return
        self._wait()
        self._pending = self._pool.submit(self._timed, fn, args)

    def _wait(self) -> None:
        if self._pending is None:
            return
        t0 = time.perf_counter()
        try:
            self._pending.result()
        finally:
            self._pending = None
            self.wait_seconds += time.perf_counter() - t0

    def drain(self) -> None:
        """Wait until every submitted call has finished; raise the error of the last one, if any."""
        self._wait()

    def close(self) -> None:
        """Finish the call in flight (its unit is then complete on disk) and stop the thread.

        Errors are not raised here (:meth:`drain` raises them): ``close`` is also the clean-up
        of a run that is already failing."""
        try:
            self._wait()
        except Exception:  # noqa: BLE001 - the run's own error is the one to report
            pass
        if self._pool is not None:
            self._pool.shutdown(wait=True)
            self._pool = None
