"""Truth-free cross-validation (clrecon.evaluation.truth_free) and the cv_tuned method."""

from __future__ import annotations

import h5py
import numpy as np
import pytest

import clrecon
from clrecon.evaluation import truth_free as tf
from clrecon.pipeline.run import run
from clrecon.reconstruction import interpolation as ip
from clrecon.reconstruction import reconstruct
from clrecon.simulation import simulate

OPTS = dict(kappa=1.0, sigma=0.15, use_cardiac=True, use_resp=True)


def _points(rng, groups=40, n=30, c_range=(0.3, 0.7)):
    """Random candidates of ``groups`` groups in c_range x [0.1, 0.9] (no wrap in c)."""
    c = rng.uniform(*c_range, size=groups * n)
    a = rng.uniform(0.1, 0.9, size=groups * n)
    off = np.arange(groups + 1) * n
    return c, a, off


def _linear_rows(c, a, n_cols=16, rng=None):
    """Rows linear in (c, a): y = b0 + b1 c + b2 a per column (c away from the wrap)."""
    rng = rng or np.random.default_rng(1)
    b = rng.normal(size=(3, n_cols))
    return (b[0] + c[:, None] * b[1] + a[:, None] * b[2]).astype(np.float64)


def test_folds_never_hold_the_held_out_row_among_its_members():
    rng = np.random.default_rng(0)
    c, a, off = _points(rng, groups=6, n=9)
    nd = rng.uniform(0.02, 0.2, size=50)
    for scheme in ("loto", "nndm", "nndm_c"):
        f = tf.make_folds(c, a, off, scheme=scheme, nn_distances=nd)
        assert f.held.size > 0
        for i in range(f.held.size):
            mem = f.member[f.offsets[i]:f.offsets[i + 1]]
            assert f.held[i] not in mem
            g = f.group[i]
            assert np.all((mem >= off[g]) & (mem < off[g + 1]))  # only its own (slice, view)
            if scheme == "nndm":  # every member at least the fold's radius from the held-out point
                dc = (c[mem] - c[f.held[i]] + 0.5) % 1.0 - 0.5
                assert np.all(np.hypot(dc, a[mem] - a[f.held[i]]) >= f.radius[i])
        if scheme == "loto":
            assert f.held.size == c.size and np.all(np.diff(f.offsets) == 8)


def test_cv_of_an_exact_method_on_linear_rows_is_zero_and_nearest_is_not():
    rng = np.random.default_rng(2)
    c, a, off = _points(rng)
    rows = _linear_rows(c, a)
    folds = {"loto": tf.make_folds(c, a, off)}
    exact = tf.Kernel("local_linear")
    # held-out points away from the corners of the cloud (there a quadrant rule may leave fewer
    # than 3 points, and local linear takes the nearest one by design)
    inner = (np.abs(c - 0.5) < 0.1) & (np.abs(a - 0.5) < 0.3)

    def masks(f):
        return {"row": np.repeat(inner[f.held][:, None], rows.shape[1], axis=1)}

    err = tf.kernel_errors(folds, rows, None, [exact, tf.Kernel("nearest")], dict(OPTS, extrapolate=True),
                           masks_of=masks)
    assert err["loto"]["nearest"]["row"]["cells"] > 100 * rows.shape[1]
    scale = float(np.sqrt(np.mean(rows ** 2)))
    assert err["loto"][exact.label]["row"]["rms_hu_mm"] < 1e-4 * scale  # float32 kernel solve
    assert err["loto"]["nearest"]["row"]["rms_hu_mm"] > 1e-2 * scale


def test_a_row_predicting_itself_would_show_held_out_rows_are_not_used():
    # i.i.d. rows: nothing predicts them. Were the held-out row among its own predictors,
    # nearest (distance 0) would give zero error; its true error is sqrt(2) sigma.
    rng = np.random.default_rng(3)
    c, a, off = _points(rng, groups=30, n=12)
    rows = rng.normal(size=(c.size, 32))
    err = tf.kernel_errors({"loto": tf.make_folds(c, a, off)}, rows, None, [tf.Kernel("nearest")], OPTS)
    assert err["loto"]["nearest"]["row"]["rms_hu_mm"] == pytest.approx(np.sqrt(2.0), rel=0.05)


