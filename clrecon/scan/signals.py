"""Breathing and heart rhythm: the recorded signals and the phantom's pose (stage 1 of the pipeline).

Everything here is a fixed, seeded function of time for the whole scene. The random parts
(per-cycle breathing periods and depths, drift, R-R intervals) are drawn once per scene
over a *trace* of ``trace_duration_s(scene)`` seconds = max(60 s, the longest scan over
the scene's pitches) + 5 s margin, and kept (memoised); :func:`physiology` then evaluates
the trace at any times. Evaluating at a subset of times, in any order, gives bit-identical
values, so both pitches of a scene see the same patient.

Recorded traces (``[signals] breathing_trace`` / ``ecg_trace``, and every measured scan) replace
the model's breathing or rhythm by :mod:`clrecon.scan.recorded` (:func:`uses_recorded`); views in
lost or invalid trace stretches are then left out of the planning (:func:`usable_views`).

Conventions
-----------
Respiratory amplitude ``a`` in [0, 1]: **0 = end-exhale, 1 = end-inhale** (the XCAT
convention; clinical 4DCT often calls end-inhale 0 %). Direction: +1 while inhaling,
-1 while exhaling (sign of dr/dt; dr/dt = 0 counts as +1). Cardiac phase ``c`` in [0, 1):
fraction of the current R-R interval, ``c = (t - R_k) / (R_{k+1} - R_k)``, 0 at the R peak.

Breathing (Lujan et al., Med Phys 26:715, 1999)
----------------------------------------------
``r(t) = b cos^(2n)(pi t / tau - phi)``. We write cycle k (start ``T_k``, period ``tau_k``,
depth ``b_k``) from end-exhale to end-exhale, i.e. ``phi = pi/2`` per cycle:
``r(t) = b_k sin^(2n)(pi (t - T_k) / tau_k) + drift(t)``. This keeps r and dr/dt continuous
across cycles whose depth differs. ``tau_k = tau (1 + eps_k)``, ``b_k = b (1 + eta_k)``,
``eps ~ N(0, resp_period_cv)``, ``eta ~ N(0, resp_depth_cv)`` (clipped at 0.3 tau and 0.1 b so
no cycle is degenerate); b = 1 (arbitrary unit, only the normalised amplitude is used).
``drift(t) = resp_drift * b / 2 * sin(2 pi t / P_d + psi)`` with a seeded period
P_d in [40, 80] s: ``resp_drift`` of the mean depth peak to peak. The first cycle starts at a
seeded time in (-tau_0, 0], so t = 0 falls at a random point of the breathing cycle.
Normalised amplitude: ``a = (r - P5) / (P95 - P5)`` with the 5th/95th percentiles of r over
the whole trace (a 5 ms grid), clipped to [0, 1]: keeps the real depth variation.

Breath hold: ``a = breath_hold_amplitude`` everywhere and direction **0** (neither inhaling
nor exhaling), so no caller mistakes a held breath for one half of a cycle.

Heart rhythm (docs/simulation.md "Breathing and heart rhythm")
--------------------------------------------------------------
- ``periodic``: R-R = ``rr_s`` exactly.
- ``hrv``: sinus variability at 0.1 Hz, ``RR_k = rr (1 + sqrt(2) cv sin(2 pi 0.1 R_k + psi))``
  so the CV of R-R is ``cv = rr_cv`` or 3 % when ``rr_cv`` = 0.
- ``af``: i.i.d. log-normal R-R with mean ``rr_s`` and CV ``rr_cv`` or 20 % when 0
  (log-normal: positive and right-skewed like AF R-R histograms), clipped at 0.4 rr.
- ``pvc``: after each normal interval, with probability p the next one is premature,
  ``c rr`` with c ~ U(0.6, 0.7), followed by the compensatory ``(2 - c) rr``. p is set so
  that a fraction ``ectopic_rate`` (0.1 when 0) of all intervals is premature.
The first R peak is at a seeded time in (-RR_0, 0].

Phantom pose (``state_*``)
--------------------------
What the phantom is posed at for each projection. Equal to the recorded signals except:
(a) ``frame_time_s > 0``: the motion is frozen per phantom frame, the state is the signals
evaluated at the frame start ``floor(t / frame) * frame``, while the recorded columns keep
the projection's own time, as a scanner's ECG and respiratory monitor would;
(b) ``phantom.cardiac_motion = false``: ``state_cardiac = 0``;
(c) ``phantom.respiratory_motion = false``: ``state_resp = 0.5`` (mid amplitude, the
scene's single respiratory target), or ``breath_hold_amplitude`` under a breath hold.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np

from clrecon.scan import recorded
from clrecon.scan.config import TRACE_MARGIN_S, TRACE_MIN_S, Acquisition, SignalsConfig  # noqa: F401

#: Sampling step of the grid the amplitude percentiles are taken on (s).
PERCENTILE_GRID_S = 0.005
#: Rhythm defaults used when ``rr_cv`` / ``ectopic_rate`` are 0.
HRV_DEFAULT_CV = 0.03
HRV_FREQUENCY_HZ = 0.1
AF_DEFAULT_CV = 0.20
PVC_DEFAULT_RATE = 0.10
PVC_PREMATURE_RANGE = (0.6, 0.7)

# Independent random streams, so that drawing more of one quantity never shifts another.
_STREAM_RESP_PERIOD, _STREAM_RESP_DEPTH, _STREAM_RESP_MISC, _STREAM_CARDIAC = 1, 2, 3, 4


def _rng(cfg: SignalsConfig, stream: int) -> np.random.Generator:
    return np.random.default_rng(np.random.SeedSequence([cfg.seed, stream]))


@dataclass(frozen=True)
class Physiology:
    """Signals at a set of times; every field has shape (n,).

    cardiac_phase  float64 recorded cardiac phase in [0, 1)
    resp_amplitude float64 recorded respiratory amplitude in [0, 1], 0 end-exhale, 1 end-inhale
    resp_direction int8    +1 inhale, -1 exhale (sign of dr/dt); 0 during a breath hold
    state_cardiac  float64 cardiac phase the phantom is posed at
    state_resp     float64 respiratory amplitude the phantom is posed at
    """

    cardiac_phase: np.ndarray
    resp_amplitude: np.ndarray
    resp_direction: np.ndarray
    state_cardiac: np.ndarray
    state_resp: np.ndarray


@dataclass(frozen=True)
class RespiratoryTrace:
    """The breathing trace of a scene on a regular grid, for plots.

    time_s (m,) s; raw (m,) r(t) in units of the mean depth; amplitude (m,) normalised a in
    [0, 1]; direction (m,) int8; cycle_start_s (K+1,) edges of the breathing cycles (s);
    p5, p95: the percentiles of r that map to a = 0 and a = 1.
    """

    time_s: np.ndarray
    raw: np.ndarray
    amplitude: np.ndarray
    direction: np.ndarray
    cycle_start_s: np.ndarray
    p5: float
    p95: float


def trace_duration_s(scene: Acquisition) -> float:
    """Length of the scene's signal trace (s): :attr:`clrecon.scan.config.Acquisition.trace_duration_s`."""
    return scene.trace_duration_s


