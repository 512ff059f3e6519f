"""DICOM-CT-PD writer: a run's scan as a measured scan, one projection per file.

``python -m clrecon export RUN --format dicom-ct-pd [--pitch P] [--out DIR]`` writes

- ``DIR/projections/PROJ000001.dcm ...``: every projection of one pitch (the noisy variant when
  the scene has noise: noise is drawn on read, :mod:`clrecon.simulation.noise`), uint16 with
  RescaleSlope/RescaleIntercept to line integrals (per file: slope = range / 65535, so the
  quantisation error is at most slope / 2), in the format's conventions (:class:`Convention`,
  ``docs/measured-conventions.md``): DICOM Rows = detector channels (the TCIA layout), the channel index
  towards decreasing phi0, row 1 at the +z0 end, the DetectorCentralElement reflected with them,
  with the DICOM-CT-PD private tags of :data:`clrecon.scan.dicom_ct_pd.TAGS`, the water coefficient
  and the patient position, and every attribute the CT Image IOD asks for (dciodvfy: no error; ImageType
  DERIVED\\SECONDARY, a measured run's re-export too);
- ``DIR/breathing.vxp``: the breathing trace (RPM 1.6 layout, 200 samples/s, the model's raw
  amplitude r(t) in cm with Scale_factor 10, ttlin = 1 while the beam is on) when the scene breathes;
- ``DIR/r_peaks.csv``: the R-peak times (``r_peak_s``) when the heart beats;
- ``DIR/measured.toml``: a scene that reconstructs the folder as a measured scan on the run's
  grid, targets and methods.

A run whose store lacks projections (``--slices``) has them simulated first.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from clrecon.config.scene import Scene
from clrecon.core import atomic
from clrecon.core.errors import ClreconError
from clrecon.outputs.writers import WRITERS
from clrecon.outputs.writers.base import Writer
from clrecon.scan import dicom_ct_pd as pd_tags
from clrecon.scan import signals
from clrecon.simulation import simulate

CT_IMAGE_STORAGE = "1.2.840.10008.5.1.4.1.1.2"
#: Private creator of every DICOM-CT-PD group written here (readers match the tags by number).
PRIVATE_CREATOR = "CLRECON DICOM-CT-PD"
#: Breathing-trace sample rate of the .vxp (Hz): the model's percentile grid (5 ms).
VXP_RATE = 200
#: Projections read and written per batch.
BATCH = 256
#: Patient-identifying attributes copied from a measured input only with --keep-identifiers.
IDENTIFIERS = ("PatientName", "PatientID", "PatientBirthDate", "PatientSex", "PatientAge", "OtherPatientIDs",
               "AccessionNumber", "InstitutionName", "ReferringPhysicianName", "StudyDate", "StudyTime",
               "StudyID")


def quantise(p: np.ndarray) -> tuple[np.ndarray, float, float]:
    """Line integrals -> (uint16 stored, RescaleSlope, RescaleIntercept), p = stored * slope + intercept."""
    lo = float(f"{min(float(p.min()), 0.0):.9g}")  # values as the DS strings will hold them (<= 16 chars)
    hi = float(p.max())
    slope = float(f"{max(hi - lo, 1e-6) / 65535.0 * (1 + 1e-8):.9g}")
    stored = np.clip(np.rint((p - lo) / slope), 0, 65535).astype(np.uint16)
    return stored, slope, lo


def input_identifiers(scene: Scene) -> dict:
    """The patient attributes of a measured scene's first projection file (for --keep-identifiers)."""
    if not scene.measured:
        return {}
    import pydicom

    first = pd_tags.series_index(scene.scan.projections).files[0]
    ds = pydicom.dcmread(first, stop_before_pixels=True)
    return {k: ds.get(k) for k in IDENTIFIERS if ds.get(k) not in (None, "")}


