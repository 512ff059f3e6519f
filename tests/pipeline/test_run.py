"""`run` end to end on the tiny scene: run directory, reuse, what is skipped, motionless scenes."""

import json

import numpy as np
import pytest

from clrecon.cli import main
from clrecon.config.scene import load_scene
from clrecon.outputs.volumes import open_volumes, read_volume
from clrecon.pipeline.run import run
from clrecon.reconstruction import interpolation
from clrecon.reconstruction.interpolation import METHODS


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    return tmp_path_factory.mktemp("cache")


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory, cache):
    out = tmp_path_factory.mktemp("run")
    res = run(load_scene("tiny"), out, cache_dir=cache, progress=False, log=lambda *a: None)
    return out, res


def test_run_directory_is_complete_and_valid(tiny_run):
    out, res = tiny_run
    on_disk = json.loads((out / "results.json").read_text())
    assert on_disk["format_version"] == 1
    for key in ("scene", "versions", "device", "request", "dimensions", "stages", "metrics", "method_seconds"):
        assert key in on_disk
    assert (out / "report.md").read_text().startswith("# clrecon run")
    # phase-space sampling per pitch; tiny's periodic beat (0.3 s / 0.75 s = 2/5): at most 5 phases per view
    samp = on_disk["sampling"]["p0.100"]
    assert 1 <= samp["distinct_cardiac_phases_per_view"]["min"] <= samp["distinct_cardiac_phases_per_view"]["max"] <= 5
    assert samp["distinct_cardiac_phases_per_view"]["max"] <= samp["candidates_per_view"]["max"]
    assert "distinct cardiac phases among" in (out / "report.md").read_text()
    # measured memory and disk beside the pre-flight's model; small runs' volumes are not compressed
    assert "## Memory and disk (measured against the pre-flight model)" in (out / "report.md").read_text()
    # the machine's speed beside the stage seconds: the probe before and after, its CPUs over the run
    ms = on_disk["machine_speed"]
    assert 0 < ms["probe_seconds"]["start"] < 10 and 0 < ms["probe_seconds"]["end"] < 10
    assert 0 < ms["wall_s"] <= on_disk["total_seconds"] and ms["own_core_s"] > 0
    assert "Machine during the run: probe" in (out / "report.md").read_text()
    assert on_disk["outputs"]["volume_compression"] == "none"
    assert not list(out.glob("*.partial"))
    s = load_scene("tiny")
    with open_volumes(out) as f:
        shape = (2, 2, s.recon.nz, s.recon.ny, s.recon.nx)
        assert f["groundtruth"].shape == shape
        assert list(f["groundtruth"].attrs["dims"]) == ["cardiac", "resp", "z", "y", "x"]
        assert np.allclose(f["axes/resp_amplitude"][()], [0.25, 0.75])
        assert np.allclose(f["axes/cardiac_phase"][()], [0.0, 0.4])
        for v in ("noisy", "noise-free"):
            for m in s.recon.methods:
                name = f"recon/p0.100/{v}/{m}"
                vol = read_volume(f, name)
                assert vol.shape == shape and vol.dtype == np.float32 and np.isfinite(vol).all()
                # r4dct is stored once per amplitude, helical once (attribute "broadcast")
                grid = METHODS[m].target_grid
                assert f[name].shape == {"resp": (1, 2), "none": (1, 1)}.get(grid, (2, 2)) + shape[2:]
                assert list(f[name].attrs["broadcast"]) == {"resp": ["cardiac"], "none": ["cardiac", "resp"]}.get(
                    grid, [])
                assert np.array_equal(read_volume(f, name, (1, 0)), vol[1, 0])
        gt = f["groundtruth"][()]
    # the ground truth looks like a thorax: air outside, soft tissue and lung inside, contrast blood
    assert gt.min() < -900 and gt.max() > 200
    for v in ("noisy", "noise-free"):
        for m in s.recon.methods:
            r = res["metrics"]["p0.100"][v][m]
            assert np.isfinite(r["large"]["mae_hu"]) and r["large"]["n_voxels"] > 0
            assert len(r["per_target"]["small"]) == 2 and len(r["per_target"]["small"][0]) == 2


