"""Motion-compensated FBP of SSRB rows: every row serves every target through the motion model.

Rit, Sarrut & Desbat, "Comparison of analytic and algebraic methods for motion-compensated
cone-beam CT reconstruction of the thorax", IEEE TMI 28:1513 (2009): each projection is
backprojected along the deformation from the target state to its own state. Here the projections
are the helical scan's single-slice rebinned rows (docs/algorithms.md "SSRB"), so following a
voxel means following it across slices: every projection a slab uses is rebinned onto a grid of
z planes (:func:`plane_rows`, the pipeline's own SSRB on every detector and focal-spot mode, then
its ramp filter), and the kernel (``kernels/mc_backproject.cl``) reads, for each voxel and row,
the plane through the voxel's moved position. docs/motion-model.md "The method" (step 4).

Shapes: volumes (S, ny, nx); rows (P, NPMAX, C) float32; slots (S, V, K) per target; the model's
fields (NB, 3, MZ, ny, nx) on the reconstruction's in-plane grid
(:class:`clrecon.reconstruction.motion.model.FieldGrid`), or a :class:`ModelWindow` of some of
those planes (a slab's: :func:`clrecon.reconstruction.motion.method.refine`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from clrecon.core import drivers
from clrecon.core.detector import atan_defines, spot_shift_in_frame
from clrecon.core.runtime import get_runtime
from clrecon.reconstruction import rebin
from clrecon.reconstruction.fbp import FanBeamGeometry, filter_rows, view_table
from clrecon.reconstruction.motion.model import FieldGrid, MotionModel
from clrecon.scan.table import ProjectionTable

#: Voxels along x per work-item, the vector lanes of ``kernels/mc_backproject.cl``: None = by the
#: device (:func:`lanes_for`), or 8 or 16 for every device (tests and benchmarks set it).
LANES: int | None = None
#: Fixed local size (x, y) of the kernel in work-items (PoCL specialises per local size): a tile
#: of lanes * LX x LY voxels that sweeps VIEW_CHUNK views between barriers, so the plane rows the
#: tile reads stay in cache (as backproject.cl). The default, PoCL's and every other device's
#: (:func:`launch_shape`).
LOCAL_SIZE = (1, 8)
#: Views per barrier-separated chunk of :data:`LOCAL_SIZE`.
VIEW_CHUNK = 8
#: Intel's CPU runtime: a larger tile (128 x 32 voxels at 16 lanes) and shorter chunks. Its work-
#: items share the rows of a chunk from cache instead of each tile fetching them again: 1.4x the
#: (1, 8) x 8 shape on the same data and bits (docs/results/mc-cost.md "Cost"); on PoCL the same
#: shape was 0.85-0.9x (its work-items' private vectors are saved and restored at every barrier).
INTEL_LOCAL_SIZE = (8, 32)
INTEL_VIEW_CHUNK = 4
#: Fixed-point steps of the model's inversion x_r = x - u_t(x_r) (docs/motion-model.md).
INVERSION_STEPS = 8
_KERNEL_FILE = "mc_backproject.cl"


@dataclass
class PlaneRows:
    """Filtered SSRB rows of projections on a grid of z planes ``g * plane_dz_mm``.

    rows : (P, NPMAX, C) float32, plane i of projection q at global plane ``plane_first[q] + i``
    plane_first, plane_count : (P,) int32 (``plane_count >= 1``; planes past the count are 0)
    projection : (P,) int64 global projection numbers, increasing
    proj_z_mm : (P,) float64 focal-centre z of each projection
    plane_dz_mm : float
    window_mm : float  the SSRB window the planes were cut to (|z_plane - z_k| <= window + dz)
    """

    rows: np.ndarray
    plane_first: np.ndarray
    plane_count: np.ndarray
    projection: np.ndarray
    proj_z_mm: np.ndarray
    plane_dz_mm: float
    window_mm: float

    def local_index(self, projections) -> np.ndarray:
        """Position in ``projection`` of each global projection number (-1 stays -1); a number
        that is not held raises ValueError."""
        p = np.asarray(projections, np.int64)
        pos = np.searchsorted(self.projection, np.where(p < 0, 0, p))
        pos = np.clip(pos, 0, max(len(self.projection) - 1, 0))
        ok = (p < 0) | ((len(self.projection) > 0) & (self.projection[pos] == p))
        if not np.all(ok):
            raise ValueError(f"projection {int(p[~ok].ravel()[0])} has no plane rows")
        return np.where(p < 0, -1, pos).astype(np.int32)


def plane_range(proj_z_mm, window_mm: float, plane_dz_mm: float, z_lo_mm: float, z_hi_mm: float):
    """Global plane indices ``[first, first + count)`` of each projection (numpy arrays, int64):
    the planes within ``window + dz`` of its source z and inside ``[z_lo, z_hi]`` (mm)."""
    zk = np.asarray(proj_z_mm, np.float64)
    g_lo = np.ceil((np.maximum(zk - window_mm - plane_dz_mm, z_lo_mm)) / plane_dz_mm - 1e-9)
    g_hi = np.floor((np.minimum(zk + window_mm + plane_dz_mm, z_hi_mm)) / plane_dz_mm + 1e-9)
    first = g_lo.astype(np.int64)
    count = np.maximum(g_hi - g_lo + 1, 0).astype(np.int64)
    return first, count


def plane_rows(projections, table: ProjectionTable, projection_ids, scanner, geom: FanBeamGeometry, window: str,
               *, plane_dz_mm: float, z_lo_mm: float, z_hi_mm: float, object_radius_mm: float, rt=None,
               first_row: int = 0) -> PlaneRows:
    """SSRB rows of ``projection_ids`` on the planes of :func:`plane_range`, ramp-filtered.

    Parameters
    ----------
    projections : (m, n_rows_block, C) array
        Line integrals of the projections ``projection_ids`` (same order), detector rows
        ``first_row ..``: as read from the store (noise already added for a noisy variant).
    table : ProjectionTable of the scan (``source_z_mm``, ``focal_shift`` by projection number)
    projection_ids : (m,) int, increasing
    scanner : ScannerConfig
    geom : FanBeamGeometry (the filter's geometry), window: ramp window name
    plane_dz_mm : plane spacing (mm); z_lo_mm, z_hi_mm: the planes kept (mm)
    object_radius_mm : the reconstruction circle (sets the SSRB window, :func:`rebin.slice_window_mm`)

    Returns
    -------
    PlaneRows
    """
    ids = np.asarray(projection_ids, np.int64)
    if ids.ndim != 1 or (ids.size > 1 and np.any(np.diff(ids) <= 0)):
        raise ValueError("projection_ids: must be 1-D and strictly increasing")
    if not (math.isfinite(plane_dz_mm) and plane_dz_mm > 0):
        raise ValueError(f"plane_dz_mm = {plane_dz_mm!r}: must be a finite number > 0")
    proj = np.asarray(projections)
    if proj.ndim != 3 or proj.shape[0] != ids.size:
        raise ValueError(f"projections: expected ({ids.size}, rows, {scanner.n_cols}), got {proj.shape}")
    w = rebin.slice_window_mm(scanner, object_radius_mm)
    zk = table.source_z_mm[ids]
    first, count = plane_range(zk, w, plane_dz_mm, z_lo_mm, z_hi_mm)
    if np.any(count < 1):
        bad = int(ids[np.argmin(count)])
        raise ValueError(f"projection {bad}: no plane of [{z_lo_mm}, {z_hi_mm}] mm lies within its SSRB window")
    np_max = int(count.max()) if ids.size else 1
    C = scanner.n_cols
    out = np.zeros((ids.size, np_max, C), np.float32)
    slot = np.repeat(np.arange(ids.size), count)
    plane = np.concatenate([f + np.arange(n) for f, n in zip(first, count, strict=True)]) if ids.size else first
    dz = plane * plane_dz_mm - zk[slot]
    shift = None
    if table.focal_shift is not None:
        shift = spot_shift_in_frame(table.focal_shift[ids][slot], scanner.sid_mm)
    flat = rebin.ssrb_rows(proj, slot.astype(np.int32), dz.astype(np.float32), scanner, rt=rt,
                           first_row=first_row if proj.shape[1] != scanner.n_rows else None,
                           pair_shift=shift) if slot.size else np.zeros((0, C), np.float32)
    filter_rows(flat, geom, window, out=flat)
    within = np.concatenate([np.arange(n) for n in count]) if ids.size else np.zeros(0, np.int64)
    out[slot, within] = flat
    return PlaneRows(rows=out, plane_first=first.astype(np.int32), plane_count=count.astype(np.int32),
                     projection=ids, proj_z_mm=zk, plane_dz_mm=float(plane_dz_mm), window_mm=float(w))


def displacement_margin_mm(fields) -> float:
    """How far the model can move a point between two states (mm), the reach the kernel's atan fit
    covers (:func:`_defines`): twice the largest sum over b >= 1 of |U_b| components of ``fields``
    (NB, 3, ...) float32 (0 for the constant alone); (NB, 3, nz, ny, nx) fields a plane at a time."""
    f = np.asarray(fields)
    if f.shape[0] < 2:
        return 0.0
    if f.ndim == 5:  # (NB, 3, nz, ny, nx): plane by plane, no copy of the whole fields (the same maximum)
        return max(displacement_margin_mm(f[:, :, k]) for k in range(f.shape[2]))
    return float(np.abs(f[1:]).sum(axis=0).max()) * 2.0


@dataclass(frozen=True, kw_only=True)
class ModelWindow:
    """Planes ``first .. first + model.grid.nz - 1`` of a model on the grid ``whole``.

    ``model`` holds only those planes (its grid: theirs, ``nz >= 2``); the kernel samples on
    ``whole`` (its plane coordinates and its clamp at the end planes) and reads the held planes, so
    every sample whose two planes are held is the whole model's, bit for bit: the caller holds every
    plane its voxels' reference positions can reach (:func:`clrecon.reconstruction.motion.method.reach_planes`).
    ``margin_mm``: the whole model's :func:`displacement_margin_mm` (the kernel's build depends on it).
    """

    model: MotionModel
    whole: FieldGrid
    first: int
    margin_mm: float

    def __post_init__(self):
        g, w = self.model.grid, self.whole
        if (g.nx, g.ny, g.voxel_mm) != (w.nx, w.ny, w.voxel_mm):
            raise ValueError(f"the window's grid ({g.nx} x {g.ny} at {g.voxel_mm} mm) must be the whole model's "
                             f"in-plane grid ({w.nx} x {w.ny} at {w.voxel_mm} mm)")
        if not (isinstance(self.first, (int, np.integer)) and 0 <= self.first <= w.nz - g.nz):
            raise ValueError(f"first = {self.first!r}: the window's {g.nz} planes must lie within the whole "
                             f"model's {w.nz}")

    @property
    def basis(self):
        """The model's :class:`~clrecon.reconstruction.motion.model.MotionBasis` (a window holds all of it)."""
        return self.model.basis

    @classmethod
    def of(cls, model) -> ModelWindow:
        """``model`` as a window (a :class:`MotionModel`: every plane of it; a window: itself)."""
        if isinstance(model, ModelWindow):
            return model
        return cls(model=model, whole=model.grid, first=0, margin_mm=displacement_margin_mm(model.fields))


