"""Recorded motion signals: a breathing trace and an ECG, read from files (stage 1 of the pipeline).

``[signals] breathing_trace = "FILE"`` and ``ecg_trace = "FILE"`` replace the modelled breathing
and heart rhythm (:mod:`clrecon.scan.signals`) by what a scanner recorded. Conventions
(``docs/measured-data.md`` "Recorded signals"):

Breathing trace
---------------
- **Varian RPM** ``.vxp`` (versions 1.5/1.6): a ``[Header]`` block of ``Key=Value`` lines, of
  which ``Data_layout`` (the column names), ``Samples_per_second`` and ``Scale_factor`` are
  required, then ``[Data]`` and one comma-separated row per sample in the ``Data_layout``
  order (``amplitude, phase, timestamp, validflag, ttlin, mark, ttlout``). ``timestamp`` is in
  ms; the amplitude in cm is ``amplitude * Scale_factor / 10``; ``validflag`` >= 0 is a valid
  periodic signal, -1 lost tracking, -2 non-periodic breathing (e.g. coughing); ``ttlin`` = 1
  while the CT beam is on (the scanner's X-ray-on signal into RPM); ``mark`` is ``Z`` at phase
  0, ``P`` at phase pi or empty.
- **CSV** with the header ``time_s,amplitude`` (optional third column ``valid``: 1 or 0).
- Inhalation raises the amplitude (``breathing_inhale = "up"``); ``"down"`` negates it.

ECG
---
- **CSV** of R-peak times: header ``r_peak_s``, one time (s) per row, strictly increasing.
- **WFDB** record (``.hea`` header with its signal file): the R peaks are detected on its first
  channel with :func:`wfdb.processing.xqrs_detect`.

Alignment: trace time = scan time + ``trace_offset_s`` (``trace_align = "offset"``), or, with
``trace_align = "beam-on"``, the trace time of the first ``ttlin = 1`` sample of the ``.vxp``
is scan time 0. ECG time = scan time + ``ecg_offset_s``.

Per view
--------
- Cardiac phase ``c = (t - R_k) / (R_{k+1} - R_k)`` in [0, 1) (as the model's).
- Respiratory amplitude: ``a = clip((r - P5) / (P95 - P5), 0, 1)`` with the 5th/95th
  percentiles (``numpy.percentile``, linear) of the valid samples of the **whole** trace, r
  linearly interpolated at the view time. The model normalises over its whole trace the same way.
- Direction: sign of the slope of the two samples bracketing the view (+1 when flat).
- A view is **left out** (``usable`` false) when a bracketing sample is flagged (-1 or -2,
  or ``valid`` = 0 in a CSV), has no finite amplitude (a ``.vxp`` row whose amplitude is ``nan``
  or ``inf``: a lost RPM sample; counted as ``non_finite_amplitude``), or the two bracketing
  samples are further apart than ``GAP_FACTOR`` times the nominal sample interval (a gap in the
  trace). A lost sample's amplitude is filled from its finite neighbours (every number stays
  finite) and never enters the percentiles.
- A non-finite time (a ``.vxp`` timestamp, a CSV time, an R peak), validflag or ttlin, and a
  non-finite CSV amplitude of a sample not marked ``valid`` = 0, is an error naming the file,
  the line and the value (:class:`InputError`); so is a WFDB record with a missing (NaN) sample.
- A trace or ECG that does not cover every view is an error (:class:`InputError`), as is an
  ECG with fewer than two R peaks.
"""

from __future__ import annotations

import csv
import functools
import hashlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from clrecon.core.errors import InputError, SceneError


def trace_files(path) -> list[Path]:
    """The files of a recorded trace: the file itself, or every file of a WFDB record (``.hea`` or its
    base name); empty when there is none."""
    p = Path(path)
    if p.suffix.lower() in (".hea", ".dat") or (not p.suffix and p.with_suffix(".hea").exists()):
        base = p.with_suffix("")
        return sorted(q for q in base.parent.glob(base.name + ".*") if q.is_file())
    return [p] if p.is_file() else []


