"""DICOM writer: one CT Image Storage series per target, one file per slice.

The volumes are in the scanner frame: rows run along +x and columns along +y of it. For a
patient head first supine (HFS, every simulated scan) that is the patient's LPS frame, so
ImageOrientationPatient = [1, 0, 0, 0, 1, 0] and ImagePositionPatient is the centre of the
first voxel of the slice (x0, y0, z_k) in mm; for another patient position (a measured series'
PatientPosition) the LPS axes are the scanner's with signs (sx, sy, sz)
(:mod:`clrecon.scan.patient_frame`): ImageOrientationPatient = [sx, 0, 0, 0, sy, 0] and
ImagePositionPatient = (sx x0, sy y0, sz z_k), so a planning system shows the patient's left as left;
PixelSpacing = [dy, dx] (row spacing, column spacing). Stored values are int16 with
RescaleSlope/RescaleIntercept giving HU (slope 1 HU unless the HU range does not fit in
int16). All series of one export share one StudyInstanceUID and one FrameOfReferenceUID,
derived from the run (scene, run directory), so exporting another method of the same run adds
series to the same study. (c, a) is carried in the SeriesDescription (``"5DCT local_linear
C40% R05%"``), in the standard TemporalPositionIdentifier / NumberOfTemporalPositions (target
number, cardiac-major), in NominalPercentageOfCardiacPhase /
NominalPercentageOfRespiratoryPhase, and in a private block (creator ``"CLRECON 5DCT"``, group
0x0011: 0x10 cardiac phase, 0x11 respiratory amplitude, both fractions in [0, 1], 0x12 cardiac
index, 0x13 respiratory index). Files: ``<out>/<C40_R05>/IM0001.dcm ...``.
"""

from __future__ import annotations

import datetime
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from clrecon.core import atomic
from clrecon.core.errors import StoreError
from clrecon.outputs.writers import WRITERS
from clrecon.outputs.writers.base import Writer, _file_tag, _spacing, target_tag
from clrecon.scan.patient_frame import image_orientation, lps_signs

if TYPE_CHECKING:
    from clrecon.outputs.rundir import Source

PRIVATE_CREATOR = "CLRECON 5DCT"
PRIVATE_GROUP = 0x0011
CT_IMAGE_STORAGE = "1.2.840.10008.5.1.4.1.1.2"


@WRITERS.register("dicom")
class DicomWriter(Writer):
    name = "dicom"
    label = "DICOM"
    frame = "LPS (DICOM patient frame)"
    requires = "pydicom"

    #: patient attributes to write in place of the phantom's (export() sets them for a measured run)
    patient: dict | None = None
    #: patient position of the run's volumes (export() sets it; docs/measured-conventions.md "Patient position")
    position: str = "HFS"

    def begin(self, ident: str, src: Source, n_targets: int) -> _DicomContext:
        ctx = _DicomContext.create(ident, src, n_targets)
        ctx.patient = dict(self.patient or {})
        ctx.position = self.position or "HFS"
        return ctx

    def write_target(self, out, vol, axes, src, ci, ri, ctx):
        return _write_dicom_target(out, vol, axes, src, ci, ri, ctx)

    def finish(self, ctx: _DicomContext) -> dict:
        return {"study_instance_uid": ctx.study_uid, "frame_of_reference_uid": ctx.frame_uid}


def _pydicom():
    return DicomWriter().require()


@dataclass
class _DicomContext:
    ident: str
    study_uid: str
    frame_uid: str
    n_targets: int
    when: datetime.datetime
    patient: dict | None = None
    position: str = "HFS"

    @classmethod
    def create(cls, ident: str, src: Source, n_targets: int) -> _DicomContext:
        _pydicom()
        from pydicom.uid import generate_uid

        return cls(ident=f"{ident}|{src.dataset}", study_uid=generate_uid(entropy_srcs=[ident, "study"]),
                   frame_uid=generate_uid(entropy_srcs=[ident, "frame"]), n_targets=n_targets,
                   when=datetime.datetime.now())


def hu_to_stored(vol_hu: np.ndarray) -> tuple[np.ndarray, float, float]:
    """HU -> (int16 stored values, RescaleSlope, RescaleIntercept) with HU = stored*slope + intercept.

    Slope 1 (HU rounding error <= 0.5 HU) whenever the HU range fits int16; otherwise the
    smallest slope that fits the range (error <= slope/2).
    """
    finite = np.isfinite(vol_hu)
    if not finite.all():
        raise StoreError("volume has NaN or infinite values; refusing to export it")
    lo, hi = (float(vol_hu.min()), float(vol_hu.max())) if vol_hu.size else (0.0, 0.0)
    intercept = 0.0
    slope = 1.0
    if lo < -32768 or hi > 32767:
        intercept = float(np.floor((lo + hi) / 2.0))
        slope = float(max(hi - intercept, intercept - lo) / 32767.0)
        slope = float(np.ceil(slope * 1e4) / 1e4)  # short decimal string in DS
    stored = np.clip(np.rint((vol_hu - intercept) / slope), -32768, 32767).astype(np.int16)
    return stored, slope, intercept


