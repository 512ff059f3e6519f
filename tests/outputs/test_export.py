"""DICOM / NIfTI export of a run directory: files read back with pydicom / nibabel."""

from __future__ import annotations

import h5py
import numpy as np
import pytest
from fake_run_dir import fake_scene, make_fake_run

from clrecon.cli import main
from clrecon.core.errors import ClreconError, StoreError
from clrecon.outputs.export import export, hu_to_stored, resolve_source, target_tag
from clrecon.outputs.volumes import open_volumes, read_volume

pydicom = pytest.importorskip("pydicom")
nib = pytest.importorskip("nibabel")


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    d = tmp_path_factory.mktemp("run")
    make_fake_run(d)
    return d


def _truth(run_dir, dataset):
    with open_volumes(run_dir) as f:
        ax = {k: f[f"axes/{k}"][()] for k in ("cardiac_phase", "resp_amplitude", "z_mm", "y_mm", "x_mm")}
        return ax, read_volume(f, dataset)


def test_dicom_roundtrip_values_geometry_and_uids(run_dir, tmp_path):
    index = export(run_dir, "dicom", method="barycentric", pitch="0.1", variant="noisy", out=tmp_path / "dcm")
    ax, vol = _truth(run_dir, "recon/p0.100/noisy/barycentric")
    nc, nr, nz, ny, nx = vol.shape
    assert len(index["targets"]) == nc * nr
    dx, dy, dz = (float(ax[k][1] - ax[k][0]) for k in ("x_mm", "y_mm", "z_mm"))
    studies, frames, series, temporal = set(), set(), set(), set()
    for t in index["targets"]:
        ci, ri = t["cardiac_index"], t["resp_index"]
        assert len(t["files"]) == nz
        series_of_target = set()
        for k, name in enumerate(t["files"]):
            ds = pydicom.dcmread(tmp_path / "dcm" / name)
            studies.add(ds.StudyInstanceUID)
            frames.add(ds.FrameOfReferenceUID)
            series_of_target.add(ds.SeriesInstanceUID)
            temporal.add(int(ds.TemporalPositionIdentifier))
            assert ds.Modality == "CT" and ds.SOPClassUID == "1.2.840.10008.5.1.4.1.1.2"
            assert ds.pixel_array.dtype == np.int16
            hu = ds.pixel_array * float(ds.RescaleSlope) + float(ds.RescaleIntercept)
            assert np.max(np.abs(hu - vol[ci, ri, k])) <= 0.5 * float(ds.RescaleSlope) + 1e-3
            assert [float(v) for v in ds.ImageOrientationPatient] == [1, 0, 0, 0, 1, 0]
            ipp = np.array([float(v) for v in ds.ImagePositionPatient])
            np.testing.assert_allclose(ipp, [ax["x_mm"][0], ax["y_mm"][0], ax["z_mm"][k]], atol=1e-6)
            np.testing.assert_allclose([float(v) for v in ds.PixelSpacing], [dy, dx])
            assert float(ds.SliceThickness) == pytest.approx(dz)
            assert (ds.Rows, ds.Columns) == (ny, nx)
            # pixel (row r, column c) lies at IPP + c*dx*row_cosine + r*dy*column_cosine: a voxel centre
            r, c = ny - 2, 3
            pos = (ipp + c * float(ds.PixelSpacing[1]) * np.array([1, 0, 0])
                   + r * float(ds.PixelSpacing[0]) * np.array([0, 1, 0]))
            np.testing.assert_allclose(pos, [ax["x_mm"][c], ax["y_mm"][r], ax["z_mm"][k]], atol=1e-6)
            tag = target_tag(ax["cardiac_phase"][ci], ax["resp_amplitude"][ri])
            assert ds.SeriesDescription.startswith(f"5DCT barycentric {tag}")
            block = ds.private_block(0x0011, "CLRECON 5DCT")
            assert block[0x10].value == pytest.approx(ax["cardiac_phase"][ci])
            assert block[0x11].value == pytest.approx(ax["resp_amplitude"][ri])
            assert float(ds.NominalPercentageOfCardiacPhase) == pytest.approx(100 * ax["cardiac_phase"][ci], abs=1e-3)
            assert int(ds.NumberOfTemporalPositions) == nc * nr
        assert len(series_of_target) == 1
        series |= series_of_target
    assert len(studies) == 1 and len(frames) == 1
    assert len(series) == nc * nr and temporal == set(range(1, nc * nr + 1))
    uid = next(iter(studies))
    assert uid == index["study_instance_uid"] and pydicom.uid.UID(uid).is_valid


