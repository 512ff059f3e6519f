"""Laws the science must obey, measured on real scans' phase-space samples.

* Convergence: on smooth periodic fields sampled at the (c, a) points of a real scan, the
  interpolating methods' error falls faster than ``nearest``'s as the pitch (hence the
  phase-space spacing per view) falls.
* Periodic rhythm: with T_rot / RR = p / q in lowest terms a view sees min(candidates, q)
  distinct cardiac phases (demo: 2/5, five); heart-rate variability gives more.
* The ``*-hrv`` built-in scenes are their base scenes with only the rhythm changed.
"""

from __future__ import annotations

from fractions import Fraction

import numpy as np
import pytest
from scipy.spatial import ConvexHull, QhullError

from clrecon.config.scene import load_scene
from clrecon.reconstruction import rebin, reconstruct
from clrecon.reconstruction.interpolation.barycentric import BRANCH_TRIANGLE
from clrecon.reconstruction.interpolation.weights import batch_weights
from clrecon.scan.sampling import DISTINCT_PHASE_TOL, distinct_cardiac_phases, sampling_summary
from clrecon.scan.table import projection_table

PITCHES = (0.02, 0.04, 0.08, 0.16)
#: slices (mm from the scan centre) whose (slice, view) groups are sampled; every view
SLICE_OFFSETS_MM = (-8.0, 0.0, 8.0)
#: targets: 20 cardiac phases x 10 amplitudes (the scene's bin midpoints)
TARGETS = np.stack(np.meshgrid(np.arange(20) / 20.0, 0.05 + 0.1 * np.arange(10), indexing="ij"), -1).reshape(-1, 2)


def _field_one_harmonic(c, a):
    """f = sin(2 pi c) (1 + a) + a^2 / 2: periodic in c, coupled to a, curved in a."""
    return np.sin(2 * np.pi * c) * (1 + a) + 0.5 * a * a


def _field_two_harmonics(c, a):
    """f = cos(2 pi c) + 0.4 a sin(4 pi c + 1) + 0.3 cos(pi a): a second harmonic in c."""
    return np.cos(2 * np.pi * c) + 0.4 * a * np.sin(4 * np.pi * c + 1.0) + 0.3 * np.cos(np.pi * a)


FIELDS = {"one harmonic": _field_one_harmonic, "two harmonics": _field_two_harmonics}


def _inside_periodic_hull(c, a, offsets, targets):
    """(G, T) bool: target inside the convex hull of the group's points and their copies at
    c -/+ 1 (the sampled region in periodic phase space, the region barycentric triangulates).
    Facet equations n . x + d <= 0 inside; 1e-12 keeps targets on an edge inside."""
    out = np.zeros((offsets.size - 1, targets.shape[0]), bool)
    for g in range(offsets.size - 1):
        s = slice(offsets[g], offsets[g + 1])
        pts = np.stack([c[s], a[s]], axis=1)
        ext = np.concatenate([pts - [1.0, 0.0], pts, pts + [1.0, 0.0]])
        try:
            eq = ConvexHull(ext).equations                            # (facets, 3)
        except QhullError:  # all points at one amplitude: no area, nothing inside
            continue
        out[g] = np.all(targets @ eq[:, :2].T + eq[:, 2] <= 1e-12, axis=1)
    return out


@pytest.fixture(scope="module")
def demo_samples():
    """Per pitch: candidates' (c, a), CSR offsets, the inside-hull mask, every method's weights."""
    scene = load_scene("demo")
    r = reconstruct.object_radius_mm(scene)
    assert max(PITCHES) < rebin.max_covering_pitch(scene.scanner, r)
    zs = scene.scan.z_centre_mm + np.asarray(SLICE_OFFSETS_MM)
    out = {}
    for p in PITCHES:
        table = projection_table(scene, p)
        g = rebin.candidate_groups(table, zs, scene.scanner, r)
        assert not g.empty.any()
        c, a = table.cardiac_phase[g.row], table.resp_amplitude[g.row]
        w = {m: batch_weights(m, c, a, g.offsets, TARGETS) for m in ("nearest", "barycentric", "local_linear")}
        out[p] = (c, a, g, _inside_periodic_hull(c, a, g.offsets, TARGETS), w)
    return out


