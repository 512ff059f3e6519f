"""Matched cone-beam backprojector (``kernels/voxel_backproject.cl``): the transpose of the voxel
projector. (a) its float64 reference is the transpose of the dense matrix built column by
column from the projector's float64 reference; (b) the kernel matches that reference on random
and edge-case inputs; (c) the dot-product test <A x, y> = <x, A^T y> of the two kernels, flat
and cylindrical detectors, flying focal spot; (d) bit-identical results whatever the chunking.

Tolerances live in ``TOL`` below, each with its reason; nothing else in this file is a tolerance.
"""

import numpy as np
import pytest

from clrecon.core.conventions import detector_coords, detector_frames
from clrecon.core.detector import CylindricalDetector, spot_shift_in_frame
from clrecon.reconstruction.iterative import cone_backprojector as bp
from clrecon.simulation import voxel_projector as vp
from clrecon.simulation.projector import spot_frames

SID, SDD = 595.0, 1085.6
EPS32 = float(np.finfo(np.float32).eps)

#: The one tolerance table: name -> (value, reason).
TOL = {
    # float64 reference vs the dense transpose of the projector's float64 reference: the same
    # weights summed in another order, rounding only
    "dense_rel": (1e-12, "float64 rounding"),
    # kernel vs reference, per voxel: |b - r| <= k eps32 (A + N) max_v (sum_r A[r, v] |y_r|), A the
    # largest |index coordinate| of a source, N the largest axis (as the projector's kernel_k:
    # float32 index coordinates move each bilinear weight by ~eps32 A between neighbouring
    # voxels, and the clipped end weights too; the fixed-point sum itself is exact). Measured
    # max k: 0.70 on random geometries (8 seeds), 0.36 cylindrical + flying focal spot, 0.33 on
    # the edge cases; k = 4 (the projector's) leaves a factor 5.7.
    "kernel_k": (4.0, "float32 index coordinates of the sample points"),
    # dot-product test: |<A x, y> - <x, A^T y>| / <|A| |x|, |y|> (the dot's own scale). The two
    # kernels compute the same float32 weights; what remains is the float32 rounding of the
    # projector's sums and of the products (worst case ~eps32 (A + N) ~ 2e-5 here, but random in
    # sign over 1e4..1e6 products). Measured: 2e-11..4e-10 flat (4 seeds), 1.0e-9 cylindrical +
    # flying focal spot, 1.3e-8 on one-voxel-thick volumes; 1e-6 leaves a factor 80.
    "dot_rel": (1e-6, "float32 sums of the projector; float32 weights in both"),
}


def tol(name):
    return TOL[name][0]


def random_frames(rng, m, centre, r_lo=300.0, r_hi=700.0):
    """Views from random directions (any dominant axis), orthonormal e_u, e_v."""
    w = rng.normal(size=(m, 3))
    w /= np.linalg.norm(w, axis=1, keepdims=True)
    src = centre + rng.uniform(r_lo, r_hi, m)[:, None] * w
    det = centre - rng.uniform(200, 500, m)[:, None] * w
    a = rng.normal(size=(m, 3))
    eu = a - np.sum(a * w, 1, keepdims=True) * w
    eu /= np.linalg.norm(eu, axis=1, keepdims=True)
    return src, det, eu, np.cross(w, eu)


def small_volume(rng, shape):
    spacing = rng.uniform(1.0, 5.0, 3)
    n = np.array(shape[::-1])
    centre = rng.uniform(-20, 20, 3)
    return centre - 0.5 * (n - 1) * spacing, spacing, centre


def curved_spot_geometries(n_views=3, n_cols=41, n_rows=5, col_pitch=12.0, row_pitch=8.0):
    """Per flying-focal-spot state (phi + z: four spots), (frames, u, v, v_scale) of a cylindrical detector."""
    det = CylindricalDetector(sid_mm=SID, sdd_mm=SDD, n_cols=n_cols, n_rows=n_rows, col_pitch_mm=col_pitch,
                              row_pitch_mm=row_pitch, central_col=(n_cols - 1) / 2 + 0.25,
                              central_row=(n_rows - 1) / 2)
    beta = np.linspace(0.2, 5.9, n_views)
    z = np.linspace(-6.0, 6.0, n_views)
    out = []
    for st in ([0.002, 0.8, 0.5], [0.002, 0.8, -0.5], [-0.002, -0.8, 0.5], [-0.002, -0.8, -0.5]):
        shift = spot_shift_in_frame(np.array([st]), SID)[0]
        frames, (u, v, vs) = spot_frames(det, beta, z, shift)
        out.append((frames, u, v, vs))
    return out


