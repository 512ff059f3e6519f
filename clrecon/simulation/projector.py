"""Cone-beam projector: exact line integrals through the analytic phantom (stage 3 of the pipeline).

Takes the packed quadric objects of :mod:`clrecon.simulation.phantoms.analytic` (one set per view) and the
canonical per-view detector frames of :func:`clrecon.core.conventions.detector_frames`, and
returns ``proj[view, row, col]`` = integral of mu along the ray from the source through the
centre of each flat-detector cell (dimensionless, float32). Line integrals through
quadrics are closed-form (docs/simulation.md "Analytic projector"), so the
projections are exact up to float32 rounding -- no voxel "inverse crime".

The integral is over the whole line through source and cell; objects are assumed to lie in
front of the source (always so in CT). The OpenCL kernel is ``kernels/project.cl``.

Work split (measured on the PoCL CPU device, see :mod:`clrecon.bench.projector`):

- per (view, object), in float64 (``kernels/project_cull.cl``, one work-item per view; its NumPy
  reference :func:`prepare_records` is the fallback on devices without float64): culling
  of the object's bounding sphere against the pyramid of rays, the object's detector
  rectangle (projected corners of its bounding box), and a record of ray-independent
  constants expressed relative to the ray through the object's centre, so that float32
  never subtracts large numbers;
- per cell, in float32 (``kernels/project.cl``): one work-item per 8 neighbouring cells of
  a row (explicit float8); one work-group per 64 x 8 cell tile builds the tile's object
  list in local memory; a work-item skips objects (and cut ellipsoids) whose rectangle
  misses its cells, and uses the closed-form chord directly for plain ellipsoids and for
  cylinders whose end caps no ray of the view meets. A ray pays only for the objects it
  can hit: about 6 of the phantom's 142 per ray at the paper's 900 x 64 detector.

The supersampled voxeliser is :mod:`clrecon.simulation.voxelise`.
"""

from __future__ import annotations

import functools

import numpy as np

from clrecon.core.conventions import detector_coords, detector_frames
from clrecon.core.detector import spot_shift_in_frame
from clrecon.core.errors import SceneError
from clrecon.core.runtime import get_runtime
from clrecon.scan import signals
from clrecon.simulation import quadrics as q
from clrecon.simulation.phantom_sources import phantom_from_config
from clrecon.simulation.phantoms import layout as ph
from clrecon.simulation.voxel_projector import check_v_scale

# ---------------------------------------------------------------------------------------
# per (view, object) kernel record, float32; must match kernels/project.cl
REC = 76
R_FLAGS, R_MU, R_RECT, R_UC, R_VC, R_TC = 0, 1, slice(2, 6), 6, 7, 8
R_DC, R_EU, R_EV = slice(9, 12), slice(12, 15), slice(15, 18)
R_WU, R_WV, R_W0 = slice(18, 21), slice(21, 24), slice(24, 27)
R_BU, R_BV, R_B0, R_OX, R_OY, R_OZ = 27, 28, 29, 30, 31, 64
R_CUT_RECT = 68  # 2 x (u_lo, u_hi, v_lo, v_hi) of the cut ellipsoids
R_PLANE, R_CUT, CUT_STRIDE = 32, 40, 12
VIEW_REC = 12
#: local object-list capacity of a work-group (objects beyond it go in further passes)
LIST_MAX = 256
#: cells per work-item (float vector width) and work-group shapes (segments x rows)
VW = 8
_SHAPE_MULTIROW = (8, 8)
_SHAPE_ONEROW = (16, 1)
#: output cells per kernel launch (bounds the memory of one chunk: 64 MiB of float32)
CHUNK_CELLS = 1 << 24



def _local_box(objs):
    """Local bounding box lo, hi (..., 3) in [-1, 1], tightened by axis-aligned clip planes."""
    lo = -np.ones(objs.shape[:-1] + (3,))
    hi = np.ones_like(lo)
    R = objs[..., ph.AXES].reshape(objs.shape[:-1] + (3, 3))
    semi = objs[..., ph.SEMI]
    c = objs[..., ph.CENTRE]
    for k in range(ph.N_PLANES):
        n = objs[..., 17 + 4 * k:20 + 4 * k]
        d = objs[..., 20 + 4 * k]
        nl = np.einsum("...ji,...j->...i", R, n) * semi  # plane in local coords: nl . x' <= d - n . c
        rhs = d - q.dot(n, c)
        mag = np.abs(nl)
        big = mag.max(-1, keepdims=True)
        for ax in range(3):
            others = np.delete(mag, ax, axis=-1).max(-1)
            aligned = (mag[..., ax] > 0) & (others <= 1e-9 * big[..., 0])
            with np.errstate(divide="ignore", invalid="ignore"):
                bound = rhs / nl[..., ax]
            hi[..., ax] = np.where(aligned & (nl[..., ax] > 0), np.minimum(hi[..., ax], bound), hi[..., ax])
            lo[..., ax] = np.where(aligned & (nl[..., ax] < 0), np.maximum(lo[..., ax], bound), lo[..., ax])
    return lo, hi


