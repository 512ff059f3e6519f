"""Lucas-Kanade on OpenCL (clrecon.reconstruction.motion.lk, kernels/lk.cl) against its references
and against scikit-image's ``optical_flow_ilk``, which it ports.

Each kernel against its float64 NumPy reference on random and edge-case inputs (shapes not
multiples of any work-group size, axes of two voxels, windows longer than the axis, flows that
reach past the grid, singular and pivoting 3 x 3 systems); the host's parts (images, pyramid,
resize tables) and the kernels' NumPy-order parts against NumPy / scikit-image bit for bit; the
whole registration against scikit-image on a textured band-limited pair with a known shift and
one with a smooth deformation; determinism, the selection through ``[recon.mc] registration``,
its memory against ``lk.BYTES_PER_VOXEL`` and bad inputs.
"""

from __future__ import annotations

import os

import numpy as np
import pytest
import scipy.ndimage

from clrecon.core.runtime import get_runtime
from clrecon.reconstruction.motion import lk, registration

# One table for every tolerance in this file: (quantity, why this size).
TOL = {
    # float32 kernel vs float64 reference, max |cl - ref| / max(1, max |ref|): float32 arithmetic on
    # O(1) data, a handful of operations per output (ulp 6e-8)
    "f32": 1e-6,
    # the float32 (no float64 on the device) box mean vs its reference (float32 input), per output relative
    # to |mean| (+ 1e-10 max |src|): the compensated sum is the exact sum to ~ulp**2 of the line's values
    # (no drift along the line), then one rounding and one division: 2 ulp (1.2e-7 each)
    "box": 2.5e-7,
    # the 3 x 3 solve vs float64, relative to max |v| and the system's condition number: LU in float32
    # moves the solution by ~cond * ulp (measured <= 1.5e-7 per unit of cond)
    "solve_per_cond": 1e-6,
    # whole registration vs scikit-image (mm; fields of 1-4 mm): max / RMS measured 1.7e-6 / 2.6e-7 (shift,
    # 16 x 64 x 64 at 3 x 3 x 4 mm), 5.4e-7 / 8.1e-8 (shift, 36 x 40 x 44 at 1 mm), 4.8e-7 / 6.6e-8 (deform,
    # |u| <= 2.0 mm) on Intel's CPU runtime (float64 box sums): the float32 warp and solve differ from
    # SciPy's / LAPACK's in the last bits and 10 warps per level carry them. About 10x the largest measured
    "vs_skimage_max_mm": 2e-5,
    "vs_skimage_rms_mm": 3e-6,
    # the known shift recovered (voxels, median over the inner part): LK's own error on this texture
    "shift_vox": 0.05,
}
#: The OpenCL driver's own allocations in a process's first registration of a size, beside the
#: modelled bytes per voxel: up to 2.9 MB above the 16 volumes on Intel's CPU runtime (16 x 128 x 128; none later).
DRIVER_BYTES = 8 << 20
RNG = np.random.default_rng(41)
SHAPES = [(5, 7, 9), (2, 3, 2), (2, 2, 17)]


def _close(got, ref, tol=TOL["f32"]):
    scale = max(1.0, float(np.abs(ref).max()))
    assert np.abs(got - ref).max() <= tol * scale, (np.abs(got - ref).max(), scale)


def _texture(shape, seed=0):
    rng = np.random.default_rng(seed)
    f = scipy.ndimage.gaussian_filter(rng.normal(0, 1, shape), 2.0, mode="wrap")
    return (f / f.std() * 300.0 - 200.0).astype(np.float32)


def _shift_pair(shape, shift=(0.6, -1.3, 0.8)):
    fixed = _texture(shape)
    return fixed, scipy.ndimage.shift(fixed, shift, order=3, mode="grid-wrap").astype(np.float32), shift


def _deform_pair(shape, amp=2.0):
    fixed = _texture(shape, seed=1)
    k, j, i = np.meshgrid(*(np.arange(n, dtype=np.float64) for n in shape), indexing="ij", sparse=True)
    d = [amp * np.sin(2 * np.pi * (i / shape[2] + j / shape[1] + c / 3.0)) * np.cos(np.pi * k / shape[0])
         for c in range(3)]
    moving = scipy.ndimage.map_coordinates(fixed, [k - d[0], j - d[1], i - d[2]], order=1, mode="nearest")
    return fixed, moving.astype(np.float32)