def dense_matrix(shape, origin, spacing, frames, u, v, v_scale=None):
    """A (rays, voxels) float64, one column per voxel from the projector's float64 reference."""
    cols = []
    for i in range(int(np.prod(shape))):
        e = np.zeros(int(np.prod(shape)))
        e[i] = 1.0
        cols.append(vp.project_volume_reference(e.reshape(shape), origin, spacing, *frames, u, v,
                                                v_scale=v_scale).ravel())
    return np.stack(cols, axis=1)


def check_kernel_vs_reference(y, shape, origin, spacing, frames, u, v, v_scale=None, chunk_views=None):
    """Kernel against the float64 reference; returns (measured k, kernel result, reference)."""
    got = bp.backproject_volume(y, shape, origin, spacing, *frames, u, v, v_scale=v_scale, chunk_views=chunk_views)
    ref = bp.backproject_volume_reference(y, shape, origin, spacing, *frames, u, v, v_scale=v_scale)
    assert got.dtype == np.float32 and got.shape == ref.shape == tuple(shape)
    mag = bp.backproject_volume_reference(np.abs(y), shape, origin, spacing, *frames, u, v, v_scale=v_scale)
    A = np.abs((frames[0] - np.asarray(origin)) / np.asarray(spacing)).max()
    scale = EPS32 * (A + max(shape)) * max(mag.max(), 1e-300)
    err = np.abs(got.astype(np.float64) - ref)
    k = float(err.max() / scale)
    worst = np.unravel_index(np.argmax(err), err.shape)
    assert k <= tol("kernel_k"), f"voxel {worst}: |{got[worst]} - {ref[worst]}|, k = {k:.3g}"
    assert np.all(got[mag == 0] == 0)                   # voxels no ray reaches get exactly nothing
    return k, got, ref


def dot_test(x, shape, origin, spacing, geoms):
    """Relative dot-product mismatch |<A x, y> - <x, A^T y>| / <|A| |x|, |y|> of the two kernels,
    the sums running over ``geoms``: (frames, u, v, v_scale, y) per spot state (A stacks them)."""
    lhs = rhs = scale = 0.0
    x64 = x.astype(np.float64)
    for frames, u, v, vs, y in geoms:
        ax = vp.project_volume(x, origin, spacing, *frames, u, v, v_scale=vs).astype(np.float64)
        aty = bp.backproject_volume(y, shape, origin, spacing, *frames, u, v, v_scale=vs).astype(np.float64)
        y64 = y.astype(np.float64)
        lhs += float(np.sum(ax * y64))
        rhs += float(np.sum(x64 * aty))
        scale += float(np.sum(vp.project_volume(np.abs(x), origin, spacing, *frames, u, v, v_scale=vs)
                              .astype(np.float64) * np.abs(y64)))
    return abs(lhs - rhs) / scale, lhs, rhs


# ---------------------------------------------------------------------------------------
# (a) the float64 reference is the transpose of the projector's
@pytest.mark.parametrize("detector", ["flat", "cylindrical"])
def test_reference_is_the_transpose_of_the_projectors_dense_matrix(detector):
    rng = np.random.default_rng(1 if detector == "flat" else 2)
    shape = (4, 5, 6)
    origin, spacing, centre = small_volume(rng, shape)
    if detector == "flat":
        half = 0.5 * np.linalg.norm(np.array(shape[::-1]) * spacing)
        geoms = [(random_frames(rng, 4, centre), detector_coords(13, 4.0 * half / 12),
                  detector_coords(5, 3.0 * half / 4), None)]
    else:
        spacing = np.array([40.0, 36.0, 3.0])             # the scan's fan over the volume, isocentre inside
        origin = -0.5 * (np.array(shape[::-1]) - 1) * spacing + rng.uniform(-5, 5, 3)
        geoms = [(f, u, v, vs) for f, u, v, vs in curved_spot_geometries(n_views=2, n_cols=21, n_rows=3)]
    for frames, u, v, vs in geoms:
        A = dense_matrix(shape, origin, spacing, frames, u, v, vs)
        assert np.count_nonzero(A.any(axis=1)) > 0.1 * A.shape[0]   # rays hit
        y = rng.normal(size=(len(frames[0]), len(v), len(u)))
        ref = bp.backproject_volume_reference(y, shape, origin, spacing, *frames, u, v, v_scale=vs)
        want = (A.T @ y.ravel()).reshape(shape)
        assert np.abs(ref - want).max() <= tol("dense_rel") * np.abs(want).max()