def file_digest(path) -> str:
    """BLAKE2b (16 hex) of a file's bytes; a WFDB record (``.hea`` or its base name): of all its files."""
    p = Path(path)
    files = trace_files(p)
    if not files:
        raise SceneError(f"{p}: no such file")
    h = hashlib.blake2b(digest_size=8)
    for q in files:
        h.update(q.name.encode())
        h.update(q.read_bytes())
    return h.hexdigest()


#: Two samples further apart than this many nominal sample intervals bracket a gap.
GAP_FACTOR = 2.5
#: Percentiles of the valid trace samples that map to amplitude 0 and 1.
NORMALISE_PERCENTILES = (5.0, 95.0)
#: Columns a .vxp Data_layout must name.
VXP_REQUIRED = ("amplitude", "timestamp", "validflag")
#: Reasons a view is left out, as counted in results.json.
EXCLUSION_REASONS = ("lost_tracking", "non_periodic", "trace_gap", "invalid", "non_finite_amplitude")
#: ``BreathingTrace.status`` of each reason a sample is not valid.
STATUS = {"lost_tracking": -1, "non_periodic": -2, "invalid": -3, "non_finite_amplitude": -4}


@dataclass(frozen=True)
class BreathingTrace:
    """A breathing trace as read.

    time_s    (m,) float64 trace time (s), strictly increasing
    amplitude (m,) float64 raw amplitude (cm for .vxp, file units for CSV), inhale = larger
    status    (m,) int8    0 valid, -1 lost tracking, -2 non-periodic, -3 invalid (CSV valid = 0),
                           -4 no finite amplitude (a lost .vxp sample; its amplitude filled from its neighbours)
    sample_s  float        nominal sample interval (s)
    beam_on_s float | None trace time of the first ttlin = 1 sample (None without a ttlin column)
    path      str
    """

    time_s: np.ndarray
    amplitude: np.ndarray
    status: np.ndarray
    sample_s: float
    beam_on_s: float | None
    path: str

    def percentiles(self) -> tuple[float, float]:
        """(P5, P95) of the valid samples: the amplitudes that map to 0 and 1."""
        ok = self.status == 0
        if ok.sum() < 2:
            lost = int((self.status == STATUS["non_finite_amplitude"]).sum())
            raise InputError(f"{self.path}: fewer than 2 valid samples with a finite amplitude (validflag >= 0"
                             f"{f'; {lost} of {self.status.size} amplitudes are nan or inf' if lost else ''}); "
                             f"cannot normalise the amplitude")
        lo, hi = (float(x) for x in np.percentile(self.amplitude[ok], NORMALISE_PERCENTILES))
        if not hi > lo:
            raise InputError(f"{self.path}: the valid amplitudes have no spread (P5 = P95 = {lo:g}); "
                             f"expected a breathing trace")
        return lo, hi


@dataclass(frozen=True)
class RPeaks:
    """R-peak times (k,) float64 s, strictly increasing, read from ``path`` (``kind`` csv or wfdb)."""

    time_s: np.ndarray
    path: str
    kind: str


@dataclass(frozen=True)
class ViewSignals:
    """What the recorded signals give each view; arrays of shape (n,).

    cardiac_phase  float64 in [0, 1) (0 where no ECG)
    resp_amplitude float64 in [0, 1] (0.5 where no breathing trace)
    resp_direction int8    +1 inhale, -1 exhale (0 where no breathing trace)
    usable         bool    False: left out (lost or invalid trace stretch)
    excluded       dict    reason -> number of views left out for it (EXCLUSION_REASONS)
    """

    cardiac_phase: np.ndarray
    resp_amplitude: np.ndarray
    resp_direction: np.ndarray
    usable: np.ndarray
    excluded: dict


# ---------------------------------------------------------------------------------------
# breathing traces
def read_breathing_trace(path, inhale: str = "up") -> BreathingTrace:
    """A ``.vxp`` or ``time_s,amplitude`` CSV breathing trace (see the module docstring)."""
    p = Path(path)
    if not p.is_file():
        raise InputError(f"{p}: breathing trace not found")
    tr = _read_vxp(p) if p.suffix.lower() == ".vxp" else _read_breathing_csv(p)
    if inhale == "down":
        tr = BreathingTrace(time_s=tr.time_s, amplitude=-tr.amplitude, status=tr.status, sample_s=tr.sample_s,
                            beam_on_s=tr.beam_on_s, path=tr.path)
    return tr


