"""Progress with an ETA for every long stage: a tqdm bar on a terminal, a log line otherwise.

A paper-scale run is often started with ``nohup`` or under a batch scheduler, where stderr is
a file: a tqdm bar there writes a carriage-return update ten times a second into the log. So
:func:`progress` returns a tqdm bar only when stderr is a terminal, and otherwise a
:class:`LogProgress` that writes one line (done/total, rate, elapsed, ETA) at most every
``CLRECON_PROGRESS_INTERVAL`` seconds (default 60) and one when the stage ends.
``CLRECON_NO_PROGRESS=1`` or ``enabled=False`` silences both.
"""

from __future__ import annotations

import os
import sys
import time

from tqdm import tqdm


def _hms(seconds: float) -> str:
    s = int(round(max(seconds, 0.0)))
    return f"{s // 3600:d}:{s // 60 % 60:02d}:{s % 60:02d}"


class LogProgress:
    """A tqdm-like counter (``update``, ``close``, context manager) that logs lines with an ETA."""

    def __init__(self, total: int, desc: str, unit: str = "it", interval: float = 60.0, stream=None):
        self.total, self.desc, self.unit, self.interval = int(total), desc, unit, float(interval)
        self.stream = stream if stream is not None else sys.stderr
        self.n = 0
        self.t0 = self._last = time.perf_counter()
        self._closed = False

    def _line(self, final: bool = False) -> str:
        dt = time.perf_counter() - self.t0
        rate = self.n / dt if dt > 0 else 0.0
        pct = f" ({100.0 * self.n / self.total:.0f} %)" if self.total else ""
        if final:
            return f"[clrecon] {self.desc}: {self.n}/{self.total} {self.unit} in {_hms(dt)} ({rate:.3g} {self.unit}/s)"
        eta = _hms((self.total - self.n) / rate) if rate > 0 else "?"
        return (f"[clrecon] {self.desc}: {self.n}/{self.total} {self.unit}{pct}, {rate:.3g} {self.unit}/s, "
                f"elapsed {_hms(dt)}, ETA {eta}")

    def update(self, n: int = 1) -> None:
        self.n += int(n)
        now = time.perf_counter()
        if now - self._last >= self.interval and self.n < self.total:
            self._last = now
            print(self._line(), file=self.stream, flush=True)

    def close(self) -> None:
        if not self._closed:
            self._closed = True
            print(self._line(final=True), file=self.stream, flush=True)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def progress(total: int, desc: str, enabled: bool = True, unit: str = "it"):
    """A progress counter for a stage of ``total`` steps (see the module docstring)."""
    if not enabled or os.environ.get("CLRECON_NO_PROGRESS") == "1":
        return tqdm(total=total, disable=True)
    if getattr(sys.stderr, "isatty", lambda: False)():
        return tqdm(total=total, desc=desc, unit=unit, leave=False, dynamic_ncols=True)
    return LogProgress(total, desc, unit, interval=float(os.environ.get("CLRECON_PROGRESS_INTERVAL", "60")))
