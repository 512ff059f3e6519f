"""Every convention a DICOM-CT-PD series can be written in, read right or refused (issue 35).

The engine's simulator scans a water cylinder with an off-centre bone rod and a bone sphere
(``tests/support/rod_phantom.py``) on a cylindrical detector with a quarter-detector offset; the DICOM-CT-PD
writer writes the scan in one convention per test (pixel layout, channel and row numbering, gantry
and table direction, flying focal spot, patient position); the measured reconstruction must put the
rod within 0.5 mm of its true place and water within 1 HU, or refuse the series in one line, never
reconstruct it mirrored. Conventions: ``docs/measured-conventions.md``.
"""

from __future__ import annotations

import json
from pathlib import Path

import h5py
import numpy as np
import pydicom
import pytest
import rod_phantom as rp

from clrecon.config.scene import load_scene
from clrecon.core.errors import ClreconError
from clrecon.outputs.export import export
from clrecon.outputs.rundir import RunDirectory
from clrecon.outputs.volumes import read_volume
from clrecon.outputs.writers.dicom_ct_pd import Convention, export_scan
from clrecon.pipeline.run import run
from clrecon.scan import dicom_ct_pd, orientation_check
from clrecon.scan.patient_frame import LPS_SIGNS, image_orientation, lps_signs, to_lps

ROD_TOL_MM = 0.5
WATER_TOL_HU = 1.0


def _quiet(*a, **k):
    pass


def _simulate(root: Path, name: str, symmetric: bool = False, **scan) -> Path:
    frames = rp.write_phantom(root / f"phantom-{'sym' if symmetric else 'rod'}", symmetric=symmetric)
    (root / f"{name}.toml").write_text(rp.scene_toml(frames, **scan))
    run(load_scene(root / f"{name}.toml"), root / name, cache_dir=root / "cache", progress=False, report=False,
        log=_quiet)
    return root / name


@pytest.fixture(scope="module")
def root(tmp_path_factory):
    return tmp_path_factory.mktemp("conventions")


@pytest.fixture(scope="module")
def sim(root):
    """The reference scan: gantry angle and table increasing, no flying focal spot."""
    return _simulate(root, "sim")


def _write(sim_dir: Path, out: Path, **convention) -> Path:
    export_scan(RunDirectory(sim_dir), out, convention=Convention(**convention))
    return out


def _undeclared(series: Path) -> Path:
    """The series' measured.toml without the flip keys the writer declared: the reading from the tags alone."""
    text = "".join(line for line in (series / "measured.toml").read_text().splitlines(keepends=True)
                   if not line.startswith("flip_"))
    (series / "undeclared.toml").write_text(text)
    return series / "undeclared.toml"


def _measure(root: Path, series: Path, name: str, **scan_keys) -> dict:
    """Reconstruct ``series/measured.toml`` (plus ``scan_keys``) and measure the rod and the water."""
    toml = series / "measured.toml"
    if scan_keys:
        extra = "".join(f"{k} = {json.dumps(v)}\n" for k, v in scan_keys.items())
        toml = series / f"{name}.toml"
        toml.write_text(_undeclared(series).read_text().replace('timestamp_unit = "ms"\n',
                                                                'timestamp_unit = "ms"\n' + extra))
    scene = load_scene(toml)
    res = run(scene, root / f"run-{name}", cache_dir=root / "cache", progress=False, report=True, log=_quiet)
    with h5py.File(root / f"run-{name}" / "volumes.h5") as f:
        x, y = f["axes/x_mm"][()], f["axes/y_mm"][()]
        vol = read_volume(f, f"recon/p{scene.scan.pitches[0]:.3f}/measured/nearest", (0, 0))
    m = [rp.rod_position_and_water(vol[k], x, y) for k in range(vol.shape[0])]
    return {"scene": scene, "results": res, "slices": m, "rod_error_mm": max(s["rod_error_mm"] for s in m),
            "water_hu": max((s["water_hu"] for s in m), key=abs), "dir": root / f"run-{name}"}


def _assert_right(meas: dict) -> None:
    assert meas["rod_error_mm"] <= ROD_TOL_MM, meas["slices"]
    assert abs(meas["water_hu"]) <= WATER_TOL_HU, meas["slices"]
    check = meas["results"]["measured_scan"]["orientation_check"]
    assert check["channels"]["verdict"] == "confirmed", check
    assert check["rows"]["verdict"] == "confirmed", check


