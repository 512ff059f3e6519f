"""Stage ``assemble`` (once per run): ``volumes.h5`` made from the volume unit files, in place
(:meth:`clrecon.outputs.volumes.VolumeWriter.assemble`), once every stage that writes volume
units is done (``after``: :data:`clrecon.pipeline.graph.VOLUME_WRITERS`); :func:`close` renames it
into place at the end. Its product, ``volumes``, is the assembled file open for reading."""

from __future__ import annotations

import time


def stage(run, pitch=None):
    return run.writer.assemble()


def close(run) -> None:
    """Finish ``volumes.h5`` (timed as ``assemble_volumes``); the previous run's results and report
    are removed first: they must not describe the new volumes, even for a moment."""
    for name in ("results.json", "report.md", "report.html"):
        (run.out / name).unlink(missing_ok=True)
    t0 = time.perf_counter()
    run.writer.close()
    run.clock.add("assemble_volumes", time.perf_counter() - t0)
