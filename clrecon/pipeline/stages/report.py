"""Stage ``report`` (once per run): ``report.md``, ``report.html`` and the figures
(:func:`clrecon.outputs.report.write_report`), the figures drawn from ``results`` alone in the
executor's helper process where there is one. The two report files are staged (whole, under
their temporary names): :func:`clrecon.pipeline.run.run` puts them under their names once
``results.json`` is whole, so a failed run leaves no report that reads as finished."""

from __future__ import annotations

from clrecon.outputs import report as report_mod


def skip(run) -> str | None:
    return None if run.report else "report=False"


def stage(run, pitch=None, results=None):
    return report_mod.write_report(run.out, results, pool=run.pool, staged=True)