# -- kernels against their references --------------------------------------------------------------
@pytest.mark.parametrize("shape", SHAPES)
def test_warp_and_term_kernels_match_the_references(shape):
    src, ref = RNG.uniform(0, 1, shape), RNG.uniform(0, 1, shape)
    v = RNG.normal(0, 3.0, (3,) + shape)          # reaches past every edge: clamped sampling
    v[:, 0, 0, 0] = 0.0                            # an exact voxel centre
    _close(lk.warp_cl(src, v), lk.warp_reference(src, v))
    for q in range(9):
        _close(lk.term_cl(src, ref, v, q), lk.term_reference(src, ref, v, q))


def test_term_kernel_is_numpys_float32_arithmetic_bit_for_bit():
    """The gradient (np.gradient), the error image and the products in NumPy's order, no fma."""
    shape = (4, 6, 5)
    w, ref = (RNG.uniform(-0.6, 0.4, shape).astype(np.float32) for _ in range(2))
    v = RNG.normal(0, 2, (3,) + shape).astype(np.float32)
    g = np.stack(np.gradient(w), axis=0)
    e = (g * v).sum(axis=0) + ref - w
    want = [g[a] * g[b] for a, b in lk.A_PAIRS] + [g[a] * e for a in range(3)]
    for q in range(9):
        assert np.array_equal(lk.term_cl(w, ref, v, q), want[q]), q


@pytest.mark.parametrize("shape", [(5, 7, 9), (2, 3, 2), (1, 4, 30), (3, 40, 6)])
@pytest.mark.parametrize("radius", [1, 7, 20])
def test_box_kernel_matches_the_reference_and_scipy(shape, radius):
    """Windows shorter and longer than the axis (mirrored repeatedly), an axis of one voxel; values
    over six decades: the float64 sum is SciPy's uniform_filter1d bit for bit, the float32 one within
    2 ulp of the mean."""
    src = RNG.normal(0, 1, shape) * 10.0 ** RNG.uniform(-3, 3, shape)
    src[0, 0, :] += 1e3                            # a large value beside small ones: no drift along the line
    src = src.astype(np.float32)
    double = lk.has_fp64(get_runtime())
    for axis in range(3):
        ref = lk.box_reference(src, axis, radius)
        scipys = scipy.ndimage.uniform_filter1d(src, 2 * radius + 1, axis=axis, mode="mirror")
        assert np.abs(ref - scipys).max() <= 1e-6 * np.abs(src).max()
        if double:
            assert np.array_equal(lk.box_cl(src, axis, radius, double=True), scipys), axis
        err = np.abs(lk.box_cl(src, axis, radius, double=False) - ref)
        assert np.all(err <= TOL["box"] * np.abs(ref) + 1e-10 * np.abs(src).max()), (axis, (err / np.abs(ref)).max())


def _systems(n, cond_max=1e3):
    """n symmetric positive definite 3 x 3 systems as lk_term's (9, n) terms, condition <= cond_max."""
    q, _ = np.linalg.qr(RNG.normal(size=(n, 3, 3)))
    ev = np.exp(RNG.uniform(0, np.log(cond_max), (n, 3))) * 10.0 ** RNG.uniform(-4, 0, (n, 1))
    a = np.einsum("nij,nj,nkj->nik", q, ev, q)
    b = RNG.normal(size=(n, 3)) * 10.0 ** RNG.uniform(-4, 0, (n, 1))
    terms = np.stack([a[:, i, j] for i, j in lk.A_PAIRS] + [b[:, i] for i in range(3)])
    return terms, np.linalg.cond(a)


def test_solve_kernel_matches_the_reference_within_the_conditioning():
    terms, cond = _systems(3 * 4 * 5)
    terms = terms.reshape((9, 3, 4, 5))
    got, ref = lk.solve_cl(terms), lk.solve_reference(terms)
    err = np.abs(got - ref).max(0).ravel() / np.abs(ref).max(0).ravel()
    assert np.all(err <= TOL["solve_per_cond"] * cond), (err / cond).max()


