"""Measured scans: recorded traces, DICOM-CT-PD export and import, the round trip, bad inputs.

No patient scan can ship: every series, .vxp, CSV and WFDB record here is written from the
engine's own simulation of the ``tiny`` scene (flat detector, no flying focal spot).
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import h5py
import numpy as np
import pydicom
import pytest

from clrecon.config.scene import load_scene
from clrecon.core.errors import ClreconError
from clrecon.outputs.export import export
from clrecon.outputs.volumes import read_volume
from clrecon.pipeline.run import run
from clrecon.reconstruction import reconstruct
from clrecon.scan import dicom_ct_pd, recorded, signals
from clrecon.scan.table import projection_table
from clrecon.simulation.measured import import_series
from clrecon.simulation.store import ProjectionStore

METHODS = ["nearest", "local_linear"]


def _quiet(*a, **k):
    pass


@pytest.fixture(scope="module")
def sim(tmp_path_factory):
    """tiny simulated and run, exported as DICOM-CT-PD (with patient identifiers stamped in)."""
    root = tmp_path_factory.mktemp("measured")
    cache = root / "cache"
    scene = load_scene("tiny")
    run(scene, root / "sim", methods=METHODS, cache_dir=cache, progress=False, report=False, log=_quiet)
    exp = root / "exp"
    index = export(root / "sim", "dicom-ct-pd", out=exp)
    for f in sorted((exp / "projections").glob("*.dcm")):  # a 'patient' scan: identifiers in every file
        ds = pydicom.dcmread(f)
        ds.PatientName, ds.PatientID = "DOE^JANE", "PID-4711"
        ds.save_as(f)
    return {"root": root, "cache": cache, "scene": scene, "exp": exp, "index": index}


@pytest.fixture(scope="module")
def measured_run(sim):
    scene = load_scene(sim["exp"] / "measured.toml")
    lines = []
    res = run(scene, sim["root"] / "meas", methods=METHODS, cache_dir=sim["cache"], progress=False, report=True,
              log=lambda *a, **k: lines.append(" ".join(map(str, a))))
    return {"scene": scene, "res": res, "log": "\n".join(lines)}


# ---------------------------------------------------------------------------------------
def test_export_layout_and_tags(sim):
    scene, exp = sim["scene"], sim["exp"]
    files = sorted((exp / "projections").glob("*.dcm"))
    table = projection_table(scene, 0.1)
    assert len(files) == len(table)
    ds = pydicom.dcmread(files[5])
    sc = scene.scanner
    assert (ds.Rows, ds.Columns) == (sc.n_cols, sc.n_rows)  # DICOM Rows = channels
    assert ds[0x7029, 0x1011].value == sc.n_cols and ds[0x7029, 0x1010].value == sc.n_rows
    assert ds[0x7033, 0x100E].value == "FFSNONE" and ds[0x7037, 0x1009].value == "HELICAL"
    # focal centre (-rho sin phi, rho cos phi) = (R cos beta, R sin beta): beta = phi + pi/2
    phi = ds[0x7031, 0x1001].value
    beta = table.angle_rad[5]
    assert np.isclose(-sc.sid_mm * np.sin(phi), sc.sid_mm * np.cos(beta), atol=1e-3)
    assert np.isclose(sc.sid_mm * np.cos(phi), sc.sid_mm * np.sin(beta), atol=1e-3)
    assert np.isclose(ds[0x7031, 0x1002].value, table.source_z_mm[5], atol=1e-4)
    assert np.isclose(ds[0x7033, 0x1067].value, table.time_s[5] * 1000.0, rtol=1e-6)
    # pixel layout, numbering and rescale: pixel[channel, row] with the format's numbering (channel index
    # towards decreasing phi, row 1 at the +z end): the store's [row, column] transposed and both axes
    # reversed, within half a quantisation step; the central element reflected with them
    store = ProjectionStore.open(scene, 0.1, cache_dir=sim["cache"], create=False)
    p = store.read_indices([5], noisy=True)[0]
    store.close()
    pix = ds.pixel_array.astype(np.float64) * float(ds.RescaleSlope) + float(ds.RescaleIntercept)
    assert np.abs(pix.T[::-1, ::-1] - p).max() <= float(ds.RescaleSlope) * 0.5 + 1e-6
    assert list(ds[0x7031, 0x1033].value) == [(sc.n_cols + 1) / 2, (sc.n_rows + 1) / 2]
    assert ds.PatientPosition == "HFS" and float(ds[0x7041, 0x1001].value) == pytest.approx(0.0193)
    assert sim["index"]["files"]["quantisation_max_error"] <= float(ds.RescaleSlope)


def test_scene_from_series_maps_the_geometry(sim):
    m = load_scene(sim["exp"] / "measured.toml")
    s = sim["scene"]
    for k in ("sid_mm", "sdd_mm", "n_cols", "n_rows", "col_pitch_mm", "row_pitch_mm", "views_per_rotation",
              "rotation_time_s"):
        assert np.isclose(getattr(m.scanner, k), getattr(s.scanner, k), rtol=1e-6), k
    assert m.scan.pitches == (0.1,) and m.measured and m.has_cardiac and m.has_respiratory
    ta, tb = projection_table(s, 0.1), projection_table(m, 0.1)
    for col in ("time_s", "angle_rad", "source_z_mm", "cardiac_phase"):
        assert np.abs(getattr(ta, col) - getattr(tb, col)).max() < 1e-5, col
    # the amplitude: the .vxp holds r(t) every 5 ms, the model's own percentile grid
    assert np.abs(ta.resp_amplitude - tb.resp_amplitude).max() < 1e-4


def test_round_trip_gives_the_noisy_volumes(sim, measured_run):
    """simulate -> export -> run measured.toml: the simulated run's noisy volumes.

    The methods select the same rows (the same plan), and the volumes differ only by the uint16
    quantisation of the line integrals (<= slope/2 = 9e-5 per cell) and the trace sampling
    (amplitude within 1e-4): measured 0.07 HU at most on 2026-12-02.
    """
    cfg = reconstruct.ReconstructionConfig.from_scene(sim["scene"])
    cfg_m = reconstruct.ReconstructionConfig.from_scene(measured_run["scene"])
    tg = reconstruct.Targets(cardiac=sim["scene"].cardiac_targets, resp=sim["scene"].resp_targets)
    z = reconstruct.slice_positions(sim["scene"])
    pa = reconstruct.plan(cfg, projection_table(sim["scene"], 0.1), z, tg, ["nearest"])
    pb = reconstruct.plan(cfg_m, projection_table(measured_run["scene"], 0.1), z, tg, ["nearest"])
    assert np.array_equal(pa.methods["nearest"].proj_index, pb.methods["nearest"].proj_index)
    with h5py.File(sim["root"] / "sim" / "volumes.h5") as a, h5py.File(sim["root"] / "meas" / "volumes.h5") as b:
        for m in METHODS:
            for ij in [(0, 0), (0, 1), (1, 0), (1, 1)]:
                va = read_volume(a, f"recon/p0.100/noisy/{m}", ij)
                vb = read_volume(b, f"recon/p0.100/measured/{m}", ij)
                assert np.abs(va - vb).max() < 0.25, (m, ij)
                assert np.abs(va - vb).max() > 0  # the quantisation is there: not the same store


def test_measured_run_has_no_truth_and_no_identifiers(sim, measured_run):
    res, out = measured_run["res"], sim["root"] / "meas"
    assert res["measured"] and not res["ground_truth"]["available"]
    assert res["metrics"] == {} and res["stages"]["groundtruth"]["skipped_because"]
    report = (out / "report.md").read_text()
    assert "error against truth is unavailable" in report
    assert "a measured scan has no ground truth, so no error" in report and (out / "figures" / "coronal.png").exists()
    # the stage table says what "simulate" and "noise" mean for a measured scan, not the simulator's words
    assert "own noise" in res["stages"]["noise"]["skipped_because"] and "noise.enabled" not in report
    assert res["stages"]["simulate"]["does"] == "imports the measured projections into the projection store"
    assert res["stages"]["simulate"]["ran"] is False or "| simulate | yes (imports the measured projections" in report
    for text in ((out / "results.json").read_text(), report, measured_run["log"]):
        assert "DOE^JANE" not in text and "PID-4711" not in text
    with h5py.File(out / "volumes.h5") as f:
        assert "groundtruth" not in f
    # re-export of the measured scan: the run records the series only by its digest, so the scene file is
    # given again (and checked); anonymous unless --keep-identifiers
    with pytest.raises(ClreconError, match=r"records its series only as 'dicom-ct-pd series [0-9a-f]+'.*--scene"):
        export(out, "dicom-ct-pd", out=sim["root"] / "reexp")
    scene_file = sim["exp"] / "measured.toml"
    idx = export(out, "dicom-ct-pd", out=sim["root"] / "reexp", scene=scene_file)
    ds = pydicom.dcmread(sorted((sim["root"] / "reexp" / "projections").glob("*.dcm"))[0])
    assert str(ds.PatientName) == "ANONYMOUS" and idx["variant"] == "measured"
    export(out, "dicom-ct-pd", out=sim["root"] / "reexp-keep", keep_identifiers=True, scene=scene_file)
    ds = pydicom.dcmread(sorted((sim["root"] / "reexp-keep" / "projections").glob("*.dcm"))[0])
    assert str(ds.PatientName) == "DOE^JANE"
    # the volumes as DICOM CT series: the same rule
    export(out, "dicom", method="nearest", out=sim["root"] / "vol")
    ds = pydicom.dcmread(sorted((sim["root"] / "vol").rglob("*.dcm"))[0])
    assert str(ds.PatientName) == "ANONYMOUS" and str(ds.PatientID) == "ANONYMOUS"
    export(out, "dicom", method="nearest", out=sim["root"] / "vol-keep", keep_identifiers=True, scene=scene_file)
    ds = pydicom.dcmread(sorted((sim["root"] / "vol-keep").rglob("*.dcm"))[0])
    assert str(ds.PatientID) == "PID-4711"


def test_import_resumes_after_a_bad_file(sim, measured_run, tmp_path):
    """A truncated file fails its chunk with one line before anything of the chunk is written;
    earlier chunks stay as checksummed units; the fixed series resumes with only the rest and
    gives the same store as an uninterrupted import."""
    exp = tmp_path / "exp"
    shutil.copytree(sim["exp"], exp)
    victim = sorted((exp / "projections").glob("*.dcm"))[200]
    good = victim.read_bytes()
    victim.write_bytes(good[:-200])
    scene = load_scene(exp / "measured.toml")
    cache = tmp_path / "cache"
    with pytest.raises(ClreconError, match=rf"{victim.name}: PixelData holds \d+ bytes, expected \d+") as e:
        import_series(scene, 0.1, cache_dir=cache, chunk=64, progress=False)
    assert "\n" not in str(e.value)
    assert len(list(cache.glob("*.h5.units/*.unit*"))) == 3 and not list(cache.glob("*.h5"))  # 3 x 64 kept
    victim.write_bytes(good)  # a changed file is a changed series (listing signature): a fresh, whole import
    scene = load_scene(exp / "measured.toml")
    store = import_series(scene, 0.1, cache_dir=cache, chunk=64, progress=False)
    assert store.n_simulated == 384 and store.complete
    ref = import_series(measured_run["scene"], 0.1, cache_dir=tmp_path / "ref", progress=False)
    assert np.array_equal(store.read(0, 384), ref.read(0, 384))
    store.close()
    ref.close()


def test_interrupted_import_resumes(sim, tmp_path, monkeypatch):
    """An import stopped mid-way (here: an exception in the 4th chunk, as a kill -9 would stop
    it) keeps its finished chunks; the same command again imports only the rest."""
    from clrecon.simulation import measured as measured_mod

    scene = load_scene(sim["exp"] / "measured.toml")
    cache = tmp_path / "cache"
    real = measured_mod.read_projection
    calls = {"n": 0}

    def flaky(*a, **k):
        calls["n"] += 1
        if calls["n"] == 200:
            raise KeyboardInterrupt
        return real(*a, **k)

    monkeypatch.setattr(measured_mod, "read_projection", flaky)
    with pytest.raises(KeyboardInterrupt):
        import_series(scene, 0.1, cache_dir=cache, chunk=64, progress=False)
    monkeypatch.setattr(measured_mod, "read_projection", real)
    store = import_series(scene, 0.1, cache_dir=cache, chunk=64, progress=False)
    assert store.n_reused == 3 * 64 and store.n_simulated == 384 - 3 * 64 and store.complete
    store.close()


# ---------------------------------------------------------------------------------------
# recorded traces
def _vxp(path, t, amp, flag=None, ttl=None, rate=None):
    rate = rate or round(1.0 / np.median(np.diff(t)))
    flag = np.zeros(t.size, int) if flag is None else flag
    ttl = np.ones(t.size, int) if ttl is None else ttl
    rows = [f"{a:.7f},0.0,{int(round(x * 1000))},{f},{g},,0" for x, a, f, g in zip(t, amp, flag, ttl, strict=True)]
    path.write_text("[Header]\nCRC=0\nVersion=1.6\nData_layout=amplitude,phase,timestamp,validflag,ttlin,mark,ttlout\n"
                    f"Samples_per_second={rate}\nScale_factor=10.0\n[Data]\n" + "\n".join(rows) + "\n")


def test_vxp_and_csv_give_the_same_signals_and_lost_views_are_left_out(tmp_path):
    scene = load_scene("tiny")
    tr = signals.respiratory_trace(scene, step_s=0.04)
    flag = np.zeros(tr.time_s.size, int)
    lost = (tr.time_s > 0.3) & (tr.time_s < 0.5)  # the scan lasts 1.28 s
    cough = (tr.time_s > 0.8) & (tr.time_s < 0.9)
    flag[lost], flag[cough] = -1, -2
    _vxp(tmp_path / "b.vxp", tr.time_s, tr.raw, flag)
    csv_rows = "".join(f"{x:.6f},{a:.7f},{int(f == 0)}\n" for x, a, f in zip(tr.time_s, tr.raw, flag, strict=True))
    (tmp_path / "b.csv").write_text("time_s,amplitude,valid\n" + csv_rows)
    t = projection_table(scene, 0.1).time_s
    sv = scene.replace(signals={"breathing_trace": str(tmp_path / "b.vxp")}).signals
    sc = scene.replace(signals={"breathing_trace": str(tmp_path / "b.csv")}).signals
    a, b = recorded.view_signals(sv, t), recorded.view_signals(sc, t)
    assert np.allclose(a.resp_amplitude, b.resp_amplitude, atol=1e-6)
    assert a.excluded["lost_tracking"] > 0 and a.excluded["non_periodic"] > 0
    assert b.excluded["invalid"] == a.excluded["lost_tracking"] + a.excluded["non_periodic"]
    assert not a.usable[(t > 0.32) & (t < 0.48)].any() and a.usable[t < 0.27].all()
    # the amplitude rule: 5th/95th percentiles of the valid samples, clipped to [0, 1]
    lo, hi = np.percentile(tr.raw[flag == 0], [5, 95])
    want = np.clip((np.interp(t, tr.time_s, tr.raw) - lo) / (hi - lo), 0, 1)
    assert np.allclose(a.resp_amplitude, want, atol=1e-6)
    # the run counts the views left out and plans without them
    res = run(scene.replace(signals={"breathing_trace": str(tmp_path / "b.vxp")}), tmp_path / "run",
              methods=["nearest"], cache_dir=tmp_path / "cache", progress=False, report=False, log=_quiet)
    rs = res["recorded_signals"]["p0.100"]
    assert rs["views_excluded"] == int((~a.usable).sum()) > 0
    assert rs["excluded_by_reason"]["lost_tracking"] == a.excluded["lost_tracking"]


def test_trace_offset_and_beam_on(tmp_path):
    scene = load_scene("tiny")
    tr = signals.respiratory_trace(scene, step_s=0.02)
    ttl = (tr.time_s >= 0).astype(int)
    shifted = tr.time_s + 7.0  # the trace clock runs 7 s ahead of scan time; beam on at 7 s
    ttl[: 1] = 0
    _vxp(tmp_path / "s.vxp", np.concatenate([[6.98], shifted[1:]]), np.concatenate([[tr.raw[0]], tr.raw[1:]]),
         ttl=ttl)
    t = projection_table(scene, 0.1).time_s[1:]
    off = scene.replace(signals={"breathing_trace": str(tmp_path / "s.vxp"), "trace_offset_s": 7.0}).signals
    beam = scene.replace(signals={"breathing_trace": str(tmp_path / "s.vxp"), "trace_align": "beam-on",
                                  "trace_offset_s": -tr.time_s[1]}).signals
    a, b = recorded.view_signals(off, t), recorded.view_signals(beam, t)
    assert np.allclose(a.resp_amplitude, b.resp_amplitude, atol=1e-9)


def test_wfdb_r_peaks_match_the_csv(tmp_path):
    wfdb = pytest.importorskip("wfdb")
    scene = load_scene("tiny")
    peaks = signals.r_peaks(scene)
    fs = 250
    tt = np.arange(0, 20.0, 1 / fs)
    ecg = 0.05 * np.sin(2 * np.pi * 0.3 * tt)
    for p in peaks[(peaks > 0.2) & (peaks < 19.8)]:  # narrow QRS-like spikes at the R peaks
        ecg += 1.2 * np.exp(-0.5 * ((tt - p) / 0.012) ** 2) - 0.25 * np.exp(-0.5 * ((tt - p - 0.04) / 0.02) ** 2)
    wfdb.wrsamp("ecg", fs=fs, units=["mV"], sig_name=["II"], p_signal=ecg[:, None], write_dir=str(tmp_path),
                fmt=["16"])
    got = recorded.read_r_peaks(tmp_path / "ecg.hea")
    want = peaks[(peaks > 0.5) & (peaks < 19.5)]
    near = np.abs(got.time_s[:, None] - want[None, :]).min(axis=0)
    assert got.kind == "wfdb" and np.all(near < 0.02)


# ---------------------------------------------------------------------------------------
# bad inputs: one line naming the file, the tag or row, and what was expected
def _copy(sim, tmp_path) -> Path:
    exp = tmp_path / "exp"
    shutil.copytree(sim["exp"], exp)
    return exp


def _edit(path: Path, fn) -> None:
    ds = pydicom.dcmread(path)
    fn(ds)
    ds.save_as(path)


def _files(exp):
    return sorted((exp / "projections").glob("*.dcm"))


BAD_SERIES = {
    "missing tag": (lambda fs: _edit(fs[7], lambda ds: ds.__delitem__((0x7031, 0x1001))),
                    r"PROJ000008\.dcm: tag \(7031,1001\) DetectorFocalCenterAngularPosition is missing"),
    "mixed detector": (lambda fs: _edit(fs[9], lambda ds: ds.__setitem__(
        (0x7029, 0x1011), pydicom.DataElement((0x7029, 0x1011), "US", 95))),
        r"PROJ000010\.dcm: \(7029,1011\) NumberofDetectorColumns = 95 but .* has 96"),
    "duplicated view": (lambda fs: _edit(fs[11], lambda ds: setattr(ds, "InstanceNumber", 11)),
                        r"InstanceNumber 11 also in .*expected one file per view"),
    "gap": (lambda fs: fs[20].unlink(), r"PROJ000022\.dcm: InstanceNumber 22 follows 20 .*1 missing"),
    "non-monotonic timestamp": (lambda fs: _edit(fs[30], lambda ds: ds.__setitem__(
        (0x7033, 0x1067), pydicom.DataElement((0x7033, 0x1067), "FL", 1.0))),
        r"PROJ000031\.dcm: \(7033,1067\) Timestamp = 1 after .* expected strictly increasing"),
    "contradictory angle": (lambda fs: _edit(fs[40], lambda ds: ds.__setitem__(
        (0x7031, 0x1001), pydicom.DataElement((0x7031, 0x1001), "FL", 0.5))),
        r"PROJ00004[12]\.dcm: \(7031,1001\) DetectorFocalCenterAngularPosition steps by"),
    "truncated header": (lambda fs: fs[50].write_bytes(fs[50].read_bytes()[:300]),
                         r"PROJ000051\.dcm: truncated: the file ends after 300 bytes, inside its header"),
}


@pytest.mark.parametrize("case", sorted(BAD_SERIES))
def test_bad_series_is_one_line(sim, tmp_path, case):
    exp = _copy(sim, tmp_path)
    damage, pattern = BAD_SERIES[case]
    damage(_files(exp))
    with pytest.raises(ClreconError, match=pattern) as e:
        load_scene(exp / "measured.toml")
    assert "\n" not in str(e.value)


def test_contradictory_scene_key(sim, tmp_path):
    exp = _copy(sim, tmp_path)
    toml = exp / "measured.toml"
    toml.write_text(toml.read_text().replace("[scan]", "[scanner]\nn_cols = 90\n\n[scan]"))
    with pytest.raises(ClreconError, match=r"scanner\.n_cols = 90 contradicts .*\(7029,1011\) "
                                           r"NumberofDetectorColumns gives 96"):
        load_scene(toml)


def test_bad_traces_are_one_line(sim, tmp_path):
    exp = _copy(sim, tmp_path)
    vxp = exp / "breathing.vxp"
    lines = vxp.read_text().splitlines()
    short = tmp_path / "short.vxp"  # a trace shorter than the scan
    short.write_text("\n".join(lines[:10 + 200]) + "\n")
    toml = (exp / "measured.toml").read_text()
    (exp / "m.toml").write_text(toml.replace('"breathing.vxp"', f'"{short}"'))
    with pytest.raises(ClreconError, match=r"short\.vxp: the trace spans 0\.000\.\.0\.995 s .*expected a trace "
                                           r"covering every view"):
        run(load_scene(exp / "m.toml"), tmp_path / "r", methods=["nearest"], cache_dir=tmp_path / "c",
            progress=False, report=False, log=_quiet)
    trunc = tmp_path / "trunc.vxp"  # a torn last row
    trunc.write_text("\n".join(lines[:500] + [lines[500][:9]]) + "\n")
    with pytest.raises(ClreconError, match=r"trunc\.vxp: line 501: 1 fields, expected 7 .*truncated"):
        recorded.read_breathing_trace(trunc)
    back = tmp_path / "back.vxp"
    back.write_text("\n".join(lines[:20] + [lines[21], lines[20]] + lines[22:40]) + "\n")
    with pytest.raises(ClreconError, match=r"back\.vxp: line 22: timestamp .* expected strictly increasing"):
        recorded.read_breathing_trace(back)
    nohdr = tmp_path / "nohdr.vxp"
    nohdr.write_text("\n".join([lines[0]] + lines[4:]) + "\n")  # no Data_layout
    with pytest.raises(ClreconError, match=r"nohdr\.vxp: \[Header\] has no Data_layout="):
        recorded.read_breathing_trace(nohdr)
    flat = tmp_path / "flat.csv"
    flat.write_text("time_s,amplitude\n" + "".join(f"{0.04 * i:.2f},1.0\n" for i in range(100)))
    with pytest.raises(ClreconError, match=r"flat\.csv: the valid amplitudes have no spread"):
        recorded.read_breathing_trace(flat).percentiles()


def test_ecg_without_r_peaks(tmp_path):
    wfdb = pytest.importorskip("wfdb")
    none = tmp_path / "none.csv"
    none.write_text("r_peak_s\n0.5\n")
    with pytest.raises(ClreconError, match=r"none\.csv: the file holds 1 R peak\(s\); expected at least 2"):
        recorded.read_r_peaks(none)
    fs = 250
    wfdb.wrsamp("flat", fs=fs, units=["mV"], sig_name=["II"], p_signal=np.zeros((fs * 10, 1)) + 0.01,
                write_dir=str(tmp_path), fmt=["16"])
    with pytest.raises(ClreconError, match=r"flat\.hea: xqrs_detect found 0 R peak\(s\)"):
        recorded.read_r_peaks(tmp_path / "flat.hea")
    scene = load_scene("tiny")
    short = tmp_path / "short.csv"
    short.write_text("r_peak_s\n" + "".join(f"{x:.6f}\n" for x in signals.r_peaks(scene)[:2]))
    sig = scene.replace(signals={"ecg_trace": str(short)}).signals
    with pytest.raises(ClreconError, match=r"short\.csv: R peaks span .* expected an R peak before the first view "
                                           r"and after the last"):
        recorded.view_signals(sig, projection_table(scene, 0.1).time_s)


def test_dicom_ct_pd_tag_table_is_the_published_one():
    # (group, element) of the tags the TCIA manual and its readers use (Moen et al. 2021, Table IV)
    t = dicom_ct_pd.TAGS
    assert t["DetectorFocalCenterAngularPosition"][0] == (0x7031, 0x1001)
    assert t["ConstantRadialDistance"][0] == (0x7031, 0x1031)
    assert t["FlyingFocalSpotMode"][0] == (0x7033, 0x100E)
    assert t["Timestamp"][0] == (0x7033, 0x1067)
    assert json.dumps(sorted(t))  # every name serialisable (index.json)


def test_sigkill_mid_import_then_resume(sim, measured_run, tmp_path):
    """kill -9 in the middle of writing the 3rd chunk: the two finished chunks survive, the torn one
    is discarded, and the rerun imports the rest into a store equal to an uninterrupted import."""
    import os
    import subprocess
    import sys

    cache = tmp_path / "cache"
    code = ("import sys; from clrecon.config.scene import load_scene; "
            "from clrecon.simulation.measured import import_series; "
            "s = load_scene(sys.argv[1]); import_series(s, 0.1, cache_dir=sys.argv[2], chunk=64, progress=False)")
    env = dict(os.environ, CLRECON_FAULT="simulate:3", PYTHONPATH=str(Path(__file__).resolve().parents[2]))
    proc = subprocess.run([sys.executable, "-c", code, str(sim["exp"] / "measured.toml"), str(cache)], env=env,
                          capture_output=True, timeout=300)
    assert proc.returncode == -9, proc.stderr.decode()[-500:]
    store = import_series(measured_run["scene"], 0.1, cache_dir=cache, chunk=64, progress=False)
    assert store.n_reused == 2 * 64 and store.n_simulated == 384 - 2 * 64 and store.complete
    ref = import_series(measured_run["scene"], 0.1, cache_dir=tmp_path / "ref", progress=False)
    assert np.array_equal(store.read(0, 384), ref.read(0, 384))
    store.close()
    ref.close()


def test_cylindrical_ffs_series_maps_onto_the_scanner_keys(sim, tmp_path):
    """CYLINDRICAL + FFSXY with a quarter-channel offset map onto the cylindrical/FFS scanner keys
    (scanner.detector, central_col/row, flying_focal_spot, ffs_*)."""
    from clrecon.core.detector import DETECTORS

    exp = _copy(sim, tmp_path)
    a, r = 5e-4, 0.1
    files = _files(exp)

    def fl(tag, value):
        return pydicom.DataElement(tag, "FL", value)

    for k, f in enumerate(files):
        s = -1.0 if k % 2 == 0 else 1.0  # minus state first
        def edit(ds, s=s):
            ds[0x7029, 0x100B] = pydicom.DataElement((0x7029, 0x100B), "CS", "CYLINDRICAL")
            ds[0x7033, 0x100E] = pydicom.DataElement((0x7033, 0x100E), "CS", "FFSXY")
            ds[0x7033, 0x100B] = fl((0x7033, 0x100B), s * a)
            ds[0x7033, 0x100D] = fl((0x7033, 0x100D), s * r)
            ds[0x7031, 0x1033] = fl((0x7031, 0x1033), [48.75, 4.5])
        _edit(f, edit)
    g = dicom_ct_pd.series_geometry(exp / "projections", None)
    assert g.scanner["detector"] == "cylindrical" and g.scanner["flying_focal_spot"] == "phi"
    assert np.isclose(g.scanner["ffs_angle_rad"], a, rtol=1e-6) and np.isclose(g.scanner["ffs_radial_mm"], r, rtol=1e-6)
    # the format numbers channels towards decreasing phi and rows from the +z end: the store's numbering
    # reverses both, so the 1-based central element (48.75, 4.5) is the 0-based (96 - 48.75, 8 - 4.5)
    assert g.scanner["ffs_z_mm"] == 0.0 and g.scanner["central_col"] == 47.25 and g.scanner["central_row"] == 3.5
    assert "cylindrical" in DETECTORS
    m = load_scene(exp / "measured.toml")
    assert m.scanner.detector == "cylindrical" and m.scanner.flying_focal_spot == "phi"
    assert m.scanner.central_col == 47.25 and np.isclose(m.scanner.ffs_angle_rad, a, rtol=1e-6)
    _edit(files[0], lambda ds: ds.__setitem__((0x7033, 0x100B), fl((0x7033, 0x100B), a)))
    with pytest.raises(ClreconError, match=r"PROJ000001\.dcm: source shifts .* expected -0\.0005, -0\.1, 0 for "
                                           r"focal-spot state 0 of mode 'phi'"):
        dicom_ct_pd.series_geometry(exp / "projections", None)


def test_view_time_without_timestamps(sim, tmp_path):
    """No Timestamp tag: t_k = k * rotation_time_s / views, and the scene must give rotation_time_s."""
    exp = _copy(sim, tmp_path)
    for f in _files(exp):
        _edit(f, lambda ds: ds.__delitem__((0x7033, 0x1067)))
    with pytest.raises(ClreconError, match=r"no \(7033,1067\) Timestamp in the series; give scanner\.rotation_time_s"):
        load_scene(exp / "measured.toml")
    toml = exp / "measured.toml"
    toml.write_text(toml.read_text().replace("[scan]", "[scanner]\nrotation_time_s = 0.3\n\n[scan]"))
    m = load_scene(toml)
    t = projection_table(m, 0.1).time_s
    assert np.allclose(t, np.arange(t.size) * 0.3 / 90, rtol=0, atol=1e-12)


def test_cylindrical_z_ffs_round_trip(tmp_path):
    """A cylindrical scan with a quarter-channel offset and z-FFS, simulated -> exported ->
    reconstructed as measured: the same table (each view's focal-spot shift included), the same
    plan and the noisy volumes within the uint16 quantisation, as for the flat detector."""
    cache = tmp_path / "cache"
    scene = load_scene("tiny").replace(scanner={"detector": "cylindrical", "central_col": 47.75,
                                                "flying_focal_spot": "z", "ffs_z_mm": 0.4})
    run(scene, tmp_path / "sim", methods=["nearest"], cache_dir=cache, progress=False, report=False, log=_quiet)
    exp = tmp_path / "exp"
    export(tmp_path / "sim", "dicom-ct-pd", out=exp)
    m = load_scene(exp / "measured.toml")
    assert (m.scanner.detector, m.scanner.central_col, m.scanner.flying_focal_spot) == ("cylindrical", 47.75, "z")
    assert np.isclose(m.scanner.ffs_z_mm, 0.4, rtol=1e-6)
    ta, tb = projection_table(scene, 0.1), projection_table(m, 0.1)
    assert np.abs(ta.focal_shift - tb.focal_shift).max() < 1e-6
    assert np.abs(ta.source_z_mm - tb.source_z_mm).max() < 1e-4
    run(m, tmp_path / "meas", methods=["nearest"], cache_dir=cache, progress=False, report=False, log=_quiet)
    with h5py.File(tmp_path / "sim" / "volumes.h5") as a, h5py.File(tmp_path / "meas" / "volumes.h5") as b:
        for ij in [(0, 0), (1, 1)]:
            va = read_volume(a, "recon/p0.100/noisy/nearest", ij)
            vb = read_volume(b, "recon/p0.100/measured/nearest", ij)
            assert 0 < np.abs(va - vb).max() < 0.25, ij


def test_dicom_ct_pd_export_passes_dciodvfy(sim):
    """Zero dciodvfy errors on the exported projections (17 per file before issue 37); the private groups
    are 'unrecognized tag' warnings only."""
    import subprocess

    if shutil.which("dciodvfy") is None:
        pytest.skip("dciodvfy not installed (Debian package dicom3tools: apt-get install -y dicom3tools)")
    files = _files(sim["exp"])
    for f in (files[0], files[len(files) // 2], files[-1]):
        out = subprocess.run(["dciodvfy", str(f)], capture_output=True, text=True, timeout=60)
        errors = [line for line in (out.stdout + out.stderr).splitlines() if line.startswith("Error")]
        assert errors == [], (f.name, errors)


def test_measured_re_export_passes_dciodvfy_and_reads_back(sim, measured_run, tmp_path):
    """A measured run re-exported as DICOM-CT-PD is derived data (ImageType DERIVED\\SECONDARY): with
    ORIGINAL\\PRIMARY and RescaleType LINE_INTEGRAL dciodvfy gave one error per file ("must be HU for
    ORIGINAL non-LOCALIZER images"). The re-export reads back as a series with the input's geometry."""
    import subprocess

    out = tmp_path / "reexp"
    export(sim["root"] / "meas", "dicom-ct-pd", out=out, scene=sim["exp"] / "measured.toml")
    files = _files(out)
    ds = pydicom.dcmread(files[0], stop_before_pixels=True)
    assert list(ds.ImageType)[:2] == ["DERIVED", "SECONDARY"] and ds.RescaleType == "LINE_INTEGRAL"
    a, b = dicom_ct_pd.series_index(sim["exp"] / "projections"), dicom_ct_pd.series_index(out / "projections")
    assert len(a) == len(b) and np.abs(a.z_mm - b.z_mm).max() < 1e-4 and np.abs(a.phi_rad - b.phi_rad).max() < 1e-6
    m = load_scene(out / "measured.toml")
    assert m.measured and np.isclose(m.scanner.sid_mm, sim["scene"].scanner.sid_mm, rtol=1e-6)
    if shutil.which("dciodvfy") is None:
        pytest.skip("dciodvfy not installed (Debian package dicom3tools: apt-get install -y dicom3tools)")
    for f in (files[0], files[len(files) // 2], files[-1]):
        p = subprocess.run(["dciodvfy", str(f)], capture_output=True, text=True, timeout=60)
        errors = [line for line in (p.stdout + p.stderr).splitlines() if line.startswith("Error")]
        assert errors == [], (f.name, errors)
