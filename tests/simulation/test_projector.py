"""Projector and voxeliser kernels against float64 references, exact cases and the phantom.

Tolerances live in ``TOL`` (tests/support/projector_tolerances.py), each with its reason;
nothing else in this file is a tolerance.
"""

import numpy as np
import pytest
from projector_tolerances import EPS32, tol
from random_objects import make_object, random_objects
from ref_projector import project_views_ref
from scipy.ndimage import map_coordinates

from clrecon.config.scene import load_scene
from clrecon.core.conventions import MU_WATER_PER_MM, detector_coords, detector_frames, mu_to_hu
from clrecon.scan.table import projection_table
from clrecon.simulation import projector, voxelise
from clrecon.simulation.phantoms import analytic as ph

SID, SDD = 595.0, 1085.6

def views(rng, m, z_spread=40.0):
    beta = rng.uniform(0, 2 * np.pi, m)
    return detector_frames(beta, rng.uniform(-z_spread, z_spread, m), SID, SDD)


def assert_close_to_ref(p, r, atol, rtol=None):
    rtol = tol("kernel_rtol") if rtol is None else rtol
    err = np.abs(p.astype(np.float64) - r)
    bound = atol + rtol * np.abs(r)
    worst = np.unravel_index(np.argmax(err - bound), err.shape)
    assert np.all(err <= bound), f"max excess at {worst}: |{p[worst]} - {r[worst]}| > {bound[worst]}"


# ---------------------------------------------------------------------------------------
# kernel vs float64 reference on random quadrics
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_random_quadrics_match_float64_reference(seed):
    rng = np.random.default_rng(seed)
    m = 3
    objs = np.broadcast_to(random_objects(rng, 10), (m, 10, ph.STRIDE))
    src, det, eu, ev = views(rng, m)
    u = detector_coords(96, 7.5, offset_cells=rng.uniform(-0.5, 0.5))
    v = detector_coords(12, 16.0)
    p = projector.project_views(objs, src, det, eu, ev, u, v)
    r = project_views_ref(objs, src, det, eu, ev, u, v)
    assert p.shape == (m, 12, 96) and p.dtype == np.float32
    assert np.count_nonzero(r) > 0.08 * r.size, "the random scene must be hit by many rays"
    assert_close_to_ref(p, r, tol("kernel_atol"))
    # the unculled kernel agrees with the reference too, and culling changes nothing
    q = projector.project_views(objs, src, det, eu, ev, u, v, cull=False)
    np.testing.assert_array_equal(p, q)


def test_every_feature_is_exercised_by_the_random_scene():
    """Guards the test above: planes, both cut modes and both kinds appear."""
    objs = random_objects(np.random.default_rng(0), 10)
    modes = {int(o[ph.cut_fields(k)[0]]) for o in objs for k in range(2)}
    assert {ph.CUT_SUBTRACT, ph.CUT_INTERSECT} <= modes
    assert {ph.KIND_ELLIPSOID, ph.KIND_CYLINDER} <= set(objs[:, ph.KIND].astype(int))
    assert np.any(objs[:, 17:20] != 0)


def test_reference_can_fail():
    """A wrong density or geometry is caught by the comparison used above."""
    rng = np.random.default_rng(0)
    objs = random_objects(rng, 4)[None]
    src, det, eu, ev = views(rng, 1)
    u, v = detector_coords(32, 20.0), detector_coords(4, 6.4)
    r = project_views_ref(objs, src, det, eu, ev, u, v)
    bad = objs.copy()
    bad[0, :, ph.MU] *= 1.01
    p = projector.project_views(bad, src, det, eu, ev, u, v)
    with pytest.raises(AssertionError):
        assert_close_to_ref(p, r, tol("kernel_atol"))


