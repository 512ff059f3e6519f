"""Seconds and work counts of one piece of work, by part: what a unit hands its executor.

An algorithm (e.g. :func:`clrecon.reconstruction.reconstruct.reconstruct`) books its own split
into a :class:`StageTimes` (``times.add("fbp", seconds)``, ``times.count("read_cells", n)``);
the executors (:mod:`clrecon.pipeline.executors`) sum those of every unit into the run's stage
table. It lives here, below both, so that neither imports the other for it.
"""

from __future__ import annotations

from dataclasses import dataclass, field


@dataclass
class StageTimes:
    """Seconds per part (``add``; s) and work counts (``count``: e.g. detector cells read, noise cells).

    A key with a ``:`` (``"method:nearest:noisy"``) is the caller's own detail, not a part of
    the stage table.
    """

    seconds: dict = field(default_factory=dict)
    counts: dict = field(default_factory=dict)

    def add(self, name: str, dt: float) -> None:
        self.seconds[name] = self.seconds.get(name, 0.0) + dt

    def count(self, name: str, n) -> None:
        self.counts[name] = self.counts.get(name, 0) + int(n)