def _read_vxp(p: Path) -> BreathingTrace:
    lines = p.read_text(errors="replace").splitlines()
    if not lines or lines[0].strip() != "[Header]":
        raise InputError(f"{p}: line 1 is {lines[0].strip()[:40] if lines else ''!r}; a .vxp file starts with [Header]")
    header: dict[str, str] = {}
    data_at = None
    for i, line in enumerate(lines[1:], start=2):
        s = line.strip()
        if s == "[Data]":
            data_at = i
            break
        if "=" in s:
            k, v = s.split("=", 1)
            header[k.strip()] = v.strip()
    if data_at is None:
        raise InputError(f"{p}: no [Data] line; a .vxp file has [Header] then [Data]")
    for key in ("Data_layout", "Samples_per_second", "Scale_factor"):
        if key not in header:
            raise InputError(f"{p}: [Header] has no {key}=; expected Data_layout, Samples_per_second and Scale_factor")
    layout = [c.strip().lower() for c in header["Data_layout"].split(",")]
    missing = [c for c in VXP_REQUIRED if c not in layout]
    if missing:
        raise InputError(f"{p}: Data_layout={header['Data_layout']} lacks {missing[0]}; expected "
                         f"amplitude,phase,timestamp,validflag,ttlin,mark,ttlout")
    try:
        rate = float(header["Samples_per_second"])
        scale = float(header["Scale_factor"])
    except ValueError:
        raise InputError(f"{p}: Samples_per_second={header['Samples_per_second']!r}, Scale_factor="
                         f"{header['Scale_factor']!r}: expected numbers") from None
    if not (rate > 0 and np.isfinite(rate)) or not (np.isfinite(scale) and scale != 0):
        raise InputError(f"{p}: Samples_per_second = {rate:g}, Scale_factor = {scale:g}: expected > 0 and non-zero")
    col = {c: layout.index(c) for c in layout}
    rows = [(i, s) for i, s in enumerate(lines[data_at:], start=data_at + 1) if s.strip()]
    if len(rows) < 2:
        raise InputError(f"{p}: fewer than 2 data rows after [Data]")
    amp = np.empty(len(rows))
    ts = np.empty(len(rows))
    flag = np.empty(len(rows), np.int64)
    ttl = np.zeros(len(rows), np.int64)
    for j, (lineno, s) in enumerate(rows):
        f = s.strip().split(",")
        if len(f) < len(layout) and not (len(f) == len(layout) - 1 and layout[-1] in ("ttlout", "mark")):
            raise InputError(f"{p}: line {lineno}: {len(f)} fields, expected {len(layout)} ({header['Data_layout']}); "
                             f"truncated file?")
        try:
            amp[j] = float(f[col["amplitude"]])
            ts[j] = _finite(p, lineno, "timestamp", float(f[col["timestamp"]]), "a time in ms")
            flag[j] = _integer(p, lineno, "validflag", f[col["validflag"]])
            if "ttlin" in col and col["ttlin"] < len(f) and f[col["ttlin"]].strip():
                ttl[j] = _integer(p, lineno, "ttlin", f[col["ttlin"]])
        except InputError:  # a ValueError too: its own message names the column
            raise
        except ValueError:
            raise InputError(f"{p}: line {lineno}: {s.strip()[:60]!r}: expected numbers in amplitude, timestamp, "
                             f"validflag, ttlin") from None
    bad = np.flatnonzero(np.diff(ts) <= 0)
    if bad.size:
        lineno = rows[bad[0] + 1][0]
        raise InputError(f"{p}: line {lineno}: timestamp {ts[bad[0] + 1]:g} ms after {ts[bad[0]]:g} ms; "
                         f"expected strictly increasing timestamps")
    t = ts / 1000.0
    dt = float(np.median(np.diff(t)))
    if abs(dt * rate - 1.0) > 0.2:
        raise InputError(f"{p}: Samples_per_second = {rate:g} but the timestamps are {1.0 / dt:.4g} samples/s apart "
                         f"(median); expected them to agree within 20 %")
    status = np.where(flag >= 0, 0, np.where(flag == -1, -1, -2)).astype(np.int8)
    with np.errstate(over="ignore"):  # an amplitude beyond float64 once scaled is lost as inf is
        amp = amp * scale / 10.0
    amp, status = _lost_amplitudes(p, t, amp, status, [r[0] for r in rows])
    beam = np.flatnonzero(ttl == 1)
    beam_on = float(t[beam[0]]) if ("ttlin" in col and beam.size) else None
    return BreathingTrace(time_s=t, amplitude=amp, status=status, sample_s=1.0 / rate,
                          beam_on_s=beam_on, path=str(p))