# ---------------------------------------------------------------------------------------
def test_the_format_numbering_in_the_tcia_layout(root, sim):
    """DICOM Rows = channels (the TCIA files), channels towards decreasing phi, row 1 at the +z end."""
    series = _write(sim, root / "tcia")
    ds = pydicom.dcmread(root / "tcia" / "projections" / "PROJ000001.dcm")
    assert (ds.Rows, ds.Columns) == (160, 8)
    meas = _measure(root, series, "tcia")
    _assert_right(meas)
    assert meas["results"]["measured_scan"]["reading"]["pixel_layout"] == "rows-are-channels"
    report = (meas["dir"] / "report.md").read_text()
    assert "Orientation check" in report and "conjugate rays" in report and "channels mirrored" in report


def test_the_format_numbering_with_rows_as_dicom_rows(root, sim):
    """DICOM Rows = detector rows: the layout comes from the tags, not from the user."""
    series = _write(sim, root / "rowsrows", layout="rows-are-detector-rows")
    ds = pydicom.dcmread(root / "rowsrows" / "projections" / "PROJ000001.dcm")
    assert (ds.Rows, ds.Columns) == (8, 160)
    meas = _measure(root, series, "rowsrows")
    _assert_right(meas)
    assert meas["results"]["measured_scan"]["reading"]["pixel_layout"] == "rows-are-detector-rows"


def test_channels_numbered_the_other_way_are_refused_unless_declared(root, sim):
    """A series numbering its channels opposite to the format (clrecon's store order, as exported before
    issue 35): read from the tags it would be point-reflected, so it is refused in one line naming the
    residuals and the remedy; declared, or with scan.orientation = 'auto', it reconstructs right."""
    series = _write(sim, root / "chanrev", flip_channels=True)
    with pytest.raises(ClreconError, match=r"the data contradict the numbering read from the tags \(channels: residual "
                                           r"[0-9.e-]+ as read, [0-9.e-]+ channels mirrored\); the image would be "
                                           r"mirrored: set scan.flip_channels = true") as e:
        load_scene(_undeclared(series))
    assert "\n" not in str(e.value)
    _assert_right(_measure(root, series, "chanrev-declared", flip_channels=True))
    auto = _measure(root, series, "chanrev-auto", orientation="auto")
    assert auto["rod_error_mm"] <= ROD_TOL_MM and abs(auto["water_hu"]) <= WATER_TOL_HU
    ck = auto["results"]["measured_scan"]["orientation_check"]
    assert ck["channels"]["verdict"] == "mirror fits better" and ck["used"]["flip_channels"] is True
    assert auto["scene"].scan.flip_channels is True
    assert "mirrored by the data; the better fit was taken" in (auto["dir"] / "report.md").read_text()


def test_rows_numbered_the_other_way_are_refused_unless_declared(root, sim):
    series = _write(sim, root / "rowrev", flip_rows=True)
    with pytest.raises(ClreconError, match=r"\(rows: residual [0-9.e-]+ as read, [0-9.e-]+ rows mirrored\).*"
                                           r"set scan.flip_rows = true"):
        load_scene(_undeclared(series))
    _assert_right(_measure(root, series, "rowrev-declared", flip_rows=True))
    auto = _measure(root, series, "rowrev-auto", orientation="auto")
    assert auto["rod_error_mm"] <= ROD_TOL_MM and auto["scene"].scan.flip_rows is True


def test_central_element_not_reflected_with_the_channels_is_refused(root, sim, tmp_path):
    """The issue's flip_channels case: channels reversed but the quarter offset's central element kept
    (0.8 mm half-column error, up to 247 HU at the edges): the conjugate rays see it, in any mode."""
    src = root / "tcia"
    if not src.exists():
        _write(sim, src)
    series = tmp_path / "central"
    series.mkdir()
    for f in sorted((src / "projections").glob("*.dcm")):
        ds = pydicom.dcmread(f)
        x, y = ds[0x7031, 0x1033].value
        ds[0x7031, 0x1033].value = [161.0 - x, y]  # the element number of the other channel numbering
        (series / "projections").mkdir(exist_ok=True)
        ds.save_as(series / "projections" / f.name)
    (series / "measured.toml").write_text((src / "measured.toml").read_text())
    for orientation in ("tags", "auto"):
        toml = series / f"{orientation}.toml"
        toml.write_text((series / "measured.toml").read_text().replace(
            'timestamp_unit = "ms"\n', f'timestamp_unit = "ms"\norientation = "{orientation}"\n'))
        with pytest.raises(ClreconError, match=r"\(7031,1033\) DetectorCentralElement does not fit the channel "
                                               r"numbering"):
            load_scene(toml)


