"""The paper's claims as measured results (``clrecon.evaluation.claims``) on synthetic results."""

from __future__ import annotations

import pytest

from clrecon.evaluation import claims
from clrecon.outputs.report import claims_markdown

KEYS = {"claim", "holds", "numbers", "detail", "pitch", "variant", "fov", "method"}


def _metrics(table: dict) -> dict:
    """{pk: {variant: {method: (large MAE, small MAE)}}} -> the results["metrics"] layout."""
    return {pk: {v: {m: {"large": {"mae_hu": lg, "std_hu": 1.0, "n_voxels": 10},
                         "small": {"mae_hu": sm, "std_hu": 1.0, "n_voxels": 5}, "per_target": {}}
                     for m, (lg, sm) in bym.items()} for v, bym in byv.items()} for pk, byv in table.items()}


def _by(cl, claim_start, **where):
    out = [c for c in cl if c["claim"].startswith(claim_start)
           and all(c.get(k) == x for k, x in where.items())]
    assert out, (claim_start, where)
    return out


ONE_PITCH = {"p0.100": {"noise-free": {"local_linear": (30.0, 20.0), "barycentric": (35.0, 25.0),
                                       "nearest": (40.0, 45.0), "bin": (41.0, 44.0), "helical": (60.0, 70.0)}}}


def test_a_claim_that_holds_one_that_fails_and_one_skipped():
    met = _metrics(ONE_PITCH)
    met["p0.100"]["noise-free"]["local_linear"]["large"]["mae_hu"] = 36.0   # above barycentric's 35
    cl = claims.evaluate_claims({"metrics": met, "respiratory_only": {}})
    for c in cl:
        assert KEYS <= set(c)
        assert (c["holds"] is None) == ("skipped" in c)
    (a_small,) = _by(cl, "interpolation", fov="small")
    assert a_small["holds"] is True and a_small["numbers"]["helical"] == 70.0 and a_small["pitch"] == "p0.100"
    (ll_large,) = _by(cl, "local linear at or below", fov="large")
    assert ll_large["holds"] is False and ll_large["detail"] == "36.0 > 35.0 HU"
    (ll_small,) = _by(cl, "local linear at or below", fov="small")
    assert ll_small["holds"] is True
    (pitch,) = _by(cl, "lower pitch below higher pitch")
    assert pitch["holds"] is None and "one pitch" in pitch["skipped"]
    # no respiratory-only comparison in the results: skipped, with the reason
    ro = _by(cl, "respiratory-only")
    assert len(ro) == 2 and all(c["holds"] is None and "r4dct" in c["skipped"] for c in ro)


def test_interpolation_claim_fails_when_one_baseline_beats_one_interpolation():
    t = {pk: {v: dict(bym) for v, bym in byv.items()} for pk, byv in ONE_PITCH.items()}
    t["p0.100"]["noise-free"]["nearest"] = (40.0, 24.0)     # below barycentric's 25 in the small FOV
    cl = claims.evaluate_claims({"metrics": _metrics(t)})
    assert _by(cl, "interpolation", fov="small")[0]["holds"] is False
    assert _by(cl, "interpolation", fov="large")[0]["holds"] is True