# ---------------------------------------------------------------------------------------
# the float64 record kernel (kernels/project_cull.cl) against its NumPy reference
@pytest.mark.parametrize("cull", [True, False])
def test_record_kernel_matches_numpy_reference(cull):
    rng = np.random.default_rng(11)
    m = 6
    mixed = np.concatenate([random_objects(rng, 12), ph.Phantom().objects(0.3, 0.4)])
    objs = np.broadcast_to(mixed, (m,) + mixed.shape)
    src, det, eu, ev = views(rng, m, z_spread=60.0)
    args = (objs, src, det, eu, ev, (-350.0, 350.0), (-25.0, 25.0), cull)
    ref, iv_ref = projector.prepare_records(*args)
    got, iv = projector.prepare_records_device(*args)
    np.testing.assert_array_equal(iv, iv_ref)
    assert len(iv) > 5 * m and (len(iv) < m * len(mixed)) == cull
    np.testing.assert_array_equal(got[:, projector.R_FLAGS], ref[:, projector.R_FLAGS])
    # the same float64 formulas in another order: equal up to a float32 ulp or two
    np.testing.assert_allclose(got, ref, rtol=tol("record_rtol"), atol=tol("record_atol"))


def test_host_records_give_the_same_projections(monkeypatch):
    rng = np.random.default_rng(12)
    objs = np.broadcast_to(random_objects(rng, 8), (3, 8, ph.STRIDE))
    src, det, eu, ev = views(rng, 3)
    u, v = detector_coords(64, 10.0), detector_coords(8, 16.0)
    dev = projector.project_views(objs, src, det, eu, ev, u, v)
    monkeypatch.setattr(projector, "has_fp64", lambda rt: False)
    host = projector.project_views(objs, src, det, eu, ev, u, v)
    assert_close_to_ref(host, dev.astype(np.float64), tol("kernel_atol"))


# ---------------------------------------------------------------------------------------
# edge cases
def single_view(beta=0.4, z=0.0):
    return detector_frames(np.array([beta]), np.array([z]), SID, SDD)


def ray_point(det, eu, ev, u, v):
    return det[0] + u * eu[0] + v * ev[0]


def test_tangent_and_missing_rays():
    src, det, eu, ev = single_view()
    u, v = detector_coords(41, 2.0), detector_coords(5, 2.0)
    # sphere tangent to the ray through cell (row 2, col 20): its centre sits r from that ray
    target = ray_point(det, eu, ev, u[20], v[2])
    d = (target - src[0]) / np.linalg.norm(target - src[0])
    side = np.cross(d, [0.0, 0.0, 1.0])
    side /= np.linalg.norm(side)
    r = 20.0
    centre = src[0] + 600.0 * d + r * side
    tangent = make_object(ph.KIND_ELLIPSOID, 0.02, centre, np.eye(3), [r, r, r])
    far = make_object(ph.KIND_ELLIPSOID, 0.02, [0.0, 0.0, 500.0], np.eye(3), [10, 10, 10])  # above the cone
    # behind the source on the central ray: the whole line is integrated (documented), so
    # culling must keep it and kernel and reference agree
    behind = make_object(ph.KIND_CYLINDER, 0.02, src[0] * 3.0, np.eye(3), [10, 10, 10])
    t_only = projector.project_views(tangent[None, None], src, det, eu, ev, u, v)
    t_ref = project_views_ref(tangent[None, None], src, det, eu, ev, u, v)
    assert abs(t_ref[0, 2, 20]) < 1e-6          # exactly tangent: zero chord
    assert t_only[0, 2, 20] == pytest.approx(0.0, abs=tol("tangent_atol"))
    nb = sorted([t_ref[0, 2, 19], t_ref[0, 2, 21]])
    assert nb[0] == 0.0 and nb[1] > 0.05  # one neighbour outside, one inside
    objs = np.array([tangent, far, behind])[None]
    p = projector.project_views(objs, src, det, eu, ev, u, v)
    ref = project_views_ref(objs, src, det, eu, ev, u, v)
    assert ref[0, 2, 20] > 0  # the central ray reaches the object behind the source
    assert_close_to_ref(p, ref, tol("kernel_atol"))
    # the far sphere alone is missed by every ray
    alone = projector.project_views(np.array([far])[None], src, det, eu, ev, u, v)
    assert np.all(alone == 0.0)


