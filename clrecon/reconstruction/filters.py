"""Ramp-filter windows (``recon.filter``): the one list, a registry of window functions.

A window is ``window(f) -> multiplier`` with ``f`` (n,) the FFT frequencies in cycles per
sample (Nyquist 0.5, :func:`scipy.fft.fftfreq` order); :func:`clrecon.reconstruction.fbp.ramp_filter_response`
multiplies the ramp's response by it. A new window is one ``@FILTERS.register("name")``
function here. Imports only ``clrecon.core`` and NumPy (the config layer reads the names).
"""

from __future__ import annotations

import numpy as np

from clrecon.core.registry import Registry

FILTERS: Registry = Registry("ramp filter window")


@FILTERS.register("ram-lak")
def ram_lak(f: np.ndarray) -> np.ndarray:
    """The plain band-limited ramp: 1."""
    return np.ones_like(f)


@FILTERS.register("shepp-logan")
def shepp_logan(f: np.ndarray) -> np.ndarray:
    """``sinc(f)``."""
    return np.sinc(f)


@FILTERS.register("hann")
def hann(f: np.ndarray) -> np.ndarray:
    """``(1 + cos 2 pi f) / 2``."""
    return 0.5 * (1.0 + np.cos(2.0 * np.pi * f))
