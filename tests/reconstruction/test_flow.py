"""The TV-L1 registration (clrecon.reconstruction.motion.flow, kernels/flow.cl).

Each kernel against its float64 NumPy reference on random and edge-case inputs (shapes not
multiples of any work-group size, axes of one and two voxels, anisotropic spacing, fields that
reach past the grid); the whole OpenCL registration against the NumPy composition of the
references; the registration on pairs with known motion (a smooth shift, a smooth deformation);
determinism, the selection through ``[recon.mc] registration`` and bad inputs.
"""

from __future__ import annotations

import numpy as np
import pytest
import scipy.ndimage

from clrecon.reconstruction.motion import flow, registration

# One table for every tolerance in this file: (quantity, why this size).
TOL = {
    # float32 kernel vs float64 reference, max |cl - ref| / max(1, max |ref|): float32 arithmetic on
    # O(1) data, a handful of operations per output (ulp 6e-8; sums of up to ~30 terms)
    "f32": 1e-5,
    # the whole registration (float32 device) vs the float64 NumPy composition of the references:
    # 2 levels x 2 warps x 5 iterations of float32 rounding, mm on a 7 mm field
    "pipeline_mm": 1e-3,
    # recovered displacement (mm) of a smooth known motion in the body's inner half (textured and
    # flat parts): a shift within 0.15 mm per component (measured <= 0.04 with the defaults); a
    # deformation of ~3 mm RMS within the goal for known motion, 0.5 mm RMS (measured 0.45)
    "shift_mm": 0.15,
    "deform_rms_mm": 0.5,
}
RNG = np.random.default_rng(41)
SPACINGS = [(1.0, 1.0, 1.0), (0.7, 0.9, 2.5)]
SHAPES = [(5, 7, 9), (1, 6, 11), (2, 3, 2)]


def _close(got, ref, tol=TOL["f32"]):
    scale = max(1.0, float(np.abs(ref).max()))
    assert np.abs(got - ref).max() <= tol * scale, (np.abs(got - ref).max(), scale)


@pytest.mark.parametrize("shape", SHAPES)
@pytest.mark.parametrize("spacing", SPACINGS)
def test_warp_and_residual_kernels_match_the_references(shape, spacing):
    src = RNG.uniform(0, 1, shape)
    u = RNG.normal(0, 3.0, (3,) + shape)       # reaches past every edge: clamped sampling
    u[:, 0, 0, 0] = 0.0                         # an exact voxel centre
    w = flow.warp_cl(src, u, spacing)
    _close(w, flow.warp_reference(src, u, spacing))
    fixed = RNG.uniform(0, 1, shape)
    _close(flow.residual_cl(w, fixed, u, spacing), flow.residual_reference(w, fixed, u, spacing))


@pytest.mark.parametrize("shape", SHAPES)
@pytest.mark.parametrize("spacing", SPACINGS)
def test_primal_and_dual_kernels_match_the_references(shape, spacing):
    u = RNG.normal(0, 1, (3,) + shape)
    p = RNG.uniform(-0.6, 0.6, (9,) + shape)
    warped = RNG.uniform(0, 1, shape)
    warped[..., :2] = 0.25                       # a flat patch: |grad I| = 0 there, u moves by div p only
    rho0 = RNG.normal(0, 0.3, shape)
    lt, theta = 0.4, 0.3
    _close(flow.primal_cl(u, p, warped, rho0, spacing, lt, theta),
           flow.primal_reference(u, p, warped, rho0, spacing, lt, theta))
    s = 0.25 / sum(1 / h ** 2 for h in spacing) / theta
    for eps in (0.0, 0.1):                      # TV and Huber-TV; |q| > 1 (projected) and < 1 both occur
        _close(flow.dual_cl(u, p, spacing, s, eps), flow.dual_reference(u, p, spacing, s, eps))


def test_primal_thresholding_takes_all_three_branches():
    """rho below, inside and above +-lt |g|^2 at one voxel each: the reference's three cases."""
    shape = (1, 1, 3)
    warped = np.array([[[0.0, 1.0, 2.0]]])      # grad_x = 1 everywhere (one-sided at the ends)
    u = np.zeros((3,) + shape)
    p = np.zeros((9,) + shape)
    rho0 = np.array([[[-2.0, 0.1, 2.0]]])
    got = flow.primal_cl(u, p, warped, rho0, (1.0, 1.0, 1.0), 0.5, 0.3)
    assert np.allclose(got[0, 0, 0], [0.5, -0.1, -0.5], atol=1e-6)
    _close(got, flow.primal_reference(u, p, warped, rho0, (1.0, 1.0, 1.0), 0.5, 0.3))


def test_divergence_is_minus_the_adjoint_of_the_gradient():
    shape, spacing = (4, 5, 6), (0.7, 0.9, 2.5)
    f, q = RNG.normal(size=shape), RNG.normal(size=(3,) + shape)
    lhs = (flow.forward_gradient_reference(f, spacing) * q).sum()
    assert np.isclose(lhs, -(f * flow.divergence_reference(q, spacing)).sum(), rtol=1e-12)


