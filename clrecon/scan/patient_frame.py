"""From the scanner's frame to the patient's: the patient position and the image's LPS axes.

clrecon reconstructs in the scanner (gantry) frame: x, y in the axial plane, z along the table
(for a measured scan, the DICOM-CT-PD frame of ``docs/measured-conventions.md``; for a simulated one,
the phantom's frame). The frame is the patient's LPS frame for a patient lying head first and
supine (HFS), as a CT scanner's image matrix is; for the other positions the patient lies
rotated in it, and the patient's LPS axes are the scanner axes with signs
(``docs/measured-conventions.md`` "Patient position and the image frame"):

| position | LPS x (left) | LPS y (posterior) | LPS z (superior) | ImageOrientationPatient |
|---|---|---|---|---|
| HFS | +x | +y | +z | 1, 0, 0, 0, 1, 0 |
| HFP | -x | -y | +z | -1, 0, 0, 0, -1, 0 |
| FFS | -x | +y | -z | -1, 0, 0, 0, 1, 0 |
| FFP | +x | -y | -z | 1, 0, 0, 0, -1, 0 |

Head first / feet first turns the patient by 180 degrees about the vertical axis (y): left and
superior swap sign; supine / prone by 180 degrees about the table axis (z): left and posterior
swap sign. Both are rotations, so the image keeps its handedness: the sign of the determinant
of ``diag(signs)`` is +1 for every position (``tests/scan/test_measured_conventions.py`` checks the
table and the exported series). Decubitus positions are refused (not modelled).
"""

from __future__ import annotations

import numpy as np

from clrecon.core.errors import InputError

#: patient position -> signs (sx, sy, sz) with LPS = (sx x, sy y, sz z) of the scanner frame
LPS_SIGNS = {"HFS": (1, 1, 1), "HFP": (-1, -1, 1), "FFS": (-1, 1, -1), "FFP": (1, -1, -1)}


def lps_signs(position: str, where: str = "scan.patient_position") -> tuple[int, int, int]:
    """(sx, sy, sz) of a patient position; one-line InputError for one clrecon does not model."""
    p = str(position or "HFS").upper()
    if p not in LPS_SIGNS:
        raise InputError(f"{where} = {position!r}; expected one of {', '.join(LPS_SIGNS)} (a decubitus position is "
                         f"not modelled: the image axes would not be the scanner's)")
    return LPS_SIGNS[p]


def image_orientation(position: str) -> list[float]:
    """DICOM ImageOrientationPatient of an axial image whose columns run along +x and rows along +y of the
    scanner frame: the row direction cosine (sx, 0, 0), then the column direction cosine (0, sy, 0)."""
    sx, sy, _ = lps_signs(position)
    return [float(sx), 0.0, 0.0, 0.0, float(sy), 0.0]


def to_lps(position: str, xyz) -> np.ndarray:
    """Scanner-frame point(s) (..., 3) mm -> patient LPS (..., 3) mm."""
    return np.asarray(xyz, dtype=np.float64) * np.asarray(lps_signs(position), dtype=np.float64)


def position_of_run(results: dict) -> str:
    """The patient position a run's volumes are in: the measured series', HFS for a simulated scan."""
    scan = ((results or {}).get("scene") or {}).get("scan") or {}
    return str(scan.get("patient_position") or "HFS").upper()
