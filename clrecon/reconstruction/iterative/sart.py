"""Ordered-subset SART (simultaneous algebraic reconstruction), with its residual and a stopping rule.

For a linear operator split into subsets A_s (``op.forward(x, s)``, ``op.adjoint(r, s)``,
``op.n_subsets``, ``op.unknown_shape``) and data p_s (``data(s)``), one *epoch* visits every
subset once in order and updates

    x <- x + lam C_s^-1 A_s^T R_s^-1 (p_s - A_s x),   R_s = |A_s| 1,  C_s = |A_s|^T 1

(Andersen and Kak 1984; the ordered-subset form of Wang and Jiang 2004), then clamps x at 0
where ``nonnegative`` (with a stacked unknown (K, ...), its first component, the attenuation) and
applies the operator's own constraint where it has one (``op.constrain(x, epoch_end)`` after
every subset and after every epoch: the motion operator's density term, :mod:`motion_operator`).
R_s is each ray's length through the volume (mm); rays shorter than ``min_ray_mm`` carry no
update (grazing rays would divide by almost nothing); C_s is each voxel's total weight in the
subset, and voxels with C_s = 0 are left alone. R_s and C_s are computed once per subset, the
first time it is visited, and kept only where a later epoch will visit it again (``epochs`` > 1:
one epoch holds one subset's weights at a time, not one volume per subset). An operator with
``direction_and_col_sums(r, w, s)`` gives C_s and that visit's update from one pass over the rays
(a backprojector's pair), and ``row_sums(s)`` where it knows R_s without projecting (a ray's chord).

**Residual**: the data misfit ``||p - A x|| / ||p||`` (relative, over all subsets' rays). The
*running* residual of an epoch sums ``||p_s - A_s x||^2`` as each subset is visited (before its
update); it costs nothing extra. An operator with entries of both signs (the density term's)
provides ``row_sums(s)`` and ``col_sums(w, s)`` for |A_s|; otherwise A_s itself is used; an
operator may steer part of the unknown itself (``update_direction(r, s)`` instead of A_s^T r:
the density term's once-per-epoch step). The
exact residual of the initial and the final volume costs one forward pass each (A is ~5x
cheaper than A^T) and is always computed.

**Stopping rule**: at most ``epochs`` epochs; stop earlier when an epoch lowered the running
residual by less than ``tol`` (relative) against the previous epoch's. The relaxation of epoch k
(0-based) is ``relaxation / (1 + decay k)``: OS methods with a fixed relaxation end in a limit
cycle between subsets; a decaying one lets the last epochs settle.

**Never worse than the start without saying so**: if the final exact residual exceeds the
initial volume's, :func:`os_sart` returns the initial volume and says so in its history
(``stop`` = ``"diverged: returned the initial volume"``).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True, kw_only=True)
class SARTConfig:
    """``epochs`` >= 1, ``relaxation`` in (0, 2), ``decay`` >= 0, ``tol`` >= 0, ``min_ray_mm`` >= 0."""

    epochs: int = 4
    relaxation: float = 1.0
    decay: float = 0.5
    tol: float = 0.01
    nonnegative: bool = True
    min_ray_mm: float = 1.0

    def __post_init__(self):
        if not (isinstance(self.epochs, (int, np.integer)) and not isinstance(self.epochs, bool) and self.epochs >= 1):
            raise ValueError(f"epochs = {self.epochs!r}: must be an integer >= 1")
        if not (0.0 < float(self.relaxation) < 2.0):
            raise ValueError(f"relaxation = {self.relaxation!r}: must be in (0, 2)")
        for name in ("decay", "tol", "min_ray_mm"):
            v = float(getattr(self, name))
            if not (np.isfinite(v) and v >= 0):
                raise ValueError(f"{name} = {getattr(self, name)!r}: must be a finite number >= 0")


@dataclass
class SARTHistory:
    """What the solver did: ``initial`` / ``final`` exact relative residuals, ``running`` (one per
    epoch), ``seconds`` (per epoch), ``relaxation`` (per epoch), ``stop`` (why it stopped)."""

    initial: float = float("nan")
    final: float = float("nan")
    running: list = field(default_factory=list)
    seconds: list = field(default_factory=list)
    relaxation: list = field(default_factory=list)
    stop: str = ""

    def as_dict(self) -> dict:
        return {"initial": self.initial, "final": self.final, "running": list(self.running),
                "seconds": list(self.seconds), "relaxation": list(self.relaxation), "stop": self.stop}


def residual(op, data, x) -> tuple[float, float]:
    """(||p - A x||^2, ||p||^2) over all subsets, float64."""
    rr = pp = 0.0
    for s in range(op.n_subsets):
        p = np.asarray(data(s), np.float64)
        r = p - op.forward(x, s)
        rr += float(np.sum(r * r))
        pp += float(np.sum(p * p))
    return rr, pp


def _inverse_cols(C) -> np.ndarray:
    """C_s^-1 where C_s > 0, else 0 (voxels no ray of the subset reaches are left alone)."""
    return np.where(C > 0, 1.0 / np.maximum(C, 1e-30), 0.0).astype(np.float32)


def os_sart(op, data, x0, cfg: SARTConfig = SARTConfig(), log=None) -> tuple[np.ndarray, SARTHistory]:
    """Run OS-SART from ``x0`` (``op.unknown_shape``); returns (x float32, :class:`SARTHistory`).

    ``data(s)`` returns subset s's measured projections (shape of ``op.forward(x, s)``); ``log``,
    if given, is called with one line per epoch (residual, seconds, an ETA).
    """
    x = np.array(x0, np.float32, copy=True)
    if x.shape != tuple(op.unknown_shape):
        raise ValueError(f"x0: expected shape {tuple(op.unknown_shape)}, got {x.shape}")
    hist = SARTHistory()
    rr0, pp = residual(op, data, x)
    if pp <= 0:
        raise ValueError("the data are all zero: nothing to reconstruct")
    hist.initial = float(np.sqrt(rr0 / pp))
    rows, cols = {}, {}
    row_sums = getattr(op, "row_sums", lambda s: op.forward(np.ones(op.unknown_shape, np.float32), s))
    col_sums = getattr(op, "col_sums", op.adjoint)
    direction = getattr(op, "update_direction", op.adjoint)
    constrain = getattr(op, "constrain", None)
    paired = hasattr(op, "direction_and_col_sums")
    keep = cfg.epochs > 1
    attenuation = x[0] if x.ndim == 4 else x          # a view: the component kept >= 0
    prev = None
    hist.stop = f"reached {cfg.epochs} epochs"
    for k in range(cfg.epochs):
        t0 = time.perf_counter()
        lam = float(cfg.relaxation) / (1.0 + float(cfg.decay) * k)
        run = 0.0
        for s in range(op.n_subsets):
            p = np.asarray(data(s), np.float32)
            first = s not in rows
            if first:
                R = row_sums(s)
                rows[s] = np.where(R > cfg.min_ray_mm, 1.0 / np.maximum(R, 1e-30), 0.0).astype(np.float32)
                mask = np.where(rows[s] > 0, 1.0, 0.0).astype(np.float32)
                if not paired:
                    cols[s] = _inverse_cols(col_sums(mask, s))
            r = p - op.forward(x, s)
            run += float(np.sum(r.astype(np.float64) ** 2))
            if first and paired:
                d, C = op.direction_and_col_sums(r * rows[s], mask, s)
                cols[s] = _inverse_cols(C)
            else:
                d = direction(r * rows[s], s)
            x += lam * cols[s] * d
            if not keep:                      # no later epoch visits s: its weights go now
                del rows[s], cols[s]
            if cfg.nonnegative:
                np.maximum(attenuation, 0.0, out=attenuation)
            if constrain:
                constrain(x, epoch_end=False)
        if constrain:
            constrain(x, epoch_end=True)
        hist.running.append(float(np.sqrt(run / pp)))
        hist.seconds.append(time.perf_counter() - t0)
        hist.relaxation.append(lam)
        if log:
            left = (cfg.epochs - k - 1) * float(np.median(hist.seconds))
            log(f"OS-SART epoch {k + 1}/{cfg.epochs}: running residual {hist.running[-1]:.5f} "
                f"(start {hist.initial:.5f}), {hist.seconds[-1]:.1f} s, ETA {left:.0f} s at most")
        if prev is not None and prev - hist.running[-1] < cfg.tol * prev:
            hist.stop = f"residual fell by less than {cfg.tol:g} (relative) in epoch {k + 1}"
            break
        prev = hist.running[-1]
    rr1, _ = residual(op, data, x)
    hist.final = float(np.sqrt(rr1 / pp))
    if hist.final > hist.initial:
        hist.stop = "diverged: returned the initial volume"
        if log:
            log(f"OS-SART: final residual {hist.final:.5f} above the initial {hist.initial:.5f}; "
                "returning the initial volume")
        return np.array(x0, np.float32, copy=True), hist
    return x, hist
