"""The shrinkage of registered fields towards zero where the images cannot show the motion
(clrecon.reconstruction.motion.confidence, ``recon.mc.shrink``; docs/motion-model.md "Knobs")."""

import numpy as np
import pytest
import scipy.ndimage

from clrecon.core.resources import spawned_pool
from clrecon.reconstruction.motion import confidence, estimate, registration
from clrecon.reconstruction.motion.model import FieldGrid

SPACING = (3.0, 3.0, 4.0)
HU = (-900.0, 600.0)
NZ, NY, NX = 12, 40, 56


def _pair(noise_hu: float, seed: int = 0, shifts=(0.0, -1.0)):
    """A volume whose left half holds strong texture (about 100 HU of smooth structure) and whose
    right half is flat (noise only), and the same volume moved by one voxel (3 mm) along x:
    ``moving(x - 3 mm) = fixed(x)``. Returns (fixed, moving, textured (nz, ny, nx) bool, flat bool)."""
    rng = np.random.default_rng(seed)
    tex = scipy.ndimage.gaussian_filter(rng.standard_normal((NZ, NY, NX + 8)), [1.5, 2, 2]) * 2000.0
    tex[:, :, NX // 2 + 4:] = 0.0

    def vol(shift):
        v = scipy.ndimage.shift(tex, (0, 0, shift), order=3, mode="nearest")[:, :, 4:4 + NX]
        return (v + noise_hu * rng.standard_normal(v.shape)).astype(np.float32)

    x = np.arange(NX)
    textured = np.broadcast_to((x >= 8) & (x < NX // 2 - 8), (NZ, NY, NX))
    flat = np.broadcast_to((x >= NX // 2 + 12) & (x < NX - 4), (NZ, NY, NX))
    return (*[vol(sh) for sh in shifts], textured, flat)


def _shrink(fixed, moving, u, chunk=1 << 18):
    grid = FieldGrid(nx=NX, ny=NY, nz=NZ, voxel_mm=SPACING[0], z0_mm=0.0, dz_mm=SPACING[2])
    warped = estimate.to_reference(moving, u, grid)
    f = confidence.normalise(fixed, HU)
    r = f - confidence.normalise(warped, HU)
    vox = np.stack([u[2] / SPACING[2], u[1] / SPACING[1], u[0] / SPACING[0]])
    inside = (fixed > HU[0]) & (fixed < HU[1])
    out, info = confidence.shrink_voxels(f, r, vox, 4, inside, chunk=chunk)
    return np.stack([out[2] * SPACING[0], out[1] * SPACING[1], out[0] * SPACING[2]]).astype(np.float32), info


def test_a_texture_free_region_shrinks_to_zero_and_strong_texture_keeps_its_field():
    fixed, moving, textured, flat = _pair(noise_hu=40.0)
    u = registration.register(fixed, moving, SPACING, cfg=registration.FlowConfig(radius=4))
    us, info = confidence.shrink_field(fixed, estimate.to_reference(
        moving, u, FieldGrid(nx=NX, ny=NY, nz=NZ, voxel_mm=3.0, z0_mm=0.0, dz_mm=4.0)), u, SPACING, 4, HU)
    mag = lambda f, m: float(np.sqrt((f[:, m] ** 2).sum(0)).mean())  # noqa: E731
    # the registration invents motion where there is nothing to see (noise only) ...
    assert mag(u, flat) > 0.5, mag(u, flat)
    # ... which the shrinkage takes (nearly) all back
    assert mag(us, flat) <= 0.1 * mag(u, flat), (mag(u, flat), mag(us, flat))
    # where the texture is strong the field is the registration's, to 5 % (the true -3 mm along x)
    assert abs(float(np.median(u[0][textured])) + 3.0) < 0.3
    assert mag(us, textured) == pytest.approx(mag(u, textured), rel=0.05)
    assert 0.0 <= info["mean_gain"] <= 1.0 and info["n_eff"] >= 1.0 and info["residual_std"] > 0


def test_without_noise_a_flat_region_has_no_field_to_shrink_and_a_zero_field_stays_zero():
    fixed, moving, textured, flat = _pair(noise_hu=0.0)
    zero = np.zeros((3, NZ, NY, NX), np.float32)
    out, _ = _shrink(fixed, moving, zero)
    assert np.array_equal(out, zero)


def test_the_shrinkage_is_the_same_bits_for_any_chunk_and_repeated():
    fixed, moving, _, _ = _pair(noise_hu=40.0, seed=1)
    u = registration.register(fixed, moving, SPACING, cfg=registration.FlowConfig(radius=4))
    a, _ = _shrink(fixed, moving, u)
    b, _ = _shrink(fixed, moving, u, chunk=997)
    assert np.array_equal(a, b) and np.array_equal(a, _shrink(fixed, moving, u)[0])
    assert not np.array_equal(a, u)


def test_separable_fields_with_the_shrinkage_are_the_same_bits_in_a_process_pool():
    v00, v01, v10, v11, _, _ = _pair(noise_hu=40.0, seed=2, shifts=(0.0, -1.0, 0.5, -0.5))
    vols = np.stack([np.stack([v00, v01]), np.stack([v10, v11])])  # (n_c 2, n_r 2, ...)
    grid = FieldGrid(nx=NX, ny=NY, nz=NZ, voxel_mm=3.0, z0_mm=0.0, dz_mm=4.0)
    cfg = registration.FlowConfig(radius=4)
    serial, parts = estimate.separable_fields(vols, (0, 0), grid, cfg, shrink=(4, HU))
    plain, _ = estimate.separable_fields(vols, (0, 0), grid, cfg)
    pool = spawned_pool(2)
    assert pool is not None
    try:
        pooled, _ = estimate.separable_fields(vols, (0, 0), grid, cfg, pool=pool, shrink=(4, HU))
    finally:
        pool.shutdown()
    assert np.array_equal(serial, pooled)
    assert len(parts["shrink"]) == 2 and not np.array_equal(serial, plain)


def _half_moving_pair(seed: int = 3):
    """Along x: a textured band moved by one voxel (3 mm) in ``moving``, a textured band that stays
    where it is but differs by smooth 30-HU "streaks", and a flat half with 5 HU of noise (most of a
    CT volume is flat, which is where the shrinkage measures the gradient noise); a field of -3 mm
    along x in the first band (the truth), an invented +2 mm in the second, 0 in the flat half.
    Returns (fixed, moving, field, first band (nz, ny, nx2) bool, second band bool)."""
    nx = 2 * NX
    rng = np.random.default_rng(seed)
    tex = scipy.ndimage.gaussian_filter(rng.standard_normal((NZ, NY, nx + 8)), [1.5, 2, 2]) * 2000.0
    x = np.arange(nx + 8) - 4
    tex[:, :, x >= NX] = 0.0
    moved = scipy.ndimage.shift(tex, (0, 0, -1.0), order=3, mode="nearest")
    streaks = scipy.ndimage.gaussian_filter(rng.standard_normal(tex.shape), [2, 4, 4]) * 30.0 / 0.05
    moving = np.where(x < NX // 2, moved, tex + np.where(x < NX, streaks, 0.0))
    fixed = tex + 5.0 * rng.standard_normal(tex.shape)
    moving = moving + 5.0 * rng.standard_normal(tex.shape)
    xs = np.arange(nx)
    first = np.broadcast_to((xs >= 6) & (xs < NX // 2 - 6), (NZ, NY, nx))
    second = np.broadcast_to((xs >= NX // 2 + 6) & (xs < NX - 6), (NZ, NY, nx))
    field = np.zeros((3, NZ, NY, nx), np.float32)
    field[0] = np.where(xs < NX // 2, -3.0, np.where(xs < NX, 2.0, 0.0))
    return fixed[:, :, 4:4 + nx].astype(np.float32), moving[:, :, 4:4 + nx].astype(np.float32), field, first, second


def test_the_local_prior_takes_back_a_field_that_explains_nothing_where_the_global_one_keeps_it():
    """Both halves are textured, so the global prior keeps both halves' fields; only the left half's
    explains the images' difference, and the local prior keeps that one and takes the other back."""
    fixed, moving, u, left, right = _half_moving_pair()
    grid = FieldGrid(nx=2 * NX, ny=NY, nz=NZ, voxel_mm=3.0, z0_mm=0.0, dz_mm=4.0)
    at_ref = estimate.to_reference(moving, u, grid)
    glob, _ = confidence.shrink_field(fixed, at_ref, u, SPACING, 4, HU)
    loc, info = confidence.shrink_field(fixed, at_ref, u, SPACING, 4, HU, moving=moving)
    mean_x = lambda f, m: float(f[0][m].mean())  # noqa: E731
    assert mean_x(glob, right) > 1.5 and mean_x(glob, left) < -2.7     # the global prior keeps both
    assert abs(mean_x(loc, right)) < 0.1 * 2.0                         # the invented field is taken back
    assert mean_x(loc, left) == pytest.approx(mean_x(glob, left), rel=0.05)  # the seen one is kept
    assert 0.0 <= info["mean_prior_scale"] <= 1.0


def test_the_local_prior_scale_is_zero_where_the_field_explains_nothing_and_at_most_one():
    rng = np.random.default_rng(4)
    shape = (6, 10, 12)
    r0 = rng.standard_normal(shape)
    A = np.abs(rng.standard_normal((3, 3) + shape))
    q = confidence.local_prior_scale(r0, r0, A, np.zeros(3), np.ones(3), 3)
    assert np.array_equal(q, np.zeros(shape))
    q = confidence.local_prior_scale(r0 * 100.0, r0, A, np.zeros(3), np.ones(3), 3)
    assert q.max() == 1.0 and q.min() >= 0.0


def test_the_local_prior_is_the_same_bits_for_any_chunk():
    fixed, moving, u, _, _ = _half_moving_pair(seed=5)
    grid = FieldGrid(nx=2 * NX, ny=NY, nz=NZ, voxel_mm=3.0, z0_mm=0.0, dz_mm=4.0)
    f = confidence.normalise(fixed, HU)
    r = f - confidence.normalise(estimate.to_reference(moving, u, grid), HU)
    r0 = f - confidence.normalise(moving, HU)
    vox = np.stack([u[2] / SPACING[2], u[1] / SPACING[1], u[0] / SPACING[0]])
    inside = np.ones(f.shape, bool)
    a, _ = confidence.shrink_voxels(f, r, vox, 4, inside, unregistered=r0)
    b, _ = confidence.shrink_voxels(f, r, vox, 4, inside, chunk=997, unregistered=r0)
    assert np.array_equal(a, b)


def _sym(n, rng, eigenvalues=None):
    """n random symmetric 3 x 3 matrices (n, 3, 3): with ``eigenvalues`` (n, 3) those, in random bases."""
    q, _ = np.linalg.qr(rng.standard_normal((n, 3, 3)))
    w = rng.standard_normal((n, 3)) if eigenvalues is None else np.asarray(eigenvalues, np.float64)
    return np.einsum("nik,nk,njk->nij", q, w, q)


def _upper(a):
    return [a[:, i, j].copy() for i, j in confidence._UPPER]


def _full(c):
    a = np.empty((c[0].shape[0], 3, 3))
    for k, (i, j) in enumerate(confidence._UPPER):
        a[:, i, j] = a[:, j, i] = c[k]
    return a


def _psd_reference(a):
    """The float64 reference: LAPACK's eigen-decomposition with the negative eigenvalues set to 0."""
    w, v = np.linalg.eigh(a)
    return np.einsum("nik,nk,njk->nij", v, np.maximum(w, 0.0), v)


def test_the_closed_form_psd_part_is_lapacks_on_random_and_degenerate_matrices():
    """psd_part against eigh's projection, to 1e-12 of each matrix's norm: random matrices (every
    count of negative eigenvalues) and the cases a closed form gets wrong first -- repeated
    eigenvalues on either side of 0, zeros, a sign change at 1e-18, one matrix of all zeros,
    multiples of the identity, and near-degenerate pairs."""
    rng = np.random.default_rng(7)
    edge = [(-1, -1, 2), (-1, 2, 2), (-2, -2, -2), (0, 0, 0), (3, 3, 3), (-1e-18, 0, 1), (0, 0, -1),
            (1, 1 + 1e-10, -1), (-1, -1 - 1e-10, 1), (1e-300, 2e-300, -1e-300), (5, 0, 0), (-5, 0, 0),
            (1e8, 1, -1e-8)]
    mats = np.concatenate([_sym(4000, rng), _sym(len(edge) * 50, rng, np.repeat(edge, 50, axis=0)),
                           np.zeros((1, 3, 3)), np.eye(3)[None] * -2.0, np.diag([2.0, -1.0, 0.5])[None]])
    got = _full(confidence.psd_part(_upper(mats)))
    ref = _psd_reference(mats)
    norm = np.linalg.norm(mats, axis=(1, 2)) + 1e-300
    err = np.abs(got - ref).max(axis=(1, 2)) / norm
    assert err.max() < 1e-12, (err.max(), mats[np.argmax(err)])
    assert np.linalg.eigvalsh(got).min(axis=1).min() >= -1e-12 * norm.max()


def test_the_closed_form_shrinkage_solve_is_lapacks_with_ridges_over_24_orders():
    """shrink_solve's S v and trace(S) / 3 against numpy.linalg.solve on (a_s + R) S = a_s, with
    positive semi-definite a_s (of every rank) and diagonal ridges from 1e-12 to 1e12 of a_s's
    scale, per axis independently (the local prior's range). Where nothing pins the solution but a
    ridge 1e12 below the texture, every float64 solver errs by about cond(M) eps (M = a_s + R scaled
    to a unit diagonal; LAPACK on the unscaled system differs from LAPACK on the scaled one by up to
    150 cond eps here): both are held to 1000 cond eps of |v| against the scaled LAPACK reference,
    and to 1e-13 where the system is well conditioned (cond < 10)."""
    rng = np.random.default_rng(8)
    n = 6000
    w = np.maximum(rng.standard_normal((n, 3)), 0.0) * 10.0 ** rng.uniform(-3, 1, (n, 1))
    a_s = _sym(n, rng, w)
    ridge = 10.0 ** rng.uniform(-12, 12, (3, n))
    v = rng.standard_normal((3, n))
    out, tr = confidence.shrink_solve(_upper(a_s), list(ridge), v)
    m = a_s + np.einsum("kn,kl->nkl", ridge, np.eye(3))
    d = 1.0 / np.sqrt(np.einsum("nkk->nk", m))
    scaled = d[:, :, None] * m * d[:, None, :]
    s = d[:, :, None] * np.linalg.solve(scaled, d[:, :, None] * a_s)
    ref = np.einsum("nij,jn->in", s, v)
    bound = 1e3 * np.linalg.cond(scaled) * np.finfo(np.float64).eps
    err = np.abs(out - ref).max(axis=0) / np.abs(v).max(axis=0)
    assert (err <= bound).all(), (err / bound).max()
    well = np.linalg.cond(scaled) < 10.0
    assert well.sum() > n // 4 and err[well].max() < 1e-13
    assert (np.abs(tr - np.trace(s, axis1=1, axis2=2) / 3.0) <= bound).all()
    # nothing seen (a_s = 0): all shrunk; no ridge to speak of: the field unchanged
    zero, _ = confidence.shrink_solve([np.zeros(n)] * 6, list(ridge), v)
    assert np.abs(zero).max() == 0.0
    big = _sym(n, rng, np.full((n, 3), 1.0))
    keep, tk = confidence.shrink_solve(_upper(big), [np.full(n, 1e-14)] * 3, v)
    assert np.abs(keep - v).max() < 1e-12 and np.abs(tk - 1.0).max() < 1e-12


def test_the_local_prior_with_a_residual_of_exactly_zero_is_finite_and_keeps_the_field():
    """Identical images (residual and unexplained difference both 0, so c = 0 and q = 0): the ridge
    is the global prior's floor, not 0 / 0 (a NaN field before 2026-12-07); the textured half keeps
    its field as under the global prior."""
    fixed, _, u, left, _ = _half_moving_pair(seed=5)
    loc, info = confidence.shrink_field(fixed, fixed, u, SPACING, 4, HU, moving=fixed)
    glob, _ = confidence.shrink_field(fixed, fixed, u, SPACING, 4, HU)
    assert info["residual_std"] == 0.0 and np.isfinite(loc).all()
    assert np.allclose(loc[:, left], glob[:, left], atol=1e-4)
