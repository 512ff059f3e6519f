"""The error-against-run-time sweep: Pareto fronts, the sweep's points, the figure, the bench wiring,
and one quick sweep on ``tiny``."""

from __future__ import annotations

import json

import numpy as np
import pytest

from clrecon.bench import suite as bench
from clrecon.bench import tradeoff as tr
from clrecon.config.scene import load_scene
from clrecon.core.errors import ClreconError
from clrecon.reconstruction.motion import method as mcm


def _dominated(i, s, e):
    return any(s[j] <= s[i] and e[j] <= e[i] and (s[j] < s[i] or e[j] < e[i]) for j in range(len(s)))


def test_pareto_front_is_exactly_the_undominated_points():
    rng = np.random.default_rng(0)
    for _ in range(50):
        n = int(rng.integers(1, 15))
        s, e = rng.random(n).tolist(), rng.random(n).tolist()
        front = tr.pareto_front(s, e)
        assert sorted(front) == [i for i in range(n) if not _dominated(i, s, e)]
        assert [s[i] for i in front] == sorted(s[i] for i in front)          # fastest first
        assert all(e[a] > e[b] for a, b in zip(front, front[1:], strict=False))  # error falls along it


def test_sweep_points_cover_the_knobs_once_each():
    demo = load_scene("demo")
    pts = tr.sweep_points(demo)
    names = [p.name for p in pts]
    assert len(names) == len(set(names))
    ll = {p.code for p in pts if p.method == "local_linear"}
    assert {"q1", "q2", "q3", "n5", "n8", "κ0.5", "κ2", "σ0.1", "σ0.3", "v180", "64²", "v180 64²"} == ll
    for m in tr.TURN_METHODS:
        assert {p.code for p in pts if p.method == m} == {"all", "t4", "t2", "v180", "64²", "v180 64²"}
    mc = {p.code: p for p in pts if p.method == "mc"}
    assert set(mc) == {"r2", "r1", "ds2", "tvl1", "skimage", "z64"} and mc["r2"].knob == "base"
    assert mc["z64"].run_slices == (0, demo.recon.nz) and not mc["z64"].recon   # base knobs, every slice
    knobs = {c: demo.replace(recon=p.recon).recon.mc if p.recon else demo.recon.mc for c, p in mc.items()}
    assert all(p.run_slices is None for p in pts if p.code != "z64")
    assert (knobs["r2"].rounds, knobs["r2"].downsample, knobs["r2"].registration) == (2, 0, "lucas_kanade_cl")
    assert mcm.factor_of(demo.recon.nx, demo.recon.ny, demo.recon.voxel_mm, knobs["r2"]) == 1  # auto: demo's 3 mm
    assert knobs["r1"].rounds == 1 and knobs["ds2"].downsample == 2 and knobs["tvl1"].registration == "tvl1"
    assert (knobs["skimage"].registration, knobs["skimage"].beat_registration) == ("lucas_kanade", "tvl1")
    # only the scikit-image point needs the motion extra (mcir's points use the base's registrations)
    assert [p.name for p in pts if tr.needs_motion_extra(demo, p)] == ["mc-skimage"]
    assert tr.run_methods("mc") == ("barycentric", "mc") and tr.run_methods("nearest") == ("nearest",)
    assert not any(p.method == "mc" for p in tr.sweep_points(demo, quick=True))
    g = next(p for p in pts if p.code == "64²")
    assert g.recon["nx"] * g.recon["voxel_mm"] == demo.recon.nx * demo.recon.voxel_mm   # same FOV
    for p in pts:   # every point is a valid scene
        demo.replace(**{k: v for k, v in (("recon", p.recon), ("scanner", p.scanner)) if v})


def _fake_result():
    rng = np.random.default_rng(1)
    rows = []
    for m in ("local_linear", "barycentric", "nearest"):
        for code in ("a", "b", "c", "d"):
            for v in ("noise-free", "noisy"):
                rows.append({"method": m, "code": code, "variant": v, "mae_small_hu": float(20 + 10 * rng.random()),
                             "mae_large_hu": float(15 + 5 * rng.random()), "seconds": float(10 ** rng.uniform(-1, 1)),
                             "plan_seconds": 0.1})
    return {"scene": "demo", "pitch": 0.02, "slices": [6, 10], "slices_z_mm": [-6.0, -2.0, 2.0, 6.0],
            "points": rows, "fronts": tr.fronts(rows), "quick": False, "targets": "all"}


