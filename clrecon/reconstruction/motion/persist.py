"""A fitted motion model as a unit file (atomic, checksummed: :mod:`clrecon.core.units`), so that a
resumed run loads it instead of registering again."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from clrecon.core import units
from clrecon.reconstruction.motion.model import FieldGrid, MotionBasis, MotionModel


def _hits(folder: Path, stem: str) -> list[Path]:
    return sorted(folder.glob(f"{stem}.*{units.SUFFIX}")) if folder.is_dir() else []


def save_model(folder: Path, stem: str, model: MotionModel, info: dict, fault: str) -> Path:
    """Write ``model`` (its basis fields, grid and reference) and ``info`` (plain JSON) as unit ``stem``
    in ``folder``; ``fault`` names its :mod:`clrecon.core.faults` point. Returns the file's path."""
    g = model.grid
    meta = {"grid": {"nx": g.nx, "ny": g.ny, "nz": g.nz, "voxel_mm": g.voxel_mm, "z0_mm": g.z0_mm, "dz_mm": g.dz_mm},
            "reference": list(model.reference), "info": info}
    return units.write_unit(folder, stem, {"fields": np.ascontiguousarray(model.fields)}, meta, fault)


def load_model(folder: Path, stem: str, basis: MotionBasis) -> tuple[MotionModel, dict] | None:
    """(model, info) of unit ``stem`` in ``folder`` with ``basis`` (the run's: it is not stored), or
    None when there is none; a damaged file is deleted (the model is then registered again)."""
    for p in _hits(Path(folder), stem):
        try:
            arrays, meta = units.read_unit(p)
        except (OSError, ValueError, KeyError, EOFError):
            p.unlink(missing_ok=True)
            continue
        model = MotionModel(basis=basis, grid=FieldGrid(**meta["grid"]), fields=arrays["fields"],
                            reference=tuple(meta["reference"]))
        return model, meta["info"]
    return None
