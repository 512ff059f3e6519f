"""DICOM-CT-PD projection series: the header index and its mapping onto scanner and scan keys.

A measured scan is a folder of DICOM-CT-PD files, one projection per file (the TCIA "LDCT and
Projection Data" format; Chen et al., Med Phys 42:4917, 2015; Moen et al., Med Phys 48:902,
2021). This module reads every file's header (never the pixels) with pydicom, refuses a
hostile or inconsistent series in one line (file, tag, value, what is allowed), and maps the
geometry onto the scene's ``[scanner]`` and ``[scan]`` keys, so that every later stage sees a
scene like a simulated one. The conventions (which tag gives what, the angle and table
directions, the pixel layout, the channel and row numbering, the patient position) are in
``docs/measured-conventions.md``; the pixels are read by :mod:`clrecon.scan.dicom_ct_pd_pixels`, the
data's own check of the numbering is :mod:`clrecon.scan.orientation_check`, the per-view table
:mod:`clrecon.scan.measured`, the import into the store :mod:`clrecon.simulation.measured`.

Mapping (lengths mm, angles rad; frame D = the DICOM-CT-PD Cartesian frame, docs/measured-conventions.md):

- ``sid_mm`` = DetectorFocalCenterRadialDistance rho0 (7031,1003); ``sdd_mm`` =
  ConstantRadialDistance d0 (7031,1031);
- ``n_cols``, ``n_rows`` = NumberofDetectorColumns (7029,1011), NumberofDetectorRows (7029,1010);
  which of them the DICOM Rows (0028,0010) run along is read from the tags (``pixel layout``);
- ``col_pitch_mm``, ``row_pitch_mm`` = DetectorElementTransverseSpacing (7029,1002) and
  DetectorElementAxialSpacing (7029,1006), at the detector;
- ``views_per_rotation`` = NumberofSourceAngularSteps (7033,1013); ``detector`` from
  DetectorShape (7029,100B) (FLAT -> flat, CYLINDRICAL -> cylindrical);
- gantry angle ``beta = phi0 + pi/2`` with phi0 = DetectorFocalCenterAngularPosition (7031,1001):
  DICOM-CT-PD puts the focal centre at (-rho0 sin phi0, rho0 cos phi0, z0), clrecon at
  (R cos beta, R sin beta, z); increasing or decreasing (``scan.rotation``);
- source z = DetectorFocalCenterAxialPosition z0 (7031,1002), increasing or decreasing
  (``scan.table_direction``);
- the channel index of the format increases towards decreasing phi0 and the row index towards
  decreasing z0 (row 1 at the +z end); clrecon's store numbers them the other way, so a series
  in the format's numbering is reversed on import and its DetectorCentralElement reflected
  (``scan.flip_channels`` / ``scan.flip_rows``: a series numbered the other way);
- view time = Timestamp (7033,1067) minus the first view's (``scan.timestamp_unit``), else
  ``k * rotation_time_s / views_per_rotation``; ``rotation_time_s`` = median time step x views
  per rotation when there are timestamps;
- ``phantom.mu_water_per_mm`` = WaterAttenuationCoefficient (7041,1001) where the series has it;
- ``scan.patient_position`` = PatientPosition (0018,5100).
"""

from __future__ import annotations

import functools
import hashlib
import math
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from clrecon.core.detector import ffs_states
from clrecon.core.errors import InputError
from clrecon.scan import orientation_check
from clrecon.scan.patient_frame import lps_signs

#: tag name -> ((group, element), VR): the private DICOM-CT-PD tags clrecon reads and writes.
TAGS = {
    "NumberofDetectorRows": ((0x7029, 0x1010), "US"),
    "NumberofDetectorColumns": ((0x7029, 0x1011), "US"),
    "DetectorElementTransverseSpacing": ((0x7029, 0x1002), "FL"),
    "DetectorElementAxialSpacing": ((0x7029, 0x1006), "FL"),
    "DetectorShape": ((0x7029, 0x100B), "CS"),
    "DetectorFocalCenterAngularPosition": ((0x7031, 0x1001), "FL"),
    "DetectorFocalCenterAxialPosition": ((0x7031, 0x1002), "FL"),
    "DetectorFocalCenterRadialDistance": ((0x7031, 0x1003), "FL"),
    "ConstantRadialDistance": ((0x7031, 0x1031), "FL"),
    "DetectorCentralElement": ((0x7031, 0x1033), "FL"),
    "SourceAngularPositionShift": ((0x7033, 0x100B), "FL"),
    "SourceAxialPositionShift": ((0x7033, 0x100C), "FL"),
    "SourceRadialDistanceShift": ((0x7033, 0x100D), "FL"),
    "FlyingFocalSpotMode": ((0x7033, 0x100E), "CS"),
    "NumberofSourceAngularSteps": ((0x7033, 0x1013), "US"),
    "PhotonStatistics": ((0x7033, 0x1065), "FL"),
    "Timestamp": ((0x7033, 0x1067), "FL"),
    "TypeofProjectionData": ((0x7037, 0x1009), "CS"),
    "TypeofProjectionGeometry": ((0x7037, 0x100A), "CS"),
    "WaterAttenuationCoefficient": ((0x7041, 0x1001), "DS"),
}
#: public attributes read from every file: name -> ((group, element), VR)
PUBLIC = {"InstanceNumber": ((0x0020, 0x0013), "IS"), "Rows": ((0x0028, 0x0010), "US"),
          "Columns": ((0x0028, 0x0011), "US"), "RescaleSlope": ((0x0028, 0x1053), "DS"),
          "RescaleIntercept": ((0x0028, 0x1052), "DS"), "PatientPosition": ((0x0018, 0x5100), "CS"),
          "StudyInstanceUID": ((0x0020, 0x000D), "UI"), "SeriesInstanceUID": ((0x0020, 0x000E), "UI"),
          "FrameOfReferenceUID": ((0x0020, 0x0052), "UI"), "PatientID": ((0x0010, 0x0020), "LO"),
          "PatientName": ((0x0010, 0x0010), "PN")}
