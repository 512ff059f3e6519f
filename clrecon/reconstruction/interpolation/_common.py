"""Helpers shared by the interpolation methods: chunking, deltas, nearest point, 1-D bracket."""

from __future__ import annotations

import numpy as np

from clrecon.core.conventions import circular_difference
from clrecon.reconstruction.interpolation.base import Chunk

LOCAL = 64  # fixed work-group size of the interp.cl kernels (PoCL specialises binaries per local size)


def chunk(c, a, off, g0, g1, dz=None) -> Chunk:
    """Groups g0..g1 of the flat (n,) ``c``, ``a`` (and optional ``dz``, mm) padded to (g, N)."""
    counts = np.diff(off[g0:g1 + 1])
    n = max(int(counts.max(initial=0)), 2)  # >= 2: argpartition(kth=1) needs two columns
    j = np.arange(n)
    valid = j[None, :] < counts[:, None]
    flat = np.minimum(off[g0:g1, None] + j[None, :], max(c.size - 1, 0))
    cc = np.where(valid, c[flat] if c.size else 0.0, 0.0)
    aa = np.where(valid, a[flat] if a.size else 0.0, 0.0)
    zz = None if dz is None else np.where(valid, dz[flat] if dz.size else 0.0, np.inf)
    return Chunk(c=cc, a=aa, valid=valid, counts=counts, start=off[g0:g1], dz=zz)


def deltas(ch: Chunk, targets, use_cardiac: bool, use_resp: bool, cardiac_scale: float = 1.0):
    """dc, da, squared distance (g, T, N); invalid points have distance inf.

    The squared distance is ``(cardiac_scale dc)^2 + da^2`` (``recon.cardiac_distance_scale``,
    dimensionless); dc and da themselves are unscaled.
    """
    if use_cardiac:
        dc = circular_difference(ch.c[:, None, :], targets[None, :, 0, None])
    else:
        dc = np.zeros((ch.c.shape[0], targets.shape[0], ch.c.shape[1]))
    if use_resp:
        da = ch.a[:, None, :] - targets[None, :, 1, None]
    else:
        da = np.zeros_like(dc)
    sdc = dc if cardiac_scale == 1.0 else cardiac_scale * dc
    d2 = np.where(ch.valid[:, None, :], sdc * sdc + da * da, np.inf)
    return dc, da, d2


def take(x, idx):
    return np.take_along_axis(x, idx, axis=-1)


def nearest(d2):
    """The nearest point, (g, T, 1)."""
    idx = np.argmin(d2, axis=-1)[..., None]
    return idx, np.ones(idx.shape)


def bracket(x, valid, max_gap=None, with_both=False):
    """1-D linear interpolation at x = 0 between the bracketing points, (g, T, 2).

    Outside the sampled range (one side empty) or, with ``max_gap``, when a bracketing point
    is farther than ``max_gap``: the nearest point. ``with_both``: also return the (g, T)
    bool array, True where the two bracketing points were used (False: the nearest).
    """
    v = valid[:, None, :] if valid.ndim == 2 else valid
    lo_val = np.where(v & (x <= 0), x, -np.inf)
    hi_val = np.where(v & (x >= 0), x, np.inf)
    lo = np.argmax(lo_val, axis=-1)
    hi = np.argmin(hi_val, axis=-1)
    xl = take(lo_val, lo[..., None])[..., 0]
    xh = take(hi_val, hi[..., None])[..., 0]
    both = np.isfinite(xl) & np.isfinite(xh)
    if max_gap is not None:
        both &= (-xl <= max_gap) & (xh <= max_gap)
    span = np.where(both, xh - xl, 1.0)
    t = np.where(both & (span > 0), -np.where(both, xl, 0.0) / np.where(span > 0, span, 1.0), 0.0)
    # one side only, or a gap too wide: the nearest of the two (an absent side is at inf)
    near_lo = np.abs(np.where(np.isfinite(xl), xl, np.inf)) <= np.abs(np.where(np.isfinite(xh), xh, np.inf))
    first = np.where(both | near_lo, lo, hi)
    idx = np.stack([first, hi], axis=-1)
    w = np.stack([np.where(both, 1.0 - t, 1.0), np.where(both, t, 0.0)], axis=-1)
    if with_both:
        return idx, w, both
    return idx, w