@dataclass(frozen=True, kw_only=True)
class MCConfig:
    """Knobs of the kernel: ``taper_mm`` (width of the weight's fall to 0 at the SSRB window, mm,
    > 0), ``inversion_steps`` (fixed-point steps of the model's inversion)."""

    taper_mm: float = 2.0
    inversion_steps: int = INVERSION_STEPS

    def __post_init__(self):
        if not (isinstance(self.taper_mm, (int, float)) and math.isfinite(self.taper_mm) and self.taper_mm > 0):
            raise ValueError(f"taper_mm = {self.taper_mm!r}: must be a finite number > 0")
        if not (isinstance(self.inversion_steps, int) and 0 <= self.inversion_steps <= 64):
            raise ValueError(f"inversion_steps = {self.inversion_steps!r}: must be an integer in [0, 64]")


def _check(rows: PlaneRows, slot_proj, slot_w, model: MotionModel, target, slices_z, geom: FanBeamGeometry):
    sp = np.asarray(slot_proj)
    sw = np.asarray(slot_w)
    S = len(np.atleast_1d(slices_z))
    if sp.ndim != 3 or sp.shape[:2] != (S, geom.n_views) or sw.shape != sp.shape:
        raise ValueError(f"slot_proj {sp.shape} and slot_w {sw.shape}: expected (S, V, K) = ({S}, {geom.n_views}, K)")
    if sp.dtype.kind not in "iu":
        raise TypeError(f"slot_proj: expected integers (local projection indices), got {sp.dtype}")
    P = rows.rows.shape[0]
    if sp.size and (sp.max() >= P or sp.min() < -1):
        raise ValueError(f"slot_proj: values must lie in [-1, {P})")
    if not np.all(np.isfinite(sw)) or np.any(sw < 0):
        raise ValueError("slot_w: weights must be finite and >= 0")
    g = model.grid
    if (g.nx, g.ny) != (geom.nx, geom.ny) or not math.isclose(g.voxel_mm, geom.voxel_mm):
        raise ValueError(f"the model's grid ({g.nx} x {g.ny} at {g.voxel_mm} mm) must be the reconstruction's "
                         f"in-plane grid ({geom.nx} x {geom.ny} at {geom.voxel_mm} mm)")
    if rows.rows.shape[2] != geom.n_cols:
        raise ValueError(f"rows: {rows.rows.shape[2]} columns, the geometry has {geom.n_cols}")
    c, a = target
    if not (math.isfinite(c) and math.isfinite(a)):
        raise ValueError(f"target = {target!r}: must be a finite (c, a)")