def test_fronts_and_figure_and_table(tmp_path):
    res = _fake_result()
    for v, bym in res["fronts"].items():
        for m, codes in bym.items():
            sel = [r for r in res["points"] if r["variant"] == v and r["method"] == m]
            want = [sel[i]["code"] for i in tr.pareto_front([r["seconds"] for r in sel],
                                                            [r["mae_small_hu"] for r in sel])]
            assert codes == want and codes
    path = tr.plot_tradeoff(res, tmp_path / "t.png")
    assert path.stat().st_size > 10_000
    text = tr.format_table(res)
    assert text.count("\n") == len(res["points"]) and "*" in text


def test_bench_tradeoff_only_on_request():
    assert "tradeoff" not in bench.SECTIONS and "tradeoff" in bench.EXTRA_SECTIONS
    with pytest.raises(ClreconError, match="tradeoff"):
        bench.run_bench(quick=True, only=["nope"])


@pytest.mark.parametrize("quick", [True])
def test_quick_sweep_on_tiny(tmp_path, quick):
    res = tr.run_tradeoff(quick=quick, scene="tiny", pitch=0.1, out_dir=tmp_path, log=lambda *a, **k: None)
    assert (tmp_path / "tradeoff.png").stat().st_size > 10_000
    back = json.loads((tmp_path / "tradeoff.json").read_text())
    assert len(back["points"]) == 2 * len(tr.sweep_points(load_scene("tiny"), quick=True))   # two noise variants
    assert not (tmp_path / "runs").exists() or not any((tmp_path / "runs").iterdir())        # run dirs removed
    for r in back["points"]:
        assert r["seconds"] >= r["plan_seconds"] >= 0 and np.isfinite(r["mae_small_hu"])
    assert back["load_average_1min"]["samples"]
    text = bench.format_report({"machine": bench.machine(), "tradeoff": res})
    assert "error against run time" in text and "local_linear" in text


def test_mc_points_on_tiny_are_made_with_their_first_pass_merged_and_labelled(tmp_path, monkeypatch):
    """mc's five points run (barycentric first pass + mc), each with its knob reaching the run (its
    registrations kept in the row); a point's seconds are the two methods' method_seconds together;
    scikit-image's Lucas-Kanade (``skimage``) makes the base's (the OpenCL Lucas-Kanade's) MAE to the
    hundredth of a HU; merged into an earlier sweep they replace only its mc points, and the figure
    labels them by knob code."""
    res = tr.run_tradeoff(scene="tiny", pitch=0.1, out_dir=tmp_path, methods=("mc",), warmup=False, repeats=1,
                          log=lambda *a, **k: None)
    rows = res["points"]
    assert {r["method"] for r in rows} == {"mc"} and res["methods"] == ["mc"]
    assert sorted((r["code"], r["variant"]) for r in rows) == sorted(
        (c, v) for c in ("r2", "r1", "ds2", "tvl1", "skimage") for v in ("noise-free", "noisy"))
    breathing = {"tvl1": "tvl1", "skimage": "lucas_kanade"}
    for r in rows:
        parts = r["seconds_parts"]
        assert list(parts) == ["barycentric", "mc"] and min(parts.values()) > 0
        assert r["seconds"] == pytest.approx(sum(parts.values()), abs=1.5e-3) and r["seconds"] > parts["mc"]
        assert r["model_error"]["heart"]["rms_mm"] > 0 and r["model_seconds"] > 0
        assert "cover 10 mm of z" in r["warning"]    # tiny's 2 slices: thinner than mc's THIN_Z_MM
        assert r["registrations"]["breathing"] == breathing.get(r["code"], "lucas_kanade_cl"), r["registrations"]
    nf = {r["code"]: r["mae_small_hu"] for r in rows if r["variant"] == "noise-free"}
    assert len({nf[c] for c in ("r2", "r1", "ds2", "tvl1")}) == 4   # each knob changed what the run made
    for r in rows:   # the same Lucas-Kanade by scikit-image: the base's MAE to the hundredth
        base_row = next(b for b in rows if b["code"] == "r2" and b["variant"] == r["variant"])
        if r["code"] == "skimage":
            for fov in ("small", "large"):
                assert abs(r[f"mae_{fov}_hu"] - base_row[f"mae_{fov}_hu"]) < 0.01, (r, base_row)
    # merged into an earlier sweep: its other methods kept, its mc points replaced
    base = _fake_result()
    for r in base["points"]:
        r["name"] = f"{r['method']}-{r['code']}"
    base.update(scene=res["scene"], pitch=res["pitch"], slices=res["slices"], quick=False)
    old_mc = dict(base["points"][0], method="mc", code="r1", name="mc-r1")
    base["points"].append(old_mc)
    merged = tr.merge_results(base, res)
    assert [r for r in merged["points"] if r["method"] != "mc"] == base["points"][:-1]
    assert [r for r in merged["points"] if r["method"] == "mc"] == rows
    assert merged["fronts"]["noisy"]["mc"] and merged["added"][-1]["methods"] == ["mc"]
    again = tr.merge_results(merged, dict(res, points=rows[:2], run_points=[rows[0]["name"]]))  # one point again
    assert len(again["points"]) == len(merged["points"]) and len(again["added"]) == 2
    with pytest.raises(ClreconError, match="slices"):
        tr.merge_results(dict(base, slices=[0, 1]), res)
    with pytest.raises(ClreconError, match="no point"):
        tr.run_tradeoff(scene="tiny", pitch=0.1, out_dir=tmp_path, methods=("nope",))
    labels = []
    monkeypatch.setattr(tr, "_place_labels", lambda fig, ax, items, **kw: labels.extend(items))
    tr.plot_tradeoff(merged, tmp_path / "merged.png")
    mc_colour = tr._method_style()["mc"][0]
    assert sorted(t for _, _, t, c in labels if c == mc_colour) == sorted(["r2", "r1", "ds2", "tvl1", "skimage"] * 2)