def test_pitch_claims_with_two_pitches_and_the_terminal_line():
    t = {"p0.020": {"noise-free": {"local_linear": (18.0, 20.3), "barycentric": (26.0, 24.0)}},
         "p0.100": {"noise-free": {"local_linear": (33.0, 41.6), "barycentric": (38.0, 34.0)}}}
    res = {"metrics": _metrics(t)}
    res["claims"] = cl = claims.evaluate_claims(res)
    p = {(c["method"], c["fov"]): c for c in _by(cl, "pitch 0.02 below 0.1")}
    assert set(p) == {(m, f) for m in ("barycentric", "local_linear") for f in ("large", "small")}
    assert all(c["holds"] for c in p.values()) and p[("local_linear", "small")]["numbers"] == {
        "pitch 0.02": 20.3, "pitch 0.1": 41.6}
    assert ("claim: pitch 0.02 below 0.1 (local_linear, noise-free, small FOV): holds (20.3 < 41.6 HU)"
            in claims.claim_lines(res))
    summary = claims.claim_summary_lines(res)
    assert "claim holds 4/4: pitch 0.02 below 0.1" in summary
    assert not any("fails" in s for s in summary if "pitch 0.02 below 0.1" in s)
    # gain of barycentric - local linear: large FOV 8.0 at 0.02 vs 5.0 at 0.1, small 3.7 vs -7.6: both hold
    g = {c["fov"]: c for c in _by(cl, "local linear's gain")}
    assert g["large"]["holds"] is True and g["large"]["numbers"]["gain at pitch 0.02"] == pytest.approx(8.0)
    assert g["small"]["holds"] is True
    # best combination: local linear at 0.02 (18.0, 20.3) is below every other (method, pitch)
    best = {c["fov"]: c for c in _by(cl, "lowest pitch with local linear")}
    assert best["large"]["holds"] is True and best["small"]["holds"] is True
    # a pitch where local linear is worse than barycentric at 0.02: the best-combination claim fails
    t["p0.020"]["noise-free"]["local_linear"] = (27.0, 20.3)
    cl2 = claims.evaluate_claims({"metrics": _metrics(t)})
    best2 = {c["fov"]: c for c in _by(cl2, "lowest pitch with local linear")}
    assert best2["large"]["holds"] is False and "barycentric, pitch 0.02" in best2["large"]["detail"]
    assert {c["fov"]: c["holds"] for c in _by(cl2, "local linear's gain")}["large"] is False


def test_pitch_claim_fails_when_the_lower_pitch_is_worse():
    t = {"p0.020": {"noisy": {"barycentric": (50.0, 24.0)}}, "p0.100": {"noisy": {"barycentric": (38.0, 34.0)}}}
    cl = claims.evaluate_claims({"metrics": _metrics(t)})
    p = {c["fov"]: c for c in _by(cl, "pitch 0.02 below 0.1")}
    assert p["large"]["holds"] is False and p["large"]["detail"] == "50.0 >= 38.0 HU" and p["small"]["holds"] is True
    # only one 5DCT method: the local-linear claims are skipped
    assert _by(cl, "local linear at or below")[0]["holds"] is None


def _ro_row(c, mae: dict, lv: dict) -> dict:
    return {"cardiac_phase": c, "small_fov_mae_hu": mae, "lv_volume_ml": lv,
            "lv_volume_spread_ml": {m: max(x) - min(x) for m, x in lv.items()}}


def test_respiratory_only_claims():
    rows = [_ro_row(0.0, {"barycentric": 20.0, "local_linear": 30.0, "r4dct": 25.0},
                    {"groundtruth": [100.0, 101.0], "barycentric": [99.0, 100.0], "local_linear": [98.0, 101.0],
                     "r4dct": [90.0, 100.0]}),
            _ro_row(0.4, {"barycentric": 22.0, "local_linear": 30.0, "r4dct": 27.0},
                    {"groundtruth": [60.0, 60.0], "barycentric": [61.0, 61.0], "local_linear": [60.0, 75.0],
                     "r4dct": [50.0, 55.0]})]
    res = {"metrics": _metrics(ONE_PITCH), "respiratory_only": {"p0.100": {"noise-free": rows}}}
    cl = claims.evaluate_claims(res)
    mae = {c["method"]: c for c in _by(cl, "respiratory-only 5DCT below r4DCT")}
    assert mae["barycentric"]["holds"] is True and mae["barycentric"]["numbers"] == {"barycentric": 21.0, "r4dct": 26.0}
    assert mae["local_linear"]["holds"] is False and mae["local_linear"]["fov"] == "small"
    lv = {c["method"]: c for c in _by(cl, "respiratory-only 5DCT LV")}
    # spread of V - V_truth: barycentric 0 and 0; local linear 2 and 15; r4dct 9 and 5
    assert lv["barycentric"]["holds"] is True and lv["barycentric"]["numbers"]["barycentric"] == 0.0
    assert lv["local_linear"]["holds"] is False and lv["local_linear"]["numbers"]["local_linear"] == 8.5
    assert lv["barycentric"]["numbers"]["r4dct"] == 7.0


