"""Bad input: malformed or out-of-range scenes, NaN/inf, truncated or corrupt projection
stores, missing run directories. Each gives a one-line error naming the file or key and
what is allowed (a :class:`~clrecon.core.errors.ClreconError`), the CLI exits non-zero without a
traceback unless ``--debug``; fuzzed scene files and stores raise nothing else."""

from __future__ import annotations

import math
import random
import warnings

import hostile_scenes as hostile
import numpy as np
import pytest

from clrecon.cli import main
from clrecon.config.scene import SCENE_DIR, SECTIONS, load_scene, scene_from_dict
from clrecon.core.errors import ClreconError, SceneError, StoreError
from clrecon.reconstruction.config import MAX_GRID_MM
from clrecon.simulation.store import ProjectionStore

# Sizes of the fuzz loops (seeded: the same cases every run).
N_SCENE_FUZZ = 400
N_STORE_FUZZ = 120


def _one_line_cli_error(capsys, argv, *fragments):
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith("clrecon: error: ") and err.count("\n") == 1, err
    assert "Traceback" not in err
    for f in fragments:
        assert f in err, (f, err)
    return err


# ---------------------------------------------------------------------------------------
# scenes
@pytest.mark.parametrize("text,fragments", [
    ("[scanner\nn_cols = 3", ["malformed TOML"]),
    ("[scanner]\nn_colz = 96", ["scanner.n_colz: unknown key", "did you mean 'n_cols'"]),
    ("colour = 1", ["colour: unknown key", "valid keys"]),
    ("[recon]\nresp_bins = 99", ["recon.resp_bins = 99", "an integer in 1..50"]),
    ("[noise]\ni0_photons = nan", ["noise.i0_photons = nan", "a number in [1, 1e+15] photons"]),
    ("[noise]\ni0_photons = 1e19", ["noise.i0_photons = 1e+19", "a number in [1, 1e+15] photons"]),
    ("[scan]\npitches = 0.5", ["scan.pitches = 0.5", "a list of 1 to 64 numbers"]),  # scalar for a list
    ("[scan]\npitches = [0.1, inf]", ["scan.pitches = [0.1, inf]", "[0.001, 2]"]),
    ("[signals]\nrhythm = 3", ["signals.rhythm = 3", "one of periodic"]),
    ("scanner = 5", ["scanner: expected a table"]),
    ("[scanner]\nsid_mm = 1e-308", ["scanner.sid_mm = 1e-308", "a number in [10, 5000] mm (clinical CT"]),
    ("[scanner]\nsdd_mm = 1e308", ["scanner.sdd_mm = 1e+308", "a number in [10, 10000] mm"]),
    ("[scanner]\ncol_pitch_mm = 1e12", ["scanner.col_pitch_mm = 1000000000000.0", "[0.005, 100] mm (detector cells"]),
    ("[recon]\nny = 1000000", ["recon.ny = 1000000", "an integer in 2..4096"]),
    ("[scanner]\nrotation_time_s = 30.0", ["a scan of 4", "at most 600 s"]),            # too long a scan
    ("[noise]\nelectronic_sigma = 3e5", ["noise.electronic_sigma = 300000.0", "at most noise.i0_photons"]),
    ("[recon]\nnx = 400\nvoxel_mm = 12.0", ["recon.nx x recon.voxel_mm = 400 x 12 mm", "at most 2000 mm"]),
    ("[signals]\nbreathing_trace = 'no-such.vxp'", ["signals.breathing_trace = ",
                                                      "no-such.vxp': no such file (expected a Varian RPM"]),
    ("[scan]\nflip_rows = true", ["scan.flip_rows = True", "only used with scan.source = 'dicom-ct-pd'"]),
    ("[scan]\npitches = [1.5]", ["pitch 1.5 leaves (slice, view) pairs without data",
                                 "the largest pitch that covers every (slice, view) is 0.8870"]),
])
def test_bad_scene_files_give_one_line_errors_naming_file_and_key(tmp_path, text, fragments):
    f = tmp_path / "bad.toml"
    f.write_text(text)
    with pytest.raises(SceneError) as e:
        load_scene(f)
    msg = str(e.value)
    assert "\n" not in msg and msg.startswith(str(f))
    for frag in fragments:
        assert frag in msg, (frag, msg)