def test_ray_parallel_to_cylinder_axis():
    src, det, eu, ev = single_view(beta=1.1, z=5.0)
    u, v = detector_coords(21, 1.0), detector_coords(3, 1.0)
    target = ray_point(det, eu, ev, u[10], v[1])
    axis = (target - src[0]) / np.linalg.norm(target - src[0])
    frame = ph._axis_frame(axis)
    h, mu = 30.0, 0.02
    inside = make_object(ph.KIND_CYLINDER, mu, src[0] + 500.0 * axis, frame, [4.0, 6.0, h])
    p = projector.project_views(inside[None, None], src, det, eu, ev, u, v)
    ref = project_views_ref(inside[None, None], src, det, eu, ev, u, v)
    assert ref[0, 1, 10] == pytest.approx(2 * h * mu, rel=1e-12)
    assert p[0, 1, 10] == pytest.approx(2 * h * mu, rel=tol("kernel_rtol"))
    assert_close_to_ref(p, ref, tol("kernel_atol"))
    # the same cylinder shifted sideways: the parallel ray misses it
    outside = inside.copy()
    outside[ph.CENTRE] += 10.0 * frame[:, 0]
    p2 = projector.project_views(outside[None, None], src, det, eu, ev, u, v)
    assert p2[0, 1, 10] == 0.0


def test_objects_at_the_detector_edge_and_clip_planes_parallel_to_rays():
    src, det, eu, ev = single_view(beta=2.0, z=-3.0)
    u, v = detector_coords(64, 5.0), detector_coords(8, 5.0)
    edge = ray_point(det, eu, ev, u[-1], v[0])
    d = (edge - src[0]) / np.linalg.norm(edge - src[0])
    # a sphere centred on the outermost corner ray: only part of it is seen
    a = make_object(ph.KIND_ELLIPSOID, 0.03, src[0] + 550.0 * d, np.eye(3), [25, 25, 25])
    # a box-like cylinder clipped by a plane that contains the rays of column 31
    col = ray_point(det, eu, ev, u[31], 0.0) - src[0]
    n = np.cross(col, ev[0])
    n /= np.linalg.norm(n)
    b = make_object(ph.KIND_CYLINDER, 0.02, src[0] + 0.55 * col, np.eye(3), [30, 30, 40],
                    planes=[(n, n @ src[0])])
    objs = np.array([a, b])[None]
    p = projector.project_views(objs, src, det, eu, ev, u, v)
    ref = project_views_ref(objs, src, det, eu, ev, u, v)
    assert ref[0, 0, -1] > 0 and ref[0, -1, 0] == 0.0
    assert_close_to_ref(p, ref, tol("kernel_atol"))
    np.testing.assert_array_equal(p, projector.project_views(objs, src, det, eu, ev, u, v, cull=False))


def test_cylinders_whose_caps_no_ray_meets_skip_the_slab_exactly():
    """The host marks cylinders whose end caps no ray of the view meets (the kernel then
    drops the slab); marking one whose finite part is out of view would be wrong."""
    src, det, eu, ev = single_view(beta=0.8, z=2.0)
    u, v = detector_coords(48, 15.0), detector_coords(6, 8.0)
    tilt = ph._axis_frame(np.array([0.1, 0.05, 1.0]))
    long_ = make_object(ph.KIND_CYLINDER, 0.02, [5.0, -3.0, 0.0], tilt, [80.0, 60.0, 300.0])
    short = make_object(ph.KIND_CYLINDER, 0.02, [0.0, 0.0, 4.0], np.eye(3), [50.0, 50.0, 8.0])
    beyond = make_object(ph.KIND_CYLINDER, 0.02, [0.0, 0.0, 250.0], np.eye(3), [80.0, 80.0, 100.0])
    objs = np.array([long_, short, beyond])[None]
    rec, iv = projector.prepare_records(objs, src, det, eu, ev, (u[0], u[-1]), (v[0], v[-1]), cull=False)
    no_slab = (rec[:, projector.R_FLAGS].astype(int) >> 8) & 1
    assert list(no_slab) == [1, 0, 0]
    p = projector.project_views(objs, src, det, eu, ev, u, v)
    assert_close_to_ref(p, project_views_ref(objs, src, det, eu, ev, u, v), tol("kernel_atol"))
    only_beyond = projector.project_views(objs[:, 2:], src, det, eu, ev, u, v, cull=False)
    assert np.all(only_beyond == 0.0)


