"""Detector models: where the cells are, how SSRB rows map onto them, which region they see.

Every stage that needs detector geometry asks the scene's detector model (``scanner.detector``,
registry :data:`DETECTORS`) rather than writing the formulas again: the projector and the ground
truth take the cell centres and the per-view frames, SSRB takes the row coordinate of its
oblique ray and the slice window, the scene check takes the largest covering pitch, FBP takes the
field-of-view radius. A cylindrical detector is one new class here plus its kernel variants
(``docs/extending.md``).

Two models: the flat panel (``"flat"``, the paper's TIGRE geometry) and the cylindrical arc of
clinical scanners (``"cylindrical"``, focused on the focal centre). Conventions
(``docs/conventions.md`` "Flat detector", "Cylindrical detector"): lengths in mm, columns along ``e_u`` (index
increasing with u, and with the fan angle gamma for the arc), rows along ``e_v = +z``.

Both give the projector their cells as *flat-equivalent* coordinates (:meth:`ray_cells`): the
cell at column c, row coordinate v lies on the ray from the source through the point
``det_centre + u_eq[c] e_u + (v - v_off) v_scale[c] e_v`` of the plane at distance SDD from the
source, perpendicular to the central ray. A line integral over the whole line does not depend on
where along the ray the cell sits, so one projector kernel serves both models (its ``CURVED``
variant reads the per-column ``v_scale``).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np
from numpy.typing import ArrayLike

from clrecon.core.conventions import collimation_iso_mm, detector_coords, detector_frames
from clrecon.core.registry import Registry

#: Detector models by the name a scene gives in ``scanner.detector``.
DETECTORS: Registry[type] = Registry("detector model")


class DetectorModel(Protocol):
    """What every stage asks of a detector model (:class:`FlatDetector` is the one today)."""

    name: str
    n_cols: int
    n_rows: int

    def u_mm(self) -> np.ndarray: ...
    def v_mm(self) -> np.ndarray: ...
    def frames(self, angle_rad: ArrayLike, source_z_mm: ArrayLike
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]: ...
    @property
    def collimation_iso_mm(self) -> float: ...
    @property
    def fov_radius_mm(self) -> float: ...
    def ssrb_v_mm(self, u_mm: ArrayLike, dz_mm: ArrayLike) -> np.ndarray: ...
    def object_half_width_u_mm(self, object_radius_mm: float) -> float: ...
    def slice_window_mm(self, object_radius_mm: float) -> float: ...
    def max_covering_pitch(self, object_radius_mm: float) -> float: ...
    def ray_cells(self, shift_mm: ArrayLike = (0.0, 0.0, 0.0)
                  ) -> tuple[np.ndarray, np.ndarray | None, float]: ...


#: Largest error (rad) of the kernels' atan polynomials (float64 fit): that of float32 atan near
#: 0.5 rad (the kernels evaluate it in float32 anyway); 1e-7 rad is < 1e-4 of a column.
ATAN_MAX_ERR = 1e-7


@functools.lru_cache(maxsize=64)
def atan_coefficients(t_max: float) -> np.ndarray:
    """Coefficients (n,) float64 of atan(t) ~ t sum_k a_k t^(2k) on [0, t_max] (least squares on 4000
    points), the fewest n <= 9 whose maximum error on a fine grid is <= :data:`ATAN_MAX_ERR` rad.
    ``t_max <= 1`` (fans of up to +-45 degrees). Used by the cylindrical kernels (``-D ATAN_C0..``),
    since PoCL does not inline the ``atan`` builtin (docs/fbp.md "Equiangular FBP")."""
    t = np.linspace(1e-6, t_max, 4000)
    tt = np.linspace(0.0, t_max, 20001)
    for n in range(3, 10):
        a, *_ = np.linalg.lstsq(np.stack([t ** (2 * k + 1) for k in range(n)], 1), np.arctan(t), rcond=None)
        if np.abs(np.stack([tt ** (2 * k + 1) for k in range(n)], 1) @ a - np.arctan(tt)).max() <= ATAN_MAX_ERR:
            break
    return a


def atan_defines(t_max: float, scale: float = 1.0) -> dict:
    """``-D`` defines ``ATAN_TERMS``, ``ATAN_C0..`` of :func:`atan_coefficients` times ``scale``."""
    a = atan_coefficients(float(t_max)) * scale
    return {"ATAN_TERMS": len(a), **{f"ATAN_C{k}": float(np.float32(c)) for k, c in enumerate(a)}}


def flat_fov_radius_mm(sid_mm: float, sdd_mm: float, half_width_mm: float) -> float:
    """Radius (mm) at the isocentre of the circle every column of a flat detector sees.

    ``SID sin(atan(half_width / SDD))`` for a detector of half width ``half_width_mm``.
    """
    return sid_mm * math.sin(math.atan2(half_width_mm, sdd_mm))


@DETECTORS.register("flat")
@dataclass(frozen=True)
class FlatDetector:
    """Flat-panel detector perpendicular to the central ray at distance SDD from the source.

    Lengths in mm. Built from a scanner config with :meth:`from_scanner` (any object with
    ``sid_mm, sdd_mm, n_cols, n_rows, col_pitch_mm, row_pitch_mm``).
    """

    sid_mm: float
    sdd_mm: float
    n_cols: int
    n_rows: int
    col_pitch_mm: float
    row_pitch_mm: float

    name = "flat"

    @classmethod
    def from_scanner(cls, scanner: Any) -> FlatDetector:
        return cls(sid_mm=scanner.sid_mm, sdd_mm=scanner.sdd_mm, n_cols=scanner.n_cols, n_rows=scanner.n_rows,
                   col_pitch_mm=scanner.col_pitch_mm, row_pitch_mm=scanner.row_pitch_mm)

    # -- cells and frames -------------------------------------------------------------
    def u_mm(self) -> np.ndarray:
        """Column centres (n_cols,) mm."""
        return detector_coords(self.n_cols, self.col_pitch_mm)

    def v_mm(self) -> np.ndarray:
        """Row centres (n_rows,) mm."""
        return detector_coords(self.n_rows, self.row_pitch_mm)

    def frames(self, angle_rad: ArrayLike, source_z_mm: ArrayLike
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Per-view ``(source, detector_centre, e_u, e_v)``, each (n, 3) mm."""
        return detector_frames(angle_rad, source_z_mm, self.sid_mm, self.sdd_mm)

    def ray_cells(self, shift_mm: ArrayLike = (0.0, 0.0, 0.0)) -> tuple[np.ndarray, np.ndarray | None, float]:
        """Flat-equivalent cells ``(u_eq (C,), v_scale, v_off)``: the cells themselves, ``v_scale = None``.

        The flat detector takes no focal-spot shift (scene check); ``shift_mm`` must be zero.
        """
        if np.any(np.asarray(shift_mm, np.float64) != 0.0):
            raise ValueError("the flat detector has no flying focal spot: shift_mm must be (0, 0, 0)")
        return self.u_mm(), None, 0.0

    @property
    def collimation_iso_mm(self) -> float:
        """W = N_rows * row_pitch * SID / SDD (mm)."""
        return collimation_iso_mm(self.n_rows, self.row_pitch_mm, self.sid_mm, self.sdd_mm)

    @property
    def fov_radius_mm(self) -> float:
        """Radius at the isocentre of the circle every column sees (mm)."""
        return flat_fov_radius_mm(self.sid_mm, self.sdd_mm, self.n_cols * self.col_pitch_mm / 2.0)

    # -- single-slice rebinning -------------------------------------------------------
    def ssrb_v_mm(self, u_mm: ArrayLike, dz_mm: ArrayLike) -> np.ndarray:
        """Row coordinate v(u) (mm) of the SSRB ray for column ``u_mm`` and ``dz = z_slice - z_k``.

        The fan ray of column u passes closest to the axis at in-plane distance SID cos(gamma)
        from the source (gamma = atan(u / SDD)); the oblique ray through that point at height z
        hits the detector at ``v = (u^2 + SDD^2) / (SID SDD) * dz`` (Noo et al., PMB 44:561, 1999).
        """
        u = np.asarray(u_mm, dtype=np.float64)
        dz = np.asarray(dz_mm, dtype=np.float64)
        return (u * u + self.sdd_mm ** 2) / (self.sid_mm * self.sdd_mm) * dz

    def object_half_width_u_mm(self, object_radius_mm: float) -> float:
        """Largest |u| (mm) of a column whose fan ray passes within ``object_radius_mm`` of the axis.

        The ray of column u passes the axis at distance SID |u| / sqrt(u^2 + SDD^2); it is within
        r for |u| <= r SDD / sqrt(SID^2 - r^2). Capped at the outermost column centre, since no
        column beyond it exists. The bound is continuous (not snapped to a column centre), which
        makes the window at most one column conservative.
        """
        u_outer = 0.5 * (self.n_cols - 1) * self.col_pitch_mm
        r = float(object_radius_mm)
        if r >= self.sid_mm:
            return u_outer
        return min(u_outer, r * self.sdd_mm / math.sqrt(self.sid_mm ** 2 - r * r))

    def slice_window_mm(self, object_radius_mm: float) -> float:
        """Largest |z - z_k| (mm) for which SSRB needs no row outside the detector.

        v(u) must stay inside the outer row centres, |v| <= (n_rows - 1)/2 * row_pitch, for all
        columns whose rays pass within ``object_radius_mm`` (finite, > 0) of the rotation axis;
        |v(u)| grows with |u|, so the binding column is the outermost one that sees the object.
        Zero for a single-row detector (only the source in the slice plane itself is exact).
        """
        if not (math.isfinite(object_radius_mm) and object_radius_mm > 0):
            raise ValueError(f"object_radius_mm = {object_radius_mm!r}: must be a finite number > 0")
        u_max = self.object_half_width_u_mm(object_radius_mm)
        v_max = 0.5 * (self.n_rows - 1) * self.row_pitch_mm
        return v_max * self.sid_mm * self.sdd_mm / (u_max * u_max + self.sdd_mm ** 2)

    def max_covering_pitch(self, object_radius_mm: float) -> float:
        """Largest helical pitch for which every (slice, view) in the scanned range has a candidate.

        The sources of one view advance by h = pitch * W per rotation, so a slice between two
        of them is up to h / 2 from the nearer one; it has an SSRB candidate of that view when
        h / 2 <= :meth:`slice_window_mm`. Hence ``pitch <= 2 * window / W`` (0 for one row).
        """
        return 2.0 * self.slice_window_mm(object_radius_mm) / self.collimation_iso_mm


