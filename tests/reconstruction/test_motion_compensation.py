"""Motion-model building blocks (clrecon.reconstruction.motion, docs/motion-model.md).

Kernels against their float64 NumPy references on random and edge-case inputs
(``kernels/mc_backproject.cl``; the study's ``benchmarks/studies/motion-model/mc_warp.cl``); the
motion-compensated backprojection with no motion against the fan-beam FBP's own backprojector;
the model fit, its inversion, the row weights, the study's state bins, the registration wrapper
(Lucas-Kanade, and the study's SimpleITK demons plugged in) on shifted blobs, the separable
estimate, and the analytic phantom's true motion.
"""

from __future__ import annotations

import dataclasses
import os

import numpy as np
import pytest
import scipy.ndimage
from motion_study import correction, demons, registration_memory, warp

from clrecon.bench import reference_kernels
from clrecon.core.resources import spawned_pool
from clrecon.core.runtime import HOST_ALIGN_BYTES
from clrecon.reconstruction.config import MotionCompensationConfig
from clrecon.reconstruction.fbp import FanBeamGeometry, backproject
from clrecon.reconstruction.motion import confidence, estimate, memory, registration, slots
from clrecon.reconstruction.motion import method as mcm
from clrecon.reconstruction.motion import model as motion_model
from clrecon.reconstruction.motion.backproject import (
    MCBackprojector,
    MCConfig,
    ModelWindow,
    PlaneRows,
    displacement_margin_mm,
    mc_backproject,
    mc_backproject_reference,
    plane_range,
)
from clrecon.reconstruction.motion.model import (
    FieldGrid,
    MotionBasis,
    MotionModel,
    fit_motion_model,
    fit_separable_model,
    sample,
)
from clrecon.reconstruction.rebin import CandidateGroups
from clrecon.simulation.phantoms import motion_field
from clrecon.simulation.phantoms.analytic import Phantom

# One table for every tolerance in this file: (quantity, why this size).
TOL = {
    # float32 kernel vs float64 reference, max |cl - ref| / max |ref|: float32 columns and plane
    # coordinates (ulp ~ 1e-5 of a cell) times O(1) jumps of random rows, over the views
    "mc_f32": 2e-5,
    # the same for the warp: float32 fixed-point steps through random smooth fields
    "warp_f32": 2e-5,
    # the kernel (8 voxels per work-item in float8 lanes) vs the scalar kernel it replaced
    # (kernels/reference/), max |new - old| / max |old|: the same float32 operations per voxel in
    # the same order, but the compilers contract different products into FMAs (measured 4e-6 on
    # Intel's runtime, 9e-6 on PoCL, on demo's geometry: benchmarks/mc_backproject.py)
    "lanes_vs_scalar": 2e-5,
    # no motion, one row per view at its own plane vs the fan-beam backprojector (same float32
    # geometry, different order of operations)
    "static_vs_fbp": 1e-5,
    # least-squares fit of fields made exactly from the basis (float32 fields, float64 solve)
    "fit_rel": 1e-5,
    # fixed-point inversion of smooth fields (|grad u| < 0.3): residual, mm
    "inverse_mm": 1e-3,
    # Lucas-Kanade flow on a (4, -3, 4) mm-shifted ellipsoid, median over its interior, mm
    "flow_mm": 0.5,
    # demons on the same: it creeps (measured 2.3-3.0 of 4 mm in x after 80 + 40 iterations,
    # docs/results/mc-study.md "Registration"), so only the share of the shift it must recover
    "demons_share": 0.5,
}

RNG = np.random.default_rng(34)


def _smooth_model(basis, grid, scale_mm, seed=0):
    rng = np.random.default_rng(seed)
    f = scipy.ndimage.gaussian_filter(rng.normal(size=(basis.size, 3) + grid.shape), (0, 0, 1, 2, 2))
    f *= scale_mm / np.abs(f).max()
    return MotionModel(basis=basis, grid=grid, fields=f.astype(np.float32), reference=(0.5, 0.5))


def _random_case(detector="flat", source_shifts=(), seed=1, nx=13):
    rng = np.random.default_rng(seed)
    geom = FanBeamGeometry(sid_mm=500.0, sdd_mm=900.0, n_cols=40, col_pitch_mm=4.0, n_views=12, nx=nx, ny=11,
                           voxel_mm=6.0, detector=detector, source_shifts=source_shifts, beta0_rad=0.2)
    basis = MotionBasis(resp_degree=1, cardiac_harmonics=1)
    grid = FieldGrid(nx=nx, ny=11, nz=4, voxel_mm=6.0, z0_mm=-9.0, dz_mm=6.0)
    model = MotionModel(basis=basis, grid=grid, fields=(rng.normal(size=(basis.size, 3) + grid.shape) * 2)
                        .astype(np.float32), reference=(0.5, 0.5))
    P, NP = 30, 9
    rows = PlaneRows(rows=rng.normal(size=(P, NP, geom.n_cols)).astype(np.float32),
                     plane_first=rng.integers(-12, -2, P).astype(np.int32),
                     plane_count=rng.integers(1, NP + 1, P).astype(np.int32),   # a count of 1: one plane
                     projection=np.arange(P), proj_z_mm=rng.uniform(-10, 10, P), plane_dz_mm=2.0, window_mm=7.0)
    S, K = 3, 4
    sp = rng.integers(0, P, (S, geom.n_views, K)).astype(np.int32)
    sp[:, :, 3] = -1          # empty slots at the end of every list
    sp[0, 0, 1:] = -1         # a view with one slot
    sw = rng.uniform(0, 1, sp.shape).astype(np.float32)
    sw[1, 2, 0] = 0.0         # a zero weight
    pb = basis.values(rng.uniform(0, 1, P), rng.uniform(0, 1, P))
    zs = np.array([-8.0, 0.5, 7.0])
    return geom, model, rows, pb, sp, sw, zs


# ---------------------------------------------------------------------------------------
# the motion-compensated backprojection kernel
@pytest.mark.parametrize("detector, shifts", [("flat", ()), ("cylindrical", ()),
                                              ("cylindrical", ((0.002, 0.6), (-0.002, -0.6)))])
def test_mc_backproject_matches_reference(detector, shifts):
    geom, model, rows, pb, sp, sw, zs = _random_case(detector, shifts)
    cfg = MCConfig(taper_mm=3.0)
    got = mc_backproject(rows, pb, sp, sw, model, (0.3, 0.6), zs, geom, cfg)
    ref = mc_backproject_reference(rows, pb, sp, sw, model, (0.3, 0.6), zs, geom, cfg)
    assert got.shape == (3, geom.ny, geom.nx) and got.dtype == np.float32
    assert np.abs(got - ref).max() < TOL["mc_f32"] * np.abs(ref).max()
    assert np.all(got[:, ~geom.fov_mask()] == 0)