# ---------------------------------------------------------------------------------------
# (b) kernel vs float64 reference
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_random_volumes_and_geometries_match_reference(seed):
    rng = np.random.default_rng(seed)
    shape = tuple(int(n) for n in rng.integers(5, 20, 3))
    origin, spacing, centre = small_volume(rng, shape)
    half = 0.5 * np.linalg.norm(np.array(shape[::-1]) * spacing)
    u = detector_coords(27, 4.0 * half / 26)            # wider than the shadow: grazing rays and misses
    v = detector_coords(7, 3.0 * half / 6)
    for frames in (random_frames(rng, 6, centre),
                   detector_frames(rng.uniform(0, 2 * np.pi, 4), centre[2] + rng.uniform(-20, 20, 4), SID, SDD)):
        y = rng.normal(size=(len(frames[0]), len(v), len(u)))
        check_kernel_vs_reference(y, shape, origin, spacing, frames, u, v)


def test_cylindrical_detector_with_flying_focal_spot_matches_reference():
    rng = np.random.default_rng(3)
    shape = (6, 9, 11)
    spacing = np.array([30.0, 28.0, 3.0])
    origin = -0.5 * (np.array(shape[::-1]) - 1) * spacing
    for frames, u, v, vs in curved_spot_geometries():
        y = rng.normal(size=(len(frames[0]), len(v), len(u)))
        check_kernel_vs_reference(y, shape, origin, spacing, frames, u, v, vs)


def test_rays_parallel_to_an_axis_on_centre_lines_edges_faces_and_outside():
    """One ray per view along each axis, through voxel centres, midpoints, box faces and outside
    (the projector's edge cases): the transpose of each ray's clamped samples."""
    rng = np.random.default_rng(5)
    shape = (6, 7, 5)
    spacing = np.array([2.0, 3.0, 1.5])
    n = np.array(shape[::-1])
    origin = np.array([-4.0, 7.0, 2.5])
    positions = np.array([0.0, 1.0, 2.5, -0.5, 0.3, 1.7])
    outside = np.array([-0.75, -3.0])
    for k in range(3):
        j, l = [a for a in range(3) if a != k]
        gj = np.concatenate([positions, [n[j] - 0.5, n[j] - 1.0], outside, [1.0, 1.0]])
        gl = np.concatenate([positions[::-1], [n[l] - 0.5, 0.0], [1.0, 1.0], outside])
        m = len(gj)
        g = np.zeros((m, 3))
        g[:, j], g[:, l] = gj, gl
        sgn = np.where(np.arange(m) % 2, 1.0, -1.0)
        g[:, k] = 0.5 * (n[k] - 1) - sgn * 40.0
        src = origin + g * spacing
        det = src + sgn[:, None] * 100.0 * np.eye(3)[k]
        frames = (src, det, np.tile(np.eye(3)[j], (m, 1)), np.tile(np.eye(3)[l], (m, 1)))
        y = rng.normal(size=(m, 1, 1))
        _, got, ref = check_kernel_vs_reference(y, shape, origin, spacing, frames, np.zeros(1), np.zeros(1))
        # view 7 runs along a line of voxel centres (g_j = n_j - 1, g_l = 0): y_7 h_k on each voxel of it
        one = np.zeros((m, 1, 1))
        one[7] = 1.0
        line = np.moveaxis(np.transpose(bp.backproject_volume_reference(one, shape, origin, spacing, *frames,
                                                                         np.zeros(1), np.zeros(1)), (2, 1, 0)), k, -1)
        assert np.allclose(line[n[j] - 1, 0], spacing[k], rtol=1e-12) and line.sum() == pytest.approx(
            n[k] * spacing[k], rel=1e-12)