def _read_breathing_csv(p: Path) -> BreathingTrace:
    with p.open(newline="") as fh:
        rows = list(csv.reader(fh))
    if not rows or [c.strip().lower() for c in rows[0][:2]] != ["time_s", "amplitude"]:
        first = ",".join(rows[0]) if rows else ""
        raise InputError(f"{p}: line 1 is {first!r}; expected the header time_s,amplitude[,valid]")
    has_valid = len(rows[0]) > 2 and rows[0][2].strip().lower() == "valid"
    body = [(i, r) for i, r in enumerate(rows[1:], start=2) if any(c.strip() for c in r)]
    if len(body) < 2:
        raise InputError(f"{p}: fewer than 2 data rows")
    t = np.empty(len(body))
    a = np.empty(len(body))
    status = np.zeros(len(body), np.int8)
    for j, (lineno, r) in enumerate(body):
        need = 3 if has_valid else 2
        if len(r) < need:
            raise InputError(f"{p}: line {lineno}: {len(r)} fields, expected {need}; truncated file?")
        try:
            t[j], a[j] = _finite(p, lineno, "time_s", float(r[0]), "a time in s"), float(r[1])
            if has_valid and _integer(p, lineno, "valid", r[2]) == 0:
                status[j] = STATUS["invalid"]
        except InputError:  # a ValueError too: its own message names the column
            raise
        except ValueError:
            raise InputError(f"{p}: line {lineno}: {','.join(r)[:60]!r}: expected numbers") from None
        if not np.isfinite(a[j]) and status[j] == 0:
            raise InputError(f"{p}: line {lineno}: amplitude = {r[1].strip()!r}: expected a finite number "
                             f"(mark a lost sample with valid = 0{'' if has_valid else ' in a third column valid'})")
    bad = np.flatnonzero(np.diff(t) <= 0)
    if bad.size:
        raise InputError(f"{p}: line {body[bad[0] + 1][0]}: time_s {t[bad[0] + 1]:g} after {t[bad[0]]:g}; "
                         f"expected strictly increasing times")
    a, status = _lost_amplitudes(p, t, a, status, [b[0] for b in body], counted="invalid")
    return BreathingTrace(time_s=t, amplitude=a, status=status, sample_s=float(np.median(np.diff(t))),
                          beam_on_s=None, path=str(p))


def _finite(p: Path, lineno: int, what: str, x: float, expected: str) -> float:
    if not np.isfinite(x):
        raise InputError(f"{p}: line {lineno}: {what} = {x!r}: expected {expected} (a finite number)")
    return x


def _integer(p: Path, lineno: int, what: str, text: str) -> int:
    """An integer column (validflag, ttlin, valid): nan/inf/fractions refused naming the line."""
    x = float(text)  # a ValueError (not a number at all) is reported by the caller with the whole row
    if not (np.isfinite(x) and x == int(x) and abs(x) < 2 ** 31):
        raise InputError(f"{p}: line {lineno}: {what} = {text.strip()!r}: expected an integer (a flag such as 0, 1, "
                         f"-1)")
    return int(x)


def _lost_amplitudes(p: Path, t, amp, status, linenos, counted: str = "non_finite_amplitude"):
    """Samples without a finite amplitude: status ``counted`` (their views are left out and counted),
    amplitude filled from the finite neighbours so that every number downstream stays finite."""
    lost = ~np.isfinite(amp)
    if not lost.any():
        return amp, status
    if lost.all():
        raise InputError(f"{p}: line {linenos[0]}: every amplitude is nan or inf; expected a breathing trace")
    status = status.copy()
    status[lost & (status == 0)] = STATUS[counted]
    amp = amp.copy()
    amp[lost] = np.interp(t[lost], t[~lost], amp[~lost])
    return amp, status


