"""The analytic thorax: parameter table, anatomy constraints, motion, volume curve, HU.

Tolerances live in ``TOL``; ranges quoted from the literature (docs/simulation.md "Analytic phantom") are data,
not tolerances.
"""

import numpy as np
import pytest

from clrecon.config.scene import PhantomConfig, load_scene
from clrecon.core.conventions import hu_to_mu, mu_to_hu
from clrecon.simulation.phantoms import analytic as ph
from clrecon.simulation.voxelise import voxelise_objects

#: name -> (value, reason)
TOL = {
    "volume_rel": (0.015, "1 mm voxels, 3x3x3 samples: sampling error of a ~60-130 mL blob"),
    "rv_volume_rel": (0.06, "the RV crescent is calibrated at ED/ES by Monte Carlo (see the table)"),
    "motion_mm": (0.3, "surface positions found by bisection to 0.01 mm; tilt of the dome"),
    "hu": (1e-6, "HU -> mu -> HU round trip in float64"),
}
STATES = [(0.0, 0.0), (0.38, 0.0), (0.0, 1.0), (0.38, 1.0), (0.7, 0.5)]


def tol(name):
    return TOL[name][0]


@pytest.fixture(scope="module")
def phantom():
    return ph.Phantom()


# ---------------------------------------------------------------------------------------
def test_parameter_table_is_complete_and_sourced():
    names = [r.name for r in ph.PARAMETERS]
    assert len(names) == len(set(names))
    for r in ph.PARAMETERS:
        assert r.source in ph.PARAMETER_SOURCES, r
        assert r.unit and np.isfinite(r.value), r
    P = ph.P
    assert -900 <= P["hu_lung_inhale"] <= P["hu_lung_exhale"] <= -700
    assert 300 <= P["hu_blood_right"] <= P["hu_blood_left"] <= 450
    assert 80 <= P["hu_myocardium"] <= 100 and 40 <= P["hu_muscle"] <= 50
    assert 1000 <= P["hu_cortical_bone"] <= 1500 and 150 <= P["hu_trabecular_bone"] <= 300
    assert P["hu_metal"] >= 3000 and P["metal_radius"] == pytest.approx(3.0, abs=1.0)
    assert P["body_semi_lr"] <= 165 and 100 <= P["body_semi_ap"] <= 110


def test_objects_layout_and_batch(phantom):
    c = np.array([0.0, 0.25, 0.5, 0.99])
    a = np.array([0.0, 1.0, 0.3, 0.7])
    batch = phantom.objects_batch(c, a)
    assert batch.shape == (4, phantom.n_objects, ph.STRIDE) and batch.dtype == np.float64
    for i in range(4):
        np.testing.assert_array_equal(batch[i], phantom.objects(c[i], a[i]))
    kinds = set(batch[..., ph.KIND].astype(int).ravel())
    assert kinds <= {ph.KIND_ELLIPSOID, ph.KIND_CYLINDER}
    assert np.all(np.isfinite(batch))
    axes = batch[..., ph.AXES].reshape(4, -1, 3, 3)
    np.testing.assert_allclose(np.einsum("...ji,...jk->...ik", axes, axes), np.broadcast_to(np.eye(3), axes.shape),
                               atol=1e-12)
    assert len(set(phantom.names)) == phantom.n_objects
    with pytest.raises(ValueError):
        phantom.objects_batch(c, a[:2])
    with pytest.raises(ValueError):
        phantom.objects_batch(np.array([np.nan]), np.array([0.0]))


def test_frozen_motion_switches():
    still = ph.Phantom(PhantomConfig(cardiac_motion=False, respiratory_motion=False))
    ref = still.objects(0.0, 0.0)
    for c, a in STATES:
        np.testing.assert_array_equal(still.objects(c, a), ref)
    beating = ph.Phantom(PhantomConfig(respiratory_motion=False))
    assert not np.array_equal(beating.objects(0.38, 0.0), beating.objects(0.0, 0.0))
    np.testing.assert_array_equal(beating.objects(0.38, 1.0), beating.objects(0.38, 0.0))
    breathing = ph.Phantom(PhantomConfig(cardiac_motion=False))
    np.testing.assert_array_equal(breathing.objects(0.38, 1.0), breathing.objects(0.0, 1.0))
    assert not np.array_equal(breathing.objects(0.0, 1.0), breathing.objects(0.0, 0.0))
    assert still.lv_blood_volume_ml(0.38) == pytest.approx(ph.P["lv_edv"])


