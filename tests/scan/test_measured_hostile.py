"""Hostile DICOM-CT-PD series, made from the engine's own export: each refused in one line, no traceback.

Every broken variant goes through the command line (``python -m clrecon run``, in-process through
:func:`clrecon.cli.main`), which turns a :class:`~clrecon.core.errors.ClreconError` into one line on
stderr and exit code 2 and lets anything else escape as a traceback: a variant that raises anything
but a one-line refusal fails here. Each refusal names the file, the tag, the value and what is allowed
(issue 37, part "measured inputs").
"""

from __future__ import annotations

import shutil
from pathlib import Path

import pydicom
import pytest

from clrecon.cli import main
from clrecon.config.scene import load_scene
from clrecon.outputs.export import export
from clrecon.pipeline.run import run


def _quiet(*a, **k):
    pass


@pytest.fixture(scope="module")
def series(tmp_path_factory):
    """``tiny`` simulated and exported as DICOM-CT-PD: the intact series every variant breaks."""
    root = tmp_path_factory.mktemp("hostile")
    run(load_scene("tiny"), root / "sim", methods=["nearest"], cache_dir=root / "cache", progress=False, report=False,
        log=_quiet)
    export(root / "sim", "dicom-ct-pd", out=root / "exp")
    return root / "exp"


def _fl(tag, value):
    return pydicom.DataElement(tag, "FL", value)


def _set(tag, value, vr="FL"):
    def edit(ds):
        ds[tag] = pydicom.DataElement(tag, vr, value)
    return edit


def _edit(path: Path, fn) -> None:
    ds = pydicom.dcmread(path)
    fn(ds)
    ds.save_as(path)


def _cut_in_header(path: Path) -> None:
    """Cut the file inside its private groups (before the pixel data)."""
    raw = path.read_bytes()
    at = raw.find(b"\x31\x70")  # the first element of group 7031
    path.write_bytes(raw[: at + 6])


def _one(fs, i, fn):
    _edit(fs[i], fn)


def _all(fs, fn):
    for f in fs:
        _edit(f, fn)


def _other_series(fs):
    ds = pydicom.dcmread(fs[17])
    ds.SeriesInstanceUID = "1.2.826.0.1.3680043.8.498.99"
    ds.save_as(fs[17])