# ---------------------------------------------------------------------------------------
# ECG
def read_r_peaks(path) -> RPeaks:
    """R-peak times from a CSV (``r_peak_s``) or a WFDB record (``.hea``); see the module docstring."""
    p = Path(path)
    if p.suffix.lower() in (".hea", ".dat") or (not p.suffix and p.with_suffix(".hea").exists()):
        return _read_wfdb(p)
    if not p.is_file():
        raise InputError(f"{p}: ECG file not found")
    with p.open(newline="") as fh:
        rows = list(csv.reader(fh))
    if not rows or rows[0][0].strip().lower() != "r_peak_s":
        raise InputError(f"{p}: line 1 is {','.join(rows[0]) if rows else ''!r}; expected the header r_peak_s "
                         f"(or give a WFDB record's .hea)")
    body = [(i, r) for i, r in enumerate(rows[1:], start=2) if r and r[0].strip()]
    t = np.empty(len(body))
    for j, (lineno, r) in enumerate(body):
        try:
            t[j] = _finite(p, lineno, "r_peak_s", float(r[0]), "an R-peak time in s")
        except InputError:  # a ValueError too: its own message names the column
            raise
        except ValueError:
            raise InputError(f"{p}: line {lineno}: {r[0][:40]!r}: expected an R-peak time in s") from None
    bad = np.flatnonzero(np.diff(t) <= 0)
    if bad.size:
        raise InputError(f"{p}: line {body[bad[0] + 1][0]}: R peak {t[bad[0] + 1]:g} s after {t[bad[0]]:g} s; "
                         f"expected strictly increasing times")
    return _checked(RPeaks(time_s=t, path=str(p), kind="csv"))


def _read_wfdb(p: Path) -> RPeaks:
    try:
        import wfdb
        from wfdb import processing
    except ImportError:  # pragma: no cover - wfdb is a core dependency
        raise InputError(f"{p}: reading a WFDB record needs wfdb: pip install wfdb") from None
    base = p.with_suffix("")
    try:
        rec = wfdb.rdrecord(str(base), channels=[0])
    except Exception as e:  # noqa: BLE001 - wfdb raises many types (ValueError, FileNotFoundError, struct errors)
        msg = str(e).splitlines()[0][:80] if str(e) else ""
        raise InputError(f"{p}: not a readable WFDB record ({type(e).__name__}: {msg})") from None
    sig = np.asarray(rec.p_signal[:, 0], dtype=np.float64)
    if sig.size < 2 * rec.fs:
        raise InputError(f"{p}: channel 0 ({rec.sig_name[0]}) has {sig.size} samples at {rec.fs:g} Hz; expected at "
                         f"least 2 s of ECG")
    gap = np.flatnonzero(~np.isfinite(sig))
    if gap.size:
        k = int(gap[0])
        raise InputError(f"{p}: channel 0 ({rec.sig_name[0]}) sample {k} (t = {k / rec.fs:.3f} s) is "
                         f"{float(sig[k])!r}, "
                         f"{gap.size} of {sig.size} samples are missing or not finite; expected a continuous ECG "
                         f"(R peaks cannot be detected across a gap: give the R peaks as a CSV instead)")
    idx = np.asarray(processing.xqrs_detect(sig=sig, fs=rec.fs, verbose=False), dtype=np.int64)
    return _checked(RPeaks(time_s=np.sort(idx) / float(rec.fs), path=str(p), kind="wfdb"))


def _checked(r: RPeaks) -> RPeaks:
    if r.time_s.size < 2:
        what = "xqrs_detect found" if r.kind == "wfdb" else "the file holds"
        raise InputError(f"{r.path}: {what} {r.time_s.size} R peak(s); expected at least 2 (an ECG with R peaks)")
    return r


# ---------------------------------------------------------------------------------------
@functools.lru_cache(maxsize=8)
def _breathing_cached(path: str, inhale: str, digest: str) -> BreathingTrace:
    return read_breathing_trace(path, inhale)