# ---------------------------------------------------------------------------------------
def _aabb(o):
    R = o[ph.AXES].reshape(3, 3)
    ext = np.sqrt((R ** 2) @ o[ph.SEMI] ** 2) if o[ph.KIND] == ph.KIND_ELLIPSOID else np.abs(R) @ o[ph.SEMI]
    return o[ph.CENTRE] - ext, o[ph.CENTRE] + ext


def _ancestors(phantom, i):
    out = {i}
    p = phantom.parents[i]
    while p != "air":
        j = phantom.names.index(p)
        out.add(j)
        p = phantom.parents[j]
    return out


@pytest.mark.parametrize("state", STATES)
def test_objects_nest_in_their_parents_and_never_overlap_otherwise(phantom, state):
    """Additive densities are right only if every object lies in its parent and no
    other object: sampled points of each object are inside exactly its ancestors."""
    objs = phantom.objects(*state)
    rng = np.random.default_rng(1)
    anc = [_ancestors(phantom, i) for i in range(phantom.n_objects)]
    for i, o in enumerate(objs):
        lo, hi = _aabb(o)
        pts = rng.uniform(lo, hi, (4000, 3))
        pts = pts[ph.inside(o, pts)][:150]
        assert len(pts) > 20, phantom.names[i]
        members = np.array([ph.inside(q, pts) for q in objs])  # (n_obj, n_pts)
        expected = np.zeros(len(objs), bool)
        expected[list(anc[i])] = True
        # descendants of i may contain some of its points; everything else must not
        desc = np.array([i in anc[j] for j in range(len(objs))])
        wrong = members[~expected & ~desc].any(axis=0)
        missing = ~members[expected].all(axis=0)
        assert not wrong.any() and not missing.any(), (
            phantom.names[i], [phantom.names[j] for j in np.nonzero(members[:, wrong.argmax()] & ~expected & ~desc)[0]])


def test_body_inside_fov_and_long_enough(phantom):
    fov = load_scene("paper-p002").scanner.fov_radius_mm
    assert fov == pytest.approx(187, abs=1)
    ang = np.linspace(0, 2 * np.pi, 360, endpoint=False)
    dirs = np.stack([np.cos(ang), np.sin(ang), np.zeros_like(ang)], -1)
    i = phantom.names.index("body_fat")
    for c, a in STATES:
        o = phantom.objects(c, a)[i]
        reach = ph.support(ph.KIND_CYLINDER, o[ph.CENTRE], o[ph.AXES].reshape(3, 3), o[ph.SEMI], dirs)
        assert reach.max() < fov - 15.0
    objs = phantom.objects(0.0, 1.0)
    for name in ("body_fat", "body_muscle", "lung_left", "lung_right"):
        lo, hi = _aabb(objs[phantom.names.index(name)])
        assert lo[2] <= -140 and hi[2] > 200, name
    zs = [objs[phantom.names.index(f"vertebra_{k}")][ph.CENTRE][2] for k in range(int(ph.P["vertebra_count"]))]
    assert min(zs) < -150 and max(zs) > 150


# ---------------------------------------------------------------------------------------
def test_volume_curve_shape():
    c = np.linspace(0, 1, 2001)[:-1]
    v = ph.lv_blood_volume_ml(c)
    edv, esv = v.max(), v.min()
    assert edv == pytest.approx(130, abs=1) and esv == pytest.approx(54, abs=1)
    assert 0.57 <= (edv - esv) / edv <= 0.61
    assert 0.35 <= c[np.argmin(v)] <= 0.40          # first instant of end-systole
    assert v[0] == edv and np.all(np.diff(v[(c > 0.03) & (c < 0.38)]) < 0)
    sv = edv - esv
    kick = ph.lv_blood_volume_ml(0.9999) - ph.lv_blood_volume_ml(0.85)
    assert kick == pytest.approx(0.07 * sv, rel=0.01)
    rate = np.gradient(v, c)
    assert 0.90 <= c[(c > 0.85)][np.argmax(rate[c > 0.85])] <= 0.95  # atrial inflow peak
    assert np.all(np.abs(np.diff(v)) < 0.5)          # continuous
    assert ph.rv_blood_volume_ml(0.0) == 140 and ph.rv_blood_volume_ml(0.4) == 65


def _object_volume_ml(objs, i, step=1.0, ss=3):
    o = objs[i].copy()
    o[ph.MU] = 1.0
    lo, hi = _aabb(o)
    axes = [np.arange(lo[k] - step, hi[k] + step, step) for k in range(3)]
    vox = voxelise_objects(o[None], *axes, supersample=ss)
    return float(vox.sum(dtype=np.float64)) * step ** 3 / 1000.0