def _rms_errors(samples, field):
    """{method: (len(PITCHES),) RMS of sum_k w_k f(c_k, a_k) - f(c*, a*)} over the (slice, view,
    target) triples inside the sampled hull at every pitch (the same triples at every pitch)."""
    common = np.logical_and.reduce([samples[p][3] for p in PITCHES])
    truth = field(TARGETS[:, 0], TARGETS[:, 1])[None, :]
    err: dict = {}
    for p in PITCHES:
        c, a, _, _, weights = samples[p]
        y = field(c, a)
        for m, w in weights.items():
            est = (w.weight * y[w.index]).sum(-1)
            err.setdefault(m, []).append(float(np.sqrt(np.mean((est - truth)[common] ** 2))))
    return common, {m: np.asarray(e) for m, e in err.items()}


@pytest.mark.parametrize("name", list(FIELDS))
def test_interpolation_converges_faster_than_nearest(demo_samples, name):
    """RMS error on `demo`'s phase points, 3 slices x 360 views x 200 targets, pitch 0.02-0.16
    (42 down to 5 candidates per (slice, view)); slopes of log error vs log pitch.

    Measured (demo's periodic rhythm: 5 cardiac phases per view at every pitch, so only the
    amplitude spacing refines; 104 740 common triples):

    ============  ===================================  ===================================
    method        one harmonic: RMS 0.02..0.16, slope  two harmonics: RMS 0.02..0.16, slope
    ============  ===================================  ===================================
    nearest       0.437 0.543 0.604 0.669, 0.20        0.310 0.418 0.468 0.501, 0.22
    barycentric   0.238 0.386 0.390 0.474, 0.30        0.161 0.252 0.318 0.368, 0.39
    local_linear  0.330 0.475 0.561 0.674, 0.33        0.236 0.346 0.437 0.502, 0.36
    ============  ===================================  ===================================

    Barycentric before its triangle |dc| limit: 0.234 .. 0.729, slope 0.52 and 0.159 .. 0.510,
    0.58 (the limit mostly helps at coarse pitch, where slivers spanned far in c). The orders
    are far below a filled 2-D space's 1/2 (nearest) and 1 (linear) in pitch: the five
    cardiac lines 0.2 apart never refine (an incommensurate R-R, 0.7854 s, gives the same
    slopes within 0.06: the error is dominated by the sparse cardiac sampling either way).
    """
    common, err = _rms_errors(demo_samples, FIELDS[name])
    assert common.sum() > 10_000  # the comparison rests on many (slice, view, target) triples
    logp = np.log(np.asarray(PITCHES))
    slope = {m: float(np.polyfit(logp, np.log(e), 1)[0]) for m, e in err.items()}
    msg = f"{name}: RMS {({m: np.round(e, 4).tolist() for m, e in err.items()})}, slopes {slope}"
    assert slope["barycentric"] > slope["nearest"], msg
    assert slope["local_linear"] > slope["nearest"], msg
    i = PITCHES.index(0.02)
    assert err["barycentric"][i] < err["nearest"][i], msg
    assert err["local_linear"][i] < err["nearest"][i], msg


def test_linear_fields_are_reproduced_inside_the_hull(demo_samples):
    """Both interpolants are exact for f linear in a (constant in c) inside the sampled hull:
    barycentric wherever it interpolates in a triangle (linear precision; its |dc| limit sends
    some targets to the segment / nearest fallback, which is not), local linear everywhere (an
    unguarded weighted linear fit: inside the hull the selected points bracket a*); nearest is
    not. Float64 weights over at most 8 rows with |f| <= 3: 1e-9 leaves ~10^6 ulps, far below
    nearest's error."""
    for p in PITCHES:
        c, a, g, inside, weights = demo_samples[p]
        y = 1.0 + 2.0 * a
        truth = 1.0 + 2.0 * TARGETS[None, :, 1]

        def err(m, y=y, truth=truth, weights=weights):
            return np.abs((weights[m].weight * y[weights[m].index]).sum(-1) - truth)

        tri = inside & (weights["barycentric"].branch == BRANCH_TRIANGLE)
        if p == min(PITCHES):  # not vacuous: with 42 candidates per view most targets are in triangles
            assert tri.sum() > 0.5 * inside.sum()
        assert err("barycentric")[tri].max() < 1e-9, p
        assert err("local_linear")[inside].max() < 1e-9, p
        assert err("nearest")[inside].max() > 1e-3, p