@functools.lru_cache(maxsize=8)
def _ecg_cached(path: str, digest: str) -> RPeaks:
    return read_r_peaks(path)


def load_breathing(cfg) -> BreathingTrace | None:
    """The scene's breathing trace (``cfg`` = its SignalsConfig), memoised by content; None if not set."""
    if not cfg.breathing_trace:
        return None
    return _breathing_cached(cfg.breathing_trace, cfg.breathing_inhale, file_digest(cfg.breathing_trace))


def load_ecg(cfg) -> RPeaks | None:
    """The scene's R peaks (``cfg`` = its SignalsConfig), memoised by content; None if not set."""
    if not cfg.ecg_trace:
        return None
    return _ecg_cached(cfg.ecg_trace, file_digest(cfg.ecg_trace))


def breathing_offset_s(cfg, trace: BreathingTrace) -> float:
    """Trace time of scan time 0 (s): ``trace_offset_s``, or the beam-on sample (``trace_align``)."""
    if cfg.trace_align == "beam-on":
        if trace.beam_on_s is None:
            raise InputError(f"{trace.path}: signals.trace_align = 'beam-on' but the trace has no ttlin = 1 sample "
                             f"(no beam-on mark); give signals.trace_offset_s instead")
        return trace.beam_on_s + cfg.trace_offset_s
    return cfg.trace_offset_s


def view_signals(cfg, t_s) -> ViewSignals:
    """Cardiac phase, amplitude, direction and usability of views at scan times ``t_s`` (n,) s."""
    t = np.asarray(t_s, dtype=np.float64)
    n = t.size
    usable = np.ones(n, bool)
    excluded = {k: 0 for k in EXCLUSION_REASONS}
    c = np.zeros(n)
    a = np.full(n, 0.5)
    d = np.zeros(n, np.int8)
    tr = load_breathing(cfg)
    if tr is not None and n:
        tt = t + breathing_offset_s(cfg, tr)
        if tt.min() < tr.time_s[0] or tt.max() > tr.time_s[-1]:
            raise InputError(f"{tr.path}: the trace spans {tr.time_s[0]:.3f}..{tr.time_s[-1]:.3f} s (trace time) but "
                             f"the scan needs {tt.min():.3f}..{tt.max():.3f} s; expected a trace covering every view "
                             f"(check signals.trace_offset_s / trace_align)")
        p5, p95 = tr.percentiles()
        r = np.interp(tt, tr.time_s, tr.amplitude)
        a = np.clip((r - p5) / (p95 - p5), 0.0, 1.0)
        hi = np.clip(np.searchsorted(tr.time_s, tt, side="right"), 1, tr.time_s.size - 1)
        lo = hi - 1
        slope = tr.amplitude[hi] - tr.amplitude[lo]
        d = np.where(slope >= 0, 1, -1).astype(np.int8)
        s_lo, s_hi = tr.status[lo], tr.status[hi]
        # an exact hit on a sample needs only that sample
        on = tt == tr.time_s[lo]
        s_hi = np.where(on, s_lo, s_hi)
        gap = (tr.time_s[hi] - tr.time_s[lo] > GAP_FACTOR * tr.sample_s) & ~on
        worst = np.minimum(s_lo, s_hi)
        for reason, mask in [(r, worst == code) for r, code in STATUS.items()] + [("trace_gap", gap & (worst == 0))]:
            excluded[reason] = int(mask.sum())
            usable &= ~mask
    ecg = load_ecg(cfg)
    if ecg is not None and n:
        te = t + cfg.ecg_offset_s
        r = ecg.time_s
        if te.min() < r[0] or te.max() >= r[-1]:
            raise InputError(f"{ecg.path}: R peaks span {r[0]:.3f}..{r[-1]:.3f} s (ECG time) but the scan needs "
                             f"{te.min():.3f}..{te.max():.3f} s; expected an R peak before the first view and after "
                             f"the last (check signals.ecg_offset_s)")
        k = np.searchsorted(r, te, side="right") - 1
        c = np.minimum((te - r[k]) / (r[k + 1] - r[k]), np.nextafter(1.0, 0.0))
    return ViewSignals(cardiac_phase=c, resp_amplitude=a, resp_direction=d, usable=usable, excluded=excluded)