def test_missing_and_binary_scene_files(tmp_path):
    with pytest.raises(SceneError, match="does not exist"):
        load_scene(tmp_path / "nope.toml")
    f = tmp_path / "binary.toml"
    f.write_bytes(bytes(range(256)))
    with pytest.raises(SceneError, match="malformed TOML"):
        load_scene(f)


def test_cli_bad_scene_is_one_line_and_debug_shows_the_traceback(tmp_path, capsys):
    f = tmp_path / "bad.toml"
    f.write_text("[recon]\nnx = -3\n")
    _one_line_cli_error(capsys, ["run", "--scene", str(f), "--out", str(tmp_path / "out")],
                        str(f), "recon.nx = -3", "an integer in 2..4096")
    with pytest.raises(SceneError):
        main(["--debug", "run", "--scene", str(f), "--out", str(tmp_path / "out")])


def _mutate_scene(rnd: random.Random, texts) -> bytes:
    b = bytearray(rnd.choice(texts))
    op = rnd.randrange(5)
    if op == 0:                                   # truncated
        return bytes(b[:rnd.randrange(len(b))])
    if op == 1:                                   # random bytes flipped
        for _ in range(rnd.randint(1, 5)):
            b[rnd.randrange(len(b))] = rnd.randrange(256)
        return bytes(b)
    if op == 2:                                   # lines shuffled (keys move between tables)
        lines = bytes(b).split(b"\n")
        rnd.shuffle(lines)
        return b"\n".join(lines)
    if op == 3:                                   # random bytes
        return bytes(rnd.randrange(256) for _ in range(rnd.randrange(200)))
    lines = bytes(b).split(b"\n")                 # one value replaced by an odd one
    j = rnd.randrange(len(lines))
    if b"=" in lines[j]:
        k, _, _ = lines[j].partition(b"=")
        lines[j] = k + b"= " + rnd.choice([b"-1", b"0", b"1e400", b"nan", b"-inf", b'"x"', b"[]", b"{}",
                                           b"9999999999999999999999", b"1979-05-27", b"true",
                                           b'[1, "a"]', b"0.0", b"1e-320", b"1e308", b"[0.5, 0.5]"])
    return b"\n".join(lines)


def test_fuzzed_scene_files_raise_only_scene_errors(tmp_path):
    rnd = random.Random(20240611)
    texts = [p.read_bytes() for p in sorted(SCENE_DIR.glob("*.toml"))]
    n_ok = n_err = 0
    for i in range(N_SCENE_FUZZ):
        f = tmp_path / f"fuzz{i}.toml"
        f.write_bytes(_mutate_scene(rnd, texts))
        try:
            load_scene(f)
            n_ok += 1
        except SceneError as e:                   # anything else fails the test
            assert "\n" not in str(e)
            n_err += 1
    assert n_ok > 0 and n_err > 0                 # the fuzz reaches both outcomes


def _finite_numbers(obj, where=""):
    """Every number in a (nested) dict/list is finite; yields the path of any that is not."""
    if isinstance(obj, float) and not math.isfinite(obj):
        yield where
    elif isinstance(obj, dict):
        for k, v in obj.items():
            yield from _finite_numbers(v, f"{where}.{k}")
    elif isinstance(obj, (list, tuple)):
        for i, v in enumerate(obj):
            yield from _finite_numbers(v, f"{where}[{i}]")


def _assert_sane(scene):
    """What an accepted scene must satisfy whatever its values: finite numbers, every ranged key in its
    declared range, and derived geometry (collimation, field of view, projection count, scan length)
    finite and within the limits the stages are built for."""
    from dataclasses import fields

    from clrecon.scan.config import MAX_SCAN_S
    assert not list(_finite_numbers(scene.to_dict()))
    for sec in SECTIONS:
        cfg = getattr(scene, sec)
        for f in fields(cfg):
            rng = f.metadata.get("range")
            v = getattr(cfg, f.name)
            if rng is not None and isinstance(v, (int, float)) and not isinstance(v, bool):
                lo, hi = rng
                assert v == 0 or lo <= v <= hi, (sec, f.name, v, rng)
    sc = scene.scanner
    assert math.isfinite(sc.collimation_iso_mm) and sc.collimation_iso_mm > 0
    assert math.isfinite(sc.fov_radius_mm) and sc.fov_radius_mm > 0
    for p in scene.scan.pitches:
        assert 1 <= scene.scan.projection_count(sc, p) <= 10 ** 8
        assert 0 < scene.scan.duration_s(sc, p) <= MAX_SCAN_S
    rc = scene.recon
    assert max(rc.nx, rc.ny) * rc.voxel_mm <= MAX_GRID_MM and rc.nz * rc.slice_mm <= MAX_GRID_MM