def test_solve_kernel_guards_singular_systems_and_pivots():
    """|det A| < 1e-14: v = 0 (a zero and a rank-one matrix; det 1e-15; a pivot that underflows to a
    subnormal, not NaN); a zero first pivot and a zero second pivot solved by row swaps; det 1e-13 solved."""
    cases = [  # (A, b)
        (np.zeros((3, 3)), [1.0, 2.0, 3.0]),
        (np.outer([1.0, 2.0, 0.5], [1.0, 2.0, 0.5]), [1.0, 2.0, 0.5]),
        (np.diag([1e-5, 1e-5, 1e-5]), [1e-5, 0.0, 0.0]),
        (np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 2.0]]), [1.0, 2.0, 3.0]),
        (np.array([[1.0, 1.0, 0.0], [1.0, 1.0, 1.0], [0.0, 1.0, 1.0]]), [1.0, -1.0, 2.0]),
        (np.diag([1e-4, 1e-4, 1e-5]), [1e-4, 2e-4, 3e-5]),
    ]
    # a window with no gradient along one axis (met on a paper-p010 slab's first pass, where the kernel
    # returned NaN): the second pivot underflows to a subnormal (-1.6e-41), whose reciprocal overflows
    cases.insert(3, (np.array([[5.6549638e-08, 9.4114774e-25, 0.0], [9.4114774e-25, 0.0, 0.0],
                               [0.0, 0.0, 6.3292802e-09]]), [0.0, 0.0, -2.2587546e-23]))
    terms = np.zeros((9, 1, 1, len(cases)))
    for c, (a, b) in enumerate(cases):
        for q, (i, j) in enumerate(lk.A_PAIRS):
            terms[q, 0, 0, c] = a[i, j]
        terms[6:9, 0, 0, c] = b
    got, ref = lk.solve_cl(terms)[:, 0, 0], lk.solve_reference(terms)[:, 0, 0]
    assert np.all(got[:, :4] == 0.0) and np.all(ref[:, :4] == 0.0)
    np.testing.assert_allclose(got[:, 4:], ref[:, 4:], rtol=1e-6)
    np.testing.assert_allclose(ref[:, 4], [2.0, 1.0, 1.5])
    np.testing.assert_allclose(ref[:, 6], [1.0, 2.0, 3.0])


@pytest.mark.parametrize("src,dst", [((3, 4, 5), (5, 8, 9)), ((2, 2, 2), (3, 4, 3)), ((28, 9, 16), (55, 17, 32))])
def test_resize_kernel_is_scikit_images_resize_flow_bit_for_bit(src, dst):
    utils = pytest.importorskip("skimage.registration._optical_flow_utils")
    v = RNG.normal(0, 2, (3,) + src).astype(np.float32)
    want = utils._resize_flow(v, dst)
    assert np.array_equal(lk.resize_cl(v, dst), want)
    _close(lk.resize_reference(v, dst), want)


# -- the host's parts: scikit-image's bits ------------------------------------------------------------
@pytest.mark.parametrize("shape", [(5, 7, 9), (33, 40, 70), (66, 34, 35)])
def test_pyramid_is_scikit_images_bit_for_bit(shape):
    utils = pytest.importorskip("skimage.registration._optical_flow_utils")
    img = RNG.uniform(0, 1, shape).astype(np.float32)
    mine, theirs = lk.pyramid(img), utils._get_pyramid(img, 2, 10, 16)
    assert len(mine) == len(theirs) == {(5, 7, 9): 1, (33, 40, 70): 2, (66, 34, 35): 2}[shape]
    for a, b in zip(mine, theirs, strict=True):
        assert a.dtype == b.dtype == np.float32 and np.array_equal(a, b)


def test_prepared_images_are_the_scikit_image_paths_bits():
    vol = RNG.normal(-100, 700, (3, 4, 5)).astype(np.float32)
    lo, hi = (-900.0, 600.0)
    want = (np.clip(np.asarray(vol, np.float64), lo, hi) / (hi - lo)).astype(np.float32)
    assert np.array_equal(lk.prepare(vol, (lo, hi)), want)


# -- the whole registration --------------------------------------------------------------------------
def _against_skimage(fixed, moving, spacing):
    pytest.importorskip("skimage")
    mine = lk.register_lk(fixed, moving, spacing)
    theirs = registration.register(fixed, moving, spacing, cfg=registration.FlowConfig())
    d = np.abs(mine.astype(np.float64) - theirs)
    return mine, theirs, float(d.max()), float(np.sqrt(np.mean(d ** 2)))


@pytest.mark.parametrize("shape,spacing", [((16, 64, 64), (3.0, 3.0, 4.0)), ((36, 40, 44), (1.0, 1.0, 1.0))])
def test_registration_agrees_with_scikit_image_on_a_shift(shape, spacing):
    """A band-limited texture shifted by (0.6, -1.3, 0.8) voxels (z, y, x): the fields agree with
    scikit-image's to float32 rounding (the second shape has a pyramid of two levels)."""
    fixed, moving, shift = _shift_pair(shape)
    mine, theirs, dmax, drms = _against_skimage(fixed, moving, spacing)
    assert dmax <= TOL["vs_skimage_max_mm"] and drms <= TOL["vs_skimage_rms_mm"], (dmax, drms)
    inner = tuple(slice(8, n - 8) for n in shape) if min(shape) > 24 else (slice(None),) * 3
    for c, (s, h) in enumerate(zip(shift[::-1], spacing, strict=True)):
        assert abs(np.median(mine[c][inner]) / h - s) <= TOL["shift_vox"], (c, np.median(mine[c][inner]) / h, s)


