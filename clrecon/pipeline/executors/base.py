"""The executor: runs the graph of stages (:mod:`clrecon.pipeline.graph`) and times it, once.

:class:`Executor` is the serial one: every node in this thread, in the graph's order (the
per-pitch stages pitch by pitch), every piece written as it is made. A node is ready when the
nodes giving what it needs and those of the stages it comes ``after`` are done
(:meth:`Executor.ready`, which every executor uses). The others change only
*where* work runs, never what it computes: :class:`~clrecon.pipeline.executors.local.LocalExecutor`
overlaps the nodes on this machine's cores (a helper process, a writer thread, a thread beside
the reconstruction), :class:`~clrecon.pipeline.executors.dask.DaskExecutor` sends the units to
Dask workers. Every stage is the same function under each, so the run's volumes and numbers
are the same bit for bit.

**Timing** (``results.json["stages"]``) is measured here and nowhere else. ``seconds`` of a
part is time on the run's own path (this thread, or what it waited for); ``beside_seconds``
time spent on it elsewhere while the run went on (a helper process, a thread). Each node's wall
time goes to its stage: the units' own split (e.g. the reconstruction's read, noise, rebin,
interpolate, fbp), the writing of its pieces to ``write_part``, what is left to ``rest``.
"""

from __future__ import annotations

import contextlib
import threading
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Any

from clrecon.core import write_behind
from clrecon.core.progress import progress as progress_counter
from clrecon.core.resources import rss_mark
from clrecon.core.stage_times import StageTimes


class StageClock:
    """Seconds per part, on the run's path (:meth:`add`) and beside it (:meth:`beside`); thread-safe."""

    def __init__(self):
        self.seconds: dict[str, float] = {}
        self.beside_seconds: dict[str, float] = {}
        self._lock = threading.Lock()

    def add(self, part: str, seconds: float) -> None:
        with self._lock:
            self.seconds[part] = self.seconds.get(part, 0.0) + seconds

    def beside(self, part: str, seconds: float) -> None:
        with self._lock:
            self.beside_seconds[part] = self.beside_seconds.get(part, 0.0) + seconds

    def total(self) -> float:
        with self._lock:
            return sum(self.seconds.values())


@dataclass
class Unit:
    """One independent piece of a stage's work.

    ``local(emit, times)``: runs it in this process, handing each piece it makes to ``emit`` and
    its seconds and counts to ``times`` (:class:`StageTimes`). ``remote()``: ``(fn, args)``, a
    top-level function and picklable arguments for a Dask worker, ``fn(*args) -> (pieces,
    seconds, counts)``, made when the unit is sent (so that nothing it holds is kept before);
    None: this unit runs in the run's process only. ``label`` names it in errors.
    ``drain_first``: in this process, wait for the pieces still being written behind
    (:class:`clrecon.core.write_behind.WriteBehind`) before the unit starts, so that a unit whose
    own working set is large never holds the previous unit's piece beside it (``mc``'s slabs:
    :func:`clrecon.reconstruction.motion.memory.working_parts` counts one slab of output).
    """

    local: Callable[[Callable, StageTimes], None]
    remote: Callable[[], tuple] | None = None
    label: str = ""
    drain_first: bool = False


@dataclass
class Work:
    """A node's work as units; each piece they make is handed to ``write`` in this process.

    ``finish(times)``: after every piece is written; gives the node's product (``times``: the
    units' seconds and counts, their ``a:b`` keys included). ``abort(exc)``: on an error, before
    it is raised. ``progress``: ``(desc, total, unit)`` of a counter advanced by ``weight(piece)``.
    ``prepare(piece) -> piece``: optional, run in this process's thread once the previous piece is
    written and before this one is handed to ``write`` (which may run in the writer thread): the
    reconstruction converts its finished slab to the volume dtype there, so the writer never holds
    a float32 slab beside the next one being made (the slab rule,
    :func:`clrecon.reconstruction.reconstruct.slab_bytes_per_slice`, counts what it does hold).
    """

    units: Iterable[Unit]
    write: Callable[[Any], None]
    finish: Callable[[StageTimes], Any] = lambda times: None
    abort: Callable[[BaseException], None] = lambda exc: None
    progress: tuple | None = None
    weight: Callable[[Any], int] = lambda piece: 1
    prepare: Callable[[Any], Any] | None = None


@dataclass
class Idle:
    """What a stage returns when its node had nothing to do (a resumed run's finished pitch): the
    executor books no time for it, so its parts say they did not run."""

    product: Any = None


def book_times(clock: StageClock, times: StageTimes, beside: bool = False) -> None:
    """A node's unit seconds into the clock (keys with ``:`` are the node's own detail)."""
    for key, sec in times.seconds.items():
        if ":" not in key:
            (clock.beside if beside else clock.add)(key, sec)


def serial_order(graph, pitches) -> list[tuple]:
    """The nodes ``(stage, pitch)`` in the order a serial run walks them: each run of consecutive
    per-pitch stages pitch by pitch, the once-per-run stages in place (pitch None)."""
    out, block = [], []
    for st in list(graph) + [None]:
        if st is not None and st.per_pitch:
            block.append(st)
            continue
        out += [(b, p) for p in pitches for b in block]
        block = []
        if st is not None:
            out.append((st, None))
    return out