def test_fuzzed_scene_dicts_are_refused_in_one_line_or_sane():
    """Random values of every type in random keys of every section: a one-line SceneError naming the
    key, or a scene that passes :func:`_assert_sane` (no other exception, nothing absurd accepted)."""
    from dataclasses import fields

    rnd = random.Random(7)
    values = [0, 1, -1, 2 ** 63 - 1, -2 ** 63, 2 ** 63, 10 ** 30, 0.0, 1e308, -1e308, 1e-308, 5e-324, 1e-300,
              float("inf"), -float("inf"), float("nan"), True, "x", [], [1], [1.0, 2.0], {}, {"a": 1}, 0.5, 3, 1e6,
              1e12, [float("nan")], [0.02, float("inf")]]
    outcomes = {"refused": 0, "accepted": 0}
    for _ in range(2000):
        d = {}
        for sec, cls in SECTIONS.items():
            if rnd.random() < 0.5:
                names = [f.name for f in fields(cls)]
                d[sec] = {k: rnd.choice(values) for k in rnd.sample(names, rnd.randint(1, 3))}
        try:
            scene = scene_from_dict(d)
        except SceneError as e:
            msg = str(e)
            assert "\n" not in msg and any(f"{sec}." in msg or f"{sec}:" in msg for sec in d), (d, msg)
            outcomes["refused"] += 1
            continue
        _assert_sane(scene)
        outcomes["accepted"] += 1
    assert outcomes["refused"] > 1000 and outcomes["accepted"] > 10, outcomes


# ---------------------------------------------------------------------------------------
# the hostile grid: every key x VALUES (tests/support/hostile_scenes.py), on the tiny scene
def _grid_outcomes():
    base = hostile.base_dict()
    for sec, key in hostile.grid_keys():
        for label, value in hostile.VALUES:
            yield sec, key, label, value, hostile.validate(hostile.case_dict(base, sec, key, value))


def test_hostile_grid_refuses_every_absurd_value_in_one_line_naming_key_and_value():
    """79 keys x 13 values: no exception other than a one-line SceneError that names ``section.key =``
    (the key and the value it was given), a refusal of every case not declared legitimate in
    ``hostile_scenes.ACCEPTED``, and acceptance of every declared case (a seed of 10^12, a table
    position of -1 mm, truth_free = true), each accepted scene sane."""
    counts = {"refused": 0, "accepted": 0}
    for sec, key, label, _value, (status, detail) in _grid_outcomes():
        case = f"{sec}.{key} = {label}"
        assert status != "traceback", (case, detail)
        if hostile.expected_accepted(sec, key, label):
            assert status == "accepted", (case, detail)
            _assert_sane(detail)
        else:
            assert status == "refused", f"{case}: accepted, but declared absurd"
            assert "\n" not in detail and f"{sec}.{key} = " in detail, (case, detail)
        counts[status] += 1
    assert counts["refused"] + counts["accepted"] == len(hostile.grid_keys()) * len(hostile.VALUES)
    assert counts["accepted"] == sum(len(v) for v in hostile.ACCEPTED.values())


def test_hostile_grid_covers_every_key_and_declares_only_real_keys():
    keys = {f"{sec}.{key}" for sec, key in hostile.grid_keys()}
    assert len(keys) >= 79
    assert set(hostile.ACCEPTED) <= keys
    labels = {label for label, _ in hostile.VALUES}
    assert all(v <= labels for v in hostile.ACCEPTED.values())


def test_every_range_end_is_accepted_or_refused_across_keys_in_one_line():
    """Both ends of every declared range: accepted (then sane), or refused by a check across keys
    (an end of one key's range can clash with the tiny scene's other values) in one line."""
    base = hostile.base_dict()
    cases = hostile.edge_cases()
    assert len(cases) >= 60
    accepted = 0
    for sec, key, label, value in cases:
        status, detail = hostile.validate(hostile.case_dict(base, sec, key, value))
        assert status != "traceback", (sec, key, label, detail)
        if status == "refused":
            assert "\n" not in detail and (key in detail or "scan." in detail), (sec, key, label, detail)
        else:
            _assert_sane(detail)
            accepted += 1
    assert accepted > len(cases) // 2


