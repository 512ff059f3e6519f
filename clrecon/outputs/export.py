"""Hand the 5D volumes of a run directory over: DICOM CT series or NIfTI files, one per target.

Last stage of the pipeline (after metrics/report): ``python -m clrecon export RUN_DIR
--format dicom|nifti [--method M] [--pitch P] [--variant V] [--out DIR]``.

Frames. Volumes are stored ``[z, y, x]`` in the DICOM patient frame (LPS: +x patient left,
+y posterior, +z superior) with voxel centres from ``/axes/*_mm``.

The formats are the writers registered in :data:`clrecon.outputs.writers.WRITERS` (one module
each under ``clrecon/outputs/writers/``; the details below live there too):

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

import json
from pathlib import Path

from clrecon.core import atomic
from clrecon.core.errors import ClreconError, StoreError
from clrecon.outputs.measured_record import run_input_scene

# Run directory -> one volume source: the one reader, clrecon.outputs.rundir (names re-exported)
from clrecon.outputs.rundir import (  # noqa: F401
    METHOD_PREFERENCE,
    REFERENCE_VOLUMES,
    VARIANT_PREFERENCE,
    RunDirectory,
    Source,
    describe_sources,
    normalise_pitch,
    resolve_source,
    run_axes,
    sources,
)
from clrecon.outputs.rundir import open_volume_store as open_run  # noqa: F401 (h5py.File, one-line errors)
from clrecon.outputs.volumes import FORMAT_VERSION, list_recons, open_volumes, read_volume  # noqa: F401
from clrecon.outputs.writers import WRITERS
from clrecon.outputs.writers.base import _file_tag, _spacing, source_stem, target_tag  # noqa: F401 (re-exported)
from clrecon.outputs.writers.dicom import CT_IMAGE_STORAGE, PRIVATE_CREATOR, PRIVATE_GROUP, hu_to_stored  # noqa: F401
from clrecon.outputs.writers.dicom_ct_pd import input_identifiers
from clrecon.outputs.writers.nifti import nifti_affine  # noqa: F401 (re-exported)
from clrecon.scan.patient_frame import position_of_run

#: Export formats, in registry order (``clrecon.outputs.writers``).
FORMATS = WRITERS.names


def _run_identity(run_dir: Path, run: RunDirectory) -> str:
    """A string that identifies one run (seed of its Study and Frame of Reference UIDs)."""
    scene = ""
    if run.has_results:
        try:
            scene = json.dumps(run.results.get("scene", {}), sort_keys=True)
        except StoreError:
            scene = ""
    return f"{run_dir.resolve()}|{scene}"


# ----------------------------------------------------------------------------------------
def export(run_dir, fmt: str, method: str | None = None, pitch=None, variant: str | None = None,
           out=None, keep_identifiers: bool = False, scene=None) -> dict:
    """Export one source of a run, every target; returns the ``index.json`` dictionary.

    ``out`` defaults to ``RUN_DIR/export/<fmt>/<method>[_<pitch>_<variant>]``. Files:
    DICOM ``<out>/<C40_R05>/IM0001.dcm ...``; NIfTI ``<out>/<method>_<C40_R05>.nii.gz``.
    The writer is ``WRITERS[fmt]`` (:class:`clrecon.outputs.writers.base.Writer`). ``scene`` (a scene
    file or :class:`~clrecon.config.scene.Scene`): a measured run's own scene, which ``results.json``
    records without the series' path (patient data): needed to re-export its projections or to copy
    its identifiers (``docs/patient-data.md`` "Patient data").
    """
    if fmt not in WRITERS:
        raise ClreconError(f"--format {fmt!r}: must be one of {', '.join(WRITERS.names)}")
    writer = WRITERS[fmt]()
    run_dir = Path(run_dir)
    f = RunDirectory(run_dir)
    need_input = getattr(writer, "scan_export", False) or keep_identifiers
    given = run_input_scene(f, scene) if need_input else None
    if getattr(writer, "scan_export", False):  # the run's projections, not its volumes (dicom-ct-pd)
        try:
            out = Path(out) if out is not None else run_dir / "export" / fmt
            index = writer.export_scan(f, out, pitch=pitch, keep_identifiers=keep_identifiers, scene=given)
            atomic.write_json(out / "index.json", index, indent=1)
            return index
        finally:
            f.close()
    try:
        if f.has_results and f.results.get("measured"):  # a patient's scan: anonymous unless asked
            writer.patient = (input_identifiers(given) if keep_identifiers
                              else {"PatientName": "ANONYMOUS", "PatientID": "ANONYMOUS"})
        if f.has_results:  # the volumes are in the scanner frame: the patient position maps it onto LPS
            writer.position = position_of_run(f.results)
    except StoreError:
        pass
    try:
        src = f.resolve(method, pitch, variant)
        axes = f.axes
        if out is None:
            out = run_dir / "export" / fmt / source_stem(src)
        out = Path(out)
        out.mkdir(parents=True, exist_ok=True)
        ident = _run_identity(run_dir, f)
        index = {"run_dir": str(run_dir.resolve()), "format": fmt, "source": src.dataset, "method": src.method,
                 "pitch_key": src.pitch_key, "variant": src.variant, "frame": writer.frame, "targets": []}
        nc, nr = len(axes["cardiac_phase"]), len(axes["resp_amplitude"])
        ctx = writer.begin(ident, src, nc * nr)
        for ci, c in enumerate(axes["cardiac_phase"]):
            for ri, a in enumerate(axes["resp_amplitude"]):
                vol = f.read_target(src, ci, ri)
                files = writer.write_target(out, vol, axes, src, ci, ri, ctx)
                index["targets"].append({"cardiac_index": ci, "resp_index": ri, "cardiac_phase": float(c),
                                         "resp_amplitude": float(a), "tag": target_tag(c, a),
                                         "files": [str(Path(p).relative_to(out)) for p in files]})
        index.update(writer.finish(ctx))
        atomic.write_json(out / "index.json", index, indent=1)
        index["out"] = str(out)
        return index
    finally:
        f.close()
