"""Phase-space interpolation: exactness on linear data, fallbacks, degenerate inputs,
the two OpenCL kernels against their float64 references, and weight invariants."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from scipy.spatial import Delaunay, QhullError

from clrecon.bench import reference_kernels
from clrecon.core.conventions import circular_difference
from clrecon.reconstruction.interpolation import barycentric as ip_bary
from clrecon.reconstruction.interpolation import weights as ip

# One table for every tolerance in this file: (what is compared, why it is not zero).
TOL = {
    # float64 weights: sum to one / reproduce linear data, relative to max(1, sum |w|)
    "weights_f64": 1e-9,
    # local_linear_weights kernel vs float64 reference, max |dl| / max(1, sum |l_ref|):
    # double build (rounding only) and single build (cond(C) <= 1 / LL_RCOND = 1e4 times
    # float32 eps; measured 1.2e-4 on random near-collinear rows)
    "ll_kernel_double": 1e-9,
    "ll_kernel_single": 1e-3,
    # apply_weights kernel (float32 rows, weights and sums) vs float64 reference,
    # max |diff| / (max |rows| * max sum_k |w|)
    "apply_f32": 1e-6,
    # linear sinogram reproduced through float32 weights and apply_weights, relative to max |row|
    "linear_rows_f32": 1e-5,
}

TARGETS = np.array([[c, a] for c in (0.0, 0.2, 0.4, 0.6, 0.8) for a in np.arange(0.05, 1.0, 0.1)])


def _moments(W, c, a, targets, use_cardiac=True, use_resp=True):
    """Per target: sum w, sum w dc, sum w da (dc circular about the target)."""
    dc = circular_difference(c[W.index], targets[:, None, 0]) if use_cardiac else 0.0 * W.weight
    da = a[W.index] - targets[:, None, 1] if use_resp else 0.0 * W.weight
    return W.weight.sum(-1), (W.weight * dc).sum(-1), (W.weight * da).sum(-1)


def _scale(W):
    return np.maximum(1.0, np.abs(W.weight).sum(-1))


def _as_dict(W, t):
    d = {}
    for i, w in zip(W.index[t], W.weight[t], strict=True):
        if w != 0:
            d[int(i)] = d.get(int(i), 0.0) + float(w)
    return d


# ---------------------------------------------------------------------------------------
# exactness on linear and constant data
@pytest.mark.parametrize("method", ["barycentric", "local_linear"])
def test_linear_data_reproduced_exactly_including_the_seam(method):
    rng = np.random.default_rng(11)
    c, a = rng.random(150), rng.random(150)
    targets = np.array([[cs, as_] for cs in (0.0, 0.004, 0.5, 0.99, 0.997) for as_ in (0.3, 0.5, 0.72)])
    W = ip.method_weights(method, c, a, targets)
    s, mc, ma = _moments(W, c, a, targets)
    tol = TOL["weights_f64"] * _scale(W)
    assert np.all(np.abs(s - 1) < tol)
    assert np.all(np.abs(mc) < tol)   # linear in the circular dc: exact across c = 0/1
    assert np.all(np.abs(ma) < tol)
    if method == "barycentric":
        assert np.all(W.weight >= 0) and W.index.shape[-1] == 3


@pytest.mark.parametrize("method", ["barycentric", "local_linear"])
def test_linear_sinogram_rows_through_apply_weights(method):
    """Rows y_k = alpha + beta dc_k + gamma da_k (circular-linear about a seam target)."""
    rng = np.random.default_rng(5)
    n, C = 120, 70
    c, a = rng.random(n), rng.random(n)
    target = np.array([[0.995, 0.45]])
    alpha, beta, gamma = rng.random(C) + 1.0, rng.normal(size=C), rng.normal(size=C)
    dc = circular_difference(c, target[0, 0])
    rows = (alpha + beta * dc[:, None] + gamma * (a - target[0, 1])[:, None]).astype(np.float32)
    W = ip.method_weights(method, c, a, target)
    out = reference_kernels.apply_weights(rows, W.index, W.weight.astype(np.float32))
    assert np.abs(out[0] - alpha).max() < TOL["linear_rows_f32"] * np.abs(rows).max()


@pytest.mark.parametrize("method", ip.METHODS)
def test_constant_rows_reproduced_by_every_method(method):
    rng = np.random.default_rng(2)
    c, a = rng.random(40), rng.random(40)
    W = ip.method_weights(method, c, a, TARGETS, dz=rng.random(40) * 10)   # dz (mm): helical reads it
    rows = np.full((40, 33), 2.5, np.float32)
    out = reference_kernels.apply_weights(rows, W.index, W.weight.astype(np.float32))
    assert out.shape == (TARGETS.shape[0], 33)
    np.testing.assert_allclose(out, 2.5, rtol=TOL["linear_rows_f32"])
    assert np.all(np.abs(W.weight.sum(-1) - 1) < TOL["weights_f64"] * _scale(W))


def test_r4dct_is_linear_in_amplitude_and_ignores_cardiac_phase():
    rng = np.random.default_rng(4)
    c, a = rng.random(30), rng.uniform(0.1, 0.9, 30)
    targets = np.array([[0.0, 0.5], [0.7, 0.5], [0.3, 0.2], [0.3, 0.05], [0.3, 0.97]])
    W = ip.method_weights("r4dct", c, a, targets)
    s, _, ma = _moments(W, c, a, targets)
    assert np.all(np.abs(s - 1) < TOL["weights_f64"])
    assert np.all(np.abs(ma[:3]) < TOL["weights_f64"])                    # inside: linear in a
    np.testing.assert_array_equal(W.weight[0], W.weight[1])               # c* does not matter
    assert _as_dict(W, 3) == {int(np.argmin(a)): 1.0}                     # below: nearest in a
    assert _as_dict(W, 4) == {int(np.argmax(a)): 1.0}                     # above: nearest in a


def test_nearest_uses_the_circular_cardiac_distance():
    c = np.array([0.98, 0.06, 0.5])
    a = np.array([0.5, 0.5, 0.5])
    W = ip.method_weights("nearest", c, a, [[0.01, 0.5]])
    assert _as_dict(W, 0) == {0: 1.0}


def test_bin_averages_the_bin_across_the_seam_and_falls_back_to_nearest():
    c = np.array([0.95, 0.05, 0.12, 0.93, 0.5])
    a = np.array([0.52, 0.48, 0.5, 0.7, 0.5])
    W = ip.method_weights("bin", c, a, [[0.0, 0.5], [0.5, 0.95]], cardiac_bin_width=0.2, resp_bin_width=0.1)
    assert _as_dict(W, 0) == pytest.approx({0: 0.5, 1: 0.5})   # 0.12 outside in c, 0.93 in a
    assert _as_dict(W, 1) == {4: 1.0}                            # empty bin: nearest point
    # a wider amplitude bin takes in the 0.93 point as well
    W = ip.method_weights("bin", c, a, [[0.0, 0.5]], cardiac_bin_width=0.2, resp_bin_width=0.5)
    assert _as_dict(W, 0) == pytest.approx({0: 1 / 3, 1: 1 / 3, 3: 1 / 3})


# ---------------------------------------------------------------------------------------
# barycentric: agreement with a plain full Delaunay, fallbacks, degenerate input
def _barycentric_reference(c, a, targets):
    """Paper algorithm written plainly: full copied Delaunay, else two nearest / nearest.
    A triangle with a vertex of non-zero coordinate (> 1e-9) farther than 0.3 from the target
    in circular c is not used (the |dc| limit, docs/choices-reconstruction.md "Barycentric details")."""
    n = c.size
    P = np.concatenate([np.stack([c + s, a], axis=1) for s in (0.0, -1.0, 1.0)])
    tri = Delaunay(P)
    simp = tri.find_simplex(targets)
    out = []
    for t, s in enumerate(simp):
        use = s >= 0
        if use:
            b = tri.transform[s, :2] @ (targets[t] - tri.transform[s, 2])
            lam = [b[0], b[1], 1 - b.sum()]
            far = np.abs(circular_difference(c[tri.simplices[s] % n], targets[t, 0])) > 0.3 + 1e-12
            use = not np.any(far & (np.array(lam) > 1e-9))
        if use:
            d = {}
            for v, l in zip(tri.simplices[s] % n, lam, strict=True):
                d[int(v)] = d.get(int(v), 0.0) + l
            out.append(d)
            continue
        dc = circular_difference(c, targets[t, 0])
        da = a - targets[t, 1]
        i1, i2 = np.argsort(dc ** 2 + da ** 2, kind="stable")[:2]
        if abs(dc[i1]) > 0.3 or abs(dc[i2]) > 0.3:
            out.append({int(i1): 1.0})
            continue
        e = np.array([dc[i2] - dc[i1], da[i2] - da[i1]])
        tt = np.clip(-(dc[i1] * e[0] + da[i1] * e[1]) / (e @ e), 0, 1)
        out.append({int(i1): 1 - tt, int(i2): tt})
    return out


def _dicts_close(got, ref, tol):
    keys = set(got) | set(ref)
    return all(abs(got.get(k, 0.0) - ref.get(k, 0.0)) < tol for k in keys)


@pytest.mark.parametrize("seed,n", [(0, 6), (1, 15), (2, 44), (3, 90)])
def test_barycentric_matches_a_plain_full_delaunay(seed, n):
    rng = np.random.default_rng(seed)
    c, a = rng.random(n), rng.uniform(0.1, 0.9, n)
    targets = np.concatenate([TARGETS, rng.random((20, 2))])
    W = ip.method_weights("barycentric", c, a, targets)
    ref = _barycentric_reference(c, a, targets)
    for t in range(targets.shape[0]):
        assert _dicts_close(_as_dict(W, t), ref[t], 1e-9), (t, _as_dict(W, t), ref[t])


def test_barycentric_margin_shortcut_is_exact(monkeypatch):
    """With a tiny margin many triangles found in the cut-down point set are not Delaunay
    in the full copied set: the circumcircle check must send those groups to a full
    triangulation, and the result must equal the plain full Delaunay."""
    monkeypatch.setattr(ip_bary, "DELAUNAY_MARGIN", 0.02)
    sizes = []
    real = ip_bary._delaunay_one
    monkeypatch.setattr(ip_bary, "_delaunay_one", lambda pts, tg: sizes.append(pts.shape[0]) or real(pts, tg))
    rng = np.random.default_rng(8)
    n, G = 20, 6
    c, a = rng.random(n * G), rng.uniform(0.1, 0.9, n * G)
    W = ip.batch_weights("barycentric", c, a, np.arange(G + 1) * n, TARGETS)
    assert 3 * n in sizes and min(sizes) < 3 * n          # shortcut tried, some groups redone
    for g in range(G):
        ref = _barycentric_reference(c[g * n:(g + 1) * n], a[g * n:(g + 1) * n], TARGETS)
        Wg = ip.Weights(index=W.index[g] - g * n, weight=W.weight[g])
        for t in range(TARGETS.shape[0]):
            assert _dicts_close(_as_dict(Wg, t), ref[t], 1e-9), (g, t)


def test_barycentric_fallback_projects_onto_the_two_nearest_or_takes_the_nearest():
    # every point at a <= 0.3: a target at a = 0.5 is in no triangle
    c = np.array([0.45, 0.6, 0.05])
    a = np.array([0.3, 0.28, 0.1])
    W = ip.method_weights("barycentric", c, a, [[0.55, 0.5], [0.95, 0.5]])
    # target 0: nearest (0.45, 0.3), then (0.6, 0.28); projection parameter from the nearest
    p1, p2, q = np.array([0.45, 0.3]), np.array([0.6, 0.28]), np.array([0.55, 0.5])
    t = (q - p1) @ (p2 - p1) / ((p2 - p1) @ (p2 - p1))
    assert 0 < t < 1
    assert _as_dict(W, 0) == pytest.approx({0: 1 - t, 1: t})
    # target 1 (c = 0.95): nearest is (0.05, 0.1) across the seam; the next one is 0.4 away
    # in c (> 0.3): the nearest alone
    assert _as_dict(W, 1) == {2: 1.0}


@pytest.mark.parametrize("a_value", [0.5, 0.0])
def test_barycentric_all_points_at_one_amplitude_is_not_an_error(a_value):
    """Breath hold requested as 2-D: collinear points, Qhull cannot triangulate."""
    c = np.array([0.1, 0.3, 0.5, 0.7, 0.3])
    a = np.full(5, a_value)
    W = ip.method_weights("barycentric", c, a, TARGETS)
    assert np.all(np.isfinite(W.weight)) and np.all(np.abs(W.weight.sum(-1) - 1) < TOL["weights_f64"])


# ---------------------------------------------------------------------------------------
# reduced (1-D) problems
@pytest.mark.parametrize("method", ["barycentric", "local_linear", "r4dct"])
def test_no_cardiac_motion_is_exact_1d_in_amplitude(method):
    rng = np.random.default_rng(9)
    c, a = rng.random(25), rng.random(25)
    targets = np.array([[0.0, 0.35], [0.6, 0.35], [0.2, 0.71]])
    inside = (targets[:, 1] > a.min()) & (targets[:, 1] < a.max())
    assert inside.all()
    W = ip.method_weights(method, c, a, targets, use_cardiac=False)
    s, _, ma = _moments(W, c, a, targets, use_cardiac=False)
    assert np.all(np.abs(s - 1) < TOL["weights_f64"]) and np.all(np.abs(ma) < TOL["weights_f64"])
    np.testing.assert_array_equal(W.weight[0], W.weight[1])                # c* ignored
    W2 = ip.method_weights(method, rng.permutation(c), a, targets, use_cardiac=False)
    np.testing.assert_allclose(W2.weight, W.weight, atol=1e-12)            # c ignored


@pytest.mark.parametrize("method", ["barycentric", "local_linear"])
def test_no_breathing_is_exact_1d_in_cardiac_phase(method):
    c = np.linspace(0.0, 1.0, 12, endpoint=False) + 0.01
    a = np.random.default_rng(1).random(12)
    targets = np.array([[0.0, 0.1], [0.5, 0.9], [0.97, 0.5]])
    W = ip.method_weights(method, c, a, targets, use_resp=False)
    s, mc, _ = _moments(W, c, a, targets, use_resp=False)
    assert np.all(np.abs(s - 1) < TOL["weights_f64"]) and np.all(np.abs(mc) < TOL["weights_f64"])
    np.testing.assert_array_equal(W.weight[1], ip.method_weights(method, c, a[::-1], targets,
                                                                 use_resp=False).weight[1])


def test_no_breathing_barycentric_gap_rule():
    c = np.array([0.1, 0.5])
    W = ip.method_weights("barycentric", c, [0.5, 0.5], [[0.2, 0.5]], use_resp=False)
    assert _as_dict(W, 0) == {0: 1.0}    # bracket 0.1 .. 0.5 but 0.5 is 0.3 + away: nearest


def test_no_motion_at_all_takes_the_first_candidate():
    """Every phase-space method sees one point when nothing moves; the phase-blind ``helical``
    keeps its own rule (the turn nearest in z)."""
    from clrecon.reconstruction.interpolation import METHODS as REGISTRY
    for method in ip.METHODS:
        W = ip.method_weights(method, [0.3, 0.1], [0.2, 0.9], TARGETS, use_cardiac=False, use_resp=False,
                              dz=[5.0, 1.0])
        first = 1 if not REGISTRY[method].axes else 0
        assert np.all(W.index[:, 0] == first) and np.all(W.weight[:, 0] == 1.0), method


# ---------------------------------------------------------------------------------------
# local linear: selection and degenerate fits
def test_local_linear_selects_two_nearest_per_quadrant_with_axis_points_non_negative():
    t = np.array([[0.5, 0.5]])
    pts = np.array([
        [0.55, 0.55], [0.6, 0.6], [0.7, 0.7],        # (+,+): two nearest only
        [0.5, 0.58],                                  # on the da axis (dc = 0): (+,+), nearest
        [0.45, 0.45], [0.4, 0.4],                     # (-,-)
        [0.42, 0.56],                                 # (-,+)
        [0.58, 0.44], [0.56, 0.5],                    # (+,-) and on the dc axis (da = 0): (+,+)
    ])
    W = ip.method_weights("local_linear", pts[:, 0], pts[:, 1], t)
    # (+,+) holds 0.56/0.5 (distance 0.06), 0.55/0.55 (0.071), 0.5/0.58 (0.08), 0.6/0.6,
    # 0.7/0.7 -> 8 and 0; (-,-) -> 4, 5; (-,+) -> 6 only (point 3 is not in it); (+,-) -> 7
    assert set(_as_dict(W, 0)) == {8, 0, 4, 5, 6, 7}


def test_local_linear_fewer_than_three_points_gives_the_nearest():
    c = np.array([0.6, 0.7, 0.9])
    a = np.array([0.6, 0.7, 0.9])     # all in one quadrant: two selected
    W = ip.method_weights("local_linear", c, a, [[0.5, 0.5]])
    assert _as_dict(W, 0) == {0: 1.0}


def test_local_linear_collinear_points_fit_along_the_line():
    s = np.array([-0.2, -0.1, 0.05, 0.15, 0.3])
    c = 0.5 + s
    a = 0.4 + s                        # on the line a - c = -0.1, target off the line
    target = np.array([[0.5, 0.5]])
    W = ip.method_weights("local_linear", c, a, target)
    w, mc, ma = _moments(W, c, a, target)
    foot = np.array([0.05, -0.05])     # perpendicular foot of the target on the line, target-centred
    assert abs(w[0] - 1) < TOL["weights_f64"]
    np.testing.assert_allclose([mc[0], ma[0]], foot, atol=TOL["weights_f64"])


def test_local_linear_coinciding_points_and_underflowing_weights_stay_finite():
    W = ip.method_weights("local_linear", [0.3] * 4, [0.6] * 4, [[0.3, 0.6], [0.9, 0.0]])
    assert np.all(np.isfinite(W.weight)) and np.all(np.abs(W.weight.sum(-1) - 1) < TOL["weights_f64"])
    rng = np.random.default_rng(3)
    c, a = rng.random(30), rng.random(30)
    W = ip.method_weights("local_linear", c, a, TARGETS, kappa=50.0, sigma=1e-4)
    assert np.all(np.isfinite(W.weight)) and np.all(np.abs(W.weight.sum(-1) - 1) < TOL["weights_f64"])


# ---------------------------------------------------------------------------------------
# the local_linear_weights kernel
def _ll_rows(rng, n):
    """Realistic rows (8 points spread around the target) and adversarial edge rows."""
    dc = rng.normal(0, 0.1, (n, 8))
    da = rng.normal(0, 0.2, (n, 8))
    count = rng.integers(1, 9, n)
    edge_dc = np.zeros((8, 8))
    edge_da = np.zeros((8, 8))
    edge_cnt = np.array([0, 1, 2, 8, 8, 8, 8, 3])
    edge_dc[1, 0], edge_da[1, 0] = 0.3, -0.2                      # one point
    edge_dc[2, :2], edge_da[2, :2] = [0.1, -0.1], [0.05, 0.05]   # two points
    edge_dc[3] = np.linspace(-0.2, 0.2, 8)                        # all at one amplitude
    edge_da[4] = np.linspace(-0.2, 0.2, 8)                        # all at one phase
    edge_dc[5] = edge_da[5] = np.linspace(-0.3, 0.3, 8)           # collinear on a diagonal
    edge_dc[6], edge_da[6] = 0.1, 0.1                             # all coincide, off target
    edge_dc[7, :3], edge_da[7, :3] = [-0.5, 0.49, 0.0], [1.0, -1.0, 0.0]  # far points, tiny weights
    return (np.concatenate([dc, edge_dc]), np.concatenate([da, edge_da]),
            np.concatenate([count, edge_cnt]))


@pytest.mark.parametrize("precision", ["double", "single"])
def test_local_linear_kernel_matches_reference(precision):
    rng = np.random.default_rng(21)
    dc, da, count = _ll_rows(rng, 3000)
    ref = ip.local_linear_solve_reference(dc, da, count, 1.0, 0.15)
    got = ip.local_linear_solve(dc, da, count, 1.0, 0.15, precision=precision)
    scale = np.maximum(1.0, np.abs(ref).sum(1))
    assert np.all(np.isfinite(got))
    assert np.all(np.abs(got - ref).max(1) / scale < TOL[f"ll_kernel_{precision}"])
    live = count > 0
    assert np.all(np.abs(ref[live].sum(1) - 1) < TOL["weights_f64"] * scale[live])
    assert np.all(ref[~live] == 0)


def test_local_linear_reference_equals_the_normal_equations_when_well_posed():
    rng = np.random.default_rng(7)
    dc, da = rng.normal(0, 0.1, (200, 8)), rng.normal(0, 0.2, (200, 8))
    count = np.full(200, 8)
    kappa, sigma = 1.0, 0.15
    got = ip.local_linear_solve_reference(dc, da, count, kappa, sigma)
    for i in range(200):
        X = np.stack([np.ones(8), dc[i], da[i]], axis=1)
        w = np.exp(kappa * (np.cos(2 * np.pi * dc[i]) - 1)) * np.exp(-da[i] ** 2 / (2 * sigma ** 2))
        XtW = X.T * w
        l = np.linalg.solve(XtW @ X, XtW)[0]          # e1^T (X^T W X)^-1 X^T W
        np.testing.assert_allclose(got[i], l, atol=TOL["weights_f64"] * max(1, np.abs(l).sum()))


def test_local_linear_solve_rejects_bad_shapes():
    # K slots come from the shape (1..LL_MAX_SLOTS); dc and da must agree
    with pytest.raises(ValueError):
        ip.local_linear_solve(np.zeros((3, 7)), np.zeros((3, 8)), np.ones(3, int), 1.0, 0.15)
    with pytest.raises(ValueError):
        ip.local_linear_solve(np.zeros((3, 33)), np.zeros((3, 33)), np.ones(3, int), 1.0, 0.15)
    with pytest.raises(ValueError, match="count"):
        ip.local_linear_solve(np.zeros((3, 5)), np.zeros((3, 5)), np.full(3, 6), 1.0, 0.15)
    with pytest.raises(ValueError, match="count"):
        ip.local_linear_solve(np.zeros((3, 8)), np.zeros((3, 8)), np.full(3, 9), 1.0, 0.15)
    with pytest.raises(ValueError, match="precision"):
        ip.local_linear_solve(np.zeros((3, 8)), np.zeros((3, 8)), np.ones(3, int), 1.0, 0.15, precision="half")


# ---------------------------------------------------------------------------------------
# the apply_weights kernel
@pytest.mark.parametrize("P,B,K,C", [(50, 37, 8, 900), (5, 3, 1, 1), (7, 64, 3, 65), (1, 2, 2, 130)])
def test_apply_weights_kernel_matches_reference(P, B, K, C):
    rng = np.random.default_rng(P * B + K + C)
    rows = rng.normal(size=(P, C)).astype(np.float32)
    index = rng.integers(0, P, (B, K)).astype(np.int32)
    weight = rng.normal(size=(B, K)).astype(np.float32)
    weight[rng.random((B, K)) < 0.2] = 0.0
    got = reference_kernels.apply_weights(rows, index, weight)
    ref = ip.apply_weights_reference(rows, index, weight)
    scale = np.abs(rows).max() * max(np.abs(weight).sum(1).max(), 1e-30)
    assert got.shape == (B, C) and got.dtype == np.float32
    assert np.abs(got - ref).max() / scale < TOL["apply_f32"]


def test_apply_weights_edge_cases():
    rows = np.ones((3, 10), np.float32)
    rows[2] = np.nan                                      # a row no target uses
    index = np.array([[0, 2, 0], [1, 1, 2]], np.int32)    # zero-weight slots point at it
    weight = np.array([[0.25, 0.0, 0.75], [0.5, 0.5, 0.0]], np.float32)
    for fn in (reference_kernels.apply_weights, ip.apply_weights_reference):
        out = fn(rows, index, weight)
        np.testing.assert_allclose(out, 1.0, rtol=1e-7)   # duplicate indices add, NaN never read
    empty = reference_kernels.apply_weights(rows, np.zeros((0, 3), np.int32), np.zeros((0, 3), np.float32))
    assert empty.shape == (0, 10)
    with pytest.raises(ValueError, match="index"):
        reference_kernels.apply_weights(rows, np.array([[3]], np.int32), np.array([[1.0]], np.float32))
    with pytest.raises(TypeError, match="index"):
        reference_kernels.apply_weights(rows, np.array([[0.0]]), np.array([[1.0]], np.float32))
    with pytest.raises(ValueError, match="shape"):
        reference_kernels.apply_weights(rows, np.array([[0, 1]], np.int32), np.array([[1.0]], np.float32))


# ---------------------------------------------------------------------------------------
# batching, API and invariants
@pytest.mark.parametrize("method", ip.METHODS)
def test_batch_weights_equal_per_group_weights(method):
    rng = np.random.default_rng(13)
    counts = np.array([1, 2, 3, 17, 40, 5])
    off = np.concatenate([[0], np.cumsum(counts)])
    c, a = rng.random(off[-1]), rng.random(off[-1])
    dz = rng.uniform(-10, 10, off[-1])
    B = ip.batch_weights(method, c, a, off, TARGETS, chunk_groups=4, dz=dz)
    assert B.index.shape[:2] == (counts.size, TARGETS.shape[0]) and B.index.dtype == np.int32
    for g in range(counts.size):
        W = ip.method_weights(method, c[off[g]:off[g + 1]], a[off[g]:off[g + 1]], TARGETS, dz=dz[off[g]:off[g + 1]])
        K = W.index.shape[-1]
        np.testing.assert_allclose(B.weight[g, :, :K], W.weight, atol=1e-12)
        assert np.all(B.weight[g, :, K:] == 0)
        live = W.weight != 0
        np.testing.assert_array_equal(B.index[g, :, :K][live], W.index[live] + off[g])


def test_empty_groups_raise_unless_allowed():
    off = [0, 3, 3, 5]
    c, a = np.linspace(0, 0.9, 5), np.linspace(0.1, 0.9, 5)
    with pytest.raises(ip.NoCandidatesError, match="group 1"):
        ip.batch_weights("local_linear", c, a, off, TARGETS)
    B = ip.batch_weights("local_linear", c, a, off, TARGETS, allow_empty=True)
    assert np.all(B.weight[1] == 0) and np.all(np.abs(B.weight[[0, 2]].sum(-1) - 1) < 1e-9)
    with pytest.raises(ip.NoCandidatesError):
        ip.method_weights("nearest", [], [], TARGETS)


def test_bad_arguments_are_rejected():
    with pytest.raises(ValueError, match="method"):
        ip.method_weights("cubic", [0.1], [0.2], TARGETS)
    with pytest.raises(ValueError, match="targets"):
        ip.method_weights("nearest", [0.1], [0.2], np.zeros((3, 3)))
    with pytest.raises(ValueError, match="offsets"):
        ip.batch_weights("nearest", [0.1, 0.2], [0.2, 0.3], [0, 1], TARGETS)
    with pytest.raises(ValueError, match="finite"):
        ip.method_weights("nearest", [np.nan], [0.2], TARGETS)
    with pytest.raises(ValueError, match="sigma"):
        ip.method_weights("local_linear", [0.1], [0.2], TARGETS, sigma=0.0)


def test_compact_keeps_only_candidates_with_weight():
    rng = np.random.default_rng(0)
    off = np.array([0, 30, 60])
    c, a = rng.random(60), rng.random(60)
    W = ip.batch_weights("barycentric", c, a, off, TARGETS)
    used, Wc = W.compact()
    assert np.all(np.diff(used) > 0) and used.size < 60
    rows = rng.normal(size=(60, 9)).astype(np.float32)
    full = reference_kernels.apply_weights(rows, W.index.reshape(-1, 3), W.weight.reshape(-1, 3).astype(np.float32))
    small = reference_kernels.apply_weights(rows[used], Wc.index.reshape(-1, 3),
                                            Wc.weight.reshape(-1, 3).astype(np.float32))
    np.testing.assert_array_equal(full, small)


# coordinates on a coarse lattice make duplicates, collinear runs and targets on edges common
_coord = st.one_of(st.integers(0, 4).map(lambda i: i / 4), st.floats(0, 1, exclude_max=True))
_points = st.lists(st.tuples(_coord, _coord), min_size=1, max_size=25)


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(pts=_points, targets=st.lists(st.tuples(_coord, _coord), min_size=1, max_size=6),
       method=st.sampled_from(ip.METHODS), use_cardiac=st.booleans(), use_resp=st.booleans(),
       same_amplitude=st.booleans())
def test_weights_are_finite_and_sum_to_one(pts, targets, method, use_cardiac, use_resp, same_amplitude):
    p = np.array(pts, dtype=np.float64)
    c, a = p[:, 0] % 1.0, p[:, 1]
    if same_amplitude:
        a = np.full_like(a, a[0])
    dz = np.arange(c.size, 0, -1) % 3.0   # mm, with ties
    W = ip.method_weights(method, c, a, np.array(targets), use_cardiac=use_cardiac, use_resp=use_resp, dz=dz)
    assert np.all(np.isfinite(W.weight))
    assert np.all((W.index >= 0) & (W.index < c.size))
    assert np.all(np.abs(W.weight.sum(-1) - 1) < TOL["weights_f64"] * _scale(W))
    if method != "local_linear":  # all but the regression are convex combinations
        assert np.all(W.weight >= 0)


def _inside_copied_hull(c, a, targets):
    """Targets inside the convex hull of the points and their copies at c - 1 and c + 1, by
    a margin (barycentric 1e-9): a target within rounding of the hull is inside for Qhull's
    default tolerance but outside for the exact amplitude test, and either answer is right."""
    P = np.concatenate([np.stack([c + s, a], axis=1) for s in (0.0, -1.0, 1.0)])
    try:
        # bruteforce: the directed walk can cycle forever on degenerate (lattice) triangulations
        return Delaunay(P).find_simplex(targets, bruteforce=True, tol=-1e-9) >= 0
    except (QhullError, ValueError):  # fewer than three distinct points, or all collinear
        return np.zeros(len(targets), dtype=bool)


@settings(max_examples=100, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(pts=_points, targets=st.lists(st.tuples(_coord, _coord), min_size=1, max_size=6),
       method=st.sampled_from(["barycentric", "local_linear", "r4dct"]),
       kernel=st.sampled_from([(1.0, 0.15), (10.0, 0.05), (100.0, 0.01)]),
       n_dup=st.integers(0, 3), collinear=st.booleans())
def test_linear_data_reproduced_where_the_method_promises_it(pts, targets, method, kernel, n_dup, collinear):
    """Barycentric inside the hull of the copied points (in some consistent unwrapping of c)
    where the triangle is used (its |dc| limit),
    local linear where its weighted points are well conditioned (>= 3, not collinear), r4dct
    in amplitude inside the sampled range; weights always finite and summing to one."""
    p = np.array(pts, dtype=np.float64)
    c, a = p[:, 0] % 1.0, p[:, 1]
    if collinear:                          # all points on one line through the plane
        a = 0.2 + 0.5 * c
    c, a = np.concatenate([c, c[:n_dup]]), np.concatenate([a, a[:n_dup]])   # duplicates
    tg = np.array(targets, dtype=np.float64)
    kappa, sigma = kernel
    W = ip.method_weights(method, c, a, tg, kappa=kappa, sigma=sigma)
    scale = _scale(W)
    assert np.all(np.isfinite(W.weight))
    assert np.all(np.abs(W.weight.sum(-1) - 1) < TOL["weights_f64"] * scale)
    tol = TOL["weights_f64"] * scale
    dc = circular_difference(c[W.index], tg[:, None, 0])
    da = a[W.index] - tg[:, None, 1]
    ma = (W.weight * da).sum(-1)
    if method == "r4dct":
        inside = (tg[:, 1] >= a.min()) & (tg[:, 1] <= a.max())
        assert np.all(np.abs(ma[inside]) < tol[inside])
    elif method == "barycentric":
        # inside the hull, where the containing triangle is used: always when every point lies
        # within BARY_MAX_DC of the target in c (no vertex can break the triangle |dc| limit),
        # else where the method reports the triangle branch
        inside = _inside_copied_hull(c, a, tg % [1.0, 2.0])
        near = np.all(np.abs(circular_difference(c[None, :], tg[:, None, 0])) <= ip.BARY_MAX_DC, axis=1)
        inside &= near | (W.branch == ip_bary.BRANCH_TRIANGLE)
        assert np.all(np.abs(ma[inside]) < tol[inside])
        # c is periodic: each slot's vertex is the point or one of its copies at +-1
        shifts = np.array(np.meshgrid(*[[-1.0, 0.0, 1.0]] * 3, indexing="ij")).reshape(3, -1).T  # (27, 3)
        mc = np.abs((W.weight[:, None, :] * (dc[:, None, :] + shifts[None])).sum(-1)).min(-1)
        assert np.all(mc[inside] < tol[inside])
    else:
        for t in range(tg.shape[0]):
            used = W.weight[t] != 0
            x, y = dc[t][used], da[t][used]
            lk = kappa * (np.cos(2 * np.pi * x) - 1) - y * y / (2 * sigma * sigma)
            k = np.exp(lk - lk.max())
            m = np.array([k @ x, k @ y]) / k.sum()
            cov = np.cov(np.stack([x, y]), aweights=k, bias=True) if used.sum() > 1 else np.zeros((2, 2))
            d2 = np.trace(cov) + m @ m
            # the promise holds where the points bracket the target on both axes (no extrapolation guard)
            bracketed = not ((x > 0).all() or (x < 0).all() or (y > 0).all() or (y < 0).all())
            if bracketed and used.sum() >= 3 and np.linalg.eigvalsh(cov)[0] > 10 * max(ip.LL_RCOND * d2,
                                                                                       ip.LL_SPREAD ** 2):
                assert abs(W.weight[t] @ dc[t]) < tol[t] and abs(W.weight[t] @ da[t]) < tol[t]


def test_local_linear_does_not_extrapolate_along_an_unbracketed_axis():
    """Every point below the target amplitude: the default fit is constant in amplitude
    (weights within [0, 1] when c is bracketed, exact for data depending on c only), while
    ``extrapolate=True`` (the paper's plain fit) reproduces linear data by extrapolating."""
    import clrecon.reconstruction.interpolation.weights as ip
    c = np.array([0.30, 0.35, 0.45, 0.50, 0.38, 0.42])
    a = np.array([0.10, 0.20, 0.15, 0.05, 0.12, 0.18])
    target = np.array([[0.40, 0.60]])
    guarded = ip.method_weights("local_linear", c, a, target, precision="double")
    plain = ip.method_weights("local_linear", c, a, target, precision="double", extrapolate=True)
    lin_c = 3.0 + 2.0 * (c - 0.40)
    lin_ca = lin_c + 5.0 * (a - 0.60)
    g = guarded.weight[0] @ lin_c[guarded.index[0]]
    assert g == pytest.approx(3.0, abs=1e-9)                     # exact in c
    assert abs(guarded.weight[0]).sum() < 1.5                     # no amplification
    assert plain.weight[0] @ lin_ca[plain.index[0]] == pytest.approx(3.0, abs=1e-9)
    assert abs(plain.weight[0]).sum() > 2.0                       # it extrapolates
    assert guarded.weight[0].sum() == pytest.approx(1.0)


# ---------------------------------------------------------------------------------------
# the extrapolation guard keeps the kernel weights of the guarded axis (issue 10)
def _wls_value(y, dc, da, cols, kappa=1.0, sigma=0.15):
    """b0 of the weighted least squares y ~ b0 + (slopes of ``cols``), with the paper's kernel
    weights of the true (dc, da): the normal equations written out, independent of the solver."""
    w = np.exp(kappa * (np.cos(2 * np.pi * dc) - 1)) * np.exp(-da ** 2 / (2 * sigma ** 2))
    X = np.stack([np.ones_like(dc)] + [{"dc": dc, "da": da}[k] for k in cols], axis=1)
    return np.linalg.solve(X.T @ (w[:, None] * X), X.T @ (w * y))[0]


def test_local_linear_guard_keeps_the_amplitude_kernel_weights():
    """Issue 10 probe: every point below the target amplitude (guard along a), c bracketed.

    The expected value is b0 of y ~ b0 + b1 dc (the amplitude slope column dropped) with the
    full kernel weights of the true (dc, da), from the normal equations (``_wls_value``):
    0.5599. The old guard zeroed da before the weights, so every amplitude weight was 1: the
    same two-column fit with da = 0 in the kernel gives 0.5116. With the amplitude kernel the
    point nearest in amplitude (a = 0.6) weighs most, so the value moves towards the
    nearest-amplitude clamp 0.60. (It does not lie between the clamp and the kernel-weighted
    mean 0.5759, as the issue expected: the fit keeps its slope in c, and these rows fall
    with c, the points left of the target having the larger amplitudes.)"""
    c = np.array([0.35, 0.45, 0.30, 0.50])
    a = np.array([0.6, 0.4, 0.55, 0.5])
    target = np.array([[0.4, 0.95]])
    dc, da = c - 0.4, a - 0.95
    expected = _wls_value(a, dc, da, ["dc"])
    old = _wls_value(a, dc, 0.0 * da, ["dc"])
    clamp = a[np.argmin(np.abs(da))]
    for precision in ("double", "single"):
        W = ip.method_weights("local_linear", c, a, target, precision=precision)
        got = W.weight[0] @ a[W.index[0]]
        tol = TOL[f"ll_kernel_{precision}"] * max(1.0, np.abs(W.weight[0]).sum())
        assert got == pytest.approx(expected, abs=tol), precision
        assert abs(got - old) > 10 * tol                            # the old 0.512 is gone
        assert abs(got - clamp) < abs(old - clamp)                   # nearer the clamp than before
        assert a.min() <= got <= a.max()                             # no extrapolation in a
    # no cardiac motion (1-D in a): the two nearest points below the target, no slope left:
    # the mean weighted by the amplitude kernel (the old guard gave the plain mean, 0.575)
    W = ip.method_weights("local_linear", c, a, target, precision="double", use_cardiac=False)
    near = np.argsort(np.abs(da))[:2]
    w = np.exp(-da[near] ** 2 / (2 * 0.15 ** 2))
    assert W.weight[0] @ a[W.index[0]] == pytest.approx(w @ a[near] / w.sum(), abs=TOL["weights_f64"])
    assert abs(W.weight[0] @ a[W.index[0]] - a[near].mean()) > 1e-3


def test_local_linear_guard_reproduces_the_cardiac_slope_and_is_constant_in_amplitude():
    """Rows y = f(c) + g(a), both linear, every point below the target amplitude: the fit is
    y ~ b0 + b1 dc with the full kernel weights, so f is reproduced exactly (sum l = 1,
    sum l dc = 0) while g enters only through the weighted fit, with no amplitude slope (its
    value is the two-column fit of g, within the sampled amplitudes); the plain fit
    (``extrapolate=True``) instead reproduces g by extrapolating."""
    c = np.array([0.30, 0.35, 0.45, 0.50])   # two per lower quadrant: all four selected
    a = np.array([0.10, 0.30, 0.15, 0.05])
    t = np.array([0.40, 0.60])
    dc, da = circular_difference(c, t[0]), a - t[1]
    f = 3.0 + 2.0 * dc                       # linear in c
    g = 5.0 * da                             # linear in a
    W = ip.method_weights("local_linear", c, a, t[None], precision="double")
    l, idx = W.weight[0], W.index[0]
    assert sorted(idx[l != 0]) == [0, 1, 2, 3]
    tol = TOL["weights_f64"] * max(1.0, np.abs(l).sum())
    assert l.sum() == pytest.approx(1.0, abs=tol)
    assert abs(l @ dc[idx]) < tol                                   # the c-slope is reproduced
    assert l @ (f + g)[idx] == pytest.approx(3.0 + _wls_value(g, dc, da, ["dc"]), abs=tol)
    assert g.min() <= l @ g[idx] <= g.max()                         # constant in a: no extrapolation
    plain = ip.method_weights("local_linear", c, a, t[None], precision="double", extrapolate=True)
    assert plain.weight[0] @ (f + g)[plain.index[0]] == pytest.approx(3.0, abs=tol)
    # guard along c instead (every point left of the target), a bracketed: the mirror image
    t2 = np.array([0.55, 0.12])
    dc2, da2 = circular_difference(c, t2[0]), a - t2[1]
    W2 = ip.method_weights("local_linear", c, a, t2[None], precision="double")
    l2, idx2 = W2.weight[0], W2.index[0]
    assert abs(l2 @ da2[idx2]) < tol and l2.sum() == pytest.approx(1.0, abs=tol)
    assert l2 @ (2.0 * dc2)[idx2] == pytest.approx(_wls_value(2.0 * dc2, dc2, da2, ["da"]), abs=tol)


def _guard_flags(rng, n):
    return rng.integers(0, 4, n)             # bits ip.LL_GUARD_CARDIAC, ip.LL_GUARD_RESP


@pytest.mark.parametrize("precision", ["double", "single"])
def test_local_linear_kernel_matches_reference_with_guard_flags(precision):
    rng = np.random.default_rng(22)
    dc, da, count = _ll_rows(rng, 3000)
    guard = _guard_flags(rng, count.size)
    ref = ip.local_linear_solve_reference(dc, da, count, 1.0, 0.15, guard=guard)
    got = ip.local_linear_solve(dc, da, count, 1.0, 0.15, precision=precision, guard=guard)
    scale = np.maximum(1.0, np.abs(ref).sum(1))
    assert np.all(np.isfinite(got))
    assert np.all(np.abs(got - ref).max(1) / scale < TOL[f"ll_kernel_{precision}"])
    live = count > 0
    assert np.all(np.abs(ref[live].sum(1) - 1) < TOL["weights_f64"] * scale[live])
    # guard 0 is the plain solve, bit for bit
    zero = guard == 0
    np.testing.assert_array_equal(ref[zero], ip.local_linear_solve_reference(dc, da, count, 1.0, 0.15)[zero])


def test_local_linear_reference_with_guard_equals_the_reduced_normal_equations():
    """Well-posed rows: the reference with guard flags is the normal-equation solution with
    the guarded slope columns left out and the kernel weights of the true differences."""
    rng = np.random.default_rng(8)
    n = 300
    dc, da = rng.normal(0, 0.1, (n, 8)), rng.normal(0, 0.2, (n, 8))
    guard = _guard_flags(rng, n)
    got = ip.local_linear_solve_reference(dc, da, np.full(n, 8), 1.0, 0.15, guard=guard)
    for i in range(n):
        cols = [x for bit, x in ((ip.LL_GUARD_CARDIAC, dc[i]), (ip.LL_GUARD_RESP, da[i])) if not guard[i] & bit]
        X = np.stack([np.ones(8)] + cols, axis=1)
        w = np.exp(np.cos(2 * np.pi * dc[i]) - 1) * np.exp(-da[i] ** 2 / (2 * 0.15 ** 2))
        XtW = X.T * w
        l = np.linalg.solve(XtW @ X, XtW)[0]
        np.testing.assert_allclose(got[i], l, atol=TOL["weights_f64"] * max(1, np.abs(l).sum()))


def test_local_linear_solve_rejects_bad_guard_flags():
    z = np.zeros((3, 8))
    with pytest.raises(ValueError, match="guard"):
        ip.local_linear_solve(z, z, np.ones(3, int), 1.0, 0.15, guard=np.full(3, 4))
    with pytest.raises(ValueError, match="guard"):
        ip.local_linear_solve_reference(z, z, np.ones(3, int), 1.0, 0.15, guard=np.zeros(2, int))


# ---------------------------------------------------------------------------------------
# barycentric: the triangle |dc| limit and the branch report (issue 10)
def test_barycentric_rejects_a_triangle_with_a_vertex_far_in_cardiac_phase():
    """A sliver along the top of the sampled amplitudes: the target (0.4, 0.75) lies in the
    Delaunay triangle (0.35, 0.70), (0.45, 0.78), (0.75, 0.76), whose vertex at c = 0.75 is
    0.35 away in c (> BARY_MAX_DC): the segment fallback of the two nearest points is taken
    instead (both within 0.3). A target inside a triangle of near vertices keeps it."""
    c = np.array([0.35, 0.45, 0.75, 0.40, 0.10, 0.60, 0.90])
    a = np.array([0.70, 0.78, 0.76, 0.20, 0.10, 0.15, 0.10])
    targets = np.array([[0.4, 0.75], [0.4, 0.4]])
    P = np.concatenate([np.stack([c + s, a], axis=1) for s in (0.0, -1.0, 1.0)])
    tri = Delaunay(P)
    s = tri.find_simplex(targets[:1])[0]
    assert sorted(tri.simplices[s] % c.size) == [0, 1, 2]           # the sliver holds the target
    W = ip.method_weights("barycentric", c, a, targets)
    assert W.branch[0] == ip_bary.BRANCH_SEGMENT
    dc = circular_difference(c, 0.4)
    da = a - 0.75
    i1, i2 = np.argsort(dc ** 2 + da ** 2)[:2]
    e = np.array([dc[i2] - dc[i1], da[i2] - da[i1]])
    t = np.clip(-(np.array([dc[i1], da[i1]]) @ e) / (e @ e), 0, 1)
    assert _as_dict(W, 0) == pytest.approx({int(i1): 1 - t, int(i2): t})
    used = W.weight[0] != 0
    assert np.all(np.abs(circular_difference(c[W.index[0][used]], 0.4)) <= ip.BARY_MAX_DC)
    # (0.4, 0.4) lies in the triangle (0.35, 0.70), (0.40, 0.20), (0.60, 0.15), all within 0.3: kept
    assert W.branch[1] == ip_bary.BRANCH_TRIANGLE


def test_barycentric_branch_report_does_not_change_the_weights_and_names_each_branch():
    rng = np.random.default_rng(12)
    n, G = 25, 8
    c, a = rng.random(n * G), rng.uniform(0.1, 0.7, n * G)
    W = ip.batch_weights("barycentric", c, a, np.arange(G + 1) * n, TARGETS)
    assert W.branch.shape == W.weight.shape[:2] and W.branch.dtype == np.int8
    assert set(np.unique(W.branch)) <= {ip_bary.BRANCH_TRIANGLE, ip_bary.BRANCH_SEGMENT, ip_bary.BRANCH_NEAREST}
    live = (W.weight != 0).sum(-1)
    # nearest: one point; segment: at most two slots; triangle: the target in the convex hull
    # of its (up to three) weighted points
    assert np.all(live[W.branch == ip_bary.BRANCH_NEAREST] == 1)
    assert np.all(W.weight[..., 2][W.branch != ip_bary.BRANCH_TRIANGLE] == 0)
    assert {0, 1, 2} <= set(np.unique(W.branch).tolist())           # every branch occurs here
    for g in range(G):                                               # per group = batched
        Wg = ip.method_weights("barycentric", c[g * n:(g + 1) * n], a[g * n:(g + 1) * n], TARGETS)
        np.testing.assert_array_equal(Wg.branch, W.branch[g])
        np.testing.assert_array_equal(Wg.weight, W.weight[g])
    assert ip.method_weights("nearest", c[:n], a[:n], TARGETS).branch is None