def test_noise_floor_subtraction_is_unbiased():
    # linear signal (barycentric is exact inside its triangles, nearly all folds here) + known heteroscedastic noise:
    # after subtracting the held-out row's variance, E[e^2] = sum_j w_j^2 var_j, the method's
    # own noise amplification; before, that plus the held-out variance
    rng = np.random.default_rng(4)
    c, a, off = _points(rng, groups=60, n=20)
    clean = _linear_rows(c, a, n_cols=64)
    var = rng.uniform(0.5, 2.0, size=clean.shape)
    rows = clean + rng.normal(size=clean.shape) * np.sqrt(var)
    folds = tf.make_folds(c, a, off)
    k = tf.Kernel("barycentric")
    inner = (np.abs(c - 0.5) < 0.12) & (np.abs(a - 0.5) < 0.32)
    sel = inner[folds.held]

    def masks(f):
        return {"row": np.repeat(sel[:, None], rows.shape[1], axis=1)}

    err = tf.kernel_errors({"loto": folds}, rows, var, [k], OPTS, masks_of=masks)["loto"][k.label]["row"]
    idx, w = tf.fold_weights(folds, k, OPTS)
    bias = np.mean((clean[folds.held] - np.einsum("fk,fkc->fc", w, clean[idx]))[sel] ** 2)
    amp = np.mean(np.einsum("fk,fkc->fc", w ** 2, var[idx])[sel])
    assert bias < 0.01 * amp  # nearly exact (a few folds take barycentric's fallback)
    expect = bias + amp
    raw_expect = expect + np.mean(var[folds.held][sel])
    assert err["rms_hu_mm"] ** 2 == pytest.approx(expect, rel=0.03)
    assert err["rms_raw_hu_mm"] ** 2 == pytest.approx(raw_expect, rel=0.03)
    assert raw_expect > 1.5 * expect  # the floor matters: without subtraction the test would fail


def test_the_choice_follows_the_data():
    # smooth but curved noise-free rows: barycentric (the most local interpolant) predicts best;
    # pure noise: a kernel that averages more wins; nearest never. A choice that ignored the
    # data would fail one of them.
    rng = np.random.default_rng(5)
    c, a, off = _points(rng, groups=40, n=30)
    folds = {"nndm": tf.make_folds(c, a, off, scheme="nndm", nn_distances=np.full(10, 0.05))}
    kernels = tf.DEFAULT_KERNELS
    curved = np.sin(2 * np.pi * c)[:, None] * rng.normal(size=32) + np.cos(3 * np.pi * a)[:, None]
    noise = rng.normal(size=curved.shape)
    by = ("nndm", "row")
    pick_c = tf.choose(tf.kernel_errors(folds, curved, None, kernels, OPTS), kernels=kernels, by=by)["label"]
    pick_n = tf.choose(tf.kernel_errors(folds, noise, None, kernels, OPTS), kernels=kernels, by=by)["label"]
    assert pick_c == "barycentric"
    assert pick_n not in ("barycentric", "nearest")


def test_nndm_radii_come_from_the_target_distances():
    rng = np.random.default_rng(6)
    c, a, off = _points(rng, groups=10, n=15)
    targets = np.array([[0.4, 0.3], [0.6, 0.7]])
    nd = tf.target_nearest_distances(c, a, off, targets)
    assert nd.shape == (20,) and np.all(nd >= 0)
    f = tf.make_folds(c, a, off, scheme="nndm", nn_distances=nd)
    assert set(np.round(f.radius, 12)) <= set(np.round(nd, 12))


