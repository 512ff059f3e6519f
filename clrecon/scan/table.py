"""Helical scan geometry: the per-projection table (stage 2 of the pipeline).

Turns a scene and one pitch into plain per-projection arrays (docs/conventions.md "Gantry and source"): index,
time, gantry angle, source z, cardiac phase, respiratory amplitude and breathing direction.
Projectors and the rebinner see only these arrays and the canonical vector form from
:func:`clrecon.core.conventions.detector_frames`.
"""

from __future__ import annotations

import dataclasses
import functools
from dataclasses import dataclass

import numpy as np

from clrecon.scan import dicom_ct_pd, measured, signals
from clrecon.scan.config import Acquisition
from clrecon.scan.recorded import file_digest

#: Projection tables :func:`cached_projection_table` keeps per process (a run's pitches, a worker's scans).
TABLES_KEPT = 8


@dataclass(frozen=True)
class ProjectionTable:
    """Per-projection columns, each of shape (n,).

    index          int64   projection number k in the helical scan (0-based)
    time_s         float64 acquisition time t_k = k T_rot / N_views (s)
    angle_rad      float64 gantry angle beta_k = beta0 +- 2 pi k / N_views (rad, not wrapped; - when
                           ``angle_sign`` = -1, a gantry turning the other way)
    source_z_mm    float64 source z_k = z_start + h k / N_views (mm)
    cardiac_phase  float64 c in [0, 1): fraction of the current R-R interval (recorded)
    resp_amplitude float64 a in [0, 1], 1 = end-inhale (recorded)
    resp_direction int8    +1 inhaling, -1 exhaling (sign of da/dt)
    state_cardiac  float64 cardiac phase the phantom is posed at (= cardiac_phase unless frames)
    state_resp     float64 amplitude the phantom is posed at (= resp_amplitude unless frames)

    ``angle_rad`` and ``source_z_mm`` are the *focal centre* (where the detector is centred).
    With a flying focal spot, ``focal_shift`` (n, 3) float64 is each projection's focal-spot
    shift from it, (dphi rad, drho mm, dz mm) (:func:`clrecon.core.detector.ffs_states`); None
    means no shift. The spot sits at gantry angle ``spot_angle_rad``, radius SID + drho and
    z ``spot_z_mm``. It is derived from ``index`` and the scanner, so it is not a stored column.
    """

    index: np.ndarray
    time_s: np.ndarray
    angle_rad: np.ndarray
    source_z_mm: np.ndarray
    cardiac_phase: np.ndarray
    resp_amplitude: np.ndarray
    resp_direction: np.ndarray
    state_cardiac: np.ndarray
    state_resp: np.ndarray
    views_per_rotation: int
    focal_shift: np.ndarray | None = None
    angle_sign: int = 1

    COLUMNS = ("index", "time_s", "angle_rad", "source_z_mm", "cardiac_phase", "resp_amplitude",
               "resp_direction", "state_cardiac", "state_resp")

    def __len__(self) -> int:
        return int(self.index.shape[0])

    @property
    def view(self) -> np.ndarray:
        """View number within the rotation, shape (n,): k mod N_views, or -k mod N_views when the gantry
        angle decreases (``angle_sign`` = -1), so that view j is always at angle beta0 + 2 pi j / N_views."""
        return (self.angle_sign * self.index) % self.views_per_rotation

    @property
    def shifts(self) -> np.ndarray:
        """Focal-spot shifts (n, 3) (dphi rad, drho mm, dz mm); zeros without a flying focal spot."""
        return np.zeros((len(self), 3)) if self.focal_shift is None else self.focal_shift

    @property
    def spot_angle_rad(self) -> np.ndarray:
        """Gantry angle of each projection's focal spot (n,) rad."""
        return self.angle_rad + self.shifts[:, 0]

    @property
    def spot_z_mm(self) -> np.ndarray:
        """z of each projection's focal spot (n,) mm."""
        return self.source_z_mm + self.shifts[:, 2]

    def take(self, sel) -> ProjectionTable:
        """Sub-table of the rows ``sel`` (indices or boolean mask)."""
        return ProjectionTable(**{c: getattr(self, c)[sel] for c in self.COLUMNS},
                               views_per_rotation=self.views_per_rotation,
                               focal_shift=None if self.focal_shift is None else self.focal_shift[sel],
                               angle_sign=self.angle_sign)

    def as_dict(self) -> dict:
        return {c: getattr(self, c) for c in self.COLUMNS}


