"""A water cylinder with an off-centre bone rod and a bone sphere: the measured-scan convention fixtures.

The engine's own simulator scans it (a static NIfTI voxel phantom, ``docs/voxel-phantoms.md``) on a
cylindrical detector with a quarter-detector offset, as the issue-35 reference scan; the DICOM-CT-PD
writer then writes the scan in each convention and the measured reconstruction must put the rod
where it is (``tests/scan/test_measured_conventions.py``). Lengths mm, LPS.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

#: true centre (x, y) of the rod, mm (LPS: +x patient left, +y posterior)
ROD_XY = (40.0, 24.0)
ROD_RADIUS_MM = 8.0
ROD_HU = 1000.0
WATER_RADIUS_MM = 95.0
#: a sphere (z-structure for the helix row check) at (x, y, z) mm
SPHERE_XYZ = (-35.0, -30.0, 0.0)
SPHERE_RADIUS_MM = 9.0
VOXEL_MM = 1.0


def write_phantom(folder: Path, symmetric: bool = False) -> Path:
    """NIfTI frame + frames table; ``symmetric``: the water cylinder alone (mirror-symmetric)."""
    import nibabel as nib

    folder.mkdir(parents=True, exist_ok=True)
    n_xy, n_z = 220, 64
    ax = (np.arange(n_xy) - (n_xy - 1) / 2.0) * VOXEL_MM
    az = (np.arange(n_z) - (n_z - 1) / 2.0) * VOXEL_MM
    z, y, x = np.meshgrid(az, ax, ax, indexing="ij")
    hu = np.full(z.shape, -1000.0, np.float32)
    hu[(x ** 2 + y ** 2 <= WATER_RADIUS_MM ** 2) & (np.abs(z) <= 30.0)] = 0.0
    if not symmetric:
        hu[(x - ROD_XY[0]) ** 2 + (y - ROD_XY[1]) ** 2 <= ROD_RADIUS_MM ** 2] = ROD_HU
        sx, sy, sz = SPHERE_XYZ
        hu[(x - sx) ** 2 + (y - sy) ** 2 + (z - sz) ** 2 <= SPHERE_RADIUS_MM ** 2] = ROD_HU
    # LPS grid -> RAS affine (x and y negated)
    lps = np.diag([VOXEL_MM, VOXEL_MM, VOXEL_MM, 1.0])
    lps[:3, 3] = [ax[0], ax[0], az[0]]
    affine = np.diag([-1.0, -1.0, 1.0, 1.0]) @ lps
    nib.save(nib.Nifti1Image(hu.transpose(2, 1, 0).copy(), affine), str(folder / "rod.nii"))
    (folder / "frames.toml").write_text('[[frame]]\nfile = "rod.nii"\ncardiac_phase = 0.0\nresp_amplitude = 0.5\n')
    return folder / "frames.toml"


def scene_toml(frames: Path, rotation: str = "increasing", table: str = "increasing", detector: str = "cylindrical",
               ffs: str = "none") -> str:
    """A static scan of the phantom: 160 x 8 cells (a quarter-channel offset when cylindrical), 120 views per
    rotation, 3 rotations."""
    det = ('detector = "cylindrical"\ncentral_col = 79.75\n' if detector == "cylindrical" else "")
    if ffs != "none":
        det += f'flying_focal_spot = "{ffs}"\nffs_angle_rad = 0.0004\nffs_z_mm = 0.3\n'
    return f"""name = "rod"
description = "water cylinder, bone rod at (40, 24) mm, bone sphere"
[scanner]
n_cols = 160
col_pitch_mm = 2.965
n_rows = 8
row_pitch_mm = 6.4
views_per_rotation = 120
{det}
[scan]
pitches = [0.5]
n_projections = 360
rotation = "{rotation}"
table_direction = "{table}"
[phantom]
kind = "voxel"
frames = "{frames}"
values = "hu"
cardiac_motion = false
respiratory_motion = false
[noise]
enabled = false
[recon]
nx = 96
ny = 96
voxel_mm = 2.5
nz = 2
slice_mm = 4.0
methods = ["nearest"]
"""


def rod_position_and_water(vol_yx: np.ndarray, x_mm: np.ndarray, y_mm: np.ndarray) -> dict:
    """Rod centre (x, y) mm (HU-weighted centroid of the rod's bone above 500 HU near it, after water
    subtraction), the rod's error from ROD_XY (mm), water mean HU (ring 20..60 mm from the centre away
    from rod and sphere) and the core HU of the rod (within 4 mm)."""
    yy, xx = np.meshgrid(y_mm, x_mm, indexing="ij")
    near = (xx - ROD_XY[0]) ** 2 + (yy - ROD_XY[1]) ** 2 <= (2.0 * ROD_RADIUS_MM) ** 2
    w = np.where(near, np.clip(vol_yx, 0.0, None), 0.0)
    cx, cy = float((w * xx).sum() / w.sum()), float((w * yy).sum() / w.sum())
    r = np.hypot(xx, yy)
    far = ((np.hypot(xx - ROD_XY[0], yy - ROD_XY[1]) > 25) & (np.hypot(xx - SPHERE_XYZ[0], yy - SPHERE_XYZ[1]) > 25)
           & (r >= 10) & (r <= 60))
    core = np.hypot(xx - ROD_XY[0], yy - ROD_XY[1]) <= 4.0
    # the mirror image's rod, for the report of a wrong reading
    mirror = (xx + ROD_XY[0]) ** 2 + (yy - ROD_XY[1]) ** 2 <= 16.0
    return {"rod_xy_mm": (cx, cy), "rod_error_mm": float(np.hypot(cx - ROD_XY[0], cy - ROD_XY[1])),
            "water_hu": float(vol_yx[far].mean()), "rod_core_hu": float(vol_yx[core].mean()),
            "mirror_site_hu": float(vol_yx[mirror].mean())}
