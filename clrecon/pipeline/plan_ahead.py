"""The later pitches planned in a second process while this one plans the first (``CLRECON_PLAN_AHEAD``).

A run of several pitches (demo: 0.02 and 0.10) plans, simulates and reconstructs them one after
the other, and the planning (:func:`clrecon.pipeline.slabs.plan_pitch`: candidates, Delaunay
triangulations, local-linear fits, in NumPy and SciPy) keeps about one of the two cores busy.
:class:`PlanAhead` starts the planning of every pitch after the first in one spawned process
at the start of the run, so that it runs while this process plans the first pitch (on demo:
3-4 s of planning for pitch 0.10 beside 7-8 s for pitch 0.02); by the time the loop reaches a
later pitch its plan is usually there, and the run waits only for what is left of it.

A plan is a pure function of the scene, the pitch, the slices, the targets and the methods, so
the plan received is the one this process would have made, and the run's volumes are bit for
bit the same either way (tests/test_plan_ahead.py). The child plans every slice for the
requested methods; :meth:`PlanAhead.take` hands it over only when the loop asks for exactly
that (a resumed run, with some slices or methods already done, plans for itself), and a child
that fails or cannot start only means the loop plans for itself.

``CLRECON_PLAN_AHEAD``: unset, automatic: on for runs of two or more pitches on a machine with
two or more cores, where a spawned child cannot run the caller's script again
(:func:`clrecon.core.resources.spawn_is_safe`), and in one process (not with ``--workers``,
measured scans or the truth-free cross-validation, whose planning differs); ``1`` forces it
where it applies, ``0`` turns it off.
"""

from __future__ import annotations

import os
import time

import numpy as np

from clrecon.core.resources import spawn_is_safe, spawned_pool
from clrecon.pipeline import slabs as slabs_mod

ENV = "CLRECON_PLAN_AHEAD"


def enabled(n_pitches: int, helper: bool = False) -> bool:
    """Whether to plan the later pitches ahead (module docstring); ``helper``: the run has its
    helper process (:mod:`clrecon.pipeline.helper_process`), which decided already that a child
    can run here."""
    choice = os.environ.get(ENV, "").strip()
    if choice == "0" or n_pitches < 2:
        return False
    return choice == "1" or helper or ((os.cpu_count() or 1) >= 2 and spawn_is_safe())


def _plan(scene, cfg, pitch, slices_z, targets, methods, n_variants):
    """:func:`clrecon.pipeline.slabs.plan_pitch` of every slice, in the child; (plan, its own seconds)."""
    t0 = time.perf_counter()
    pp = slabs_mod.plan_pitch(scene, cfg, pitch, slices_z, np.arange(len(slices_z)), targets, methods,
                              n_variants, False)
    return pp, time.perf_counter() - t0


class PlanAhead:
    """The plans of ``pitches`` (every slice, ``methods``) made in one spawned process.

    :meth:`take` returns a pitch's :class:`clrecon.pipeline.slabs.PitchPlan` when the loop's
    request matches what was planned, else None; :attr:`wait_seconds` is this process's wait for
    the plans taken, :attr:`beside_seconds` the child's own time on them.
    """

    def __init__(self, scene, cfg, pitches, slices_z, targets, methods, n_variants, pool=None):
        self._methods = tuple(methods)
        self._n = len(slices_z)
        self._futures: dict = {}
        self.wait_seconds = 0.0
        self.beside_seconds = 0.0
        # ``pool``: the run's helper process (clrecon.pipeline.helper_process), not shut down here
        self._own_pool = pool is None
        self._pool = spawned_pool(1) if pool is None else pool
        try:
            for p in pitches if self._pool is not None else ():
                self._futures[float(p)] = self._pool.submit(_plan, scene, cfg, p, np.asarray(slices_z), targets,
                                                            self._methods, n_variants)
        except RuntimeError:  # the pool broke while starting: the loop plans every pitch itself
            self.close()

    def take(self, pitch: float, todo: np.ndarray, methods):
        """The plan of ``pitch`` if it was planned for every slice and exactly ``methods``, else None."""
        fut = self._futures.pop(float(pitch), None)
        if fut is None:
            return None
        if tuple(methods) != self._methods or not np.array_equal(todo, np.arange(self._n)):
            fut.cancel()
            return None
        t0 = time.perf_counter()
        try:
            pp, own = fut.result()
        except Exception:  # noqa: BLE001 - the child died or failed: the loop plans this pitch itself
            return None
        finally:
            self.wait_seconds += time.perf_counter() - t0
        self.beside_seconds += own
        return pp

    def close(self) -> None:
        """Stop the child (plans not taken are dropped)."""
        for fut in self._futures.values():
            fut.cancel()
        self._futures.clear()
        if self._pool is not None and self._own_pool:
            self._pool.shutdown(wait=False, cancel_futures=True)
        self._pool = None
