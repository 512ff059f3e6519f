"""One spawned helper process for the whole run (``CLRECON_HELPER_PROCESS``).

Three parts of a run use a second process: the later pitches' plans
(:mod:`clrecon.pipeline.plan_ahead`), the metrics' second group of accumulators
(:mod:`clrecon.pipeline.evaluate`) and the report's figures drawn from ``results`` alone
(:func:`clrecon.outputs.figures.write_figures`). Each used to spawn its own, and a spawned
child first imports NumPy, SciPy, h5py, PyOpenCL, matplotlib and the package: about 1-2 s of CPU
before it does anything. On demo that start-up is why the metrics stayed in one process (a
second one started at the metrics cost as much as it saved: 0.96x in ``bench --only levers``).

:func:`start` spawns one process at the start of the run and queues its imports behind the
plans made ahead, so that by the metrics and the report the child is warm; the three parts
take :attr:`HelperProcess.pool` instead of spawning their own, and the run closes it at the
end. The work done there is the same function on the same inputs as in this process, so
results are bit for bit the same with or without it (the parts' own tests, and
tests/test_helper_process.py).

``CLRECON_HELPER_PROCESS``: unset, automatic: on a machine with two or more cores where a
spawned child cannot run the caller's script again (:func:`clrecon.core.resources.spawn_is_safe`);
``1`` forces it, ``0`` turns it off (each part then decides for itself, as before). The
parts' own switches (``CLRECON_PLAN_AHEAD``, ``CLRECON_METRICS_PROCESSES``,
``CLRECON_FIGURE_PROCESS``) still apply.
"""

from __future__ import annotations

import os

from clrecon.core.resources import spawn_is_safe, spawned_pool
from clrecon.outputs import figures
from clrecon.pipeline import evaluate  # noqa: F401 - imported in the child by unpickling _warm

ENV = "CLRECON_HELPER_PROCESS"


def enabled() -> bool:
    """Whether the run starts a helper process (module docstring)."""
    choice = os.environ.get(ENV, "").strip()
    if choice == "0":
        return False
    return choice == "1" or ((os.cpu_count() or 1) >= 2 and spawn_is_safe())


def _warm() -> int:
    """In the child: import what the metrics and the figures need (this module's imports, and
    matplotlib's pyplot, which the figures load on first use); returns the child's pid."""
    figures._plt()
    return os.getpid()


class HelperProcess:
    """A one-worker spawned pool that lives for the run; :meth:`warm` queues the imports."""

    def __init__(self, pool):
        self.pool = pool

    def warm(self) -> None:
        """Queue the child's imports (after whatever was submitted before, e.g. the plans ahead)."""
        if self.pool is None:
            return
        try:
            self.pool.submit(_warm)
        except RuntimeError:  # the pool broke: the parts run here
            self.close()

    def close(self) -> None:
        if self.pool is not None:
            self.pool.shutdown(wait=True, cancel_futures=True)
            self.pool = None


def start() -> HelperProcess | None:
    """The run's helper process, or None where it is off or cannot start."""
    if not enabled():
        return None
    pool = spawned_pool(1)
    return HelperProcess(pool) if pool is not None else None