def test_sources_inside_and_volume_behind_the_source():
    rng = np.random.default_rng(6)
    shape = (9, 8, 10)
    spacing = np.array([2.0, 2.0, 2.5])
    origin = -0.5 * (np.array(shape[::-1]) - 1) * spacing
    src, det, eu, ev = random_frames(rng, 5, np.zeros(3))
    src[:2] = rng.uniform(-5, 5, (2, 3))
    det[:2] = src[:2] - 300.0 * (src[:2] / np.linalg.norm(src[:2], axis=1, keepdims=True))
    det[2:] = src[2:] + (src[2:] - det[2:])              # the volume behind the source: no weight
    eu[:2] = np.cross(src[:2] - det[:2], [0.3, 0.1, 1.0])
    eu[:2] /= np.linalg.norm(eu[:2], axis=1, keepdims=True)
    ev[:2] = np.cross(src[:2] - det[:2], eu[:2])
    ev[:2] /= np.linalg.norm(ev[:2], axis=1, keepdims=True)
    u, v = detector_coords(11, 20.0), detector_coords(5, 20.0)
    y = rng.normal(size=(5, 5, 11))
    check_kernel_vs_reference(y, shape, origin, spacing, (src, det, eu, ev), u, v)
    behind = y.copy()
    behind[:2] = 0.0
    assert not np.any(bp.backproject_volume(behind, shape, origin, spacing, src, det, eu, ev, u, v))


@pytest.mark.parametrize("shape", [(1, 9, 8), (7, 1, 6), (5, 6, 1), (1, 1, 1)])
def test_single_voxel_thick_volumes(shape):
    rng = np.random.default_rng(sum(shape))
    origin, spacing, centre = small_volume(rng, shape)
    u, v = detector_coords(15, 3.0), detector_coords(4, 3.0)
    frames = random_frames(rng, 6, centre)
    y = rng.normal(size=(6, 4, 15))
    check_kernel_vs_reference(y, shape, origin, spacing, frames, u, v)
    rel, _, _ = dot_test(rng.normal(size=shape).astype(np.float32), shape, origin, spacing,
                         [(frames, u, v, None, y.astype(np.float32))])
    assert rel <= tol("dot_rel")


# ---------------------------------------------------------------------------------------
# (c) dot-product tests of the kernel pair
@pytest.mark.parametrize("seed", [0, 1])
def test_dot_product_flat_detector(seed):
    rng = np.random.default_rng(10 + seed)
    shape = (24, 40, 36)
    spacing = np.array([6.0, 6.0, 2.0])
    origin = -0.5 * (np.array(shape[::-1]) - 1) * spacing
    frames = detector_frames(rng.uniform(0, 2 * np.pi, 8), rng.uniform(-15, 15, 8), SID, SDD)
    u, v = detector_coords(96, 4.0), detector_coords(12, 2.0)
    x = rng.normal(size=shape).astype(np.float32)
    y = rng.normal(size=(8, 12, 96)).astype(np.float32)
    rel, lhs, rhs = dot_test(x, shape, origin, spacing, [(frames, u, v, None, y)])
    assert rel <= tol("dot_rel"), f"<Ax, y> = {lhs}, <x, A^T y> = {rhs}, relative {rel:.2e}"


def test_dot_product_cylindrical_detector_with_flying_focal_spot():
    rng = np.random.default_rng(12)
    shape = (10, 30, 28)
    spacing = np.array([9.0, 9.0, 1.5])
    origin = -0.5 * (np.array(shape[::-1]) - 1) * spacing
    x = rng.normal(size=shape).astype(np.float32)
    geoms = [(f, u, v, vs, rng.normal(size=(len(f[0]), len(v), len(u))).astype(np.float32))
             for f, u, v, vs in curved_spot_geometries(n_views=4)]
    rel, lhs, rhs = dot_test(x, shape, origin, spacing, geoms)
    assert rel <= tol("dot_rel"), f"<Ax, y> = {lhs}, <x, A^T y> = {rhs}, relative {rel:.2e}"


# ---------------------------------------------------------------------------------------
# (d) determinism, degenerate input, errors
def test_bit_identical_whatever_the_chunking_and_repeat():
    rng = np.random.default_rng(7)
    shape = (12, 20, 18)
    spacing = np.array([4.0, 4.0, 3.0])
    origin = -0.5 * (np.array(shape[::-1]) - 1) * spacing
    frames = detector_frames(rng.uniform(0, 2 * np.pi, 5), rng.uniform(-10, 10, 5), SID, SDD)
    u, v = detector_coords(33, 4.0), detector_coords(3, 2.0)
    y = rng.normal(size=(5, 3, 33)).astype(np.float32)
    full = bp.backproject_volume(y, shape, origin, spacing, *frames, u, v)
    for chunk in (1, 2, None):
        np.testing.assert_array_equal(bp.backproject_volume(y, shape, origin, spacing, *frames, u, v,
                                                            chunk_views=chunk), full)
    check_kernel_vs_reference(y, shape, origin, spacing, frames, u, np.asarray(v))   # one call, 3 rows


