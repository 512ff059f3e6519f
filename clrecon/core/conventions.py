"""Units, coordinate frames and scanner conventions, written once for the whole package.

Units: millimetres, seconds, radians; attenuation mu in 1/mm.

World frame = DICOM patient frame (LPS): +x towards the patient's left, +y posterior,
+z superior (head). Volumes are stored as ``volume[z, y, x]`` (x fastest) so that an
axial slice shown with row 0 at the top has anterior at the top, as radiologists expect.
Voxel centres sit symmetrically around the isocentre in x and y:
``x_i = (i - (nx - 1) / 2) * dx``.

Gantry (docs/conventions.md "Gantry and source"): view k (0-based, over the whole helical scan) has
    beta_k = beta0 + 2*pi*k / N_views
    t_k    = k * T_rot / N_views
    z_k    = z_start + h * k / N_views        (h = table feed per rotation)
The source sits at ``(R cos beta, R sin beta, z_k)`` with ``R = SID``. The flat detector is
perpendicular to the central ray at distance SDD from the source; its centre is
``((R - SDD) cos beta, (R - SDD) sin beta, z_k)``. Detector columns run along
``e_u = (-sin beta, cos beta, 0)``, rows along ``e_v = (0, 0, 1)``. A projection is stored
as ``proj[row, col]`` (column fastest); cell centres are
``u_j = (j - (n_cols - 1)/2) * col_pitch``, ``v_i = (i - (n_rows - 1)/2) * row_pitch``.

A point P projects onto the detector at
    U = R - (x cos beta + y sin beta)                 (distance from the source along the central ray)
    u = SDD * (-x sin beta + y cos beta) / U
    v = SDD * (z - z_k) / U
"""

from __future__ import annotations

import numpy as np

#: Linear attenuation of water at about 70 keV effective energy, 1/mm.
MU_WATER_PER_MM = 0.0193
#: Water attenuations a scene may give (1/mm): water from 150 keV (0.015) to 20 keV (0.081), NIST XCOM,
#: with a margin; outside it a value is a unit slip (1/cm, 1/m) or not a number of this world.
MU_WATER_RANGE_PER_MM = (0.01, 0.1)
MU_WATER_WHY = "water at 150-20 keV: 0.015-0.081 /mm (NIST XCOM), at 120 kVp ~0.019"


def hu_to_mu(hu, mu_water: float = MU_WATER_PER_MM):
    """Hounsfield units -> linear attenuation (1/mm): mu = mu_w * (1 + HU/1000)."""
    return mu_water * (1.0 + np.asarray(hu, dtype=np.float64) / 1000.0)


def mu_to_hu(mu, mu_water: float = MU_WATER_PER_MM):
    """Linear attenuation (1/mm) -> Hounsfield units: HU = 1000 (mu - mu_w) / mu_w."""
    return 1000.0 * (np.asarray(mu, dtype=np.float64) - mu_water) / mu_water


def collimation_iso_mm(n_rows: int, row_pitch_mm: float, sid_mm: float, sdd_mm: float) -> float:
    """Total collimation at the isocentre, W = N_rows * row_pitch * SID / SDD (mm)."""
    return n_rows * row_pitch_mm * sid_mm / sdd_mm


def detector_coords(n: int, pitch_mm: float, offset_cells: float = 0.0) -> np.ndarray:
    """Centres of ``n`` detector cells (mm), symmetric about the central ray, shape (n,)."""
    return (np.arange(n, dtype=np.float64) - (n - 1) / 2.0 + offset_cells) * pitch_mm


def voxel_coords(n: int, spacing_mm: float, centre_mm: float = 0.0) -> np.ndarray:
    """Voxel-centre coordinates (mm) of an axis of ``n`` voxels centred on ``centre_mm``."""
    return centre_mm + (np.arange(n, dtype=np.float64) - (n - 1) / 2.0) * spacing_mm


def source_positions(angle_rad, source_z_mm, sid_mm: float) -> np.ndarray:
    """Source positions ``(R cos b, R sin b, z)`` in mm, shape (n, 3)."""
    b = np.asarray(angle_rad, dtype=np.float64)
    return np.stack([sid_mm * np.cos(b), sid_mm * np.sin(b), np.asarray(source_z_mm, np.float64)], axis=-1)


def detector_frames(angle_rad, source_z_mm, sid_mm: float, sdd_mm: float):
    """Per-view detector frame, each of shape (n, 3), in mm.

    Returns ``(source, detector_centre, e_u, e_v)``: the canonical vector form every
    projector and test uses (column direction ``e_u``, row direction ``e_v``).
    """
    b = np.asarray(angle_rad, dtype=np.float64)
    z = np.asarray(source_z_mm, dtype=np.float64)
    src = source_positions(b, z, sid_mm)
    r = sid_mm - sdd_mm
    det = np.stack([r * np.cos(b), r * np.sin(b), z], axis=-1)
    e_u = np.stack([-np.sin(b), np.cos(b), np.zeros_like(b)], axis=-1)
    e_v = np.zeros_like(e_u)
    e_v[..., 2] = 1.0
    return src, det, e_u, e_v


def circular_difference(c, c_ref):
    """Signed circular difference of cardiac phases, in [-0.5, 0.5).

    ``x - floor(x)`` with x = c - c_ref + 0.5, the same float64 values as ``x % 1.0`` (NumPy's
    remainder: an exact fmod, plus 1.0 for a negative one, one rounding either way; an exact
    +0.0 for whole x; NaN for NaN and inf) for every finite x below 2**52 in magnitude
    (tests/core/test_conventions.py), and 7x faster: the planning calls it on every candidate of
    every slice (1.3 s of demo's 8.5 s planning of pitch 0.02 with ``%``).
    """
    d = np.asarray(c, dtype=np.float64) - np.asarray(c_ref, dtype=np.float64) + 0.5
    return d - np.floor(d) - 0.5