def mc_backproject_reference(rows: PlaneRows, proj_basis, slot_proj, slot_w, model: MotionModel | ModelWindow,
                             target, slices_z, geom: FanBeamGeometry, cfg: MCConfig | None = None) -> np.ndarray:
    """Float64 NumPy reference of :func:`mc_backproject`, step for step as the kernel; (S, ny, nx) mu."""
    cfg = cfg or MCConfig()
    win = ModelWindow.of(model)
    model, g, first = win.model, win.whole, win.first
    _check(rows, slot_proj, slot_w, model, target, slices_z, geom)
    F = model.fields.astype(np.float64)
    tb = model.basis.values(*target)[0].astype(np.float32).astype(np.float64)
    u_t = np.tensordot(tb.astype(np.float32), model.fields, axes=(0, 0)).astype(np.float64)
    pb = np.asarray(proj_basis, np.float32).astype(np.float64)
    trig = view_table(geom).astype(np.float64)  # the kernel's own (float32) table
    S = len(slices_z)
    x = (np.arange(geom.nx) - 0.5 * (geom.nx - 1)) * geom.voxel_mm
    y = (np.arange(geom.ny) - 0.5 * (geom.ny - 1)) * geom.voxel_mm
    out = np.zeros((S, geom.ny, geom.nx))
    R = rows.rows.astype(np.float64)
    C = geom.n_cols
    fov = x[None, :] ** 2 + y[:, None] ** 2 <= geom.fov_radius_mm ** 2
    for s in range(S):
        X, Y = np.meshgrid(x, y)
        X, Y = X[fov], Y[fov]
        Z = np.full_like(X, float(slices_z[s]))
        rx, ry, rz = X.copy(), Y.copy(), Z.copy()
        for _ in range(cfg.inversion_steps):
            u = _trilinear(u_t, g, rx, ry, rz, first)
            rx, ry, rz = X - u[0], Y - u[1], Z - u[2]
        Wb = _trilinear(F.reshape((-1,) + model.grid.shape), g, rx, ry, rz, first).reshape(F.shape[0], 3, -1)
        acc = np.zeros_like(X)
        for j in range(geom.n_views):
            num = np.zeros_like(X)
            den = np.zeros_like(X)
            best_tz = np.full_like(X, np.inf)
            best_val = np.zeros_like(X)
            for k in range(slot_proj.shape[2]):
                p = int(slot_proj[s, j, k])
                if p < 0:
                    break
                w0 = float(np.float32(slot_w[s, j, k]))
                if w0 == 0.0:
                    continue
                beta = pb[p, 1:] - tb[1:]
                d = np.tensordot(beta, Wb[1:], axes=(0, 0))
                zm = Z + d[2]
                col, wd = _fan_column(X + d[0], Y + d[1], trig[j], geom)
                col = np.clip(col, 0.0, C - 1)
                i0 = np.minimum(np.floor(col).astype(np.int64), C - 2)
                tc = col - i0
                cnt = int(rows.plane_count[p])
                gz = np.clip(zm / rows.plane_dz_mm - rows.plane_first[p], 0.0, cnt - 1)
                g0 = np.maximum(np.minimum(np.floor(gz).astype(np.int64), cnt - 2), 0)
                g1 = np.minimum(g0 + 1, cnt - 1)
                tg = gz - g0
                r0, r1 = R[p, g0], R[p, g1]
                val = ((1 - tg) * ((1 - tc) * r0[np.arange(len(X)), i0] + tc * r0[np.arange(len(X)), i0 + 1])
                       + tg * ((1 - tc) * r1[np.arange(len(X)), i0] + tc * r1[np.arange(len(X)), i0 + 1]))
                dzp = np.abs(zm - float(np.float32(rows.proj_z_mm[p])))
                taper = np.clip((rows.window_mm - dzp) / cfg.taper_mm, 0.0, 1.0)
                w = w0 * taper
                num += w * wd * val
                den += w
                closer = dzp < best_tz
                best_tz = np.where(closer, dzp, best_tz)
                best_val = np.where(closer, wd * val, best_val)
            acc += np.where(den > 0, num / np.where(den > 0, den, 1.0), best_val)
        out[s][fov] = acc * geom.delta_beta_rad
    return out


