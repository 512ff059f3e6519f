"""The iterative method's geometry: its voxel volume and the rays of the scan's views.

**Volume** (:class:`VolumeGrid`): the reconstruction's in-plane grid (``nx`` x ``ny`` voxels of
``voxel_mm``, centred on the axis, ``clrecon.core.conventions.voxel_coords``) on ``nz`` uniform
planes of ``dz_mm`` along z. Unlike the 5DCT slices, the iterative volume must hold everything
the used rays cross: the rays of a view reach z up to the cone's half-width *at the far side of
the reconstruction circle*, so :func:`volume_grid` extends the z range of the views' sources by
``half_cone_mm(scanner, radius)`` on both sides (an object outside the volume would be unmodelled
data, the long-object problem). Arrays on it are (nz, ny, nx) float32 ``[z, y, x]``.

**Rays** (:func:`view_groups`): the scan's own detector, as the simulator's projector builds
them (:func:`clrecon.simulation.projector.project`): the flat panel's frames and cells, or the
cylindrical arc's flat-equivalent cells per focal-spot state
(:func:`clrecon.simulation.projector.spot_frames`); a flying focal spot is one group of views
per spot state.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from clrecon.core.conventions import voxel_coords
from clrecon.core.detector import spot_shift_in_frame
from clrecon.reconstruction.motion.model import FieldGrid
from clrecon.simulation.projector import spot_frames


@dataclass(frozen=True, kw_only=True)
class VolumeGrid(FieldGrid):
    """``nx`` x ``ny`` voxels of ``voxel_mm`` in-plane, ``nz`` planes ``z0_mm + k dz_mm``: a motion
    field's grid (:class:`~clrecon.reconstruction.motion.model.FieldGrid`: its checks, ``shape``
    and ``coords``) that may be one voxel thick, with the projector's origin and spacing."""

    MIN_SIZE = 1

    @property
    def origin_mm(self) -> tuple:
        """Centre (x, y, z) mm of voxel [0, 0, 0] (the projector's order)."""
        return (float(voxel_coords(self.nx, self.voxel_mm)[0]), float(voxel_coords(self.ny, self.voxel_mm)[0]),
                float(self.z0_mm))

    @property
    def spacing_mm(self) -> tuple:
        """(hx, hy, hz) mm."""
        return (float(self.voxel_mm), float(self.voxel_mm), float(self.dz_mm))

    def z_mm(self) -> np.ndarray:
        """Plane centres (nz,) mm."""
        return self.coords()[2]


def half_cone_mm(scanner, radius_mm: float) -> float:
    """Half the z extent of the cone at distance ``radius_mm`` beyond the axis, on the far side (mm).

    The outer row edge is at ``n_rows row_pitch / 2`` on the detector (distance SDD); at distance
    SID + radius from the source it has shrunk by (SID + radius) / SDD.
    """
    return 0.5 * scanner.n_rows * scanner.row_pitch_mm * (scanner.sid_mm + radius_mm) / scanner.sdd_mm


def volume_grid(scanner, nx: int, ny: int, voxel_mm: float, source_z_mm, radius_mm: float,
                dz_mm: float) -> VolumeGrid:
    """The volume holding every ray of views with sources at ``source_z_mm`` (any shape, mm)
    through the circle of ``radius_mm``: z from the lowest source minus the cone's far half-width
    to the highest plus it, on planes of ``dz_mm`` (the count rounded up, centred)."""
    z = np.asarray(source_z_mm, np.float64)
    if z.size == 0 or not np.all(np.isfinite(z)):
        raise ValueError("source_z_mm: need at least one finite source position")
    w = half_cone_mm(scanner, radius_mm)
    lo, hi = float(z.min()) - w, float(z.max()) + w
    nz = max(1, int(math.ceil((hi - lo) / dz_mm)) + 1)
    z0 = 0.5 * (lo + hi) - 0.5 * (nz - 1) * dz_mm
    return VolumeGrid(nx=int(nx), ny=int(ny), nz=nz, voxel_mm=float(voxel_mm), z0_mm=z0, dz_mm=float(dz_mm))


@dataclass(frozen=True)
class ViewGroup:
    """Views sharing one focal-spot state: ``rows`` (m,) int64 positions in the caller's view list,
    ``frames`` (source, plane centre, e_u, e_v) each (m, 3) mm, ``cells`` (u (C,), v (R,), v_scale
    (C,) or None) for :func:`clrecon.simulation.voxel_projector.project_volume`."""

    rows: np.ndarray
    frames: tuple
    cells: tuple

    def take(self, sel) -> ViewGroup:
        """The group's views ``sel`` (indices into ``rows``)."""
        return ViewGroup(self.rows[sel], tuple(np.ascontiguousarray(f[sel]) for f in self.frames), self.cells)


def view_groups(scanner, table) -> list[ViewGroup]:
    """The rays of every projection of ``table`` (a :class:`clrecon.scan.table.ProjectionTable`),
    one :class:`ViewGroup` per focal-spot state (one without a flying focal spot); ``rows`` index
    the table."""
    dm = scanner.detector_model
    if scanner.detector == "flat":
        frames = dm.frames(table.angle_rad, table.source_z_mm)
        return [ViewGroup(np.arange(len(table), dtype=np.int64), frames, (dm.u_mm(), dm.v_mm(), None))]
    shifts = spot_shift_in_frame(table.shifts, scanner.sid_mm)
    states, inverse = np.unique(shifts, axis=0, return_inverse=True)
    inverse = np.asarray(inverse).reshape(-1)
    out = []
    for k, shift in enumerate(states):
        rows = np.flatnonzero(inverse == k)
        frames, cells = spot_frames(dm, table.angle_rad[rows], table.source_z_mm[rows], shift)
        out.append(ViewGroup(rows.astype(np.int64), frames, cells))
    return out