def test_results_carry_the_weight_diagnostics(tiny_run):
    """results.json: per pitch and method, per target (cardiac-major) the reach of the rows used
    (|dc| in [0, 0.5], |da| in [0, 1]); barycentric's branch shares; a table in report.md."""
    out, res = tiny_run
    on_disk = json.loads((out / "results.json").read_text())
    diag = on_disk["diagnostics"]["p0.100"]
    assert set(diag) == set(res["request"]["methods"])
    for m, d in diag.items():
        assert d["targets"] == [[0.0, 0.25], [0.0, 0.75], [0.4, 0.25], [0.4, 0.75]], m
        assert len(d["max_abs_dc"]) == len(d["max_abs_da"]) == 4, m
        assert all(0.0 <= x <= 0.5 for x in d["max_abs_dc"]) and all(0.0 <= x <= 1.0 for x in d["max_abs_da"]), m
    if "barycentric" in diag:
        shares = np.array(list(diag["barycentric"]["branch_share"].values()))
        assert np.allclose(shares.sum(0), 1.0)
    assert "## Interpolation diagnostics" in (out / "report.md").read_text()


def test_stage_times_name_the_whole_wall(tiny_run):
    """Writing the volume units and assembling volumes.h5 are stages of their own (they were
    the largest share of paper-p010's unaccounted wall time), no stage is counted twice (the
    remainder is not negative) and what is left is named."""
    out, _ = tiny_run
    res = json.loads((out / "results.json").read_text())
    st = res["stages"]
    for name in ("write_volumes", "assemble_volumes"):
        assert st[name]["ran"] and st[name]["seconds"] > 0, name
    assert st["unaccounted"]["seconds"] >= -0.01
    named = sum(v["seconds"] for k, v in st.items() if k != "unaccounted")
    assert named <= res["total_seconds"] + 0.01
    assert abs(named + st["unaccounted"]["seconds"] - res["total_seconds"]) < 0.01


def test_a_run_without_mc_does_not_pay_for_its_consistency_check(tiny_run):
    """The truth-free check of mc (stage consistency) is skipped and left out when mc is not asked for."""
    out, res = tiny_run
    assert "mc" not in res["request"]["methods"]
    assert "consistency" not in res and "consistency" not in res["stages"]
    assert "Did mc help?" not in (out / "report.md").read_text()


def test_second_run_reuses_the_store(tmp_path, cache, tiny_run):
    res = run(load_scene("tiny"), tmp_path, methods=["nearest"], cache_dir=cache, progress=False,
              log=lambda *a: None)
    st = res["stages"]["simulate"]
    assert st["ran"] is False and "already in the projection store" in st["skipped_because"]
    assert st["per_pitch"]["p0.100"]["projections_simulated"] == 0
    assert st["per_pitch"]["p0.100"]["projections_reused"] > 0


def test_requests_limit_the_work(tmp_path):
    s = load_scene("tiny")
    res = run(s, tmp_path, methods=["nearest"], cardiac=[0.4], resp=[0.75], slice_range=(1, 2),
              cache_dir=tmp_path / "c", progress=False, log=lambda *a: None)
    pp = res["stages"]["simulate"]["per_pitch"]["p0.100"]
    # nearest at one target and one slice touches one projection per view
    assert pp["projections_simulated"] == pp["projections_needed"] <= s.scanner.views_per_rotation
    assert pp["projections_needed"] < pp["projections_total"]
    assert list(res["metrics"]["p0.100"]["noisy"]) == ["nearest"]
    with open_volumes(tmp_path) as f:
        assert f["recon/p0.100/noisy/nearest"].shape == (1, 1, 1, s.recon.ny, s.recon.nx)