def test_report_has_a_claims_section():
    res = {"metrics": _metrics(ONE_PITCH)}
    res["claims"] = claims.evaluate_claims(res)
    md = claims_markdown(res)
    assert md[0].startswith("## Claims")
    body = "\n".join(md)
    assert "| local linear at or below barycentric | pitch 0.1, noise-free, large FOV | yes | 30.0 <= 35.0 HU |" in body
    assert "| skipped | the run has one pitch (0.1) |" in body
    assert claims_markdown({"metrics": {}}) == []


def test_respiratory_only_claims_give_the_runs_own_skip_reason():
    """A run that skipped the respiratory-only study (e.g. a voxel phantom without an LV model)
    records why; the claims repeat that reason instead of a generic one."""
    t = {"p0.100": {"noise-free": {"local_linear": (18.0, 20.3), "barycentric": (26.0, 24.0)}}}
    why = "phantom.kind = 'voxel' has no LV blood-pool model (the LV volume needs it)"
    res = {"metrics": _metrics(t), "stages": {"metrics": {"respiratory_only_skipped_because": why}}}
    ro = [c for c in claims.evaluate_claims(res) if c["claim"].startswith("respiratory-only")]
    assert ro and all(c["holds"] is None and c["skipped"] == why for c in ro)
    generic = [c for c in claims.evaluate_claims({"metrics": _metrics(t)}) if c["claim"].startswith("respiratory-only")]
    assert all(c["skipped"] != why for c in generic)


def test_second_pass_goals_at_each_pitch():
    """mc's goals (issue 34): 0.75 x min(barycentric, local linear) at pitch >= 0.1 only, no worse
    than that minimum and below r4DCT at every pitch; nothing about mc where it did not run."""
    t = {"p0.100": {"noisy": {"barycentric": (40.0, 40.0), "local_linear": (42.0, 36.0), "r4dct": (30.0, 50.0),
                              "mc": (29.0, 28.0)}},        # large 29 / 40 = 0.725; small 28 / 36 = 0.78
         "p0.020": {"noisy": {"barycentric": (20.0, 20.0), "local_linear": (21.0, 22.0), "r4dct": (25.0, 30.0),
                              "mc": (19.0, 20.5)}}}
    cl = claims.evaluate_claims({"metrics": _metrics(t)})
    (g_large,) = _by(cl, "mc at or below 0.75", fov="large")
    (g_small,) = _by(cl, "mc at or below 0.75", fov="small")
    assert g_large["holds"] is True and g_large["pitch"] == "p0.100" and g_large["numbers"]["ratio"] == 29.0 / 40.0
    assert g_small["holds"] is False and "0.778 x 36.0 HU" in g_small["detail"]
    no_worse = {c["pitch"] + c["fov"]: c["holds"] for c in _by(cl, "mc at or below min(")}
    assert no_worse == {"p0.100large": True, "p0.100small": True, "p0.020large": True, "p0.020small": False}
    r4 = {c["pitch"] + c["fov"]: c["holds"] for c in _by(cl, "mc below r4DCT")}
    assert r4 == {"p0.100large": True, "p0.100small": True, "p0.020large": True, "p0.020small": True}
    # the paper's claims stay about the paper's methods: mc is in none of them
    assert not [c for c in cl if not c["claim"].startswith("mc ") and "mc" in c["numbers"]]
    assert not [c for c in claims.evaluate_claims({"metrics": _metrics(ONE_PITCH)}) if c["claim"].startswith("mc ")]