def test_docs_table_of_ranges_is_the_codes():
    """docs/hostile-inputs.md "Ranges of scene values" lists every ranged key with the code's text."""
    from dataclasses import fields
    from pathlib import Path

    from clrecon.simulation.phantoms.voxel import VoxelPhantomConfig
    doc = (Path(__file__).resolve().parents[2] / "docs" / "hostile-inputs.md").read_text()
    for sec, cls in list(SECTIONS.items()) + [("phantom", VoxelPhantomConfig)]:
        tag = " (voxel)" if cls is VoxelPhantomConfig else ""
        for f in fields(cls):
            if f.metadata.get("range") is not None:
                row = f"| `{sec}.{f.name}`{tag} | {f.metadata['allowed'].replace('|', '/')} |"
                assert row in doc, row


#: Range ends and hostile values that reach the kernels, run end to end on the tiny scene (kept
#: few: the full end-to-end grid is ``python tests/support/hostile_scenes.py --grids hostile,edge``).
E2E_CASES = [
    ("scanner", "col_pitch_mm", "min", None),     # 1e-300 was a ZeroDivisionError in the ramp filter
    ("recon", "voxel_mm", "min", None),           # 1e-300 was a ZeroDivisionError in the motion metrics
    ("phantom", "mu_water_per_mm", "min", None),  # 1e-300 gave rc 0 with non-finite voxels
    ("noise", "i0_photons", "min", {"noise": {"electronic_sigma": 0.0}}),  # one photon per cell: most counts 0
    ("recon", "sigma", "min", None),
    ("recon", "kappa", "max", None),
]


@pytest.mark.parametrize("sec,key,end,extra", E2E_CASES)
def test_range_ends_that_reach_the_kernels_run_to_finite_outputs(tmp_path, sec, key, end, extra):
    from dataclasses import fields

    cls = SECTIONS[sec]
    lo, hi = next(f.metadata["range"] for f in fields(cls) if f.name == key)
    rec = hostile.run_one(sec, key, lo if end == "min" else hi, tmp_path, tmp_path / "cache", report=False,
                          extra=extra)
    assert rec == {"outcome": "ran", "strict_json": True, "non_finite_voxels": 0}, rec


def test_truth_free_results_are_strict_json_with_a_reason_for_each_null(tmp_path):
    """recon.truth_free = true wrote 144 bare NaN tokens into results.json (strict parsers reject the file)."""
    from clrecon.core import jsonio
    from clrecon.outputs.rundir import RunDirectory
    from clrecon.pipeline.run import run

    scene = load_scene("tiny").replace(recon={"truth_free": True})
    run(scene, tmp_path / "run", methods=["nearest", "local_linear"], cache_dir=tmp_path / "cache", progress=False,
        log=lambda *a: None, report=False)
    text = (tmp_path / "run" / "results.json").read_text()
    res = hostile.strict_json(text)  # json.loads with parse_constant raising: no NaN / Infinity token
    nulls = res[jsonio.NULLS_KEY]
    assert nulls and all(r.startswith(("NaN: ", "Infinity: ", "-Infinity: ")) for r in nulls.values()), nulls
    for ptr in nulls:  # each pointer names a null in the file
        node = res
        for part in ptr.split("/")[1:]:
            node = node[int(part)] if isinstance(node, list) else node[part.replace("~1", "/").replace("~0", "~")]
        assert node is None, ptr
    back = RunDirectory(tmp_path / "run").results  # clrecon's reader sees the floats again
    ptr = next(iter(nulls))
    node = back
    for part in ptr.split("/")[1:]:
        node = node[part.replace("~1", "/").replace("~0", "~")]
    assert math.isnan(node)


def test_strict_json_round_trip():
    from clrecon.core import jsonio

    obj = {"a": [1.0, float("nan"), {"b": float("inf"), "null_because": "no images"}], "c/d": -float("inf"),
           "e": np.float32(2.5), "f": np.arange(3), "g": (1, 2)}
    text = jsonio.dumps(obj)
    strict = jsonio.loads_strictly(text)
    assert strict["a"][1] is None and strict["a"][2]["b"] is None and strict["c/d"] is None
    assert strict["null_values"] == {"/a/1": "NaN", "/a/2/b": "Infinity: no images", "/c~1d": "-Infinity"}
    back = jsonio.loads(text)
    assert math.isnan(back["a"][1]) and back["a"][2]["b"] == math.inf and back["c/d"] == -math.inf
    assert back["e"] == 2.5 and back["f"] == [0, 1, 2] and back["g"] == [1, 2]
    with pytest.raises(ValueError, match="bare NaN"):
        jsonio.loads_strictly('{"x": NaN}')
    assert math.isnan(jsonio.loads('{"x": NaN}')["x"])  # a results.json of an earlier version still reads


