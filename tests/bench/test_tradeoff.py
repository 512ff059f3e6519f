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
            "points": rows, "fronts": tr.fronts(rows), "quick": False}


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