def _new_old_ref(geom, model, rows, pb, sp, sw, zs, target=(0.3, 0.6), cfg=None):
    """The kernel, the scalar reference kernel (same buffers) and the float64 reference."""
    with MCBackprojector(rows, pb, model, zs, geom, cfg) as bp:
        new = bp(sp, sw, target)
        old = reference_kernels.mc_backproject_scalar(bp, sp, sw, target)
    return new, old, mc_backproject_reference(rows, pb, sp, sw, model, target, zs, geom, cfg)


def _assert_close(new, old, ref, geom):
    scale = np.abs(ref).max()
    assert scale > 0
    assert np.abs(new - old).max() <= TOL["lanes_vs_scalar"] * np.abs(old).max()
    assert np.abs(new - ref).max() < TOL["mc_f32"] * scale
    assert np.abs(old - ref).max() < TOL["mc_f32"] * scale
    outside = ~geom.fov_mask()
    assert np.all(new[:, outside] == 0) and np.all(old[:, outside] == 0)


@pytest.mark.parametrize("nx", [5, 8, 13, 17])
@pytest.mark.parametrize("detector", ["flat", "cylindrical"])
def test_mc_backproject_lanes_match_scalar_kernel_and_reference(nx, detector):
    """nx below, at and not a multiple of the 8 lanes (the last work-item's lanes past nx are
    not stored), voxels outside the FOV (0 in both kernels), empty slots, one-plane projections."""
    geom, model, rows, pb, sp, sw, zs = _random_case(detector, nx=nx, seed=nx)
    sw[2, 5] = 0.0            # a view whose weights are all 0: adds 0
    sw[0, 3, 1] = 0.0         # a zero weight beside non-zero ones
    new, old, ref = _new_old_ref(geom, model, rows, pb, sp, sw, zs, cfg=MCConfig(taper_mm=3.0))
    assert new.shape == (3, geom.ny, nx) and new.dtype == np.float32
    assert (~geom.fov_mask()).any() == (nx >= 13)   # the corners leave the FOV circle from nx = 13
    _assert_close(new, old, ref, geom)


@pytest.mark.parametrize("lanes", [8, 16])
def test_mc_backproject_either_lane_count(monkeypatch, lanes):
    """Both builds of the kernel (LANES = 8 or 16; which one a device gets: ``lanes_for``) give the
    scalar kernel's result up to contraction, and each other's."""
    import clrecon.reconstruction.motion.backproject as mcb

    geom, model, rows, pb, sp, sw, zs = _random_case("cylindrical", nx=13)   # 3 or 5 lanes past nx
    monkeypatch.setattr(mcb, "LANES", lanes)
    got, old, ref = _new_old_ref(geom, model, rows, pb, sp, sw, zs)
    _assert_close(got, old, ref, geom)
    monkeypatch.setattr(mcb, "LANES", 24 - lanes)
    other, _, _ = _new_old_ref(geom, model, rows, pb, sp, sw, zs)
    assert np.abs(got - other).max() <= TOL["lanes_vs_scalar"] * np.abs(other).max()


def test_lanes_follow_the_device_vector_width():
    from types import SimpleNamespace

    import clrecon.reconstruction.motion.backproject as mcb

    assert mcb.lanes_for(SimpleNamespace(native_vector_width_float=16)) == 16
    assert mcb.lanes_for(SimpleNamespace(native_vector_width_float=8)) == 8
    assert mcb.lanes_for(SimpleNamespace(native_vector_width_float=1)) == 8   # Oclgrind
    assert mcb.lanes_for(object()) == 8


@pytest.mark.parametrize("nx", [13, 150])
def test_mc_backproject_launch_shape_changes_no_bit(monkeypatch, nx):
    """The work-group shape and the views per barrier chunk (``launch_shape``: Intel's runtime gets
    a larger tile) decide which work-item computes a voxel, never how: the same bits for every
    shape, tiles past the image's edges included (150 voxels: two 128-wide tiles), and the scalar
    kernel's values up to contraction. Against the float64 reference only at nx = 13 (the tolerance
    of the tests above): at nx = 150 the voxels sit half a voxel off those, and 5 of them differ from
    float64 by up to 1.0e-4 of the maximum, in the scalar kernel as in this one (float32 fixed-point
    steps through these rough random fields), so the scalar kernel is the check there."""
    import clrecon.reconstruction.motion.backproject as mcb

    geom, model, rows, pb, sp, sw, zs = _random_case("flat", nx=nx)
    got = {}
    for shape in [((1, 8), 8), (mcb.INTEL_LOCAL_SIZE, mcb.INTEL_VIEW_CHUNK), ((2, 4), 5)]:
        monkeypatch.setattr(mcb, "launch_shape", lambda device, shape=shape: shape)
        with MCBackprojector(rows, pb, model, zs, geom) as bp:
            assert (bp.local_size, bp.view_chunk) == shape
            got[shape] = bp(sp, sw, (0.3, 0.6))
            old = reference_kernels.mc_backproject_scalar(bp, sp, sw, (0.3, 0.6))
    first = next(iter(got.values()))
    for img in got.values():
        assert np.array_equal(img, first)
    assert np.abs(first - old).max() <= TOL["lanes_vs_scalar"] * np.abs(old).max()
    if nx == 13:
        ref = mc_backproject_reference(rows, pb, sp, sw, model, (0.3, 0.6), zs, geom)
        assert np.abs(first - ref).max() < TOL["mc_f32"] * np.abs(ref).max()


def test_mc_backproject_reads_aligned_rows_and_fields_in_place():
    """On a CPU device the plane rows and the model's fields, page-aligned float32 (what
    ``method.slab_rows`` and ``method.refine`` make), are read where they lie (``CL_MEM_USE_HOST_PTR``,
    no device copy in host memory); unaligned ones are copied. The same bits either way."""
    from clrecon.core.runtime import aligned_empty, get_runtime

    geom, model, rows, pb, sp, sw, zs = _random_case("flat", nx=13)

    def aligned(a):
        out = aligned_empty(a.shape, np.float32)
        out[...] = a
        return out

    rt = get_runtime()
    shared, copied = [], []
    real_share, real_copy = rt.share_with_device, rt.to_device
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(rt, "share_with_device", lambda a, name="array", dtype=np.float32: (
            shared.append(name), real_share(a, name, dtype))[1])
        mp.setattr(rt, "to_device", lambda a, dtype=np.float32, name="array": (
            copied.append(name), real_copy(a, dtype, name))[1])
        with MCBackprojector(rows, pb, model, zs, geom, runtime=rt) as bp:
            plain = bp(sp, sw, (0.3, 0.6))
        in_place = dataclasses.replace(rows, rows=aligned(rows.rows))
        model_in_place = dataclasses.replace(model, fields=aligned(model.fields))
        copied.clear()
        with MCBackprojector(in_place, pb, model_in_place, zs, geom, runtime=rt) as bp:
            got = bp(sp, sw, (0.3, 0.6))
    assert {"plane rows", "model fields"} <= set(shared)
    if rt.is_cpu:  # read in place: not copied
        assert not {"plane rows", "model fields"} & set(copied)
    assert np.array_equal(got, plain)


