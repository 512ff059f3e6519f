"""Fan-beam FBP: kernels against float64 NumPy references, and physics on analytic disks.

References (Kak & Slaney 1988, ch. 3): the discrete band-limited ramp kernel (eq. 61),
convolved directly in float64; the weighted fan-beam backprojection (sec. 3.4.2) written
out in float64 NumPy, with the kernel's interpolation and edge rule. Analytic sinograms of
disks use the ray geometry of ``clrecon.core.conventions.detector_frames``, so orientation and
sign conventions are checked against the one place they are defined.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from fan_disks import disk_sinogram, radius_map, rel_max_err

from clrecon.bench.fbp import bench_backprojection
from clrecon.bench.reference_kernels import backproject_single
from clrecon.config.scene import load_scene
from clrecon.core.conventions import MU_WATER_PER_MM, mu_to_hu
from clrecon.reconstruction.fbp import (
    WINDOWS,
    FanBeamGeometry,
    backproject,
    cosine_weights,
    fbp,
    fbp_hu,
    filter_sinograms,
    interleave_batch,
    padded_length,
    ramp_filter_response,
)

# One table for every tolerance in this file: (quantity, why this size).
TOL = {
    # float32 kernel vs float64 reference, max |cl - ref| / max |ref|: float32 column
    # positions (ulp(C) ~ 1e-5 cells) times O(1) jumps of random data, summed over views.
    "backproject_f32": 2e-5,
    # batched vs one-per-work-item kernel: same float32 arithmetic, different order/FMAs.
    "batched_vs_single": 1e-5,
    # complex64 FFT filtering vs float64 direct convolution, relative to max |ref|.
    "filter_f32": 2e-6,
    # water cylinder, central 80 % of its radius: |mean| and std in HU (noise-free data).
    "water_mean_hu": 1.0,
    "water_std_hu": 0.5,
    # air around the cylinder (inside the FOV, > 10 mm from the edge): |mean + 1000| in HU.
    "air_mean_hu": 5.0,
    # centroid of an off-centre dense disk vs its true centre, in pixels.
    "centroid_px": 0.1,
    # noise std must drop by at least this factor from one window to the next smoother one.
    "window_noise_ratio": 0.95,
    # ramp response at Nyquist vs the ideal ramp 1/(2 tau) (times 1/2 for g = h/2).
    "ramp_nyquist": 0.02,
}

# Small geometry for the kernel checks: the FOV circle (radius ~20 mm) cuts the image
# (half-width up to 24.75 mm), so pixels near and outside the FOV edge are exercised;
# sizes are neither multiples of the local size (8) nor of the view chunk (16).
SMALL = FanBeamGeometry(sid_mm=100.0, sdd_mm=200.0, n_cols=41, col_pitch_mm=2.0, n_views=90,
                        nx=33, ny=28, voxel_mm=1.5, beta0_rad=0.3)

# Realistic scanner (Table 1 distances), coarser detector and grid so the test is fast.
CT = FanBeamGeometry(sid_mm=595.0, sdd_mm=1085.6, n_cols=400, col_pitch_mm=1.6, n_views=360,
                     nx=128, ny=128, voxel_mm=2.0)


# ---------------------------------------------------------------------------------------
# float64 references
def reference_backproject(filtered: np.ndarray, geom: FanBeamGeometry) -> np.ndarray:
    """mu(x, y) = dbeta sum_j (R/U_j)^2 Q_j(c_j), c clamped to [0, C-1]; 0 outside the FOV."""
    q = np.asarray(filtered, np.float64)
    x, y = geom.pixel_coords_mm()
    X, Y = np.meshgrid(x, y)  # (ny, nx)
    out = np.zeros((q.shape[0], geom.ny, geom.nx))
    c_max = geom.n_cols - 1
    for j, b in enumerate(geom.view_angles_rad()):
        U = geom.sid_mm - (X * np.cos(b) + Y * np.sin(b))
        u = geom.sdd_mm * (-X * np.sin(b) + Y * np.cos(b)) / U
        c = np.clip(u / geom.col_pitch_mm + c_max / 2.0, 0.0, c_max)
        i0 = np.minimum(np.floor(c).astype(int), c_max - 1)
        t = c - i0
        val = (1.0 - t) * q[:, j, i0] + t * q[:, j, i0 + 1]
        out += (geom.sid_mm / U) ** 2 * val
    out *= geom.delta_beta_rad
    out[:, ~geom.fov_mask()] = 0.0
    return out


def reference_filter(sino: np.ndarray, geom: FanBeamGeometry) -> np.ndarray:
    """Ram-Lak by direct float64 convolution with h(n tau) of K&S eq. (61), times tau / 2."""
    tau = geom.iso_col_pitch_mm
    n = np.arange(-(geom.n_cols - 1), geom.n_cols)
    h = np.zeros(n.shape)
    h[n == 0] = 1.0 / (4 * tau * tau)
    odd = n % 2 != 0
    h[odd] = -1.0 / (np.pi * n[odd] * tau) ** 2
    rows = np.asarray(sino, np.float64).reshape(-1, geom.n_cols) * cosine_weights(geom)
    out = np.array([np.convolve(r, h, mode="full")[geom.n_cols - 1:2 * geom.n_cols - 1] for r in rows])
    return (0.5 * tau * out).reshape(np.shape(sino))


# ---------------------------------------------------------------------------------------
# geometry value object
def test_geometry_repr_roundtrip_and_fov():
    assert eval(repr(SMALL), {"FanBeamGeometry": FanBeamGeometry}) == SMALL
    # FOV formula identical to ScannerConfig's
    scene = load_scene("tiny")
    g = FanBeamGeometry.from_scene(scene)
    assert g.fov_radius_mm == pytest.approx(scene.scanner.fov_radius_mm)
    assert (g.n_cols, g.n_views, g.nx, g.voxel_mm) == (scene.scanner.n_cols, scene.scanner.views_per_rotation,
                                                        scene.recon.nx, scene.recon.voxel_mm)
    assert g.beta0_rad == pytest.approx(math.radians(scene.scan.start_angle_deg))


@pytest.mark.parametrize("field, bad", [
    ("sid_mm", 0.0), ("sdd_mm", -1.0), ("col_pitch_mm", float("nan")), ("voxel_mm", float("inf")),
    ("n_cols", 1), ("n_views", 0), ("nx", 2.5), ("ny", True), ("beta0_rad", float("nan")),
    ("sdd_mm", 50.0),  # not beyond the isocentre
])
def test_geometry_rejects_invalid(field, bad):
    with pytest.raises(ValueError, match=field):
        dataclasses.replace(SMALL, **{field: bad})


def test_input_checks():
    with pytest.raises(ValueError, match="shape"):
        filter_sinograms(np.zeros((SMALL.n_views, SMALL.n_cols)), SMALL)  # missing batch axis
    with pytest.raises(ValueError, match="shape"):
        backproject(np.zeros((1, SMALL.n_views, SMALL.n_cols + 1)), SMALL)
    with pytest.raises(TypeError):
        fbp(np.zeros((1, SMALL.n_views, SMALL.n_cols), complex), SMALL)
    with pytest.raises(ValueError, match="window"):
        filter_sinograms(np.zeros((1, SMALL.n_views, SMALL.n_cols)), SMALL, window="cosine")
    bad = np.zeros((1, SMALL.n_views, SMALL.n_cols))
    bad[0, 3, 4] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        filter_sinograms(bad, SMALL)


# ---------------------------------------------------------------------------------------
# filter
def test_filter_matches_direct_convolution():
    """Odd number of rows (the complex-pair packing's lone last row) and tiny chunks."""
    rng = np.random.default_rng(1)
    sino = rng.standard_normal((3, SMALL.n_views, SMALL.n_cols))  # 270 rows
    ref = reference_filter(sino, SMALL)
    for chunk in (2048, 6, 7):
        got = filter_sinograms(sino[:, :89], dataclasses.replace(SMALL, n_views=89), rows_per_chunk=chunk)
        assert got.dtype == np.float32 and got.shape == (3, 89, SMALL.n_cols)
        assert rel_max_err(got, ref[:, :89]) < TOL["filter_f32"]
    # edge cases: an impulse in the first and in the last column, a constant row
    edge = np.zeros((1, SMALL.n_views, SMALL.n_cols))
    edge[0, 0, 0] = 1.0
    edge[0, 1, -1] = 1.0
    edge[0, 2, :] = 1.0
    assert rel_max_err(filter_sinograms(edge, SMALL), reference_filter(edge, SMALL)) < TOL["filter_f32"]


def test_ramp_response_windows():
    n = padded_length(CT.n_cols)
    assert n >= 2 * CT.n_cols - 1
    f = np.fft.fftfreq(n)
    nyq = np.argmin(np.abs(np.abs(f) - 0.5))
    tau = CT.iso_col_pitch_mm
    resp = {w: ramp_filter_response(CT, w, n) for w in WINDOWS}
    # Ram-Lak follows the ramp |f| / tau up to Nyquist, times 1/2 (g = h/2) ...
    assert resp["ram-lak"][nyq] == pytest.approx(0.5 / (2 * tau), rel=TOL["ramp_nyquist"])
    # ... and keeps a small positive DC term from the spatially sampled kernel (no offset)
    assert 0 < resp["ram-lak"][0] < 1e-3 * resp["ram-lak"][nyq]
    assert resp["shepp-logan"][nyq] == pytest.approx(resp["ram-lak"][nyq] * 2 / np.pi, rel=1e-6)
    assert abs(resp["hann"][nyq]) < 1e-9 * resp["ram-lak"][nyq]
    for w in WINDOWS:  # real and even kernel -> symmetric response
        assert np.allclose(resp[w][1:], resp[w][1:][::-1])


# ---------------------------------------------------------------------------------------
# backprojection kernels vs the float64 reference
@pytest.mark.parametrize("batch", [1, 15, 16, 17])
def test_backproject_matches_reference(batch):
    rng = np.random.default_rng(batch)
    q = rng.standard_normal((batch, SMALL.n_views, SMALL.n_cols)).astype(np.float32)
    q[0, :, 0] += 5.0  # edge columns: the pad/clamp path
    q[-1, :, -1] -= 5.0
    ref = reference_backproject(q, SMALL)
    got = backproject(q, SMALL)
    assert got.shape == (batch, SMALL.ny, SMALL.nx) and got.dtype == np.float32
    assert rel_max_err(got, ref) < TOL["backproject_f32"]
    for b in range(batch):  # each image on its own: a lane mix-up cannot hide in the max
        assert rel_max_err(got[b], ref[b]) < TOL["backproject_f32"]
    assert not np.any(got[:, ~SMALL.fov_mask()])  # outside the FOV: exactly 0
    single = backproject_single(q, SMALL)
    assert rel_max_err(got, single.astype(np.float64)) < TOL["batched_vs_single"]


@pytest.mark.parametrize("geom", [
    dataclasses.replace(SMALL, nx=34, ny=27, n_cols=40, n_views=33),  # even columns, odd views
    dataclasses.replace(SMALL, nx=3, ny=5, n_views=16, voxel_mm=7.0),  # smaller than a work-group
    dataclasses.replace(SMALL, nx=20, ny=20, voxel_mm=2.5, beta0_rad=-2.0),  # FOV inside the image
], ids=["even-cols", "tiny-image", "fov-inside"])
def test_backproject_sizes_and_edge_values(geom):
    fov = geom.fov_mask()
    x, y = geom.pixel_coords_mm()
    r2 = x[None, :] ** 2 + y[:, None] ** 2
    # precondition: no pixel centre so close to the FOV circle that float32 and float64
    # could classify it differently
    assert np.min(np.abs(r2 - geom.fov_radius_mm ** 2)) > 1e-4 * geom.fov_radius_mm ** 2
    rng = np.random.default_rng(7)
    q = np.stack([
        rng.standard_normal((geom.n_views, geom.n_cols)),
        np.ones((geom.n_views, geom.n_cols)),  # constant: the distance weights alone
        np.zeros((geom.n_views, geom.n_cols)),
        np.where(np.arange(geom.n_cols) == geom.n_cols - 1, 1e3, 0.0) * np.ones((geom.n_views, 1)),
    ]).astype(np.float32)
    ref = reference_backproject(q, geom)
    got = backproject(q, geom)
    for b in (0, 1, 3):
        assert rel_max_err(got[b], ref[b]) < TOL["backproject_f32"]
    assert not np.any(got[2])
    assert not np.any(got[:, ~fov])


def test_interleave_layout():
    q = np.arange(17 * 2 * 3, dtype=np.float32).reshape(17, 2, 3)
    il = interleave_batch(q)
    assert il.shape == (2, 2, 5, 16)
    assert il[1, 1, 2, 0] == q[16, 1, 1] and not il[1, :, :, 1:].any()
    assert il[0, 0, 0, 5] == q[5, 0, 0] and il[0, 0, 4, 5] == q[5, 0, 2]  # edge replicas


# ---------------------------------------------------------------------------------------
# physics: calibration, orientation, windows
def test_water_cylinder_is_zero_hu():
    radius = 100.0
    sino = disk_sinogram(CT, (0.0, 0.0), radius, MU_WATER_PER_MM)[None]
    r = radius_map(CT)
    centre, air = r < 0.8 * radius, (r > radius + 10) & CT.fov_mask()
    for window in WINDOWS:
        hu = fbp_hu(sino, CT, window)[0]
        mean, std = float(hu[centre].mean()), float(hu[centre].std())
        # measured (ram-lak): mean -0.11 HU, std 0.05 HU
        assert abs(mean) < TOL["water_mean_hu"], (window, mean)
        assert std < TOL["water_std_hu"], (window, std)
        assert abs(hu[air].mean() + 1000.0) < TOL["air_mean_hu"], window
        assert np.all(hu[~CT.fov_mask()] == -1000.0)


@pytest.mark.parametrize("beta0", [0.0, 0.7])
def test_off_centre_disk_position(beta0):
    """A dense disk at (40, -60) mm reconstructs there: x, y, signs and beta0 all matter."""
    geom = dataclasses.replace(CT, beta0_rad=beta0)
    centre = (40.0, -60.0)
    img = fbp(disk_sinogram(geom, centre, 10.0, 0.05)[None], geom)[0]
    w = np.where(img > 0.5 * img.max(), img, 0.0)
    x, y = geom.pixel_coords_mm()
    cx = float((w * x[None, :]).sum() / w.sum())
    cy = float((w * y[:, None]).sum() / w.sum())
    assert abs(cx - centre[0]) < TOL["centroid_px"] * geom.voxel_mm
    assert abs(cy - centre[1]) < TOL["centroid_px"] * geom.voxel_mm
    inside = radius_map(geom, centre) < 7.0
    assert float(img[inside].mean()) == pytest.approx(0.05, rel=0.01)


def test_windows_reduce_noise():
    rng = np.random.default_rng(3)
    clean = disk_sinogram(CT, (0.0, 0.0), 100.0, MU_WATER_PER_MM)
    sino = (clean + rng.normal(0.0, 0.01, size=clean.shape))[None]
    centre = radius_map(CT) < 80.0
    std = {w: float(fbp_hu(sino, CT, w)[0][centre].std()) for w in WINDOWS}
    assert std["shepp-logan"] < TOL["window_noise_ratio"] * std["ram-lak"]
    assert std["hann"] < TOL["window_noise_ratio"] * std["shepp-logan"]


def test_batch_lanes_are_independent():
    """Scaled copies in one batch of 17 come back scaled: no cross-talk between lanes."""
    base = disk_sinogram(CT, (20.0, 30.0), 40.0, MU_WATER_PER_MM)
    scales = np.linspace(0.5, 2.0, 17)
    out = fbp(scales[:, None, None] * base[None], CT)
    one = out[0] / scales[0]
    for k, s in enumerate(scales):
        assert rel_max_err(out[k] / s, one.astype(np.float64)) < TOL["batched_vs_single"]


def test_fbp_hu_of_empty_scan_is_air():
    hu = fbp_hu(np.zeros((2, SMALL.n_views, SMALL.n_cols)), SMALL)
    assert hu.shape == (2, SMALL.ny, SMALL.nx) and np.all(hu == -1000.0)
    assert np.allclose(mu_to_hu(0.0), -1000.0)


def test_bench_smoke():
    """The benchmark runs both kernels on the same data and they agree (no timing asserted)."""
    res = bench_backprojection(nx=20, n_views=24, n_cols=32, batch=17, repeats=1)
    assert res["updates"] == 20 * 20 * 24 * 17
    assert res["batched_gups"] > 0 and res["single_gups"] > 0
    assert 0.5 < res["fov_fraction"] < 1.0
    assert res["max_rel_diff"] < TOL["batched_vs_single"]


def test_a_rows_filtered_value_does_not_depend_on_its_batch():
    """Determinism across slab sizes and workers: filtering rows alone, in any batch and at any
    offset, gives the same bits (a shared complex FFT of two rows did not)."""
    from clrecon.config.scene import load_scene
    from clrecon.reconstruction.fbp import FanBeamGeometry, filter_rows

    geom = FanBeamGeometry.from_scene(load_scene("demo"))
    rows = np.random.default_rng(4).random((37, geom.n_cols)).astype(np.float32)
    whole = filter_rows(rows, geom)
    for a, b in [(0, 1), (1, 2), (3, 20), (5, 37), (36, 37)]:
        np.testing.assert_array_equal(filter_rows(rows[a:b], geom), whole[a:b])
    np.testing.assert_array_equal(filter_rows(rows, geom, rows_per_chunk=5), whole)


@pytest.mark.parametrize("batch", [1, 17, 45])
def test_fbp_interleaves_on_the_device_bit_for_bit(batch):
    """fbp() puts the filtered rows into the backprojector's layout on the device (the interpolation
    kernel, one slot of weight 1): the images are backproject(filter_sinograms(...)) of the host's
    interleaving copy, bit for bit, over several launches (45 = 2 launches of 32, the last one
    partial)."""
    rng = np.random.default_rng(batch)
    sino = rng.random((batch, SMALL.n_views, SMALL.n_cols)).astype(np.float32)
    filtered = filter_sinograms(sino, SMALL)
    ref = np.concatenate([backproject(filtered[b0:b0 + 32], SMALL) for b0 in range(0, batch, 32)])
    got = fbp(sino, SMALL)
    np.testing.assert_array_equal(got.view(np.uint32), ref.view(np.uint32))


def test_signed_zeros_in_a_sinogram_give_the_same_image_bits():
    """The device interleave turns a filtered -0 into +0 (0 + 1 * -0); the backprojection's sums
    start at +0, so either zero adds the same bits: images of a sinogram with -0 entries and of
    the same with +0 there are identical."""
    rng = np.random.default_rng(9)
    q = rng.standard_normal((17, SMALL.n_views, SMALL.n_cols)).astype(np.float32)
    zeros = rng.random(q.shape) < 0.3
    q[zeros] = -0.0
    q[0] = -0.0  # a whole sinogram of -0: its image is exactly +0 either way
    plus = q.copy()
    plus[plus == 0] = 0.0
    assert np.signbit(q[zeros]).all() and not np.signbit(plus[zeros]).any()
    np.testing.assert_array_equal(backproject(q, SMALL).view(np.uint32), backproject(plus, SMALL).view(np.uint32))