_CORNERS = np.array([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)], dtype=np.float64)


def _uv(r, eu, ev):
    """Detector coordinates (u, v) of in-plane vectors r = u e_u + v e_v (reciprocal basis)."""
    n0 = q.cross(eu, ev)
    nn = q.dot(n0, n0)
    return q.dot(q.cross(r, ev), n0) / nn, q.dot(q.cross(eu, r), n0) / nn


def _rect(centre, axes_flat, semi, lo, hi, s, D0, eu, ev, n, nn):
    """Detector rectangle (u_lo, u_hi, v_lo, v_hi), each (K,), of a box's 8 corners.

    ``n`` is the detector normal pointing away from the source, ``nn = n . n``. A corner X
    projects to ``u = (D0 . n) ((X - s) . a_u) / ((X - s) . n) - D0 . a_u`` with
    ``a_u = (e_v x n0) / |n0|^2``, ``n0 = e_u x e_v`` (and alike for v), and the three
    dot products are linear in the corner, so the 8 corners cost 3 x 8 multiply-adds.
    A box reaching behind the source plane gets an infinite rectangle (never culled).
    """
    R = axes_flat.reshape(-1, 3, 3)
    cols = R * semi[:, None, :]                           # column j = local axis j x semi-axis j
    base = centre - s + q.apply(cols, lo)                  # corner (0, 0, 0), relative to the source
    span = cols * (hi - lo)[:, None, :]                   # edge vectors of the box, columns
    n0 = q.cross(eu, ev)
    nn0 = q.dot(n0, n0)
    a_u = q.cross(ev, n0) / nn0[:, None]
    a_v = q.cross(n0, eu) / nn0[:, None]
    vals = []
    for f in (n, a_u, a_v):
        fb = q.dot(base, f)
        fs = np.einsum("kij,ki->kj", span, f)             # f . edge_j, (K, 3)
        vals.append(fb[:, None] + fs @ _CORNERS.T)        # (K, 8)
    den, nu, nv = vals
    size = np.linalg.norm(base, axis=-1) + np.linalg.norm(span, axis=1).sum(-1)
    ok = den.min(-1) > 1e-9 * size * np.sqrt(nn)
    with np.errstate(divide="ignore", invalid="ignore"):
        lam = q.dot(D0, n)[:, None] / den
    u = lam * nu - q.dot(D0, a_u)[:, None]
    v = lam * nv - q.dot(D0, a_v)[:, None]
    inf = np.inf
    return np.stack([np.where(ok, u.min(-1), -inf), np.where(ok, u.max(-1), inf),
                     np.where(ok, v.min(-1), -inf), np.where(ok, v.max(-1), inf)], -1)