#: tags every file must carry (Timestamp, PhotonStatistics, the water coefficient are optional)
REQUIRED = ("NumberofDetectorRows", "NumberofDetectorColumns", "DetectorElementTransverseSpacing",
            "DetectorElementAxialSpacing", "DetectorShape", "DetectorFocalCenterAngularPosition",
            "DetectorFocalCenterAxialPosition", "DetectorFocalCenterRadialDistance", "ConstantRadialDistance",
            "DetectorCentralElement", "NumberofSourceAngularSteps", "TypeofProjectionData")
#: tags that must be equal in every file of a series
CONSTANT = ("NumberofDetectorRows", "NumberofDetectorColumns", "DetectorElementTransverseSpacing",
            "DetectorElementAxialSpacing", "DetectorShape", "ConstantRadialDistance", "DetectorCentralElement",
            "FlyingFocalSpotMode", "NumberofSourceAngularSteps", "TypeofProjectionData", "TypeofProjectionGeometry",
            "WaterAttenuationCoefficient", "PatientPosition", "Rows", "Columns")
#: attributes that tie every file to one series (a file of another series in the folder is refused)
SAME_SERIES = ("StudyInstanceUID", "SeriesInstanceUID", "FrameOfReferenceUID")
#: patient attributes every file must share; compared by digest, never printed (patient data)
SAME_PATIENT = ("PatientID", "PatientName")
DETECTOR_SHAPES = {"FLAT": "flat", "CYLINDRICAL": "cylindrical"}
#: an angle step within this (rad) of 2 pi / views_per_rotation is regular
ANGLE_TOL_RAD = 1e-3
#: source shifts below these (rad, mm) count as none (no flying focal spot)
SHIFT_TOL = (1e-6, 1e-3)
#: The physical range of every numeric tag: name -> (low, high, what is allowed and why). A value
#: outside (or NaN, inf) is refused in one line naming the file, the tag and the value.
RANGES = {
    "NumberofDetectorRows": (1, 4096, "1..4096 detector rows"),
    "NumberofDetectorColumns": (2, 16384, "2..16384 detector channels"),
    "DetectorElementTransverseSpacing": (1e-3, 50.0, "a cell width of 0.001..50 mm at the detector"),
    "DetectorElementAxialSpacing": (1e-3, 50.0, "a cell height of 0.001..50 mm at the detector"),
    "DetectorFocalCenterAngularPosition": (-1e4, 1e4, "a finite angle, |phi0| <= 1e4 rad"),
    "DetectorFocalCenterAxialPosition": (-1e5, 1e5, "a finite table position, |z0| <= 1e5 mm"),
    "DetectorFocalCenterRadialDistance": (50.0, 5000.0, "a source radius of 50..5000 mm (a CT gantry)"),
    "ConstantRadialDistance": (50.0, 1e4, "a source-detector distance of 50..10000 mm"),
    "DetectorCentralElement": (-1e5, 1e5, "finite 1-based (column, row) indices"),
    "SourceAngularPositionShift": (-0.1, 0.1, "a focal-spot shift |dphi| <= 0.1 rad"),
    "SourceAxialPositionShift": (-20.0, 20.0, "a focal-spot shift |dz| <= 20 mm"),
    "SourceRadialDistanceShift": (-20.0, 20.0, "a focal-spot shift |drho| <= 20 mm"),
    "NumberofSourceAngularSteps": (2, 65535, "2..65535 views per rotation"),
    "PhotonStatistics": (0.0, 1e15, "finite photon counts >= 0"),
    "Timestamp": (-1e15, 1e15, "a finite time"),
    "WaterAttenuationCoefficient": (0.005, 0.1, "mu_water in 1/mm, 0.005..0.1 (water at 20..150 keV is "
                                                "0.015..0.03 /mm; 0.19 would be per cm)"),
    "RescaleSlope": (-1e9, 1e9, "a finite, non-zero slope"),
    "RescaleIntercept": (-1e9, 1e9, "a finite intercept"),
    "InstanceNumber": (-2**31, 2**31 - 1, "an integer"),
}


def _tag_text(name: str) -> str:
    """``(7031,1001) DetectorFocalCenterAngularPosition`` (or the bare name of an untabled attribute)."""
    t = TAGS.get(name, PUBLIC.get(name))
    return f"({t[0][0]:04X},{t[0][1]:04X}) {name}" if t else name