# ---------------------------------------------------------------------------------------
# breathing
class _Breathing:
    """Per-cycle breathing parameters of one trace and the percentile normalisation."""

    def __init__(self, cfg: SignalsConfig, duration_s: float):
        tau = cfg.resp_period_s
        self.n = cfg.resp_exponent
        # Enough cycles for the worst case: every period clipped to 0.3 tau.
        k = int(math.ceil((duration_s + tau) / (0.3 * tau))) + 2
        eps = _rng(cfg, _STREAM_RESP_PERIOD).standard_normal(k) * cfg.resp_period_cv
        eta = _rng(cfg, _STREAM_RESP_DEPTH).standard_normal(k) * cfg.resp_depth_cv
        self.tau = tau * np.maximum(1.0 + eps, 0.3)
        self.depth = np.maximum(1.0 + eta, 0.1)
        misc = _rng(cfg, _STREAM_RESP_MISC)
        start = -misc.uniform(0.0, 1.0) * self.tau[0]
        self.drift_period_s = misc.uniform(40.0, 80.0)
        self.drift_phase = misc.uniform(0.0, 2.0 * np.pi)
        self.drift_half = 0.5 * cfg.resp_drift  # b = 1
        self.edges = start + np.concatenate([[0.0], np.cumsum(self.tau)])
        self.duration_s = duration_s
        grid = np.arange(0.0, duration_s, PERCENTILE_GRID_S)
        r, _ = self.raw(grid)
        self.p5, self.p95 = (float(x) for x in np.percentile(r, [5.0, 95.0]))

    def raw(self, t):
        """r(t) and dr/dt (1/s) at times t (s), both shape (n,)."""
        k = np.searchsorted(self.edges, t, side="right") - 1
        tau = self.tau[k]
        x = np.pi * (t - self.edges[k]) / tau
        s, c = np.sin(x), np.cos(x)
        s_pow = s ** (2 * self.n - 1)
        w = 2.0 * np.pi / self.drift_period_s
        arg = w * t + self.drift_phase
        r = self.depth[k] * s_pow * s + self.drift_half * np.sin(arg)
        dr = self.depth[k] * (2 * self.n) * s_pow * c * (np.pi / tau) + self.drift_half * w * np.cos(arg)
        return r, dr

    def amplitude(self, t):
        """Normalised amplitude in [0, 1] and direction (int8 +1/-1) at times t (s)."""
        r, dr = self.raw(t)
        span = self.p95 - self.p5
        # A span of 0 cannot happen with depth >= 0.1, but never divide by it.
        a = np.clip((r - self.p5) / span, 0.0, 1.0) if span > 1e-12 else np.full_like(r, 0.5)
        return a, np.where(dr >= 0.0, 1, -1).astype(np.int8)