def test_a_folder_named_like_a_builtin_scene_does_not_hide_it(tmp_path, monkeypatch):
    """``--out demo`` leaves a folder ``demo``; ``--scene demo`` must still mean the built-in scene."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "tiny").mkdir()
    assert load_scene("tiny").name == "tiny"
    assert main(["run", "--scene", "tiny", "--out", "tiny", "--methods", "nearest", "--slices", "0:1", "--targets",
                 "0/0.25", "--no-progress", "--cache", str(tmp_path / "cache")]) == 0  # and a run into that folder
    (tmp_path / "x.toml").mkdir()
    with pytest.raises(SceneError, match=r"'x.toml' is a folder; expected a scene TOML file or a built-in"):
        load_scene("x.toml")


# ---------------------------------------------------------------------------------------
# recorded traces: non-finite values refused naming file, line and value, or (a lost .vxp sample)
# left out and counted; never a traceback, never a silently wrong amplitude
def _write_vxp(path, t, amp, flag=None, ttl=None):
    """A Varian RPM .vxp of samples at times ``t`` (s); ``amp``, ``flag``, ``ttl``: strings or numbers per row."""
    flag = ["0"] * len(t) if flag is None else flag
    ttl = ["1"] * len(t) if ttl is None else ttl
    rows = [f"{a},0.0,{ts},{f},{g},,0" for a, ts, f, g in zip(amp, t, flag, ttl, strict=True)]
    path.write_text("[Header]\nCRC=0\nVersion=1.6\nData_layout=amplitude,phase,timestamp,validflag,ttlin,mark,ttlout\n"
                    "Samples_per_second=25\nScale_factor=10.0\n[Data]\n" + "\n".join(rows) + "\n")
    return path


@pytest.fixture(scope="module")
def trace():
    """The tiny scene's breathing (0..3 s at 25 Hz: the scan lasts 1.28 s) as .vxp fields (strings)."""
    from clrecon.scan import signals

    tr = signals.respiratory_trace(load_scene("tiny"), step_s=0.04)
    keep = tr.time_s <= 3.0
    ms = [str(int(round(x * 1000))) for x in tr.time_s[keep]]
    return ms, [f"{a:.7f}" for a in tr.raw[keep]]


VXP_LINE0 = 8  # file line of the first data row


@pytest.mark.parametrize("column,row,token,fragment", [
    ("timestamp", 30, "inf", "timestamp = inf: expected a time in ms (a finite number)"),
    ("timestamp", 30, "nan", "timestamp = nan: expected a time in ms"),
    ("timestamp", 0, "-inf", "timestamp = -inf"),
    ("validflag", 12, "nan", "validflag = 'nan': expected an integer"),
    ("validflag", 12, "inf", "validflag = 'inf': expected an integer"),
    ("ttlin", 5, "inf", "ttlin = 'inf': expected an integer"),
    ("validflag", 12, "0.5", "validflag = '0.5': expected an integer"),
    ("amplitude", 12, "x", "expected numbers in amplitude"),
])
def test_broken_vxp_rows_are_one_line_errors_naming_file_line_and_value(tmp_path, trace, column, row, token,
                                                                        fragment):
    from clrecon.core.errors import InputError
    from clrecon.scan import recorded

    ms, amp = trace
    fields = {"timestamp": list(ms), "amplitude": list(amp), "validflag": ["0"] * len(ms), "ttlin": ["1"] * len(ms)}
    fields[column][row] = token
    f = _write_vxp(tmp_path / "b.vxp", fields["timestamp"], fields["amplitude"], fields["validflag"],
                   fields["ttlin"])
    with pytest.raises(InputError) as e:
        recorded.read_breathing_trace(f)
    msg = str(e.value)
    assert "\n" not in msg and msg.startswith(f"{f}: line {VXP_LINE0 + row}: ") and fragment in msg, msg