def test_noise_free_scene_skips_noise_and_motionless_axes_drop(tmp_path):
    s = load_scene("tiny").replace(noise={"enabled": False}, phantom={"cardiac_motion": False})
    res = run(s, tmp_path, methods=["local_linear", "nearest"], cache_dir=tmp_path / "c", progress=False,
              log=lambda *a: None)
    assert res["stages"]["noise"]["ran"] is False
    assert "noise.enabled = false" in res["stages"]["noise"]["skipped_because"]
    assert res["request"]["variants"] == ["noise-free"]
    assert res["dimensions"] == {"cardiac": False, "resp": True}
    with open_volumes(tmp_path) as f:
        ds = f["recon/p0.100/noise-free/local_linear"]
        assert list(ds.attrs["dims"]) == ["resp", "z", "y", "x"] and ds.ndim == 4
        assert read_volume(f, "groundtruth").shape[:2] == (1, 2)


@pytest.mark.parametrize("still", [
    {"phantom": {"cardiac_motion": False, "respiratory_motion": False}},
    {"phantom": {"cardiac_motion": False}, "signals": {"breath_hold": True}},
], ids=["motion-off", "breath-hold"])
def test_static_scene_gives_the_same_volume_for_every_method(tmp_path, still):
    """Motionless: every registered method (the registry, so a new one is covered) takes the
    same rows, so the volumes agree to float32 rounding: the only freedom left is the order of
    float32 operations (a sinogram's place in its FBP batch), a sum over the views per
    rotation, bounded by n_views * eps32 * max|HU| (0.015 HU here). Phase-blind methods
    (no phase axis, e.g. ``helical``: the turn nearest in z) choose rows by another rule, and a
    second-pass method (``mc``) reads its rows through z planes 2 mm apart instead of the
    slice's own SSRB rows: both are compared with the ground truth instead, as is ``mcir``, which
    solves a voxel volume from the cone-beam rows (its own floor against the FBP truth)."""
    s = load_scene("tiny").replace(noise={"enabled": False}, **still)
    methods = interpolation.METHODS.names
    phase_space = [m for m in methods if interpolation.METHODS[m].axes and interpolation.METHODS[m].stage is None]
    res = run(s, tmp_path, methods=list(methods), cache_dir=tmp_path / "c", progress=False, log=lambda *a: None)
    assert res["request"]["methods"] == list(methods)
    with open_volumes(tmp_path) as f:
        vols = {m: f[f"recon/p0.100/noise-free/{m}"][()] for m in methods}
        gt = f["groundtruth"][()]
    ref = vols["nearest"]
    tol = s.scanner.views_per_rotation * np.finfo(np.float32).eps * np.abs(ref).max()
    for m in phase_space:
        assert np.abs(vols[m] - ref).max() <= tol, m  # HU; all methods see the same static data
    voxel_basis = {"mcir"}  # solved on a voxel basis, not from SSRB rows: its own floor (below)
    for m in set(methods) - set(phase_space) - voxel_basis:  # another turn's SSRB rows: same error floor
        assert res["metrics"]["p0.100"]["noise-free"][m]["large"]["mae_hu"] < 15.0, m
    # mcir (OS-SART on 12-mm voxels, from mc's image) against an FBP truth: the voxel basis's own floor,
    # measured 64.1 and 57.3 HU large FOV on these two scenes (67.8 and 72.1 from zero; docs/iterative.md
    # "Coarse grids"); a geometry or sign slip gives several hundred
    for m in voxel_basis & set(methods):
        assert res["metrics"]["p0.100"]["noise-free"][m]["large"]["mae_hu"] < 100.0, m
    # and it matches the ground truth up to SSRB's cone-angle approximation
    assert res["metrics"]["p0.100"]["noise-free"]["nearest"]["large"]["mae_hu"] < 15.0
    assert gt.shape == ref.shape


def test_cli_one_line_errors(tmp_path, capsys):
    assert main(["run", "--scene", "no-such-scene", "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("clrecon: error: scene 'no-such-scene'") and err.count("\n") == 1
    assert main(["run", "--scene", "tiny", "--slices", "5:1", "--out", str(tmp_path)]) == 2
    assert "--slices 5:1" in capsys.readouterr().err


def test_scenes_listing(capsys):
    assert main(["scenes"]) == 0
    out = capsys.readouterr().out
    assert "paper-p002" in out and "160,689" in out and "900x64" in out and "512x512x110" in out
