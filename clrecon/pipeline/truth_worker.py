"""The truths of a run computed beside its reconstruction, in a background thread.

The ground truth and the phantom truth of every target (:mod:`clrecon.evaluation.groundtruth`)
depend on the phantom, the detector, the grid and the targets, never on the projections or the
reconstruction, so they need not wait for it. Before, they ran after the reconstruction, in
the foreground: 13 % of paper-p010's wall time (443 s of 3 356 s) and about 8 s of the demo's
70 s, while much of the reconstruction keeps only one core busy (planning, HDF5 reads and
writes, the LZF compression of the volumes; the whole demo used 1.3 of 2 cores). Started
once the first pitch's projections are stored (during the planning and the simulation both
cores are already busy: started with the run, the thread hid only 3 of the demo's 8.5 s), the
truths fill those gaps; the run waits for what is left of them only after
the reconstruction (stage ``groundtruth`` then counts that wait; ``beside_seconds`` the
thread's own time).

The thread has its own OpenCL context, queue and kernels (:func:`clrecon.core.runtime.thread_runtime`):
a kernel object's arguments are not safe to set from two threads at once. It runs the same
kernels on the same inputs as the foreground path, so the truths are bit-identical; each
target is one atomic unit as before (a SIGKILL at any instant loses at most the unit being
written, and a resumed run computes only the missing targets). An error in the thread is
raised again in the run's thread (at the next :meth:`TruthWorker.check` or at
:meth:`TruthWorker.finish`); an error in the run stops the thread after its current target.

``CLRECON_TRUTH_THREAD=0`` runs the truths in the foreground after the reconstruction, as
before (same numbers; for comparison and debugging).
"""

from __future__ import annotations

import os
import threading
import time

import numpy as np

from clrecon.core.runtime import Runtime, thread_runtime
from clrecon.evaluation import groundtruth

#: The truth datasets, in the order they are computed.
NAMES = ("groundtruth", "phantom")
#: Seconds between progress checks while the run waits for the thread.
POLL_S = 0.2


def enabled() -> bool:
    """Whether the truths run beside the reconstruction (``CLRECON_TRUTH_THREAD``, default on)."""
    return os.environ.get("CLRECON_TRUTH_THREAD", "1").strip().lower() not in ("0", "false", "no", "off")


def working_bytes(nz: int, views: int, cols: int, ny: int, nx: int) -> int:
    """Modelled memory of the thread at one target (bytes): per FBP batch of slices its in-plane
    sinograms, their filtered copy and the interleaved launch (3 x batch x V x C floats), and the
    target's volume. Paper-p010 (110 slices, 984 x 900, 512^2): 0.80 GB modelled, 0.66 GB measured
    (peak RSS over the run's, warm; 0.98 GB when all 110 slices went to the projector at once)."""
    b = min(nz, groundtruth.BATCH_SLICES)
    return int(3 * b * views * cols * 4 + nz * ny * nx * 4)


class TruthWorker:
    """Computes every not-yet-done truth target of ``writer`` in a thread; see the module docstring.

    ``writer``: the run's :class:`clrecon.outputs.volumes.VolumeWriter` with the truth datasets
    declared (:func:`clrecon.pipeline.slabs.declare_truths`); ``truths``: the run's
    :class:`clrecon.evaluation.truth_cache.TruthCache`; ``cfg``:
    :class:`clrecon.evaluation.groundtruth.GroundTruthConfig`; ``slices_z`` (nz,) mm; ``targets``:
    :class:`clrecon.reconstruction.reconstruct.Targets`.
    """

    def __init__(self, writer, truths, cfg, slices_z, targets, device_spec: str | None = None):
        self.writer, self.truths, self.cfg = writer, truths, cfg
        self.slices_z, self.targets = slices_z, targets
        self.device_spec = device_spec
        n_t = targets.shape[0] * targets.shape[1]
        #: flat target indices already done (units of an interrupted run, or the truth cache's)
        self.skip = {name: {int(k) for k in np.flatnonzero(writer.done(name))} for name in NAMES}
        self.todo = sum(n_t - len(s) for s in self.skip.values())
        self.done = 0
        #: thread wall seconds per truth dataset (its own time, beside the reconstruction)
        self.seconds = dict.fromkeys(NAMES, 0.0)
        self.error: BaseException | None = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="clrecon-truths", daemon=True)

    @property
    def started(self) -> bool:
        return self._thread.ident is not None

    def start(self) -> TruthWorker:
        self._thread.start()
        return self

    def _run(self) -> None:
        n_r = self.targets.shape[1]
        try:
            with thread_runtime(Runtime(self.device_spec)) as rt:
                gens = {"groundtruth": groundtruth.groundtruth_volumes(self.cfg, self.slices_z, self.targets, rt=rt,
                                                                       skip=self.skip["groundtruth"]),
                        "phantom": groundtruth.phantom_truth_volumes(self.cfg, self.slices_z, self.targets, rt=rt,
                                                                     skip=self.skip["phantom"])}
                for name in NAMES:
                    t0 = time.perf_counter()
                    for i, j, vol in gens[name]:
                        self.truths.put(self.writer.write_target(name, i, j, n_r, vol))
                        self.done += 1
                        if self._stop.is_set():
                            break
                    self.seconds[name] += time.perf_counter() - t0
                    if self._stop.is_set():
                        return
        except BaseException as e:  # noqa: BLE001 - handed to the run's thread, raised there
            self.error = e

    def check(self) -> None:
        """Raise the thread's error, if it has failed."""
        if self.error is not None:
            raise self.error

    def finish(self, bar_factory=None) -> float:
        """Wait for the thread; returns the seconds waited. Raises its error, if any.

        ``bar_factory(total)``: a progress counter over the targets still to compute when the
        wait starts (None: no progress).
        """
        t0 = time.perf_counter()
        if not self.started:  # (every pitch was already reconstructed: a resumed run)
            self.start()
        left = self.todo - self.done
        bar = bar_factory(left) if bar_factory is not None and left > 0 and self._thread.is_alive() else None
        seen = self.done
        while self._thread.is_alive():
            self._thread.join(POLL_S)
            if bar is not None and self.done > seen:
                bar.update(self.done - seen)
                seen = self.done
        if bar is not None:
            bar.close()
        self.check()
        return time.perf_counter() - t0

    def stop(self) -> None:
        """Ask the thread to stop after its current target and wait for it (errors are not raised)."""
        self._stop.set()
        if self.started:
            self._thread.join()