def test_a_point_run_on_more_slices_is_scored_on_the_sweeps_slices(tmp_path, monkeypatch):
    """A point with ``run_slices`` (mc's z point) runs every slice of that range and is scored on
    the sweep's: barycentric (slice by slice) scores on tiny's second slice the same from a run
    of both slices as from a run of that slice alone; the run's own MAE of both slices is kept."""
    pts = [tr.SweepPoint("barycentric", "all", "base"), tr.SweepPoint("barycentric", "wide", "x", run_slices=(0, 2))]
    monkeypatch.setattr(tr, "sweep_points", lambda scene, quick=False: pts)
    res = tr.run_tradeoff(scene="tiny", pitch=0.1, out_dir=tmp_path, slices=(1, 2), warmup=False, repeats=1,
                          log=lambda *a, **k: None)
    for v in ("noise-free", "noisy"):
        one, wide = (next(r for r in res["points"] if r["code"] == c and r["variant"] == v) for c in ("all", "wide"))
        assert "mae_run_slices_hu" not in one
        for fov in ("small", "large"):
            assert wide[f"mae_{fov}_hu"] == pytest.approx(one[f"mae_{fov}_hu"], rel=1e-5)
            assert wide["mae_run_slices_hu"][fov] != pytest.approx(one[f"mae_{fov}_hu"], rel=1e-3)


def test_the_full_sweep_runs_without_the_motion_extra_less_the_scikit_image_points(tmp_path, monkeypatch):
    """Without scikit-image the full sweep leaves out the points registering with it (``registration =
    "lucas_kanade"``) and says so; asked for by name, such a point is refused. (The default
    registrations need no extra: tests/pipeline/test_mc_method.py runs mc without it.)"""
    def missing(module="skimage"):
        raise ClreconError(f"{module} is not installed")

    monkeypatch.setattr(tr.registration, "require", missing)
    sk = tr.SweepPoint("mc", "skimage", "registration", {"mc": {"registration": "lucas_kanade"}})
    monkeypatch.setattr(tr, "sweep_points", lambda scene, quick=False: [tr.SweepPoint("nearest", "all", "base"), sk])
    res = tr.run_tradeoff(scene="tiny", pitch=0.1, out_dir=tmp_path, warmup=False, repeats=1, log=lambda *a, **k: None)
    assert {r["method"] for r in res["points"]} == {"nearest"}
    assert res["skipped"]["mc"].startswith("skimage: ") and "not installed" in res["skipped"]["mc"]
    assert res["run_points"] == ["nearest-all"]
    with pytest.raises(ClreconError, match="not installed"):
        tr.run_tradeoff(scene="tiny", pitch=0.1, out_dir=tmp_path / "mc", methods=("mc",), warmup=False, repeats=1,
                        log=lambda *a, **k: None)