#: Flying-focal-spot modes (``scanner.flying_focal_spot``).
FFS_MODES = ("none", "phi", "z", "phi+z")


def ffs_cycle(mode: str) -> int:
    """Views per focal-spot cycle: 1 (none), 2 (phi or z), 4 (phi+z)."""
    return {"none": 1, "phi": 2, "z": 2, "phi+z": 4}[mode]


def ffs_states(mode: str, angle_rad: float, radial_mm: float, z_mm: float) -> np.ndarray:
    """Focal-spot shifts of each state of the cycle, (cycle, 3) float64: (dphi rad, drho mm, dz mm).

    Projection k is in state ``k % cycle``. Signs alternate from view to view starting with
    the minus state: phi (and z): ``-, +``; phi+z: ``(-phi, -z), (+phi, -z), (-phi, +z), (+phi, +z)``.
    The radial shift goes with the angular one (``+radial_mm`` with ``+angle_rad``).
    """
    n = ffs_cycle(mode)
    s_phi = {"none": [0.0], "phi": [-1.0, 1.0], "z": [0.0, 0.0], "phi+z": [-1.0, 1.0, -1.0, 1.0]}[mode]
    s_z = {"none": [0.0], "phi": [0.0, 0.0], "z": [-1.0, 1.0], "phi+z": [-1.0, -1.0, 1.0, 1.0]}[mode]
    out = np.zeros((n, 3))
    out[:, 0] = np.asarray(s_phi) * angle_rad
    out[:, 1] = np.asarray(s_phi) * radial_mm
    out[:, 2] = np.asarray(s_z) * z_mm
    return out