def test_launch_shape_follows_the_driver():
    from types import SimpleNamespace

    import clrecon.reconstruction.motion.backproject as mcb

    def dev(name):
        return SimpleNamespace(platform=SimpleNamespace(name=name))

    assert mcb.launch_shape(dev("Intel(R) OpenCL")) == (mcb.INTEL_LOCAL_SIZE, mcb.INTEL_VIEW_CHUNK)
    assert mcb.launch_shape(dev("Portable Computing Language")) == (mcb.LOCAL_SIZE, mcb.VIEW_CHUNK)
    assert mcb.launch_shape(dev("Oclgrind")) == (mcb.LOCAL_SIZE, mcb.VIEW_CHUNK)
    assert mcb.launch_shape(object()) == (mcb.LOCAL_SIZE, mcb.VIEW_CHUNK)


def test_mc_backproject_lanes_at_the_window_edge():
    """Rows whose moved SSRB distance crosses the taper and the window within one work-item's
    8 voxels: some lanes take the weighted mean, others the nearest slot's fallback."""
    geom, model, rows, pb, sp, sw, zs = _random_case(nx=17, seed=5)
    # a z field varying along x by +-1.5 mm and every row 0.5 mm inside the window from slice 1:
    # the amplitude term's coefficient B_1(row) - B_1(target) lies in [-0.6, 0.4], so the moved
    # distances span window - 1.4 .. window + 0.4 mm and the 1-mm taper is 1, partial and 0
    f = np.zeros_like(model.fields)
    x = np.linspace(-1.5, 1.5, geom.nx, dtype=np.float32)
    f[1, 2] = x[None, None, :]
    model = dataclasses.replace(model, fields=f)
    edge = dataclasses.replace(rows, proj_z_mm=np.full(rows.proj_z_mm.shape, zs[1] + rows.window_mm - 0.5))
    new, old, ref = _new_old_ref(geom, model, edge, pb, sp, sw, zs, target=(0.3, 0.6), cfg=MCConfig(taper_mm=1.0))
    _assert_close(new, old, ref, geom)
    # both branches were taken within a row of slice 1: compare with no displacement at all
    still = dataclasses.replace(model, fields=np.zeros_like(f))
    n0, _, _ = _new_old_ref(geom, still, edge, pb, sp, sw, zs, cfg=MCConfig(taper_mm=1.0))
    assert np.abs(new[1] - n0[1]).max() > 0


def test_mc_backproject_fallback_when_every_taper_is_zero():
    """Rows farther than the SSRB window from every moved point: the slot nearest in z alone."""
    geom, model, rows, pb, sp, sw, zs = _random_case()
    far = dataclasses.replace(rows, proj_z_mm=rows.proj_z_mm + 100.0)
    got = mc_backproject(far, pb, sp, sw, model, (0.3, 0.6), zs, geom)
    ref = mc_backproject_reference(far, pb, sp, sw, model, (0.3, 0.6), zs, geom)
    assert np.abs(got - ref).max() < TOL["mc_f32"] * np.abs(ref).max()
    assert np.abs(ref).max() > 0


def _refine_case(detector, slab_z, f=2):
    """A model on a 7 x 6 x 20 grid (dz 2 mm, z -19 .. 19 mm) with smooth fields of 0.8 mm, to be
    refined ``f`` times in-plane onto ``geom`` (1: the same grid), and random rows for a slab at ``slab_z``."""
    geom, _, rows, pb, sp, sw, _ = _random_case(detector, nx=7 * f, seed=5)
    geom = dataclasses.replace(geom, ny=6 * f, voxel_mm=6.0 / f)
    basis = MotionBasis(resp_degree=1, cardiac_harmonics=1)
    coarse = FieldGrid(nx=7, ny=6, nz=20, voxel_mm=6.0, z0_mm=-19.0, dz_mm=2.0)
    model = _smooth_model(basis, coarse, 0.8, seed=3)
    S = len(slab_z)
    return geom, model, rows, pb, sp[:S], sw[:S], np.asarray(slab_z, np.float64)


@pytest.mark.parametrize("detector", ["flat", "cylindrical"])
@pytest.mark.parametrize("slab_z", [[-1.0, 1.0], [17.5, 20.5]])  # mid-model; past its last plane (clamped)
@pytest.mark.parametrize("f", [1, 2])                           # the model's own grid; refined 2x in-plane
def test_refining_a_slabs_planes_is_the_same_bits_as_every_plane(detector, slab_z, f):
    geom, model, rows, pb, sp, sw, zs = _refine_case(detector, slab_z, f)
    pairs = np.array([(0.3, 0.6), (0.9, 0.05), (0.55, 1.0)])
    whole = mcm.refine(model, geom)
    assert (whole is model) == (f == 1)
    win = mcm.refine(model, geom, zs, pairs)
    assert isinstance(win, ModelWindow) and win.whole == whole.grid
    k0, k1 = win.first, win.first + win.model.grid.nz
    assert 0 < k1 - k0 < model.grid.nz / 2                  # a strict subset
    if slab_z[0] < 0:
        assert k0 > 0 and k1 < model.grid.nz                # cut on both sides
    assert np.array_equal(win.model.fields, whole.fields[:, :, k0:k1])
    assert win.model.fields.ctypes.data % HOST_ALIGN_BYTES == 0  # read in place on a CPU device
    reach = mcm.reach_mm(model, pairs)  # bounds every target's z field on the refined grid, and not loosely
    worst = max(float(np.abs(whole.displacement(*t)[2]).max()) for t in pairs)
    assert worst <= reach < 1.01 * worst
    for tgt in pairs:
        a = mc_backproject(rows, pb, sp, sw, whole, tuple(tgt), zs, geom)
        b = mc_backproject(rows, pb, sp, sw, win, tuple(tgt), zs, geom)
        assert np.array_equal(a, b), np.abs(a - b).max()
        ref = mc_backproject_reference(rows, pb, sp, sw, win, tuple(tgt), zs, geom)
        assert np.abs(b - ref).max() < TOL["mc_f32"] * np.abs(ref).max()


