"""The graph of stages checks itself when it is made (clrecon.pipeline.stage): each kind of wrong
stage or graph fails with one line naming the stage and what is wrong; the run's own graph passes
when clrecon.pipeline.graph is imported, and a wrong one fails that import; the executors honour
``after`` (a per-pitch stage waits for its own pitch's node, a once-per-run stage for every pitch's)."""

import importlib

import pytest

from clrecon.core.errors import ClreconError
from clrecon.pipeline import graph as graph_mod
from clrecon.pipeline.executors.base import Executor, serial_order
from clrecon.pipeline.stage import GraphError, Stage, graph
from clrecon.pipeline.stages import assemble


def make(run, pitch):
    return 1


def take(run, pitch, thing):
    return thing


def take_other(run, pitch, other):
    return other


def planned(run, pitch, ahead=None):
    return ahead


def read_back(run, pitch):
    return None


def ahead_call(run, pitch):
    return None


def _one_line(excinfo, *parts):
    msg = str(excinfo.value)
    assert "\n" not in msg and msg.startswith("graph: ")
    for p in parts:
        assert p in msg, (p, msg)
    assert isinstance(excinfo.value, ClreconError)


def test_the_run_graph_is_checked_and_whole():
    names = [st.name for st in graph_mod.GRAPH]
    assert names[0] == "plan" and names[-1] == "report" and len(set(names)) == len(names)
    assert graph(*graph_mod.GRAPH) == graph_mod.GRAPH
    asm = next(st for st in graph_mod.GRAPH if st.name == "assemble")
    assert asm.after == graph_mod.VOLUME_WRITERS and not asm.needs
    # no ordering token is dressed as a product any more
    assert not any("volume_units" in st.gives + st.needs for st in graph_mod.GRAPH)


def test_stages_take_keyword_arguments_only():
    with pytest.raises(TypeError):
        Stage("make", make, (), ("thing",))


@pytest.mark.parametrize("kw, parts", [
    (dict(rest="other", parts=("a",)), ["stage 'make'", "rest 'other' is not one of its parts ('a',)"]),
    (dict(write_part="w", parts=("a",), rest="a"), ["stage 'make'", "write_part 'w' is not one of its parts"]),
    (dict(gives="thing"), ["stage 'make'", "gives must be a tuple of names, not 'thing'"]),
    (dict(after=("",)), ["stage 'make'", "after must be a tuple of names"]),
    (dict(skip=3), ["stage 'make'", "skip must be callable"]),
    (dict(priority=1.5), ["stage 'make'", "priority must be an int"]),
])
def test_a_wrong_stage_fails_with_one_line(kw, parts):
    with pytest.raises(GraphError) as e:
        Stage(name="make", fn=make, **kw)
    _one_line(e, *parts)


@pytest.mark.parametrize("fn, kw, parts", [
    (make, dict(needs=("thing",)), ["stage 's'", "takes no keyword 'thing' for its need 'thing'"]),
    (take, dict(), ["stage 's'", "takes 'thing', which is not one of its needs (needs: none; for ordering use "
                    "after=)"]),
    (take, dict(needs=("other",)), ["stage 's'", "takes no keyword 'other'"]),
    (make, dict(ahead=ahead_call), ["stage 's'", "takes no keyword 'ahead'"]),
    (planned, dict(), ["stage 's'", "takes 'ahead', which is not one of its needs (ahead= is not set)"]),
    (lambda pitch, run: 1, dict(), ["stage 's'", "must start with (run, pitch), not (pitch, run)"]),
    (lambda run, pitch, **kw: 1, dict(needs=("x",)), ["stage 's'", "takes *kw"]),
    (lambda run: 1, dict(), ["stage 's'", "must start with (run, pitch), not (run)"]),
    ("not a function", dict(), ["stage 's'", "fn must be callable"]),
])
def test_a_function_whose_signature_does_not_match_its_needs_fails(fn, kw, parts):
    with pytest.raises(GraphError) as e:
        Stage(name="s", fn=fn, **kw)
    _one_line(e, *parts)


def test_a_matching_signature_passes():
    Stage(name="s", fn=take, needs=("thing",))
    Stage(name="s", fn=planned, ahead=ahead_call)
    Stage(name="s", fn=assemble.stage)