def test_decreasing_gantry_angle(root):
    """The gantry turning the other way (phi0 decreasing, as the TCIA Siemens files): read, not refused."""
    sim_dir = _simulate(root, "sim-cw", rotation="decreasing")
    series = _write(sim_dir, root / "cw")
    phis = [float(pydicom.dcmread(f, stop_before_pixels=True)[0x7031, 0x1001].value)
            for f in sorted((series / "projections").glob("*.dcm"))[:3]]
    step = np.diff(np.unwrap(phis))
    assert np.all(step < 0) and np.allclose(step, -2 * np.pi / 120, atol=1e-5)
    meas = _measure(root, series, "cw")
    _assert_right(meas)
    assert meas["scene"].scan.rotation == "decreasing"


def test_decreasing_table(root):
    """The source moving towards -z (the table the other way)."""
    sim_dir = _simulate(root, "sim-down", table="decreasing")
    series = _write(sim_dir, root / "down")
    z = [float(pydicom.dcmread(f, stop_before_pixels=True)[0x7031, 0x1002].value)
         for f in sorted((series / "projections").glob("*.dcm"))[:3]]
    assert z[0] > z[1] > z[2]
    meas = _measure(root, series, "down")
    _assert_right(meas)
    assert meas["scene"].scan.table_direction == "decreasing"


def test_flying_focal_spot_states_as_recorded_with_the_gantry_turning_back(root):
    """In-plane and z flying focal spot (FFSXYZ) recorded per view, gantry angle decreasing: each view's
    source shifts are read as written and the FBP takes view j's state on a backwards gantry."""
    sim_dir = _simulate(root, "sim-ffs", rotation="decreasing", ffs="phi+z")
    series = _write(sim_dir, root / "ffs")
    ds = pydicom.dcmread(series / "projections" / "PROJ000002.dcm", stop_before_pixels=True)
    assert ds[0x7033, 0x100E].value == "FFSXYZ" and ds[0x7033, 0x100B].value > 0
    meas = _measure(root, series, "ffs")
    assert meas["rod_error_mm"] <= ROD_TOL_MM and abs(meas["water_hu"]) <= WATER_TOL_HU, meas["slices"]
    assert meas["scene"].scanner.flying_focal_spot == "phi+z"


def test_symmetric_phantom_cannot_tell(root):
    """A centred water cylinder is its own mirror image: the check says it cannot tell (a warning in the
    results and the report), reads from the tags and, with 'auto', never guesses."""
    sim_dir = _simulate(root, "sim-sym", symmetric=True)
    series = _write(sim_dir, root / "sym", flip_channels=True)  # numbered the other way: the data cannot see it
    for orientation in ("tags", "auto"):
        toml = series / f"{orientation}.toml"
        toml.write_text(_undeclared(series).read_text().replace(
            'timestamp_unit = "ms"\n', f'timestamp_unit = "ms"\norientation = "{orientation}"\n'))
        scene = load_scene(toml)
        g = dicom_ct_pd.series_geometry(scene.scan.projections, None, orientation=orientation)
        ck = g.check
        assert ck["channels"]["verdict"] == "cannot tell", ck
        assert "cannot tell the channels' numbering" in ck["warning"]
        assert scene.scan.flip_channels is False  # the tags' reading, never a guess
    res = run(scene, root / "run-sym", cache_dir=root / "cache", progress=False, report=True, log=_quiet)
    assert "cannot tell" in res["measured_scan"]["orientation_check"]["warning"]
    assert "**Warning: the data cannot tell" in (root / "run-sym" / "report.md").read_text()


def test_auto_never_picks_a_wrong_reading_on_the_fixtures(root, sim):
    """On every reading of the reference scan (the four channel x row numberings), 'auto' takes the
    right one: the residual of the right reading is the lowest by at least CONFIRM_RATIO."""
    for fc in (False, True):
        for fr in (False, True):
            out = root / f"auto-{int(fc)}{int(fr)}"
            if not out.exists():
                _write(sim, out, flip_channels=fc, flip_rows=fr)
            g = dicom_ct_pd.series_geometry(out / "projections", None, orientation="auto")
            assert g.reading_keys == {"flip_channels": fc, "flip_rows": fr}, (fc, fr, g.check)
            for test in ("channels", "rows"):
                r = g.check[test]
                assert r["verdict"] in ("confirmed", "mirror fits better") and r["ratio"] is not None
                ratio = r["ratio"] if r["verdict"] == "confirmed" else 1.0 / r["ratio"]
                assert ratio >= orientation_check.CONFIRM_RATIO


