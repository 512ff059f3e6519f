"""Timing helpers shared by the bench sections: the machine's load and medians of repeats."""

from __future__ import annotations

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