def test_a_window_narrower_than_the_reach_changes_the_images():
    """The window's bound matters: planes cut to the slab's own (reach 0) read other field values."""
    geom, model, rows, pb, sp, sw, zs = _refine_case("flat", [-1.0, 1.0])
    pairs = np.array([(0.3, 0.6), (0.9, 0.05)])
    whole = mcm.refine(model, geom)
    assert mcm.reach_mm(model, pairs) > 0.5
    k0, k1 = mcm.reach_planes(whole.grid, zs, 0.0)
    k0, k1 = k0 + 1, k1 - 1                                  # no rounding plane either
    held = dataclasses.replace(whole.grid, nz=k1 - k0, z0_mm=float(whole.grid.coords()[2][k0]))
    narrow = ModelWindow(model=MotionModel(basis=model.basis, grid=held, fields=whole.fields[:, :, k0:k1].copy(),
                                           reference=model.reference), whole=whole.grid, first=k0, margin_mm=0.0)
    a = mc_backproject_reference(rows, pb, sp, sw, whole, (0.9, 0.05), zs, geom)
    b = mc_backproject_reference(rows, pb, sp, sw, narrow, (0.9, 0.05), zs, geom)
    assert not np.array_equal(a, b)


def test_the_displacement_margin_plane_by_plane_is_the_whole_fields_one():
    """The curved kernel's build reads the margin: a plane at a time it is the same float as over the
    whole fields at once (the sum over b runs in the same order per voxel)."""
    f = (np.random.default_rng(8).normal(size=(7, 3, 9, 13, 11)) * 3).astype(np.float32)
    assert displacement_margin_mm(f) == float(np.abs(f[1:]).sum(axis=0).max()) * 2.0
    assert displacement_margin_mm(f[:1]) == 0.0


def test_reach_planes_bound_the_slab_and_clamp_to_the_grid():
    g = FieldGrid(nx=4, ny=4, nz=12, voxel_mm=1.0, z0_mm=-11.0, dz_mm=2.0)
    assert mcm.reach_planes(g, [-1.0, 1.0], 3.0) == (2, 10)     # planes of z -7 .. 7 read and 1 more each side
    assert mcm.reach_planes(g, [-1.0, 1.0], 100.0) == (0, 12)
    assert mcm.reach_planes(g, [30.0, 40.0], 1.0) == (10, 12)   # past the last plane: the clamp's two
    assert mcm.reach_planes(g, [-40.0, -30.0], 1.0) == (0, 2)
    with pytest.raises(ValueError, match="first"):
        ModelWindow(model=_smooth_model(MotionBasis(), dataclasses.replace(g, nz=3), 1.0), whole=g, first=10,
                    margin_mm=0.0)


def test_mc_backproject_is_slab_independent():
    geom, model, rows, pb, sp, sw, zs = _random_case()
    whole = mc_backproject(rows, pb, sp, sw, model, (0.7, 0.2), zs, geom)
    for s in range(len(zs)):
        one = mc_backproject(rows, pb, sp[s:s + 1], sw[s:s + 1], model, (0.7, 0.2), zs[s:s + 1], geom)
        assert np.array_equal(one[0], whole[s])


@pytest.mark.parametrize("detector", ["flat", "cylindrical"])
def test_mc_backproject_without_motion_is_the_fan_beam_backprojection(detector):
    """Zero fields, one row per view lying on the slice's own plane: the FBP's backprojector."""
    geom = FanBeamGeometry(sid_mm=300.0, sdd_mm=600.0, n_cols=48, col_pitch_mm=3.0, n_views=30, nx=20, ny=17,
                           voxel_mm=4.0, detector=detector)
    basis = MotionBasis(resp_degree=1, cardiac_harmonics=2)
    grid = FieldGrid(nx=20, ny=17, nz=3, voxel_mm=4.0, z0_mm=-4.0, dz_mm=4.0)
    model = MotionModel(basis=basis, grid=grid, fields=np.zeros((basis.size, 3) + grid.shape, np.float32),
                        reference=(0.0, 0.5))
    q = RNG.normal(size=(geom.n_views, geom.n_cols)).astype(np.float32)
    # projection j holds the row of view j on the plane z = 2 mm (plane 1 of 3 at 1 mm spacing)
    rows = PlaneRows(rows=np.repeat(q[:, None, :], 3, axis=1), plane_first=np.ones(geom.n_views, np.int32),
                     plane_count=np.full(geom.n_views, 3, np.int32), projection=np.arange(geom.n_views),
                     proj_z_mm=np.full(geom.n_views, 2.0), plane_dz_mm=1.0, window_mm=5.0)
    sp = np.arange(geom.n_views, dtype=np.int32).reshape(1, -1, 1)
    sw = np.ones(sp.shape, np.float32)
    pb = basis.values(RNG.uniform(0, 1, geom.n_views), RNG.uniform(0, 1, geom.n_views))
    got = mc_backproject(rows, pb, sp, sw, model, (0.4, 0.1), np.array([2.0]), geom)
    want = backproject(q[None], geom)
    assert np.abs(got - want).max() < TOL["static_vs_fbp"] * np.abs(want).max()


def test_mc_backproject_rejects_bad_inputs():
    geom, model, rows, pb, sp, sw, zs = _random_case()
    with pytest.raises(ValueError, match="slot_proj"):
        mc_backproject(rows, pb, sp[:, :5], sw[:, :5], model, (0.3, 0.6), zs, geom)
    with pytest.raises(ValueError, match="slot_w"):
        mc_backproject(rows, pb, sp, -sw, model, (0.3, 0.6), zs, geom)
    bad = np.where(sp >= 0, sp + 100, sp)
    with pytest.raises(ValueError, match=r"\[-1, 30\)"):
        mc_backproject(rows, pb, bad, sw, model, (0.3, 0.6), zs, geom)
    with pytest.raises(ValueError, match="in-plane grid"):
        mc_backproject(rows, pb, sp, sw, model, (0.3, 0.6), zs, dataclasses.replace(geom, nx=14))
    with pytest.raises(ValueError, match="proj_basis"):
        MCBackprojector(rows, pb[:, :2], model, zs, geom)
    with pytest.raises(ValueError, match="taper_mm"):
        MCConfig(taper_mm=0.0)


def test_plane_range_keeps_the_window_and_the_slab():
    first, count = plane_range([0.0, 10.0], window_mm=5.0, plane_dz_mm=2.0, z_lo_mm=-100.0, z_hi_mm=100.0)
    assert first.tolist() == [-3, 2] and count.tolist() == [7, 7]          # |z_g - z_k| <= 5 + 2
    first, count = plane_range([0.0], 5.0, 2.0, z_lo_mm=1.0, z_hi_mm=3.0)
    assert first.tolist() == [1] and count.tolist() == [1]                 # only z = 2 inside [1, 3]


