"""Figures of a run directory (matplotlib Agg) from a fake run: files, skips, phase-space choices."""

from __future__ import annotations

import json

import numpy as np
import pytest
from fake_run_dir import fake_scene, make_fake_run

from clrecon.core.conventions import circular_difference
from clrecon.core.resources import spawned_pool
from clrecon.outputs import figures, report

ALL = ("phase_space.png", "coronal.png", "motion_rows.png", "mae_per_target_small.png",
       "mae_per_target_large.png", "error_vs_time.png", "motion_metrics.png")


def _img(path):
    import matplotlib.image as mpimg

    return mpimg.imread(path)[..., :3].mean(axis=-1)


@pytest.fixture(scope="module")
def full_run(tmp_path_factory):
    d = tmp_path_factory.mktemp("run")
    return d, make_fake_run(d)


def test_write_report_makes_every_figure_and_html(full_run):
    d, results = full_run
    md = report.write_report(d, results).read_text()
    expected = ALL
    for name in expected:
        png = d / "figures" / name
        assert f"(figures/{name})" in md
        img = _img(png)
        assert img.shape[0] > 200 and img.shape[1] > 300
        assert img.std() > 0.05, f"{name} looks blank"
    assert "failed" not in md and md.count("skipped") == len(ALL) - len(expected)
    page = (d / "report.html").read_text()
    assert page.count("data:image/png;base64,") == len(expected) and "<table>" in page


def test_phase_space_candidates_are_the_plans():
    """The figure's candidates of one (slice, view) honour recon.candidate_window_mm and
    recon.max_turns as the plan does: all projections of the view within the window, then the
    max_turns nearest in z (ties: the earlier), in projection order."""
    from clrecon.reconstruction import rebin, reconstruct
    from clrecon.scan.table import projection_table

    scene = fake_scene()
    ssrb = rebin.slice_window_mm(scene.scanner, reconstruct.object_radius_mm(scene))
    table = projection_table(scene, 0.02)
    dz = np.abs(0.0 - table.source_z_mm)
    counts = []
    for window in (0.0, 0.5 * ssrb):
        sc = scene.replace(recon={"candidate_window_mm": window})
        want = table.index[(table.view == 0) & (dz <= (window or ssrb))]
        s = figures.phase_space_sample(sc, 0.02, 0.0, 0, (0.4, 0.5))
        assert np.array_equal(s["index"], want)
        counts.append(len(want))
        near = figures.phase_space_sample(sc.replace(recon={"max_turns": 3}), 0.02, 0.0, 0, (0.4, 0.5))
        assert np.array_equal(near["index"], np.sort(want[np.lexsort((want, dz[want]))[:3]]))
    assert 3 < counts[1] < counts[0]


def test_phase_space_choices_follow_the_methods():
    pytest.importorskip("clrecon.reconstruction.interpolation.weights")
    scene = fake_scene()
    s = figures.phase_space_sample(scene, 0.02, 0.0, 0, (0.4, 0.5))
    n = len(s["c"])
    assert n >= 8 and len(s["index"]) == n
    b, ll = s["barycentric"], s["local_linear"]
    assert 1 <= len(b["index"]) <= 3 and np.all(b["weight"] > 0) and b["weight"].sum() == pytest.approx(1.0)
    assert 3 <= len(ll["index"]) <= 8 and ll["weight"].sum() == pytest.approx(1.0)
    dc = circular_difference(s["c"][ll["index"]], 0.4)
    da = s["a"][ll["index"]] - 0.5
    quadrant = (dc >= 0).astype(int) * 2 + (da >= 0).astype(int)
    assert np.bincount(quadrant, minlength=4).max() <= 2  # two nearest per quadrant
    if len(b["index"]) == 3:  # the target lies inside the chosen triangle (unwrapped)
        p = np.stack([0.4 + circular_difference(s["c"][b["index"]], 0.4), s["a"][b["index"]]], 1)
        lam = np.linalg.solve(np.vstack([p.T, np.ones(3)]), [0.4, 0.5, 1.0])
        assert np.all(lam >= -1e-9)