def prepare_records(objects, src, det_centre, e_u, e_v, u_range, v_range, cull=True):
    """Kernel records of the (view, object) pairs that can reach the detector.

    Parameters
    ----------
    objects : (m, n_obj, STRIDE) float64 packed objects (:mod:`clrecon.simulation.phantoms.analytic` layout).
    src, det_centre, e_u, e_v : (m, 3) per-view frames (mm).
    u_range, v_range : (lo, hi) mm, the outermost cell centres.
    cull : bool
        False keeps every active object for every view (the unculled reference).

    Returns
    -------
    rec : (K, REC) float32 records, ordered by view then object.
    view_index : (K,) int64 view of each record.
    """
    objs = np.asarray(objects, dtype=np.float64)
    m, n_obj, _ = objs.shape
    s = np.asarray(src, np.float64)
    D0v = np.asarray(det_centre, np.float64) - s
    euv, evv = np.asarray(e_u, np.float64), np.asarray(e_v, np.float64)
    nv = q.cross(euv, evv)
    nv *= np.sign(q.dot(D0v, nv))[:, None]  # detector normal pointing away from the source
    active = (objs[..., ph.KIND] != ph.KIND_NONE) & (objs[..., ph.MU] != 0.0)
    # side planes of the pyramid of rays through the outermost cell centres (unit normals
    # pointing inwards; degenerate sides of a one-row or one-column detector are zero)
    (ul, uh), (vl, vh) = u_range, v_range
    dirs = [D0v + a * euv + b * evv for a, b in ((ul, vl), (uh, vl), (uh, vh), (ul, vh))]
    inner = D0v + 0.5 * (ul + uh) * euv + 0.5 * (vl + vh) * evv
    sides = []
    for k in range(4):
        N = q.cross(dirs[k], dirs[(k + 1) % 4])
        norm = np.linalg.norm(N, axis=-1)
        live = norm > 1e-12 * q.dot(dirs[k], dirs[k])
        sgn = np.where(q.dot(N, inner) >= 0, 1.0, -1.0)
        sides.append(N * np.where(live, sgn / np.where(live, norm, 1.0), 0.0)[:, None])
    sides = np.stack(sides, 1)                                        # (m, 4, 3)

    if cull:
        # bounding sphere against the pyramid
        kind = objs[..., ph.KIND]
        semi = objs[..., ph.SEMI]
        rho = np.where(kind == ph.KIND_CYLINDER, np.hypot(np.maximum(semi[..., 0], semi[..., 1]), semi[..., 2]),
                       semi.max(-1))
        rel = objs[..., ph.CENTRE] - s[:, None, :]
        dist = np.einsum("mnj,mkj->mnk", rel, sides)                  # (m, n, 4)
        keep = active & np.all(dist >= -rho[..., None], axis=-1)
        depth = q.dot(rel, (nv / np.linalg.norm(nv, axis=-1, keepdims=True))[:, None, :])
        keep |= active & (depth <= rho)  # reaches the source plane: never culled
    else:
        keep = active
    iv, io = np.nonzero(keep)
    o = objs[iv, io]                                   # (K, STRIDE)
    K = len(iv)
    s, D0, eu, ev, n = s[iv], D0v[iv], euv[iv], evv[iv], nv[iv]
    nn = q.dot(n, n)
    kind = o[:, ph.KIND].astype(np.int64)
    c = o[:, ph.CENTRE]
    M = q.local_map(o[:, ph.AXES], o[:, ph.SEMI])

    # the ray through the centre: p_c = s + lam (c - s) on the detector, tc = 1 / lam
    rc = c - s
    den = q.dot(rc, n)
    front = den > 1e-12 * np.linalg.norm(rc, axis=-1) * np.sqrt(nn)
    with np.errstate(divide="ignore", invalid="ignore"):
        lam = np.where(front, q.dot(D0, n) / den, 1.0)
    pc_rel = np.where(front[:, None], rc * lam[:, None], D0)         # p_c - s
    tc = np.where(front, 1.0 / lam, q.dot(rc, D0) / q.dot(D0, D0))
    r = pc_rel - D0                                                   # p_c - det, in the plane
    uc, vc = _uv(r, eu, ev)
    Xc = s + tc[:, None] * pc_rel                                     # ray point at tau = 0
    oo = q.apply(M, Xc - c)
    dc, eul, evl = q.apply(M, pc_rel), q.apply(M, eu), q.apply(M, ev)
    cyl = kind == ph.KIND_CYLINDER
    t = tc[:, None]
    Wu = q.cross(oo, eul) + t * q.cross(eul, dc)
    Wv = q.cross(oo, evl) + t * q.cross(evl, dc)
    W0 = q.cross(oo, dc)
    mask = np.where(cyl[:, None], np.array([1.0, 1.0, 0.0]), 1.0)   # the quadric's axes
    Bu = q.dot(oo * mask, eul) + tc * q.dot(eul * mask, dc)
    Bv = q.dot(oo * mask, evl) + tc * q.dot(evl * mask, dc)
    B0 = q.dot(oo * mask, dc)

    rec = np.zeros((K, REC))
    rec[:, R_MU] = o[:, ph.MU]
    rec[:, R_UC], rec[:, R_VC], rec[:, R_TC] = uc, vc, tc
    rec[:, R_DC], rec[:, R_EU], rec[:, R_EV] = dc, eul, evl
    rec[:, R_WU], rec[:, R_WV], rec[:, R_W0] = Wu, Wv, W0
    rec[:, R_BU], rec[:, R_BV], rec[:, R_B0] = Bu, Bv, B0
    rec[:, R_OX], rec[:, R_OY], rec[:, R_OZ] = oo[:, 0], oo[:, 1], oo[:, 2]

    # clip planes (world): tau g <= k with g = g0 + du gu + dv gv, k = hk - tc (du gu + dv gv)
    nplanes = np.zeros(K, np.int64)
    for k in range(ph.N_PLANES):
        pn = o[:, 17 + 4 * k:20 + 4 * k]
        pd = o[:, 20 + 4 * k]
        on = np.any(pn != 0.0, axis=-1)
        vals = np.stack([q.dot(pn, pc_rel), q.dot(pn, eu), q.dot(pn, ev), pd - q.dot(pn, Xc)], -1)
        slot = R_PLANE + 4 * nplanes
        for j in range(4):
            rec[np.nonzero(on)[0], slot[on] + j] = vals[on, j]
        # a plane with n = 0 and d < 0 excludes everything: encode as g = 0, k = -1
        dead = (~on) & (pd < 0)
        rec[np.nonzero(dead)[0], R_PLANE + 4 * nplanes[dead] + 3] = -1.0
        nplanes += on | dead

    # cut ellipsoids, in their own normalised frames but on the same tau
    flags = kind | (nplanes << 2)
    lo, hi = _local_box(o)
    rect = _rect(c, o[:, ph.AXES], o[:, ph.SEMI], lo, hi, s, D0, eu, ev, n, nn)
    for k in range(ph.N_CUTS):
        mi, cs, ca, cm = ph.cut_fields(k)
        mode = o[:, mi].astype(np.int64)
        flags |= mode << (4 + 2 * k)
        j = np.nonzero(mode != ph.CUT_NONE)[0]
        if not len(j):
            continue
        M2 = q.local_map(o[j, ca], o[j, cm])
        base = R_CUT + CUT_STRIDE * k
        rec[j, base:base + 3] = q.apply(M2, Xc[j] - o[j, cs])
        rec[j, base + 3:base + 6] = q.apply(M2, pc_rel[j])
        rec[j, base + 6:base + 9] = q.apply(M2, eu[j])
        rec[j, base + 9:base + 12] = q.apply(M2, ev[j])
        r2 = _rect(o[j, cs], o[j, ca], o[j, cm], -np.ones((len(j), 3)), np.ones((len(j), 3)),
                   s[j], D0[j], eu[j], ev[j], n[j], nn[j])
        rect2 = r2 + np.array([-1.0, 1.0, -1.0, 1.0]) * (1e-4 + 1e-5 * np.abs(r2))
        rec[j, R_CUT_RECT + 4 * k:R_CUT_RECT + 4 * k + 4] = np.clip(rect2, -3e38, 3e38)
        isect = mode[j] == ph.CUT_INTERSECT  # the object lies inside the cut: intersect the rectangles
        ji = j[isect]
        rect[ji] = np.stack([np.maximum(rect[ji, 0], r2[isect, 0]), np.minimum(rect[ji, 1], r2[isect, 1]),
                             np.maximum(rect[ji, 2], r2[isect, 2]), np.minimum(rect[ji, 3], r2[isect, 3])], -1)
    # cylinders whose end caps no ray of the view meets: the kernel skips the slab. The rays
    # that meet an infinite cylinder form a connected family along which the chord moves
    # continuously, so if no ray crosses a cap disc and one ray (through a point of the
    # axis inside the pyramid) meets the finite part, every chord lies inside the slab.
    # A cap (in its bounding sphere) misses both nappes of the double pyramid if some
    # side sees it beyond -rho and some beyond +rho.
    sd = sides[iv]
    axis = o[:, ph.AXES].reshape(K, 3, 3)[:, :, 2]
    half = o[:, 16]
    rho_cap = np.maximum(o[:, 14], o[:, 15])
    no_slab = cyl.copy()
    for sgn in (-1.0, 1.0):
        dist = np.einsum("kj,kij->ki", c + sgn * half[:, None] * axis - s, sd)
        no_slab &= np.any(dist < -rho_cap[:, None], -1) & np.any(dist > rho_cap[:, None], -1)
    dd = inner[iv] / np.linalg.norm(inner[iv], axis=-1, keepdims=True)
    r0, b = s - c, q.dot(dd, axis)
    denom = 1.0 - b * b
    with np.errstate(divide="ignore", invalid="ignore"):
        t_ax = np.where(denom > 1e-12, (q.dot(r0, axis) - q.dot(r0, dd) * b) / denom, 0.0)
    on_axis = c + np.clip(t_ax, -half, half)[:, None] * axis - s
    no_slab &= np.all(np.einsum("kj,kij->ki", on_axis, sd) >= 0.0, -1) & (q.dot(on_axis, n) > 0.0)
    flags |= no_slab.astype(np.int64) << 8
    # a safety margin so that float32 rounding of the rectangle never culls a grazing ray
    pad = 1e-4 + 1e-5 * np.abs(rect)
    rect = rect + np.array([-1.0, 1.0, -1.0, 1.0]) * pad
    rec[:, R_RECT] = np.clip(rect, -3e38, 3e38)
    rec[:, R_FLAGS] = flags
    if cull:
        (ul, uh), (vl, vh) = u_range, v_range
        hit = (rect[:, 1] >= ul) & (rect[:, 0] <= uh) & (rect[:, 3] >= vl) & (rect[:, 2] <= vh)
        rec, iv = rec[hit], iv[hit]
    return rec.astype(np.float32), iv


