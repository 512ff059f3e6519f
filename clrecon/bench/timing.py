"""Helpers shared by the bench sections: the machine's load, medians of repeats, numbers for the report."""

from __future__ import annotations

import math
import os
import time

import numpy as np


def load1() -> float:
    """1-minute load average (the bench prints it beside every figure: the machine is shared)."""
    return round(os.getloadavg()[0], 2)


def timed(fn) -> float:
    """Seconds of one call of ``fn``."""
    t0 = time.perf_counter()
    fn()
    return time.perf_counter() - t0


def median_time(fn, repeats: int, warmup: bool = True) -> tuple[float, list]:
    """(median seconds, all seconds) of ``repeats`` calls of ``fn`` after one untimed warm-up."""
    if warmup:
        fn()
    times = [timed(fn) for _ in range(max(1, repeats))]
    return float(np.median(times)), [round(t, 4) for t in times]


def fmt(x, nd=2) -> str:
    """A figure for the report: ``nd`` decimals, 3 significant digits from 1e6 up, "-" if None or not finite."""
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "-"
    if abs(x) >= 1e6:
        return f"{x:.3g}"
    return f"{x:.{nd}f}"