def test_plane_rows_local_index():
    rows = PlaneRows(rows=np.zeros((3, 1, 4), np.float32), plane_first=np.zeros(3, np.int32),
                     plane_count=np.ones(3, np.int32), projection=np.array([5, 9, 12]), proj_z_mm=np.zeros(3),
                     plane_dz_mm=1.0, window_mm=1.0)
    assert rows.local_index([[12, -1], [5, 9]]).tolist() == [[2, -1], [0, 1]]
    with pytest.raises(ValueError, match="projection 7"):
        rows.local_index([7])


# ---------------------------------------------------------------------------------------
# the warp kernel
def test_warp_matches_reference_and_is_identity_without_motion():
    basis = MotionBasis(resp_degree=1, cardiac_harmonics=2)
    grid = FieldGrid(nx=13, ny=11, nz=5, voxel_mm=3.0, z0_mm=-8.0, dz_mm=4.0)
    model = _smooth_model(basis, grid, 8.0)
    vg = FieldGrid(nx=13, ny=11, nz=9, voxel_mm=3.0, z0_mm=-10.0, dz_mm=2.5)   # finer z of its own
    vol = RNG.normal(size=vg.shape) * 100
    states = RNG.uniform(0, 1, (4, 2))
    zo = np.array([-12.0, -3.3, 0.0, 7.9, 14.0])   # beyond both ends: clamped
    got = warp.warp(vol, model, states, zo, volume_grid=vg)
    ref = warp.warp_reference(vol, model, states, zo, volume_grid=vg)
    assert np.abs(got - ref).max() < TOL["warp_f32"] * np.abs(ref).max()
    still = dataclasses.replace(model, fields=np.zeros_like(model.fields))
    on_planes = warp.warp(vol, still, states[:1], vg.coords()[2], volume_grid=vg)[0]
    assert np.abs(on_planes - vol).max() < TOL["warp_f32"] * np.abs(vol).max()
    with pytest.raises(ValueError, match="in-plane grid"):
        warp.warp(vol[:, :, :5], model, states, zo, volume_grid=dataclasses.replace(vg, nx=5))


# ---------------------------------------------------------------------------------------
# the model
def test_basis_values_and_validation():
    b = MotionBasis(resp_degree=2, cardiac_harmonics=1)
    v = b.values([0.25, 0.0], [0.5, 1.0])
    assert b.size == 5 and b.names == ("1", "a^1", "a^2", "cos1c", "sin1c")
    assert np.allclose(v, [[1, 0.5, 0.25, 0, 1], [1, 1, 1, 1, 0]], atol=1e-12)
    for bad in (dict(resp_degree=-1), dict(cardiac_harmonics=9), dict(resp_degree=1.5)):
        with pytest.raises(ValueError):
            MotionBasis(**bad)
    with pytest.raises(ValueError, match="finite"):
        b.values([np.nan], [0.1])


def test_field_grid_validation():
    g = FieldGrid.of_slices(4, 3, 2.0, [-2.0, 2.0, 6.0])
    assert g.shape == (3, 3, 4) and g.dz_mm == 4.0 and g.z0_mm == -2.0
    with pytest.raises(ValueError, match="uniformly"):
        FieldGrid.of_slices(4, 3, 2.0, [0.0, 1.0, 3.0])
    with pytest.raises(ValueError, match="nz"):
        FieldGrid(nx=4, ny=3, nz=1, voxel_mm=1.0, z0_mm=0.0, dz_mm=1.0)


def test_fit_recovers_fields_made_from_the_basis():
    basis = MotionBasis(resp_degree=1, cardiac_harmonics=2)
    grid = FieldGrid(nx=6, ny=5, nz=3, voxel_mm=2.0, z0_mm=0.0, dz_mm=3.0)
    truth = _smooth_model(basis, grid, 5.0, seed=3)
    cc, aa = np.meshgrid(np.arange(5) / 5, (np.arange(10) + 0.5) / 10, indexing="ij")
    states = np.stack([cc.ravel(), aa.ravel()], 1)
    fields = np.stack([truth.displacement(c, a) for c, a in states])
    model, rms = fit_motion_model(fields, states, basis, grid, (0.0, 0.5), ridge=0.0)
    assert np.abs(model.fields - truth.fields).max() < TOL["fit_rel"] * np.abs(truth.fields).max()
    assert rms.max() < 1e-5
    with pytest.raises(ValueError, match="cannot fit"):
        fit_motion_model(fields[:4], states[:4], basis, grid, (0.0, 0.5))
    with pytest.raises(ValueError, match="displacements"):
        fit_motion_model(fields[:, :2], states, basis, grid, (0.0, 0.5))


def test_inverse_points_undo_the_model():
    basis = MotionBasis(resp_degree=1, cardiac_harmonics=1)
    grid = FieldGrid(nx=16, ny=14, nz=6, voxel_mm=3.0, z0_mm=-10.0, dz_mm=4.0)
    model = _smooth_model(basis, grid, 2.0, seed=5)
    pts = RNG.uniform(-15, 15, (50, 3))
    xr = model.inverse_points(pts, 0.3, 0.8, iterations=30)
    back = xr + np.moveaxis(sample(model.displacement(0.3, 0.8), grid, xr), 0, -1)
    assert np.abs(back - pts).max() < TOL["inverse_mm"]


# ---------------------------------------------------------------------------------------
# row weights and state bins
def _groups(c, a, counts):
    offsets = np.concatenate([[0], np.cumsum(counts)])
    n = offsets[-1]
    return CandidateGroups(offsets=offsets, row=np.arange(n), projection=np.arange(n) * 10, dz_mm=np.zeros(n),
                           slice_z_mm=np.zeros(1), views_per_rotation=len(counts)), np.asarray(c), np.asarray(a)


def test_kernel_slots_weights():
    g, c, a = _groups([0.0, 0.5, 0.95, 0.2, 0.3], [0.5, 0.5, 0.5, 0.1, 0.9], [3, 2])
    sp, sw = slots.kernel_slots(g, c, a, [[0.0, 0.5]], sigma_c=0.1, sigma_a=0.2, max_slots=2)
    assert sp.shape == (1, 1, 2, 2)
    assert sp[0, 0, 0].tolist() == [0, 20]                  # c = 0 and its circular neighbour 0.95 first
    assert np.allclose(sw.sum(-1), 1.0)
    flat = slots.kernel_slots(g, c, a, [[0.0, 0.5]], sigma_c=np.inf, sigma_a=np.inf, max_slots=3)[1]
    assert np.allclose(flat[0, 0, 0], 1 / 3) and np.allclose(flat[0, 0, 1, :2], 0.5) and flat[0, 0, 1, 2] == 0
    with pytest.raises(ValueError, match="sigma_c"):
        slots.kernel_slots(g, c, a, [[0.0, 0.5]], sigma_c=0.0, sigma_a=1.0, max_slots=2)