@pytest.mark.parametrize("text,fragment", [
    ("time_s,amplitude\n0.0,1.0\nnan,2.0\n0.2,1.0\n", "line 3: time_s = nan: expected a time in s"),
    ("time_s,amplitude\n0.0,1.0\n0.1,inf\n0.2,1.0\n", "line 3: amplitude = 'inf': expected a finite number "
                                                      "(mark a lost sample with valid = 0 in a third column valid)"),
    ("time_s,amplitude,valid\n0.0,1.0,1\n0.1,nan,1\n0.2,1.0,1\n", "line 3: amplitude = 'nan'"),
    ("time_s,amplitude,valid\n0.0,1.0,1\n0.1,1.0,inf\n0.2,1.0,1\n", "line 3: valid = 'inf': expected an integer"),
])
def test_broken_breathing_csv_rows_are_one_line_errors(tmp_path, text, fragment):
    from clrecon.core.errors import InputError
    from clrecon.scan import recorded

    f = tmp_path / "b.csv"
    f.write_text(text)
    with pytest.raises(InputError) as e:
        recorded.read_breathing_trace(f)
    assert "\n" not in str(e.value) and str(e.value).startswith(f"{f}: {fragment.split(':')[0]}:")
    assert fragment in str(e.value), str(e.value)


def test_a_csv_sample_marked_invalid_may_have_no_amplitude(tmp_path):
    from clrecon.scan import recorded

    f = tmp_path / "b.csv"
    f.write_text("time_s,amplitude,valid\n" + "".join(f"{0.04 * i:.2f},{'nan' if i == 7 else math.sin(i / 5)},"
                                                       f"{0 if i == 7 else 1}\n" for i in range(100)))
    tr = recorded.read_breathing_trace(f)
    assert np.isfinite(tr.amplitude).all() and tr.status[7] == recorded.STATUS["invalid"]


def test_lost_vxp_amplitudes_are_left_out_and_counted_like_lost_tracking(tmp_path, trace):
    """A .vxp amplitude of inf (a lost RPM sample) changed 6 176 voxels by up to 93 HU, silently: its views
    are now left out and counted, exactly the views a validflag of -1 (lost tracking) leaves out."""
    from clrecon.scan import recorded
    from clrecon.scan.table import projection_table

    ms, amp = trace
    scene = load_scene("tiny")
    t = projection_table(scene, 0.1).time_s
    bad = list(amp)
    bad[10], bad[20] = "inf", "nan"               # 0.40 s and 0.80 s: inside the 1.28 s scan
    lost = ["0"] * len(ms)
    lost[10] = lost[20] = "-1"
    a = recorded.view_signals(scene.replace(signals={"breathing_trace": str(_write_vxp(
        tmp_path / "inf.vxp", ms, bad))}).signals, t)
    b = recorded.view_signals(scene.replace(signals={"breathing_trace": str(_write_vxp(
        tmp_path / "lost.vxp", ms, amp, lost))}).signals, t)
    assert a.excluded["non_finite_amplitude"] == b.excluded["lost_tracking"] > 0
    assert np.array_equal(a.usable, b.usable)
    assert np.isfinite(a.resp_amplitude).all()
    np.testing.assert_allclose(a.resp_amplitude[a.usable], b.resp_amplitude[b.usable], rtol=0, atol=1e-12)
    # and the run counts them in results.json
    from clrecon.pipeline.run import run

    res = run(scene.replace(signals={"breathing_trace": str(tmp_path / "inf.vxp")}), tmp_path / "run",
              methods=["nearest"], cache_dir=tmp_path / "cache", progress=False, report=False, log=lambda *x: None)
    rs = res["recorded_signals"]["p0.100"]
    assert rs["excluded_by_reason"]["non_finite_amplitude"] == a.excluded["non_finite_amplitude"]
    assert rs["views_excluded"] == int((~a.usable).sum())


def test_vxp_with_no_finite_amplitudes_says_so(tmp_path, trace):
    from clrecon.core.errors import InputError
    from clrecon.scan import recorded

    ms, amp = trace
    with pytest.raises(InputError, match=r"every amplitude is nan or inf; expected a breathing trace"):
        recorded.read_breathing_trace(_write_vxp(tmp_path / "a.vxp", ms, ["nan"] * len(ms)))
    one = ["nan"] * len(ms)
    one[3] = amp[3]
    with pytest.raises(InputError) as e:  # was "no spread (P5 = P95 = nan)"
        recorded.read_breathing_trace(_write_vxp(tmp_path / "b.vxp", ms, one)).percentiles()
    assert "fewer than 2 valid samples with a finite amplitude" in str(e.value)
    assert f"{len(ms) - 1} of {len(ms)} amplitudes are nan or inf" in str(e.value) and "nan)" not in str(e.value)