def spot_shift_in_frame(shift, sid_mm: float) -> np.ndarray:
    """(dphi, drho, dz) (..., 3) -> the spot's offset ``(a, b, c)`` from the focal centre (..., 3) mm.

    ``a`` along the central ray n (source -> isocentre), ``b`` along e_u (the direction of
    increasing gantry angle), ``c`` along e_v = +z: the spot at gantry angle beta + dphi and
    radius SID + drho gives ``a = SID - (SID + drho) cos dphi``, ``b = (SID + drho) sin dphi``, ``c = dz``.
    """
    sh = np.asarray(shift, np.float64)
    rho = sid_mm + sh[..., 1]
    return np.stack([sid_mm - rho * np.cos(sh[..., 0]), rho * np.sin(sh[..., 0]), sh[..., 2]], axis=-1)


def middle(n: int, central: float) -> float:
    """The central element's 0-based fractional index: ``central``, or the middle (n - 1) / 2 for -1."""
    return 0.5 * (n - 1) if central == -1 else float(central)


@DETECTORS.register("cylindrical")
@dataclass(frozen=True)
class CylindricalDetector:
    """Cylindrical (equiangular) detector: an arc of radius SDD centred on the focal centre.

    Column c sits at fan angle ``gamma_c = (c - central_col) * col_pitch / SDD`` (rad, positive
    towards ``+e_u``), i.e. at the point ``s + SDD (cos gamma n + sin gamma e_u)`` with ``n`` the
    unit central ray (source -> isocentre); ``col_pitch_mm`` is the arc length between column
    centres at the detector. Row r sits at axial height ``v_r = (r - central_row) * row_pitch``
    above the focal centre (mm). ``central_col`` / ``central_row`` are 0-based fractional cell
    indices of the element the central ray hits (the clinical quarter offset is
    ``(n_cols - 1) / 2 + 0.25``). :meth:`u_mm` is the arc coordinate ``SDD * gamma`` (mm).
    """

    sid_mm: float
    sdd_mm: float
    n_cols: int
    n_rows: int
    col_pitch_mm: float
    row_pitch_mm: float
    central_col: float
    central_row: float
    spot_inplane_mm: float = 0.0
    spot_z_mm: float = 0.0

    name = "cylindrical"

    @classmethod
    def from_scanner(cls, scanner: Any) -> CylindricalDetector:
        """From a scanner config; its flying focal spot (if any) sets the largest spot offsets
        ``spot_inplane_mm`` (in the gantry plane) and ``spot_z_mm`` (axial), which narrow the FOV
        and the SSRB slice window."""
        shifts = getattr(scanner, "ffs_shifts", np.zeros((1, 3)))
        frame = spot_shift_in_frame(shifts, scanner.sid_mm)
        return cls(sid_mm=scanner.sid_mm, sdd_mm=scanner.sdd_mm, n_cols=scanner.n_cols, n_rows=scanner.n_rows,
                   col_pitch_mm=scanner.col_pitch_mm, row_pitch_mm=scanner.row_pitch_mm,
                   central_col=middle(scanner.n_cols, getattr(scanner, "central_col", -1.0)),
                   central_row=middle(scanner.n_rows, getattr(scanner, "central_row", -1.0)),
                   spot_inplane_mm=float(np.hypot(frame[:, 0], frame[:, 1]).max()),
                   spot_z_mm=float(np.abs(frame[:, 2]).max()))

    # -- cells and frames -------------------------------------------------------------
    @property
    def delta_gamma_rad(self) -> float:
        """Angle between neighbouring columns, col_pitch / SDD (rad)."""
        return self.col_pitch_mm / self.sdd_mm

    def gamma_rad(self) -> np.ndarray:
        """Fan angle of each column centre (n_cols,) rad, float64."""
        return (np.arange(self.n_cols, dtype=np.float64) - self.central_col) * self.delta_gamma_rad

    def u_mm(self) -> np.ndarray:
        """Arc coordinate of the column centres, SDD * gamma (n_cols,) mm."""
        return self.sdd_mm * self.gamma_rad()

    def v_mm(self) -> np.ndarray:
        """Row centres (n_rows,) mm, relative to the central row."""
        return (np.arange(self.n_rows, dtype=np.float64) - self.central_row) * self.row_pitch_mm

    def frames(self, angle_rad: ArrayLike, source_z_mm: ArrayLike
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Per-view ``(focal centre, apex of the arc, e_u, e_v)``, each (n, 3) mm.

        The arc's apex (gamma = 0, v = 0) is where the flat detector's centre is, and e_u, e_v are
        the flat detector's, so the canonical frames serve both (:func:`detector_frames`).
        """
        return detector_frames(angle_rad, source_z_mm, self.sid_mm, self.sdd_mm)

    def ray_cells(self, shift_mm: ArrayLike = (0.0, 0.0, 0.0)) -> tuple[np.ndarray, np.ndarray, float]:
        """Flat-equivalent cells of the arc seen from a focal spot shifted by ``shift_mm``.

        ``shift_mm = (a, b, c)``: the focal spot at ``s + a n + b e_u + c e_v`` (mm, in the frame
        of the focal centre s; the arc stays centred on s). The ray from the spot through cell
        (gamma, v) has direction ``(SDD cos g - a) n + (SDD sin g - b) e_u + (v - c) e_v``, which
        meets the plane at distance SDD from the spot (perpendicular to n) at
        ``u_eq = SDD (SDD sin g - b) / (SDD cos g - a)`` and ``(v - c) * v_scale``,
        ``v_scale = SDD / (SDD cos g - a)``. Returns ``(u_eq (C,), v_scale (C,), c)`` float64;
        the caller puts the plane's centre at ``spot + SDD n``.
        """
        a, b, c = (float(x) for x in np.asarray(shift_mm, np.float64))
        g = self.gamma_rad()
        den = self.sdd_mm * np.cos(g) - a
        return self.sdd_mm * (self.sdd_mm * np.sin(g) - b) / den, self.sdd_mm / den, c

    @property
    def collimation_iso_mm(self) -> float:
        """W = N_rows * row_pitch * SID / SDD (mm)."""
        return collimation_iso_mm(self.n_rows, self.row_pitch_mm, self.sid_mm, self.sdd_mm)

    def edge_gamma_rad(self) -> tuple[float, float]:
        """Fan angles (rad) of the outer column *edges*, (lowest, highest)."""
        return ((-0.5 - self.central_col) * self.delta_gamma_rad,
                (self.n_cols - 0.5 - self.central_col) * self.delta_gamma_rad)

    @property
    def fov_radius_mm(self) -> float:
        """Radius at the isocentre of the circle every column edge sees, SID sin(min |gamma_edge|) (mm).

        With an off-centre central element the shorter side of the fan binds. A flying focal spot
        (offset d in the gantry plane) moves each edge ray by at most d at the isocentre: the
        circle shrinks to ``(SID - d) sin(gamma) - d`` (the same rule as
        :attr:`clrecon.reconstruction.fbp.FanBeamGeometry.fov_radius_mm`).
        """
        lo, hi = self.edge_gamma_rad()
        g = min(-lo, hi, 0.5 * math.pi)
        d = self.spot_inplane_mm
        return self.sid_mm * math.sin(g) if d == 0 else (self.sid_mm - d) * math.sin(g) - d

    # -- single-slice rebinning -------------------------------------------------------
    def ssrb_v_mm(self, u_mm: ArrayLike, dz_mm: ArrayLike) -> np.ndarray:
        """Row coordinate v (mm) of the SSRB ray for arc coordinate ``u_mm`` and ``dz = z_slice - z_k``.

        The fan ray at gamma = u / SDD passes closest to the axis at in-plane distance SID cos(gamma)
        from the source; the arc lies at in-plane distance SDD along every ray, so the oblique
        ray through that point at height z hits the arc at ``v = SDD / (SID cos gamma) * dz``.
        """
        g = np.asarray(u_mm, dtype=np.float64) / self.sdd_mm
        dz = np.asarray(dz_mm, dtype=np.float64)
        return self.sdd_mm / (self.sid_mm * np.cos(g)) * dz

    def object_half_width_u_mm(self, object_radius_mm: float) -> float:
        """Largest |u| (arc mm) of a column whose fan ray passes within ``object_radius_mm`` of the axis.

        The ray at gamma passes the axis at distance SID |sin gamma|: |gamma| <= asin(r / SID).
        Capped at the outermost column centre (the farther side of an off-centre fan).
        """
        g_outer = max(self.central_col, self.n_cols - 1 - self.central_col) * self.delta_gamma_rad
        r = float(object_radius_mm)
        if r >= self.sid_mm:
            return self.sdd_mm * g_outer
        return self.sdd_mm * min(g_outer, math.asin(r / self.sid_mm))

    def v_half_mm(self) -> float:
        """Largest |v| (mm) that stays inside the outer row centres on both sides of the central row."""
        return min(self.central_row, self.n_rows - 1 - self.central_row) * self.row_pitch_mm

    def slice_window_mm(self, object_radius_mm: float) -> float:
        """Largest |z - z_k| (mm) for which SSRB needs no row outside the detector.

        |v| = SDD |dz| / (SID cos gamma) <= :meth:`v_half_mm` for every column whose ray passes
        within ``object_radius_mm`` (finite, > 0) of the axis; the outermost one binds. With a
        flying focal spot, ``dz`` is from the focal centre and the ray starts at the spot: v =
        c + (dz - c) k with k = t / (R' cos gamma) <= (SDD + d) / ((SID - d) cos gamma), so
        ``|dz| <= (v_half - |c| (k - 1)) / k`` (d, |c| the largest in-plane and axial offsets).
        """
        if not (math.isfinite(object_radius_mm) and object_radius_mm > 0):
            raise ValueError(f"object_radius_mm = {object_radius_mm!r}: must be a finite number > 0")
        g = self.object_half_width_u_mm(object_radius_mm) / self.sdd_mm
        if self.spot_inplane_mm == 0 and self.spot_z_mm == 0:
            return self.v_half_mm() * self.sid_mm * math.cos(g) / self.sdd_mm
        d, c = self.spot_inplane_mm, self.spot_z_mm
        k = (self.sdd_mm + d) / ((self.sid_mm - d) * math.cos(min(g + d / self.sid_mm, 0.5 * math.pi - 1e-9)))
        return max(0.0, (self.v_half_mm() - c * (k - 1.0)) / k)

    def max_covering_pitch(self, object_radius_mm: float) -> float:
        """Largest helical pitch with an SSRB candidate for every (slice, view): ``2 window / W``."""
        return 2.0 * self.slice_window_mm(object_radius_mm) / self.collimation_iso_mm


def detector_for(scanner: Any) -> DetectorModel:
    """The detector model a scanner config names (``scanner.detector``, default flat)."""
    return DETECTORS[getattr(scanner, "detector", "flat")].from_scanner(scanner)
