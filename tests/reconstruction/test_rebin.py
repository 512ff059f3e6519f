"""SSRB: window geometry, candidate selection, the ssrb_rows kernel against its float64
reference, and SSRB of a static analytic object against its exact in-plane sinogram."""

from __future__ import annotations

import numpy as np
import pytest

from clrecon.config.scene import ScannerConfig
from clrecon.core.conventions import detector_coords, detector_frames
from clrecon.reconstruction import rebin
from clrecon.scan.table import ProjectionTable

# One table for every tolerance in this file: (what is compared, why it is not zero).
TOL = {
    # kernel (float32 arithmetic, float32 output) vs float64 reference, max |diff| / max |ref|
    "ssrb_kernel_f32": 1e-5,
    # geometric identities evaluated in float64
    "geometry_f64": 1e-9,
    # SSRB of a static object vs its exact in-plane fan-beam row for |z - z_k| within the
    # slice window: the SSRB approximation itself, growing with |z - z_k|.
    # ||diff||_2 / ||exact||_2: measured <= 0.21 % at the window edge, 0.002 % at dz = 0
    "ssrb_vs_exact_rms": 3e-3,
    # max |diff| / max |exact|: worst at columns tangent to a sphere's silhouette, where the
    # chord changes fastest with z (measured <= 1.15 %)
    "ssrb_vs_exact_max": 1.5e-2,
}

# The tiny scene's detector width and collimation with finer rows (32 x 1.6 mm), so that the
# row interpolation error stays well below the SSRB approximation being measured.
SCANNER = ScannerConfig(n_cols=96, col_pitch_mm=7.5, n_rows=32, row_pitch_mm=1.6, views_per_rotation=90)


def _table(scanner: ScannerConfig, pitch: float, n: int, z_start: float = -40.0) -> ProjectionTable:
    nv = scanner.views_per_rotation
    k = np.arange(n, dtype=np.int64)
    z = z_start + pitch * scanner.collimation_iso_mm * k / nv
    zeros = np.zeros(n)
    return ProjectionTable(index=k, time_s=k * 0.3 / nv, angle_rad=2 * np.pi * k / nv, source_z_mm=z,
                           cardiac_phase=zeros, resp_amplitude=zeros, resp_direction=np.ones(n, np.int8),
                           state_cardiac=zeros, state_resp=zeros, views_per_rotation=nv)


# ---------------------------------------------------------------------------------------
# geometry
def test_v_of_u_is_where_the_axis_closest_point_projects():
    """v(u) = (u^2 + SDD^2)/(SID SDD) (z - z_k) from the conventions' projection formula."""
    sc = SCANNER
    beta, zk, z = 0.7, 3.0, 9.5
    u = detector_coords(sc.n_cols, sc.col_pitch_mm)
    src, det, e_u, _ = detector_frames(np.array([beta]), np.array([zk]), sc.sid_mm, sc.sdd_mm)
    pix = det[0] + u[:, None] * e_u[0]                      # in-plane detector points (C, 3)
    d = pix[:, :2] - src[0, :2]
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    t = -(src[0, :2] * d).sum(1)                             # closest approach to the axis
    p = src[0, :2] + t[:, None] * d
    U = sc.sid_mm - (p[:, 0] * np.cos(beta) + p[:, 1] * np.sin(beta))
    v_conv = sc.sdd_mm * (z - zk) / U
    np.testing.assert_allclose(rebin.ssrb_v_mm(u, z - zk, sc), v_conv, rtol=TOL["geometry_f64"])


def test_slice_window_puts_the_outermost_object_column_on_the_outer_row_centre():
    sc = SCANNER
    r = 150.0
    w = rebin.slice_window_mm(sc, r)
    u_lim = r * sc.sdd_mm / np.sqrt(sc.sid_mm ** 2 - r ** 2)
    # the ray of column u_lim passes exactly r from the axis
    assert sc.sid_mm * u_lim / np.hypot(u_lim, sc.sdd_mm) == pytest.approx(r, rel=TOL["geometry_f64"])
    v_outer = 0.5 * (sc.n_rows - 1) * sc.row_pitch_mm
    assert rebin.ssrb_v_mm(u_lim, w, sc) == pytest.approx(v_outer, rel=TOL["geometry_f64"])
    # every column inside u_lim stays inside at the window edge
    u = detector_coords(sc.n_cols, sc.col_pitch_mm)
    assert np.all(np.abs(rebin.ssrb_v_mm(u[np.abs(u) <= u_lim], w, sc)) <= v_outer * (1 + 1e-12))