def _trilinear(f, g, px, py, pz, first: int = 0):
    """Kernel-style trilinear samples of fields (n, nz, ny, nx) at points: (n, m) float64; the fields
    hold planes ``first ..`` of grid ``g`` (a :class:`ModelWindow`'s)."""
    fx = np.clip(px / g.voxel_mm + 0.5 * (g.nx - 1), 0, g.nx - 1)
    fy = np.clip(py / g.voxel_mm + 0.5 * (g.ny - 1), 0, g.ny - 1)
    fz = np.clip((pz - g.z0_mm) / g.dz_mm, 0, g.nz - 1)
    ix = np.minimum(np.floor(fx).astype(np.int64), g.nx - 2)
    iy = np.minimum(np.floor(fy).astype(np.int64), g.ny - 2)
    iz = np.minimum(np.floor(fz).astype(np.int64), g.nz - 2)
    tx, ty, tz = fx - ix, fy - iy, fz - iz
    iz = iz - first
    f = np.asarray(f, np.float64)
    if f.ndim == 3:
        f = f[None]

    def at(a, b, c):
        return f[:, iz + a, iy + b, ix + c]

    return ((1 - tz) * ((1 - ty) * ((1 - tx) * at(0, 0, 0) + tx * at(0, 0, 1))
                        + ty * ((1 - tx) * at(0, 1, 0) + tx * at(0, 1, 1)))
            + tz * ((1 - ty) * ((1 - tx) * at(1, 0, 0) + tx * at(1, 0, 1))
                    + ty * ((1 - tx) * at(1, 1, 0) + tx * at(1, 1, 1))))