@pytest.mark.parametrize("c", [0.0, 0.2, 0.38, 0.6, 0.9])
def test_voxelised_lv_blood_pool_follows_the_curve(phantom, c):
    objs = phantom.objects(c, 0.5)
    vol = _object_volume_ml(objs, phantom.names.index("lv_blood"))
    assert vol == pytest.approx(float(ph.lv_blood_volume_ml(c)), rel=tol("volume_rel"))


def test_rv_and_atria_volumes(phantom):
    for c, rv, at in ((0.0, 140.0, 32.0), (0.38, 65.0, 58.0)):
        objs = phantom.objects(c, 0.0)
        assert _object_volume_ml(objs, phantom.names.index("rv_blood")) == pytest.approx(rv, rel=tol("rv_volume_rel"))
        for name in ("left_atrium", "right_atrium"):
            assert _object_volume_ml(objs, phantom.names.index(name)) == pytest.approx(at, rel=tol("volume_rel"))


def test_lv_wall_thickens_and_myocardial_volume_is_constant(phantom):
    a, b, ao, bo = (np.asarray(x) for x in ph.lv_shape(np.array([0.0, 0.38])))
    assert bo[0] - b[0] == pytest.approx(ph.P["lv_wall_ed"])
    assert bo[1] - b[1] > 1.3 * (bo[0] - b[0])       # systolic thickening
    assert (a[0] - a[1]) * (1 + ph.P["lv_base_cut"]) == pytest.approx(ph.P["lv_long_shortening"])
    myo = []
    for c in (0.0, 0.38):
        objs = phantom.objects(c, 0.0)
        myo.append(_object_volume_ml(objs, phantom.names.index("lv_myocardium"))
                   - _object_volume_ml(objs, phantom.names.index("lv_blood")))
    assert myo[1] == pytest.approx(myo[0], rel=tol("volume_rel"))
    assert 100 < myo[0] < 200   # LV mass ~ 100-200 g


# ---------------------------------------------------------------------------------------
def _top_z(objs, i, x, y, z_lo=-200.0, z_hi=100.0):
    """Highest z of object i on the vertical line (x, y), by bisection on membership."""
    o = objs[i]
    zs = np.linspace(z_lo, z_hi, 3001)
    ins = ph.inside(o, np.stack([np.full_like(zs, x), np.full_like(zs, y), zs], -1))
    return zs[np.nonzero(ins)[0].max()]


def test_respiratory_motion_amplitudes(phantom):
    cfg = phantom.cfg
    liver = phantom.names.index("liver")
    # the right liver dome, lateral of the heart that rests on it
    dome = [max(_top_z(o, liver, x, o[liver, ph.CENTRE][1]) for x in np.arange(-100.0, -39.0, 5.0))
            for o in (phantom.objects(0.0, a) for a in (0.0, 1.0))]
    assert dome[0] - dome[1] == pytest.approx(cfg.diaphragm_si_mm, abs=tol("motion_mm"))
    assert -60 <= dome[1] <= -40                                # liver dome at end-inhale
    lv = [phantom.lv_blood_pool_centre(0.0, a) for a in (0.0, 1.0)]
    assert lv[0][2] - lv[1][2] == pytest.approx(cfg.heart_si_fraction * cfg.diaphragm_si_mm, abs=1e-9)
    assert lv[1][1] < lv[0][1]                                  # heart moves anteriorly too
    assert -15 <= lv[0][2] <= 15                                # heart centre near z = 0
    skin = phantom.names.index("body_fat")
    front = [phantom.objects(0.0, a)[skin] for a in (0.0, 1.0)]
    ant = [o[ph.CENTRE][1] - o[ph.SEMI][1] for o in front]
    back = [o[ph.CENTRE][1] + o[ph.SEMI][1] for o in front]
    assert ant[0] - ant[1] == pytest.approx(cfg.chest_ap_mm, abs=1e-9) and back[0] == pytest.approx(back[1])
    lung = phantom.names.index("lung_right")
    assert phantom.objects(0.0, 1.0)[lung, ph.MU] < phantom.objects(0.0, 0.0)[lung, ph.MU]


def test_coronary_displacements_over_a_beat(phantom):
    c = np.linspace(0, 1, 41)[:-1]
    objs = phantom.objects_batch(c, np.zeros_like(c))
    disp = {}
    for name in ("lad", "rca"):
        idx = [i for i, n in enumerate(phantom.names) if n.startswith(name + "_")]
        cen = objs[:, idx][:, :, ph.CENTRE]
        disp[name] = np.linalg.norm(cen[:, None] - cen[None, :], axis=-1).max(axis=(0, 1))
    assert 10 <= disp["rca"].max() <= 20 and disp["rca"].min() >= 10       # RCA 10-20 mm
    assert 5 <= disp["lad"].max() <= 10 and 5 <= disp["lad"].mean() <= 10  # LAD 5-10 mm


