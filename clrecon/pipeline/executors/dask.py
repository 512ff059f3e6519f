"""``--executor dask`` (``--workers N``, ``--cluster ADDRESS``, ``client=``): the units on Dask workers.

The same walk of the same graph as the other executors; a node whose stage returns a
:class:`~clrecon.pipeline.executors.base.Work` sends its units to the workers (each unit's
``remote``: a top-level function of :mod:`clrecon.pipeline.work_units` and picklable
arguments, the same computation as in one process) and writes each result, as it arrives, in
this process with the run's own writers: the same atomic unit files, so the volumes and the
numbers are the same bit for bit (docs/distributed.md). While units are in flight the walk goes
on with every node that is ready (the next pitch's plan, the truths), so the projection chunks
of every pitch, then each pitch's slabs once its store is assembled, and the truth targets in
between, keep the workers busy (higher ``Stage.priority`` first).

A worker killed mid-unit costs that unit only (Dask gives it to another worker; nothing was
written); a client killed or interrupted keeps every unit written so far, and the rerun
computes only the rest. A stage whose units have no ``remote`` form runs only in one process
(the truth-free cross-validation, a measured scan's import): a one-line error says so.

Timing: a stage's seconds are its units' own seconds summed over the workers (compute, not
wall: ``results["distributed"]["wall_seconds"]`` is that) and this process's writing. The
run keeps its helper process (:mod:`clrecon.pipeline.executors.local`) for the metrics and
the figures.
"""

from __future__ import annotations

import contextlib
import os
import time
import uuid
import warnings

import numpy as np
from tqdm import tqdm

from clrecon.core.errors import ClreconError
from clrecon.core.stage_times import StageTimes
from clrecon.pipeline import distributed
from clrecon.pipeline.executors.base import Work, book_times
from clrecon.pipeline.executors.local import LocalExecutor


