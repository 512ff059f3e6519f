"""Scenes: validation errors name key, value and what is allowed; built-ins follow Table 1."""

import dataclasses
import math

import pytest

from clrecon.config.scene import Scene, builtin_scene_names, load_scene, scene_from_dict
from clrecon.core.errors import SceneError


def test_builtins_load():
    names = builtin_scene_names()
    for required in ("tiny", "demo", "paper-p002", "paper-p010"):
        assert required in names
    for n in names:
        if n == "stress-high-pitch":  # invalid by design: tests/scan/test_stress.py
            continue
        s = load_scene(n)
        assert s.name == n


def test_paper_p002_matches_table1():
    s = load_scene("paper-p002")
    sc = s.scanner
    assert (sc.sid_mm, sc.sdd_mm, sc.n_cols, sc.n_rows) == (595.0, 1085.6, 900, 64)
    assert (sc.col_pitch_mm, sc.row_pitch_mm, sc.views_per_rotation, sc.rotation_time_s) == (0.8, 0.8, 984, 0.3)
    assert s.scan.pitches == (0.02,)
    assert s.scan.projection_count(sc, 0.02) == 160689
    assert s.scan.duration_s(sc, 0.02) == pytest.approx(49.0, abs=0.05)
    # coverage = travel + W reproduces the paper's 119.7 mm
    assert s.scan.travel_mm(sc, 0.02) + sc.collimation_iso_mm == pytest.approx(119.7, abs=0.05)
    assert (s.recon.nx, s.recon.ny, s.recon.voxel_mm) == (512, 512, 1.0)
    assert s.recon.resp_targets == pytest.approx([0.05 + 0.1 * i for i in range(10)])
    assert s.recon.cardiac_phases == (0.0, 0.2, 0.4, 0.6, 0.8)


def test_paper_p010_derives_scan_from_coverage():
    s = load_scene("paper-p010")
    sc = s.scanner
    n = s.scan.projection_count(sc, 0.1)
    travel = 119.7 - sc.collimation_iso_mm
    assert n == round(travel / (0.1 * sc.collimation_iso_mm) * 984) + 1
    assert s.scan.duration_s(sc, 0.1) == pytest.approx(9.8, abs=0.05)


@pytest.mark.parametrize("section,key,value,fragment", [
    ("scanner", "sid_mm", -1.0, "a number in [10, 5000] mm (clinical CT"),
    ("scanner", "n_cols", 12.5, "an integer in 2..16384"),
    ("scan", "pitches", [], "a list of 1 to 64 numbers"),
    ("scan", "pitches", [0.02, 3.0], "numbers in [0.001, 2]"),
    ("signals", "rhythm", "chaotic", "one of periodic"),
    ("signals", "rr_s", 0.1, "[0.3, 2] s (heart rates of 30-200"),
    ("noise", "enabled", "yes", "true or false"),
    ("noise", "i0_photons", float("nan"), "a number in [1, 1e+15] photons"),
    ("recon", "methods", ["barycentric", "magic"], "a non-empty list from"),
    ("recon", "cardiac_phases", [0.0, 1.0], "[0, 1)"),
    ("recon", "filter", "cosine", "ram-lak"),
    ("recon", "small_fov_mm", [10.0, 0.0, 0.0, 10.0], "min < max"),
])
def test_bad_values_name_key_value_and_allowed(section, key, value, fragment):
    with pytest.raises(SceneError) as e:
        scene_from_dict({section: {key: value}})
    msg = str(e.value)
    assert f"{section}.{key}" in msg and fragment in msg
    if not (isinstance(value, float) and math.isnan(value)):
        assert repr(value) in msg  # a list as the TOML list it was written as


def test_unknown_key_suggests_nearest():
    with pytest.raises(SceneError, match=r"scanner.sid: unknown key; did you mean 'sid_mm'\?"):
        scene_from_dict({"scanner": {"sid": 500}})
    with pytest.raises(SceneError, match=r"scaner: unknown key; did you mean 'scanner'\?"):
        scene_from_dict({"scaner": {}})


def test_inconsistent_geometry_is_an_error():
    with pytest.raises(SceneError, match="sdd_mm"):
        scene_from_dict({"scanner": {"sid_mm": 600.0, "sdd_mm": 500.0}})
    with pytest.raises(SceneError, match="coverage_mm"):
        scene_from_dict({"scan": {"coverage_mm": 10.0}})


def test_malformed_toml_and_missing_file(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text("[scanner\nsid_mm = 3")
    with pytest.raises(SceneError, match="malformed TOML"):
        load_scene(bad)
    with pytest.raises(SceneError, match="neither a file nor a built-in"):
        load_scene("no-such-scene")


def test_int_for_float_and_replace():
    s = scene_from_dict({"scanner": {"sid_mm": 600}})
    assert s.scanner.sid_mm == 600.0 and isinstance(s.scanner.sid_mm, float)
    t = load_scene("tiny").replace(recon={"nz": 1})
    assert t.recon.nz == 1 and t.scanner == load_scene("tiny").scanner
    assert isinstance(t, Scene)


def test_scene_is_immutable_and_round_trips():
    s = load_scene("demo")
    with pytest.raises(dataclasses.FrozenInstanceError):
        s.scanner.sid_mm = 1.0
    assert scene_from_dict(s.to_dict()) == s


def test_scan_hash_depends_on_scan_not_recon():
    s = load_scene("tiny")
    assert s.scan_hash(0.1) == s.replace(recon={"nz": 1}).scan_hash(0.1)
    assert s.scan_hash(0.1) != s.replace(phantom={"diaphragm_si_mm": 10.0}).scan_hash(0.1)
    assert s.scan_hash(0.1) != s.scan_hash(0.05)


def test_motion_flags_drop_axes():
    s = load_scene("tiny").replace(phantom={"cardiac_motion": False})
    assert s.cardiac_targets == (0.0,) and len(s.resp_targets) == 2
    s = load_scene("tiny").replace(signals={"breath_hold": True})
    assert s.resp_targets == (0.5,)


def test_heldout_scenes_differ_from_demo_as_issue_41_asks():
    """The mc method's held-out scenes (docs/results/mc-heldout.md): demo's grid, another heart rate
    or rhythm, breathing period 3-6 s, rotation 0.28-0.5 s, pitch 0.05-0.10, each unlike demo's."""
    demo = load_scene("demo")
    for n in ("heldout-a", "heldout-b", "heldout-c"):
        s = load_scene(n)
        assert (s.recon.nx, s.recon.ny, s.recon.nz) == (demo.recon.nx, demo.recon.ny, demo.recon.nz)
        assert 3.0 <= s.signals.resp_period_s <= 6.0 and s.signals.resp_period_s != demo.signals.resp_period_s
        assert 0.28 <= s.scanner.rotation_time_s <= 0.5 and s.scanner.rotation_time_s != demo.scanner.rotation_time_s
        assert all(0.05 <= p <= 0.10 for p in s.scan.pitches)
        assert (s.signals.rr_s, s.signals.rhythm) != (demo.signals.rr_s, demo.signals.rhythm)