# ---------------------------------------------------------------------------------------
def _as_frames(src, det_centre, e_u, e_v, m):
    out = []
    for name, a in (("src", src), ("det_centre", det_centre), ("e_u", e_u), ("e_v", e_v)):
        a = np.asarray(a)
        if a.dtype.kind not in "fiu":
            raise TypeError(f"{name}: expected a real array, got dtype {a.dtype}")
        if a.shape != (m, 3):
            raise ValueError(f"{name} must have shape ({m}, 3), got {a.shape}")
        out.append(np.asarray(a, dtype=np.float64))
    return out


class _Layout:
    """Detector-side arrays shared by every chunk: padded u, segment and tile ranges.

    With ``v_scale`` (n_cols,) the cell of column c, row r is the flat-equivalent point
    ``(u[c], v[r] * v_scale[c])`` (a cylindrical detector, kernel variant ``CURVED``); the v
    ranges of tiles and of the culling pyramid then cover every column's scaled rows.
    """

    def __init__(self, u, v, rt, v_scale=None):
        self.n_cols, self.n_rows = len(u), len(v)
        self.curved = v_scale is not None
        self.n_seg = -(-self.n_cols // VW)
        self.lx, self.ly = _SHAPE_MULTIROW if self.n_rows > 1 else _SHAPE_ONEROW
        u_pad = np.concatenate([u, np.full(self.n_seg * VW - self.n_cols, u[-1])])
        seg = u_pad.reshape(self.n_seg, VW)
        seg_lo, seg_hi = seg.min(1), seg.max(1)
        ntx = -(-self.n_seg // self.lx)
        nty = -(-self.n_rows // self.ly)
        tile_u = np.array([[seg_lo[i * self.lx:(i + 1) * self.lx].min(), seg_hi[i * self.lx:(i + 1) * self.lx].max()]
                           for i in range(ntx)])
        tile_v = np.array([[v[j * self.ly:(j + 1) * self.ly].min(), v[j * self.ly:(j + 1) * self.ly].max()]
                           for j in range(nty)])
        self.global_xy = (ntx * self.lx, nty * self.ly)
        self.u_range = (float(u.min()), float(u.max()))
        self.v_range = (float(v.min()), float(v.max()))
        extra = []
        if self.curved:
            vs = check_v_scale(v_scale, self.n_cols)
            vs_pad = np.concatenate([vs, np.full(self.n_seg * VW - self.n_cols, vs[-1])]).reshape(self.n_seg, VW)
            vs_seg = np.stack([vs_pad.min(1), vs_pad.max(1)], 1)
            # a tile's rows at every column scale: v * [min, max] of the scales (conservative)
            lo_s, hi_s = float(vs.min()), float(vs.max())
            tile_v = np.stack([np.minimum(tile_v[:, 0] * lo_s, tile_v[:, 0] * hi_s),
                               np.maximum(tile_v[:, 1] * lo_s, tile_v[:, 1] * hi_s)], 1)
            self.v_range = (min(v.min() * lo_s, v.min() * hi_s), max(v.max() * lo_s, v.max() * hi_s))
            # float32 rounding of v * scale must never fall outside a range: widen a little
            tile_v = tile_v + np.array([-1.0, 1.0]) * (1e-4 + 1e-5 * np.abs(tile_v))
            extra = [vs_pad.ravel(), vs_seg]
        self.bufs = [rt.to_device(a) for a in (u_pad, seg_lo, seg_hi, v, tile_u, tile_v, *extra)]


def project_views(objects, src, det_centre, e_u, e_v, u_mm, v_mm, rt=None, *, cull: bool = True,
                  chunk_views: int | None = None, out=None, v_scale=None) -> np.ndarray:
    """Exact line integrals of per-view quadric objects on a flat detector (or flat-equivalent cells).

    Parameters
    ----------
    objects : (m, n_obj, STRIDE) array
        Packed objects per view (:mod:`clrecon.simulation.phantoms.analytic` layout; may be a broadcast view).
    src, det_centre, e_u, e_v : (m, 3) arrays
        Source, detector centre, column and row unit directions per view (mm).
    u_mm : (n_cols,) column centres; v_mm : (n_rows,) row centres (mm).
    rt : Runtime, optional
        OpenCL runtime (default :func:`clrecon.core.runtime.get_runtime`).
    cull : bool
        False: every ray visits every object (the reference of the culling test; slow).
    chunk_views : int, optional
        Views per kernel launch (default: ``CHUNK_CELLS`` output cells per launch).
    out : (m, n_rows, n_cols) float32 array, optional
        Written in place and returned.
    v_scale : (n_cols,) array, optional
        Cells at the flat-equivalent points ``(u[c], v[r] * v_scale[c])`` (a cylindrical
        detector: :meth:`clrecon.core.detector.CylindricalDetector.ray_cells`; kernel variant
        ``CURVED``). None: the flat cells ``(u[c], v[r])``.

    Returns
    -------
    (m, n_rows, n_cols) float32 line integrals of mu (dimensionless), ``proj[view, row, col]``.
    """
    objs = np.asarray(objects)
    if objs.dtype.kind not in "fiu":
        raise TypeError(f"objects: expected a real array, got dtype {objs.dtype}")
    if objs.ndim != 3 or objs.shape[2] != ph.STRIDE:
        raise ValueError(f"objects must have shape (m, n_obj, {ph.STRIDE}), got {objs.shape}")
    m = objs.shape[0]
    src, det, eu, ev = _as_frames(src, det_centre, e_u, e_v, m)
    u, v = q.as_axis(u_mm, "u_mm"), q.as_axis(v_mm, "v_mm")
    shape = (m, len(v), len(u))
    if out is None:
        out = np.empty(shape, np.float32)
    elif out.shape != shape or out.dtype != np.float32 or not out.flags.c_contiguous:
        raise ValueError(f"out must be a C-contiguous float32 array of shape {shape}")
    if m == 0:
        return out
    rt = rt or get_runtime()
    lay = _Layout(u, v, rt, v_scale)
    step = chunk_views or max(1, CHUNK_CELLS // (lay.n_rows * lay.n_cols))
    curved = {"CURVED": 1} if lay.curved else {}
    kern = rt.kernel("project.cl", "project", VW=VW, LX=lay.lx, LY=lay.ly, CULL=int(cull), LIST_MAX=LIST_MAX,
                     **curved)
    on_device = has_fp64(rt)
    view_rec = np.zeros((m, VIEW_REC))
    view_rec[:, 0:3], view_rec[:, 3:6], view_rec[:, 6:9] = det - src, eu, ev
    broadcast = objs.strides[0] == 0  # the same objects for every view (e.g. the ground truth)
    pending = None
    for a in range(0, m, step):
        b = min(m, a + step)
        # prepare chunk a while the device still works on the previous one
        if on_device:
            records = _prepare_on_device(rt, objs[a:b], broadcast, src[a:b], view_rec[a:b], lay, cull)
        else:
            records = _prepare_on_host(rt, objs[a:b], src[a:b], det[a:b], eu[a:b], ev[a:b], lay, cull)
        launch = _launch(rt, kern, lay, records, view_rec[a:b], cull, out[a:b])
        if pending is not None:
            pending[0].wait()
        pending = launch
    pending[0].wait()
    return out


def has_fp64(rt) -> bool:
    """Whether the device runs the float64 record kernel (else records are made with NumPy)."""
    return "cl_khr_fp64" in rt.device.extensions


def _prepare_on_device(rt, objs, broadcast, src, view_rec, lay, cull):
    """Records of one chunk by kernels/project_cull.cl: (record buffer, count buffer, n_obj, events)."""
    m, n_obj = objs.shape[0], objs.shape[1]
    # a posed batch (page-aligned by the phantom) is read in place by a CPU device: no copy of
    # its 64 KB per view into fresh pages (docs/kernels.md "Rows read in place")
    obj_buf = rt.to_device(objs[0], np.float64) if broadcast else rt.share_with_device(objs, "objects", np.float64)
    views = np.concatenate([src, view_rec[:, 0:9]], axis=1)
    rec_buf = rt.empty((m, n_obj, REC))
    cnt_buf = rt.empty((m,), np.int32)
    views_buf = rt.to_device(views, np.float64)
    kern = rt.kernel("project_cull.cl", "cull_records", CULL=int(cull))
    (ul, uh), (vl, vh) = lay.u_range, lay.v_range
    ev = kern(rt.queue, (m,), None, obj_buf, np.int64(0 if broadcast else n_obj * ph.STRIDE), np.int32(n_obj),
              views_buf, np.float64(ul), np.float64(uh), np.float64(vl), np.float64(vh),
              np.int32(m), rec_buf, cnt_buf)
    # every buffer a queued kernel uses stays referenced until its results are read
    return rec_buf, cnt_buf, n_obj, [ev], [obj_buf, views_buf, objs]


def prepare_records_device(objects, src, det_centre, e_u, e_v, u_range, v_range, cull=True, rt=None):
    """:func:`prepare_records` computed by ``kernels/project_cull.cl`` (for tests): (rec (K, REC), view_index)."""
    rt = rt or get_runtime()
    objs = np.asarray(objects, dtype=np.float64)
    src = np.asarray(src, np.float64)
    m, n_obj = objs.shape[:2]
    view_rec = np.zeros((m, VIEW_REC))
    view_rec[:, 0:3] = np.asarray(det_centre, np.float64) - src
    view_rec[:, 3:6], view_rec[:, 6:9] = e_u, e_v

    class _Ranges:
        pass

    lay = _Ranges()
    lay.u_range, lay.v_range = u_range, v_range
    rec_buf, cnt_buf, _, events, _keep = _prepare_on_device(rt, objs, objs.strides[0] == 0, src, view_rec, lay, cull)
    counts = rt.from_device(cnt_buf, (m,), np.int32, wait_for=events)
    rec = rt.from_device(rec_buf, (m, n_obj, REC))
    iv = np.repeat(np.arange(m), counts)
    slot = np.concatenate([np.arange(k) for k in counts]) if m else np.zeros(0, int)
    return rec[iv, slot], iv


def _prepare_on_host(rt, objs, src, det, eu, ev, lay, cull):
    """Records of one chunk by the NumPy reference :func:`prepare_records`, uploaded."""
    m, n_obj = objs.shape[0], objs.shape[1]
    rec, iv = prepare_records(objs, src, det, eu, ev, lay.u_range, lay.v_range, cull)
    counts = np.bincount(iv, minlength=m).astype(np.int32)
    start = np.concatenate([[0], np.cumsum(counts)[:-1]])
    packed = np.zeros((m, n_obj, REC), np.float32)
    packed[iv, np.arange(len(iv)) - start[iv]] = rec
    return rt.to_device(packed), rt.to_device(counts, np.int32), n_obj, [], []


def _launch(rt, kern, lay, records, view_rec, cull, dest):
    """Enqueue the projection of one chunk (a pass per LIST_MAX records when culling) and the
    copy of its result into ``dest``. Returns (copy event, buffers to keep alive until then)."""
    rec_buf, cnt_buf, n_obj, events, keep = records
    m = len(view_rec)
    out_buf = rt.empty((m, lay.n_rows, lay.n_cols))
    view_buf = rt.to_device(view_rec)
    keep = keep + [rec_buf, cnt_buf, view_buf, out_buf]
    gx, gy = lay.global_xy
    passes = range(0, n_obj, LIST_MAX) if cull else [0]
    for first in passes:
        events.append(kern(rt.queue, (gx, gy, m), (lay.lx, lay.ly, 1), rec_buf, cnt_buf, np.int32(first), view_buf,
                           *lay.bufs, np.int32(lay.n_cols), np.int32(lay.n_rows), np.int32(lay.n_seg),
                           np.int32(n_obj), np.int32(first > 0), out_buf, wait_for=events[-1:] or None))
    copy = rt.cl.enqueue_copy(rt.queue, dest, out_buf, wait_for=events[-1:], is_blocking=False)
    return copy, keep


# ---------------------------------------------------------------------------------------
@functools.lru_cache(maxsize=8)
def _phantom_for(cfg):
    """The phantom of a phantom config (its ``kind`` picks the registered source), cached per config."""
    return phantom_from_config(cfg)


@functools.lru_cache(maxsize=8)
def phantom_for_scene(scene):
    """The scene's phantom source, with frame states bound where they come from the scene's signals.

    A voxel phantom with ``timing = "scene"`` (``needs_scene_states``) gets each frame's
    (c, a) = the pose the scene gives at the frame's time
    (:func:`clrecon.scan.signals.physiology`, ``state_cardiac``, ``state_resp``); every other
    source is returned as built from ``scene.phantom``. Cached per scene.
    """
    phantom = _phantom_for(scene.phantom)
    if getattr(phantom, "needs_scene_states", False):
        try:
            phys = signals.physiology(scene, phantom.frame_times_s)
        except ValueError as e:
            raise SceneError(f"phantom.frames ({phantom.series.header.name}), timing = 'scene': "
                             f"frame times {e}") from None
        phantom = phantom.with_states(phys.state_cardiac, phys.state_resp)
    return phantom


def spot_frames(det, angle_rad, source_z_mm, shift_mm):
    """Frames of the flat-equivalent plane of a (possibly shifted) focal spot, for :func:`project_views`.

    ``det`` a detector model, ``angle_rad``, ``source_z_mm`` (m,) the focal centre, ``shift_mm``
    (3,) the spot's offset (a, b, c) in the focal-centre frame
    (:func:`clrecon.core.detector.spot_shift_in_frame`). Returns ``(spot, plane_centre, e_u, e_v)``
    (m, 3) each and the cells ``(u_eq, v_eq, v_scale)``: the plane lies at distance SDD from the
    spot along the central ray n, so that ``plane_centre + u_eq e_u + v_eq v_scale e_v`` is on
    the ray from the spot through each cell. For the flat detector (no shift) these are its own
    frames and cells, ``v_scale = None``.
    """
    src, centre, eu, ev = det.frames(angle_rad, source_z_mm)
    u_eq, v_scale, c_off = det.ray_cells(shift_mm)
    if v_scale is None:
        return (src, centre, eu, ev), (u_eq, det.v_mm(), None)
    a, b, c = (float(x) for x in shift_mm)
    n = (centre - src) / det.sdd_mm
    spot = src + a * n + b * eu + c * ev
    return (spot, spot + det.sdd_mm * n, eu, ev), (u_eq, det.v_mm() - c_off, v_scale)


def project(scene, table, rt=None, *, chunk_views: int | None = None, cull: bool = True) -> np.ndarray:
    """Line integrals of the scene's phantom for every projection of ``table``.

    The phantom is posed at ``(table.state_cardiac, table.state_resp)`` per projection; the
    frames and cells come from the scene's detector model (``scene.scanner.detector_model``:
    the flat panel's :func:`clrecon.core.conventions.detector_frames` and ``detector_coords``,
    or the cylindrical arc's flat-equivalent cells, :func:`spot_frames`) with
    ``(table.angle_rad, table.source_z_mm)`` and, with a flying focal spot, each projection's
    focal-spot shift (``table.focal_shift``; projections are grouped by focal-spot state).
    Chunked internally, so memory stays bounded whatever ``len(table)``.

    Dispatch by phantom source: a source that carries its own projector
    (``carries_projector``, e.g. the voxel phantom) gets each chunk's states and frames
    (``source.project(c, a, src, det, e_u, e_v, u, v, rt, out)``); the analytic thorax's
    quadrics go through :func:`project_views` (``cull`` applies to it only).

    Returns
    -------
    (len(table), n_rows, n_cols) float32.
    """
    sc = scene.scanner
    phantom = phantom_for_scene(scene)
    own = getattr(phantom, "carries_projector", False)
    n = len(table)
    out = np.empty((n, sc.n_rows, sc.n_cols), np.float32)
    step = chunk_views or max(1, CHUNK_CELLS // (sc.n_rows * sc.n_cols))
    rt = rt or get_runtime()
    if sc.detector == "flat":
        u = detector_coords(sc.n_cols, sc.col_pitch_mm)
        v = detector_coords(sc.n_rows, sc.row_pitch_mm)
        for a in range(0, n, step):
            sl = slice(a, min(n, a + step))
            src, det, eu, ev = detector_frames(table.angle_rad[sl], table.source_z_mm[sl], sc.sid_mm, sc.sdd_mm)
            if own:
                phantom.project(table.state_cardiac[sl], table.state_resp[sl], src, det, eu, ev, u, v, rt=rt,
                                out=out[sl])
                continue
            objs = phantom.objects_batch(table.state_cardiac[sl], table.state_resp[sl])
            project_views(objs, src, det, eu, ev, u, v, rt=rt, cull=cull, out=out[sl])
        return out
    dm = sc.detector_model
    frame_shift = spot_shift_in_frame(table.shifts, sc.sid_mm)            # (n, 3)
    states, inverse = np.unique(frame_shift, axis=0, return_inverse=True)
    inverse = np.asarray(inverse).reshape(-1)
    # chunks of ``step`` views; the phantom is posed once per chunk (its per-call cost is fixed),
    # then each focal-spot state's views are projected with that state's flat-equivalent cells
    for a in range(0, n, step):
        b = min(n, a + step)
        objs = None if own else phantom.objects_batch(table.state_cardiac[a:b], table.state_resp[a:b])
        for k, shift in enumerate(states):
            loc = np.flatnonzero(inverse[a:b] == k)
            if not len(loc):
                continue
            rows = a + loc
            frames, (u, v, vs) = spot_frames(dm, table.angle_rad[rows], table.source_z_mm[rows], shift)
            whole = len(loc) == b - a
            dest = out[a:b] if whole else np.empty((len(rows), sc.n_rows, sc.n_cols), np.float32)
            if own:
                phantom.project(table.state_cardiac[rows], table.state_resp[rows], *frames, u, v, rt=rt, out=dest,
                                v_scale=vs)
            else:
                project_views(objs if whole else objs[loc], *frames, u, v, rt=rt, cull=cull, out=dest, v_scale=vs)
            if not whole:
                out[rows] = dest
    return out
