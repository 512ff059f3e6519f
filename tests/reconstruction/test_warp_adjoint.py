"""Warp W_u and its transpose (``kernels/warp.cl``): the kernels against their float64
references (random fields reaching past every edge, one-voxel axes, anisotropic voxels), the
reference transpose against the dense matrix of the reference warp, the dot-product test of the
kernel pair, exact cases (integer shifts, conservation of the sum) and determinism.

Tolerances live in ``TOL`` below, each with its reason; nothing else in this file is a tolerance.
"""

import numpy as np
import pytest

from clrecon.reconstruction.iterative import warp as W

EPS32 = float(np.finfo(np.float32).eps)

#: The one tolerance table: name -> (value, reason).
TOL = {
    # reference transpose vs the dense matrix's transpose: the same float64 weights, another order
    "dense_rel": (1e-12, "float64 rounding"),
    # kernel vs reference: |k - r| <= k eps32 (G + 1) M, G the largest |index coordinate| of a
    # sample point (float32 coordinates carry ~eps32 G voxels, which move each trilinear weight
    # by as much), M = max|x| for the warp, max_v sum_p T(p, v)|g_p| for the transpose (the
    # fixed-point sum is exact). Measured max k: 0.20 warp, 0.18 transpose (6 random cases);
    # k = 2 leaves a factor 10.
    "kernel_k": (2.0, "float32 sample coordinates"),
    # dot-product test, relative to <|W| |x|, |g|>: float32 weights and products, random in sign.
    # Measured: up to 3.5e-8 (6 random cases); 1e-6 leaves a factor 28.
    "dot_rel": (1e-6, "float32 weights and products"),
}


def tol(name):
    return TOL[name][0]


CASES = [((7, 9, 11), (1.5, 2.0, 3.0), 4.0), ((5, 6, 7), (1.0, 1.0, 1.0), 0.3), ((1, 6, 7), (2.0, 1.0, 3.0), 3.0),
         ((4, 1, 5), (1.0, 2.0, 2.0), 3.0), ((3, 4, 1), (1.0, 1.0, 1.0), 2.0), ((1, 1, 1), (1.0, 1.0, 1.0), 1.0)]


def case(i):
    shape, h, sigma = CASES[i]
    rng = np.random.default_rng(20 + i)
    u = rng.normal(0, sigma, (3,) + shape).astype(np.float32)          # mm; past every edge for sigma >= 3
    x = rng.normal(size=shape).astype(np.float32)
    g = rng.normal(size=shape).astype(np.float32)
    return x, g, u, h


def coord_scale(u, h):
    shape = u.shape[1:]
    idx = np.stack(np.meshgrid(*[np.arange(n) for n in shape], indexing="ij"))[::-1]     # (x, y, z) index
    return float(np.abs(idx + u / np.asarray(h, np.float64)[:, None, None, None]).max()) + 1.0


@pytest.mark.parametrize("i", range(len(CASES)))
def test_kernels_match_float64_references(i):
    x, g, u, h = case(i)
    G = coord_scale(u, h)
    got, ref = W.warp(x, u, h), W.warp_reference(x, u, h)
    assert got.dtype == np.float32 and got.shape == x.shape
    assert np.abs(got - ref).max() <= tol("kernel_k") * EPS32 * G * np.abs(x).max()
    got, ref = W.warp_adjoint(g, u, h), W.warp_adjoint_reference(g, u, h)
    mag = W.warp_adjoint_reference(np.abs(g), u, h)
    assert got.dtype == np.float32 and got.shape == g.shape
    assert np.abs(got - ref).max() <= tol("kernel_k") * EPS32 * G * mag.max()


@pytest.mark.parametrize("i", [0, 2, 4])
def test_reference_transpose_is_the_dense_transpose(i):
    x, g, u, h = case(i)
    n = x.size
    T = np.stack([W.warp_reference(np.eye(n)[k].reshape(x.shape), u, h).ravel() for k in range(n)], axis=1)
    want = (T.T @ g.astype(np.float64).ravel()).reshape(x.shape)
    assert np.abs(W.warp_adjoint_reference(g, u, h) - want).max() <= tol("dense_rel") * np.abs(want).max()