def test_hu_at_known_points(phantom):
    mw = phantom.cfg.mu_water_per_mm
    for c, a in ((0.0, 0.0), (0.38, 1.0)):
        objs = phantom.objects(c, a)
        hu = lambda p, objs=objs: float(mu_to_hu(ph.mu_at(objs, np.asarray(p, float)), mw))  # noqa: E731
        assert hu(phantom.lv_blood_pool_centre(c, a)) == pytest.approx(ph.P["hu_blood_left"], abs=tol("hu"))
        lung = ph.P["hu_lung_exhale"] + (ph.P["hu_lung_inhale"] - ph.P["hu_lung_exhale"]) * a
        assert hu([-100.0, 20.0, 60.0]) == pytest.approx(lung, abs=tol("hu"))
        assert hu([-60.0, 0.0, -120.0]) == pytest.approx(ph.P["hu_liver"], abs=tol("hu"))
        assert hu([0.0, ph.P["vertebra_y"], 0.0]) == pytest.approx(ph.P["hu_trabecular_bone"], abs=tol("hu"))
        assert hu([150.0, 0.0, 0.0]) == pytest.approx(ph.P["hu_fat"], abs=tol("hu"))
        assert hu([0.0, 0.0, 290.0]) == pytest.approx(ph.P["hu_air"], abs=tol("hu"))  # trachea
        assert hu([0.0, 200.0, 0.0]) == pytest.approx(-1000.0, abs=tol("hu"))        # outside
    # myocardium: the LV wall midway between the cavity and the epicardium
    objs = phantom.objects(0.0, 0.0)
    o = objs[phantom.names.index("lv_blood")]
    a_, b_, ao, bo = (float(x) for x in ph.lv_shape(0.0))
    p = o[ph.CENTRE] + 0.5 * (b_ + bo) * o[ph.AXES].reshape(3, 3)[:, 2]
    assert float(mu_to_hu(ph.mu_at(objs, p), 0.0193)) == pytest.approx(ph.P["hu_myocardium"], abs=tol("hu"))


def test_mu_water_scales_everything():
    a = ph.Phantom(PhantomConfig(mu_water_per_mm=0.02))
    b = ph.Phantom()
    p = np.array([[-100.0, 20.0, 60.0], [0.0, 46.0, 0.0]])
    ha = mu_to_hu(ph.mu_at(a.objects(0.2, 0.2), p), 0.02)
    hb = mu_to_hu(ph.mu_at(b.objects(0.2, 0.2), p), 0.0193)
    np.testing.assert_allclose(ha, hb, atol=1e-9)
    assert hu_to_mu(0.0, 0.02) == 0.02


def test_metal_insert():
    plain = ph.Phantom()
    metal = ph.Phantom(PhantomConfig(metal_insert=True))
    assert "metal_insert" not in plain.names and "metal_insert" in metal.names
    o = metal.objects(0.0, 0.0)[metal.names.index("metal_insert")]
    assert o[ph.SEMI][0] == pytest.approx(3.0, abs=1.0)
    hu = mu_to_hu(ph.mu_at(metal.objects(0.0, 0.0), o[ph.CENTRE]), metal.cfg.mu_water_per_mm)
    assert hu >= 3000


def test_voxelise_shape_and_values(phantom):
    x = np.linspace(-150, 150, 61)
    y = np.linspace(-100, 100, 41)
    z = np.array([0.0, 5.0])
    mu = phantom.voxelise(0.1, 0.2, x, y, z, supersample=2)
    assert mu.shape == (2, 41, 61) and mu.dtype == np.float32
    hu = mu_to_hu(mu, phantom.cfg.mu_water_per_mm)
    assert hu.min() >= -1000.5 and hu.max() < 1500
    assert (hu < -600).mean() > 0.1                    # lungs are there
    box = phantom.heart_box_mm()
    assert box[0] < phantom.lv_blood_pool_centre(0, 0)[0] < box[1]


def test_default_small_fov_holds_the_heart(phantom):
    from clrecon.config.scene import ReconConfig
    x0, x1, y0, y1 = ReconConfig().small_fov_mm
    b = phantom.heart_box_mm(margin=5.0)
    assert x0 <= b[0] and b[1] <= x1 and y0 <= b[2] and b[3] <= y1
    # and it is a box around the heart, not the whole chest
    assert (x1 - x0) * (y1 - y0) < 0.4 * (2 * ph.P["body_semi_lr"]) * (2 * ph.P["body_semi_ap"])