class DaskExecutor(LocalExecutor):
    """The units on ``client``'s workers (module docstring); ``helper`` as for the local executor."""

    kind = "dask"
    fine_units = True

    def __init__(self, client, helper: bool | None = None):
        super().__init__(helper=helper, beside=False, write_behind=False)
        self.client = client
        self.d = distributed.dask_module()

    @contextlib.contextmanager
    def session(self, run):
        info = self.client.scheduler_info().get("workers", {})
        threaded = [w for w, i in info.items() if i.get("nthreads", 1) > 1]
        if threaded:
            raise ClreconError(f"client: worker {threaded[0]} runs {info[threaded[0]]['nthreads']} threads; clrecon "
                               f"needs single-threaded worker processes (one OpenCL queue each): start them with "
                               f"threads_per_worker=1 / --nthreads 1 (docs/distributed.md)")
        # idempotent: kept if connect() registered one (with its device)
        self.client.register_plugin(distributed.runtime_plugin())
        self.nw = len(info)
        self.t_start = time.perf_counter()
        self.t_last = self.t_start
        self.pending: dict = {}  # future key -> (node, unit label)
        self.works: dict = {}  # node -> [work, units left, times]
        self.count: dict = {}
        self.unit_seconds: dict = {}
        self.ac = self.d.as_completed()
        disable = (not run.progress) or os.environ.get("CLRECON_NO_PROGRESS") == "1"
        self.bar = tqdm(total=0, desc=f"units on {self.nw} workers", unit="unit", disable=disable, leave=False,
                        dynamic_ncols=True)
        run.log(f"distributed: units on {self.nw} workers")
        try:
            with super().session(run):
                yield
        except BaseException as e:
            self._cancel(e)
            raise
        finally:
            self.bar.close()

    def summary(self) -> dict:
        """The workers, the scheduler, the units per stage and their seconds (``results["distributed"]``)."""
        address = str(getattr(self.client.scheduler, "address", ""))
        return {"workers": self.nw, "scheduler": address, "encrypted": distributed.is_tls(address),
                "units": dict(self.count), "wall_seconds": round(self.t_last - self.t_start, 3),
                "unit_seconds": {k: {"sum": round(float(np.sum(v)), 3), "median": round(float(np.median(v)), 4)}
                                 for k, v in self.unit_seconds.items() if v}}

    def _send_ahead(self, run) -> None:
        """Nothing is planned ahead: the workers are busy with the units."""

    def start_work(self, node, work: Work, t0: float, b0: float) -> None:
        st = node[0]
        units = list(work.units)
        self.count.setdefault(st.name, 0)
        self.unit_seconds.setdefault(st.name, [])
        self.works[node] = [work, len(units), StageTimes()]
        self.book_rest(st, t0, b0)
        self.bar.total += len(units)
        self.bar.refresh()
        try:
            for unit in units:
                if unit.remote is None:
                    raise ClreconError(f"{unit.label or st.name}: runs in one process only; drop --workers/--cluster "
                                       f"(or use --executor local)")
                fn, args = unit.remote()
                key = f"clrecon-{st.name}-{uuid.uuid4().hex[:12]}"
                with warnings.catch_warnings():
                    # a slab's plan (its weights, MBs at paper scale) travels with its task on purpose: a
                    # scattered copy would be lost with the worker holding it, and the unit with it
                    warnings.filterwarnings("ignore", message="Sending large graph", category=UserWarning)
                    fut = self.client.submit(fn, *args, key=key, pure=False, priority=st.priority)
                self.pending[fut.key] = (node, unit.label)
                self.ac.add(fut)
        except BaseException as e:
            work.abort(e)
            raise
        if not units:
            self._finish(node)

    def wait(self) -> None:
        """Handle the next unit to complete: write its pieces; finish its node when it was the last."""
        if not self.pending:
            super().wait()
        fut = next(self.ac)
        node, label = self.pending.pop(fut.key)
        try:
            pieces, seconds, counts = fut.result()
        except self.d.KilledWorker as e:
            raise ClreconError(f"{label}: the workers computing it died (Dask gave up after its allowed failures: "
                               f"{str(e).splitlines()[0]}); the finished units are kept: run the same command "
                               f"again to resume") from None
        except ClreconError as e:
            raise ClreconError(f"{label}: {e}; the finished units are kept") from None
        except Exception as e:  # noqa: BLE001 - any failure of a unit on a worker is reported naming the unit
            msg = str(e).splitlines()[0] if str(e) else ""
            raise ClreconError(f"{label} failed on a worker ({type(e).__name__}: {msg}); the finished units are "
                               f"kept: run the same command again to resume") from None
        finally:
            fut.release()
        self.t_last = time.perf_counter()
        st = node[0]
        work, left, times = self.works[node]
        t0 = time.perf_counter()
        for piece in pieces:
            work.write(piece)
        part = st.write_part or st.rest
        if part is not None:
            self.clock.add(part, time.perf_counter() - t0)
        for key, sec in seconds.items():
            times.add(key, sec)
        for key, n in counts.items():
            times.count(key, n)
        self.unit_seconds[st.name].append(float(sum(sec for key, sec in seconds.items() if ":" not in key)))
        self.count[st.name] += 1
        self.bar.update(1)
        self.works[node][1] = left - 1
        if left == 1:
            self._finish(node)

    def _finish(self, node) -> None:
        work, _, times = self.works.pop(node)
        book_times(self.clock, times)
        self.done[node] = work.finish(times)

    def wait_all(self) -> None:
        while self.pending:
            self.wait()

    def _cancel(self, exc: BaseException) -> None:
        futs = list(self.ac.futures) if hasattr(self.ac, "futures") else []
        if futs:
            with contextlib.suppress(Exception):
                self.client.cancel(futs)
        self.pending.clear()
        for work, _, _ in self.works.values():  # e.g. a store's finished chunks stay as unit files for the rerun
            work.abort(exc)
        self.works.clear()