def test_centred_water_cylinder_gives_exact_chords():
    """In-plane fan beam through a centred water cylinder: chord 2 sqrt(R^2 - rho^2)."""
    R = 150.0
    cyl = make_object(ph.KIND_CYLINDER, MU_WATER_PER_MM, [0, 0, 0], np.eye(3), [R, R, 500.0])
    beta = np.array([0.0, 0.7, 3.0])
    src, det, eu, ev = detector_frames(beta, np.zeros(3), SID, SDD)
    u = detector_coords(900, 0.8)
    p = projector.project_views(np.broadcast_to(cyl, (3, 1, ph.STRIDE)), src, det, eu, ev, u, np.zeros(1))
    rho = SID * np.sin(np.arctan(u / SDD))
    exact = MU_WATER_PER_MM * 2.0 * np.sqrt(np.maximum(R * R - rho * rho, 0.0))
    away = np.abs(rho) < 0.9 * R  # nearer the edge the relative error grows as 1 / (1 - rho^2/R^2)
    for k in range(3):
        np.testing.assert_allclose(p[k, 0, away], exact[away], rtol=tol("water_rtol"))
        assert np.all(p[k, 0, np.abs(rho) > R] == 0.0)
        assert np.abs(p[k, 0] - exact).max() <= 2 * R * np.sqrt(EPS32) * MU_WATER_PER_MM  # tangency bound


# ---------------------------------------------------------------------------------------
# the phantom
@pytest.fixture(scope="module")
def phantom_views():
    pht = ph.Phantom()
    rng = np.random.default_rng(5)
    m = 4
    src, det, eu, ev = views(rng, m, z_spread=60.0)
    objs = pht.objects_batch(rng.uniform(0, 1, m), rng.uniform(0, 1, m))
    return objs, src, det, eu, ev


def test_phantom_projection_matches_reference_and_culling_changes_nothing(phantom_views):
    objs, src, det, eu, ev = phantom_views
    u, v = detector_coords(900, 0.8), detector_coords(64, 0.8)
    p = projector.project_views(objs, src, det, eu, ev, u, v)
    q = projector.project_views(objs, src, det, eu, ev, u, v, cull=False)
    assert np.abs(p - q).max() <= tol("culling")
    cols, rows = np.arange(3, 900, 9), np.array([0, 21, 31, 32, 47, 63])
    r = project_views_ref(objs, src, det, eu, ev, u[cols], v[rows])
    pc = p[:, rows][:, :, cols]
    assert r.max() > 3.0
    assert_close_to_ref(pc, r, tol("phantom_atol"))
    assert np.sqrt(np.mean((pc - r) ** 2)) <= tol("phantom_rms")


def _in_plane(pht, c, a, z0, n_cols=300):
    beta = np.array([0.9])
    src, det, eu, ev = detector_frames(beta, np.array([z0]), SID, SDD)
    u = detector_coords(n_cols, 720.0 / n_cols)
    p = projector.project_views(pht.objects(c, a)[None], src, det, eu, ev, u, np.zeros(1))[0, 0]
    pts = det[0] + u[:, None] * eu[0]
    return p, src[0], pts


def _march(img, x, y, src, pts, step):
    """Bilinear ray marching through a 2-D image (ny, nx) on axes x, y (mm)."""
    out = np.zeros(len(pts))
    for i, p in enumerate(pts):
        d = p - src
        L = np.linalg.norm(d[:2])
        t = np.arange(0.0, L, step) / L
        xs, ys = src[0] + t * d[0], src[1] + t * d[1]
        fi = (xs - x[0]) / (x[1] - x[0])
        fj = (ys - y[0]) / (y[1] - y[0])
        vals = map_coordinates(img, [fj, fi], order=1, mode="constant", cval=0.0)
        out[i] = vals.sum() * step * np.linalg.norm(d) / L
    return out


