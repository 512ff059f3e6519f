"""Who runs the graph of stages, and where: serially, overlapped on this machine, or on Dask.

``make("serial" | "local" | "dask", client=...)``; ``run(..., executor=...)`` and
``clrecon run --executor`` take the same names (docs/data-flow.md "Executors").
"""

from __future__ import annotations

from clrecon.core.errors import ClreconError
from clrecon.pipeline.executors.base import Executor, StageClock, Unit, Work
from clrecon.pipeline.executors.dask import DaskExecutor
from clrecon.pipeline.executors.local import LocalExecutor

#: The executors by name, for ``--executor`` and ``run(executor=...)``.
KINDS = ("serial", "local", "dask")

__all__ = ["KINDS", "DaskExecutor", "Executor", "LocalExecutor", "StageClock", "Unit", "Work", "make"]


def make(executor: str | Executor | None = None, client=None) -> Executor:
    """The executor named ``executor`` (None: ``dask`` with a ``client``, else ``local``), or ``executor`` itself."""
    if isinstance(executor, Executor):
        if client is not None and not isinstance(executor, DaskExecutor):
            raise ClreconError(f"executor {executor.kind!r} with a Dask client: give one of them")
        return executor
    kind = executor or ("dask" if client is not None else "local")
    if kind not in KINDS:
        raise ClreconError(f"--executor {kind!r}: must be one of {', '.join(KINDS)}")
    if kind == "dask":
        if client is None:
            raise ClreconError("--executor dask needs a Dask client: --workers N or --cluster ADDRESS "
                               "(in Python: client=)")
        return DaskExecutor(client)
    if client is not None:
        raise ClreconError(f"--executor {kind} with --workers/--cluster: the workers are Dask's (--executor dask)")
    return Executor() if kind == "serial" else LocalExecutor()