# ---------------------------------------------------------------------------------------
# the LV-wall target lesion (clrecon.evaluation.motion's localisation metric)
def test_lesion_rides_on_the_lv_wall(phantom):
    """Over the beat and the breath the lesion's centre stays in the LV wall: its distance from
    the LV centre minus its radius clears the cavity, plus its radius stays inside the epicardium,
    it sits in the equatorial plane, and every point of the sphere is myocardium, not blood."""
    r = ph.P["lesion_radius"]
    xi = ph.heart_axes()[0]
    i_myo, i_blood = phantom.names.index("lv_myocardium"), phantom.names.index("lv_blood")
    i_les = phantom.names.index("lesion")
    assert phantom.parents[i_les] == "lv_myocardium"
    rng = np.random.default_rng(3)
    shell = rng.normal(size=(400, 3))
    shell /= np.linalg.norm(shell, axis=1, keepdims=True)
    ball = shell * r * rng.uniform(0, 1, (400, 1)) ** (1 / 3)
    positions = []
    for c in np.linspace(0, 1, 21)[:-1]:
        for a in (0.0, 0.5, 1.0):
            _, b, _, b_out = (float(v) for v in ph.lv_shape(c))
            p, lv = phantom.lesion_centre(c, a), phantom.lv_blood_pool_centre(c, a)
            d = np.linalg.norm(p - lv)
            assert b + r < d < b_out - r, (c, a, d, b, b_out)
            assert abs(np.dot(p - lv, xi)) < 1e-9          # on the equator
            objs = phantom.objects(c, a)
            pts = np.concatenate([p + shell * (r - 1e-6), p + ball])
            assert ph.inside(objs[i_les], pts).all()
            assert ph.inside(objs[i_myo], pts).all() and not ph.inside(objs[i_blood], pts).any()
            hu = mu_to_hu(ph.mu_at(objs, p), phantom.cfg.mu_water_per_mm)
            assert float(hu) == pytest.approx(ph.P["hu_lesion"], abs=tol("hu"))
            positions.append(p)
    positions = np.array(positions)
    # it moves: with the wall (beat) and with the heart (breathing)
    assert np.ptp(positions, axis=0).max() > 5.0
    np.testing.assert_allclose(phantom.lesion_centre(0.2, 1.0) - phantom.lesion_centre(0.2, 0.0),
                               phantom.lv_blood_pool_centre(0.2, 1.0) - phantom.lv_blood_pool_centre(0.2, 0.0),
                               atol=1e-9)


def test_lesion_is_inside_the_demo_slab_and_small_fov(phantom):
    """The demo's slab and small FOV hold the whole lesion at every state, and the lesion stays
    clear of the slice nearest the LV centre (where the edge-width profiles are cast)."""
    s = load_scene("demo")
    half = 0.5 * (s.recon.nz - 1) * s.recon.slice_mm
    z0, z1 = s.scan.z_centre_mm - half, s.scan.z_centre_mm + half      # first and last slice centres
    x0, x1, y0, y1 = s.recon.small_fov_mm
    r = ph.P["lesion_radius"]
    for c in np.linspace(0, 1, 41)[:-1]:
        for a in (0.0, 1.0):
            p = phantom.lesion_centre(c, a)
            assert z0 + r < p[2] < z1 - r and x0 + r < p[0] < x1 - r and y0 + r < p[1] < y1 - r, (c, a, p)
            lv_z = phantom.lv_blood_pool_centre(c, a)[2]
            assert abs(p[2] - lv_z) - r > 0.5 * s.recon.slice_mm, (c, a)


def test_prefetched_and_cached_states_are_the_states_posed_alone():
    """``prefetch`` poses many states in one vectorised call and ``objects`` keeps them: the
    numbers must be those of posing each state alone (bit for bit), and a caller that
    modifies what ``objects`` returned must not change the cache."""
    rng = np.random.default_rng(3)
    c, a = rng.random(7), rng.random(7)
    alone = [ph.Phantom().objects(ci, ai) for ci, ai in zip(c, a, strict=True)]
    phantom = ph.Phantom()
    phantom.prefetch(c, a)
    for k in range(7):
        got = phantom.objects(c[k], a[k])
        np.testing.assert_array_equal(got, alone[k])
        got[:] = 0.0
        np.testing.assert_array_equal(phantom.objects(c[k], a[k]), alone[k])
    np.testing.assert_array_equal(phantom.objects(0.5, 0.5), ph.Phantom().objects(0.5, 0.5))  # a state not prefetched