def test_plan_slots_moves_zero_weights_out():
    idx = np.array([[[[4, 5, 6]]]])            # (S, V, T, K) = (1, 1, 1, 3)
    w = np.array([[[[0.0, 0.7, 0.3]]]])
    p, ww = slots.plan_slots(idx, w)
    assert p[0, 0, 0].tolist() == [5, 6, -1] and np.allclose(ww[0, 0, 0], [0.7, 0.3, 0.0])


def test_state_bins_are_periodic_in_c_and_clipped_in_a():
    b, centres = correction.state_bins([0.98, 0.02, 0.5, 0.5], [0.0, 1.0, -0.2, 0.55], 10, 4)
    assert b.tolist() == [0 * 4 + 0, 0 * 4 + 3, 5 * 4 + 0, 5 * 4 + 2]
    assert np.allclose(centres[b[2]], [0.5, 0.125])
    with pytest.raises(ValueError, match="n_cardiac"):
        correction.state_bins([0.1], [0.1], 0, 4)


def test_interpolate_rows():
    rows = RNG.normal(size=(5, 7)).astype(np.float32)
    idx = np.array([[[0, 3], [4, 4]]])
    w = np.array([[[0.25, 0.75], [1.0, 0.0]]])
    out = correction.interpolate_rows(rows, idx, w)
    assert np.allclose(out[0, 0], 0.25 * rows[0] + 0.75 * rows[3], atol=1e-6)
    assert np.allclose(out[0, 1], rows[4])


# ---------------------------------------------------------------------------------------
# registration and the separable estimate
def _blob_volume(shift):
    z, y, x = np.meshgrid((np.arange(12) - 5.5) * 4, (np.arange(40) - 19.5) * 3, (np.arange(40) - 19.5) * 3,
                          indexing="ij")
    cx, cy, cz = shift
    inside = ((x - cx) / 30) ** 2 + ((y - cy) / 20) ** 2 + ((z - cz) / 14) ** 2 <= 1
    ring = ((x - cx) / 12) ** 2 + ((y - cy) / 9) ** 2 + ((z - cz) / 8) ** 2 <= 1   # texture inside
    return np.where(ring, 400.0, np.where(inside, 60.0, -800.0)).astype(np.float32), (x, y, z)


@pytest.mark.parametrize("cfg", [registration.FlowConfig(radius=7),
                                 demons.DemonsConfig(iterations=(80, 40), shrink=(2, 1), field_sigma_mm=4.0,
                                                     image_sigma_mm=1.0)], ids=["flow", "demons"])
def test_registration_recovers_a_shift_and_is_deterministic(cfg):
    fixed, (x, y, z) = _blob_volume((0.0, 0.0, 0.0))
    moving, _ = _blob_volume((4.0, -3.0, 4.0))
    u = registration.register(fixed, moving, (3.0, 3.0, 4.0), cfg=cfg)
    assert u.shape == (3,) + fixed.shape and u.dtype == np.float32
    core = (x / 30) ** 2 + (y / 20) ** 2 + (z / 14) ** 2 <= 0.6
    med = np.array([float(np.median(u[k][core])) for k in range(3)])
    want = np.array([4.0, -3.0, 4.0])
    if isinstance(cfg, registration.FlowConfig):
        assert np.allclose(med, want, atol=TOL["flow_mm"]), med
    else:
        assert np.all(np.abs(med - want) <= TOL["demons_share"] * np.abs(want)), med
    assert np.array_equal(u, registration.register(fixed, moving, (3.0, 3.0, 4.0), cfg=cfg))


def test_registration_rejects_bad_inputs():
    fixed, _ = _blob_volume((0.0, 0.0, 0.0))
    with pytest.raises(ValueError, match="one shape"):
        registration.register(fixed, fixed[:-1], (3.0, 3.0, 4.0))
    with pytest.raises(ValueError, match="spacing"):
        registration.register(fixed, fixed, (3.0, 0.0, 4.0))
    with pytest.raises(ValueError, match="iterations"):
        demons.DemonsConfig(iterations=(10,), shrink=(2, 1))
    with pytest.raises(TypeError, match="register"):
        registration.register(fixed, fixed, (3.0, 3.0, 4.0), cfg=object())
    with pytest.raises(ValueError, match="radius"):
        registration.FlowConfig(radius=0)
    with pytest.raises(ValueError, match="starts from zero"):
        registration.register(fixed, fixed, (3.0, 3.0, 4.0), cfg=registration.FlowConfig(),
                              initial=np.zeros((3,) + fixed.shape))
    with pytest.raises(ValueError, match="reference"):
        registration.register_to_reference(fixed[None], 1, (3.0, 3.0, 4.0))


def test_the_fit_in_blocks_and_from_the_separable_parts_is_the_same_bits(monkeypatch):
    """The fit works a block of columns at a time and, in the run, sums each block of the targets'
    fields from the two registration steps' parts: the same model (and residuals to rounding) as
    one block of the whole summed fields, for any block size."""
    grid = FieldGrid(nx=9, ny=7, nz=4, voxel_mm=2.0, z0_mm=0.0, dz_mm=3.0)
    rng = np.random.default_rng(5)
    card = (3 * rng.standard_normal((5, 3) + grid.shape)).astype(np.float32)
    resp = (3 * rng.standard_normal((4, 3) + grid.shape)).astype(np.float32)
    cc, aa = np.meshgrid(np.arange(5) / 5, (np.arange(4) + 0.5) / 4, indexing="ij")
    states = np.stack([cc.ravel(), aa.ravel()], 1)
    fields = (card[:, None] + resp[None, :]).reshape((20, 3) + grid.shape)
    basis = MotionBasis(resp_degree=1, cardiac_harmonics=2)
    monkeypatch.setattr(motion_model, "FIT_BLOCK", 1 << 30)
    whole, rms = fit_motion_model(fields, states, basis, grid, (0.0, 0.5))
    for block in (1, 7, 100):
        monkeypatch.setattr(motion_model, "FIT_BLOCK", block)
        for model, r in (fit_motion_model(fields, states, basis, grid, (0.0, 0.5)),
                         fit_separable_model(card, resp, states, basis, grid, (0.0, 0.5))):
            assert np.array_equal(model.fields, whole.fields), block
            assert np.allclose(r, rms, rtol=1e-12), block
    with pytest.raises(ValueError, match="states"):
        fit_separable_model(card, resp, states[:-1], basis, grid, (0.0, 0.5))


