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