class Executor:
    """Runs the graph in this thread, in order (``--executor serial``)."""

    kind = "serial"
    #: units cut for workers elsewhere (one per chunk / target) rather than for this process
    fine_units = False

    def __init__(self):
        self.clock = StageClock()
        self.pool = None  # a warm helper process lent to stages that split their work (metrics, figures)

    def summary(self) -> dict | None:
        """What the executor reports in ``results.json`` (a distributed one: its workers and units)."""
        return None

    # ---- the walk
    def run(self, graph, run) -> dict:
        """Run every node of ``graph`` for ``run`` (:class:`~clrecon.pipeline.context.RunContext`);
        returns ``{(stage name, pitch): product}``."""
        self.run_ctx = run
        self.nodes = serial_order(graph, run.pitches)
        self.done: dict = {}
        run.clock, run.pool, run.fine_units = self.clock, self.pool, self.fine_units
        with self.session(run):
            run.pool = self.pool
            self.todo = list(self.nodes)
            while self.todo:
                self.check()
                node = next((n for n in self.todo if self.startable(n)), None)
                if node is None:
                    self.wait()
                    continue
                self.todo.remove(node)
                self.start(node)
            self.wait_all()
        return {(st.name, p): v for (st, p), v in self.done.items()}

    @contextlib.contextmanager
    def session(self, run):
        """Resources for the run's duration (threads, processes, a client), closed on the way out."""
        self.writer = write_behind.WriteBehind(background=False)
        try:
            yield
        finally:
            self.writer.close()

    @staticmethod
    def _upstream(node, other) -> bool:
        """Whether ``other``'s node counts for ``node``: a once-per-run stage waits for every pitch's
        node, a per-pitch stage for its own pitch's (and for a once-per-run node)."""
        return not node[0].per_pitch or not other[0].per_pitch or other[1] == node[1]

    def givers(self, node, product: str) -> list:
        """The nodes whose product ``product`` ``node`` takes."""
        return [n for n in self.nodes if product in n[0].gives and self._upstream(node, n)]

    def before(self, node) -> list:
        """The nodes of the stages ``node``'s stage comes ``after`` (it reads what they wrote)."""
        return [n for n in self.nodes if n[0].name in node[0].after and self._upstream(node, n)]

    def ready(self, node) -> bool:
        return (all(g in self.done for need in node[0].needs for g in self.givers(node, need))
                and all(n in self.done for n in self.before(node)))

    def startable(self, node) -> bool:
        return self.ready(node)

    def inputs(self, node) -> dict:
        st, _ = node
        out = {}
        for need in st.needs:
            g = self.givers(node, need)
            if len(g) == 1 and (st.per_pitch or not g[0][0].per_pitch):
                out[need] = self.done[g[0]]
            elif len({n[0].name for n in g}) == 1:
                out[need] = {p: self.done[(s, p)] for s, p in g}
            else:
                out[need] = {(s.name, p): self.done[(s, p)] for s, p in g}
        return out

    def start(self, node) -> None:
        st, pitch = node
        if st.skip is not None and st.skip(self.run_ctx):
            self.done[node] = None
            return
        t0, b0 = time.perf_counter(), self.clock.total()
        kw = self.inputs(node)
        ahead = self.take_ahead(node)
        if ahead is not None:
            kw["ahead"] = ahead
        out = st.fn(self.run_ctx, pitch, **kw)
        rss_mark(f"stage {st.name} {pitch} (its work is {type(out).__name__})")
        if isinstance(out, Work):
            self.start_work(node, out, t0, b0)
        elif isinstance(out, Idle):
            self.done[node] = out.product
        else:
            self.book_rest(st, t0, b0)
            self.done[node] = out

    def take_ahead(self, node):
        """The node's result computed ahead elsewhere, or None (this executor computes nothing ahead)."""
        return None

    def book_rest(self, st, t0: float, b0: float) -> None:
        """What the node took and did not book itself goes to its stage's ``rest`` part."""
        rest = time.perf_counter() - t0 - (self.clock.total() - b0)
        if st.rest is not None and rest > 0:
            self.clock.add(st.rest, rest)

    # ---- units
    def start_work(self, node, work: Work, t0: float, b0: float) -> None:
        st = node[0]
        times = StageTimes()
        bar = progress_counter(work.progress[1], work.progress[0], self.run_ctx.progress, work.progress[2]) \
            if work.progress else None
        w0, wb0 = self.writer.wait_seconds, self.writer.beside_seconds

        def emit(piece):
            if bar is not None:
                bar.update(work.weight(piece))
            if work.prepare is not None:
                self.writer.drain()  # what submit waits for first anyway: the previous piece is on disk
                piece = work.prepare(piece)
            self.writer.submit(work.write, piece)

        try:
            for unit in work.units:
                self.check()
                if unit.drain_first:
                    self.writer.drain()
                unit.local(emit, times)
            self.writer.drain()
        except BaseException as e:
            work.abort(e)
            raise
        finally:
            if bar is not None:
                bar.close()
        rss_mark(f"stage {st.name}: its units")
        self.book_writes(st, self.writer.wait_seconds - w0, self.writer.beside_seconds - wb0)
        book_times(self.clock, times)
        self.done[node] = work.finish(times)
        self.book_rest(st, t0, b0)

    def book_writes(self, st, waited: float, beside: float) -> None:
        if st.write_part is not None:
            if waited > 0 or beside > 0:
                self.clock.add(st.write_part, waited)
            if self.writer.background and beside > 0:
                self.clock.beside(st.write_part, beside)

    def check(self) -> None:
        """Raise the error of work running elsewhere (a thread, a process), if any."""

    def wait(self) -> None:
        """Wait for some work in flight; the serial walk never has any."""
        raise RuntimeError("the graph cannot go on: no node is ready and none is in flight")

    def wait_all(self) -> None:
        """Wait for every work still in flight."""
