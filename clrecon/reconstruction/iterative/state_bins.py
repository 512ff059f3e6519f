"""Views grouped by motion state: the iterative method warps its volume once per bin, not per view.

Each view has its recorded state (cardiac phase c in [0, 1), respiratory amplitude a in [0, 1]).
:func:`state_bins` cuts c into ``n_cardiac`` equal bins (periodic) and the amplitude range the
views cover into ``n_resp`` equal bins, drops empty bins, and gives each bin the state its views
sit at on average: the circular mean of c and the mean of a. Within a bin the motion is taken to
be that state's (the binning error: a bin spans 1/n_cardiac of the R-R interval and 1/n_resp of
the amplitude range; docs/iterative.md "Forward model").
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class StateBins:
    """``members``: list of (m_b,) int64 sorted view positions per bin; ``states`` (B, 2) float64 (c, a)."""

    members: list
    states: np.ndarray

    def __len__(self) -> int:
        return len(self.members)


def bin_keys(cardiac_phase, resp_amplitude, n_cardiac: int, n_resp: int) -> np.ndarray:
    """Each view's bin number ``i_c n_resp + i_a`` (see the module docstring): (n,) int64. The same
    arguments and checks as :func:`state_bins`."""
    c = np.asarray(cardiac_phase, np.float64)
    a = np.asarray(resp_amplitude, np.float64)
    if c.shape != a.shape or c.ndim != 1 or c.size == 0:
        raise ValueError(f"cardiac_phase and resp_amplitude must be 1-D of equal, non-zero length; got {c.shape}, "
                         f"{a.shape}")
    if not (np.all(np.isfinite(c)) and np.all(np.isfinite(a))):
        raise ValueError("cardiac_phase and resp_amplitude must be finite")
    for name, v in (("n_cardiac", n_cardiac), ("n_resp", n_resp)):
        if not (isinstance(v, (int, np.integer)) and not isinstance(v, bool) and v >= 1):
            raise ValueError(f"{name} = {v!r}: must be an integer >= 1")
    ic = np.minimum((np.mod(c, 1.0) * n_cardiac).astype(np.int64), n_cardiac - 1)
    lo, hi = float(a.min()), float(a.max())
    span = hi - lo
    ia = np.zeros_like(ic) if span <= 0 else np.minimum(((a - lo) / span * n_resp).astype(np.int64), n_resp - 1)
    return ic * n_resp + ia


def state_bins(cardiac_phase, resp_amplitude, n_cardiac: int, n_resp: int) -> StateBins:
    """Bins of views by (c, a): see the module docstring. ``cardiac_phase`` and ``resp_amplitude``
    are (n,) arrays (the views' recorded states)."""
    key = bin_keys(cardiac_phase, resp_amplitude, n_cardiac, n_resp)
    c = np.asarray(cardiac_phase, np.float64)
    a = np.asarray(resp_amplitude, np.float64)
    order = np.argsort(key, kind="stable")
    _, starts = np.unique(key[order], return_index=True)
    members, states = [], []
    for s0, s1 in zip(starts, list(starts[1:]) + [len(order)], strict=True):
        m = np.sort(order[s0:s1])
        ang = 2 * np.pi * c[m]
        cm = float(np.mod(np.arctan2(np.sin(ang).mean(), np.cos(ang).mean()) / (2 * np.pi), 1.0))
        members.append(m.astype(np.int64))
        states.append((cm, float(a[m].mean())))
    return StateBins(members, np.array(states, np.float64).reshape(-1, 2))