def test_mcir_points_run_with_their_first_pass_and_mc_and_count_the_motion_model_once(tmp_path, monkeypatch):
    """mcir's points (stubbed runs, no reconstruction): the epochs and init knobs reach the run's
    scene; a point with mc's start runs (first pass, mc, mcir), the 'zero' point (first pass, mcir);
    a point's seconds are its methods' method_seconds with the motion model's fit, which every
    second-pass method's method_seconds holds, counted once; the solver's figures are kept."""
    demo = load_scene("demo")
    pts = {p.code: p for p in tr.sweep_points(demo) if p.method == tr.mcir.NAME}
    assert set(pts) == {"e4", "e2", "e1", "zero"} and pts["e1"].knob == "base" and not pts["e1"].recon
    fp = tr._methods.first_pass(tr.mcir.NAME)
    assert tr.run_methods(tr.mcir.NAME, pts["e1"].also) == (fp, tr.mc_fbp.NAME, tr.mcir.NAME)
    assert tr.run_methods(tr.mcir.NAME, pts["zero"].also) == (fp, tr.mcir.NAME)
    assert tr.run_methods(tr.mc_fbp.NAME, (tr.mc_fbp.NAME,)) == (fp, tr.mc_fbp.NAME)
    assert not any(p.method == tr.mcir.NAME for p in tr.sweep_points(demo, quick=True))
    # seconds: the model (6 s) is inside both mc's (10 s) and mcir's (20 s) method_seconds
    assert tr.point_seconds({fp: 1.0, "mc": 10.0, "mcir": 20.0}, 6.0) == 25.0
    assert tr.point_seconds({fp: 1.0, "mcir": 20.0}, 6.0) == 21.0          # one model user: nothing off
    assert tr.point_seconds({fp: 1.0, "mc": 10.0}, None) == 11.0

    calls = []
    model_s = {"noise-free": 6.0, "noisy": 7.0}

    def fake_run(scene, run_dir, methods, pitches, slice_range, **kw):
        pk = tr.pitch_key(pitches[0])
        ep = scene.recon.mcir.epochs
        zero = scene.recon.mcir.init == "zero"
        calls.append((tuple(methods), ep, scene.recon.mcir.init, tuple(slice_range)))
        own = {fp: 1.0, "mc": 4.0, "mcir": 3.0 * ep}        # each method's own work, s
        secs = {v: {m: own[m] + (model_s[v] if m in ("mc", "mcir") else 0.0) for m in methods} for v in model_s}
        mae = {v: {m: {fov: {"mae_hu": 30.0 - ep - (5.0 if zero else 0.0) + (v == "noisy") + (fov == "large")}
                       for fov in ("small", "large")} for m in methods} for v in model_s}
        slab = {"sart": {"initial": 0.5, "final": 0.1, "running": [0.2] * ep, "stop": "epochs"}}
        return {"metrics": {pk: mae}, "method_seconds": {pk: secs}, "method_plan_seconds": {pk: {fp: 0.25}},
                "stages": {"simulate": {"per_pitch": {pk: {"projections_simulated": 0}}},
                           "registration": {"mc": {pk: {v: {"seconds": s, "warning": "thin"}
                                                        for v, s in model_s.items()}}},
                           "mcir": {"start": "zero" if zero else "mc", "slabs": {pk: {v: {"0..3": slab}
                                                                                         for v in model_s}}}}}

    monkeypatch.setattr(tr, "run_pipeline", fake_run)
    monkeypatch.setattr(tr, "plot_tradeoff", lambda result, path: path)
    res = tr.run_tradeoff(scene=demo, out_dir=tmp_path, methods=(tr.mcir.NAME,), warmup=False, repeats=2,
                          log=lambda *a, **k: None)
    assert sorted(c[:3] for c in calls) == sorted(
        [((fp, "mc", "mcir"), e, "auto") for e in (4, 2, 1) for _ in range(2)]
        + [((fp, "mcir"), 4, "zero")] * 2)
    assert {c[3] for c in calls} == {tr.FULL_SLICES}
    rows = {(r["code"], r["variant"]): r for r in res["points"]}
    assert len(rows) == 8 and {r["method"] for r in rows.values()} == {tr.mcir.NAME}
    for (code, v), r in rows.items():
        ep = 4 if code in ("e4", "zero") else int(code[1])
        want = 1.0 + 3.0 * ep + model_s[v] + (0.0 if code == "zero" else 4.0)   # first pass + model once (+ mc)
        assert r["seconds"] == pytest.approx(want) and r["seconds_repeats"] == [r["seconds"]] * 2
        assert r["seconds_parts"][tr.mcir.NAME] == pytest.approx(3.0 * ep + model_s[v])
        assert r["model_seconds"] == model_s[v] and r["warning"] == "thin"
        assert r["solver"]["start"] == ("zero" if code == "zero" else "mc")
        assert r["solver"]["0..3"] == {"epochs": ep, "initial": 0.5, "final": 0.1, "stop": "epochs"}
        assert r["mae_small_hu"] == 30.0 - ep - (5.0 if code == "zero" else 0.0) + (v == "noisy")
    assert res["fronts"]["noise-free"][tr.mcir.NAME][0] == "e1"