def _write_dicom_target(out: Path, vol: np.ndarray, axes: dict, src: Source, ci: int, ri: int,
                        ctx: _DicomContext) -> list[Path]:
    pydicom = _pydicom()
    from pydicom.dataset import Dataset, FileMetaDataset
    from pydicom.uid import ExplicitVRLittleEndian, generate_uid

    c = float(axes["cardiac_phase"][ci])
    a = float(axes["resp_amplitude"][ri])
    x, y, z = axes["x_mm"], axes["y_mm"], axes["z_mm"]
    dx, dy = _spacing(x, "x_mm"), _spacing(y, "y_mm")
    dz = _spacing(z, "z_mm") if z.size > 1 else dx
    stored, slope, intercept = hu_to_stored(vol)
    sx, sy, sz = lps_signs(ctx.position)
    n_r = len(axes["resp_amplitude"])
    temporal = ci * n_r + ri + 1
    series_uid = generate_uid(entropy_srcs=[ctx.ident, "series", str(ci), str(ri)])
    folder = out / _file_tag(c, a)
    folder.mkdir(parents=True, exist_ok=True)
    date = ctx.when.strftime("%Y%m%d")
    time_ = ctx.when.strftime("%H%M%S")
    desc = f"5DCT {src.method} {target_tag(c, a)}"
    if src.pitch_key is not None:
        desc += f" pitch {src.pitch_key[1:]} {src.variant}"
    files = []
    for k in range(vol.shape[0]):
        sop_uid = generate_uid(entropy_srcs=[ctx.ident, "sop", str(ci), str(ri), str(k)])
        meta = FileMetaDataset()
        meta.MediaStorageSOPClassUID = CT_IMAGE_STORAGE
        meta.MediaStorageSOPInstanceUID = sop_uid
        meta.TransferSyntaxUID = ExplicitVRLittleEndian
        ds = Dataset()
        ds.file_meta = meta
        ds.SOPClassUID = CT_IMAGE_STORAGE
        ds.SOPInstanceUID = sop_uid
        ds.SpecificCharacterSet = "ISO_IR 100"
        ds.ImageType = ["DERIVED", "SECONDARY", "AXIAL"]
        ds.Modality = "CT"
        ds.Manufacturer = "clrecon"
        ds.PatientName = "clrecon^phantom"
        ds.PatientID = "CLRECON-PHANTOM"
        ds.PatientBirthDate = ""
        ds.PatientSex = ""
        ds.PatientPosition = ctx.position
        ds.StudyInstanceUID = ctx.study_uid
        ds.SeriesInstanceUID = series_uid
        ds.FrameOfReferenceUID = ctx.frame_uid
        ds.PositionReferenceIndicator = ""
        ds.StudyID = "5DCT"
        ds.StudyDescription = "clrecon 5DCT"
        ds.StudyDate = ds.SeriesDate = ds.ContentDate = date
        ds.StudyTime = ds.SeriesTime = ds.ContentTime = time_
        ds.AccessionNumber = ""
        ds.ReferringPhysicianName = ""
        for key, val in (ctx.patient or {}).items():  # after the defaults: --keep-identifiers copies them all
            setattr(ds, key, val)
        ds.SeriesNumber = temporal
        ds.AcquisitionNumber = 1
        ds.InstanceNumber = k + 1
        ds.KVP = ""
        ds.Laterality = ""  # Type 2C: not a paired organ (an empty value states it)
        ds.SeriesDescription = desc[:64]
        ds.ImageComments = f"cardiac_phase={c:.4f} resp_amplitude={a:.4f} source={src.dataset}"
        ds.TemporalPositionIdentifier = temporal
        ds.NumberOfTemporalPositions = ctx.n_targets
        ds.NominalPercentageOfCardiacPhase = c * 100.0
        ds.NominalPercentageOfRespiratoryPhase = a * 100.0
        ds.ImagePositionPatient = [_ds(sx * x[0]), _ds(sy * y[0]), _ds(sz * z[k])]
        ds.ImageOrientationPatient = image_orientation(ctx.position)
        ds.SliceLocation = _ds(sz * z[k])
        ds.SliceThickness = _ds(dz)
        ds.SpacingBetweenSlices = _ds(dz)
        ds.PixelSpacing = [_ds(dy), _ds(dx)]
        ds.Rows, ds.Columns = int(vol.shape[1]), int(vol.shape[2])
        ds.SamplesPerPixel = 1
        ds.PhotometricInterpretation = "MONOCHROME2"
        ds.BitsAllocated = 16
        ds.BitsStored = 16
        ds.HighBit = 15
        ds.PixelRepresentation = 1
        ds.RescaleSlope = _ds(slope)
        ds.RescaleIntercept = _ds(intercept)
        ds.RescaleType = "HU"
        ds.WindowCenter = 40
        ds.WindowWidth = 400
        block = ds.private_block(PRIVATE_GROUP, PRIVATE_CREATOR, create=True)
        block.add_new(0x10, "FD", c)
        block.add_new(0x11, "FD", a)
        block.add_new(0x12, "US", ci)
        block.add_new(0x13, "US", ri)
        ds.PixelData = np.ascontiguousarray(stored[k]).astype("<i2").tobytes()
        path = folder / f"IM{k + 1:04d}.dcm"
        _dcmwrite(pydicom, path, ds)
        files.append(path)
    return files


def _ds(value: float):
    """A float as a valid DICOM decimal string (at most 16 characters)."""
    from pydicom.valuerep import DSfloat

    return DSfloat(float(value), auto_format=True)


def _dcmwrite(pydicom, path: Path, ds) -> None:
    """``ds`` as the file ``path``, whole or not at all (:mod:`clrecon.core.atomic`)."""
    with atomic.replacing(path) as tmp:
        try:  # pydicom >= 3
            pydicom.dcmwrite(tmp, ds, enforce_file_format=True)
        except TypeError:  # pydicom 2.x
            ds.is_little_endian = True
            ds.is_implicit_VR = False
            ds.save_as(tmp, write_like_original=False)