NAN, INF = float("nan"), float("inf")
#: variant -> (damage(files), the one line it must give: file, tag, value, what is allowed)
HOSTILE = {
    "nan angle": (lambda fs: _one(fs, 5, _set((0x7031, 0x1001), NAN)),
                  r"PROJ000006\.dcm: \(7031,1001\) DetectorFocalCenterAngularPosition = nan; expected a finite angle"),
    "inf angle": (lambda fs: _one(fs, 6, _set((0x7031, 0x1001), INF)),
                  r"PROJ000007\.dcm: \(7031,1001\) DetectorFocalCenterAngularPosition = inf; expected a finite angle"),
    "nan radial distance": (lambda fs: _one(fs, 9, _set((0x7031, 0x1003), NAN)),
                            r"PROJ000010\.dcm: \(7031,1003\) DetectorFocalCenterRadialDistance = nan; expected a "
                            r"source radius of 50\.\.5000 mm"),
    "zero radial distance": (lambda fs: _one(fs, 9, _set((0x7031, 0x1003), 0.0)),
                             r"PROJ000010\.dcm: \(7031,1003\) DetectorFocalCenterRadialDistance = 0\.0; expected"),
    "nan axial position everywhere": (lambda fs: _all(fs, _set((0x7031, 0x1002), NAN)),
                                      r"PROJ000001\.dcm: \(7031,1002\) DetectorFocalCenterAxialPosition = nan; "
                                      r"expected a finite table position"),
    "inf axial position in one file": (lambda fs: _one(fs, 40, _set((0x7031, 0x1002), -INF)),
                                       r"PROJ000041\.dcm: \(7031,1002\) DetectorFocalCenterAxialPosition = -inf"),
    "inf timestamp": (lambda fs: _one(fs, 12, _set((0x7033, 0x1067), INF)),
                      r"PROJ000013\.dcm: \(7033,1067\) Timestamp = inf; expected a finite time"),
    "nan timestamp": (lambda fs: _one(fs, 12, _set((0x7033, 0x1067), NAN)),
                      r"PROJ000013\.dcm: \(7033,1067\) Timestamp = nan; expected a finite time"),
    "nan source shift": (lambda fs: _one(fs, 3, _set((0x7033, 0x100B), NAN)),
                         r"PROJ000004\.dcm: \(7033,100B\) SourceAngularPositionShift = nan; expected"),
    "nan central element": (lambda fs: _one(fs, 0, _set((0x7031, 0x1033), [NAN, 4.5])),
                            r"PROJ000001\.dcm: \(7031,1033\) DetectorCentralElement = nan; expected finite"),
    "nan cell width": (lambda fs: _all(fs, _set((0x7029, 0x1002), NAN)),
                       r"PROJ000001\.dcm: \(7029,1002\) DetectorElementTransverseSpacing = nan; expected a cell "
                       r"width of 0\.001\.\.50 mm"),
    "zero views per rotation": (lambda fs: _all(fs, _set((0x7033, 0x1013), 0, "US")),
                                r"PROJ000001\.dcm: \(7033,1013\) NumberofSourceAngularSteps = 0\.0; expected "
                                r"2\.\.65535"),
    "zero rescale slope": (lambda fs: _one(fs, 8, lambda ds: setattr(ds, "RescaleSlope", "0")),
                           r"PROJ000009\.dcm: \(0028,1053\) RescaleSlope = 0\.0; expected a finite, non-zero slope"),
    "water per cm": (lambda fs: _all(fs, _set((0x7041, 0x1001), "0.193", "DS")),
                     r"PROJ000001\.dcm: \(7041,1001\) WaterAttenuationCoefficient = 0\.193; expected mu_water in "
                     r"1/mm"),
    "file of another series": (_other_series,
                               r"PROJ000018\.dcm: \(0020,000E\) SeriesInstanceUID = '1\.2\.826\.0\.1\.3680043\.8\.498"
                               r"\.99' but PROJ000001\.dcm has '[0-9.]+'; expected every file of one series"),
    "file of another study": (lambda fs: _one(fs, 21, lambda ds: setattr(ds, "StudyInstanceUID", "1.2.3.4")),
                              r"PROJ000022\.dcm: \(0020,000D\) StudyInstanceUID = '1\.2\.3\.4' but"),
    "other frame of reference": (lambda fs: _one(fs, 22, lambda ds: setattr(ds, "FrameOfReferenceUID", "1.2.3.5")),
                                 r"PROJ000023\.dcm: \(0020,0052\) FrameOfReferenceUID = '1\.2\.3\.5' but"),
    "file of another patient": (lambda fs: _one(fs, 30, lambda ds: setattr(ds, "PatientID", "SOMEONE-ELSE")),
                                r"PROJ000031\.dcm: \(0010,0020\) PatientID differs from PROJ000001\.dcm's \(values "
                                r"not shown: patient data\); expected one patient"),
    "other patient position": (lambda fs: _one(fs, 31, lambda ds: setattr(ds, "PatientPosition", "FFS")),
                               r"PROJ000032\.dcm: \(0018,5100\) PatientPosition = 'FFS' but PROJ000001\.dcm has 'HFS'"),
    "no patient position": (lambda fs: _all(fs, lambda ds: ds.__delattr__("PatientPosition")),
                            r"PROJ000001\.dcm: \(0018,5100\) PatientPosition is not in the series; give "
                            r"scan\.patient_position"),
    "decubitus": (lambda fs: _all(fs, lambda ds: setattr(ds, "PatientPosition", "HFDL")),
                  r"PROJ000001\.dcm: \(0018,5100\) PatientPosition = 'HFDL'; expected one of HFS, HFP, FFS, FFP"),
    "truncated in its header": (lambda fs: _cut_in_header(fs[50]),
                                r"PROJ000051\.dcm: truncated: the file ends after \d+ bytes, inside its header"),
    "truncated after the preamble": (lambda fs: fs[51].write_bytes(fs[51].read_bytes()[:140]),
                                     r"PROJ000052\.dcm: truncated: the file ends after 140 bytes, inside its header"),
    "stray file": (lambda fs: (fs[0].parent / "notes").write_text("scanned on a Tuesday\n"),
                   r"notes: not a DICOM file \(.*\); expected one DICOM-CT-PD projection per file"),
}


