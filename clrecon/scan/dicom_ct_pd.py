"""DICOM-CT-PD projection series: the header index and its mapping onto scanner and scan keys.

A measured scan is a folder of DICOM-CT-PD files, one projection per file (the TCIA "LDCT and
Projection Data" format; Chen et al., Med Phys 42:4917, 2015; Moen et al., Med Phys 48:902,
2021). This module reads every file's header (never the pixels) with pydicom and maps the
geometry onto the scene's ``[scanner]`` and ``[scan]`` keys, so that every later stage sees a
scene like a simulated one. The conventions (which tag gives what, the angle and table
directions, the pixel layout) are in ``docs/measured-data.md``; the per-view table is
:mod:`clrecon.scan.measured`, the pixel import :mod:`clrecon.simulation.measured`.

Mapping (flat detector; lengths mm, angles rad):

- ``sid_mm`` = DetectorFocalCenterRadialDistance rho0 (7031,1003); ``sdd_mm`` =
  ConstantRadialDistance d0 (7031,1031);
- ``n_cols`` = NumberofDetectorColumns (7029,1011) = DICOM Rows (0028,0010); ``n_rows`` =
  NumberofDetectorRows (7029,1010) = DICOM Columns (0028,0011): the pixel array is
  ``[channel, row]``;
- ``col_pitch_mm``, ``row_pitch_mm`` = DetectorElementTransverseSpacing (7029,1002) and
  DetectorElementAxialSpacing (7029,1006), at the detector;
- ``views_per_rotation`` = NumberofSourceAngularSteps (7033,1013); ``detector`` from
  DetectorShape (7029,100B) (FLAT -> flat, CYLINDRICAL -> cylindrical);
- gantry angle ``beta = phi0 + pi/2`` with phi0 = DetectorFocalCenterAngularPosition (7031,1001):
  DICOM-CT-PD puts the focal centre at (-rho0 sin phi0, rho0 cos phi0, z0), clrecon at
  (R cos beta, R sin beta, z);
- source z = DetectorFocalCenterAxialPosition z0 (7031,1002);
- view time = Timestamp (7033,1067) minus the first view's (``scan.timestamp_unit``), else
  ``k * rotation_time_s / views_per_rotation``; ``rotation_time_s`` = median time step x views
  per rotation when there are timestamps.
"""

from __future__ import annotations

import functools
import hashlib
import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from clrecon.core.detector import ffs_states
from clrecon.core.errors import InputError

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
}
#: public attributes read from every file: name -> ((group, element), VR)
PUBLIC = {"InstanceNumber": ((0x0020, 0x0013), "IS"), "Rows": ((0x0028, 0x0010), "US"),
          "Columns": ((0x0028, 0x0011), "US"), "RescaleSlope": ((0x0028, 0x1053), "DS"),
          "RescaleIntercept": ((0x0028, 0x1052), "DS")}
#: tags every file must carry (Timestamp and PhotonStatistics are optional)
REQUIRED = ("NumberofDetectorRows", "NumberofDetectorColumns", "DetectorElementTransverseSpacing",
            "DetectorElementAxialSpacing", "DetectorShape", "DetectorFocalCenterAngularPosition",
            "DetectorFocalCenterAxialPosition", "DetectorFocalCenterRadialDistance", "ConstantRadialDistance",
            "DetectorCentralElement", "NumberofSourceAngularSteps", "TypeofProjectionData")
#: tags that must be equal in every file of a series
CONSTANT = ("NumberofDetectorRows", "NumberofDetectorColumns", "DetectorElementTransverseSpacing",
            "DetectorElementAxialSpacing", "DetectorShape", "ConstantRadialDistance", "DetectorCentralElement",
            "FlyingFocalSpotMode", "NumberofSourceAngularSteps", "TypeofProjectionData", "TypeofProjectionGeometry",
            "Rows", "Columns")
DETECTOR_SHAPES = {"FLAT": "flat", "CYLINDRICAL": "cylindrical"}
#: an angle step within this (rad) of 2 pi / views_per_rotation is regular
ANGLE_TOL_RAD = 1e-3
#: source shifts below these (rad, mm) count as none (no flying focal spot)
SHIFT_TOL = (1e-6, 1e-3)


