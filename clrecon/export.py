"""Hand the 5D volumes of a run directory over: DICOM CT series or NIfTI files, one per target.

Last stage of the pipeline (after metrics/report): ``python -m clrecon export RUN_DIR
--format dicom|nifti [--method M] [--pitch P] [--variant V] [--out DIR]``.

Frames. Volumes are stored ``[z, y, x]`` in the DICOM patient frame (LPS: +x patient left,
+y posterior, +z superior) with voxel centres from ``/axes/*_mm``.

- **DICOM**: one CT Image Storage series per target (cardiac phase c, respiratory amplitude
  a), one file per slice. Rows run along +x and columns along +y, so
  ImageOrientationPatient = [1, 0, 0, 0, 1, 0]; ImagePositionPatient is the centre of the
  first voxel of the slice (x0, y0, z_k) in mm; PixelSpacing = [dy, dx] (row spacing, column
  spacing). Stored values are int16 with RescaleSlope/RescaleIntercept giving HU (slope 1 HU
  unless the HU range does not fit in int16). All series of one export share one
  StudyInstanceUID and one FrameOfReferenceUID, derived from the run (scene, run directory),
  so exporting another method of the same run adds series to the same study. (c, a) is
  carried in the SeriesDescription (``"5DCT local_linear C40% R05%"``), in the standard
  TemporalPositionIdentifier / NumberOfTemporalPositions (target number, cardiac-major), in
  NominalPercentageOfCardiacPhase / NominalPercentageOfRespiratoryPhase, and in a private
  block (creator ``"CLRECON 5DCT"``, group 0x0011: 0x10 cardiac phase, 0x11 respiratory
  amplitude, both fractions in [0, 1], 0x12 cardiac index, 0x13 respiratory index).
- **NIfTI**: one ``.nii.gz`` per target, array indexed ``[i, j, k] = [x, y, z]``, float32 HU,
  with qform = sform (code 1, scanner) mapping voxel indices to **RAS** mm: NIfTI's RAS is
  LPS with x and y negated, so the affine is ``diag(-dx, -dy, dz)`` with origin
  ``(-x0, -y0, z0)``.

Both formats also get ``index.json``: the run, the source and the file(s) of every target.
"""

from __future__ import annotations

import datetime
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .errors import ClreconError, StoreError
from .volumes import FORMAT_VERSION, list_recons, open_volumes, read_volume

FORMATS = ("dicom", "nifti")
#: Preferred default source, best first (5DCT methods, then baselines).
METHOD_PREFERENCE = ("local_linear", "barycentric", "r4dct", "bin", "nearest")
VARIANT_PREFERENCE = ("noisy", "noise-free")
REFERENCE_VOLUMES = ("groundtruth", "phantom")
PRIVATE_CREATOR = "CLRECON 5DCT"
PRIVATE_GROUP = 0x0011
CT_IMAGE_STORAGE = "1.2.840.10008.5.1.4.1.1.2"


# ----------------------------------------------------------------------------------------
# Run directory -> one volume source (shared with the viewer and the figures)
@dataclass(frozen=True)
class Source:
    """One 5D volume of a run: ``dataset`` is its HDF5 path; ``method`` its name or a reference.

    ``pitch_key``/``variant`` are None for the ground truth and the phantom.
    """

    dataset: str
    method: str
    pitch_key: str | None = None
    variant: str | None = None

    @property
    def label(self) -> str:
        """Human label, e.g. ``"local_linear p0.020 noisy"`` or ``"groundtruth"``."""
        if self.pitch_key is None:
            return self.method
        return f"{self.method} {self.pitch_key} {self.variant}"


