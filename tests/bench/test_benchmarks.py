"""The A/B benchmarks and studies of ``benchmarks/`` (outside the wheel) at tiny sizes: each row
runs its lever and its reference on the same data and says whether they agree (no timed assertions)."""

from __future__ import annotations

import pytest

from benchmarks import levers
from benchmarks.backprojector import bench_backprojector, report_lines


def test_backprojector_section_tiny():
    """Every option runs on the same sinograms; speedup is over direct; the images are compared."""
    res = bench_backprojector(scene="tiny", n_images=3, repeats=1)
    assert set(res["options"]) == {"direct", "parallel-rebin"}
    o = res["options"]
    assert o["direct"]["speedup"] == 1.0
    assert o["parallel-rebin"]["speedup"] == pytest.approx(
        o["parallel-rebin"]["images_per_s"] / o["direct"]["images_per_s"])
    pd = res["pixel_diff_hu"]
    assert 0.0 < pd["rms"] <= pd["max"] < 1e4
    text = "\n".join(report_lines(res))
    assert "parallel-rebin" in text


def test_mc_backproject_bench_tiny():
    """The motion-compensated kernel, its other lane build and the scalar kernel on the same buffers
    of each installed CPU driver; outputs agree to float32 rounding
    (tests/reconstruction/test_motion_compensation.py)."""
    from benchmarks.mc_backproject import bench_mc_backproject
    from benchmarks.mc_backproject import report_lines as mc_lines

    res = bench_mc_backproject(quick=True, repeats=1, scene="tiny")
    measured = {k: d for k, d in res["drivers"].items() if "error" not in d}
    assert measured and res["updates"] > 0
    for d in measured.values():
        assert d["max_rel_diff"] < 2e-5 and d["max_rel_diff_other"] < 2e-5
        assert {d["lanes"], d["other_lanes"]} == {8, 16}
        assert d["speedup"] == pytest.approx(d["median_s"]["old"] / d["median_s"]["new"])
        assert d["updates_per_s"]["new"] == pytest.approx(res["updates"] / d["median_s"]["new"])
    text = "\n".join(mc_lines(res))
    assert all(name in text for name in res["drivers"])