@pytest.mark.parametrize("stages, parts", [
    ([Stage(name="b", fn=take, needs=("thing",)), Stage(name="a", fn=make, gives=("thing",))],
     ["stage 'b'", "needs 'thing', which no earlier stage gives (given before it: nothing)"]),
    ([Stage(name="a", fn=make, gives=("thing",)), Stage(name="b", fn=take_other, needs=("other",))],
     ["stage 'b'", "needs 'other', which no earlier stage gives (given before it: thing)"]),
    ([Stage(name="b", fn=read_back, after=("a",)), Stage(name="a", fn=make)],
     ["stage 'b'", "after 'a', which is not an earlier stage"]),
    ([Stage(name="b", fn=read_back, beside="a")], ["stage 'b'", "beside 'a', which is not an earlier stage"]),
    ([Stage(name="a", fn=make), Stage(name="a", fn=read_back)], ["stage 'a'", "a second stage of that name"]),
    ([Stage(name="a", fn=make, gives=("thing",)), Stage(name="b", fn=read_back, after=("a",))],
     ["stage 'a'", "gives 'thing', which no later stage needs"]),
    # a second giver after every taker is a product nobody reads (and would stall the taker)
    ([Stage(name="a", fn=make, gives=("thing",)), Stage(name="b", fn=take, needs=("thing",)),
      Stage(name="c", fn=make, gives=("thing",))], ["stage 'c'", "gives 'thing', which no later stage needs"]),
])
def test_a_wrong_graph_fails_with_one_line(stages, parts):
    with pytest.raises(GraphError) as e:
        graph(*stages)
    _one_line(e, *parts)


def test_a_wrong_graph_fails_at_import(monkeypatch):
    """The check runs when clrecon.pipeline.graph is imported: a stage function that lost a keyword fails it."""
    monkeypatch.setattr(assemble, "stage", take)
    try:
        with pytest.raises(GraphError) as e:
            importlib.reload(graph_mod)
        _one_line(e, "stage 'assemble'", "takes 'thing', which is not one of its needs")
    finally:
        monkeypatch.undo()
        importlib.reload(graph_mod)
    assert [st.name for st in graph_mod.GRAPH][-1] == "report"


def test_the_executors_honour_after():
    """A per-pitch stage after another waits for its own pitch's node only; a once-per-run stage after
    a per-pitch one waits for every pitch's; a product still waits for its giver."""
    g = graph(Stage(name="a", fn=make, gives=("thing",), per_pitch=True),
              Stage(name="b", fn=read_back, after=("a",), per_pitch=True),
              Stage(name="c", fn=take, needs=("thing",), after=("b",)))
    a, b, c = g
    ex = Executor()
    ex.nodes = serial_order(g, (0.1, 0.2))
    ex.done = {}
    assert not ex.ready((b, 0.1))
    ex.done[(a, 0.1)] = 1
    assert ex.ready((b, 0.1)) and not ex.ready((b, 0.2))
    ex.done[(b, 0.1)] = None
    assert not ex.ready((c, None))  # pitch 0.2 of a and b not done
    ex.done[(a, 0.2)] = 2
    assert not ex.ready((c, None))
    ex.done[(b, 0.2)] = None
    assert ex.ready((c, None)) and ex.inputs((c, None)) == {"thing": {0.1: 1, 0.2: 2}}


@pytest.mark.parametrize("name", ["mc_reconstruct", "mcir_reconstruct"])
def test_the_motion_stages_wait_for_the_truths(name):
    """``mc`` and ``mcir`` start once the truths (a once-per-run stage beside the run) are done, so
    their working sets never meet (the pre-flight counts them apart: ``costs.run_costs``)."""
    ex = Executor()
    ex.nodes = serial_order(graph_mod.GRAPH, (0.1, 0.02))
    st = next(s for s in graph_mod.GRAPH if s.name == name)
    truth = next(n for n in ex.nodes if n[0].name == "truth")
    ex.done = {n: None for n in ex.nodes if n[0].name not in (name, "truth") and n[0].name in
               ("plan", "simulate", "truth_free", "reconstruct", "mc_reconstruct")}
    node = (st, 0.1)
    assert not ex.ready(node)
    ex.done[truth] = None
    assert ex.ready(node)