def test_coronal_has_physical_aspect(full_run, tmp_path):
    d, results = full_run
    run = figures._Run(d, results)
    try:
        left, right, bottom, top = run.extent()
        assert (right - left) / (top - bottom) == pytest.approx((40 * 8.0) / (10 * 6.0))
        assert run.coronal("groundtruth", 1, 1, run.heart_plane_index(1, 1)).shape == (10, 40)
    finally:
        run.close()


def test_missing_inputs_are_skipped_with_a_reason(tmp_path):
    results = make_fake_run(tmp_path, methods=("nearest", "local_linear"), pitches=(0.1,),
                            variants=("noise-free",))
    results["method_seconds"] = {}
    lines = figures.write_figures(tmp_path, results)
    text = "\n".join(lines)
    assert "no r4dct reconstruction" in text and "no method_seconds" in text
    assert (tmp_path / "figures" / "coronal.png").exists()
    assert not (tmp_path / "figures" / "motion_rows.png").exists()


def test_single_target_run(tmp_path):
    scene = fake_scene().replace(phantom={"cardiac_motion": False, "respiratory_motion": False})
    results = make_fake_run(tmp_path, methods=("local_linear",), pitches=(0.1,), variants=("noise-free",),
                            scene=scene)
    text = "\n".join(figures.write_figures(tmp_path, json.loads(json.dumps(results))))
    assert "single target" in text and "neither cardiac nor respiratory" in text
    assert "failed" not in text
    assert _img(tmp_path / "figures" / "coronal.png").std() > 0.05


def test_figures_drawn_in_a_helper_process_are_the_same(tmp_path):
    """The results-only figures drawn in a process pool (the run's helper) are those drawn here:
    the same lines in the same order, the same pixels."""
    results = make_fake_run(tmp_path / "a")
    make_fake_run(tmp_path / "b")
    here = figures.write_figures(tmp_path / "a", json.loads(json.dumps(results)))
    pool = spawned_pool(1)
    try:
        there = figures.write_figures(tmp_path / "b", json.loads(json.dumps(results)), pool=pool)
    finally:
        pool.shutdown()
    assert here == there and "failed" not in "\n".join(here)
    for p in sorted((tmp_path / "a" / "figures").glob("*.png")):
        assert np.array_equal(_img(p), _img(tmp_path / "b" / "figures" / p.name)), p.name


def test_the_consistency_figure_marks_the_slices_where_mc_is_lower_or_higher(tmp_path):
    """Per (pitch, variant) a panel of each method's residual per sampled slice; the slices where
    the verdict's per-slice comparison says lower / higher get a green / red triangle."""
    z = np.linspace(-50, 50, 12)
    says = ["lower"] * 10 + ["higher", "no clear difference"]
    per = [{"ratio": 1.0, "z": 0.0, "says": s} for s in says]
    ent = {"config": {"slices_z_mm": z.tolist()},
           "residual": {"noise-free": {"barycentric": {"per_slice_rms_hu_mm": (1400 + 10 * z).tolist()},
                                       "mc": {"per_slice_rms_hu_mm": (1300 + 10 * z).tolist()}}},
           "verdict": {"noise-free": {"helped": True, "against": "barycentric",
                                      "regions": {"all": {"per_slice": per}}}}}
    path = tmp_path / "c.png"
    caption = figures.fig_consistency_slices({"consistency": {"p0.100": ent}}, path)
    assert "sign test" in caption
    rgb = __import__("matplotlib.image").image.imread(path)[..., :3]
    green = (rgb[..., 1] > 0.45) & (rgb[..., 0] < 0.3) & (rgb[..., 2] < 0.3)   # tab:green triangles
    red = (rgb[..., 0] > 0.75) & (rgb[..., 1] < 0.25) & (rgb[..., 2] < 0.25)   # tab:red triangle
    assert green.sum() > 10 * 20 and 20 < red.sum() < green.sum() / 4, (green.sum(), red.sum())