def test_water_coefficient_from_the_file(root, sim, tmp_path):
    """(7041,1001) WaterAttenuationCoefficient sets mu_water (HU = 1000 (mu - mu_w) / mu_w); the report and
    results say it came from the file; a value in 1/cm is refused in one line."""
    src = root / "tcia"
    if not src.exists():
        _write(sim, src)
    series = tmp_path / "w"
    (series / "projections").mkdir(parents=True)
    for f in sorted((src / "projections").glob("*.dcm")):
        ds = pydicom.dcmread(f)
        ds[0x7041, 0x1001].value = "0.01926"
        ds.save_as(series / "projections" / f.name)
    (series / "measured.toml").write_text((src / "measured.toml").read_text())
    scene = load_scene(series / "measured.toml")
    assert scene.phantom.mu_water_per_mm == pytest.approx(0.01926)
    from clrecon.outputs.measured_record import measured_summary

    cal = measured_summary(scene)["calibration"]
    assert cal["mu_water_per_mm"]["from"] == "file (7041,1001) WaterAttenuationCoefficient"
    assert cal["rescale"]["from"].startswith("file (0028,1053) RescaleSlope")
    f0 = sorted((series / "projections").glob("*.dcm"))[0]
    ds = pydicom.dcmread(f0)
    ds[0x7041, 0x1001].value = "0.1926"
    ds.save_as(f0)
    with pytest.raises(ClreconError, match=r"PROJ000001\.dcm: \(7041,1001\) WaterAttenuationCoefficient = 0\.1926; "
                                           r"expected mu_water in 1/mm"):
        load_scene(series / "measured.toml")


# ---------------------------------------------------------------------------------------
# handedness and patient position
def test_patient_position_table_is_rotations_only():
    for pos, signs in LPS_SIGNS.items():
        assert np.prod(signs) == 1 or np.linalg.det(np.diag(signs)) == 1, pos  # a rotation: no mirror
        iop = image_orientation(pos)
        row, col = np.array(iop[:3]), np.array(iop[3:])
        normal = np.cross(row, col)
        # the slice normal in LPS is the scanner's +z times the z sign: the image keeps its handedness
        assert np.allclose(normal, [0, 0, signs[0] * signs[1]])
        assert np.allclose(to_lps(pos, [1.0, 2.0, 3.0]), np.array(signs) * [1.0, 2.0, 3.0])
    with pytest.raises(ClreconError, match=r"'HFDL'; expected one of HFS, HFP, FFS, FFP"):
        lps_signs("HFDL")


@pytest.mark.parametrize("position", ["FFS", "HFP"])
def test_patient_position_from_the_series_goes_into_the_exported_image(root, sim, tmp_path, position):
    """A series written for a patient feet first (or prone): the image series says so, and the rod's pixel,
    placed by ImagePositionPatient and ImageOrientationPatient, lands at the rod's LPS position."""
    src = root / "tcia"
    if not src.exists():
        _write(sim, src)
    series = tmp_path / "pos"
    (series / "projections").mkdir(parents=True)
    for f in sorted((src / "projections").glob("*.dcm")):
        ds = pydicom.dcmread(f)
        ds.PatientPosition = position
        ds.save_as(series / "projections" / f.name)
    (series / "measured.toml").write_text((src / "measured.toml").read_text())
    meas = _measure(tmp_path, series, "pos")
    assert meas["rod_error_mm"] <= ROD_TOL_MM  # the volume is in the scanner frame, as before
    assert meas["results"]["measured_scan"]["patient_position"]["lps_signs"] == list(LPS_SIGNS[position])
    export(meas["dir"], "dicom", method="nearest", out=tmp_path / "img")
    files = sorted((tmp_path / "img").rglob("IM*.dcm"))
    ds = pydicom.dcmread(files[0])
    assert ds.PatientPosition == position
    assert [float(v) for v in ds.ImageOrientationPatient] == image_orientation(position)
    ipp = np.array([float(v) for v in ds.ImagePositionPatient])
    row_cos, col_cos = np.array(ds.ImageOrientationPatient[:3], float), np.array(ds.ImageOrientationPatient[3:], float)
    dr, dc = (float(v) for v in ds.PixelSpacing)
    hu = ds.pixel_array * float(ds.RescaleSlope) + float(ds.RescaleIntercept)
    rr, cc = np.nonzero(hu > 500)  # bone pixels: the rod and the sphere
    xy = (ipp + cc[:, None] * dc * row_cos + rr[:, None] * dr * col_cos)[:, :2]
    near = np.hypot(*(xy - to_lps(position, [*rp.ROD_XY, 0.0])[:2]).T) < 2 * rp.ROD_RADIUS_MM
    assert near.sum() > 20  # the rod's pixels are around its LPS place
    # a patient's left stays left: the rod (patient's left for HFS, x > 0) is at LPS x = sx * 40 mm
    lps = ipp + cc[near].mean() * dc * row_cos + rr[near].mean() * dr * col_cos
    assert np.allclose(lps[:2], to_lps(position, [*rp.ROD_XY, 0.0])[:2], atol=1.5)