@pytest.mark.parametrize("src_shape,dst_shape", [((6, 20, 18), (3, 10, 9)), ((3, 10, 9), (6, 20, 18)),
                                                 ((1, 8, 8), (1, 5, 3)), ((5, 7, 9), (5, 7, 9))])
@pytest.mark.parametrize("batch", [1, 3])
def test_resample_kernel_matches_the_reference(src_shape, dst_shape, batch):
    src = RNG.normal(size=(batch,) + src_shape)
    got = flow.resample_cl(src, dst_shape)
    ref = flow.resample_reference(src, dst_shape)
    _close(got, ref)
    if src_shape == dst_shape:
        assert np.allclose(got, src, atol=1e-6)  # the identity grid


def test_pyramid_levels():
    cfg = flow.TVL1Config(levels=5, min_size=16)
    assert flow.level_shapes((110, 512, 512), (1.0, 1.0, 1.0), cfg) == [
        (110, 512, 512), (55, 256, 256), (28, 128, 128), (14, 64, 64), (7, 32, 32)]
    # demo: 3 mm in-plane, 4 mm slices: z waits until the level's voxels pass 4 mm
    assert flow.level_shapes((16, 128, 128), (3.0, 3.0, 4.0), cfg) == [
        (16, 128, 128), (11, 64, 64), (5, 32, 32), (3, 16, 16)]
    assert flow.level_shapes((4, 20, 20), (1.0, 1.0, 1.0), flow.TVL1Config(levels=1)) == [(4, 20, 20)]
    assert flow.smoothing_sigmas((16, 128, 128), (16, 64, 64))[0] == 0.0


def _smooth_blobs(shape, spacing, centre_shift=(0.0, 0.0, 0.0), field=None):
    """A textured, band-limited volume (ellipsoids of several HU, blurred by one voxel), optionally
    its points moved by ``centre_shift`` (mm) or sampled at x - field(x)."""
    nz, ny, nx = shape
    hx, hy, hz = spacing
    z, y, x = np.meshgrid((np.arange(nz) - (nz - 1) / 2) * hz, (np.arange(ny) - (ny - 1) / 2) * hy,
                          (np.arange(nx) - (nx - 1) / 2) * hx, indexing="ij")
    if field is not None:
        x, y, z = x - field[0], y - field[1], z - field[2]
    x, y, z = x - centre_shift[0], y - centre_shift[1], z - centre_shift[2]
    out = np.full(shape, -800.0)
    rng = np.random.default_rng(7)
    out[(x / 34) ** 2 + (y / 26) ** 2 + (z / 22) ** 2 <= 1] = 40.0
    for _ in range(14):  # texture: small blobs of other densities inside the body
        c = rng.uniform(-18, 18, 3) * (1.0, 0.8, 0.6)
        r = rng.uniform(3, 7, 3)
        out[((x - c[0]) / r[0]) ** 2 + ((y - c[1]) / r[1]) ** 2 + ((z - c[2]) / r[2]) ** 2 <= 1] = rng.uniform(-200,
                                                                                                               400)
    out = scipy.ndimage.gaussian_filter(out, 1.0)
    return out.astype(np.float32), (x, y, z)


def test_registration_recovers_a_smooth_shift_and_is_deterministic():
    shape, spacing = (20, 48, 48), (2.0, 2.0, 2.5)
    want = (3.4, -2.2, 2.9)
    fixed, (x, y, z) = _smooth_blobs(shape, spacing)
    moving, _ = _smooth_blobs(shape, spacing, centre_shift=want)
    cfg = flow.TVL1Config()
    u = registration.register(fixed, moving, spacing, cfg=cfg)
    assert u.shape == (3,) + shape and u.dtype == np.float32
    core = (x / 34) ** 2 + (y / 26) ** 2 + (z / 22) ** 2 <= 0.5
    med = np.array([float(np.median(u[k][core])) for k in range(3)])
    assert np.allclose(med, want, atol=TOL["shift_mm"]), med
    assert np.array_equal(u, registration.register(fixed, moving, spacing, cfg=cfg))


def test_registration_recovers_a_smooth_deformation():
    """moving(x) = fixed(x - d(x)) with a smooth d of up to ~4 mm: u(x) ~ d(x + u(x)) ~ d(x)."""
    shape, spacing = (20, 48, 48), (2.0, 2.0, 2.5)
    nz, ny, nx = shape
    z, y, x = np.meshgrid((np.arange(nz) - (nz - 1) / 2) * 2.5, (np.arange(ny) - (ny - 1) / 2) * 2.0,
                          (np.arange(nx) - (nx - 1) / 2) * 2.0, indexing="ij")
    d = np.stack([3.0 * np.exp(-(x ** 2 + y ** 2 + z ** 2) / (2 * 20.0 ** 2)),
                  -2.0 * np.cos(x / 30.0),
                  2.5 * np.exp(-((y - 5) ** 2) / (2 * 25.0 ** 2))])
    fixed, _ = _smooth_blobs(shape, spacing)
    moving, _ = _smooth_blobs(shape, spacing, field=d)
    u = flow.register_tvl1(fixed, moving, spacing)
    # u solves moving(x + u) = fixed(x): x + u - d(x + u) = x, so u(x) = d(x + u(x))
    pts = np.stack([x, y, z]) + u
    d_at = np.stack([3.0 * np.exp(-(pts[0] ** 2 + pts[1] ** 2 + pts[2] ** 2) / (2 * 20.0 ** 2)),
                     -2.0 * np.cos(pts[0] / 30.0), 2.5 * np.exp(-((pts[1] - 5) ** 2) / (2 * 25.0 ** 2))])
    core = (x / 34) ** 2 + (y / 26) ** 2 + (z / 22) ** 2 <= 0.5
    err = np.sqrt(((u - d_at) ** 2).sum(0))[core]
    motion = np.sqrt((d ** 2).sum(0))[core]
    rms = float(np.sqrt((err ** 2).mean()))
    assert np.sqrt((motion ** 2).mean()) > 2.0  # the motion is several times the tolerance
    assert rms <= TOL["deform_rms_mm"], rms