def open_run(run_dir):
    """Open a run directory's ``volumes.h5`` (h5py.File) with one-line errors for wrong paths."""
    p = Path(run_dir)
    if not p.exists():
        raise StoreError(f"{p}: no such run directory")
    if p.is_file() and p.name != "volumes.h5":
        raise StoreError(f"{p}: expected a run directory (with volumes.h5), got a file")
    h5 = p / "volumes.h5" if p.is_dir() else p
    if h5.exists():  # check the format here too: open_volumes' own message reads a closed file
        import h5py

        try:
            with h5py.File(h5, "r") as f:
                version = f.attrs.get("format_version")
                version = version.item() if hasattr(version, "item") else version
        except OSError as e:
            raise StoreError(f"{h5}: not a readable HDF5 file ({e})") from None
        if version != FORMAT_VERSION:
            raise StoreError(f"{h5}: volume format {version!r} is not {FORMAT_VERSION} (an older or foreign run "
                             f"directory); re-run `clrecon run` with this version")
    return open_volumes(p)


def normalise_pitch(pitch) -> str | None:
    """``0.02``, ``"0.02"`` or ``"p0.020"`` -> ``"p0.020"`` (None stays None)."""
    if pitch is None:
        return None
    text = str(pitch).strip()
    try:
        return f"p{float(text.lstrip('pP')):.3f}"
    except ValueError:
        raise ClreconError(f"--pitch {pitch!r}: expected a number such as 0.02 or a key such as p0.020") from None


def sources(f) -> list[Source]:
    """Every volume of the run: ground truth, phantom, then each (pitch, variant, method)."""
    out = [Source(name, name) for name in REFERENCE_VOLUMES if name in f]
    out += [Source(f"recon/{p}/{v}/{m}", m, p, v) for p, v, m in list_recons(f)]
    return out


def describe_sources(f) -> str:
    """One line naming what a run holds, e.g. ``groundtruth, phantom; p0.020/noisy: local_linear, nearest``."""
    refs = [n for n in REFERENCE_VOLUMES if n in f]
    groups: dict = {}
    for p, v, m in list_recons(f):
        groups.setdefault(f"{p}/{v}", []).append(m)
    parts = [", ".join(refs) if refs else "no reference volumes"]
    parts += [f"{k}: {', '.join(ms)}" for k, ms in groups.items()]
    return "; ".join(parts) if groups else parts[0] + "; no reconstructions"


def resolve_source(f, method: str | None = None, pitch=None, variant: str | None = None) -> Source:
    """The source asked for, with defaults filled in; a ClreconError naming what exists otherwise.

    ``method``: a reconstruction method, ``groundtruth`` or ``phantom``; default the best
    method present (:data:`METHOD_PREFERENCE`), else the ground truth. ``pitch``: number or
    key, default the smallest pitch present. ``variant``: default ``noisy`` if present.
    """
    if method in REFERENCE_VOLUMES:
        if method not in f:
            raise ClreconError(f"this run has no {method} volume; it has {describe_sources(f)}")
        return Source(method, method)
    recons = list_recons(f)
    pk = normalise_pitch(pitch)
    cands = [r for r in recons if (pk is None or r[0] == pk) and (variant is None or r[1] == variant)
             and (method is None or r[2] == method)]
    if not cands:
        if method is None and pk is None and variant is None:
            for name in REFERENCE_VOLUMES:
                if name in f:
                    return Source(name, name)
        want = ", ".join(f"{k} {v}" for k, v in (("method", method), ("pitch", pk), ("variant", variant)) if v)
        raise ClreconError(f"no volume with {want or 'any name'} in this run; it has {describe_sources(f)}")

    def rank(r):
        p, v, m = r
        mi = METHOD_PREFERENCE.index(m) if m in METHOD_PREFERENCE else len(METHOD_PREFERENCE)
        vi = VARIANT_PREFERENCE.index(v) if v in VARIANT_PREFERENCE else len(VARIANT_PREFERENCE)
        return (mi, float(p[1:]), vi, m)

    p, v, m = min(cands, key=rank)
    return Source(f"recon/{p}/{v}/{m}", m, p, v)


