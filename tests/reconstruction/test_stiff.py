"""Stiff and extreme interpolation cases (docs/choices-engineering.md "Stiff and degenerate cases"): every one
has a defined, finite result, and the float32 local-linear kernel agrees with the float64 reference.

Local linear: collinear and duplicate phase points, all points at one amplitude, fewer than
three points, kernels from the paper's (kappa 1, sigma 0.15) to kappa 100 / sigma 0.01
(weights that underflow). Barycentric: degenerate triangles, targets on edges and vertices,
at the c = 0/1 seam, outside the hull, and both fallbacks (two-nearest projection; nearest
when the second point is > 0.3 away in c).
"""

from __future__ import annotations

import zlib

import numpy as np
import pytest

from clrecon.core.conventions import circular_difference
from clrecon.reconstruction.interpolation import weights as ip

# One table for every tolerance in this file: (what is compared, why it is not zero).
TOL = {
    # float64 weights: sum to one / reproduce linear data, relative to max(1, sum |w|)
    "weights_f64": 1e-9,
    # double build of the kernel vs the NumPy reference: rounding only
    "ll_double": 1e-9,
    # single build vs float64 reference, max |dl| / max(1, sum |l_ref|), on adversarial raw
    # rows (every degenerate kind, kappa <= 100, sigma >= 0.01, targets outside the points).
    # Bounded by ~eps32 / LL_RCOND = 6e-4 times the geometry; measured at most 1.4e-3.
    "ll_single_raw": 3e-3,
    # the same through the pipeline's quadrant selection (method_weights); measured 6.3e-4
    "ll_single_selected": 2e-3,
}

KERNELS = [(1.0, 0.15), (100.0, 0.15), (1.0, 0.01), (100.0, 0.01)]
TARGETS = np.array([[c, a] for c in (0.0, 0.2, 0.4, 0.6, 0.8, 0.999) for a in np.arange(0.05, 1.0, 0.1)])


def _as_dict(W, t):
    d = {}
    for i, w in zip(W.index[t], W.weight[t], strict=True):
        if w != 0:
            d[int(i)] = d.get(int(i), 0.0) + float(w)
    return d


def _moments(W, c, a, targets):
    dc = circular_difference(c[W.index], targets[:, None, 0])
    da = a[W.index] - targets[:, None, 1]
    return W.weight.sum(-1), (W.weight * dc).sum(-1), (W.weight * da).sum(-1)


def _scale(w):
    return np.maximum(1.0, np.abs(w).sum(-1))


# ---------------------------------------------------------------------------------------
# local linear: raw rows of every degenerate kind through the kernel and the reference
def _stiff_rows(kind: str, rng, n: int = 400):
    """(dc, da, count) rows of one degenerate kind; the target is at the origin."""
    dc, da = rng.normal(0, 0.1, (n, 8)), rng.normal(0, 0.2, (n, 8))
    count = rng.integers(1, 9, n)
    if kind in ("collinear", "near_collinear"):
        s = rng.normal(0, 0.2, (n, 8))
        ang = rng.random((n, 1)) * np.pi
        off = rng.normal(0, 0.05, (n, 1)) + (rng.normal(0, 1e-3, (n, 8)) if kind == "near_collinear" else 0)
        dc, da = s * np.cos(ang) - off * np.sin(ang), s * np.sin(ang) + off * np.cos(ang)
        count = np.full(n, 8)
    elif kind == "duplicates":  # 8 slots filled from 1..3 distinct points
        k = rng.integers(1, 4, n)[:, None]
        j = rng.integers(0, 3, (n, 8)) % k
        dc = np.take_along_axis(rng.normal(0, 0.1, (n, 3)), j, 1)
        da = np.take_along_axis(rng.normal(0, 0.2, (n, 3)), j, 1)
        count = np.full(n, 8)
    elif kind == "one_amplitude":
        da = np.repeat(rng.normal(0, 0.2, (n, 1)), 8, axis=1)
    elif kind == "fewer_than_three":
        count = rng.integers(1, 3, n)
    return dc, da, count


@pytest.mark.parametrize("kappa,sigma", KERNELS)
@pytest.mark.parametrize("kind", ["random", "collinear", "near_collinear", "duplicates", "one_amplitude",
                                  "fewer_than_three"])