def _decode(value, vr: str):
    """A tag value as pydicom gives it (typed, or raw bytes for an implicit-VR private tag)."""
    if isinstance(value, bytes):
        if vr == "FL":
            arr = np.frombuffer(value[: len(value) // 4 * 4], "<f4").astype(np.float64)
            return float(arr[0]) if arr.size == 1 else arr
        if vr == "US":
            if len(value) < 2:
                raise ValueError(f"{len(value)} byte(s) for a US value")
            return int(np.frombuffer(value[:2], "<u2")[0])
        text = value.decode("ascii", "replace").strip("\x00 ").strip()
        if vr in ("DS", "IS"):
            return float(text.split("\\")[0]) if text else None
        return text
    if vr == "FL":
        arr = np.atleast_1d(np.asarray(value, dtype=np.float64))
        return float(arr[0]) if arr.size == 1 else arr
    if vr == "US":
        return int(value)
    if vr in ("DS", "IS"):
        return float(value)
    return str(value).strip()


@dataclass(frozen=True)
class SeriesIndex:
    """Every file's header of one series, in view order (InstanceNumber).

    files (n,) paths; per view (n,) arrays: instance, phi_rad, z_mm, rho_mm, dphi_rad, dz_mm,
    drho_mm, timestamp (nan where absent), slope, intercept; ``const``: the CONSTANT tags'
    values (equal in every file); ``photons``: PhotonStatistics of the first file or None;
    ``skipped``: ``(file name, why)`` of the folder's files that are no projection and are
    skipped (a DICOMDIR: :func:`is_dicomdir_name`, :data:`DICOMDIR_SOP_CLASS`).
    """

    folder: str
    files: tuple
    instance: np.ndarray
    phi_rad: np.ndarray
    z_mm: np.ndarray
    rho_mm: np.ndarray
    dphi_rad: np.ndarray
    dz_mm: np.ndarray
    drho_mm: np.ndarray
    timestamp: np.ndarray
    slope: np.ndarray
    intercept: np.ndarray
    const: dict
    photons: object
    rescale_in_files: bool = True
    skipped: tuple = ()

    def __len__(self) -> int:
        return len(self.files)


#: Media Storage SOP Class of a DICOMDIR (Media Storage Directory Storage), in its file meta.
DICOMDIR_SOP_CLASS = "1.2.840.10008.1.3.10"
#: Why a DICOMDIR is skipped (the note a run prints, ``SeriesIndex.skipped``).
DICOMDIR_NOTE = ("a DICOMDIR (the media's directory of its files, Media Storage SOP Class "
                 f"{DICOMDIR_SOP_CLASS}), not a projection")


def is_dicomdir_name(p: Path) -> bool:
    """Whether ``p`` is named as a DICOMDIR is on media (``DICOMDIR``, any case)."""
    return Path(p).name.upper() == "DICOMDIR"


def series_files(folder) -> list[Path]:
    """The files of a series folder (every regular file not starting with '.', but a file named
    DICOMDIR), sorted by name."""
    d = Path(folder)
    if not d.is_dir():
        raise InputError(f"{d}: scan.projections is not a folder of DICOM-CT-PD files")
    files = sorted(p for p in d.iterdir() if p.is_file() and not p.name.startswith(".")
                   and p.suffix.lower() in (".dcm", ".ima", "") and not is_dicomdir_name(p))
    if not files:
        raise InputError(f"{d}: no projection files (*.dcm) in the folder")
    return files


def series_signature(folder) -> str:
    """Digest of the folder listing (names, sizes, modification times): changes when a file does."""
    h = hashlib.blake2b(digest_size=8)
    for p in series_files(folder):
        st = os.stat(p)
        h.update(f"{p.name}|{st.st_size}|{st.st_mtime_ns};".encode())
    return h.hexdigest()


def _dicom_magic(p: Path) -> bool:
    try:
        with open(p, "rb") as f:
            f.seek(128)
            return f.read(4) == b"DICM"
    except OSError:
        return False


def _truncated_in_header(p: Path, pydicom) -> bool:
    """True when the file holds no PixelData element: it ends inside its header (pydicom stops quietly there)."""
    try:
        ds = pydicom.dcmread(p, defer_size=256)
    except Exception:  # noqa: BLE001 - pydicom raises EOFError, struct.error, ... on a torn file
        return True
    return (0x7FE0, 0x0010) not in ds


def _check_value(p: Path, name: str, v) -> None:
    """One-line InputError when a numeric tag value is not finite or outside its physical range."""
    if v is None or name not in RANGES or isinstance(v, str):
        return
    lo, hi, allowed = RANGES[name]
    arr = np.atleast_1d(np.asarray(v, dtype=np.float64))
    bad = ~np.isfinite(arr) | (arr < lo) | (arr > hi)
    if name == "RescaleSlope":
        bad |= arr == 0
    if bad.any():
        shown = float(arr[bad][0]) if arr.size > 1 else float(arr[0])
        raise InputError(f"{p}: {_tag_text(name)} = {shown!r}; expected {allowed}")


def _read_header(p: Path, pydicom, photons: bool = False):
    """The tags of projection file ``p`` (one-line InputError on a bad one); None for a DICOMDIR
    (by its file meta's Media Storage SOP Class: one renamed)."""
    try:
        ds = pydicom.dcmread(p, stop_before_pixels=True)
    except Exception as e:  # noqa: BLE001 - pydicom raises InvalidDicomError, EOFError, struct.error, ...
        size = p.stat().st_size if p.exists() else 0
        if _dicom_magic(p):
            raise InputError(f"{p}: truncated: the file ends after {size} bytes, inside its header "
                             f"({type(e).__name__}); expected a whole DICOM-CT-PD file") from None
        raise InputError(f"{p}: not a DICOM file ({type(e).__name__}, {size} bytes); expected one DICOM-CT-PD "
                         f"projection per file") from None
    meta = getattr(ds, "file_meta", None)
    if meta is not None and str(meta.get("MediaStorageSOPClassUID", "")) == DICOMDIR_SOP_CLASS:
        return None
    out = {}
    try:
        # raw elements, decoded here: 3x faster than pydicom's per-element conversion, and the same
        # for explicit-VR files and for implicit-VR private tags (bytes), as in the TCIA collection
        for name, ((g, e), vr) in (*TAGS.items(), *PUBLIC.items()):
            if name == "PhotonStatistics" and not photons:  # one value per channel: kept of the first file only
                out[name] = None
                continue
            el = ds.get_item((g, e))
            out[name] = None if el is None or el.value in (None, b"", "") else _decode(el.value, vr)
    except (ValueError, TypeError, OverflowError) as e:
        raise InputError(f"{p}: a tag value cannot be decoded ({type(e).__name__}: {e}); corrupt header?") from None
    missing = [n for n in REQUIRED + ("InstanceNumber", "Rows", "Columns") if out[n] is None]
    if missing:
        if _truncated_in_header(p, pydicom):
            raise InputError(f"{p}: truncated: the file ends after {p.stat().st_size} bytes, inside its header "
                             f"(no {_tag_text(missing[0])} and no pixel data); expected a whole DICOM-CT-PD file")
        raise InputError(f"{p}: tag {_tag_text(missing[0])} is missing; a DICOM-CT-PD projection carries "
                         f"{', '.join(REQUIRED)}, InstanceNumber, Rows, Columns")
    for name, v in out.items():
        _check_value(p, name, v)
    if float(out["InstanceNumber"]) != int(out["InstanceNumber"]):
        raise InputError(f"{p}: {_tag_text('InstanceNumber')} = {out['InstanceNumber']!r}; expected an integer")
    return out


def _same(a, b) -> bool:
    if isinstance(a, (float, np.ndarray)) and isinstance(b, (float, np.ndarray)) and np.shape(a) == np.shape(b):
        return bool(np.allclose(a, b, rtol=1e-6, atol=1e-6))
    return a == b


def _digest(v) -> str:
    return hashlib.blake2b(str(v).encode(), digest_size=6).hexdigest()


@functools.lru_cache(maxsize=4)
def _index_cached(folder: str, signature: str) -> SeriesIndex:
    try:
        import pydicom
    except ImportError:  # pragma: no cover - an install without the extra
        raise InputError(f"{folder}: reading DICOM-CT-PD needs pydicom: pip install 'clrecon[measured]'") from None

    skipped = [(p.name, DICOMDIR_NOTE) for p in sorted(Path(folder).iterdir()) if p.is_file() and is_dicomdir_name(p)]
    files, heads = [], []
    for p in series_files(folder):
        h = _read_header(p, pydicom, photons=not heads)
        if h is None:  # a DICOMDIR under another name
            skipped.append((p.name, DICOMDIR_NOTE))
            continue
        files.append(p)
        heads.append(h)
    if not heads:
        raise InputError(f"{folder}: no projection files in the folder (only a DICOMDIR)")
    first = heads[0]
    for p, h in zip(files[1:], heads[1:], strict=True):
        for name in SAME_SERIES:  # a file of another series (or study, or frame of reference) in the folder
            if h[name] != first[name]:
                raise InputError(f"{p}: {_tag_text(name)} = {h[name]!r} but {files[0].name} has {first[name]!r}; "
                                 f"expected every file of one series (a file of another series in the folder?)")
        for name in SAME_PATIENT:  # values never printed: patient data
            if _digest(h[name]) != _digest(first[name]):
                raise InputError(f"{p}: {_tag_text(name)} differs from {files[0].name}'s (values not shown: patient "
                                 f"data); expected one patient in a series (a file of another patient's scan?)")
        for name in CONSTANT:
            a, b = first[name], h[name]
            if not _same(a, b):
                raise InputError(f"{p}: {_tag_text(name)} = {b!r} but {files[0].name} has {a!r}; expected one value "
                                 f"in every file of the series (mixed detector or protocol)")
    inst = np.array([int(h["InstanceNumber"]) for h in heads], np.int64)
    order = np.argsort(inst, kind="stable")
    inst_sorted = inst[order]
    dup = np.flatnonzero(np.diff(inst_sorted) == 0)
    if dup.size:
        a, b = files[order[dup[0]]], files[order[dup[0] + 1]]
        raise InputError(f"{b}: InstanceNumber {inst_sorted[dup[0]]} also in {a.name}; expected one file per view")
    gap = np.flatnonzero(np.diff(inst_sorted) != 1)
    if gap.size:
        k = gap[0]
        raise InputError(f"{files[order[k + 1]]}: InstanceNumber {inst_sorted[k + 1]} follows {inst_sorted[k]} "
                         f"({files[order[k]].name}); expected consecutive views (a gap: "
                         f"{inst_sorted[k + 1] - inst_sorted[k] - 1} missing)")
    heads = [heads[i] for i in order]
    files = [files[i] for i in order]

    def col(name, default=0.0):
        return np.array([default if h[name] is None else float(np.atleast_1d(h[name])[0]) for h in heads])

    ts = col("Timestamp", np.nan)
    present = np.array([h["Timestamp"] is not None for h in heads])
    if present.any() and not present.all():
        k = int(np.flatnonzero(~present)[0])
        raise InputError(f"{files[k]}: tag (7033,1067) Timestamp is missing but other files have it; expected it "
                         f"in every file or in none")
    return SeriesIndex(folder=str(folder), files=tuple(str(f) for f in files), instance=inst_sorted,
                       phi_rad=col("DetectorFocalCenterAngularPosition"), z_mm=col("DetectorFocalCenterAxialPosition"),
                       rho_mm=col("DetectorFocalCenterRadialDistance"), dphi_rad=col("SourceAngularPositionShift"),
                       dz_mm=col("SourceAxialPositionShift"), drho_mm=col("SourceRadialDistanceShift"), timestamp=ts,
                       slope=col("RescaleSlope", 1.0), intercept=col("RescaleIntercept", 0.0),
                       const={n: first[n] for n in CONSTANT}, photons=first["PhotonStatistics"],
                       rescale_in_files=all(h["RescaleSlope"] is not None and h["RescaleIntercept"] is not None
                                            for h in heads), skipped=tuple(skipped))


def series_index(folder) -> SeriesIndex:
    """The header index of a series folder (memoised by the folder's listing signature)."""
    folder = str(Path(folder))
    return _index_cached(folder, series_signature(folder))


#: DICOM-CT-PD FlyingFocalSpotMode -> the scanner.flying_focal_spot mode of the FFS model (issue 17)
FFS_MODES = {"FFSNONE": "none", "FFSXY": "phi", "FFSZ": "z", "FFSXYZ": "phi+z"}
#: (dphi, dz) signs of each focal-spot state, view k in state k % cycle: the engine's own order
#: (:func:`clrecon.core.detector.ffs_states`), so an exported series reads back unchanged.
FFS_SIGNS = {m: tuple(map(tuple, ffs_states(m, 1.0, 0.0, 1.0)[:, [0, 2]].astype(int).tolist()))
             for m in FFS_MODES.values()}


def _ffs_keys(ix: SeriesIndex, mode: str, nv: int) -> dict:
    """Scanner keys of the flying focal spot (none: {}), checked against every view's source shifts.

    View k is in state k % cycle with the signs of :data:`FFS_SIGNS` (dphi, dz); the radial shift
    goes with +dphi. Magnitudes from the first cycle; every view must match within SHIFT_TOL.
    """
    signs = np.asarray(FFS_SIGNS[mode], dtype=np.float64)
    cycle = len(signs)
    k = np.arange(len(ix)) % cycle
    if mode == "none":
        ang = rad = z = 0.0
    else:
        if nv % cycle:
            raise InputError(f"{ix.files[0]}: (7033,1013) NumberofSourceAngularSteps = {nv} with FlyingFocalSpotMode "
                             f"{mode}: expected a multiple of the focal-spot cycle {cycle}")
        ang = float(np.abs(ix.dphi_rad[:cycle]).max())
        z = float(np.abs(ix.dz_mm[:cycle]).max())
        plus = signs[k[:cycle], 0] > 0
        rad = float(ix.drho_mm[:cycle][plus].mean()) if plus.any() else 0.0
    want = np.stack([signs[k, 0] * ang, signs[k, 0] * rad, signs[k, 1] * z])
    got = np.stack([ix.dphi_rad, ix.drho_mm, ix.dz_mm])
    tol = np.array([SHIFT_TOL[0], SHIFT_TOL[1], SHIFT_TOL[1]])[:, None]
    bad = np.flatnonzero((np.abs(got - want) > tol).any(axis=0))
    if bad.size:
        j = int(bad[0])
        raise InputError(f"{ix.files[j]}: source shifts (7033,100B/D/C) = {got[0, j]:.4g} rad, {got[1, j]:.4g} mm, "
                         f"{got[2, j]:.4g} mm; expected {want[0, j]:.4g}, {want[1, j]:.4g}, {want[2, j]:.4g} for "
                         f"focal-spot state {k[j]} of mode {mode!r} (view k in state k % {cycle}, minus state first)")
    if mode == "none":
        return {}
    return {"flying_focal_spot": mode, "ffs_angle_rad": ang, "ffs_radial_mm": rad, "ffs_z_mm": z}


# ---------------------------------------------------------------------------------------
# the reading: pixel layout, channel and row numbering (docs/measured-conventions.md)
LAYOUTS = ("rows-are-channels", "rows-are-detector-rows")


@dataclass(frozen=True)
class Reading:
    """How the files' pixels map onto clrecon's store ``proj[row, column]``.

    ``layout``: DICOM Rows run along the detector channels (TCIA) or along the detector rows;
    ``reverse_channels`` / ``reverse_rows``: the store's index runs opposite to the file's (true
    for a series in the DICOM-CT-PD numbering, whose channel index increases towards decreasing
    phi0 and whose row index towards decreasing z0); ``central_col`` / ``central_row``: 0-based
    central element in the store's numbering (the file's DetectorCentralElement, reflected with
    its axis).
    """

    layout: str
    reverse_channels: bool
    reverse_rows: bool
    central_col: float
    central_row: float

    def describe(self) -> str:
        return (f"{self.layout}, channels {'reversed' if self.reverse_channels else 'as stored'}, rows "
                f"{'reversed' if self.reverse_rows else 'as stored'} on import")


def pixel_layout(ix: SeriesIndex, requested: str = "auto") -> str:
    """``rows-are-channels`` or ``rows-are-detector-rows``, from DICOM Rows/Columns against the detector's
    NumberofDetectorColumns/Rows (FreeCT's rule); a square detector needs ``scan.pixel_layout``."""
    c, f0 = ix.const, ix.files[0]
    n_rows, n_cols = int(c["NumberofDetectorRows"]), int(c["NumberofDetectorColumns"])
    rows, cols = int(c["Rows"]), int(c["Columns"])
    fits = []
    if (rows, cols) == (n_cols, n_rows):
        fits.append("rows-are-channels")
    if (rows, cols) == (n_rows, n_cols):
        fits.append("rows-are-detector-rows")
    if not fits:
        raise InputError(f"{f0}: DICOM Rows x Columns = {rows} x {cols} but (7029,1011) NumberofDetectorColumns x "
                         f"(7029,1010) NumberofDetectorRows = {n_cols} x {n_rows}; expected the pixel matrix to hold "
                         f"one value per detector cell (Rows = channels or Rows = detector rows)")
    if requested != "auto":
        if requested not in fits:
            raise InputError(f"{f0}: scan.pixel_layout = {requested!r} but DICOM Rows x Columns = {rows} x {cols} "
                             f"with {n_cols} channels and {n_rows} detector rows fits only {fits[0]!r}")
        return requested
    if len(fits) > 1:
        raise InputError(f"{f0}: DICOM Rows = Columns = {rows} for a {n_cols} x {n_rows} detector: the tags cannot "
                         f"tell which axis the Rows run along; set scan.pixel_layout = 'rows-are-channels' (as the "
                         f"TCIA files) or 'rows-are-detector-rows'")
    return fits[0]


def reading_for(ix: SeriesIndex, layout: str, flip_channels: bool, flip_rows: bool) -> Reading:
    """The reading of a series in the DICOM-CT-PD numbering (``flip_*``: the series numbers that axis the
    other way)."""
    c = ix.const
    n_rows, n_cols = int(c["NumberofDetectorRows"]), int(c["NumberofDetectorColumns"])
    central = np.atleast_1d(np.asarray(c["DetectorCentralElement"], dtype=np.float64))
    if central.size != 2:
        raise InputError(f"{ix.files[0]}: (7031,1033) DetectorCentralElement = {central.tolist()}; expected two "
                         f"values (column, row), 1-based")
    rev_c, rev_r = not flip_channels, not flip_rows
    x, y = float(central[0]), float(central[1])
    col = (n_cols - x) if rev_c else (x - 1.0)
    row = (n_rows - y) if rev_r else (y - 1.0)
    return Reading(layout=layout, reverse_channels=rev_c, reverse_rows=rev_r, central_col=col, central_row=row)


# ---------------------------------------------------------------------------------------
@dataclass(frozen=True)
class SeriesViews:
    """The per-view geometry of a series: angle_rad, source_z_mm, time_s (n,) float64, in view order,
    and the directions (+1/-1) of the gantry angle and of the table."""

    angle_rad: np.ndarray
    source_z_mm: np.ndarray
    time_s: np.ndarray
    rotation_sign: int
    table_sign: int
    rotation_time_s: float | None


def series_views(folder, rotation_time_s: float | None, timestamp_unit: str = "ms") -> SeriesViews:
    """Gantry angle, source z and time of every view; one-line InputError on a bad series."""
    ix = series_index(folder)
    f0, n = ix.files[0], len(ix)
    nv = int(ix.const["NumberofSourceAngularSteps"])
    beta = np.unwrap(ix.phi_rad) + np.pi / 2.0
    beta -= 2.0 * np.pi * np.floor(beta[0] / (2.0 * np.pi))  # the first view's angle in [0, 2 pi)
    step = 2.0 * np.pi / nv
    sign = 1
    if n > 1:
        d = np.diff(beta)
        sign = 1 if np.median(d) >= 0 else -1
        badk = np.flatnonzero(np.abs(d - sign * step) > ANGLE_TOL_RAD)
        if badk.size:
            k = int(badk[0])
            raise InputError(f"{ix.files[k + 1]}: (7031,1001) DetectorFocalCenterAngularPosition steps by "
                             f"{d[k]:.5f} rad from {Path(ix.files[k]).name}; expected {'+' if sign > 0 else '-'}2 pi / "
                             f"NumberofSourceAngularSteps = {sign * step:.5f} rad as the other views (a missing, "
                             f"duplicated or reordered view)")
    z = ix.z_mm
    tsign = 1
    if n > 1:
        dz = np.diff(z)
        tsign = 1 if np.median(dz) >= 0 else -1
        if not np.all(dz * tsign > 0):
            k = int(np.flatnonzero(dz * tsign <= 0)[0])
            raise InputError(f"{ix.files[k + 1]}: (7031,1002) DetectorFocalCenterAxialPosition = {z[k + 1]:.4f} mm "
                             f"after {z[k]:.4f} mm; expected a table moving one way (strictly monotonic z)")
    ts = ix.timestamp
    t_rot = None
    if np.isfinite(ts).all():
        unit = 1e-3 if timestamp_unit == "ms" else 1.0
        t = (ts - ts[0]) * unit
        dt = np.diff(t)
        badk = np.flatnonzero(dt <= 0)
        if badk.size:
            k = int(badk[0])
            raise InputError(f"{ix.files[k + 1]}: (7033,1067) Timestamp = {ts[k + 1]:g} after {ts[k]:g} "
                             f"({Path(ix.files[k]).name}); expected strictly increasing timestamps")
        t_rot = float(np.median(dt)) * nv if n > 1 else float(rotation_time_s or 0.0)
        if n > 1 and not 0.05 <= t_rot <= 10.0:
            raise InputError(f"{f0}: (7033,1067) Timestamp steps give a rotation time of {t_rot:.4g} s with "
                             f"scan.timestamp_unit = {timestamp_unit!r}; expected 0.05..10 s (the other unit?)")
        t_rot = round(t_rot, 9)
    else:
        if rotation_time_s is None:
            raise InputError(f"{f0}: no (7033,1067) Timestamp in the series; give scanner.rotation_time_s so the view "
                             f"times are view index x rotation time / views per rotation")
        t = np.arange(n) * (rotation_time_s / nv)
    return SeriesViews(angle_rad=beta, source_z_mm=z.astype(np.float64), time_s=t, rotation_sign=sign,
                       table_sign=tsign, rotation_time_s=t_rot)


@dataclass(frozen=True)
class SeriesGeometry:
    """What a series gives the scene: ``scanner``, ``scan`` and ``phantom`` key values, the per-view
    geometry, the reading of its pixels and the orientation check's verdict.

    angle_rad, source_z_mm, time_s: (n,) float64 in view order. ``tag_of``: scene key -> the tag it
    came from. ``reading``: the :class:`Reading` used; ``reading_keys``: the ``scan.flip_*`` values
    that give it; ``check``: :func:`clrecon.scan.orientation_check.check_series`'s dictionary.
    """

    scanner: dict
    scan: dict
    phantom: dict
    angle_rad: np.ndarray
    source_z_mm: np.ndarray
    time_s: np.ndarray
    tag_of: dict
    reading: Reading | None = None
    reading_keys: dict = field(default_factory=dict)
    check: dict = field(default_factory=dict)


TAG_OF = {"sid_mm": "(7031,1003) DetectorFocalCenterRadialDistance",
          "sdd_mm": "(7031,1031) ConstantRadialDistance", "n_cols": "(7029,1011) NumberofDetectorColumns",
          "n_rows": "(7029,1010) NumberofDetectorRows",
          "col_pitch_mm": "(7029,1002) DetectorElementTransverseSpacing",
          "row_pitch_mm": "(7029,1006) DetectorElementAxialSpacing",
          "views_per_rotation": "(7033,1013) NumberofSourceAngularSteps", "detector": "(7029,100B) DetectorShape",
          "rotation_time_s": "(7033,1067) Timestamp", "central_col": "(7031,1033) DetectorCentralElement",
          "central_row": "(7031,1033) DetectorCentralElement",
          "flying_focal_spot": "(7033,100E) FlyingFocalSpotMode",
          "ffs_angle_rad": "(7033,100B) SourceAngularPositionShift",
          "ffs_radial_mm": "(7033,100D) SourceRadialDistanceShift",
          "ffs_z_mm": "(7033,100C) SourceAxialPositionShift",
          "rotation": "(7031,1001) DetectorFocalCenterAngularPosition",
          "table_direction": "(7031,1002) DetectorFocalCenterAxialPosition",
          "n_projections": "the number of files", "pitches": "(7031,1002) DetectorFocalCenterAxialPosition",
          "z_centre_mm": "(7031,1002) DetectorFocalCenterAxialPosition",
          "start_angle_deg": "(7031,1001) DetectorFocalCenterAngularPosition",
          "patient_position": "(0018,5100) PatientPosition",
          "mu_water_per_mm": "(7041,1001) WaterAttenuationCoefficient"}


def series_geometry(folder, rotation_time_s: float | None, timestamp_unit: str = "ms", pixel_layout_key: str = "auto",
                    flip_channels: bool = False, flip_rows: bool = False, orientation: str = "tags",
                    patient_position: str = "", check: bool = True) -> SeriesGeometry:
    """Map a series onto scanner/scan/phantom keys (see the module docstring); one-line InputError on a bad series.

    With ``check`` the orientation check (:mod:`clrecon.scan.orientation_check`) runs on the pixels:
    ``orientation = "tags"`` refuses a reading that a mirror fits better, ``"auto"`` takes the best fit.
    Memoised by the folder's listing signature and the keys.
    """
    folder = str(Path(folder))
    return _geometry_cached(folder, series_signature(folder), rotation_time_s, timestamp_unit, pixel_layout_key,
                            bool(flip_channels), bool(flip_rows), orientation, patient_position, bool(check))


@functools.lru_cache(maxsize=16)
def _geometry_cached(folder, signature, rotation_time_s, timestamp_unit, pixel_layout_key, flip_channels, flip_rows,
                     orientation, patient_position, check) -> SeriesGeometry:
    ix = series_index(folder)
    c = ix.const
    f0 = ix.files[0]
    n = len(ix)
    shape = str(c["DetectorShape"]).upper()
    if shape not in DETECTOR_SHAPES:
        raise InputError(f"{f0}: (7029,100B) DetectorShape = {shape!r}; expected one of {', '.join(DETECTOR_SHAPES)}")
    if str(c["TypeofProjectionData"]).upper() != "HELICAL":
        raise InputError(f"{f0}: (7037,1009) TypeofProjectionData = {c['TypeofProjectionData']!r}; expected HELICAL "
                         f"(clrecon reconstructs helical scans)")
    geo = c.get("TypeofProjectionGeometry")
    if geo not in (None, "") and str(geo).upper() != "FANBEAM":
        raise InputError(f"{f0}: (7037,100A) TypeofProjectionGeometry = {geo!r}; expected FANBEAM "
                         f"(third-generation geometry, as in the TCIA collection)")
    layout = pixel_layout(ix, pixel_layout_key)
    n_rows, n_cols = int(c["NumberofDetectorRows"]), int(c["NumberofDetectorColumns"])
    nv = int(c["NumberofSourceAngularSteps"])
    ffs = str(c.get("FlyingFocalSpotMode") or "FFSNONE").upper()
    if ffs not in FFS_MODES:
        raise InputError(f"{f0}: (7033,100E) FlyingFocalSpotMode = {ffs!r}; expected one of {', '.join(FFS_MODES)}")
    ffs_keys = _ffs_keys(ix, FFS_MODES[ffs], nv)
    rho = ix.rho_mm
    if np.ptp(rho) > 1e-3 * rho[0]:
        k = int(np.argmax(np.abs(rho - rho[0])))
        raise InputError(f"{ix.files[k]}: (7031,1003) DetectorFocalCenterRadialDistance = {rho[k]:g} mm but the first "
                         f"view has {rho[0]:g} mm; expected a constant source radius")
    sid, sdd = float(rho[0]), float(c["ConstantRadialDistance"])
    if sdd <= sid:
        raise InputError(f"{f0}: (7031,1031) ConstantRadialDistance = {sdd:g} mm; expected more than the source "
                         f"radius (7031,1003) = {sid:g} mm (the detector lies beyond the isocentre)")
    central = np.atleast_1d(np.asarray(c["DetectorCentralElement"], dtype=np.float64))
    if central.size != 2 or not (0.5 <= central[0] <= n_cols + 0.5 and 0.5 <= central[1] <= n_rows + 0.5):
        raise InputError(f"{f0}: (7031,1033) DetectorCentralElement = {central.tolist()}; expected (column, row), "
                         f"1-based, within the {n_cols} x {n_rows} detector")
    want = np.array([(n_cols + 1) / 2.0, (n_rows + 1) / 2.0])
    centred = bool(np.abs(central - want).max() <= 1e-3)
    if shape == "FLAT" and not centred:
        raise InputError(f"{f0}: (7031,1033) DetectorCentralElement = {central.tolist()}; this build's flat "
                         f"detector is centred: expected (column, row) = {want.tolist()} (1-based; an offset detector "
                         f"is modelled as CYLINDRICAL only)")
    views = series_views(folder, rotation_time_s, timestamp_unit)
    z = views.source_z_mm
    scanner = {"sid_mm": sid, "sdd_mm": sdd, "n_cols": n_cols, "n_rows": n_rows,
               "col_pitch_mm": float(c["DetectorElementTransverseSpacing"]),
               "row_pitch_mm": float(c["DetectorElementAxialSpacing"]), "views_per_rotation": nv,
               "detector": DETECTOR_SHAPES[shape], **ffs_keys}
    if views.rotation_time_s is not None:
        scanner["rotation_time_s"] = views.rotation_time_s
    w = n_rows * scanner["row_pitch_mm"] * sid / sdd
    feed = abs(float(z[-1] - z[0])) / max(n - 1, 1) * nv
    pitch = float(f"{feed / w:.6g}") if n > 1 else 0.0
    if not pitch > 0:
        raise InputError(f"{f0}: the series has {n} view(s) and no table feed; expected a helical scan")
    position = str(c.get("PatientPosition") or "").upper()
    if position and patient_position and position != patient_position:
        raise InputError(f"{f0}: scan.patient_position = {patient_position!r} contradicts (0018,5100) PatientPosition "
                         f"= {position!r} of the series; remove the key or fix it")
    position = position or patient_position
    if not position:
        raise InputError(f"{f0}: (0018,5100) PatientPosition is not in the series; give scan.patient_position "
                         f"(HFS, HFP, FFS or FFP) so that the image's left is the patient's left")
    lps_signs(position, where=f"{f0}: (0018,5100) PatientPosition")
    scan = {"n_projections": n, "pitches": (pitch,), "z_centre_mm": 0.5 * float(z[0] + z[-1]),
            "start_angle_deg": math.degrees(float(views.angle_rad[0])),
            "rotation": "increasing" if views.rotation_sign > 0 else "decreasing",
            "table_direction": "increasing" if views.table_sign > 0 else "decreasing",
            "patient_position": position}
    phantom = {}
    if c.get("WaterAttenuationCoefficient") is not None:
        phantom["mu_water_per_mm"] = float(c["WaterAttenuationCoefficient"])
    reading = reading_for(ix, layout, flip_channels, flip_rows)
    result = {}
    keys = {"flip_channels": flip_channels, "flip_rows": flip_rows}
    if check:
        result = orientation_check.check_series(ix, scanner, views, reading, flip_channels, flip_rows)
        keys = orientation_check.decide(result, ix.folder, flip_channels, flip_rows, orientation)
        reading = reading_for(ix, layout, keys["flip_channels"], keys["flip_rows"])
    if shape == "CYLINDRICAL":
        # the cylindrical model's keys: 0-based fractional cell of the central ray, in the store's numbering
        scanner.update(central_col=reading.central_col, central_row=reading.central_row)
    geom = SeriesGeometry(scanner=scanner, scan=scan, phantom=phantom, angle_rad=views.angle_rad,
                          source_z_mm=z, time_s=views.time_s, tag_of=dict(TAG_OF), reading=reading,
                          reading_keys=keys, check=result)
    if check:  # the scene records the reading it settled on: find this geometry (and its check) by it
        RESOLVED[(folder, signature, pixel_layout_key, orientation, keys["flip_channels"], keys["flip_rows"])] = geom
    return geom


#: (folder, signature, pixel_layout key, orientation, resolved flip_channels, flip_rows) -> the checked
#: geometry of the last scene load in this process (:func:`resolved_geometry`)
RESOLVED: dict = {}


def resolved_geometry(folder, pixel_layout_key: str, orientation: str, flip_channels: bool,
                      flip_rows: bool) -> SeriesGeometry | None:
    """The geometry (with its orientation check) that a scene load in this process settled on with these
    resolved keys, or None: the check as it ran, before ``orientation = 'auto'`` changed the keys."""
    folder = str(Path(folder))
    return RESOLVED.get((folder, series_signature(folder), pixel_layout_key, orientation, bool(flip_channels),
                         bool(flip_rows)))
