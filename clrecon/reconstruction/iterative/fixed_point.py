"""The host side of the deterministic fixed-point scatter (``kernels/fixed_add.h``).

A scatter kernel adds each float32 contribution ``c``, rounded to the integer ``rint(c 2^S)``,
into a two's-complement 64-bit accumulator per output voxel (two uint32 words, low then high)
with 32-bit atomics and an exact carry. Integer addition is associative, so the sum is
bit-identical whatever the order of the additions. The host picks ``S`` from a bound on any
voxel's |sum| (:func:`scale_exponent`) and converts the words back (:func:`to_float`).
"""

from __future__ import annotations

import math

import numpy as np

#: headroom: S is chosen so that no voxel's |sum| exceeds 2^FIXED_BITS quanta (int64 holds 2^63)
FIXED_BITS = 61


def scale_exponent(bound: float) -> int:
    """The largest S with ``bound 2^S <= 2^FIXED_BITS``, clipped to [-100, 100] (the scale is a
    float32 in the kernel); 0 for a bound that is 0. ``bound``: an upper bound on every output's |sum|."""
    b = float(bound)
    if not math.isfinite(b) or b < 0:
        raise ValueError(f"bound = {bound!r}: must be finite and >= 0")
    if b == 0:
        return 0
    return int(np.clip(math.floor(FIXED_BITS - math.log2(b)), -100, 100))


def to_float(words: np.ndarray, S: int, shape: tuple) -> np.ndarray:
    """Accumulator words (n, 2) uint32 (low, high) -> (shape) float32: the int64 sums times 2^-S."""
    w = np.asarray(words, np.uint32).reshape(-1, 2)
    fixed = ((w[:, 1].astype(np.uint64) << np.uint64(32)) | w[:, 0].astype(np.uint64)).view(np.int64)
    return (fixed.astype(np.float64) * 2.0 ** -S).astype(np.float32).reshape(shape)


def zero_accumulator(rt, n: int):
    """A read-write device buffer of ``n`` zeroed accumulators (2 n uint32 words)."""
    nbytes = 8 * max(int(n), 1)
    if nbytes > rt.max_alloc_bytes:
        raise MemoryError(f"accumulator: one device buffer of {nbytes / 2**30:.2f} GiB (8 bytes per voxel) is above "
                          f"the device's largest allocation ({rt.max_alloc_bytes / 2**30:.2f} GiB)")
    mf = rt.cl.mem_flags
    return rt.cl.Buffer(rt.context, mf.READ_WRITE | mf.COPY_HOST_PTR, hostbuf=np.zeros(2 * max(int(n), 1), np.uint32))