def test_slice_window_shrinks_with_radius_and_saturates_at_the_detector_edge():
    sc = SCANNER
    assert sc.fov_radius_mm < 200.0
    ws = [rebin.slice_window_mm(sc, r) for r in (10.0, 50.0, 100.0, 150.0, 180.0)]
    assert all(a > b for a, b in zip(ws[:-1], ws[1:], strict=True))
    # beyond the scanner FOV every column sees the object: the outer column binds
    u_outer = 0.5 * (sc.n_cols - 1) * sc.col_pitch_mm
    v_outer = 0.5 * (sc.n_rows - 1) * sc.row_pitch_mm
    w_all = v_outer * sc.sid_mm * sc.sdd_mm / (u_outer ** 2 + sc.sdd_mm ** 2)
    assert rebin.slice_window_mm(sc, 2 * sc.sid_mm) == pytest.approx(w_all)
    assert rebin.slice_window_mm(sc, sc.fov_radius_mm * 1.01) == pytest.approx(w_all)
    assert rebin.slice_window_mm(sc, 300.0) == pytest.approx(w_all)
    # near the axis the window is (nearly) the central-column value: v_outer SID / SDD
    assert rebin.slice_window_mm(sc, 1e-3) == pytest.approx(v_outer * sc.sid_mm / sc.sdd_mm, rel=1e-9)


def test_slice_window_single_row_detector_is_zero():
    sc = ScannerConfig(n_cols=16, n_rows=1, views_per_rotation=8)
    assert rebin.slice_window_mm(sc, 100.0) == 0.0


@pytest.mark.parametrize("r", [0.0, -1.0, float("nan"), float("inf")])
def test_slice_window_rejects_bad_radius(r):
    with pytest.raises(ValueError, match="object_radius_mm"):
        rebin.slice_window_mm(SCANNER, r)


# ---------------------------------------------------------------------------------------
# candidates
def test_candidates_are_exactly_the_projections_inside_the_window():
    sc, r = SCANNER, 150.0
    table = _table(sc, 0.1, 4000)
    w = rebin.slice_window_mm(sc, r)
    z = 1.234
    cand = rebin.candidates(table, z, sc, r)
    inside = np.abs(z - table.source_z_mm) <= w
    np.testing.assert_array_equal(cand, table.index[inside])
    assert np.all(np.diff(cand) > 0)
    # about 2 w / h candidates per view (one per turn covering the slice)
    per_view = np.bincount(cand % sc.views_per_rotation, minlength=sc.views_per_rotation)
    expected = 2 * w / (0.1 * sc.collimation_iso_mm)
    assert np.all(np.abs(per_view - expected) <= 1)


def test_candidate_groups_match_candidates_per_slice_and_view():
    sc, r = SCANNER, 150.0
    table = _table(sc, 0.25, 1500)
    slices = np.array([-10.0, 0.0, 3.3])
    groups = rebin.candidate_groups(table, slices, sc, r)
    nv = sc.views_per_rotation
    assert groups.n_groups == slices.size * nv
    for s, z in enumerate(slices):
        cand = rebin.candidates(table, z, sc, r)
        for j in (0, 1, nv - 1):
            g = s * nv + j
            got = groups.projection[groups.offsets[g]:groups.offsets[g + 1]]
            np.testing.assert_array_equal(got, cand[cand % nv == j])
            np.testing.assert_allclose(groups.dz_mm[groups.offsets[g]:groups.offsets[g + 1]],
                                       z - table.source_z_mm[got])
    assert np.all(groups.group_slice[: nv] == 0) and groups.group_view[nv + 5] == 5


def test_candidate_groups_work_on_a_shuffled_sub_table():
    sc, r = SCANNER, 150.0
    full = _table(sc, 0.25, 1500)
    rng = np.random.default_rng(3)
    sub = full.take(rng.permutation(len(full))[:900])
    groups = rebin.candidate_groups(sub, [0.0], sc, r)
    np.testing.assert_array_equal(sub.index[groups.row], groups.projection)
    np.testing.assert_array_equal(np.sort(groups.projection), rebin.candidates(sub, 0.0, sc, r))


def test_candidate_groups_report_empty_groups_when_the_pitch_is_too_high():
    sc = SCANNER
    table = _table(sc, 1.9, 400)
    groups = rebin.candidate_groups(table, [0.0], sc, 250.0)
    assert groups.empty.any() and not groups.empty.all()
    assert groups.counts.sum() == groups.row.size


# ---------------------------------------------------------------------------------------
# the ssrb_rows kernel against its float64 reference
def _rel(a, b):
    return np.abs(np.asarray(a, np.float64) - b).max() / max(np.abs(b).max(), 1e-30)