@WRITERS.register("dicom-ct-pd")
class DicomCtPdWriter(Writer):
    name = "dicom-ct-pd"
    label = "DICOM-CT-PD"
    frame = "DICOM-CT-PD scanner frame (docs/measured-data.md)"
    requires = "pydicom"
    #: exports the run's projections (not its volumes): export() calls export_scan
    scan_export = True

    def export_scan(self, run, out: Path, pitch=None, keep_identifiers: bool = False, scene=None) -> dict:
        return export_scan(run, out, pitch=pitch, keep_identifiers=keep_identifiers, scene=scene)


def _private(ds, name: str, value) -> None:
    (group, elem), vr = pd_tags.TAGS[name]
    block = ds.private_block(group, PRIVATE_CREATOR, create=True)
    block.add_new(elem & 0xFF, vr, value)


@dataclass(frozen=True)
class Convention:
    """How the exported files lay out and number the detector (docs/measured-conventions.md).

    ``layout``: ``rows-are-channels`` (DICOM Rows = detector channels, as the TCIA files) or
    ``rows-are-detector-rows``; ``flip_channels`` / ``flip_rows``: number that axis opposite to the
    DICOM-CT-PD convention (the store's own order; a reader then needs ``scan.flip_channels`` /
    ``scan.flip_rows``). The default is the format's convention, which every reader of it expects.
    """

    layout: str = "rows-are-channels"
    flip_channels: bool = False
    flip_rows: bool = False

    def __post_init__(self):
        if self.layout not in pd_tags.LAYOUTS:
            raise ClreconError(f"layout = {self.layout!r}: must be one of {', '.join(pd_tags.LAYOUTS)}")


def export_scan(run, out: Path, pitch=None, keep_identifiers: bool = False, convention: Convention | None = None,
                scene: Scene | None = None) -> dict:
    """Write the scan of ``run`` (a :class:`clrecon.outputs.rundir.RunDirectory`) under ``out``.

    ``scene``: the run's scene where ``results.json`` records a measured series only by its signature
    (patient data): the measured scene the run was made from (checked against that record).
    """
    pydicom = DicomCtPdWriter().require()
    from pydicom.uid import generate_uid

    convention = convention or Convention()
    res = run.results
    scene = scene if scene is not None else run.scene
    pitches = [float(p) for p in res["request"]["pitches"]]
    if pitch is None:
        pitch = min(pitches)
    pitch = float(pitch)
    match = [p for p in pitches if abs(p - pitch) < 1e-9]
    if not match:
        raise ClreconError(f"--pitch {pitch:g}: the run has pitches {', '.join(f'{p:g}' for p in pitches)}")
    pitch = match[0]
    pk = f"p{pitch:.3f}"
    store_path = res["stages"]["simulate"]["per_pitch"].get(pk, {}).get("store", "")
    cache_dir = Path(store_path).parent if store_path else None
    store = simulate.simulate(scene, pitch, cache_dir=cache_dir, progress=False)  # fills what --slices left out
    table = store.table
    noisy = scene.noise.enabled and not scene.measured
    variant = "measured" if scene.measured else ("noisy" if noisy else "noise-free")
    ident = input_identifiers(scene) if keep_identifiers else {}
    sc = scene.scanner
    out = Path(out)
    proj_dir = out / "projections"
    proj_dir.mkdir(parents=True, exist_ok=True)
    seed = f"{Path(run.dir).resolve()}|{scene.scan_hash(pitch)}|{variant}"
    study_uid = generate_uid(entropy_srcs=[seed, "study"])
    series_uid = generate_uid(entropy_srcs=[seed, "series"])
    frame_uid = generate_uid(entropy_srcs=[seed, "frame"])
    n = len(table)
    photons = np.full(sc.n_cols, scene.noise.i0_photons if noisy else 0.0, np.float32)
    max_err = 0.0
    for lo in range(0, n, BATCH):
        idx = np.arange(lo, min(n, lo + BATCH), dtype=np.int64)
        data = store.read_indices(idx, noisy=noisy)
        for j, k in enumerate(idx):
            p = data[j]
            stored, slope, intercept = quantise(p)
            max_err = max(max_err, float(np.abs(stored * slope + intercept - p).max()))
            sop = generate_uid(entropy_srcs=[seed, "sop", str(int(k))])
            ds = projection_dataset(scene, table, int(k), stored, slope, intercept, photons,
                                    (study_uid, series_uid, frame_uid), sop,
                                    f"clrecon {scene.name} pitch {pitch:g} {variant} projections", ident, convention)
            ds.SpiralPitchFactor = float(pitch)
            with atomic.replacing(proj_dir / f"PROJ{int(k) + 1:06d}.dcm") as tmp:
                pydicom.dcmwrite(tmp, ds, enforce_file_format=True)
    store.close()
    written = {"projections": "projections", "n_projections": n, "variant": variant,
               "quantisation_max_error": max_err, "convention": {"layout": convention.layout,
                                                                 "flip_channels": convention.flip_channels,
                                                                 "flip_rows": convention.flip_rows}}
    sig = {}
    if scene.has_respiratory and not scene.measured:
        write_vxp(out / "breathing.vxp", scene, float(table.time_s[-1]))
        written["breathing_trace"] = "breathing.vxp"
        sig.update(breathing_trace="breathing.vxp", trace_align="beam-on")
    # a measured run: the traces are the input's (not copied: they may carry identifiers)
    if scene.has_cardiac and not scene.measured:
        write_r_peaks(out / "r_peaks.csv", signals.r_peaks(scene))
        written["ecg_trace"] = "r_peaks.csv"
        sig["ecg_trace"] = "r_peaks.csv"
    scan_keys = {}
    if convention.flip_channels:
        scan_keys["flip_channels"] = True
    if convention.flip_rows:
        scan_keys["flip_rows"] = True
    atomic.write_text(out / "measured.toml", measured_toml(scene, sig, res, scan_keys))
    written["scene"] = "measured.toml"
    return {"format": "dicom-ct-pd", "pitch": pitch, "source": f"projections {pk}", "method": "projections",
            "pitch_key": pk, "variant": variant, "frame": DicomCtPdWriter.frame, "targets": [],
            "files": written, "out": str(out)}


