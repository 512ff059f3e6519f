"""Signals: ranges, rhythms, irregular breathing, subset evaluation, phantom pose."""

import numpy as np
import pytest

from clrecon.config.scene import load_scene
from clrecon.scan import signals
from clrecon.scan.table import projection_table


@pytest.fixture(scope="module")
def demo():
    return load_scene("demo")


def _times(scene, n=20000):
    return np.linspace(0.0, 60.0, n)


def test_ranges(demo):
    ph = signals.physiology(demo, _times(demo))
    assert ph.cardiac_phase.dtype == np.float64 and ph.resp_direction.dtype == np.int8
    assert ph.cardiac_phase.min() >= 0.0 and ph.cardiac_phase.max() < 1.0
    assert ph.resp_amplitude.min() == 0.0 and ph.resp_amplitude.max() == 1.0  # clipped percentiles
    assert set(np.unique(ph.resp_direction)) == {-1, 1}
    # Continuous motion, all motion on: the phantom is posed at the recorded signals.
    np.testing.assert_array_equal(ph.state_cardiac, ph.cardiac_phase)
    np.testing.assert_array_equal(ph.state_resp, ph.resp_amplitude)


def test_amplitude_convention_inhale_is_one(demo):
    """a rises while direction is +1 (inhaling) and 1 is reached at the end of inhalation."""
    t = np.arange(0.0, 60.0, 0.01)
    ph = signals.physiology(demo, t)
    da = np.diff(ph.resp_amplitude)
    moving = np.abs(da) > 1e-3  # away from the clipped plateaus and the end-exhale dwell
    assert np.all(np.sign(da[moving]) == ph.resp_direction[:-1][moving])
    peaks = np.flatnonzero((ph.resp_direction[:-1] == 1) & (ph.resp_direction[1:] == -1))
    assert np.median(ph.resp_amplitude[peaks]) > 0.8


def test_periodic_rr_exact_and_phase_linear(demo):
    rp = signals.r_peaks(demo)
    np.testing.assert_allclose(np.diff(rp), demo.signals.rr_s, rtol=0, atol=1e-9)
    assert rp[0] <= 0.0 and rp[-1] > signals.trace_duration_s(demo)
    t = np.linspace(0.0, 50.0, 777)
    c0 = signals.physiology(demo, t).cardiac_phase
    c1 = signals.physiology(demo, t + demo.signals.rr_s).cardiac_phase
    np.testing.assert_allclose(np.cos(2 * np.pi * (c1 - c0)), 1.0, atol=1e-9)
    # Phase is 0 at the R peaks (just after) and close to 1 just before.
    inside = rp[(rp > 0.01) & (rp < 59.0)]
    ph = signals.physiology(demo, np.concatenate([inside + 1e-6, inside - 1e-6])).cardiac_phase
    assert np.all(ph[: inside.size] < 1e-5) and np.all(ph[inside.size:] > 1 - 1e-5)


def test_hrv_statistics(demo):
    rr = np.diff(signals.r_peaks(demo.replace(signals={"rhythm": "hrv"})))
    assert rr.mean() == pytest.approx(0.75, rel=0.01)
    assert 0.02 < rr.std() / rr.mean() < 0.04  # default 3 % sinus variability


@pytest.mark.parametrize("rr_cv, lo, hi", [(0.0, 0.15, 0.25), (0.3, 0.25, 0.35)])
def test_af_statistics(demo, rr_cv, lo, hi):
    """i.i.d. R-R with the requested CV; ~220 intervals give a CV standard error of ~0.01."""
    rr = np.diff(signals.r_peaks(demo.replace(signals={"rhythm": "af", "rr_cv": rr_cv})))
    assert rr.mean() == pytest.approx(0.75, rel=0.05)
    assert lo < rr.std() / rr.mean() < hi
    # Independent: lag-1 autocorrelation near 0 (|r| < 4 / sqrt(n)).
    d = rr - rr.mean()
    assert abs(np.dot(d[1:], d[:-1]) / np.dot(d, d)) < 4 / np.sqrt(rr.size)


def test_pvc_premature_and_compensatory(demo):
    rate = 0.2
    rr = np.diff(signals.r_peaks(demo.replace(signals={"rhythm": "pvc", "ectopic_rate": rate})))
    mean = 0.75
    premature = np.flatnonzero(rr < 0.71 * mean)
    assert premature.size > 0
    frac = premature.size / rr.size
    # Binomial-ish count over ~220 intervals: standard error ~0.03.
    assert abs(frac - rate) < 0.1
    assert np.all((rr[premature] >= 0.6 * mean - 1e-12) & (rr[premature] <= 0.7 * mean + 1e-12))
    premature = premature[premature + 1 < rr.size]
    # Every premature beat is followed by the compensatory pause: the pair spans 2 R-R.
    np.testing.assert_allclose(rr[premature] + rr[premature + 1], 2 * mean, atol=1e-9)
    normal = np.setdiff1d(np.arange(rr.size), np.concatenate([premature, premature + 1]))
    np.testing.assert_allclose(rr[normal], mean, atol=1e-9)