def test_opencl_registration_matches_the_numpy_reference():
    shape, spacing = (6, 20, 18), (2.0, 2.0, 3.0)
    fixed, _ = _smooth_blobs(shape, spacing)
    moving, _ = _smooth_blobs(shape, spacing, centre_shift=(2.5, -1.5, 2.0))
    cfg = flow.TVL1Config(warps=2, iterations=5, levels=2, min_size=8)
    assert len(flow.level_shapes(shape, spacing, cfg)) == 2
    ref = flow.register_reference(fixed, moving, spacing, cfg)
    got = flow.register_tvl1(fixed, moving, spacing, cfg)
    assert np.abs(ref).max() > 1.0  # it moved
    assert np.abs(got - ref).max() <= TOL["pipeline_mm"], np.abs(got - ref).max()


def test_bad_inputs_are_refused_in_one_line():
    vol = np.zeros((4, 8, 8), np.float32)
    with pytest.raises(ValueError, match="one shape"):
        flow.register_tvl1(vol, vol[:-1], (1.0, 1.0, 1.0))
    with pytest.raises(ValueError, match="spacing"):
        flow.register_tvl1(vol, vol, (1.0, -1.0, 1.0))
    with pytest.raises(ValueError, match="finite"):
        flow.register_tvl1(vol, np.full_like(vol, np.nan), (1.0, 1.0, 1.0))
    with pytest.raises(ValueError, match="at least 2 voxels"):
        flow.register_tvl1(vol[:, :1], vol[:, :1], (1.0, 1.0, 1.0))
    with pytest.raises(ValueError, match="lam"):
        flow.TVL1Config(lam=0.0)
    with pytest.raises(ValueError, match="tau"):
        flow.TVL1Config(tau=0.9)
    with pytest.raises(ValueError, match="warps"):
        flow.TVL1Config(warps=0)
    with pytest.raises(ValueError, match="starts from zero"):
        registration.register(vol, vol, (1.0, 1.0, 1.0), cfg=flow.TVL1Config(), initial=np.zeros((3,) + vol.shape))


def test_recon_mc_registration_selects_the_method():
    from clrecon.config.overrides import load_scene
    from clrecon.core.errors import SceneError
    from clrecon.reconstruction.motion import lk, method

    assert isinstance(method.flow_of(load_scene("demo").recon.mc), lk.LKConfig)  # the default (breathing)
    assert isinstance(method.flow_of(load_scene("demo", recon__mc__registration="lucas_kanade").recon.mc),
                      registration.FlowConfig)
    assert isinstance(method.flow_of(load_scene("demo", recon__mc__registration="tvl1").recon.mc), flow.TVL1Config)
    assert isinstance(method.flow_of(load_scene("demo", recon__mc__registration="tvl1").recon.mc, "beat"),
                      flow.TVL1Config)
    with pytest.raises(SceneError, match="recon.mc.registration = 'tv': must be one of "
                       "lucas_kanade, tvl1, lucas_kanade_cl"):
        load_scene("demo", recon__mc__registration="tv")


def test_separable_fields_with_tvl1_ignore_the_process_pool():
    """TV-L1 runs in the caller's process (OpenCL uses every core): a pool passed in is not used."""
    from clrecon.reconstruction.motion import estimate
    from clrecon.reconstruction.motion.model import FieldGrid

    class Refuses:
        def submit(self, *a, **k):
            raise AssertionError("the pool was used")

    shape, spacing = (8, 24, 24), (3.0, 3.0, 4.0)
    vols = np.stack([np.stack([_smooth_blobs(shape, spacing, centre_shift=(cx, 0.0, rz))[0] for rz in (-3.0, 0.0)])
                     for cx in (0.0, 3.0)])
    grid = FieldGrid(nx=24, ny=24, nz=8, voxel_mm=3.0, z0_mm=-14.0, dz_mm=4.0)
    fields, _ = estimate.separable_fields(vols, (0, 1), grid, flow.TVL1Config(), pool=Refuses())
    assert fields.shape == (4, 3) + shape and np.abs(fields).max() > 1.0