@pytest.mark.parametrize("n_rows,n_cols", [(32, 96), (7, 33), (2, 65), (1, 5)])
def test_ssrb_kernel_matches_reference_random(n_rows, n_cols):
    sc = ScannerConfig(n_cols=n_cols, col_pitch_mm=7.5, n_rows=n_rows, row_pitch_mm=1.6, views_per_rotation=90)
    rng = np.random.default_rng(n_rows * 100 + n_cols)
    m, p = 5, 37
    proj = rng.random((m, n_rows, n_cols)).astype(np.float32)
    slot = rng.integers(0, m, p).astype(np.int32)
    w = max(rebin.slice_window_mm(sc, 200.0), 1.0)
    dz = rng.uniform(-1.5 * w, 1.5 * w, p)  # includes clamped pairs beyond the window
    got = rebin.ssrb_rows(proj, slot, dz, sc)
    ref = rebin.ssrb_rows_reference(proj, slot, dz, sc)
    assert got.dtype == np.float32 and got.shape == (p, n_cols)
    assert _rel(got, ref) < TOL["ssrb_kernel_f32"]


def test_ssrb_kernel_edge_cases():
    sc = SCANNER
    rng = np.random.default_rng(0)
    proj = rng.random((3, sc.n_rows, sc.n_cols)).astype(np.float32)
    v_outer = 0.5 * (sc.n_rows - 1) * sc.row_pitch_mm
    dz_outer_centre = v_outer * sc.sid_mm / sc.sdd_mm       # centre column hits the outer row centre
    dz = np.array([0.0, dz_outer_centre, -dz_outer_centre, 1e4, -1e4, 1e-7])
    slot = np.array([0, 1, 2, 0, 1, 2], np.int32)
    got = rebin.ssrb_rows(proj, slot, dz, sc)
    ref = rebin.ssrb_rows_reference(proj, slot, dz, sc)
    assert _rel(got, ref) < TOL["ssrb_kernel_f32"]
    # dz = 0: the two middle rows (even n_rows) averaged, no path scaling
    p0 = proj[0].astype(np.float64)
    mid = 0.5 * (p0[sc.n_rows // 2 - 1] + p0[sc.n_rows // 2])
    np.testing.assert_allclose(ref[0], mid, rtol=1e-12)
    # far beyond the window: clamped to the outer rows (never NaN, never out of bounds)
    u = detector_coords(sc.n_cols, sc.col_pitch_mm)
    q = u ** 2 + sc.sdd_mm ** 2
    np.testing.assert_allclose(ref[3], proj[0, -1] * np.sqrt(q / (q + v_outer ** 2)), rtol=1e-6)
    np.testing.assert_allclose(ref[4], proj[1, 0] * np.sqrt(q / (q + v_outer ** 2)), rtol=1e-6)
    assert np.all(np.isfinite(got))


def test_ssrb_rows_empty_and_bad_inputs():
    sc = SCANNER
    proj = np.zeros((2, sc.n_rows, sc.n_cols), np.float32)
    assert rebin.ssrb_rows(proj, np.zeros(0, np.int32), np.zeros(0), sc).shape == (0, sc.n_cols)
    with pytest.raises(ValueError, match="shape"):
        rebin.ssrb_rows(proj[:, :-1], [0], [0.0], sc)
    with pytest.raises(ValueError, match="pair_slot"):
        rebin.ssrb_rows(proj, [2], [0.0], sc)
    with pytest.raises(TypeError, match="pair_slot"):
        rebin.ssrb_rows(proj, [0.5], [0.0], sc)
    with pytest.raises(ValueError, match="finite"):
        rebin.ssrb_rows(proj, [0], [np.nan], sc)
    with pytest.raises(TypeError, match="projections"):
        rebin.ssrb_rows(proj.astype(complex), [0], [0.0], sc)


# ---------------------------------------------------------------------------------------
# physics: SSRB of a static object against its exact in-plane fan-beam rows
# additive ellipsoids (centre mm, semi-axes mm, mu 1/mm): an off-centre body and a sphere
# whose edge the slice cuts, so the object varies in z across the oblique rays
ELLIPSOIDS = [((30.0, -20.0, 0.0), (120.0, 90.0, 150.0), 0.02),
              ((-60.0, 40.0, 10.0), (40.0, 40.0, 40.0), 0.01)]
OBJECT_RADIUS = 160.0


def _line_integrals(src, pix):
    """Exact float64 line integrals of ELLIPSOIDS from ``src`` (..., 3) to ``pix`` (..., 3).

    Chord of the ray x = s + t d (|d| = 1) through an axis-aligned ellipsoid: scaled to the
    unit sphere, A t^2 + 2 B t + C = 0 with A = |d'|^2, B = s'.d', C = |s'|^2 - 1; the chord
    length is 2 sqrt(B^2 - A C) / A where the discriminant is positive.
    """
    d = pix - src
    d = d / np.linalg.norm(d, axis=-1, keepdims=True)
    out = 0.0
    for centre, axes, mu in ELLIPSOIDS:
        s = (src - np.asarray(centre)) / np.asarray(axes)
        dd = d / np.asarray(axes)
        A = (dd * dd).sum(-1)
        B = (s * dd).sum(-1)
        C = (s * s).sum(-1) - 1.0
        out = out + mu * 2.0 * np.sqrt(np.maximum(B * B - A * C, 0.0)) / A
    return out


def _cone_projection(sc, beta, zk):
    """(n_rows, n_cols) cone-beam line integrals at gantry angle beta, source z zk."""
    src, det, e_u, e_v = detector_frames(np.array([beta]), np.array([zk]), sc.sid_mm, sc.sdd_mm)
    u = detector_coords(sc.n_cols, sc.col_pitch_mm)
    v = detector_coords(sc.n_rows, sc.row_pitch_mm)
    pix = det[0] + u[None, :, None] * e_u[0] + v[:, None, None] * e_v[0]
    return _line_integrals(src[0], pix)


def _inplane_row(sc, beta, z):
    """(n_cols,) exact fan-beam line integrals of the slice plane z at angle beta."""
    src, det, e_u, _ = detector_frames(np.array([beta]), np.array([z]), sc.sid_mm, sc.sdd_mm)
    u = detector_coords(sc.n_cols, sc.col_pitch_mm)
    return _line_integrals(src[0], det[0] + u[:, None] * e_u[0])


def test_ssrb_of_a_static_object_matches_its_inplane_fan_beam_rows():
    sc = SCANNER
    w = rebin.slice_window_mm(sc, OBJECT_RADIUS)
    z = 5.0
    fractions = np.array([-1.0, -0.6, -0.2, 0.0, 0.3, 0.7, 1.0])
    for beta in (0.3, 2.0, 4.4):
        exact = _inplane_row(sc, beta, z)
        dz = fractions * w
        proj = np.stack([_cone_projection(sc, beta, z - d) for d in dz]).astype(np.float32)
        rows = rebin.ssrb_rows(proj, np.arange(dz.size, dtype=np.int32), dz, sc)
        for i in range(dz.size):
            rms = np.linalg.norm(rows[i] - exact) / np.linalg.norm(exact)
            assert rms < TOL["ssrb_vs_exact_rms"], (beta, dz[i])
            assert _rel(rows[i], exact) < TOL["ssrb_vs_exact_max"], (beta, dz[i])
        # and the rebinning matters: the uncorrected central row at the window edge is worse
        raw = proj[-1, sc.n_rows // 2].astype(np.float64)
        assert np.linalg.norm(raw - exact) / np.linalg.norm(exact) > 3 * TOL["ssrb_vs_exact_rms"]


@pytest.mark.parametrize("dz_lo,dz_hi", [(-1.0, 1.0), (2.0, 4.5), (-9.0, -6.0), (-200.0, -150.0)])
def test_a_block_of_the_rows_it_reads_gives_the_same_rows(dz_lo, dz_hi):
    """The reconstruction reads only rows ``ssrb_row_range`` of a chunk: the kernel on that
    block (every other row absent, here: NaN in the whole array) equals the kernel on whole
    projections, bit for bit, and the float64 reference agrees."""
    sc = SCANNER
    rng = np.random.default_rng(21)
    proj = rng.random((4, sc.n_rows, sc.n_cols)).astype(np.float32)
    slot = rng.integers(0, 4, 50).astype(np.int32)
    dz = rng.uniform(dz_lo, dz_hi, 50)
    lo, hi = rebin.ssrb_row_range(dz, sc)
    assert 0 <= lo < hi <= sc.n_rows
    poisoned = np.full_like(proj, np.nan)
    poisoned[:, lo:hi] = proj[:, lo:hi]
    block = np.ascontiguousarray(poisoned[:, lo:hi])
    whole = rebin.ssrb_rows(proj, slot, dz, sc)
    got = rebin.ssrb_rows(block, slot, dz, sc, first_row=lo)
    np.testing.assert_array_equal(got, whole)
    # the rows outside the range are really never read
    assert np.all(np.isfinite(rebin.ssrb_rows_reference(poisoned, slot, dz, sc)))
    np.testing.assert_allclose(rebin.ssrb_rows_reference(block, slot, dz, sc, first_row=lo),
                               rebin.ssrb_rows_reference(proj, slot, dz, sc), rtol=0, atol=0)
    if lo > 0 or hi < sc.n_rows:  # a block that misses a row the pairs read is refused
        short = block[:, 1:] if hi - lo > 1 else block
        with pytest.raises(ValueError, match="read detector rows"):
            rebin.ssrb_rows(short, slot, dz, sc, first_row=lo + 1)
