"""Single-slice rebinning (SSRB) of helical cone-beam projections (pipeline stage: rebin).

For every (slice, view) the candidates are the projections of that view, from every turn
whose rays still reach the slice inside the detector (docs/algorithms.md "Candidate selection": 5DCT keeps all
turns, each one is another sample in phase space). SSRB turns one candidate projection
into one in-plane fan-beam row of the slice; :mod:`clrecon.reconstruction.interpolation.weights` then combines the
rows of one (slice, view) in the (cardiac, respiratory) phase space.

Geometry (Noo, Defrise, Clackdoyle & Kudo, Phys. Med. Biol. 44:561, 1999): the fan ray of
flat-detector column u passes closest to the rotation axis at in-plane distance
SID cos(gamma) from the source, gamma = atan(u / SDD). The oblique ray from the source at
z_k through that point at height z hits the detector at row coordinate

    v(u) = (u^2 + SDD^2) / (SID SDD) * (z - z_k)          (mm)

and its line integral is converted to the in-plane one by the factor
sqrt(SDD^2 + u^2) / sqrt(SDD^2 + u^2 + v^2).

On a cylindrical detector (``scanner.detector = "cylindrical"``, kernel variant ``CURVED``) the
arc lies at in-plane distance SDD along every ray, so ``v(gamma) = SDD / (SID cos gamma) * dz``
and the factor is ``SDD / sqrt(SDD^2 + v^2)``; with a flying focal spot each pair carries its
spot's offset from the focal centre (``pair_shift``, variant ``FFS``/``FFS_PHI``,
docs/algorithms.md "SSRB on a cylindrical detector").
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from clrecon.core.conventions import detector_coords
from clrecon.core.detector import atan_defines
from clrecon.core.runtime import get_runtime
from clrecon.scan.config import ScannerConfig

if TYPE_CHECKING:  # only for annotations: rebinning needs the table's arrays, not its builder
    from clrecon.scan.table import ProjectionTable

#: Work-group size along the detector columns (fixed: PoCL specialises per local size).
_LOCAL_COLS = 64


def _round_up(n: int, m: int) -> int:
    return max(m, ((n + m - 1) // m) * m)


def ssrb_v_mm(u_mm, dz_mm, scanner: ScannerConfig) -> np.ndarray:
    """Detector row coordinate v(u) (mm) of the SSRB ray: :meth:`FlatDetector.ssrb_v_mm`.

    ``u_mm`` flat-detector column coordinate (mm), ``dz_mm = slice_z - z_k`` (mm); float64,
    broadcast of the inputs.
    """
    return scanner.detector_model.ssrb_v_mm(u_mm, dz_mm)


def slice_window_mm(scanner: ScannerConfig, object_radius_mm: float) -> float:
    """Largest |z - z_k| (mm) for which SSRB needs no row outside the detector.

    The scanner's detector model defines it (:meth:`clrecon.core.detector.FlatDetector.slice_window_mm`).
    """
    return scanner.detector_model.slice_window_mm(object_radius_mm)


def max_covering_pitch(scanner: ScannerConfig, object_radius_mm: float) -> float:
    """Largest helical pitch for which every (slice, view) inside the scanned range has a candidate.

    See :meth:`clrecon.core.detector.FlatDetector.max_covering_pitch`.
    """
    return scanner.detector_model.max_covering_pitch(object_radius_mm)


def candidates(table: ProjectionTable, slice_z_mm: float, scanner: ScannerConfig,
               object_radius_mm: float) -> np.ndarray:
    """Projections whose source is close enough to a slice for SSRB, all turns, every view.

    Parameters
    ----------
    table : ProjectionTable
    slice_z_mm : float
        z of the slice plane (mm).
    scanner : ScannerConfig
    object_radius_mm : float
        See :func:`slice_window_mm`.

    Returns
    -------
    np.ndarray
        int64 (n,), sorted: projection numbers ``table.index`` with
        |slice_z - z_k| <= :func:`slice_window_mm`. Group them by ``index % N_views``
        for the per-(slice, view) candidates, or use :func:`candidate_groups`.
    """
    w = slice_window_mm(scanner, object_radius_mm)
    sel = np.abs(float(slice_z_mm) - table.source_z_mm) <= w
    return np.sort(table.index[sel])


@dataclass(frozen=True)
class CandidateGroups:
    """Candidates of many (slice, view) groups in compressed sparse-row form.

    Group ``g = s * views_per_rotation + j`` is slice ``s`` (position in the ``slice_z_mm``
    given) and view ``j``; its candidates are entries ``offsets[g]:offsets[g + 1]`` of the
    flat arrays, in increasing projection number. Every (slice, view) has a group; a group
    with no candidate (pitch too high for the object radius) has ``offsets[g] ==
    offsets[g + 1]`` and shows in :attr:`empty`.

    Attributes
    ----------
    offsets : int64 (G + 1,)
    row : int64 (n,)           position of the candidate in the table (for c, a lookups)
    projection : int64 (n,)    projection number ``table.index[row]``
    dz_mm : float64 (n,)       slice_z - z_k (mm), the SSRB ``pair_dz_mm``
    slice_z_mm : float64 (S,)
    views_per_rotation : int
    """

    offsets: np.ndarray
    row: np.ndarray
    projection: np.ndarray
    dz_mm: np.ndarray
    slice_z_mm: np.ndarray
    views_per_rotation: int

    @property
    def n_groups(self) -> int:
        return int(self.offsets.shape[0] - 1)

    @property
    def counts(self) -> np.ndarray:
        """Candidates per group, int64 (G,)."""
        return np.diff(self.offsets)

    @property
    def empty(self) -> np.ndarray:
        """bool (G,): groups without any candidate."""
        return self.counts == 0

    @property
    def group_slice(self) -> np.ndarray:
        """Slice position of each group, int64 (G,)."""
        return np.arange(self.n_groups) // self.views_per_rotation

    @property
    def group_view(self) -> np.ndarray:
        """View of each group, int64 (G,)."""
        return np.arange(self.n_groups) % self.views_per_rotation


def candidate_groups(table: ProjectionTable, slice_z_mm, scanner: ScannerConfig,
                     object_radius_mm: float, window_mm: float | None = None) -> CandidateGroups:
    """Candidates of every (slice, view) for a set of slices, vectorised.

    Parameters
    ----------
    table : ProjectionTable
        Full scan or any sub-table (rows need not be in z order).
    slice_z_mm : array_like
        (S,) slice positions (mm).
    scanner : ScannerConfig
    object_radius_mm : float
        See :func:`slice_window_mm`.
    window_mm : float, optional
        Half-width of the candidate window |slice_z - z_k| (mm); default (None or 0) the
        SSRB-exact :func:`slice_window_mm`. A wider window (the 5DCT paper: half the detector
        width projected to the isocentre, ~28 mm, ``recon.candidate_window_mm``) takes turns
        whose outer columns' SSRB rows lie off the detector: the kernel clamps them to the
        edge row.

    Returns
    -------
    CandidateGroups
        S * views_per_rotation groups, slice-major.
    """
    zs = np.atleast_1d(np.asarray(slice_z_mm, dtype=np.float64))
    nv = int(table.views_per_rotation)
    w = float(window_mm) if window_mm else slice_window_mm(scanner, object_radius_mm)
    zk = np.asarray(table.source_z_mm, dtype=np.float64)
    # Sort the table once by z so each slice is a contiguous range (a helical table already is).
    order = np.argsort(zk, kind="stable")
    zsorted = zk[order]
    view = np.asarray(table.view)
    rows, dzs, counts = [], [], np.zeros(zs.size * nv, dtype=np.int64)
    for s, z in enumerate(zs):
        lo = np.searchsorted(zsorted, z - w, side="left")
        hi = np.searchsorted(zsorted, z + w, side="right")
        r = order[lo:hi]
        # Within a slice: group by view, then by projection number (turn order).
        r = r[np.lexsort((table.index[r], view[r]))]
        rows.append(r)
        dzs.append(z - zk[r])
        counts[s * nv:(s + 1) * nv] = np.bincount(view[r], minlength=nv)
    row = np.concatenate(rows) if rows else np.zeros(0, np.int64)
    offsets = np.zeros(zs.size * nv + 1, dtype=np.int64)
    np.cumsum(counts, out=offsets[1:])
    return CandidateGroups(offsets=offsets, row=row.astype(np.int64),
                           projection=np.asarray(table.index)[row].astype(np.int64),
                           dz_mm=np.concatenate(dzs) if dzs else np.zeros(0),
                           slice_z_mm=zs, views_per_rotation=nv)


# ---------------------------------------------------------------------------------------
def _curved_rows(dz, scanner: ScannerConfig, shift=None) -> np.ndarray:
    """Float64 fractional rows, columns and scales of the cylindrical SSRB (the kernel's formulas).

    ``dz`` (p,) slice_z - focal-centre z; ``shift`` (p, 3) the spot offsets (a, b, c) or None.
    Returns ``(fr (p, C) unclamped, fc (p, C) or None, t (p, C) or SDD, c (p, 1))``.
    """
    det = scanner.detector_model
    g = det.gamma_rad()[None, :]
    dz = np.asarray(dz, np.float64)[:, None]
    sdd, sid = det.sdd_mm, det.sid_mm
    fc = None
    if shift is None:
        t, c = np.full_like(g, sdd), np.zeros_like(dz)
        v = sdd / (sid * np.cos(g)) * dz
    else:
        sh = np.asarray(shift, np.float64)
        a, b, c = sh[:, 0:1], sh[:, 1:2], sh[:, 2:3]
        if np.any(a != 0) or np.any(b != 0):
            na, nb = sid - a, -b
            rp = np.hypot(na, nb)
            dx = (np.cos(g) * na - np.sin(g) * nb) / rp
            dy = (np.cos(g) * nb + np.sin(g) * na) / rp
            ad = a * dx + b * dy
            t = -ad + np.sqrt(ad * ad - (a * a + b * b) + sdd * sdd)
            fc = np.arctan2(b + t * dy, a + t * dx) / det.delta_gamma_rad + det.central_col
            mid = rp * np.cos(g)
        else:
            t, mid = np.full_like(g, sdd), sid * np.cos(g)
        v = c + (dz - c) * t / mid
    return v / scanner.row_pitch_mm + det.central_row, fc, t, c


def _ffs_kind(pair_shift) -> str:
    """'' (no shift), 'z' (axial only) or 'phi' (an in-plane shift) for (p, 3) spot offsets."""
    if pair_shift is None:
        return ""
    sh = np.asarray(pair_shift, np.float64)
    return "phi" if np.any(sh[:, :2] != 0) else "z"


def ssrb_row_range(pair_dz_mm, scanner: ScannerConfig, pair_shift=None) -> tuple[int, int]:
    """Detector rows ``[lo, hi)`` that :func:`ssrb_rows` reads for pairs at ``pair_dz_mm`` (p,), mm.

    v(u) is linear in dz and grows with |u|, so the rows of every column of every pair lie
    between those of the outermost columns at the smallest and the largest dz. One row of
    margin on each side covers the float32 rounding of the kernel's row coordinate. The
    reconstruction reads, and draws noise for, only these rows of a chunk (a 4-slice slab
    of paper-p002 uses about 15 of the 64). ``(0, 0)`` for no pairs.
    """
    dz = np.asarray(pair_dz_mm, dtype=np.float64)
    if dz.size == 0:
        return 0, 0
    n_rows = scanner.n_rows
    if scanner.detector != "flat":
        # every column of the pairs at the extreme dz (v is monotonic in dz for a fixed shift);
        # with a flying focal spot, every distinct spot offset at both extremes
        if pair_shift is None:
            fr = _curved_rows(np.array([dz.min(), dz.max()]), scanner)[0]
        else:
            sh = np.unique(np.asarray(pair_shift, np.float64), axis=0)
            zz = np.repeat([dz.min(), dz.max()], len(sh))
            fr = _curved_rows(zz, scanner, np.tile(sh, (2, 1)))[0]
        fr = np.clip(fr, 0.0, n_rows - 1)
        r0 = np.minimum(np.floor(fr), max(n_rows - 2, 0))
        return int(max(0, r0.min() - 1)), int(min(n_rows, r0.max() + 3))
    u = detector_coords(scanner.n_cols, scanner.col_pitch_mm)
    u_edge = np.array([0.0, np.abs(u).max()])
    v = ssrb_v_mm(u_edge[:, None], np.array([dz.min(), dz.max()])[None, :], scanner)
    centre = 0.5 * (n_rows - 1)
    fr = np.clip(v / scanner.row_pitch_mm + centre, 0.0, n_rows - 1)
    r0 = np.minimum(np.floor(fr), max(n_rows - 2, 0))
    lo = int(max(0, r0.min() - 1))
    hi = int(min(n_rows, r0.max() + 3))  # r1 = r0 + 1, plus the margin, exclusive
    return lo, hi


def _check_pairs(projections, pair_slot, pair_dz_mm, scanner: ScannerConfig, first_row: int | None = None,
                 pair_shift=None):
    proj = np.asarray(projections)
    if proj.dtype.kind not in "fiu":
        raise TypeError(f"projections: expected a real numeric array, got dtype {proj.dtype}")
    whole = first_row is None
    if proj.ndim != 3 or proj.shape[2] != scanner.n_cols or not (
            (whole and proj.shape[1] == scanner.n_rows)
            or (not whole and 0 <= first_row and first_row + proj.shape[1] <= scanner.n_rows and proj.shape[1] > 0)):
        raise ValueError(f"projections: expected shape (m, {scanner.n_rows}, {scanner.n_cols}), or a block of "
                         f"rows first_row.. inside the {scanner.n_rows} detector rows; got {proj.shape} "
                         f"with first_row = {first_row}")
    slot = np.asarray(pair_slot)
    if slot.dtype.kind not in "iu":
        raise TypeError(f"pair_slot: expected an integer array, got dtype {slot.dtype}")
    dz = np.asarray(pair_dz_mm, dtype=np.float64)
    if slot.ndim != 1 or dz.shape != slot.shape:
        raise ValueError(f"pair_slot {slot.shape} and pair_dz_mm {dz.shape} must be 1-D of equal length")
    if slot.size and (slot.min() < 0 or slot.max() >= proj.shape[0]):
        raise ValueError(f"pair_slot: values must lie in [0, {proj.shape[0]}), "
                         f"got [{slot.min()}, {slot.max()}]")
    if not np.all(np.isfinite(dz)):
        raise ValueError("pair_dz_mm: must be finite")
    if pair_shift is not None:
        sh = np.asarray(pair_shift, np.float64)
        if sh.shape != (slot.size, 3) or not np.all(np.isfinite(sh)):
            raise ValueError(f"pair_shift: expected finite (p, 3) = ({slot.size}, 3) spot offsets, got {sh.shape}")
        if scanner.detector == "flat":
            raise ValueError("pair_shift: the flat detector has no flying focal spot")
    if not whole and dz.size:
        lo, hi = ssrb_row_range(dz, scanner, pair_shift)
        if lo < first_row or hi > first_row + proj.shape[1]:
            raise ValueError(f"projections: the pairs read detector rows {lo}..{hi - 1}, the block holds rows "
                             f"{first_row}..{first_row + proj.shape[1] - 1}")
    return proj, slot, dz


def ssrb_rows_reference(projections, pair_slot, pair_dz_mm, scanner: ScannerConfig,
                        first_row: int | None = None, pair_shift=None) -> np.ndarray:
    """Float64 NumPy reference of :func:`ssrb_rows` (same clamping), shape (p, C)."""
    proj, slot, dz = _check_pairs(projections, pair_slot, pair_dz_mm, scanner, first_row, pair_shift)
    first_row = first_row or 0
    proj = proj.astype(np.float64)
    n_rows, n_cols = scanner.n_rows, scanner.n_cols
    if scanner.detector != "flat":
        det = scanner.detector_model
        fr, fc, t, c = _curved_rows(dz, scanner, pair_shift)
        fr = np.clip(fr, 0.0, n_rows - 1)
        r0 = np.minimum(np.floor(fr).astype(np.int64), max(n_rows - 2, 0))
        r1 = np.minimum(r0 + 1, n_rows - 1)
        tr = fr - r0
        s = slot[:, None]
        if fc is None:
            cols = np.broadcast_to(np.arange(n_cols)[None, :], fr.shape)
            a0, a1 = proj[s, r0 - first_row, cols], proj[s, r1 - first_row, cols]
        else:
            fc = np.clip(fc, 0.0, n_cols - 1)
            c0 = np.minimum(np.floor(fc).astype(np.int64), max(n_cols - 2, 0))
            c1 = np.minimum(c0 + 1, n_cols - 1)
            tc = fc - c0
            a0 = (1 - tc) * proj[s, r0 - first_row, c0] + tc * proj[s, r0 - first_row, c1]
            a1 = (1 - tc) * proj[s, r1 - first_row, c0] + tc * proj[s, r1 - first_row, c1]
        vs = (fr - det.central_row) * scanner.row_pitch_mm - c
        return t / np.sqrt(t * t + vs * vs) * ((1 - tr) * a0 + tr * a1)
    u = detector_coords(n_cols, scanner.col_pitch_mm)                       # (C,)
    q = u * u + scanner.sdd_mm ** 2
    v = ssrb_v_mm(u[None, :], dz[:, None], scanner)                          # (p, C)
    centre = 0.5 * (n_rows - 1)
    fr = np.clip(v / scanner.row_pitch_mm + centre, 0.0, n_rows - 1)
    r0 = np.minimum(np.floor(fr).astype(np.int64), max(n_rows - 2, 0))
    r1 = np.minimum(r0 + 1, n_rows - 1)
    t = fr - r0
    cols = np.arange(n_cols)[None, :]
    s = slot[:, None]
    val = (1 - t) * proj[s, r0 - first_row, cols] + t * proj[s, r1 - first_row, cols]
    vs = (fr - centre) * scanner.row_pitch_mm
    return np.sqrt(q / (q + vs * vs)) * val


def ssrb_rows(projections, pair_slot, pair_dz_mm, scanner: ScannerConfig, rt=None,
              first_row: int | None = None, pair_shift=None) -> np.ndarray:
    """Rebin helical cone-beam projections to in-plane fan-beam rows (OpenCL, ``kernels/ssrb.cl``).

    Parameters
    ----------
    projections : array_like
        (m, n_rows, n_cols) line integrals (converted to C-contiguous float32), or (m, b, n_cols):
        detector rows ``first_row .. first_row + b - 1`` only, which must hold every row the
        pairs read (:func:`ssrb_row_range`; ValueError otherwise).
    pair_slot : array_like of int
        (p,) which projection each output row comes from, index into m.
    pair_dz_mm : array_like
        (p,) slice_z - z_k (mm) of each pair.
    scanner : ScannerConfig
    rt : Runtime, optional
        Defaults to :func:`clrecon.core.runtime.get_runtime`.
    first_row : int, optional
        Detector row of the block's row 0; None (default): whole projections.
    pair_shift : array_like, optional
        (p, 3) each pair's focal-spot offset (a, b, c) mm from the focal centre
        (:func:`clrecon.core.detector.spot_shift_in_frame`), cylindrical detector only; then
        ``pair_dz_mm`` is slice_z minus the focal centre's z, and with an in-plane offset the
        output row is the equiangular fan of the spot (kernel ``FFS_PHI``).

    Returns
    -------
    np.ndarray
        float32 (p, n_cols): fan-beam line integrals of the slice plane at the projection's
        gantry angle, one row per pair. Where v(u) falls outside the outer row centres the
        outer row is used (clamped); candidates from :func:`candidates` never need that for
        columns that see the object.
    """
    proj, slot, dz = _check_pairs(projections, pair_slot, pair_dz_mm, scanner, first_row, pair_shift)
    p, n_cols = slot.size, scanner.n_cols
    if p == 0:
        return np.zeros((0, n_cols), np.float32)
    rt = rt or get_runtime()
    if scanner.detector != "flat":
        return _ssrb_rows_curved(proj, slot, dz, scanner, rt, first_row or 0, pair_shift)
    d_proj = rt.to_device(proj, np.float32, "projections")
    d_slot = rt.to_device(slot, np.int32, "pair_slot")
    d_dz = rt.to_device(dz, np.float32, "pair_dz_mm")
    d_out = rt.empty((p, n_cols), np.float32)
    knl = rt.kernel("ssrb.cl", "ssrb_rows")
    ev = knl(rt.queue, (_round_up(n_cols, _LOCAL_COLS), p), (_LOCAL_COLS, 1),
             d_proj, d_slot, d_dz, d_out, np.int32(p), np.int32(scanner.n_rows), np.int32(first_row or 0),
             np.int32(proj.shape[1]), np.int32(n_cols),
             np.float32(scanner.col_pitch_mm), np.float32(scanner.row_pitch_mm),
             np.float32(scanner.sid_mm), np.float32(scanner.sdd_mm))
    return rt.from_device(d_out, (p, n_cols), np.float32, wait_for=[ev])


def _ssrb_rows_curved(proj, slot, dz, scanner: ScannerConfig, rt, first_row: int, pair_shift) -> np.ndarray:
    """:func:`ssrb_rows` on a cylindrical detector (``kernels/ssrb.cl`` with ``CURVED``, ``FFS``, ``FFS_PHI``)."""
    det = scanner.detector_model
    p, n_cols = slot.size, scanner.n_cols
    kind = _ffs_kind(pair_shift)
    defines = {"CURVED": 1, **({"FFS": 1} if kind else {}), **({"FFS_PHI": 1} if kind == "phi" else {})}
    if kind == "phi":   # atan of the arc's fan angles: up to the outer column edge, a little margin
        g_max = max(abs(x) for x in det.edge_gamma_rad()) + 0.01
        defines.update(atan_defines(min(1.0, round(math.tan(min(g_max, 0.25 * math.pi)), 6)),
                                    1.0 / det.delta_gamma_rad))
    d_proj = rt.to_device(proj, np.float32, "projections")
    d_slot = rt.to_device(slot, np.int32, "pair_slot")
    d_dz = rt.to_device(dz, np.float32, "pair_dz_mm")
    extra = []
    if kind:
        sh = np.zeros((p, 4))
        sh[:, :3] = pair_shift
        sh[:, 3] = 1.0 / np.hypot(scanner.sid_mm - sh[:, 0], sh[:, 1])   # 1 / R', the spot's radius
        extra = [rt.to_device(sh, np.float32, "pair_shift")]
    d_out = rt.empty((p, n_cols), np.float32)
    g = det.gamma_rad()
    colgeo = np.stack([np.cos(g), np.sin(g), det.sdd_mm / (det.sid_mm * np.cos(g)), 1.0 / np.cos(g)], 1)
    d_col = rt.to_device(colgeo, np.float32, "colgeo")
    knl = rt.kernel("ssrb.cl", "ssrb_rows", **defines)
    ev = knl(rt.queue, (_round_up(n_cols, _LOCAL_COLS), p), (_LOCAL_COLS, 1),
             d_proj, d_slot, d_dz, *extra, d_out, np.int32(p), np.int32(scanner.n_rows), np.int32(first_row),
             np.int32(proj.shape[1]), np.int32(n_cols), d_col, np.float32(det.delta_gamma_rad),
             np.float32(scanner.row_pitch_mm), np.float32(scanner.sid_mm), np.float32(scanner.sdd_mm),
             np.float32(det.central_col), np.float32(det.central_row))
    return rt.from_device(d_out, (p, n_cols), np.float32, wait_for=[ev])