def test_dicom_rescale_for_wide_hu_range():
    vol = np.array([[[-1024.0, 0.0], [50000.0, -60000.0]]], np.float32)
    stored, slope, intercept = hu_to_stored(vol)
    assert stored.dtype == np.int16 and slope > 1
    assert np.max(np.abs(stored * slope + intercept - vol)) <= slope / 2 + 1e-6
    s1, slope1, inter1 = hu_to_stored(np.array([-1000.4, 3000.6], np.float32))
    assert slope1 == 1.0 and inter1 == 0.0 and list(s1) == [-1000, 3001]
    with pytest.raises(StoreError):
        hu_to_stored(np.array([np.nan], np.float32))


def test_nifti_affine_is_ras_and_values_match(run_dir, tmp_path):
    index = export(run_dir, "nifti", method="groundtruth", out=tmp_path / "nii")
    ax, vol = _truth(run_dir, "groundtruth")
    assert len(index["targets"]) == vol.shape[0] * vol.shape[1]
    for t in index["targets"]:
        img = nib.load(tmp_path / "nii" / t["files"][0])
        data = np.asarray(img.dataobj)
        ci, ri = t["cardiac_index"], t["resp_index"]
        np.testing.assert_array_equal(data, np.transpose(vol[ci, ri], (2, 1, 0)))
        assert nib.aff2axcodes(img.affine) == ("L", "P", "S")
        assert int(img.header["qform_code"]) == 1 and int(img.header["sform_code"]) == 1
        np.testing.assert_allclose(img.header.get_zooms(), [ax["x_mm"][1] - ax["x_mm"][0],
                                                            ax["y_mm"][1] - ax["y_mm"][0],
                                                            ax["z_mm"][1] - ax["z_mm"][0]])
        i, j, k = 2, ax["y_mm"].size - 3, 1
        ras = img.affine @ [i, j, k, 1]
        lps = [-ras[0], -ras[1], ras[2]]
        np.testing.assert_allclose(lps, [ax["x_mm"][i], ax["y_mm"][j], ax["z_mm"][k]], atol=1e-6)
        np.testing.assert_allclose(img.get_qform(), img.affine)


def test_default_source_and_missing_method(run_dir):
    with open_volumes(run_dir) as f:
        src = resolve_source(f)
        assert (src.method, src.pitch_key, src.variant) == ("local_linear", "p0.020", "noisy")
        with pytest.raises(ClreconError, match="bin.*it has groundtruth.*local_linear"):
            resolve_source(f, method="bin")
        with pytest.raises(ClreconError, match="p0.500"):
            resolve_source(f, pitch=0.5)


def test_export_without_cardiac_axis(tmp_path):
    scene = fake_scene().replace(phantom={"cardiac_motion": False})
    make_fake_run(tmp_path / "run", methods=("local_linear",), pitches=(0.1,), variants=("noise-free",), scene=scene)
    with h5py.File(tmp_path / "run" / "volumes.h5") as f:
        assert list(f["groundtruth"].attrs["dims"]) == ["resp", "z", "y", "x"]
    index = export(tmp_path / "run", "nifti", out=tmp_path / "nii")
    assert len(index["targets"]) == 3 and all(t["cardiac_phase"] == 0.0 for t in index["targets"])