def _fan_column(x, y, cs, geom: FanBeamGeometry):
    """Float64 form of fan_column.h: (fractional column, weight) of points in one view."""
    ur = 1.0 - (x * cs[0] + y * cs[1])
    if geom.curved:
        vr = y * cs[0] - x * cs[1]
        return np.arctan2(vr, ur) / geom.delta_gamma_rad + geom.centre_col, 1.0 / (ur * ur + vr * vr)
    r = 1.0 / ur
    return geom.sdd_mm / geom.col_pitch_mm * (y * cs[0] - x * cs[1]) * r + 0.5 * (geom.n_cols - 1), r * r


def _defines(geom: FanBeamGeometry, nb: int, cfg: MCConfig, margin_mm: float, lanes: int,
             local_size: tuple = LOCAL_SIZE, view_chunk: int = VIEW_CHUNK) -> dict:
    d = {"LANES": int(lanes), "LX": int(local_size[0]), "LY": int(local_size[1]), "VCHUNK": int(view_chunk),
         "NB": int(nb),
         "NINV": int(cfg.inversion_steps), "_fast": True}
    if geom.curved:
        # moved points may leave the FOV circle by the largest displacement: fit atan that far
        r = geom.fov_radius_mm + margin_mm
        rmin = geom.sid_mm - max((abs(s[1]) for s in geom.source_shifts), default=0.0)
        t_max = min(1.0, round(1.02 * math.tan(math.asin(min(1.0, r / rmin))), 6))
        d["CURVED"] = 1
        d.update(atan_defines(t_max, 1.0 / geom.delta_gamma_rad))
    return d