def test_levers_section_reports_each_lever_against_its_reference(monkeypatch):
    """The volume row writes, assembles and reads both settings (the uncompressed one on more disk);
    the posing row poses the same states both ways; speedups are the reference over the lever."""
    small = levers._ct_like
    monkeypatch.setattr(levers, "_ct_like", lambda shape, k: small((2, 1, 8, 32, 32), k))
    res = levers.bench_levers(quick=True, repeats=1, metrics_scene="tiny", write_scene="tiny", simulate_scene="tiny",
                              store_scene="tiny")
    v, p = res["volumes"], res["posing"]
    assert v["datasets"] == 2 and v["raw_bytes"] == 2 * 2 * 8 * 32 * 32 * 4
    assert v["median"]["none"]["disk_bytes"] > v["median"]["lzf"]["disk_bytes"] > 0
    assert v["speedup"] == pytest.approx(v["total_s"]["lzf"] / v["total_s"]["none"])
    assert p["block"] == p["chunk"] * levers.simulate_mod.BLOCK_CHUNKS and p["repeats"] >= 2
    assert p["speedup"] == pytest.approx(p["median_s"]["chunk"] / p["median_s"]["block"])
    text = "\n".join(levers.report_lines(res))
    assert "phantom posing" in text and "volumes" in text
    m = res["metrics"]
    assert m["identical"] is True and m["volumes"] == 2 and set(m["median_s"]) == {"1", "2"}
    assert "metrics stage" in text and "bit-identical" in text
    t2 = res["table2_kept"]  # kept arrays against the fresh-array formula: the same float64 sums
    assert t2["identical"] is True and t2["shape"][0] == 8 and "Table-2 sums per volume" in text
    a = res["assembly"]   # in place against format 2's copy, on the same units: the same values read back
    assert a["identical"] is True and a["datasets"] == 2 and set(a["median"]) == {"copy", "in_place"}
    assert a["speedup"] == pytest.approx(a["median"]["copy"]["assemble_s"] / a["median"]["in_place"]["assemble_s"])
    assert "volume assembly" in text
    wb = res["write_behind"]  # the same unit values written behind and in the foreground
    assert wb["identical"] is True and wb["steps"] == 3 and set(wb["median_s"]) == {"behind", "foreground"}
    assert wb["unit_shape"] == [2, 1, 8, 32, 32] and wb["write_step_s"] > 0 and wb["backproject_step_s"] > 0
    assert wb["speedup"] == pytest.approx(wb["median_s"]["foreground"] / wb["median_s"]["behind"])
    assert "write behind" in text
    sb = res["simulate_behind"]  # the same projections stored either way
    assert sb["identical"] is True and sb["scene"] == "tiny" and set(sb["median_s"]) == {"behind", "foreground"}
    assert sb["speedup"] == pytest.approx(sb["median_s"]["foreground"] / sb["median_s"]["behind"])
    assert "simulation written behind" in text
    il = res["interp_launch"]  # now against before on the same launches: the same images
    assert il["scene"] == "tiny" and set(il["by_k"]) == {"3", "8"}
    for r in il["by_k"].values():
        assert r["identical"] is True
        assert set(r["median_s"]) == {"before", "fresh", "lanes", "now", "interp_lanes", "interp_now"}
        assert r["speedup"] == pytest.approx(r["median_s"]["before"] / r["median_s"]["now"])
        assert r["speedup"] == pytest.approx(r["kernel_speedup"] * r["scratch_speedup"] * r["cols8_speedup"])
        assert r["cols8_interp_speedup"] == pytest.approx(r["median_s"]["interp_lanes"] / r["median_s"]["interp_now"])
    assert "interpolation + backprojection launches" in text
    rs = res["rows_shared"]  # rows read in place against copied: the same sinograms
    assert rs["identical"] is True and rs["in_place"] is True and rs["scene"] == "tiny"
    assert rs["rows_bytes"] >= 64 << 20 and set(rs["median_s"]) == {"shared", "copied"}
    assert rs["speedup"] == pytest.approx(rs["median_s"]["copied"] / rs["median_s"]["shared"])
    assert "a slab's rows to the device" in text
    sr = res["store_rows"]  # rows chunked in blocks of 8 against whole projections: the same floats read
    assert sr["identical"] is True and sr["scene"] == "tiny" and set(sr["speedup"]) == {"slab", "whole"}
    assert sr["chunks"]["rows"][1] == min(8, sr["detector"][0]) and sr["chunks"]["projections"][1] == sr["detector"][0]
    assert sr["speedup"]["slab"] == pytest.approx(sr["median_s"]["projections/slab"] / sr["median_s"]["rows/slab"])
    assert "projection store read" in text
    ob = res["objects_shared"]  # posed objects read in place against copied: the same projections
    assert ob["identical"] is True and ob["scene"] == "tiny" and ob["projections"] > 0
    assert ob["speedup"] == pytest.approx(ob["median_s"]["copied"] / ob["median_s"]["shared"])
    assert "posed objects to the projector" in text


def test_levers_rows_can_be_picked():
    res = levers.bench_levers(quick=True, repeats=1, only=("posing",))
    assert set(res) == {"posing"} and "phantom posing" in "\n".join(levers.report_lines(res))
    with pytest.raises(SystemExit, match="rows are"):
        levers.bench_levers(quick=True, only=("nope",))


def test_mc_reads_study_runs_its_builds_on_tiny():
    """benchmarks/studies/motion-model/mc_reads.py: its substitutions still match the production
    kernel once each (else it stops), and the study kernel computes the production kernel's images
    (plain and with paired taps) to float32 rounding; the read variants differ by construction."""
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parents[2] / "benchmarks" / "studies" / "motion-model" / "mc_reads.py"
    spec = importlib.util.spec_from_file_location("mc_reads", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    res = mod.run(repeats=1, scene="tiny", n_slices=2)
    d = res["max_diff_over_max"]
    assert d["vec"] < 2e-5 and d["vec-pair"] < 2e-5
    assert d["lanes-noread"] > 1e-3 and d["vec-noread"] > 1e-3
    assert res["static_single_max_diff_over_max"] < 2e-5
    assert all(v > 0 for v in res["m_updates_per_s"].values())