@pytest.mark.parametrize("i", range(len(CASES)))
def test_dot_product(i):
    x, g, u, h = case(i)
    lhs = float(np.sum(W.warp(x, u, h).astype(np.float64) * g))
    rhs = float(np.sum(x.astype(np.float64) * W.warp_adjoint(g, u, h)))
    scale = float(np.sum(W.warp(np.abs(x), u, h).astype(np.float64) * np.abs(g)))
    assert abs(lhs - rhs) <= tol("dot_rel") * scale, f"<Wx, g> = {lhs}, <x, W^T g> = {rhs}"


def test_integer_shift_moves_the_volume_and_clamps_at_the_edge():
    rng = np.random.default_rng(3)
    x = rng.normal(size=(4, 5, 6)).astype(np.float32)
    h = (2.0, 3.0, 1.5)
    u = np.zeros((3,) + x.shape, np.float32)
    u[1] = -3.0                                                         # one voxel towards -y
    want = np.concatenate([x[:, :1], x[:, :-1]], axis=1)                # out[y] = x[y - 1], clamped at y = 0
    np.testing.assert_allclose(W.warp(x, u, h), want, rtol=0, atol=4 * EPS32 * np.abs(x).max())
    # the transpose moves each voxel one step towards +y; the first row of voxels receives row 0 and 1
    back = W.warp_adjoint(x, u, h)
    np.testing.assert_allclose(back[:, 1:-1], x[:, 2:], atol=4 * EPS32 * np.abs(x).max())
    np.testing.assert_allclose(back[:, 0], x[:, 0] + x[:, 1], atol=4 * EPS32 * np.abs(x).max())
    assert not back[:, -1].any()


def test_transpose_conserves_the_sum_and_is_bit_identical_on_repeats():
    x, g, u, h = case(0)
    pos = np.abs(g)
    out = W.warp_adjoint(pos, u, h)
    assert out.sum(dtype=np.float64) == pytest.approx(pos.sum(dtype=np.float64), rel=1e-6)
    for _ in range(3):                                                 # the work-items' order changes, not the bits
        np.testing.assert_array_equal(W.warp_adjoint(pos, u, h), out)
    assert not W.warp_adjoint(np.zeros_like(g), u, h).any()


@pytest.mark.parametrize("args, match", [
    ((np.zeros((2, 3, 4)), np.zeros((3, 2, 3, 5)), (1, 1, 1)), r"u must have shape \(3,\) \+ x.shape"),
    ((np.zeros((2, 3)), np.zeros((3, 2, 3)), (1, 1, 1)), r"x must be a non-empty \(nz, ny, nx\) array"),
    ((np.zeros((2, 3, 4)), np.full((3, 2, 3, 4), np.nan), (1, 1, 1)), "u has a non-finite value at index"),
    ((np.zeros((2, 3, 4)), np.zeros((3, 2, 3, 4)), (1, 0, 1)), "spacing_mm must be three finite numbers > 0"),
])
def test_bad_input_is_a_one_line_error(args, match):
    with pytest.raises(ValueError, match=match):
        W.warp(*args)


@pytest.mark.parametrize("seed", [0, 1])
def test_invert_field_kernel_against_its_float64_reference(seed):
    """The one-launch inversion equals ``steps`` rounds of the float64 warp of u's components (random
    smooth field on anisotropic voxels, with displacements past the edges: clamped)."""
    from clrecon.reconstruction.iterative.warp import invert_field, invert_field_reference

    rng = np.random.default_rng(seed)
    shape = (5, 7, 9)
    z, y, x = np.meshgrid(*[np.linspace(0, 1, n) for n in shape], indexing="ij")
    u = np.stack([3.0 * np.sin(2 * x + 1 + seed) * np.cos(y), -2.0 * np.cos(3 * z) + y, 4.0 * x * z - 1.5])
    u = (u + rng.normal(0, 0.2, u.shape)).astype(np.float32)
    h = (2.0, 1.5, 3.0)
    for steps in (0, 1, 10):
        got = invert_field(u, h, steps)
        ref = invert_field_reference(u, h, steps)
        # float32 index arithmetic and trilinear sums, fed back through the iteration: 1e-4 mm
        # against fields of a few mm (measured below 5e-6)
        assert np.abs(got - ref).max() <= 1e-4, (steps, np.abs(got - ref).max())
    with pytest.raises(ValueError, match="steps"):
        invert_field(u, h, -1)
    with pytest.raises(ValueError, match=r"\(3, nz, ny, nx\)"):
        invert_field(u[:2], h, 2)
