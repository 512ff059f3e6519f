"""A stage of the run and the graph of them, each checked when it is made.

:class:`Stage` checks itself when it is constructed (as kedro's ``Node`` does): its lists are
tuples of names, ``rest`` and ``write_part`` are among its ``parts``, and its function's
signature is ``fn(run, pitch, **needs)`` with one keyword per need (and ``ahead`` where
``ahead`` is set). :func:`graph` checks the stages together: names unique, every need given by
an earlier stage, every ``after``/``beside`` an earlier stage, every product some later stage
needs. A wrong graph so fails when :mod:`clrecon.pipeline.graph` is imported, with one line
naming the stage and what is wrong (:class:`GraphError`), never halfway through a run.
"""

from __future__ import annotations

import inspect
from collections.abc import Callable
from dataclasses import dataclass

from clrecon.core.errors import ClreconError


class GraphError(ClreconError, TypeError):
    """A stage or a graph of stages is declared wrong: the message names the stage and what is wrong."""


@dataclass(frozen=True, kw_only=True)
class Stage:
    """One stage of the run (keyword arguments only; checked when constructed).

    ``fn(run, pitch, **needs)``: the stage function (:mod:`clrecon.pipeline.graph`). ``needs``:
    the products it takes, one keyword each; ``gives``: the product its return value is, for a
    later stage that needs it (a product nobody needs is not declared). ``after``: the names of
    earlier stages that must be done before it starts though it takes none of their products
    (it reads what they wrote; for a per-pitch stage after a per-pitch stage: the same pitch's
    node). ``per_pitch``: one node per pitch (else one per run, pitch None).

    ``parts``: the names it is timed under in ``results.json["stages"]`` (the executor times
    each node; a stage may split its time among its parts, and whatever it does not split goes
    to ``rest``); ``write_part``: the part its pieces' writing is booked to (None: ``rest``).
    ``skip(run)``: a reason the stage does not run in this run, or None; ``optional``: its parts
    are left out of the stage table when it is skipped (else listed with the reason). ``ahead(run, pitch)``:
    a pure ``(fn, args)`` of the node that an executor may compute early in a helper process,
    handing the result to ``fn(..., ahead=result)``. ``beside``: the stage after whose first
    node an overlapping executor starts this one in a thread of its own. ``priority``: the
    order of units on Dask (higher first).
    """

    name: str
    fn: Callable
    needs: tuple[str, ...] = ()
    gives: tuple[str, ...] = ()
    after: tuple[str, ...] = ()
    per_pitch: bool = False
    parts: tuple[str, ...] = ()
    rest: str | None = None
    write_part: str | None = None
    skip: Callable | None = None
    optional: bool = False
    ahead: Callable | None = None
    beside: str | None = None
    priority: int = 0

    def __post_init__(self):
        if not isinstance(self.name, str) or not self.name:
            raise GraphError(f"graph: a stage's name must be a non-empty string, not {self.name!r}")
        for key in ("needs", "gives", "after", "parts"):
            val = getattr(self, key)
            if not isinstance(val, tuple) or not all(isinstance(x, str) and x for x in val):
                raise self.error(f"{key} must be a tuple of names, not {val!r}")
        for key in ("rest", "write_part"):
            val = getattr(self, key)
            if val is not None and val not in self.parts:
                raise self.error(f"{key} {val!r} is not one of its parts {self.parts}")
        for key in ("skip", "ahead"):
            if getattr(self, key) is not None and not callable(getattr(self, key)):
                raise self.error(f"{key} must be callable, not {getattr(self, key)!r}")
        if not isinstance(self.priority, int):
            raise self.error(f"priority must be an int, not {self.priority!r}")
        self._check_signature()

    def error(self, what: str) -> GraphError:
        return GraphError(f"graph: stage {self.name!r}: {what}")

    def _check_signature(self) -> None:
        """``fn(run, pitch, <one keyword per need>[, ahead])``, nothing more, nothing less."""
        fn = self.fn
        if not callable(fn):
            raise self.error(f"fn must be callable, not {fn!r}")
        where = f"its function {getattr(fn, '__module__', '?')}.{getattr(fn, '__qualname__', repr(fn))}"
        try:
            params = list(inspect.signature(fn).parameters.values())
        except (TypeError, ValueError):
            raise self.error(f"{where} has no signature to check") from None
        var = [p.name for p in params if p.kind in (p.VAR_POSITIONAL, p.VAR_KEYWORD)]
        if var:
            raise self.error(f"{where} takes *{var[0]}: a stage function names each need as a keyword")
        head = [p.name for p in params[:2] if p.kind in (p.POSITIONAL_ONLY, p.POSITIONAL_OR_KEYWORD)]
        if head != ["run", "pitch"]:
            raise self.error(f"{where} must start with (run, pitch), not ({', '.join(p.name for p in params[:2])})")
        named = [p.name for p in params[2:]]
        wanted = list(self.needs) + (["ahead"] if self.ahead is not None else [])
        missing = [n for n in wanted if n not in named]
        if missing:
            what = "ahead (the stage sets ahead=)" if missing[0] == "ahead" else f"its need {missing[0]!r}"
            raise self.error(f"{where} takes no keyword {missing[0]!r} for {what}")
        extra = [n for n in named if n not in wanted]
        if extra:
            why = (" (ahead= is not set)" if extra[0] == "ahead"
                   else f" (needs: {', '.join(self.needs) or 'none'}; for ordering use after=)")
            raise self.error(f"{where} takes {extra[0]!r}, which is not one of its needs{why}")


def graph(*stages: Stage) -> tuple[Stage, ...]:
    """The stages as a run's graph, in the order a serial run walks them, checked together.

    Raises :class:`GraphError` (one line: the stage, what is wrong) where two stages share a
    name, a stage needs a product no earlier stage gives, names in ``after`` or ``beside`` a
    stage that is not earlier, or gives a product no later stage needs.
    """
    seen: dict[str, Stage] = {}
    given: dict[str, str] = {}
    for st in stages:
        if not isinstance(st, Stage):
            raise GraphError(f"graph: {st!r} is not a Stage")
        if st.name in seen:
            raise st.error("a second stage of that name")
        for need in st.needs:
            if need not in given:
                raise st.error(f"needs {need!r}, which no earlier stage gives (given before it: "
                               f"{', '.join(given) or 'nothing'})")
        for name in st.after:
            if name not in seen:
                raise st.error(f"after {name!r}, which is not an earlier stage")
        if st.beside is not None and st.beside not in seen:
            raise st.error(f"beside {st.beside!r}, which is not an earlier stage")
        seen[st.name] = st
        for product in st.gives:
            given.setdefault(product, st.name)
    for i, st in enumerate(stages):
        for product in st.gives:
            if not any(product in later.needs for later in stages[i + 1:]):
                raise st.error(f"gives {product!r}, which no later stage needs (declare only products a stage "
                               f"takes; order stages with after=)")
    return tuple(stages)