def test_local_linear_kernel_single_and_double_match_the_reference(kind, kappa, sigma):
    # a fixed seed per case (hash() of a str changes with every process's PYTHONHASHSEED, which
    # made this test draw new rows in each run; the rare rows the single path fails on are below)
    rng = np.random.default_rng(zlib.crc32(repr((kind, kappa, sigma)).encode()))
    dc, da, count = _stiff_rows(kind, rng)
    ref = ip.local_linear_solve_reference(dc, da, count, kappa, sigma)
    scale = _scale(ref)
    assert np.all(np.isfinite(ref))
    assert np.all(np.abs(ref.sum(1) - 1) < TOL["weights_f64"] * scale)
    for precision in ("double", "single"):
        got = ip.local_linear_solve(dc, da, count, kappa, sigma, precision=precision)
        assert np.all(np.isfinite(got)), precision
        err = np.abs(got - ref).max(1) / scale
        tol = TOL["ll_double"] if precision == "double" else TOL["ll_single_raw"]
        assert err.max() < tol, (precision, err.max())


@pytest.mark.xfail(strict=True, reason="known defect, not fixed: the single-precision local linear solve loses "
                   "the weights on rare near-collinear rows (2 of 1500 random draws at kappa 100, sigma 0.15: "
                   "0.26 and 0.50 of the scale; 9.7 in one CI draw)")
@pytest.mark.parametrize("seed", [715, 933])
def test_local_linear_single_fails_on_rare_near_collinear_rows(seed):
    dc, da, count = _stiff_rows("near_collinear", np.random.default_rng(seed))
    ref = ip.local_linear_solve_reference(dc, da, count, 100.0, 0.15)
    got = ip.local_linear_solve(dc, da, count, 100.0, 0.15, precision="single")
    assert (np.abs(got - ref).max(1) / _scale(ref)).max() < TOL["ll_single_raw"]