def projection_table(scene: Acquisition, pitch: float) -> ProjectionTable:
    """The whole helical scan of ``scene`` at ``pitch`` as a :class:`ProjectionTable`."""
    sc, scan = scene.scanner, scene.scan
    nv = sc.views_per_rotation
    if scene.measured:  # the views' own geometry, from the DICOM-CT-PD headers
        k, t, beta, z = measured.views(scene)
    else:
        n = scan.projection_count(sc, pitch)
        k = np.arange(n, dtype=np.int64)
        t = k * (sc.rotation_time_s / nv)
        beta = np.deg2rad(scan.start_angle_deg) + scan.rotation_sign * 2.0 * np.pi * k / nv
        z = scan.z_start_mm(sc, pitch) + scan.table_sign * scan.feed_mm(sc, pitch) * k / nv
    phys = signals.physiology(scene, t)
    states = sc.ffs_shifts
    shift = None if sc.flying_focal_spot == "none" else states[k % len(states)]
    return ProjectionTable(index=k, time_s=t, angle_rad=beta, source_z_mm=z,
                           cardiac_phase=phys.cardiac_phase, resp_amplitude=phys.resp_amplitude,
                           resp_direction=phys.resp_direction, state_cardiac=phys.state_cardiac,
                           state_resp=phys.state_resp, views_per_rotation=nv, focal_shift=shift,
                           angle_sign=scan.rotation_sign)


def recorded_content(scene: Acquisition) -> dict:
    """Content digests of the scene's recorded inputs (traces, measured series): what a scan's
    table and projections are made from besides the scene's values (the scan hash,
    :meth:`clrecon.config.scene.Scene.scan_hash`, and :func:`cached_projection_table`'s key)."""
    out = {}
    for key in ("breathing_trace", "ecg_trace"):
        path = getattr(scene.signals, key)
        if path:
            out[key] = file_digest(path)
    if scene.measured:
        out["projections"] = dicom_ct_pd.series_signature(scene.scan.projections)
    return out


def cached_projection_table(scene: Acquisition, pitch: float) -> ProjectionTable:
    """:func:`projection_table` of ``(scene, pitch)``, made once per process and kept for the
    last :data:`TABLES_KEPT` scans: every stage, work unit and reader of one scan shares one table.

    Keyed by the scene's value (a :class:`~clrecon.config.scene.Scene` is a frozen, hashable
    dataclass: equal scenes are one key), the pitch and the content of its recorded inputs
    (:func:`recorded_content`: a trace or series changed on disk is another scan). The table's
    columns are read-only views (``flags.writeable`` False): shared by every caller, they are
    never written (:meth:`ProjectionTable.take` makes a writable sub-table).
    """
    return _cached_table(scene, float(pitch), tuple(sorted(recorded_content(scene).items())))


@functools.lru_cache(maxsize=TABLES_KEPT)
def _cached_table(scene: Acquisition, pitch: float, content: tuple) -> ProjectionTable:
    """``content`` is only part of the key (:func:`cached_projection_table`)."""
    table = projection_table(scene, pitch)
    return dataclasses.replace(table, focal_shift=_read_only(table.focal_shift),
                               **{c: _read_only(getattr(table, c)) for c in ProjectionTable.COLUMNS})


def _read_only(a: np.ndarray | None) -> np.ndarray | None:
    """A read-only view of ``a`` (``a`` itself stays as it was)."""
    if a is None:
        return None
    v = a.view()
    v.flags.writeable = False
    return v


def usable_table(scene: Acquisition, table: ProjectionTable) -> tuple[ProjectionTable, dict]:
    """The rows of ``table`` the reconstruction may use, and reason -> views left out.

    With recorded traces (:mod:`clrecon.scan.recorded`) views in lost or invalid trace stretches
    are left out; their ``index`` (= store row) stays, so the sub-table plans onto the same store.
    Without them every row is usable (``table`` itself, ``{}``).
    """
    usable, excluded = signals.usable_views(scene, table.time_s)
    if usable.all():
        return table, excluded
    return table.take(usable), excluded