def test_breathing_is_irregular(demo):
    tr = signals.respiratory_trace(demo, step_s=0.01)
    # Inhale peaks: direction flips from +1 to -1.
    peaks = np.flatnonzero((tr.direction[:-1] == 1) & (tr.direction[1:] == -1))
    periods = np.diff(tr.time_s[peaks])
    assert periods.size >= 8
    assert periods.mean() == pytest.approx(demo.signals.resp_period_s, rel=0.2)
    assert periods.std() / periods.mean() > 0.05  # cycle periods vary (cv 0.15 configured)
    depths = tr.raw[peaks]
    assert depths.std() / depths.mean() > 0.05  # and so do depths
    # A regular scene has (nearly) constant periods.
    reg = demo.replace(signals={"resp_period_cv": 0.0, "resp_depth_cv": 0.0, "resp_drift": 0.0})
    np.testing.assert_allclose(np.diff(signals.respiratory_trace(reg).cycle_start_s), 5.0, atol=1e-9)


def test_subset_and_order_identical(demo):
    t = np.sort(np.random.default_rng(0).uniform(0.0, 60.0, 5000))
    full = signals.physiology(demo, t)
    sel = np.random.default_rng(1).permutation(t.size)[:1234]
    sub = signals.physiology(demo, t[sel])
    for name in ("cardiac_phase", "resp_amplitude", "resp_direction", "state_cardiac", "state_resp"):
        np.testing.assert_array_equal(getattr(sub, name), getattr(full, name)[sel], err_msg=name)


def test_both_pitches_share_physiology(demo):
    t_low, t_high = projection_table(demo, 0.02), projection_table(demo, 0.10)
    m = len(t_high)
    assert len(t_low) > m  # same time grid t_k = k T_rot / N_views, longer at low pitch
    np.testing.assert_array_equal(t_low.cardiac_phase[:m], t_high.cardiac_phase)
    np.testing.assert_array_equal(t_low.resp_amplitude[:m], t_high.resp_amplitude)


def test_trace_is_prefix_stable(demo):
    """A longer trace (longer scan) extends the random draws, it does not redraw them."""
    long_scene = demo.replace(scan={"n_projections": 360 * 300})  # 90 s scan
    assert signals.trace_duration_s(long_scene) > signals.trace_duration_s(demo)
    a, b = signals.r_peaks(demo.replace(signals={"rhythm": "pvc"})), \
        signals.r_peaks(long_scene.replace(signals={"rhythm": "pvc"}))
    np.testing.assert_array_equal(a[:50], b[:50])
    ea = signals.respiratory_trace(demo).cycle_start_s
    eb = signals.respiratory_trace(long_scene).cycle_start_s
    np.testing.assert_array_equal(ea[:10], eb[:10])


def test_seed_changes_signals(demo):
    t = _times(demo, 500)
    a = signals.physiology(demo, t)
    b = signals.physiology(demo.replace(signals={"seed": 2}), t)
    assert not np.array_equal(a.resp_amplitude, b.resp_amplitude)
    assert not np.array_equal(a.cardiac_phase, b.cardiac_phase)


def test_breath_hold(demo):
    s = demo.replace(signals={"breath_hold": True, "breath_hold_amplitude": 0.3})
    ph = signals.physiology(s, _times(s))
    assert np.all(ph.resp_amplitude == 0.3) and np.all(ph.state_resp == 0.3)
    assert np.all(ph.resp_direction == 0)
    assert ph.cardiac_phase.max() > 0.9  # the heart still beats


def test_motion_switches(demo):
    t = _times(demo, 3000)
    ref = signals.physiology(demo, t)
    s = demo.replace(phantom={"cardiac_motion": False, "respiratory_motion": False})
    ph = signals.physiology(s, t)
    # The monitors still record the patient; only the phantom's pose is frozen.
    np.testing.assert_array_equal(ph.cardiac_phase, ref.cardiac_phase)
    np.testing.assert_array_equal(ph.resp_amplitude, ref.resp_amplitude)
    assert np.all(ph.state_cardiac == 0.0) and np.all(ph.state_resp == 0.5)


def test_frames_freeze_the_pose(demo):
    frame = 0.1
    s = demo.replace(signals={"frame_time_s": frame})
    t = np.arange(0.0, 30.0, 0.3 / 360)
    ph = signals.physiology(s, t)
    ref = signals.physiology(demo, t)
    np.testing.assert_array_equal(ph.cardiac_phase, ref.cardiac_phase)  # recorded: own time
    np.testing.assert_array_equal(ph.resp_amplitude, ref.resp_amplitude)
    starts = np.floor(t / frame) * frame
    at_start = signals.physiology(demo, starts)
    np.testing.assert_array_equal(ph.state_cardiac, at_start.cardiac_phase)
    np.testing.assert_array_equal(ph.state_resp, at_start.resp_amplitude)
    frame_id = np.floor(t / frame).astype(int)
    same = frame_id[1:] == frame_id[:-1]
    assert np.all(ph.state_resp[1:][same] == ph.state_resp[:-1][same])
    assert not np.array_equal(ph.state_cardiac, ph.cardiac_phase)


def test_times_outside_trace_rejected(demo):
    with pytest.raises(ValueError, match="signal trace"):
        signals.physiology(demo, np.array([-1.0, 0.0]))
    with pytest.raises(ValueError, match="signal trace"):
        signals.physiology(demo, np.array([signals.trace_duration_s(demo) + 1.0]))
    with pytest.raises(ValueError, match="1-D"):
        signals.physiology(demo, np.zeros((2, 2)))


def test_paper_scale_evaluates(demo):
    """160 689 projection times in one call (the pitch-0.02 paper scan)."""
    s = load_scene("paper-p002")
    ph = signals.physiology(s, np.arange(160689) * 0.3 / 984)
    assert ph.cardiac_phase.shape == (160689,)
    assert np.all(np.isfinite(ph.resp_amplitude))