def projection_dataset(scene: Scene, table, k: int, stored: np.ndarray, slope: float, intercept: float,
                       photons: np.ndarray, uids: tuple, sop: str, description: str, ident: dict | None = None,
                       convention: Convention | None = None):
    """The DICOM-CT-PD dataset of projection ``k`` of ``table`` (``stored``: uint16 (R, C) in the store's
    ``[row, column]`` order), laid out and numbered as ``convention`` says (default: the format's)."""
    from pydicom.dataset import Dataset, FileMetaDataset
    from pydicom.uid import ExplicitVRLittleEndian

    convention = convention or Convention()
    sc = scene.scanner
    study_uid, series_uid, frame_uid = uids
    meta = FileMetaDataset()
    meta.MediaStorageSOPClassUID = CT_IMAGE_STORAGE
    meta.MediaStorageSOPInstanceUID = sop
    meta.TransferSyntaxUID = ExplicitVRLittleEndian
    ds = Dataset()
    ds.file_meta = meta
    ds.SpecificCharacterSet = "ISO_IR 100"
    ds.SOPClassUID = CT_IMAGE_STORAGE
    ds.SOPInstanceUID = sop
    ds.Modality = "CT"
    ds.Manufacturer = "clrecon"
    ds.PatientName = "ANONYMOUS" if scene.measured else "clrecon^phantom"
    ds.PatientID = "ANONYMOUS" if scene.measured else "CLRECON-PHANTOM"
    ds.PatientBirthDate = ""
    ds.PatientSex = ""
    ds.StudyDate = ds.SeriesDate = ds.ContentDate = ""
    ds.StudyTime = ds.SeriesTime = ds.ContentTime = ""
    ds.StudyID = ""
    ds.AccessionNumber = ""
    ds.ReferringPhysicianName = ""
    ds.StudyInstanceUID, ds.SeriesInstanceUID, ds.FrameOfReferenceUID = study_uid, series_uid, frame_uid
    ds.PositionReferenceIndicator = ""
    for key, val in (ident or {}).items():  # --keep-identifiers: the input's own values
        setattr(ds, key, val)
    ds.SeriesNumber = 1
    ds.AcquisitionNumber = 1
    ds.SeriesDescription = description[:64]
    # derived data, a measured run's re-export too (its projections re-quantised, its private groups rewritten):
    # ORIGINAL with RescaleType LINE_INTEGRAL is invalid (the CT Image IOD wants HU there; dciodvfy: an error)
    ds.ImageType = ["DERIVED", "SECONDARY", "AXIAL"]
    ds.ImageComments = "DICOM-CT-PD projection (CT_PROJECTION): geometry in the private groups 7029-7041"
    ds.InstanceNumber = k + 1
    ds.PatientPosition = scene.scan.patient_position or "HFS"
    ds.KVP = ""
    ds.Laterality = ""  # Type 2C: not a paired organ (an empty value states it)
    # a projection lies in no patient plane: nominal values for the Type 1 image-plane attributes
    # (the geometry is in the private tags); PixelSpacing = spacing between DICOM rows, columns
    along_rows = (float(sc.col_pitch_mm), float(sc.row_pitch_mm))
    if convention.layout == "rows-are-detector-rows":
        along_rows = along_rows[::-1]
    ds.PixelSpacing = [f"{along_rows[0]:.6g}", f"{along_rows[1]:.6g}"]
    ds.ImageOrientationPatient = [1, 0, 0, 0, 1, 0]
    ds.ImagePositionPatient = [0, 0, f"{float(table.source_z_mm[k]):.6f}"[:16]]
    ds.SliceThickness = ""
    ds.SamplesPerPixel = 1
    ds.PhotometricInterpretation = "MONOCHROME2"
    ds.BitsAllocated = 16
    ds.BitsStored = 16
    ds.HighBit = 15
    ds.PixelRepresentation = 0
    ds.RescaleSlope = f"{slope:.9g}"
    ds.RescaleIntercept = f"{intercept:.9g}"
    ds.RescaleType = "LINE_INTEGRAL"[:16]
    # the format's numbering: channel index towards decreasing phi0, row index towards decreasing z0
    # (row 1 at the +z end): the store's two axes reversed, the central element reflected with them
    pix = stored if convention.flip_rows else stored[::-1, :]
    pix = pix if convention.flip_channels else pix[:, ::-1]
    cc, cr = getattr(sc, "central_col", -1.0), getattr(sc, "central_row", -1.0)
    cc = (sc.n_cols - 1) / 2.0 if cc == -1.0 else float(cc)
    cr = (sc.n_rows - 1) / 2.0 if cr == -1.0 else float(cr)
    x = cc + 1.0 if convention.flip_channels else sc.n_cols - cc
    y = cr + 1.0 if convention.flip_rows else sc.n_rows - cr
    if convention.layout == "rows-are-channels":
        ds.Rows, ds.Columns = sc.n_cols, sc.n_rows
        pix = pix.T  # pixel[channel, row]
    else:
        ds.Rows, ds.Columns = sc.n_rows, sc.n_cols
    _private(ds, "NumberofDetectorRows", sc.n_rows)
    _private(ds, "NumberofDetectorColumns", sc.n_cols)
    _private(ds, "DetectorElementTransverseSpacing", float(sc.col_pitch_mm))
    _private(ds, "DetectorElementAxialSpacing", float(sc.row_pitch_mm))
    _private(ds, "DetectorShape", sc.detector.upper())
    _private(ds, "DetectorFocalCenterAngularPosition",
             float((table.angle_rad[k] - math.pi / 2.0) % (2.0 * math.pi)))
    _private(ds, "DetectorFocalCenterAxialPosition", float(table.source_z_mm[k]))
    _private(ds, "DetectorFocalCenterRadialDistance", float(sc.sid_mm))
    _private(ds, "ConstantRadialDistance", float(sc.sdd_mm))
    _private(ds, "DetectorCentralElement", [x, y])
    # the flying focal spot (the scanner keys and the table's focal_shift of the issue-17 model)
    shift = getattr(table, "focal_shift", None)
    dphi, drho, dz = (0.0, 0.0, 0.0) if shift is None else (float(v) for v in shift[k])
    _private(ds, "SourceAngularPositionShift", dphi)
    _private(ds, "SourceAxialPositionShift", dz)
    _private(ds, "SourceRadialDistanceShift", drho)
    mode = getattr(sc, "flying_focal_spot", "none")
    _private(ds, "FlyingFocalSpotMode", {v: key for key, v in pd_tags.FFS_MODES.items()}[mode])
    _private(ds, "NumberofSourceAngularSteps", sc.views_per_rotation)
    _private(ds, "PhotonStatistics", photons.tolist())
    _private(ds, "Timestamp", float(table.time_s[k] * 1000.0))
    _private(ds, "TypeofProjectionData", "HELICAL")
    _private(ds, "TypeofProjectionGeometry", "FANBEAM")
    _private(ds, "WaterAttenuationCoefficient", f"{float(scene.phantom.mu_water_per_mm):.8g}"[:16])
    ds.PixelData = np.ascontiguousarray(pix).astype("<u2").tobytes()
    return ds


