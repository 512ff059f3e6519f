"""NIfTI writer: one ``.nii.gz`` per target, ``<out>/<stem>_<C40_R05>.nii.gz``.

Array indexed ``[i, j, k] = [x, y, z]``, float32 HU, with qform = sform (code 1, scanner)
mapping voxel indices to **RAS** mm: NIfTI's RAS is LPS with x and y negated, so the affine is
``diag(-dx, -dy, dz)`` with origin ``(-x0, -y0, z0)`` for a patient head first supine; another
patient position multiplies the axes by its LPS signs (:mod:`clrecon.scan.patient_frame`).
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from clrecon.core import atomic
from clrecon.outputs.writers import WRITERS
from clrecon.outputs.writers.base import (
    Writer,
    _file_tag,
    _spacing,
    source_stem,
    target_tag,
)
from clrecon.scan.patient_frame import lps_signs

if TYPE_CHECKING:
    from clrecon.outputs.rundir import Source


@WRITERS.register("nifti")
class NiftiWriter(Writer):
    name = "nifti"
    label = "NIfTI"
    frame = "RAS (NIfTI; LPS with x and y negated)"
    requires = "nibabel"

    #: patient position of the run's volumes (export() sets it; docs/measured-conventions.md "Patient position")
    position: str = "HFS"

    def begin(self, ident, src, n_targets):
        return self

    def write_target(self, out, vol, axes, src, ci, ri, ctx):
        return _write_nifti_target(out, vol, axes, src, ci, ri, ctx)


def nifti_affine(axes: dict, position: str = "HFS") -> np.ndarray:
    """4x4 voxel-index (i=x, j=y, k=z) -> RAS mm affine of a run's grid (LPS axes negated in x, y).

    The grid is the scanner frame; ``position`` (the patient position, :mod:`clrecon.scan.patient_frame`)
    gives the signs that turn it into the patient's LPS (all + for HFS)."""
    x, y, z = axes["x_mm"], axes["y_mm"], axes["z_mm"]
    dx, dy = _spacing(x, "x_mm"), _spacing(y, "y_mm")
    dz = _spacing(z, "z_mm") if z.size > 1 else dx
    sx, sy, sz = lps_signs(position)
    aff = np.diag([-sx * dx, -sy * dy, sz * dz, 1.0])
    aff[:3, 3] = [-sx * x[0], -sy * y[0], sz * z[0]]
    return aff


def _write_nifti_target(out: Path, vol: np.ndarray, axes: dict, src: Source, ci: int, ri: int,
                        ctx) -> list[Path]:
    nib = NiftiWriter().require()
    c = float(axes["cardiac_phase"][ci])
    a = float(axes["resp_amplitude"][ri])
    data = np.ascontiguousarray(np.transpose(vol, (2, 1, 0)), np.float32)  # [z,y,x] -> [x,y,z]
    aff = nifti_affine(axes, getattr(ctx, "position", None) or "HFS")
    img = nib.Nifti1Image(data, aff)
    img.header.set_qform(aff, code=1)
    img.header.set_sform(aff, code=1)
    img.header.set_xyzt_units("mm", "sec")
    img.header["descrip"] = f"5DCT {src.method} {target_tag(c, a)}".encode()[:79]
    path = out / f"{source_stem(src)}_{_file_tag(c, a)}.nii.gz"
    with atomic.replacing(path, keep_suffix=".nii.gz") as tmp:  # whole or not at all
        nib.save(img, tmp)
    return [path]