# ---------------------------------------------------------------------------------------
# heart rhythm
def _rr_intervals(cfg: SignalsConfig, duration_s: float) -> np.ndarray:
    """R peak times (s), strictly increasing, the first <= 0 and the last > duration_s."""
    rng = _rng(cfg, _STREAM_CARDIAC)
    rr = cfg.rr_s
    start_frac = rng.uniform(0.0, 1.0)
    # Upper bound on the beat count: no interval is shorter than 0.4 rr.
    n_max = int(math.ceil(duration_s / (0.4 * rr))) + 4
    if cfg.rhythm == "periodic":
        intervals = np.full(n_max, rr)
    elif cfg.rhythm == "af":
        cv = cfg.rr_cv if cfg.rr_cv > 0 else AF_DEFAULT_CV
        sigma2 = math.log1p(cv * cv)
        intervals = rng.lognormal(math.log(rr) - 0.5 * sigma2, math.sqrt(sigma2), n_max)
        intervals = np.maximum(intervals, 0.4 * rr)
    elif cfg.rhythm == "hrv":
        cv = cfg.rr_cv if cfg.rr_cv > 0 else HRV_DEFAULT_CV
        psi = rng.uniform(0.0, 2.0 * np.pi)
        intervals = np.empty(n_max)
        t = -start_frac * rr  # beat times feed back into the modulation: a short loop
        for i in range(n_max):
            intervals[i] = rr * (1.0 + math.sqrt(2.0) * cv * math.sin(2.0 * np.pi * HRV_FREQUENCY_HZ * t + psi))
            t += intervals[i]
    elif cfg.rhythm == "pvc":
        rate = cfg.ectopic_rate if cfg.ectopic_rate > 0 else PVC_DEFAULT_RATE
        # Each PVC takes two intervals (premature + compensatory): a fraction `rate` of
        # all intervals is premature when a normal interval is followed by one with p.
        p = min(rate / (1.0 - rate), 1.0)
        # Two draws per beat, interleaved, so the first beats never depend on n_max.
        draws = rng.uniform(0.0, 1.0, (n_max, 2))
        u = draws[:, 0]
        lo, hi = PVC_PREMATURE_RANGE
        cs = lo + (hi - lo) * draws[:, 1]
        intervals = np.empty(n_max)
        i = 0
        while i < n_max:
            if u[i] < p and i + 1 < n_max:
                intervals[i], intervals[i + 1] = cs[i] * rr, (2.0 - cs[i]) * rr
                i += 2
            else:
                intervals[i] = rr
                i += 1
    else:  # pragma: no cover - the scene validates the rhythm
        raise ValueError(f"signals.rhythm = {cfg.rhythm!r}: unknown")
    peaks = -start_frac * intervals[0] + np.concatenate([[0.0], np.cumsum(intervals)])
    return peaks


class _Trace:
    def __init__(self, cfg: SignalsConfig, duration_s: float):
        self.cfg = cfg
        self.duration_s = duration_s
        self.breathing = _Breathing(cfg, duration_s)
        self.r_peaks = _rr_intervals(cfg, duration_s)

    def cardiac_phase(self, t):
        k = np.searchsorted(self.r_peaks, t, side="right") - 1
        c = (t - self.r_peaks[k]) / (self.r_peaks[k + 1] - self.r_peaks[k])
        # Rounding can give exactly 1.0 just before the next peak; the phase lives in [0, 1).
        return np.minimum(c, np.nextafter(1.0, 0.0))

    def respiratory(self, t):
        if self.cfg.breath_hold:
            return (np.full(t.shape, self.cfg.breath_hold_amplitude, dtype=np.float64),
                    np.zeros(t.shape, dtype=np.int8))
        return self.breathing.amplitude(t)


@functools.lru_cache(maxsize=16)
def _trace(cfg: SignalsConfig, duration_s: float) -> _Trace:
    return _Trace(cfg, duration_s)