@pytest.mark.parametrize("kappa,sigma", KERNELS)
@pytest.mark.parametrize("case", ["random", "duplicates", "lattice", "one_amplitude"])
def test_local_linear_selected_rows_single_vs_double(case, kappa, sigma):
    """The pipeline's own rows (quadrant selection) at every kernel width."""
    rng = np.random.default_rng(len(case) * 1000 + int(kappa) + int(100 * sigma))
    for _ in range(6):
        n = int(rng.integers(3, 40))
        c, a = rng.random(n), rng.random(n)
        if case == "duplicates":
            c, a = np.repeat(c[:n // 3 + 1], 3)[:n], np.repeat(a[:n // 3 + 1], 3)[:n]
        elif case == "lattice":
            c, a = rng.integers(0, 5, n) / 5, rng.integers(0, 5, n) / 5
        elif case == "one_amplitude":
            a[:] = 0.5
        Wd = ip.method_weights("local_linear", c, a, TARGETS, kappa=kappa, sigma=sigma, precision="double")
        Ws = ip.method_weights("local_linear", c, a, TARGETS, kappa=kappa, sigma=sigma, precision="single")
        scale = _scale(Wd.weight)
        assert np.all(np.isfinite(Ws.weight)) and np.all(np.isfinite(Wd.weight))
        assert np.all(np.abs(Wd.weight.sum(-1) - 1) < TOL["weights_f64"] * scale)
        live = Wd.weight != 0
        np.testing.assert_array_equal(Ws.index[live], Wd.index[live])
        assert (np.abs(Ws.weight - Wd.weight).max(-1) / scale).max() < TOL["ll_single_selected"]


def test_local_linear_duplicate_points_fit_along_the_line_through_them():
    """Two distinct locations, each repeated: rank one, fitted along the line between them."""
    c = np.array([0.45, 0.45, 0.45, 0.45, 0.6, 0.6, 0.6, 0.6])
    a = np.array([0.4, 0.4, 0.4, 0.4, 0.6, 0.6, 0.6, 0.6])
    target = np.array([[0.5, 0.55]])
    W = ip.method_weights("local_linear", c, a, target)
    s, mc, ma = _moments(W, c, a, target)
    # perpendicular foot of the target on the line, target-centred
    p1, p2, q = np.array([0.45, 0.4]), np.array([0.6, 0.6]), target[0]
    e = p2 - p1
    foot = p1 + e * ((q - p1) @ e) / (e @ e) - q
    assert abs(s[0] - 1) < TOL["weights_f64"]
    np.testing.assert_allclose([mc[0], ma[0]], foot, atol=TOL["weights_f64"])


def test_local_linear_all_points_at_one_amplitude_is_exact_in_cardiac_phase():
    rng = np.random.default_rng(4)
    c = rng.random(20)
    a = np.full(20, 0.35)
    W = ip.method_weights("local_linear", c, a, TARGETS)
    s, mc, ma = _moments(W, c, a, TARGETS)
    assert np.all(np.isfinite(W.weight))
    assert np.all(np.abs(s - 1) < TOL["weights_f64"] * _scale(W.weight))
    assert np.all(np.abs(mc) < TOL["weights_f64"] * _scale(W.weight))   # linear in c: exact
    np.testing.assert_allclose(ma, 0.35 - TARGETS[:, 1], atol=1e-12)     # nothing to fit in a


@pytest.mark.parametrize("n", [1, 2])
def test_local_linear_fewer_than_three_points_is_the_nearest(n):
    c, a = np.array([0.3, 0.9])[:n], np.array([0.2, 0.7])[:n]
    W = ip.method_weights("local_linear", c, a, [[0.25, 0.25], [0.95, 0.8]])
    assert _as_dict(W, 0) == {0: 1.0}
    assert _as_dict(W, 1) == {n - 1: 1.0}


def test_local_linear_narrow_kernel_degrades_to_the_closest_points():
    """kappa 100, sigma 0.01: far points' weights underflow (< LL_WEIGHT_FLOOR) and drop out."""
    c = np.array([0.50, 0.60, 0.40, 0.62, 0.38])
    a = np.array([0.505, 0.70, 0.30, 0.30, 0.70])
    for precision in ("double", "single"):
        W = ip.method_weights("local_linear", c, a, [[0.5, 0.5]], kappa=100.0, sigma=0.01, precision=precision)
        d = _as_dict(W, 0)
        assert d[0] == pytest.approx(1.0, abs=1e-6) and sum(abs(v) for k, v in d.items() if k) < 1e-6
    # every point far away: all raw weights underflow even in float64 (exp(-1250)); the
    # relative weights keep the largest at 1, so the result is still the weighted mean
    W = ip.method_weights("local_linear", [0.0, 0.02, 0.98, 0.5], [0.0, 0.0, 0.0, 0.0], [[0.0, 0.5]],
                          kappa=100.0, sigma=0.01)
    assert np.all(np.isfinite(W.weight)) and abs(W.weight.sum() - 1) < TOL["weights_f64"]


def test_local_linear_thin_cloud_far_from_the_target_drops_the_thin_direction():
    """Points spread 1e-3 across a line 0.3 away: the paper's full fit extrapolates ~300
    spreads (|weights| summing to ~300, measured); the conditioning rule fits along the line
    instead (weights of a 1-D interpolation, exact along the principal direction)."""
    rng = np.random.default_rng(9)
    c = 0.5 + np.linspace(-0.2, 0.2, 8)
    a = 0.8 + rng.normal(0, 1e-3, 8)
    target = np.array([[0.5, 0.5]])
    for precision in ("double", "single"):
        # target below every point in amplitude: this tests the plain (paper) fit's fallback
        W = ip.method_weights("local_linear", c, a, target, precision=precision, extrapolate=True)
        used = W.weight[0] != 0
        i, l = W.index[0][used], W.weight[0][used]
        dc, da = c[i] - 0.5, a[i] - 0.5
        k = np.exp(np.cos(2 * np.pi * dc) - 1) * np.exp(-da ** 2 / (2 * 0.15 ** 2))
        X = np.stack([np.ones(i.size), dc, da], axis=1)
        full = np.linalg.solve((X.T * k) @ X, X.T * k)[0]      # e1^T (X^T W X)^-1 X^T W
        assert np.abs(full).sum() > 100
        assert np.abs(l).sum() < 1.5 and abs(l.sum() - 1) < 1e-6
        # exact along the principal direction of the weighted points
        m = np.array([k @ dc, k @ da]) / k.sum()
        cov = np.cov(np.stack([dc, da]), aweights=k, bias=True)
        v = np.linalg.eigh(cov)[1][:, -1]
        assert abs(v @ np.array([l @ dc, l @ da]) - 0) < 1e-6 and abs(v @ m) < 0.02


# ---------------------------------------------------------------------------------------
# barycentric
def test_barycentric_target_on_a_vertex_and_on_an_edge():
    c = np.array([0.2, 0.4, 0.3, 0.2, 0.4])
    a = np.array([0.2, 0.2, 0.6, 0.9, 0.9])
    W = ip.method_weights("barycentric", c, a, [[0.3, 0.6], [0.3, 0.2], [0.25, 0.4]])
    assert _as_dict(W, 0) == {2: pytest.approx(1.0)}                            # vertex
    assert _as_dict(W, 1) == pytest.approx({0: 0.5, 1: 0.5})                    # edge
    s, mc, ma = _moments(W, c, a, np.array([[0.3, 0.6], [0.3, 0.2], [0.25, 0.4]]))
    assert np.all(np.abs(s - 1) < TOL["weights_f64"]) and np.all(np.abs(mc) < TOL["weights_f64"])
    assert np.all(np.abs(ma) < TOL["weights_f64"]) and np.all(W.weight >= 0)


def test_barycentric_degenerate_triangles_collinear_runs_and_duplicates():
    """Collinear runs (zero-area candidate triangles), duplicated points, a lattice."""
    c = np.array([0.1, 0.2, 0.3, 0.2, 0.2, 0.5, 0.2, 0.2])
    a = np.array([0.5, 0.5, 0.5, 0.5, 0.8, 0.2, 0.5, 0.8])
    targets = np.array([[0.2, 0.5], [0.15, 0.5], [0.25, 0.6], [0.0, 0.5], [0.3, 0.3]])
    W = ip.method_weights("barycentric", c, a, targets)
    s, mc, ma = _moments(W, c, a, targets)
    tol = TOL["weights_f64"]
    assert np.all(np.abs(s - 1) < tol) and np.all(np.abs(ma) < tol) and np.all(W.weight >= 0)
    # linear in the circular dc where the triangle spans less than half a cycle; targets 3
    # and 4 lie in triangles through periodic copies 0.7 away (exact in the copies' c)
    assert np.all(np.abs(mc[:3]) < tol)
    assert _as_dict(W, 3) == pytest.approx({0: 0.875, 2: 0.125})   # on the edge 0.1 .. 0.3 - 1
    assert sum(v for k, v in _as_dict(W, 0).items() if k in (1, 3, 6)) == pytest.approx(1.0)  # on the duplicates


def test_barycentric_near_degenerate_slivers_stay_finite():
    """All points within 1e-14 of one amplitude: Qhull may triangulate slivers of ~zero area;
    those are rejected (area test) and the two-nearest fallback is used."""
    rng = np.random.default_rng(2)
    c = rng.random(12)
    a = 0.5 + 1e-14 * rng.random(12)
    W = ip.method_weights("barycentric", c, a, TARGETS)
    assert np.all(np.isfinite(W.weight)) and np.all(W.weight >= 0)
    assert np.all(np.abs(W.weight.sum(-1) - 1) < TOL["weights_f64"])


def test_barycentric_seam_is_continuous_and_exact():
    """Targets at c = 0, just below 1 and at a value that wraps to 1.0: same triangle."""
    rng = np.random.default_rng(3)
    c, a = rng.random(30), rng.random(30)
    targets = np.array([[0.0, 0.5], [1.0 - 1e-12, 0.5], [-1e-20, 0.5], [0.5, 0.5]])
    W = ip.method_weights("barycentric", c, a, targets)
    s, mc, ma = _moments(W, c, a, targets % [1.0, 2.0])
    tol = TOL["weights_f64"]
    assert np.all(np.abs(s - 1) < tol) and np.all(np.abs(mc) < tol) and np.all(np.abs(ma) < tol)
    d0, d1, d2 = _as_dict(W, 0), _as_dict(W, 1), _as_dict(W, 2)
    assert set(d0) == set(d1) == set(d2)
    for k in d0:
        assert d1[k] == pytest.approx(d0[k], abs=1e-9) and d2[k] == pytest.approx(d0[k], abs=1e-12)


def test_barycentric_both_fallbacks_outside_the_hull():
    c = np.array([0.45, 0.60, 0.05, 0.90])
    a = np.array([0.30, 0.28, 0.10, 0.25])
    targets = np.array([[0.55, 0.5], [0.97, 0.6], [0.25, 0.05]])
    W = ip.method_weights("barycentric", c, a, targets)
    # (1) above every point: projection onto the segment of the two nearest
    p1, p2, q = np.array([0.45, 0.30]), np.array([0.60, 0.28]), targets[0]
    t = (q - p1) @ (p2 - p1) / ((p2 - p1) @ (p2 - p1))
    assert _as_dict(W, 0) == pytest.approx({0: 1 - t, 1: t})
    # (2) across the seam: nearest (0.90, 0.25), then (0.05, 0.10) at circular dc 0.08, both
    # within 0.3 in c: projection in circular coordinates, clamped to the segment
    dc1, dc2 = circular_difference(0.90, 0.97), circular_difference(0.05, 0.97)
    p1, p2 = np.array([dc1, 0.25]), np.array([dc2, 0.10])
    e = p2 - p1
    t = np.clip((np.array([0.0, 0.6]) - p1) @ e / (e @ e), 0, 1)
    assert _as_dict(W, 1) == pytest.approx({3: 1 - t, 2: t} if t > 0 else {3: 1.0})
    # (3) below every point, the second nearest more than 0.3 away in c: the nearest alone
    W = ip.method_weights("barycentric", np.array([0.25, 0.70]), np.array([0.3, 0.9]), [[0.25, 0.05]])
    assert _as_dict(W, 0) == {0: 1.0}


def test_barycentric_fallback_with_coinciding_nearest_points():
    """The two nearest points coincide (zero-length segment): the nearest alone, finite."""
    W = ip.method_weights("barycentric", [0.5, 0.5, 0.5], [0.2, 0.2, 0.2], [[0.6, 0.9], [0.5, 0.2]])
    assert np.all(np.isfinite(W.weight))
    assert sum(_as_dict(W, 0).values()) == pytest.approx(1.0)
    assert sum(_as_dict(W, 1).values()) == pytest.approx(1.0)


_KINDS = ["random", "collinear", "near_collinear", "duplicates", "one_amplitude", "fewer_than_three"]


@pytest.mark.parametrize("kappa,sigma", KERNELS)
@pytest.mark.parametrize("kind", _KINDS)
def test_local_linear_kernel_with_guard_flags_matches_the_reference(kind, kappa, sigma):
    """The extrapolation guard's per-row flags (drop the dc and/or da slope column) on rows of
    every degenerate kind: single and double kernels against the float64 reference, which
    sums to one; guard 0 rows equal the unguarded solve exactly."""
    rng = np.random.default_rng([_KINDS.index(kind), int(kappa), int(1000 * sigma)])
    dc, da, count = _stiff_rows(kind, rng)
    guard = rng.integers(0, 4, count.size)
    ref = ip.local_linear_solve_reference(dc, da, count, kappa, sigma, guard=guard)
    scale = _scale(ref)
    assert np.all(np.isfinite(ref))
    assert np.all(np.abs(ref.sum(1) - 1) < TOL["weights_f64"] * scale)
    zero = guard == 0
    np.testing.assert_array_equal(ref[zero], ip.local_linear_solve_reference(dc, da, count, kappa, sigma)[zero])
    for precision in ("double", "single"):
        got = ip.local_linear_solve(dc, da, count, kappa, sigma, precision=precision, guard=guard)
        assert np.all(np.isfinite(got)), precision
        err = np.abs(got - ref).max(1) / scale
        tol = TOL["ll_double"] if precision == "double" else TOL["ll_single_raw"]
        assert err.max() < tol, (precision, err.max())