def test_analytic_projection_matches_ray_marching_through_voxelised_phantom():
    pht = ph.Phantom()
    c, a, z0 = 0.3, 0.6, 4.0
    p, src, pts = _in_plane(pht, c, a, z0)
    errs = []
    for h in (1.0, 0.5):
        x = np.arange(-175.0, 175.0 + h / 2, h)
        y = np.arange(-125.0, 125.0 + h / 2, h)
        img = pht.voxelise(c, a, x, y, np.array([z0, z0 + 0.01]), supersample=3)[0]
        ray = _march(img.astype(np.float64), x, y, src, pts, step=h / 4)
        errs.append(np.sqrt(np.mean((ray - p) ** 2)) / np.sqrt(np.mean(p ** 2)))
    assert errs[1] <= tol("voxel_rel_rms")
    assert errs[1] <= tol("voxel_convergence") * errs[0]


# ---------------------------------------------------------------------------------------
# project(scene, table)
def test_project_scene_table_matches_project_views_and_chunking():
    scene = load_scene("tiny")
    table = projection_table(scene, scene.scan.pitches[0])
    sub = table.take(np.arange(0, len(table), max(1, len(table) // 7)))
    p = projector.project(scene, sub)
    sc = scene.scanner
    assert p.shape == (len(sub), sc.n_rows, sc.n_cols) and p.dtype == np.float32
    src, det, eu, ev = detector_frames(sub.angle_rad, sub.source_z_mm, sc.sid_mm, sc.sdd_mm)
    objs = ph.Phantom(scene.phantom).objects_batch(sub.state_cardiac, sub.state_resp)
    q = projector.project_views(objs, src, det, eu, ev, detector_coords(sc.n_cols, sc.col_pitch_mm),
                                detector_coords(sc.n_rows, sc.row_pitch_mm))
    np.testing.assert_array_equal(p, q)
    np.testing.assert_array_equal(p, projector.project(scene, sub, chunk_views=3))
    assert p.max() > 2.0
    empty = projector.project(scene, sub.take(np.zeros(0, int)))
    assert empty.shape == (0, sc.n_rows, sc.n_cols)


def test_posed_objects_are_read_in_place_with_the_same_projections():
    """A posed batch starts on a page boundary, so the record kernel reads it in place on a CPU
    device (a CL_MEM_USE_HOST_PTR buffer over the phantom's own array); a copy of it that does
    not start there is copied to the device instead, and both project to the same bits."""
    scene = load_scene("tiny")
    table = projection_table(scene, scene.scan.pitches[0])
    sub = table.take(np.arange(0, len(table), max(1, len(table) // 5)))
    sc = scene.scanner
    objs = ph.Phantom(scene.phantom).objects_batch(sub.state_cardiac, sub.state_resp)
    assert objs.ctypes.data % 4096 == 0 and objs.flags.c_contiguous and objs.dtype == np.float64
    moved = np.empty(objs.size + 1)[1:].reshape(objs.shape)  # 8 bytes past NumPy's 16-byte alignment
    moved[...] = objs
    src, det, eu, ev = detector_frames(sub.angle_rad, sub.source_z_mm, sc.sid_mm, sc.sdd_mm)
    u, v = detector_coords(sc.n_cols, sc.col_pitch_mm), detector_coords(sc.n_rows, sc.row_pitch_mm)
    rt = projector.get_runtime()
    lay = projector._Layout(u, v, rt, None)
    view_rec = np.zeros((len(sub), projector.VIEW_REC))
    view_rec[:, 0:3], view_rec[:, 3:6], view_rec[:, 6:9] = det - src, eu, ev
    use = rt.cl.mem_flags.USE_HOST_PTR
    for arr, in_place in ((objs, rt.is_cpu), (moved, False)):
        *_, events, keep = projector._prepare_on_device(rt, arr, False, src, view_rec, lay, True)
        rt.cl.wait_for_events(events)
        assert bool(keep[0].flags & use) == in_place
    a = projector.project_views(objs, src, det, eu, ev, u, v)
    b = projector.project_views(moved, src, det, eu, ev, u, v)
    np.testing.assert_array_equal(a.view(np.uint32), b.view(np.uint32))
    assert a.max() > 1.0


def test_input_validation():
    src, det, eu, ev = single_view()
    objs = random_objects(np.random.default_rng(0), 2)[None]
    u, v = detector_coords(8, 1.0), detector_coords(2, 1.0)
    with pytest.raises(ValueError):
        projector.project_views(objs[..., :10], src, det, eu, ev, u, v)
    with pytest.raises(ValueError):
        projector.project_views(objs, src[:, :2], det, eu, ev, u, v)
    with pytest.raises(ValueError):
        projector.project_views(objs, src, det, eu, ev, np.zeros((2, 2)), v)
    with pytest.raises(TypeError):
        projector.project_views(objs.astype(object), src, det, eu, ev, u, v)
    with pytest.raises(ValueError):
        voxelise.voxelise_objects(objs[0], u, u, u, supersample=0)


# ---------------------------------------------------------------------------------------
# voxeliser kernel vs NumPy point samples
def _numpy_voxelise(objs, x, y, z, ss, dx, dy, dz):
    off = (np.arange(ss) + 0.5) / ss - 0.5
    Z, Y, X = np.meshgrid(z, y, x, indexing="ij")
    acc = np.zeros(Z.shape)
    for oz in off:
        for oy in off:
            for ox in off:
                acc += ph.mu_at(objs, np.stack([X + ox * dx, Y + oy * dy, Z + oz * dz], -1))
    return acc / ss ** 3


@pytest.mark.parametrize("ss", [1, 2])
def test_voxelise_matches_numpy_point_samples(ss):
    rng = np.random.default_rng(7)
    objs = np.concatenate([random_objects(rng, 6), ph.Phantom().objects(0.4, 0.3)])
    x = np.arange(-150.0, 150.0, 3.7)
    y = np.arange(-100.0, 100.0, 4.1)
    z = np.arange(-30.0, 42.0, 18.0)
    got = voxelise.voxelise_objects(objs, x, y, z, supersample=ss)
    ref = _numpy_voxelise(objs, x, y, z, ss, 3.7, 4.1, 18.0)
    assert got.shape == (len(z), len(y), len(x)) and got.dtype == np.float32
    bad = np.abs(got - ref) > 1e-5
    assert bad.mean() <= tol("voxelise_mismatch_fraction") * ss ** 3 + 1.0 / got.size
    assert np.abs(ref).max() > 0.01


def test_voxelise_edge_grids():
    """Grids smaller than a work-item's 8 voxels, single-sample axes (1 mm thick), empty space."""
    objs = ph.Phantom().objects(0.0, 0.0)
    x = np.array([-100.0, -99.0, -98.0, -97.0, -96.0])            # 5 < VW voxels along x
    got = voxelise.voxelise_objects(objs, x, np.array([20.0]), np.array([60.0]), supersample=2)
    ref = _numpy_voxelise(objs, x, np.array([20.0]), np.array([60.0]), 2, 1.0, 1.0, 1.0)
    assert got.shape == (1, 1, 5)
    np.testing.assert_allclose(got, ref, atol=1e-7)
    assert np.all(mu_to_hu(got) < -700)                            # inside the right lung
    outside = voxelise.voxelise_objects(objs, np.array([400.0]), np.array([0.0]), np.array([0.0]), supersample=1)
    assert outside.shape == (1, 1, 1) and outside[0, 0, 0] == 0.0


def test_bench_projector_runs_and_checks_its_reference():
    from clrecon.bench.projector import bench_projector

    res = bench_projector(6, "tiny", reference_projections=2, repeats=1)
    assert res["projections"] == 6 and res["reference"]["projections"] == 2
    assert res["max_abs_diff_vs_reference"] == 0.0
    assert res["rays_per_s"] > 0 and res["projected_total_s"] > 0
    assert 0 < res["evaluated_pairs_per_ray"] < res["n_objects"]