@pytest.mark.parametrize("case", sorted(HOSTILE))
def test_hostile_series_is_refused_in_one_line(series, tmp_path, case, capsys):
    exp = tmp_path / "exp"
    shutil.copytree(series, exp)
    files = sorted((exp / "projections").glob("*.dcm"))
    damage, pattern = HOSTILE[case]
    damage(files)
    code = main(["run", "--scene", str(exp / "measured.toml"), "--out", str(tmp_path / "run"),
                 "--cache", str(tmp_path / "cache"), "--no-progress"])
    err = capsys.readouterr().err.strip()
    assert code == 2, err
    assert err.count("\n") == 0 and "Traceback" not in err, err
    import re

    assert re.search(pattern, err), err
    assert not (tmp_path / "run" / "results.json").exists()


def _dicomdir(path: Path) -> None:
    """An empty DICOMDIR (Media Storage Directory Storage), as removable media carry beside their files."""
    from pydicom.dataset import Dataset, FileMetaDataset
    from pydicom.uid import ExplicitVRLittleEndian, generate_uid

    meta = FileMetaDataset()
    meta.MediaStorageSOPClassUID = "1.2.840.10008.1.3.10"
    meta.MediaStorageSOPInstanceUID = generate_uid()
    meta.TransferSyntaxUID = ExplicitVRLittleEndian
    ds = Dataset()
    ds.file_meta = meta
    ds.FileSetID = "CLRECON"
    ds.OffsetOfTheFirstDirectoryRecordOfTheRootDirectoryEntity = 0
    ds.OffsetOfTheLastDirectoryRecordOfTheRootDirectoryEntity = 0
    ds.FileSetConsistencyFlag = 0
    ds.DirectoryRecordSequence = []
    pydicom.dcmwrite(path, ds, enforce_file_format=True)


def test_a_dicomdir_beside_the_files_is_skipped_by_name(series, tmp_path, capsys):
    """A DICOMDIR in the projections folder (normal on media) is a whole DICOMDIR, not a truncated
    projection (it was called "truncated: the file ends after 384 bytes"): the run skips it with one note."""
    exp = tmp_path / "exp"
    shutil.copytree(series, exp)
    _dicomdir(exp / "projections" / "DICOMDIR")
    code = main(["run", "--scene", str(exp / "measured.toml"), "--methods", "nearest", "--out", str(tmp_path / "run"),
                 "--cache", str(tmp_path / "cache"), "--no-progress"])
    out, err = capsys.readouterr()
    assert code == 0, err
    notes = [ln for ln in (out + err).splitlines() if "DICOMDIR" in ln]
    assert len(notes) == 1 and "skipped" in notes[0] and "truncated" not in notes[0], notes
    assert (tmp_path / "run" / "results.json").exists()


def test_a_dicomdir_under_another_name_is_known_by_its_file_meta(series, tmp_path):
    """A DICOMDIR renamed (here 'index.dcm') is known by its Media Storage SOP Class (1.2.840.10008.1.3.10)
    and skipped by name; the series reads as without it."""
    from clrecon.scan import dicom_ct_pd

    exp = tmp_path / "exp"
    shutil.copytree(series, exp)
    _dicomdir(exp / "projections" / "index.dcm")
    ix = dicom_ct_pd.series_index(exp / "projections")
    ref = dicom_ct_pd.series_index(series / "projections")
    assert len(ix) == len(ref) and [Path(f).name for f in ix.files] == [Path(f).name for f in ref.files]
    assert [name for name, _ in ix.skipped] == ["index.dcm"] and "DICOMDIR" in ix.skipped[0][1]