@pytest.mark.parametrize("detector", ["flat", "cylindrical"])
def test_pair_kernel_gives_each_single_calls_bits(detector):
    """backproject_pair (kernel variant PAIR): each of its two volumes is the same bits as the
    single call on that array, whatever the chunking, for arrays of very different sums (each
    accumulator its own fixed-point scale) and with one array zero on some rays."""
    rng = np.random.default_rng(21)
    shape = (9, 14, 12)
    spacing = np.array([5.0, 5.0, 2.0])
    origin = -0.5 * (np.array(shape[::-1]) - 1) * spacing
    if detector == "flat":
        geoms = [(detector_frames(rng.uniform(0, 2 * np.pi, 5), rng.uniform(-8, 8, 5), SID, SDD),
                  detector_coords(31, 5.0), detector_coords(4, 2.0), None)]
    else:
        geoms = curved_spot_geometries(n_views=3)[:2]
    for frames, u, v, vs in geoms:
        y = rng.normal(size=(len(frames[0]), len(v), len(u))).astype(np.float32)
        w = (rng.uniform(size=y.shape) > 0.3).astype(np.float32) * 1e-3
        y[:, 0] = 0.0                                   # rays where only the second has a value
        for chunk in (1, None):
            a, b = bp.backproject_pair(y, w, shape, origin, spacing, *frames, u, v, v_scale=vs, chunk_views=chunk)
            np.testing.assert_array_equal(a, bp.backproject_volume(y, shape, origin, spacing, *frames, u, v,
                                                                   v_scale=vs))
            np.testing.assert_array_equal(b, bp.backproject_volume(w, shape, origin, spacing, *frames, u, v,
                                                                   v_scale=vs))
        zero, b = bp.backproject_pair(np.zeros_like(y), w, shape, origin, spacing, *frames, u, v, v_scale=vs)
        assert not zero.any()
        np.testing.assert_array_equal(b, bp.backproject_volume(w, shape, origin, spacing, *frames, u, v, v_scale=vs))


def test_zero_and_empty_projections_give_zero():
    frames = detector_frames(np.array([0.3]), np.array([0.0]), SID, SDD)
    u, v = detector_coords(9, 4.0), detector_coords(2, 2.0)
    out = bp.backproject_volume(np.zeros((1, 2, 9)), (3, 4, 5), (0, 0, 0), (1, 1, 1), *frames, u, v)
    assert out.shape == (3, 4, 5) and out.dtype == np.float32 and not out.any()
    empty = tuple(f[:0] for f in frames)
    assert not bp.backproject_volume(np.zeros((0, 2, 9)), (3, 4, 5), (0, 0, 0), (1, 1, 1), *empty, u, v).any()


@pytest.mark.parametrize("kwargs, match", [
    ({"proj": np.zeros((2, 2, 9))}, r"proj must have shape \(views, rows, cols\) = \(1, 2, 9\)"),
    ({"proj": np.full((1, 2, 9), np.nan)}, r"proj \[view, row, col\] has a non-finite value"),
    ({"shape_zyx": (3, 0, 5)}, "shape_zyx must be three integers >= 1"),
    ({"spacing_mm": (1, -1, 1)}, "spacing_mm must be finite and > 0"),
    ({"chunk_views": 0}, "chunk_views must be an integer >= 1"),
])
def test_bad_input_is_a_one_line_error(kwargs, match):
    frames = detector_frames(np.array([0.3]), np.array([0.0]), SID, SDD)
    args = {"proj": np.ones((1, 2, 9)), "shape_zyx": (3, 4, 5), "origin_mm": (0, 0, 0), "spacing_mm": (1, 1, 1)}
    args.update({k: kwargs[k] for k in args if k in kwargs})
    extra = {k: kwargs[k] for k in kwargs if k not in args}
    with pytest.raises(ValueError, match=match):
        bp.backproject_volume(args["proj"], args["shape_zyx"], args["origin_mm"], args["spacing_mm"], *frames,
                              detector_coords(9, 4.0), detector_coords(2, 2.0), **extra)
