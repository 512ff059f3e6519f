"""Smoke tests of ``python -m clrecon bench`` at tiny sizes (no timed assertions)."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest

from clrecon.bench import backprojection, interpolation, memory, paper, scaling
from clrecon.bench import suite as bench
from clrecon.cli import build_parser
from clrecon.core.errors import ClreconError
from clrecon.reconstruction import fbp


def test_disk_phantom_sinograms_are_exact_chords():
    g = fbp.FanBeamGeometry(sid_mm=595.0, sdd_mm=1085.6, n_cols=64, col_pitch_mm=8.0, n_views=36, nx=16, ny=16,
                            voxel_mm=10.0)
    s = backprojection.disk_phantom_sinograms(g, 3, n_phantoms=2)
    assert s.shape == (3, 36, 64) and s.dtype == np.float32
    assert np.all(np.isfinite(s)) and s.max() > 0
    # the central ray of every view crosses the body disk (radius 0.9 R_fov) through its centre
    mid = s[0, :, 31:33].mean(axis=1)
    assert np.all(mid > 0.019 * 2 * 0.9 * g.fov_radius_mm * 0.5)
    # sinogram 2 is phantom 0 rotated by a whole number of views
    assert any(np.array_equal(s[2], np.roll(s[0], k, axis=0)) for k in range(36))


def test_backprojection_section_tiny():
    res = backprojection.run(repeats=1, nx=32, n_views=40, n_cols=60, batch=17, reference_batch=2)
    assert res["batched_gups"] > 0 and res["single_gups"] > 0
    assert res["max_rel_diff"] < 1e-4
    a = res["astra"]
    if "skipped" not in a:
        assert "image" not in a
        # same geometry: after one scale the images agree up to the weighting model
        assert a["agreement"]["correlation"] > 0.95


def test_interpolation_section_tiny():
    res = interpolation.run(repeats=1, scene="tiny", n_slices=1, methods=("nearest", "local_linear"))
    for m in ("nearest", "local_linear"):
        r = res["methods"][m]
        assert r["output_rows"] > 0 and r["rows_per_s"] > 0
        assert r["max_rel_diff_vs_reference"] < 1e-5


def test_scaling_and_memory_sections_tiny(tmp_path):
    res = scaling.run(quick=True, scene="tiny", method="nearest")
    axes = {r["axis"] for r in res["rows"]}
    assert axes == {"slices", "targets", "projections"}
    assert all(r["reconstruct_s"] > 0 for r in res["rows"])
    mem = memory.run(scene="tiny", n_slices=1, cardiac=(0.0,), resp=(0.25,), cache_dir=tmp_path)
    assert "error" not in mem, mem
    assert 0 < mem["peak_rss_mib"] < 8 * 1024
    assert mem["full_job"]["total_bytes"] > 0


def test_report_and_json(tmp_path):
    res = {"quick": True, "repeats": 1, "machine": bench.machine(),
           "interpolation": interpolation.run(repeats=1, scene="tiny", n_slices=1, methods=("nearest",))}
    text = bench.format_report(res)
    assert "interpolation" in text and "nearest" in text
    bench.write_json(res, tmp_path / "b.json")
    back = json.loads((tmp_path / "b.json").read_text())
    assert back["machine"]["logical_cores"] >= 1 and "device" in back["machine"]


def test_the_suite_dispatches_over_its_registry(monkeypatch, capsys):
    """Each section of the registry: one name, run and report_lines; the report is the machine lines
    then each present section's lines in the registry's order; ``bench --help`` names every section."""
    names = [s.name for s in bench.REGISTRY]
    assert len(names) == len(set(names)) and set(names) == set(bench.SECTIONS + bench.EXTRA_SECTIONS)
    assert all(callable(s.run) and callable(s.report_lines) for s in bench.REGISTRY)
    order = []
    fake = [bench.Section(s.name, s.run, lambda r, n=s.name: (order.append(n), [f"<{n} {r['x']}>"])[1], s.default)
            for s in bench.REGISTRY]
    monkeypatch.setattr(bench, "REGISTRY", tuple(fake))
    picked = [names[-1], names[0], names[len(names) // 2]]
    m = {"cpu_model": "cpu", "logical_cores": 2, "memory_gib": 1.0, "load_average": [0.0], "device": "dev"}
    res = {"machine": m, **{n: {"x": i} for i, n in enumerate(picked)}, names[1]: {}}  # an empty result: no lines
    text = bench.format_report(res)
    assert order == [n for n in names if n in picked]
    assert text.splitlines()[1:] == [f"<{n} {res[n]['x']}>" for n in order]
    monkeypatch.setenv("COLUMNS", "100000")  # one line per option: argparse wraps at hyphens
    with pytest.raises(SystemExit):
        build_parser().parse_args(["bench", "--help"])
    help_text = capsys.readouterr().out
    for n in names:
        assert n in help_text, n


def test_cli_bench_arguments():
    a = build_parser().parse_args(["bench", "--quick", "--json", "x.json", "--only", "projector"])
    assert a.quick and a.json == "x.json" and a.only == "projector"
    with pytest.raises(ClreconError, match="--only 'nope'"):
        bench.run_bench(quick=True, only=["nope"])


#: Keys each paper-scale section must give (what the README table and --json readers use).
PAPER_KEYS = {
    "paper-projector": ("simulate_projections_per_s", "projector_projections_per_s", "per_call", "reference",
                        "projected_whole_scan_s", "old_16_projection_figure", "max_abs_diff_vs_reference"),
    "noise": ("cells_per_s", "reference", "own_reference", "projected_whole_scan_s", "noise_mean_std"),
    "paper-fbp": ("backproject_images_per_s", "filter_rows_per_s", "reference", "filter_reference",
                  "projected_full_job"),
    "groundtruth": ("groundtruth_slice_targets_per_s", "phantom_truth_slice_targets_per_s", "reference",
                    "phantom_truth_reference", "projected_full_job"),
}


def test_paper_sections_quick_tiny(tmp_path):
    """The paper-scale sections at their --quick sizes (capped for the tiny scene) give their keys."""
    assert set(paper.SECTIONS) <= set(bench.SECTIONS)
    small = {"paper-projector": dict(n_projections=8, chunk=4), "noise": dict(n_projections=4),
             "paper-fbp": dict(n_images=3), "groundtruth": dict(n_slices=2)}
    res = {"quick": True, "repeats": 1, "machine": bench.machine()}
    for name in paper.SECTIONS:
        r = paper.run_section(name, quick=True, repeats=1, scene="tiny", **small[name])
        for key in PAPER_KEYS[name]:
            assert key in r, (name, key)
        assert r["load_average_1min_before"] >= 0
        res[name] = r
    # the references agree with what they check (exact or to rounding), whatever the speed
    assert res["paper-projector"]["max_abs_diff_vs_reference"] < 1e-5
    assert res["noise"]["own_reference"]["max_abs_diff"] == 0.0
    assert res["paper-fbp"]["reference"]["max_rel_diff"] < 1e-4
    assert res["paper-fbp"]["filter_reference"]["max_rel_diff"] < 1e-4
    assert res["groundtruth"]["reference"]["max_abs_diff_hu_in_fov"] < 1.0
    assert res["paper-fbp"]["projected_full_job"]["images"] > 0
    text = bench.format_report(res)
    for tag in ("P1.", "P2.", "P3.", "P4."):
        assert tag in text
    bench.write_json(res, tmp_path / "p.json")
    back = json.loads((tmp_path / "p.json").read_text())
    assert set(paper.SECTIONS) <= set(back)


def test_measured_section_tiny():
    from clrecon.bench.measured import bench_measured_section, report_lines

    r = bench_measured_section(quick=True, scene_name="tiny")
    assert r["views"] == 300 and r["views_per_s"] > 0 and r["read_bytes_views_per_s"] > r["views_per_s"]
    assert r["meets_goal"] == (r["views_per_s"] >= 200) and "DICOM-CT-PD import" in "\n".join(report_lines(r))


def test_iterative_section_tiny():
    from clrecon.bench.iterative import bench_iterative, report_lines

    r = bench_iterative(repeats=1, quick=True)
    assert r["rays"] == 2 * 8 * 96 and r["samples"] > r["rays"]
    assert r["project_rays_per_s"] > 0 and r["backproject_rays_per_s"] > 0 and r["warp_adjoint_voxels_per_s"] > 0
    # the pair is matched on the timed data too (tests/reconstruction/test_cone_backprojector.py: TOL["dot_rel"])
    assert r["dot_rel_projector"] <= 1e-6 and r["dot_rel_warp"] <= 1e-6
    assert "backprojector A^T" in "\n".join(report_lines(r))
    assert r["warped_pair_seconds"] > 0 and r["warped_over_static_pair"] > 0   # figures only: no timed assertion
    assert "pair A W + W^T A^T" in "\n".join(report_lines(r))
    assert r["gather_seconds"] > 0 and r["gather_pair_seconds"] > 0 and r["matched_pair_seconds"] > 0
    assert "voxel-driven B ~ A^T" in "\n".join(report_lines(r))


def test_mc_section_tiny(monkeypatch):
    """The mc section's run, its cost split and ratio, and, with scikit-image's Lucas-Kanade
    (``registration = "lucas_kanade"``, the registration that runs in a pool), the registration round
    in a pool (forced on tiny's small volumes) giving the serial round's bits."""
    from clrecon.bench.mc import bench_mc_section, report_lines
    from clrecon.config.overrides import load_scene
    from clrecon.reconstruction.motion import registration

    monkeypatch.setattr(registration, "POOL_MIN_VOXELS", 0)
    r = bench_mc_section(quick=True, repeats=1, scene=load_scene("tiny", recon__mc__registration="lucas_kanade"))
    assert r["pitch"] == 0.1 and r["reconstruction_s"] > 0 and r["mc_s"] > 0
    assert set(r["mc_parts_s"]) == {"registration", "plane_rows", "mc_backproject"}
    assert r["ratio"] == pytest.approx(r["mc_s"] / r["reconstruction_s"])
    assert set(r["mae"]) == {"noisy", "noise-free"} and all(m["mc"][0] > 0 for m in r["mae"].values())
    g = r["registration_round"]
    assert g["steps"] == {"breathing": "lucas_kanade", "beat": "tvl1"}
    cores = len(os.sched_getaffinity(0))
    assert g["workers"] == min(cores, registration.MAX_WORKERS)
    if cores > 1:
        assert g["same_bits"] is True and g["pool_s"] > 0
    k = r["kernel"]   # the motion-compensated kernel against the static one, same geometry (tiny's)
    assert k["scene"] == "tiny" and k["repeats"] == 3 and len(k["load_average_1min_repeats"]) == 3
    assert k["mc_gups"] == pytest.approx(k["mc_updates"] / k["median_s"]["mc"] / 1e9)
    assert k["static_gups"] == pytest.approx(k["static_updates"] / k["median_s"]["static"] / 1e9)
    assert k["ratio"] == pytest.approx(k["mc_gups"] / k["static_gups"]) and k["mc_updates"] > 0
    text = "\n".join(report_lines(r))
    assert "registration round" in text and "motion-compensated" in text and "static" in text


def test_mc_sections_registration_round_with_the_default_runs_in_the_process(monkeypatch):
    """The default registrations (OpenCL Lucas-Kanade, then TV-L1) run in the run's process: the round
    makes no pool (even where one would be allowed) and says which registrations it timed."""
    from clrecon.bench import mc as bench_mc
    from clrecon.config.scene import load_scene
    from clrecon.pipeline.context import resolve_targets
    from clrecon.reconstruction import reconstruct
    from clrecon.reconstruction.motion import registration

    monkeypatch.setattr(registration, "POOL_MIN_VOXELS", 0)
    monkeypatch.setattr(bench_mc, "spawned_pool", lambda n: pytest.fail(f"a pool of {n} for the default"))
    sc = load_scene("tiny")
    t = resolve_targets(sc)
    z = reconstruct.slice_positions(sc, None)
    rng = np.random.default_rng(0)
    first = rng.normal(0.0, 50.0, (len(t.cardiac), len(t.resp), len(z), sc.recon.ny, sc.recon.nx)).astype(np.float32)
    g = bench_mc._registration_round(first, sc, z, 1)
    assert g["steps"] == {"breathing": "lucas_kanade_cl", "beat": "tvl1"}
    assert g["workers"] == 1 and g["pool_s"] is None and g["serial_s"] > 0
    text = "\n".join(bench_mc.report_lines({"scene": "tiny", "pitch": 0.1, "slices": [0, len(z)], "variants": ["noisy"],
                                             "load_average_1min_before": 0.0, "run_s": 1.0, "reconstruction_s": 1.0,
                                             "mc_s": 1.0, "mc_parts_s": {}, "ratio": 1.0, "mae": {},
                                             "registration_round": g}))
    assert "breathing lucas_kanade_cl, beat tvl1" in text and "in the run's process" in text


def test_the_ab_benchmarks_are_not_sections_of_the_users_bench():
    """The lab's A/B rows live in a checkout's benchmarks/ folder: naming one says where."""
    for name, module in bench.MOVED.items():
        assert name not in bench.SECTIONS + bench.EXTRA_SECTIONS
        with pytest.raises(ClreconError, match=f"python -m {module}"):
            bench.run_bench(quick=True, only=[name])