def _decode(value, vr: str):
    """A tag value as pydicom gives it (typed, or raw bytes for an implicit-VR private tag)."""
    if isinstance(value, bytes):
        if vr == "FL":
            arr = np.frombuffer(value[: len(value) // 4 * 4], "<f4").astype(np.float64)
            return float(arr[0]) if arr.size == 1 else arr
        if vr == "US":
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
    values (equal in every file); ``photons``: PhotonStatistics of the first file or None.
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

    def __len__(self) -> int:
        return len(self.files)


def series_files(folder) -> list[Path]:
    """The files of a series folder (every regular file not starting with '.'), sorted by name."""
    d = Path(folder)
    if not d.is_dir():
        raise InputError(f"{d}: scan.projections is not a folder of DICOM-CT-PD files")
    files = sorted(p for p in d.iterdir() if p.is_file() and not p.name.startswith(".")
                   and p.suffix.lower() in (".dcm", ".ima", ""))
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


def _read_header(p: Path, pydicom, photons: bool = False):
    try:
        ds = pydicom.dcmread(p, stop_before_pixels=True)
    except Exception as e:  # noqa: BLE001 - pydicom raises InvalidDicomError, EOFError, struct.error, ...
        raise InputError(f"{p}: not a readable DICOM file ({type(e).__name__}); truncated or not DICOM?") from None
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
    except (ValueError, TypeError) as e:
        raise InputError(f"{p}: a tag value cannot be decoded ({type(e).__name__}: {e}); corrupt header?") from None
    missing = [n for n in REQUIRED + ("InstanceNumber", "Rows", "Columns") if out[n] is None]
    if missing:
        tag = TAGS[missing[0]][0] if missing[0] in TAGS else None
        where = f"({tag[0]:04X},{tag[1]:04X}) " if tag else ""
        raise InputError(f"{p}: tag {where}{missing[0]} is missing; a DICOM-CT-PD projection carries "
                         f"{', '.join(REQUIRED)}, InstanceNumber, Rows, Columns")
    return out


@functools.lru_cache(maxsize=4)
def _index_cached(folder: str, signature: str) -> SeriesIndex:
    try:
        import pydicom
    except ImportError:  # pragma: no cover - an install without the extra
        raise InputError(f"{folder}: reading DICOM-CT-PD needs pydicom: pip install 'clrecon[measured]'") from None

    files = series_files(folder)
    heads = [_read_header(p, pydicom, photons=(i == 0)) for i, p in enumerate(files)]
    first = heads[0]
    for p, h in zip(files[1:], heads[1:], strict=True):
        for name in CONSTANT:
            a, b = first[name], h[name]
            same = (np.allclose(a, b, rtol=1e-6, atol=1e-6) if isinstance(a, (float, np.ndarray))
                    and isinstance(b, (float, np.ndarray)) and np.shape(a) == np.shape(b) else a == b)
            if not same:
                tag = TAGS[name][0] if name in TAGS else None
                where = f"({tag[0]:04X},{tag[1]:04X}) " if tag else ""
                raise InputError(f"{p}: {where}{name} = {b!r} but {files[0].name} has {a!r}; expected one value "
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
    if np.isfinite(ts).any() and not np.isfinite(ts).all():
        k = int(np.flatnonzero(~np.isfinite(ts))[0])
        raise InputError(f"{files[k]}: tag (7033,1067) Timestamp is missing but other files have it; expected it "
                         f"in every file or in none")
    return SeriesIndex(folder=str(folder), files=tuple(str(f) for f in files), instance=inst_sorted,
                       phi_rad=col("DetectorFocalCenterAngularPosition"), z_mm=col("DetectorFocalCenterAxialPosition"),
                       rho_mm=col("DetectorFocalCenterRadialDistance"), dphi_rad=col("SourceAngularPositionShift"),
                       dz_mm=col("SourceAxialPositionShift"), drho_mm=col("SourceRadialDistanceShift"), timestamp=ts,
                       slope=col("RescaleSlope", 1.0), intercept=col("RescaleIntercept", 0.0),
                       const={n: first[n] for n in CONSTANT}, photons=first["PhotonStatistics"])


def series_index(folder) -> SeriesIndex:
    """The header index of a series folder (memoised by the folder's listing signature)."""
    folder = str(Path(folder))
    return _index_cached(folder, series_signature(folder))


#: DICOM-CT-PD FlyingFocalSpotMode -> the scanner.flying_focal_spot mode of the FFS model (issue 17)
FFS_MODES = {"FFSNONE": "none", "FFSXY": "phi", "FFSZ": "z", "FFSXYZ": "phi+z"}
#: signs of (dphi, dz) per state of the FFS cycle, view k in state k % cycle (as the FFS model's ffs_states)
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


@dataclass(frozen=True)
class SeriesGeometry:
    """What a series gives the scene: ``scanner`` and ``scan`` key values, and the per-view geometry.

    angle_rad, source_z_mm, time_s: (n,) float64 in view order.
    """

    scanner: dict
    scan: dict
    angle_rad: np.ndarray
    source_z_mm: np.ndarray
    time_s: np.ndarray
    tag_of: dict  # scene key -> "(gggg,eeee) Name" it came from


def series_geometry(folder, rotation_time_s: float | None, timestamp_unit: str = "ms") -> SeriesGeometry:
    """Map a series onto scanner/scan keys (see the module docstring); one-line InputError on a bad series."""
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
    n_rows, n_cols = int(c["NumberofDetectorRows"]), int(c["NumberofDetectorColumns"])
    if int(c["Rows"]) != n_cols or int(c["Columns"]) != n_rows:
        raise InputError(f"{f0}: DICOM Rows x Columns = {c['Rows']} x {c['Columns']} but (7029,1011) "
                         f"NumberofDetectorColumns x (7029,1010) NumberofDetectorRows = {n_cols} x {n_rows}; "
                         f"expected Rows = detector columns (channels), Columns = detector rows")
    nv = int(c["NumberofSourceAngularSteps"])
    if nv < 2:
        raise InputError(f"{f0}: (7033,1013) NumberofSourceAngularSteps = {nv}; expected views per rotation >= 2")
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
    central = np.atleast_1d(np.asarray(c["DetectorCentralElement"], dtype=np.float64))
    want = np.array([(n_cols + 1) / 2.0, (n_rows + 1) / 2.0])
    offset_keys = {}
    if central.size == 2 and shape == "CYLINDRICAL" and np.abs(central - want).max() > 1e-3:
        # the cylindrical model's keys (0-based fractional cell of the central ray)
        offset_keys = {"central_col": float(central[0] - 1.0), "central_row": float(central[1] - 1.0)}
    elif central.size != 2 or np.abs(central - want).max() > 1e-3:
        raise InputError(f"{f0}: (7031,1033) DetectorCentralElement = {central.tolist()}; this build's detector "
                         f"models are centred: expected (column, row) = {want.tolist()} (1-based; a detector "
                         f"offset such as a quarter-channel shift is not modelled on this branch)")
    beta = np.unwrap(ix.phi_rad) + np.pi / 2.0
    beta -= 2.0 * np.pi * np.floor(beta[0] / (2.0 * np.pi))  # the first view's angle in [0, 2 pi)
    step = 2.0 * np.pi / nv
    if n > 1:
        d = np.diff(beta)
        if np.median(d) < 0:
            raise InputError(f"{f0}: (7031,1001) DetectorFocalCenterAngularPosition decreases from view to view "
                             f"(step {np.median(d):.5f} rad); this build reconstructs increasing angles only "
                             f"(docs/measured-data.md 'Angle direction')")
        badk = np.flatnonzero(np.abs(d - step) > ANGLE_TOL_RAD)
        if badk.size:
            k = int(badk[0])
            raise InputError(f"{ix.files[k + 1]}: (7031,1001) DetectorFocalCenterAngularPosition steps by "
                             f"{d[k]:.5f} rad from {Path(ix.files[k]).name}; expected 2 pi / "
                             f"NumberofSourceAngularSteps = {step:.5f} rad (a missing, duplicated or reordered view)")
    z = ix.z_mm
    if n > 1:
        dz = np.diff(z)
        if not (np.all(dz > 0) or np.all(dz < 0)):
            k = int(np.flatnonzero(dz * np.sign(np.median(dz)) <= 0)[0])
            raise InputError(f"{ix.files[k + 1]}: (7031,1002) DetectorFocalCenterAxialPosition = {z[k + 1]:.4f} mm "
                             f"after {z[k]:.4f} mm; expected a table moving one way (strictly monotonic z)")
    tag_of = {"sid_mm": "(7031,1003) DetectorFocalCenterRadialDistance",
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
              "ffs_z_mm": "(7033,100C) SourceAxialPositionShift"}
    scanner = {"sid_mm": sid, "sdd_mm": sdd, "n_cols": n_cols, "n_rows": n_rows,
               "col_pitch_mm": float(c["DetectorElementTransverseSpacing"]),
               "row_pitch_mm": float(c["DetectorElementAxialSpacing"]), "views_per_rotation": nv,
               "detector": DETECTOR_SHAPES[shape], **offset_keys, **ffs_keys}
    ts = ix.timestamp
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
        scanner["rotation_time_s"] = round(t_rot, 9)
    else:
        if rotation_time_s is None:
            raise InputError(f"{f0}: no (7033,1067) Timestamp in the series; give scanner.rotation_time_s so the view "
                             f"times are view index x rotation time / views per rotation")
        t = np.arange(n) * (rotation_time_s / nv)
    w = n_rows * scanner["row_pitch_mm"] * sid / sdd
    feed = abs(float(z[-1] - z[0])) / max(n - 1, 1) * nv
    pitch = float(f"{feed / w:.6g}") if n > 1 else 0.0
    if not pitch > 0:
        raise InputError(f"{f0}: the series has {n} view(s) and no table feed; expected a helical scan")
    scan = {"n_projections": n, "pitches": (pitch,), "z_centre_mm": 0.5 * float(z[0] + z[-1]),
            "start_angle_deg": math.degrees(float(beta[0]))}
    return SeriesGeometry(scanner=scanner, scan=scan, angle_rad=beta, source_z_mm=z.astype(np.float64),
                          time_s=t, tag_of=tag_of)