def _scene_trace(scene: Acquisition) -> _Trace:
    return _trace(scene.signals, trace_duration_s(scene))


def _check_times(t_s, duration_s: float) -> np.ndarray:
    t = np.asarray(t_s, dtype=np.float64)
    if t.ndim != 1:
        raise ValueError(f"t_s must be a 1-D array of times in s, got shape {t.shape}")
    if t.size and (not np.all(np.isfinite(t)) or t.min() < 0.0 or t.max() > duration_s):
        raise ValueError(f"times must lie in [0, {duration_s:.3f}] s (the scene's signal trace), "
                         f"got [{np.nanmin(t):.3f}, {np.nanmax(t):.3f}]")
    return t


# ---------------------------------------------------------------------------------------
def physiology(scene: Acquisition, t_s) -> Physiology:
    """Recorded signals and phantom pose at acquisition times.

    Parameters
    ----------
    scene : Scene
    t_s : array_like, shape (n,)
        Times in s, within ``[0, trace_duration_s(scene)]``.

    Returns
    -------
    Physiology
        Arrays of shape (n,); see the module docstring for the conventions.
    """
    if uses_recorded(scene):
        t = np.asarray(t_s, dtype=np.float64)
        signals_at = functools.partial(_recorded_signals, scene)
    else:
        tr = _scene_trace(scene)
        t = _check_times(t_s, tr.duration_s)

        def signals_at(tt):
            return (tr.cardiac_phase(tt),) + tuple(tr.respiratory(tt))
    c, a, direction = signals_at(t)

    frame = scene.signals.frame_time_s
    if frame > 0:
        t_state = np.floor(t / frame) * frame
        c_state, a_state, _ = signals_at(t_state)
    else:
        c_state, a_state = c.copy(), a.copy()
    if not scene.phantom.cardiac_motion:
        c_state = np.zeros_like(c)
    if scene.signals.breath_hold:
        a_state = np.full_like(a, scene.signals.breath_hold_amplitude)
    elif not scene.phantom.respiratory_motion:
        a_state = np.full_like(a, 0.5)
    return Physiology(cardiac_phase=c, resp_amplitude=a, resp_direction=direction,
                      state_cardiac=c_state, state_resp=a_state)


def uses_recorded(scene: Acquisition) -> bool:
    """True when a recorded trace (or a measured scan) supplies some of the signals (:mod:`clrecon.scan.recorded`)."""
    return bool(scene.signals.breathing_trace or scene.signals.ecg_trace or scene.measured)


def _recorded_signals(scene: Acquisition, t: np.ndarray):
    """(c, a, direction) at times t where recorded traces replace the model; the model fills a signal
    without a trace in a simulated scene; a measured scene without one has c = 0 / a = 0.5, direction 0."""
    vs = recorded.view_signals(scene.signals, t)
    sig = scene.signals
    model = None
    if not scene.measured and not (sig.breathing_trace and sig.ecg_trace):
        model = _scene_trace(scene)
        _check_times(t, model.duration_s)
    c = vs.cardiac_phase if (sig.ecg_trace or model is None) else model.cardiac_phase(t)
    if sig.breathing_trace or model is None:
        a, d = vs.resp_amplitude, vs.resp_direction
    else:
        a, d = model.respiratory(t)
    return c, a, d


def usable_views(scene: Acquisition, t_s) -> tuple[np.ndarray, dict]:
    """(usable (n,) bool, reason -> views left out) at scan times ``t_s``: all usable without a recorded trace."""
    t = np.asarray(t_s, dtype=np.float64)
    if not uses_recorded(scene):
        return np.ones(t.shape, bool), {}
    vs = recorded.view_signals(scene.signals, t)
    return vs.usable, vs.excluded


def r_peaks(scene: Acquisition) -> np.ndarray:
    """R-peak times (s) of the scene's trace, shape (K,), strictly increasing.

    The first peak is at or before 0 and the last after ``trace_duration_s(scene)``, so
    every time of the trace lies inside an R-R interval.
    """
    return _scene_trace(scene).r_peaks.copy()


def respiratory_trace(scene: Acquisition, step_s: float = 0.02) -> RespiratoryTrace:
    """The scene's breathing trace sampled every ``step_s`` seconds over the whole trace."""
    tr = _scene_trace(scene)
    t = np.arange(0.0, tr.duration_s, step_s)
    raw, _ = tr.breathing.raw(t)
    a, direction = tr.respiratory(t)
    return RespiratoryTrace(time_s=t, raw=raw, amplitude=a, direction=direction,
                            cycle_start_s=tr.breathing.edges.copy(), p5=tr.breathing.p5,
                            p95=tr.breathing.p95)