def test_heart_channels_cross_the_box():
    sc = clrecon.load_scene("tiny").scanner
    ang = np.array([0.0, 1.0, 2.5])
    centre = tf.heart_channels(ang, sc, (-5.0, 5.0, -5.0, 5.0))
    assert np.all(centre.any(axis=1)) and np.all(centre.sum(axis=1) < sc.n_cols // 4)
    far = tf.heart_channels(ang, sc, (5000.0, 5010.0, 5000.0, 5010.0))
    assert not far.any()


def test_rebinned_noise_variance_matches_monte_carlo():
    from clrecon.reconstruction import rebin
    from clrecon.simulation import noise

    sc = clrecon.load_scene("tiny")
    scanner, ncfg = sc.scanner, sc.noise
    p = np.full((2, scanner.n_rows, scanner.n_cols), 2.0, np.float32)
    slot = np.array([0, 1], np.int32)
    dz = np.array([3.3, -7.1], np.float32)
    pred = tf.rebinned_noise_variance(p, slot, dz, scanner, ncfg)
    draws = np.stack([rebin.ssrb_rows(noise.add_noise(p, np.array([0, 1]), type(ncfg)(
        i0_photons=ncfg.i0_photons, electronic_sigma=ncfg.electronic_sigma, seed=s)), slot, dz, scanner)
        for s in range(300)])
    emp = draws.astype(np.float64).var(axis=0)
    assert np.median(emp / pred) == pytest.approx(1.0, abs=0.05)


# ---------------------------------------------------------------------------------------
# the pipeline: results.json key, cv_tuned bit for bit
@pytest.fixture(scope="module")
def tiny_runs(tmp_path_factory):
    out = tmp_path_factory.mktemp("tf")
    sc = clrecon.load_scene("tiny")
    kw = dict(cache_dir=out / "cache", progress=False, log=lambda *a, **k: None)
    on = run(sc.replace(recon={"truth_free": True}), out / "on",
             methods=["barycentric", "local_linear", "nearest", "cv_tuned"], **kw)
    off = run(sc, out / "off", methods=["barycentric"], report=False, **kw)
    return out, on, off


def test_results_key_present_when_on_absent_when_off(tiny_runs):
    out, on, off = tiny_runs
    assert "truth_free" not in off and "truth_free" not in off["stages"]
    ent = on["truth_free"]["p0.100"]
    assert set(ent["errors"]) == set(on["request"]["variants"])
    assert on["stages"]["truth_free"]["ran"]
    for v in ent["errors"]:
        for s in tf.SCHEMES:
            assert set(ent["errors"][v][s]) == {k.label for k in tf.DEFAULT_KERNELS}
    assert "Truth-free cross-validation" in (out / "on" / "report.md").read_text()


def test_default_methods_exclude_cv_tuned():
    assert "cv_tuned" in ip.METHODS and "cv_tuned" not in clrecon.load_scene("demo").recon.methods
    assert ip.default_methods() == tuple(m for m in ip.METHODS if not ip.METHODS[m].opt_in)  # cv_tuned, mc


def test_cv_tuned_equals_the_chosen_kernel_bit_for_bit(tiny_runs):
    out, on, _ = tiny_runs
    choice = on["truth_free"]["p0.100"]["choice"]
    with h5py.File(out / "on" / "volumes.h5", "r") as f:
        for v, ch in choice.items():
            k = tf.Kernel.from_dict(ch["kernel"])
            assert k.label in ("barycentric", "local_linear", "nearest"), "tiny: the choice is a plain kernel here"
            a = f[f"recon/p0.100/{v}/cv_tuned"][...]
            b = f[f"recon/p0.100/{v}/{k.method}"][...]
            assert np.array_equal(a, b)


def test_cv_tuned_with_knobs_equals_the_method_with_those_knobs(tmp_path):
    # a kernel with non-default knobs: cv_tuned's plan and volumes equal local_linear run with them
    sc = clrecon.load_scene("tiny")
    cfg = reconstruct.ReconstructionConfig.from_scene(sc)
    pitch = sc.scan.pitches[0]
    from clrecon.scan.table import projection_table
    table = projection_table(sc, pitch)
    zs = reconstruct.slice_positions(sc)
    targets = reconstruct.Targets(cardiac=sc.cardiac_targets, resp=sc.resp_targets)
    import dataclasses
    tuned = dataclasses.replace(cfg, tuned=("local_linear", (("kappa", 4.0), ("sigma", 0.08))))
    knobs = dataclasses.replace(cfg, kappa=4.0, sigma=0.08)
    p1 = reconstruct.plan(tuned, table, zs, targets, ["cv_tuned"])
    p2 = reconstruct.plan(knobs, table, zs, targets, ["local_linear"])
    p0 = reconstruct.plan(cfg, table, zs, targets, ["local_linear"])
    assert np.array_equal(p1.methods["cv_tuned"].weight, p2.methods["local_linear"].weight)
    assert not np.array_equal(p0.methods["local_linear"].weight, p2.methods["local_linear"].weight)
    store = simulate.simulate(sc, pitch, needed=p1.needed_projections(len(table)), cache_dir=tmp_path, progress=False)
    v1 = reconstruct.reconstruct(tuned, store, p1)
    v2 = reconstruct.reconstruct(knobs, store, p2)
    assert np.array_equal(v1[("noise-free", "cv_tuned")], v2[("noise-free", "local_linear")])


def test_bench_truth_free_cost_and_trust_study_run_on_tiny(tmp_path):
    from benchmarks import truth_free_trust
    from clrecon.bench import truth_free

    cost = truth_free.run(quick=True, scene="tiny")
    assert cost["truth_free_s"] > 0 and cost["reconstruction_s"] > 0 and cost["ratio"] > 0
    res = truth_free_trust.run_study(tmp_path, ("tiny",), log=lambda *a, **k: None)
    an = res["analysis"]
    assert an["n_configurations"] == 2 * len(tf.DEFAULT_KERNELS)  # 1 pitch x 2 variants x kernels
    assert -1.0 <= an["spearman"]["small:nndm:heart"] <= 1.0
    assert {e["variant"] for e in an["selection"]} == {"noise-free", "noisy"}


def test_image_fold_error_is_the_fbp_of_the_fold_sinogram():
    from clrecon.reconstruction import fbp as fbp_mod

    sc = clrecon.load_scene("tiny")
    cfg = reconstruct.ReconstructionConfig.from_scene(sc)
    nv, step, C = sc.scanner.views_per_rotation, 2, sc.scanner.n_cols
    # one slice, every view has 3 candidates; fold f holds out candidate rank f % 3 of view f // 3
    off = np.arange(nv + 1) * 3
    held = np.arange(3 * nv)
    g = held // 3
    keep = (g % step) == 0
    folds = tf.Folds(held=held[keep], offsets=np.zeros(keep.sum() + 1, np.int64), member=np.zeros(0, np.int64),
                     c=np.zeros(0), a=np.zeros(0), dz=np.zeros(0), group=g[keep], radius=np.zeros(keep.sum()))
    rng = np.random.default_rng(7)
    signed = rng.normal(size=(keep.sum(), C)).astype(np.float32) * 1e-3
    masks = tf.image_masks(cfg, tuple(sc.recon.small_fov_mm))
    res = tf.image_fold_errors(folds, signed, off, nv, step, cfg.fbp, cfg.filter, masks, cfg.mu_water_per_mm)
    assert res["large"]["images"] == 3
    import dataclasses
    geo = dataclasses.replace(cfg.fbp, n_views=nv // step)
    sino = signed.reshape(nv // step, 3, C).transpose(1, 0, 2)
    img = fbp_mod.fbp(sino, geo, cfg.filter).astype(np.float64) * 1000.0 / cfg.mu_water_per_mm
    want = np.sqrt(np.mean(img[:, masks["large"]] ** 2))
    assert res["large"]["rms_hu"] == pytest.approx(want, rel=1e-6)
    zero = tf.image_fold_errors(folds, signed * 0, off, nv, step, cfg.fbp, cfg.filter, masks, cfg.mu_water_per_mm)
    assert zero["small"]["rms_hu"] == 0.0


def test_truth_free_and_cv_tuned_on_a_measured_scan(tmp_path):
    # no ground truth: the cross-validation still runs, and cv_tuned reconstructs
    from clrecon.outputs.export import export

    sc = clrecon.load_scene("tiny")
    kw = dict(cache_dir=tmp_path / "cache", progress=False, log=lambda *a, **k: None)
    run(sc.replace(recon={"truth_free": True}), tmp_path / "sim", methods=["nearest", "cv_tuned"], report=False, **kw)
    export(tmp_path / "sim", "dicom-ct-pd", out=tmp_path / "exp")
    meas = clrecon.load_scene(tmp_path / "exp" / "measured.toml").replace(recon={"truth_free": True})
    res = run(meas, tmp_path / "meas", methods=["nearest", "cv_tuned"], report=True, **kw)
    assert res["measured"] and not res["ground_truth"]["available"]
    ent = res["truth_free"]["p0.100"]
    assert list(ent["errors"]) == res["request"]["variants"]
    for v in ent["errors"]:
        assert np.isfinite(ent["errors"][v]["loto"]["barycentric"]["heart"]["rms_hu_mm"])
    with h5py.File(tmp_path / "meas" / "volumes.h5", "r") as f:
        assert any(k == "cv_tuned" for v in f["recon/p0.100"] for k in f[f"recon/p0.100/{v}"])


def test_interior_folds_are_the_loto_folds_inside_their_members():
    rng = np.random.default_rng(8)
    c, a, off = _points(rng, groups=8, n=9)
    f = tf.make_folds(c, a, off)
    fi = tf.interior_folds(f, OPTS)
    assert 0 < fi.held.size < f.held.size
    for i in range(fi.held.size):  # members unchanged, held-out point inside their hull
        j = int(np.flatnonzero(f.held == fi.held[i])[0])
        assert np.array_equal(fi.member[fi.offsets[i]:fi.offsets[i + 1]], f.member[f.offsets[j]:f.offsets[j + 1]])
        from scipy.spatial import Delaunay
        pts = np.stack([fi.c[fi.offsets[i]:fi.offsets[i + 1]], fi.a[fi.offsets[i]:fi.offsets[i + 1]]], axis=1)
        per = np.concatenate([pts + [s, 0.0] for s in (-1.0, 0.0, 1.0)])  # cardiac phase is periodic
        assert Delaunay(per).find_simplex([[0.5, 0.5]])[0] >= 0