def lanes_for(device) -> int:
    """The kernel's lanes on an OpenCL device: 16 where its native float vector holds 16 (AVX-512),
    else 8. Measured on the 2-core Xeon with AVX-512 (docs/results/mc-cost.md "Cost"): 16 lanes as
    fast as 8 on Intel's CPU runtime, 1.1-1.3x on PoCL; on a CPU with 256-bit vectors a 16-float
    vector is two registers and the kernel's 15 displacement vectors would not fit in 16."""
    if LANES is not None:
        return LANES
    try:
        width = int(device.native_vector_width_float)
    except Exception:  # noqa: BLE001 - a device that does not say: the narrower choice
        width = 0
    return 16 if width >= 16 else 8


def launch_shape(device) -> tuple[tuple[int, int], int]:
    """((LX, LY) local size, views per chunk) of the kernel on an OpenCL device: Intel's CPU runtime
    gets :data:`INTEL_LOCAL_SIZE`, every other device :data:`LOCAL_SIZE`. The shape changes which
    work-item computes a voxel, never how: the images are the same bits."""
    try:
        name = str(device.platform.name)
    except Exception:  # noqa: BLE001 - a device that does not say: the default
        name = ""
    if drivers.INTEL.matches(name):
        return INTEL_LOCAL_SIZE, INTEL_VIEW_CHUNK
    return LOCAL_SIZE, VIEW_CHUNK