def test_nan_r_peak_is_a_one_line_error_not_a_traceback(tmp_path):
    """A NaN R peak inside the scan gave ``ValueError: c and a: must be finite`` from deep in the planning."""
    from clrecon.scan import signals

    scene = load_scene("tiny")
    peaks = [f"{x:.6f}" for x in signals.r_peaks(scene)]
    peaks[1] = "nan"
    f = tmp_path / "ecg.csv"
    f.write_text("r_peak_s\n" + "\n".join(peaks) + "\n")
    out = tmp_path / "run"
    toml = tmp_path / "s.toml"
    toml.write_text(SCENE_DIR.joinpath("tiny.toml").read_text() + f"\n[signals]\necg_trace = '{f}'\n")
    with pytest.raises(ClreconError) as e:
        from clrecon.pipeline.run import run
        run(load_scene(toml), out, methods=["nearest"], cache_dir=tmp_path / "cache", progress=False,
            report=False, log=lambda *x: None)
    assert str(e.value) == f"{f}: line 3: r_peak_s = nan: expected an R-peak time in s (a finite number)"


def test_wfdb_record_with_a_gap_names_the_sample(tmp_path):
    wfdb = pytest.importorskip("wfdb")
    from clrecon.core.errors import InputError
    from clrecon.scan import recorded

    fs = 250
    sig = np.sin(np.arange(fs * 10) / fs * 2 * np.pi * 1.2)[:, None]
    sig[1234] = np.nan                            # WFDB's missing-sample value reads back as NaN
    wfdb.wrsamp("gap", fs=fs, units=["mV"], sig_name=["II"], p_signal=sig, write_dir=str(tmp_path), fmt=["16"])
    with pytest.raises(InputError) as e:
        recorded.read_r_peaks(tmp_path / "gap.hea")
    assert "sample 1234 (t = 4.936 s) is nan, 1 of 2500 samples are missing" in str(e.value)
    assert "\n" not in str(e.value)


def test_fuzzed_traces_raise_only_input_errors_and_give_finite_signals(tmp_path, trace):
    """Random tokens (nan, inf, -inf, 1e308, '', 'x', -1, -2) in random cells of a .vxp and of the CSVs:
    one-line InputErrors, or traces whose every number is finite."""
    from clrecon.core.errors import InputError
    from clrecon.scan import recorded

    ms, amp = trace
    rnd = random.Random(11)
    tokens = ["nan", "inf", "-inf", "1e308", "-1e308", "", "x", "-1", "-2", "0", "1e-320", "NaN", "+inf"]
    outcomes = {"error": 0, "read": 0}
    for i in range(150):
        kind = rnd.randrange(3)
        if kind == 0:
            cols = [list(ms), list(amp), ["0"] * len(ms), ["1"] * len(ms)]
            for _ in range(rnd.randint(1, 4)):
                cols[rnd.randrange(4)][rnd.randrange(len(ms))] = rnd.choice(tokens)
            f = _write_vxp(tmp_path / f"f{i}.vxp", *cols)
            read = recorded.read_breathing_trace
        elif kind == 1:
            rows = [[f"{int(x) / 1000:.3f}", a, "1"] for x, a in zip(ms, amp, strict=True)]
            for _ in range(rnd.randint(1, 4)):
                rows[rnd.randrange(len(rows))][rnd.randrange(3)] = rnd.choice(tokens)
            f = tmp_path / f"f{i}.csv"
            f.write_text("time_s,amplitude,valid\n" + "".join(",".join(r) + "\n" for r in rows))
            read = recorded.read_breathing_trace
        else:
            rows = [f"{0.8 * k:.3f}" for k in range(10)]
            for _ in range(rnd.randint(1, 2)):
                rows[rnd.randrange(len(rows))] = rnd.choice(tokens)
            f = tmp_path / f"r{i}.csv"
            f.write_text("r_peak_s\n" + "\n".join(rows) + "\n")
            read = recorded.read_r_peaks
        try:
            tr = read(f)
            if kind < 2:
                tr.percentiles()
        except InputError as e:
            assert "\n" not in str(e) and str(e).startswith(str(f)), str(e)
            outcomes["error"] += 1
            continue
        assert np.isfinite(tr.time_s).all() and (kind == 2 or np.isfinite(tr.amplitude).all())
        outcomes["read"] += 1
    assert outcomes["error"] > 30 and outcomes["read"] > 10, outcomes


