"""The run as a graph of stages, declared once: what each stage needs, what it gives, how it is timed.

:data:`GRAPH` is the whole run. An executor (:mod:`clrecon.pipeline.executors`) runs it: a node
(a stage, per pitch or once per run) starts when every node giving what it needs, and every node
of the stages it comes ``after``, is done.
Serially, overlapped on this machine's cores, or with its units on Dask workers, it is the
same graph and the same stage functions, so the volumes and the numbers are the same bit for
bit. How to add a stage: docs/adding-a-stage.md "A new pipeline stage".

Each :class:`~clrecon.pipeline.stage.Stage` is declared with keyword arguments and checked when it
is made, and :data:`GRAPH` as a whole when this module is imported (:func:`~clrecon.pipeline.stage.graph`):
a wrong graph fails at import with one line naming the stage and what is wrong. Products are what a
stage takes (``needs``/``gives``); ``after`` orders a stage behind others whose products it does not
take (it reads what they wrote), e.g. ``assemble`` behind every stage that writes volume units.

A stage function is ``fn(run, pitch, **needs)``: ``run`` is the run's
:class:`~clrecon.pipeline.context.RunContext`, ``pitch`` the node's pitch (None for a stage
that runs once), and one keyword per product it needs (for a once-per-run stage that needs a
per-pitch product: ``{pitch: value}``; for a product several stages give: ``{(stage, pitch):
value}``). It returns its product, or a :class:`~clrecon.pipeline.executors.base.Work` (units
the executor runs where it likes, their pieces written in this process) whose ``finish`` gives
the product.
"""

from __future__ import annotations

from clrecon.pipeline.stage import GraphError, Stage, graph
from clrecon.pipeline.stages import (
    assemble,
    consistency,
    mc_reconstruct,
    mcir_reconstruct,
    metrics,
    plan,
    reconstruct,
    report,
    results,
    simulate,
    truth,
    truth_free,
)

__all__ = ["GRAPH", "VOLUME_WRITERS", "GraphError", "Stage"]

_R = ("read", "noise", "rebin", "interpolate", "fbp", "write_volumes")
#: The stages that write volume units, which ``assemble`` maps into ``volumes.h5`` (``consistency``
#: reads the methods' unit files back, so it too is done before they are assembled).
VOLUME_WRITERS = ("reconstruct", "mc_reconstruct", "mcir_reconstruct", "consistency", "truth")

#: The run, in the order a serial executor walks it (the per-pitch stages pitch by pitch).
GRAPH = graph(
    Stage(name="plan", fn=plan.stage, gives=("plan",), per_pitch=True, parts=("signals", "plan"), rest="plan",
          ahead=plan.ahead),
    Stage(name="simulate", fn=simulate.stage, needs=("plan",), gives=("store",), per_pitch=True,
          parts=("simulate",), rest="simulate", priority=20),
    Stage(name="truth_free", fn=truth_free.stage, needs=("plan", "store"), gives=("tuning",), per_pitch=True,
          parts=("truth_free",), rest="truth_free", skip=truth_free.skip, optional=True),
    Stage(name="reconstruct", fn=reconstruct.stage, needs=("plan", "store", "tuning"), per_pitch=True, parts=_R,
          write_part="write_volumes", priority=10),
    Stage(name="truth", fn=truth.stage, parts=("groundtruth", "phantom_truth"), skip=truth.skip, beside="simulate"),
    Stage(name="mc_reconstruct", fn=mc_reconstruct.stage, needs=("plan", "store"),
          after=("reconstruct", "truth"),  # the truths' working set is gone before mc's (costs.run_costs)
          per_pitch=True, parts=("registration", "plane_rows", "mc_backproject", "write_volumes"),
          rest="registration", write_part="write_volumes", skip=mc_reconstruct.skip, optional=True, priority=5),
    Stage(name="mcir_reconstruct", fn=mcir_reconstruct.stage, needs=("plan", "store"),
          after=("mc_reconstruct", "truth"), per_pitch=True, parts=("registration", "mcir_solve", "write_volumes"),
          rest="registration", write_part="write_volumes", skip=mcir_reconstruct.skip, optional=True, priority=4),
    Stage(name="consistency", fn=consistency.stage, needs=("plan", "store"), after=("mcir_reconstruct",),
          per_pitch=True, parts=("consistency",), rest="consistency", skip=consistency.skip, optional=True),
    Stage(name="assemble", fn=assemble.stage, gives=("volumes",), after=VOLUME_WRITERS,
          parts=("assemble_volumes",), rest="assemble_volumes"),
    Stage(name="metrics", fn=metrics.stage, needs=("volumes",), parts=("metrics",), rest="metrics",
          skip=metrics.skip),
    Stage(name="results", fn=results.stage, gives=("results",), after=("assemble", "metrics")),
    Stage(name="report", fn=report.stage, needs=("results",), parts=("report",), rest="report", skip=report.skip,
          optional=True),
)