def test_separable_fields_add_breathing_and_beat():
    """Targets made of a breathing shift (z, by amplitude) plus a beat shift (x, by phase)."""
    resp_z, card_x = [-3.0, 0.0, 3.0], [0.0, 3.0]
    vols = np.stack([np.stack([_blob_volume((cx, 0.0, rz))[0] for rz in resp_z]) for cx in card_x])
    grid = FieldGrid(nx=40, ny=40, nz=12, voxel_mm=3.0, z0_mm=-22.0, dz_mm=4.0)
    fields, parts = estimate.separable_fields(vols, (0, 1), grid, registration.FlowConfig(radius=7))
    assert fields.shape == (6, 3) + grid.shape and parts["resp"].shape == (3, 3) + grid.shape
    _, (x, y, z) = _blob_volume((0, 0, 0))
    core = (x / 30) ** 2 + (y / 20) ** 2 + (z / 14) ** 2 <= 0.5
    for i, cx in enumerate(card_x):
        for j, rz in enumerate(resp_z):
            med = [float(np.median(fields[i * 3 + j, k][core])) for k in range(3)]
            assert np.allclose(med, [cx, 0.0, rz], atol=TOL["flow_mm"]), (i, j, med)


class _ConstantShift:
    """A plugged-in registration (``register()``) that reports one shift everywhere, to see which step used it."""

    def __init__(self, dx_mm):
        self.dx_mm = dx_mm

    def register(self, fixed, moving, spacing_mm, origin_mm, initial):
        u = np.zeros((3,) + fixed.shape, np.float32)
        u[0] = self.dx_mm
        return u


def test_the_beat_step_uses_its_own_registration():
    """``beat_cfg`` registers the beat step, ``cfg`` the breathing step (mc's registration and
    beat_registration); without ``beat_cfg`` both steps use ``cfg``."""
    vols = np.zeros((3, 2, 4, 6, 6), np.float32)
    grid = FieldGrid(nx=6, ny=6, nz=4, voxel_mm=3.0, z0_mm=0.0, dz_mm=4.0)
    parts = estimate.separable_parts(vols, (0, 1), grid, _ConstantShift(1.0), beat_cfg=_ConstantShift(2.0))
    assert np.all(parts["resp"][0, 0] == 1.0) and np.all(parts["resp"][1] == 0.0)  # amplitude 1 is the reference
    assert np.all(parts["cardiac"][1:, 0] == 2.0) and np.all(parts["cardiac"][0] == 0.0)
    same = estimate.separable_parts(vols, (0, 1), grid, _ConstantShift(1.0))
    assert np.all(same["cardiac"][1:, 0] == 1.0)


def test_a_registration_that_returns_nan_stops_the_run_naming_it():
    """A field with a NaN is never handed to the next step (the beat step would fail on "finite"
    inputs, far from the cause): ``register`` raises naming the registration and the voxels."""
    vols = np.zeros((3, 2, 4, 6, 6), np.float32)
    grid = FieldGrid(nx=6, ny=6, nz=4, voxel_mm=3.0, z0_mm=0.0, dz_mm=4.0)
    with pytest.raises(RuntimeError, match=r"registration _ConstantShift returned non-finite displacements in "
                                           r"144 of 144 voxels of a 6x6x4 pair"):
        estimate.separable_parts(vols, (0, 1), grid, _ConstantShift(float("nan")))


def test_recon_mc_registrations_select_each_steps_method():
    """The default registers the breathing with the OpenCL Lucas-Kanade and the beat with TV-L1, both in
    the run's process; either knob may name any registration; only a scikit-image Lucas-Kanade step
    (``lucas_kanade``) needs the library and the process pool."""
    from clrecon.config.overrides import load_scene
    from clrecon.core.errors import SceneError
    from clrecon.reconstruction.motion import flow, method
    from clrecon.reconstruction.motion.lk import LKConfig

    knobs = load_scene("demo").recon.mc
    assert isinstance(method.flow_of(knobs, "breathing"), LKConfig)
    assert isinstance(method.flow_of(knobs, "beat"), flow.TVL1Config)
    assert method.registrations(knobs) == {"breathing": "lucas_kanade_cl", "beat": "tvl1"}
    assert not method.uses_library(knobs) and not method.uses_pool(knobs)
    sk = load_scene("demo", recon__mc__registration="lucas_kanade").recon.mc
    assert isinstance(method.flow_of(sk, "breathing"), registration.FlowConfig)
    assert method.uses_library(sk) and method.uses_pool(sk)
    tv = load_scene("demo", recon__mc__registration="tvl1").recon.mc
    assert not method.uses_library(tv) and not method.uses_pool(tv)
    lk = load_scene("demo", recon__mc__beat_registration="lucas_kanade").recon.mc
    assert isinstance(method.flow_of(lk, "beat"), registration.FlowConfig)
    assert method.uses_library(lk) and method.uses_pool(lk)  # a scikit-image beat step alone needs them too
    with pytest.raises(ValueError, match="step = 'heart'"):
        method.flow_of(knobs, "heart")
    with pytest.raises(SceneError, match="recon.mc.beat_registration = 'tv': must be one of "
                       "lucas_kanade, tvl1, lucas_kanade_cl"):
        load_scene("demo", recon__mc__beat_registration="tv")


def test_registrations_in_a_process_pool_are_the_same_bits():
    """The run registers each step's volumes at once in spawned processes: the same fields as one
    after the other, bit for bit (the same call on the same arrays)."""
    resp_z, card_x = [-3.0, 0.0, 3.0], [0.0, 3.0]
    vols = np.stack([np.stack([_blob_volume((cx, 0.0, rz))[0] for rz in resp_z]) for cx in card_x])
    grid = FieldGrid(nx=40, ny=40, nz=12, voxel_mm=3.0, z0_mm=-22.0, dz_mm=4.0)
    cfg = registration.FlowConfig(radius=7)
    serial, _ = estimate.separable_fields(vols, (0, 1), grid, cfg)
    pool = spawned_pool(2)
    assert pool is not None
    try:
        pooled, _ = estimate.separable_fields(vols, (0, 1), grid, cfg, pool=pool)
    finally:
        pool.shutdown()
    assert np.array_equal(serial, pooled)
    assert np.abs(serial).max() > 1.0  # the fields are not all zero


def test_registration_workers_follow_cores_and_memory():
    n_vox = 512 * 512 * 110
    per = registration.FLOW_BYTES_PER_VOXEL * n_vox
    assert registration.registration_workers(n_vox, cores=2, available_bytes=100 * per) == 2
    assert registration.registration_workers(n_vox, cores=64, available_bytes=100 * per) == registration.MAX_WORKERS
    assert registration.registration_workers(n_vox, cores=8, available_bytes=5 * per) == 2  # half the memory
    assert registration.registration_workers(n_vox, cores=8, available_bytes=0) == 1
    assert registration.registration_workers(registration.POOL_MIN_VOXELS - 1, cores=8, available_bytes=100 * per) == 1


