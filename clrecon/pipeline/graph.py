"""The run as a graph of stages, declared once: what each stage needs, what it gives, how it is timed.

:data:`GRAPH` is the whole run. An executor (:mod:`clrecon.pipeline.executors`) runs it: a node
(a stage, per pitch or once per run) starts when every node giving what it needs is done.
Serially, overlapped on this machine's cores, or with its units on Dask workers, it is the
same graph and the same stage functions, so the volumes and the numbers are the same bit for
bit. How to add a stage: docs/adding-a-stage.md "A new pipeline stage".

A stage function is ``fn(run, pitch, **needs)``: ``run`` is the run's
:class:`~clrecon.pipeline.context.RunContext`, ``pitch`` the node's pitch (None for a stage
that runs once), and one keyword per product it needs (for a once-per-run stage that needs a
per-pitch product: ``{pitch: value}``; for a product several stages give: ``{(stage, pitch):
value}``). It returns its product, or a :class:`~clrecon.pipeline.executors.base.Work` (units
the executor runs where it likes, their pieces written in this process) whose ``finish`` gives
the product.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from clrecon.pipeline.stages import (
    assemble,
    consistency,
    mc_reconstruct,
    metrics,
    plan,
    reconstruct,
    report,
    results,
    simulate,
    truth,
    truth_free,
)


@dataclass(frozen=True)
class Stage:
    """One stage of the run.

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
    per_pitch: bool = False
    parts: tuple[str, ...] = ()
    rest: str | None = None
    write_part: str | None = None
    skip: Callable | None = None
    optional: bool = False
    ahead: Callable | None = None
    beside: str | None = None
    priority: int = 0


_R = ("read", "noise", "rebin", "interpolate", "fbp", "write_volumes")

#: The run, in the order a serial executor walks it (the per-pitch stages pitch by pitch).
GRAPH = (
    Stage("plan", plan.stage, gives=("plan",), per_pitch=True, parts=("signals", "plan"), rest="plan",
          ahead=plan.ahead),
    Stage("simulate", simulate.stage, ("plan",), ("store",), True, ("simulate",), "simulate", priority=20),
    Stage("truth_free", truth_free.stage, ("plan", "store"), ("tuning",), True, ("truth_free",), "truth_free",
          skip=truth_free.skip, optional=True),
    Stage("reconstruct", reconstruct.stage, ("plan", "store", "tuning"), ("recon", "volume_units"), True, _R,
          write_part="write_volumes", priority=10),
    Stage("mc_reconstruct", mc_reconstruct.stage, ("plan", "store", "recon"), ("mc", "volume_units"), True,
          ("registration", "plane_rows", "mc_backproject", "write_volumes"), "registration",
          write_part="write_volumes", skip=mc_reconstruct.skip, optional=True, priority=5),
    # gives volume_units too: it reads the methods' unit files back, so assemble waits for it
    Stage("consistency", consistency.stage, ("plan", "store", "mc"), ("consistency", "volume_units"), True,
          ("consistency",), "consistency", skip=consistency.skip, optional=True),
    Stage("truth", truth.stage, gives=("truths", "volume_units"), parts=("groundtruth", "phantom_truth"),
          skip=truth.skip, beside="simulate"),
    Stage("assemble", assemble.stage, ("volume_units",), ("volumes",), parts=("assemble_volumes",),
          rest="assemble_volumes"),
    Stage("metrics", metrics.stage, ("volumes",), ("metrics",), parts=("metrics",), rest="metrics",
          skip=metrics.skip),
    Stage("results", results.stage, ("volumes", "metrics"), ("results",)),
    Stage("report", report.stage, ("results",), ("report",), parts=("report",), rest="report", skip=report.skip,
          optional=True),
)