def test_registration_agrees_with_scikit_image_on_a_smooth_deformation():
    fixed, moving = _deform_pair((36, 40, 44))
    mine, theirs, dmax, drms = _against_skimage(fixed, moving, (1.0, 1.0, 1.0))
    assert dmax <= TOL["vs_skimage_max_mm"] and drms <= TOL["vs_skimage_rms_mm"], (dmax, drms)
    assert np.abs(theirs).max() > 1.0  # the fields are not all zero


def test_registration_is_deterministic_and_reached_through_register():
    fixed, moving, _ = _shift_pair((10, 24, 20))
    a = lk.register_lk(fixed, moving, (1.0, 1.2, 2.0))
    b = registration.register(fixed, moving, (1.0, 1.2, 2.0), cfg=lk.LKConfig())
    assert a.dtype == np.float32 and a.shape == (3, 10, 24, 20)
    assert np.array_equal(a, b)


def test_registration_peaks_within_its_modelled_bytes():
    """``lk.BYTES_PER_VOXEL`` per voxel above the resident set at the call (VmHWM after clear_refs), on
    demo's registration grid, and :data:`DRIVER_BYTES` for the driver's own. Measured at 512 x 512 x 110:
    65.8 B a voxel (the 68 modelled); on 16 x 128 x 128: 55-56 B a voxel on a process's later calls,
    65-75 on its first (a few MB that do not grow with the volume)."""
    if not os.path.exists("/proc/self/clear_refs"):
        pytest.skip("needs Linux's /proc/self/status and clear_refs")
    fixed, moving = _deform_pair((16, 128, 128))
    lk.register_lk(fixed[:4, :32, :32], moving[:4, :32, :32], (3.0, 3.0, 4.0))  # build the kernels

    def status(key):
        with open("/proc/self/status") as fh:
            return next(int(line.split()[1]) * 1024 for line in fh if line.startswith(key + ":"))

    with open("/proc/self/clear_refs", "w") as fh:
        fh.write("5")
    base = status("VmRSS")
    lk.register_lk(fixed, moving, (3.0, 3.0, 4.0))
    assert status("VmHWM") - base <= lk.BYTES_PER_VOXEL * fixed.size + DRIVER_BYTES


def test_recon_mc_registration_selects_the_opencl_lucas_kanade():
    from clrecon.config.overrides import load_scene
    from clrecon.reconstruction.motion import method

    knobs = load_scene("demo", recon__mc__registration="lucas_kanade_cl", recon__mc__flow_radius=5).recon.mc
    cfg = method.flow_of(knobs, "breathing")
    assert cfg == lk.LKConfig(radius=5, num_warp=knobs.flow_warps)
    assert not method.uses_library(knobs) and not method.uses_pool(knobs)  # in the process, like TV-L1


def test_bad_inputs_get_one_line_errors():
    vol = np.zeros((4, 5, 6), np.float32)
    for call, match in [
        (lambda: lk.register_lk(vol, vol[:3], (1, 1, 1)), r"expected two \(nz, ny, nx\) volumes of one shape"),
        (lambda: lk.register_lk(vol[:1], vol[:1], (1, 1, 1)), "at least 2 voxels along every axis"),
        (lambda: lk.register_lk(vol + np.nan, vol, (1, 1, 1)), "must be finite"),
        (lambda: lk.register_lk(vol, vol, (1, 0, 1)), "three finite spacings > 0"),
        (lambda: lk.LKConfig(radius=0), r"LKConfig.radius = 0: must be an integer >= 1"),
        (lambda: lk.LKConfig(num_warp=2.0), r"LKConfig.num_warp = 2.0: must be an integer >= 1"),
        (lambda: lk.LKConfig(hu_window=(5.0, 5.0)), "must be finite"),
        (lambda: registration.register(vol, vol, (1, 1, 1), cfg=lk.LKConfig(), initial=np.zeros((3,) + vol.shape)),
         "starts from zero"),
    ]:
        with pytest.raises(ValueError, match=match) as e:
            call()
        assert "\n" not in str(e.value)