def _global_size(geom: FanBeamGeometry, n_slices: int, lanes: int, local_size: tuple = LOCAL_SIZE) -> tuple:
    """The kernel's global size for ``lanes`` voxels along x per work-item (``local_size`` multiples)."""
    lx, ly = local_size
    blocks = -(-geom.nx // lanes)  # work-items along x
    return (-(-blocks // lx) * lx, -(-geom.ny // ly) * ly, n_slices)


class MCBackprojector:
    """The kernel with one set of rows, model and geometry on the device; one call per target.

    ``rows`` (:class:`PlaneRows`), ``proj_basis`` (P, NB) the basis at each row's (c, a),
    ``model`` (a :class:`MotionModel`, or a :class:`ModelWindow` of the planes the slices reach:
    the same images, bit for bit), ``slices_z`` (S,), ``geom``. Device buffers are released by :meth:`release`
    (or ``with``).
    """

    def __init__(self, rows: PlaneRows, proj_basis, model: MotionModel | ModelWindow, slices_z,
                 geom: FanBeamGeometry, cfg: MCConfig | None = None, runtime=None):
        self.cfg = cfg or MCConfig()
        self.rt = runtime or get_runtime()
        self.window = ModelWindow.of(model)
        model = self.window.model
        self.rows, self.model, self.geom = rows, model, geom
        self.slices_z = np.asarray(slices_z, np.float64)
        pb = np.asarray(proj_basis)
        if pb.shape != (rows.rows.shape[0], model.basis.size):
            raise ValueError(f"proj_basis: expected ({rows.rows.shape[0]}, {model.basis.size}), got {pb.shape}")
        g = model.grid
        if rows.rows.shape[1] * rows.rows.shape[2] >= 2 ** 31 or g.nz * g.ny * g.nx >= 2 ** 31:
            raise ValueError(f"one projection's plane rows ({rows.rows.shape[1]} x {rows.rows.shape[2]}) and one "
                             f"field component ({g.nz} x {g.ny} x {g.nx}) must each hold fewer than 2^31 values "
                             "(the kernel's int offsets)")
        rt = self.rt
        margin = self.window.margin_mm
        self.lanes = lanes_for(rt.device)
        self.local_size, self.view_chunk = launch_shape(rt.device)
        self._defines = _defines(geom, model.basis.size, self.cfg, margin, self.lanes, self.local_size,
                                 self.view_chunk)
        self._kernel = rt.kernel(_KERNEL_FILE, "mc_backproject", **self._defines)
        self._pb = pb.astype(np.float32)  # the per-call differences B_b(p) - B_b(t) start from it
        # the rows and the fields in place where the device reads host memory (a CPU device, page-aligned
        # float32: method.slab_rows and method.refine make them so), else a device copy
        self._bufs = [rt.share_with_device(rows.rows, "plane rows"),
                      rt.to_device(rows.plane_first, np.int32), rt.to_device(rows.plane_count, np.int32),
                      rt.to_device(rows.proj_z_mm, np.float32)]
        self._fields = rt.share_with_device(model.fields, "model fields")
        self._trig = rt.to_device(view_table(geom), np.float32)
        self._slices = rt.to_device(self.slices_z, np.float32)
        S = len(self.slices_z)
        self._out = rt.empty((S, geom.ny, geom.nx))

    def __call__(self, slot_proj, slot_w, target) -> np.ndarray:
        """mu images (S, ny, nx) float32 of target (c, a) from its slots (S, V, K) (local indices, weights)."""
        gsize = _global_size(self.geom, len(self.slices_z), self.lanes, self.local_size)
        return self._launch(self._kernel, gsize, self.local_size, slot_proj, slot_w, target)

    def _launch(self, kernel, gsize, lsize, slot_proj, slot_w, target, scalar: bool = False) -> np.ndarray:
        """Run ``kernel`` on global size ``gsize``, local ``lsize`` (x, y); (S, ny, nx) float32.

        The kernel takes the basis differences B_b(p) - B_b(t) (P, NB) float32, formed here per
        call; ``scalar``: the reference kernel of kernels/reference/, which takes B(p) (P, NB) and
        B(t) (NB,) and subtracts them itself (the same float32 subtraction)."""
        geom, rt, g = self.geom, self.rt, self.window.whole
        _check(self.rows, slot_proj, slot_w, self.model, target, self.slices_z, geom)
        tb = self.model.basis.values(*target)[0].astype(np.float32)
        u_t = np.tensordot(tb, self.model.fields, axes=(0, 0)).astype(np.float32)
        sp = rt.to_device(slot_proj, np.int32, "slot_proj")
        sw = rt.to_device(slot_w, np.float32, "slot_w")
        ut = rt.to_device(u_t, np.float32, "target field")
        if scalar:
            basis = [rt.to_device(self._pb, np.float32, "proj_basis"), rt.to_device(tb, np.float32)]
            head, tail = basis[:1], basis[1:]
        else:
            basis = [rt.to_device(self._pb - tb, np.float32, "basis differences")]
            head, tail = basis, []
        S, V, K = np.asarray(slot_proj).shape
        col_centre = geom.centre_col if geom.curved else 0.5 * (geom.n_cols - 1)
        scale = 1.0 / geom.delta_gamma_rad if geom.curved else geom.sdd_mm / geom.col_pitch_mm
        ev = kernel(rt.queue, gsize, tuple(lsize) + (1,), *self._bufs, *head, sp, sw, self._fields, ut, *tail,
                    self._trig, self._slices, self._out,
                    np.int32(geom.nx), np.int32(geom.ny), np.int32(geom.n_views), np.int32(geom.n_cols),
                    np.float32(geom.voxel_mm), np.float32(scale), np.float32(geom.fov_radius_mm ** 2),
                    np.float32(geom.delta_beta_rad), np.float32(col_centre),
                    np.int32(S), np.int32(K), np.int32(self.rows.rows.shape[1]),
                    np.float32(1.0 / self.rows.plane_dz_mm), np.int32(g.nz), np.float32(g.z0_mm),
                    np.float32(1.0 / g.dz_mm), np.int32(self.window.first), np.int32(self.model.grid.nz),
                    np.float32(self.rows.window_mm),
                    np.float32(1.0 / self.cfg.taper_mm))
        res = rt.from_device(self._out, (S, geom.ny, geom.nx), wait_for=[ev])
        for b in [sp, sw, ut] + basis:
            b.release()
        return res

    def release(self) -> None:
        for b in self._bufs + [self._fields, self._trig, self._slices, self._out]:
            b.release()
        self._bufs = []

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.release()


def mc_backproject(rows: PlaneRows, proj_basis, slot_proj, slot_w, model: MotionModel | ModelWindow, target, slices_z,
                   geom: FanBeamGeometry, cfg: MCConfig | None = None, runtime=None) -> np.ndarray:
    """Motion-compensated backprojection of one target: mu (S, ny, nx) float32 (1/mm).

    Parameters
    ----------
    rows : PlaneRows (filtered)
    proj_basis : (P, NB) basis values at each projection's recorded (c, a)
    slot_proj : (S, V, K) int local projection indices (``rows.local_index``), -1 = empty, at the ends
    slot_w : (S, V, K) float weights >= 0 (normalised per view by the kernel)
    model : MotionModel on the reconstruction's in-plane grid, or a ModelWindow of its planes
    target : (c, a) of the target state
    slices_z : (S,) slice z (mm)
    geom : FanBeamGeometry
    """
    with MCBackprojector(rows, proj_basis, model, slices_z, geom, cfg, runtime) as bp:
        return bp(slot_proj, slot_w, target)