def write_vxp(path: Path, scene: Scene, scan_end_s: float) -> None:
    """The scene's breathing trace as an RPM ``.vxp`` (1.6 layout) over the whole model trace."""
    tr = signals.respiratory_trace(scene, step_s=1.0 / VXP_RATE)
    t_ms = np.rint(tr.time_s * 1000.0).astype(np.int64)
    edges = tr.cycle_start_s
    k = np.clip(np.searchsorted(edges, tr.time_s, side="right") - 1, 0, edges.size - 2)
    phase = 2.0 * np.pi * (tr.time_s - edges[k]) / (edges[k + 1] - edges[k])
    beam = (tr.time_s >= 0.0) & (tr.time_s <= scan_end_s + 1e-9)
    lines = ["[Header]", "CRC=0", "Version=1.6", "Data_layout=amplitude,phase,timestamp,validflag,ttlin,mark,ttlout",
             "Patient_ID=", "Date=", f"Total_study_time={tr.time_s[-1] - tr.time_s[0]:.3f}",
             f"Samples_per_second={VXP_RATE}", "Scale_factor=10.0", "[Data]"]
    for i in range(t_ms.size):
        lines.append(f"{tr.raw[i]:.7f},{phase[i]:.4f},{t_ms[i]},0,{int(beam[i])},,0")
    atomic.write_text(path, "\n".join(lines) + "\n")