def run_axes(f) -> dict:
    """``{cardiac_phase, resp_amplitude, z_mm, y_mm, x_mm}`` as float64 arrays."""
    return {k: np.asarray(f[f"axes/{k}"][()], np.float64) for k in ("cardiac_phase", "resp_amplitude",
                                                                   "z_mm", "y_mm", "x_mm")}


def target_tag(c: float, a: float) -> str:
    """``C40% R05%`` for c = 0.4, a = 0.05 (percent, rounded)."""
    return f"C{round(c * 100):02d}% R{round(a * 100):02d}%"


def _file_tag(c: float, a: float) -> str:
    return f"C{round(c * 100):02d}_R{round(a * 100):02d}"


def _spacing(v: np.ndarray, name: str) -> float:
    if v.size < 2:
        return 1.0
    d = np.diff(v)
    if not np.allclose(d, d[0], rtol=1e-4, atol=1e-6) or d[0] <= 0:
        raise StoreError(f"axis {name} is not uniformly increasing; cannot write a regular grid")
    return float(d[0])


def _run_identity(run_dir: Path, f) -> str:
    """A string that identifies one run (seed of its Study and Frame of Reference UIDs)."""
    res = run_dir / "results.json"
    scene = ""
    if res.exists():
        try:
            scene = json.dumps(json.loads(res.read_text()).get("scene", {}), sort_keys=True)
        except (OSError, ValueError):
            scene = ""
    return f"{run_dir.resolve()}|{scene}"


# ----------------------------------------------------------------------------------------
def export(run_dir, fmt: str, method: str | None = None, pitch=None, variant: str | None = None,
           out=None) -> dict:
    """Export one source of a run, every target; returns the ``index.json`` dictionary.

    ``out`` defaults to ``RUN_DIR/export/<fmt>/<method>[_<pitch>_<variant>]``. Files:
    DICOM ``<out>/<C40_R05>/IM0001.dcm ...``; NIfTI ``<out>/<method>_<C40_R05>.nii.gz``.
    """
    if fmt not in FORMATS:
        raise ClreconError(f"--format {fmt!r}: must be one of {', '.join(FORMATS)}")
    run_dir = Path(run_dir)
    f = open_run(run_dir)
    try:
        src = resolve_source(f, method, pitch, variant)
        axes = run_axes(f)
        if out is None:
            stem = src.method if src.pitch_key is None else f"{src.method}_{src.pitch_key}_{src.variant}"
            out = run_dir / "export" / fmt / stem
        out = Path(out)
        out.mkdir(parents=True, exist_ok=True)
        ident = _run_identity(run_dir, f)
        writer = _write_dicom_target if fmt == "dicom" else _write_nifti_target
        index = {"run_dir": str(run_dir.resolve()), "format": fmt, "source": src.dataset, "method": src.method,
                 "pitch_key": src.pitch_key, "variant": src.variant, "frame": "LPS (DICOM patient frame)"
                 if fmt == "dicom" else "RAS (NIfTI; LPS with x and y negated)", "targets": []}
        nc, nr = len(axes["cardiac_phase"]), len(axes["resp_amplitude"])
        ctx = _DicomContext.create(ident, src, nc * nr) if fmt == "dicom" else None
        for ci, c in enumerate(axes["cardiac_phase"]):
            for ri, a in enumerate(axes["resp_amplitude"]):
                vol = np.asarray(read_volume(f, src.dataset, (ci, ri)), np.float32)
                files = writer(out, vol, axes, src, ci, ri, ctx)
                index["targets"].append({"cardiac_index": ci, "resp_index": ri, "cardiac_phase": float(c),
                                         "resp_amplitude": float(a), "tag": target_tag(c, a),
                                         "files": [str(Path(p).relative_to(out)) for p in files]})
        if ctx is not None:
            index["study_instance_uid"] = ctx.study_uid
            index["frame_of_reference_uid"] = ctx.frame_uid
        (out / "index.json").write_text(json.dumps(index, indent=1))
        index["out"] = str(out)
        return index
    finally:
        f.close()