# ---------------------------------------------------------------------------------------
# projection stores
@pytest.fixture
def small_store(tmp_path):
    """A finished store of a 40-projection scan filled with known values (no projector)."""
    scene = load_scene("tiny").replace(scan={"n_projections": 40})
    st = ProjectionStore.open(scene, 0.1, cache_dir=tmp_path)
    data = np.random.default_rng(0).random((len(st),) + st.shape[1:]).astype(np.float32)
    with st.writing():
        st.write(np.arange(len(st)), data)
    st.close()
    return scene, st.path, data


def _reopen(scene, cache):
    return ProjectionStore.open(scene, 0.1, cache_dir=cache, create=False)


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_nan_or_inf_in_a_store_is_an_error_naming_file_and_projection(tmp_path, bad):
    scene = load_scene("tiny").replace(scan={"n_projections": 40})
    st = ProjectionStore.open(scene, 0.1, cache_dir=tmp_path)
    data = np.ones((40,) + st.shape[1:], np.float32)
    data[17, 3, 5] = bad
    with st.writing():
        st.write(np.arange(40), data)
    assert st.read(0, 17).shape == (17,) + st.shape[1:]          # the good part still reads
    for noisy in (False, True):
        with pytest.raises(StoreError) as e:
            st.read(10, 30, noisy=noisy)
        assert str(st.path) in str(e.value) and "projections 17..17" in str(e.value)
        assert "NaN or inf" in str(e.value) and "\n" not in str(e.value)
    st.close()


def test_truncated_store_is_an_error(small_store):
    scene, path, _ = small_store
    path.write_bytes(path.read_bytes()[:len(path.read_bytes()) // 2])
    with pytest.raises(StoreError, match="corrupt or truncated") as e:
        _reopen(scene, path.parent)
    assert str(path) in str(e.value)


def test_corrupt_chunk_is_caught_by_its_checksum(small_store):
    """Bytes changed inside the compressed data: the Fletcher-32 checksum fails on read."""
    scene, path, data = small_store
    import h5py
    with h5py.File(path, "r") as f:
        offset = f["projections"].id.get_chunk_info(0).byte_offset
    raw = bytearray(path.read_bytes())
    for j in range(offset + 100, offset + 108):
        raw[j] ^= 0x5A
    path.write_bytes(bytes(raw))
    st = _reopen(scene, path.parent)
    with pytest.raises(StoreError, match="corrupt or truncated"):
        st.read(0, len(st))
    st.close()


def test_missing_store_is_an_error(tmp_path):
    with pytest.raises(StoreError, match="no projection store"):
        _reopen(load_scene("tiny"), tmp_path)


def test_fuzzed_stores_raise_only_store_errors_and_never_return_wrong_numbers(small_store):
    scene, path, data = small_store
    good = path.read_bytes()
    rnd = random.Random(3)
    outcomes = {"error": 0, "read": 0}
    for _ in range(N_STORE_FUZZ):
        b = bytearray(good)
        op = rnd.randrange(3)
        if op == 0:
            b = b[:rnd.randrange(len(b))]
        elif op == 1:
            for _ in range(rnd.randint(1, 20)):
                b[rnd.randrange(len(b))] = rnd.randrange(256)
        else:
            j = rnd.randrange(len(b))
            b[j:j + rnd.randrange(1, 4000)] = bytes(rnd.randrange(256) for _ in range(100))
        path.write_bytes(bytes(b))
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                st = _reopen(scene, path.parent)
            try:
                got = st.read(0, len(st))
            finally:
                st.close()
        except StoreError as e:                   # anything else fails the test
            assert "\n" not in str(e)
            outcomes["error"] += 1
            continue
        np.testing.assert_array_equal(got, data)  # bytes the data does not depend on
        outcomes["read"] += 1
    assert outcomes["error"] > N_STORE_FUZZ // 2


# ---------------------------------------------------------------------------------------
# run directories
def test_missing_run_directory_is_a_one_line_error(tmp_path, capsys):
    missing = tmp_path / "no-such-run"
    _one_line_cli_error(capsys, ["export", str(missing), "--format", "nifti"], str(missing), "no such run directory")
    with pytest.raises(ClreconError):
        main(["--debug", "export", str(missing), "--format", "nifti"])


def test_run_directory_with_a_corrupt_volume_file(tmp_path, capsys):
    (tmp_path / "volumes.h5").write_bytes(b"\x89HDF\r\n\x1a\n" + bytes(100))
    _one_line_cli_error(capsys, ["export", str(tmp_path), "--format", "nifti"], "volumes.h5",
                        "not a readable HDF5 file")