# ---------------------------------------------------------------------------------------
# heart-rate variability: distinct cardiac phases per view
def _groups(scene, pitch):
    table = projection_table(scene, pitch)
    g = rebin.candidate_groups(table, reconstruct.slice_positions(scene), scene.scanner,
                               reconstruct.object_radius_mm(scene))
    return table, g


@pytest.mark.parametrize("rr_s", [0.75, 0.9, 0.8])
def test_periodic_rhythm_gives_at_most_q_phases_per_view(rr_s):
    """T_rot / RR = p/q in lowest terms: the phase advances p/q per turn, so a view's
    candidates (consecutive turns) take exactly min(count, q) distinct phases, q apart by 1/q.
    demo (0.3 / 0.75 = 2/5): 5; 0.3 / 0.9 = 1/3: 3; 0.3 / 0.8 = 3/8: 8."""
    scene = load_scene("demo").replace(signals={"rr_s": rr_s})
    q = (Fraction(str(scene.scanner.rotation_time_s)) / Fraction(str(rr_s))).denominator
    for pitch in scene.scan.pitches:
        table, g = _groups(scene, pitch)
        n = distinct_cardiac_phases(table, g)
        assert np.array_equal(n, np.minimum(g.counts, q)), (rr_s, pitch, q, np.unique(n))
    if rr_s == 0.75:
        table, g = _groups(scene, 0.02)
        s = sampling_summary(table, g)["distinct_cardiac_phases_per_view"]
        assert s == {"median": 5.0, "min": 5, "max": 5}


def test_heart_rate_variability_breaks_the_phase_lattice():
    """demo-hrv (RR CV 5 %): at pitch 0.02 most views see far more than demo's 5 phases; the
    count never exceeds the candidates."""
    periodic, hrv = load_scene("demo"), load_scene("demo-hrv")
    t0, g0 = _groups(periodic, 0.02)
    t1, g1 = _groups(hrv, 0.02)
    n0, n1 = distinct_cardiac_phases(t0, g0), distinct_cardiac_phases(t1, g1)
    assert n0.max() == 5
    assert np.all(n1 <= g1.counts) and np.all(n1 >= 1)
    assert np.median(n1) > 4 * 5
    assert np.mean(n1 > 5) > 0.9


def test_distinct_phases_counts_across_the_seam_and_tolerance():
    """Phases within the tolerance (also across c = 0/1) are one; an empty group has none."""
    class T:
        cardiac_phase = np.array([0.1, 0.1 + DISTINCT_PHASE_TOL / 2, 0.9999, 0.0002, 0.5, 0.5 + 2 * DISTINCT_PHASE_TOL])

    class G:
        offsets = np.array([0, 2, 4, 4, 6])
        row = np.arange(6)

    assert distinct_cardiac_phases(T, G).tolist() == [1, 1, 0, 2]


# ---------------------------------------------------------------------------------------
@pytest.mark.parametrize("name,base", [("demo-hrv", "demo"), ("paper-p002-hrv", "paper-p002")])
def test_hrv_scenes_are_their_base_with_only_the_rhythm_changed(name, base):
    s, b = load_scene(name).to_dict(), load_scene(base).to_dict()
    assert s["signals"]["rhythm"] == "hrv" and 0.03 <= s["signals"]["rr_cv"] <= 0.1
    diff = {k for k in s if s[k] != b[k]} - {"name", "description"}
    assert diff == {"signals"}
    assert {k for k in s["signals"] if s["signals"][k] != b["signals"][k]} == {"rhythm", "rr_cv"}