# ----------------------------------------------------------------------------------------
# DICOM
def _pydicom():
    try:
        import pydicom
    except ImportError:
        raise ClreconError("DICOM export needs pydicom: pip install 'clrecon[export]'") from None
    return pydicom


@dataclass
class _DicomContext:
    ident: str
    study_uid: str
    frame_uid: str
    n_targets: int
    when: datetime.datetime

    @classmethod
    def create(cls, ident: str, src: Source, n_targets: int) -> "_DicomContext":
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
    from pydicom.dataset import FileMetaDataset, Dataset
    from pydicom.uid import ExplicitVRLittleEndian, generate_uid

    c = float(axes["cardiac_phase"][ci])
    a = float(axes["resp_amplitude"][ri])
    x, y, z = axes["x_mm"], axes["y_mm"], axes["z_mm"]
    dx, dy = _spacing(x, "x_mm"), _spacing(y, "y_mm")
    dz = _spacing(z, "z_mm") if z.size > 1 else dx
    stored, slope, intercept = hu_to_stored(vol)
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
        ds.PatientPosition = "HFS"
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
        ds.SeriesNumber = temporal
        ds.InstanceNumber = k + 1
        ds.SeriesDescription = desc[:64]
        ds.ImageComments = f"cardiac_phase={c:.4f} resp_amplitude={a:.4f} source={src.dataset}"
        ds.TemporalPositionIdentifier = temporal
        ds.NumberOfTemporalPositions = ctx.n_targets
        ds.NominalPercentageOfCardiacPhase = c * 100.0
        ds.NominalPercentageOfRespiratoryPhase = a * 100.0
        ds.ImagePositionPatient = [_ds(x[0]), _ds(y[0]), _ds(z[k])]
        ds.ImageOrientationPatient = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0]
        ds.SliceLocation = _ds(z[k])
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
    try:  # pydicom >= 3
        pydicom.dcmwrite(path, ds, enforce_file_format=True)
    except TypeError:  # pydicom 2.x
        ds.is_little_endian = True
        ds.is_implicit_VR = False
        ds.save_as(path, write_like_original=False)


# ----------------------------------------------------------------------------------------
# NIfTI
def nifti_affine(axes: dict) -> np.ndarray:
    """4x4 voxel-index (i=x, j=y, k=z) -> RAS mm affine of a run's grid (LPS axes negated in x, y)."""
    x, y, z = axes["x_mm"], axes["y_mm"], axes["z_mm"]
    dx, dy = _spacing(x, "x_mm"), _spacing(y, "y_mm")
    dz = _spacing(z, "z_mm") if z.size > 1 else dx
    aff = np.diag([-dx, -dy, dz, 1.0])
    aff[:3, 3] = [-x[0], -y[0], z[0]]
    return aff


def _write_nifti_target(out: Path, vol: np.ndarray, axes: dict, src: Source, ci: int, ri: int, ctx) -> list[Path]:
    try:
        import nibabel as nib
    except ImportError:
        raise ClreconError("NIfTI export needs nibabel: pip install 'clrecon[export]'") from None
    c = float(axes["cardiac_phase"][ci])
    a = float(axes["resp_amplitude"][ri])
    data = np.ascontiguousarray(np.transpose(vol, (2, 1, 0)), np.float32)  # [z,y,x] -> [x,y,z]
    aff = nifti_affine(axes)
    img = nib.Nifti1Image(data, aff)
    img.header.set_qform(aff, code=1)
    img.header.set_sform(aff, code=1)
    img.header.set_xyzt_units("mm", "sec")
    img.header["descrip"] = f"5DCT {src.method} {target_tag(c, a)}".encode()[:79]
    stem = src.method if src.pitch_key is None else f"{src.method}_{src.pitch_key}_{src.variant}"
    path = out / f"{stem}_{_file_tag(c, a)}.nii.gz"
    nib.save(img, path)
    return [path]