def test_one_lucas_kanade_registration_peaks_within_its_modelled_bytes():
    """The pre-flight counts ``FLOW_BYTES_PER_VOXEL`` per voxel for one Lucas-Kanade registration in a
    worker of ``mc``'s pool, above the worker's own ``memory.WORKER_BYTES``: measured as the constants
    were (``benchmarks/studies/motion-model/registration_memory.py``: a spawned worker's VmHWM above
    its resident set after the imports, a first and a second registration) on ``demo``'s registration
    grid, the peak is at most the modelled bytes, and the worker's own set, after its imports and
    between registrations, at most ``WORKER_BYTES``. No lower bound: the same call peaked 265 B a
    voxel in a fresh interpreter and 226 B after tests/pipeline/test_mc_method.py in one session
    (docs/results/code-history.md "One Lucas-Kanade registration's memory")."""
    if not os.path.exists("/proc/self/clear_refs"):
        pytest.skip("needs Linux's /proc/<pid>/status and clear_refs")
    m = registration_memory.measure((16, 128, 128))
    above = max(m["peak_bytes"], m["second_peak_bytes"]) - m["baseline_bytes"]
    modelled = registration.FLOW_BYTES_PER_VOXEL * m["voxels"]
    assert above <= modelled, m
    assert max(m["baseline_bytes"], m["idle_bytes"]) <= memory.WORKER_BYTES, m


def test_shrinking_a_field_peaks_within_its_modelled_bytes():
    """``estimate.shrunk`` (``knobs.shrink``) holds a copy of the step's fields and shrinks one field at a
    time: measured as ``confidence.SHRINK_BYTES_PER_VOXEL`` and ``SHRINK_CHUNK_BYTES_PER_VOXEL`` were
    (a spawned process's peak above its baseline, the call's inputs taken off, under the beat step's
    local prior) on ``demo``'s registration grid, at most the modelled bytes (164 MB; no lower bound:
    156 MB in a fresh interpreter on 2026-12-07, and before the closed-form solve 161 MB fresh and
    146 MB after tests/pipeline/test_mc_method.py in one session)."""
    if not os.path.exists("/proc/self/clear_refs"):
        pytest.skip("needs Linux's /proc/<pid>/status and clear_refs")
    m = registration_memory.measure_shrink((16, 128, 128), local=True)
    vox = m["voxels"]
    modelled = (m["fields"] * 3 * vox * 4 + confidence.SHRINK_BYTES_PER_VOXEL * vox
                + confidence.SHRINK_CHUNK_BYTES_PER_VOXEL * min(vox, confidence.CHUNK_VOXELS))
    assert m["above_baseline_less_inputs_bytes"] <= modelled, m


# ---------------------------------------------------------------------------------------
# the phantom's own motion
@pytest.fixture(scope="module")
def phantom():
    return Phantom()


def test_true_motion_of_named_points(phantom):
    s0, s1 = (0.8, 0.45), (0.3, 0.95)
    for name in ("lesion", "lv_blood"):
        i = phantom.names.index(name)
        c0, c1 = phantom.objects(*s0)[i, 2:5], phantom.objects(*s1)[i, 2:5]
        assert np.allclose(motion_field.displacement(phantom, c0[None], s0, s1)[0], c1 - c0, atol=1e-9)
    spine = phantom.objects(*s0)[phantom.names.index("vertebra_6"), 2:5]
    assert np.allclose(motion_field.displacement(phantom, spine[None], s0, s1), 0.0)


@pytest.mark.parametrize("s0, s1, share", [((0.38, 0.5), (0.0, 0.5), 0.99), ((0.0, 0.5), (0.38, 0.5), 0.93)],
                         ids=["ES-to-ED", "ED-to-ES"])
def test_true_motion_keeps_wall_points_in_the_wall(phantom, s0, s1, share):
    """The shell rule keeps LV wall points in the wall (measured 99.9 % from end-systole to
    end-diastole, where the outer ellipsoid's affine map carries 28 % into the cavity; 95 % the
    other way, the misses at the base, whose clip plane the rule does not follow)."""
    i = phantom.names.index("lv_myocardium")
    o = phantom.objects(*s0)[i]
    pts = o[2:5] + np.random.default_rng(34).uniform(-40, 40, (8000, 3))
    wall = pts[motion_field.owner(phantom, pts, *s0) == i]
    moved = wall + motion_field.displacement(phantom, wall, s0, s1)
    assert len(wall) > 500
    assert np.mean(motion_field.owner(phantom, moved, *s1) == i) > share


def test_true_fields_fill_textureless_points(phantom):
    x = (np.arange(24) - 11.5) * 8.0
    z = (np.arange(4) - 1.5) * 8.0
    f = motion_field.displacement_fields(phantom, x, x, z, (0.8, 0.45), [(0.8, 0.95)])
    raw = motion_field.displacement_fields(phantom, x, x, z, (0.8, 0.45), [(0.8, 0.95)], fill_textureless=False)
    assert f.shape == (1, 3, 4, 24, 24) and np.all(np.isfinite(f))
    Z, Y, X = np.meshgrid(z, x, x, indexing="ij")
    own = motion_field.owner(phantom, np.stack([X, Y, Z], -1), 0.8, 0.45)
    lung = own == phantom.names.index("lung_left")
    assert lung.any() and np.abs(raw[0, 2][lung]).max() == 0.0      # the lung's own rule: no SI motion
    assert np.abs(f[0, 2][lung]).max() > 1.0                        # filled from the heart and diaphragm
    kept = (own >= 0) & ~np.isin(own, [phantom.names.index(n) for n in motion_field.TEXTURELESS])
    assert np.array_equal(f[0][:, kept], raw[0][:, kept])


@pytest.mark.parametrize("nx,voxel_mm,downsample,want", [
    (128, 3.0, 0, 1),   # demo's grid: the knobs' own
    (512, 1.0, 0, 2),   # the paper scenes: 3 / 1 = 3, the largest factor <= 3 dividing 512
    (512, 0.7, 0, 4),   # a clinical 512^2 of 0.7 mm: 2.8 mm
    (500, 0.7, 0, 4),   # 4 divides 500
    (30, 12.0, 0, 1),   # tiny: coarser than 3 mm already
    (512, 1.0, 1, 1),   # an explicit factor wins
    (128, 3.0, 2, 2),
    (126, 3.0, 4, 3),   # the largest <= 4 dividing 126
])
def test_the_registration_factor_keeps_the_grid_near_the_knobs_3_mm(nx, voxel_mm, downsample, want):
    """``downsample = 0`` (auto, the default) registers on the coarsest grid whose voxels are at most
    ``REGISTRATION_VOXEL_MM`` (demo's 3 mm, where the registrations' knobs were chosen), with a factor
    that divides the grid; an explicit factor is the largest dividing the grid up to it."""
    knobs = MotionCompensationConfig(downsample=downsample)
    assert mcm.factor_of(nx, nx, voxel_mm, knobs) == want
    assert nx % want == 0 and (downsample or want == 1 or want * voxel_mm <= mcm.REGISTRATION_VOXEL_MM + 1e-9)
