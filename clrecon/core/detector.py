"""Detector models: where the cells are, how SSRB rows map onto them, which region they see.

Every stage that needs detector geometry asks the scene's detector model (``scanner.detector``,
registry :data:`DETECTORS`) rather than writing the formulas again: the projector and the ground
truth take the cell centres and the per-view frames, SSRB takes the row coordinate of its
oblique ray and the slice window, the scene check takes the largest covering pitch, FBP takes the
field-of-view radius. A cylindrical detector is one new class here plus its kernel variants
(``docs/extending.md``).

Only the flat detector exists today. Conventions (``docs/conventions.md``): lengths in mm,
columns along ``e_u``, rows along ``e_v = +z``; cell centres symmetric about the central ray.
"""

from __future__ import annotations

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


def detector_for(scanner: Any) -> DetectorModel:
    """The detector model a scanner config names (``scanner.detector``, default flat)."""
    return DETECTORS[getattr(scanner, "detector", "flat")].from_scanner(scanner)