def write_r_peaks(path: Path, peaks: np.ndarray) -> None:
    atomic.write_text(path, "r_peak_s\n" + "".join(f"{t:.9f}\n" for t in peaks))


def _toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    if isinstance(v, (float, np.floating)):
        return repr(float(v))
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    raise TypeError(type(v))


def measured_toml(scene: Scene, sig: dict, results: dict, scan_keys: dict | None = None) -> str:
    """A scene reconstructing the exported folder as a measured scan on the run's grid and methods."""
    d = scene.to_dict()
    recon = dict(d["recon"])
    recon["methods"] = list(results["request"]["methods"])
    lines = [f"# written by clrecon export --format dicom-ct-pd from the run of scene {scene.name!r}",
             f'name = "{scene.name}-measured"',
             f'description = "the {scene.name} scan exported as DICOM-CT-PD and read back as a measured scan"',
             "", "[scan]", 'source = "dicom-ct-pd"', 'projections = "projections"', 'timestamp_unit = "ms"']
    lines += [f"{k} = {_toml_value(v)}" for k, v in (scan_keys or {}).items()]
    lines += ["", "[signals]"]
    lines += [f"{k} = {_toml_value(v)}" for k, v in sig.items()]
    lines += ["", "[noise]", "enabled = false", "", "[recon]"]
    lines += [f"{k} = {_toml_value(v)}" for k, v in recon.items() if not isinstance(v, dict)]
    for k, v in recon.items():  # nested tables ([recon.mc]) after the table's own keys
        if isinstance(v, dict):
            lines += ["", f"[recon.{k}]"] + [f"{kk} = {_toml_value(vv)}" for kk, vv in v.items()]
    return "\n".join(lines) + "\n"