def test_cli_export_and_one_line_errors(run_dir, tmp_path, capsys):
    assert main(["export", str(run_dir), "--format", "nifti", "--pitch", "p0.020", "--out", str(tmp_path / "o")]) == 0
    assert "9 targets of local_linear p0.020 noisy" in capsys.readouterr().out
    assert main(["export", str(tmp_path / "nope"), "--format", "dicom"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "no such run directory" in err
    assert main(["export", str(run_dir), "--format", "dicom", "--method", "bin"]) == 2
    assert "it has groundtruth" in capsys.readouterr().err
    old = tmp_path / "old"
    old.mkdir()
    with h5py.File(old / "volumes.h5", "w") as f:
        f.attrs["format_version"] = 0
    assert main(["export", str(old), "--format", "dicom"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "re-run" in err


# ---------------------------------------------------------------------------------------
# standards: dciodvfy (dicom3tools) and two independent readers; the patient position
def _dciodvfy_errors(path) -> list[str]:
    import subprocess

    out = subprocess.run(["dciodvfy", str(path)], capture_output=True, text=True, timeout=60)
    return [line for line in (out.stdout + out.stderr).splitlines() if line.startswith("Error")]


def test_dicom_series_passes_dciodvfy(run_dir, tmp_path):
    """Zero dciodvfy errors on every file of one target's series (5 per file before issue 37)."""
    import shutil

    if shutil.which("dciodvfy") is None:
        pytest.skip("dciodvfy not installed (Debian package dicom3tools: apt-get install -y dicom3tools)")
    index = export(run_dir, "dicom", method="barycentric", pitch="0.1", variant="noisy", out=tmp_path / "dcm")
    for name in index["targets"][0]["files"]:
        assert _dciodvfy_errors(tmp_path / "dcm" / name) == [], name


def _with_position(run_dir, tmp_path, position):
    import json
    import shutil

    d = tmp_path / f"run-{position}"
    shutil.copytree(run_dir, d)
    res = json.loads((d / "results.json").read_text())
    res["scene"]["scan"]["patient_position"] = position
    (d / "results.json").write_text(json.dumps(res))
    return d


@pytest.mark.parametrize("position", ["HFS", "HFP", "FFS", "FFP"])
def test_dicom_geometry_in_two_readers_for_every_patient_position(run_dir, tmp_path, position):
    """The volumes are in the scanner frame; the series' ImageOrientationPatient / ImagePositionPatient map
    them onto the patient's LPS for its position. nibabel's DICOM wrapper (always) and SimpleITK (where
    installed) must put voxel (x_i, y_j, z_k) of the scanner frame at LPS (sx x_i, sy y_j, sz z_k)."""
    import warnings

    with warnings.catch_warnings():  # nibabel: "The DICOM readers are highly experimental" (on import)
        warnings.simplefilter("ignore", UserWarning)
        from nibabel.nicom import dicomwrappers
    from clrecon.scan.patient_frame import to_lps

    d = _with_position(run_dir, tmp_path, position)
    index = export(d, "dicom", method="barycentric", pitch="0.1", variant="noisy", out=tmp_path / "dcm")
    ax, vol = _truth(d, "recon/p0.100/noisy/barycentric")
    t = index["targets"][0]
    i, j, k = 3, ax["y_mm"].size - 2, 1
    want = to_lps(position, [ax["x_mm"][i], ax["y_mm"][j], ax["z_mm"][k]])
    w = dicomwrappers.wrapper_from_file(str(tmp_path / "dcm" / t["files"][k]))
    got = w.affine @ [j, i, 0, 1]  # nibabel's wrapper indexes (row, column): row = y, column = x
    np.testing.assert_allclose(got[:3], want, atol=1e-4)
    assert pydicom.dcmread(tmp_path / "dcm" / t["files"][k]).PatientPosition == position
    sitk = pytest.importorskip("SimpleITK", reason="SimpleITK not installed (pip install SimpleITK): the second "
                                                   "independent reader of the series")
    folder = str((tmp_path / "dcm" / t["files"][0]).parent)
    reader = sitk.ImageSeriesReader()
    reader.SetFileNames(reader.GetGDCMSeriesFileNames(folder))
    img = reader.Execute()
    assert img.GetSize() == (ax["x_mm"].size, ax["y_mm"].size, ax["z_mm"].size)
    arr = sitk.GetArrayFromImage(img)  # [slice, row, column] in the reader's slice order
    # SimpleITK sorts the slices along the slice normal: find slice k by its position
    kk = int(np.argmin([abs(img.TransformIndexToPhysicalPoint((0, 0, s))[2] - want[2]) for s in range(arr.shape[0])]))
    np.testing.assert_allclose(img.TransformIndexToPhysicalPoint((i, j, kk)), want, atol=1e-4)
    np.testing.assert_allclose(arr[kk, j, i], vol[t["cardiac_index"], t["resp_index"], k, j, i], atol=0.51)


def test_nifti_affine_follows_the_patient_position(run_dir, tmp_path):
    from clrecon.scan.patient_frame import to_lps

    d = _with_position(run_dir, tmp_path, "FFS")
    index = export(d, "nifti", method="groundtruth", out=tmp_path / "nii")
    ax, _ = _truth(d, "groundtruth")
    img = nib.load(tmp_path / "nii" / index["targets"][0]["files"][0])
    i, j, k = 2, 5, 1
    ras = img.affine @ [i, j, k, 1]
    np.testing.assert_allclose([-ras[0], -ras[1], ras[2]], to_lps("FFS", [ax["x_mm"][i], ax["y_mm"][j], ax["z_mm"][k]]),
                               atol=1e-6)
