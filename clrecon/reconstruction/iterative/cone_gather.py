"""Voxel-driven cone-beam backprojection B ~ A^T of the voxel projector: a gather (``kernels/cone_gather.cl``).

:func:`clrecon.reconstruction.iterative.cone_backprojector.backproject_volume` applies the exact
transpose A^T of Joseph's projector by scattering each ray's value along its samples, a 64-bit
fixed-point scatter that the CPU drivers run lane by lane, several times the projector's time
(measured in docs/iterative.md "Backprojectors"). :func:`gather_backproject` applies the voxel-driven
B instead, as RTK's SART and most iterative CT codes pair a ray-driven projector with it: each
voxel centre is projected onto the detector in every view and reads the values there bilinearly
(between cell centres, zero beyond the outermost ones), weighted by the voxel's expected Joseph
weight summed over the rays near it,

    V |w| (D . n)^2 / (du dv |w . n|^3)   (mm)

(V the voxel's volume, w = voxel - source, D = detector centre - source, n the detector plane's
normal, du and dv the local pitch of the cells on the flat plane: the voxel's volume times the
rays' density across it). For a smooth y, ``B y`` follows ``A^T y`` (tested against the matched
transpose); per voxel and view the two differ by the aliasing of Joseph's bilinear weights with
the ray spacing, which SART's normalisation by ``B 1`` carries consistently (update and column
sums from the same B). B is not A's transpose: the dot-product test does not apply to it.

Geometry as :func:`clrecon.simulation.voxel_projector.project_volume`: ``origin_mm``, ``spacing_mm``
(x, y, z), per-view frames ``src, det_centre, e_u, e_v`` (m, 3), cell centres ``u_mm`` (C,) and
``v_mm`` (R,) (each strictly monotone, at least 2), ``v_scale`` (C,) for a cylindrical detector's
flat-equivalent cells; a flying focal spot is one call per spot state, as for the projector.

Determinism: one work-item per voxel sums its views in order in float32 (no atomics); launches
(``CHUNK_CELLS`` detector cells each, set by the shapes alone) are added in float64 in order: the
result does not depend on the executor or the process, only on the shapes.
"""

from __future__ import annotations

import numpy as np

from clrecon.core.runtime import get_runtime
from clrecon.reconstruction.iterative.cone_backprojector import _check_proj, _check_shape
from clrecon.simulation.voxel_projector import CHUNK_CELLS, _check_frames, check_v_scale

#: floats per view record (kernels/cone_gather.cl)
GATHER_REC = 18


def plane_ranges(src, det, eu, ev, origin, spacing, shape, v, vs) -> np.ndarray:
    """(m, 2) the first and last z plane (index) whose voxel centres can read a detector row in each view,
    one plane of margin each side; (1, 0) where none can. On a plane in front of the source the
    row coordinate ``v'`` is a linear-fractional function of the in-plane position, so its extremes
    over the plane's rectangle of centres are at the corners; a plane is kept where that range meets
    the rows' (one cell beyond the outermost centres, times the smallest and largest ``vscale``), or
    where a corner is not in front of the source. Conservative: culled planes get exactly nothing."""
    nz, ny, nx = shape
    n = np.cross(eu, ev)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    D = det - src
    Dn, Dv = np.sum(D * n, 1), np.sum(D * ev, 1)
    xs = origin[0] + spacing[0] * np.array([0, nx - 1, 0, nx - 1])
    ys = origin[1] + spacing[1] * np.array([0, 0, ny - 1, ny - 1])
    zs = origin[2] + spacing[2] * np.arange(nz)
    corners = np.stack(np.broadcast_arrays(xs[None, :], ys[None, :], zs[:, None]), -1)     # (nz, 4, 3)
    w = corners[None] - src[:, None, None, :]                                               # (m, nz, 4, 3)
    wn = np.einsum("mzcq,mq->mzc", w, n)
    front = wn * Dn[:, None, None] > 0
    vp = np.where(front, Dn[:, None, None] / np.where(front, wn, 1.0) * np.einsum("mzcq,mq->mzc", w, ev)
                  - Dv[:, None, None], 0.0)
    lo_row, hi_row = v[0] - (v[1] - v[0]), v[-1] + (v[-1] - v[-2])
    scales = (1.0, 1.0) if vs is None else (float(np.min(vs)), float(np.max(vs)))
    allow_lo = min(sc * lo_row for sc in scales)
    allow_hi = max(sc * hi_row for sc in scales)
    keep = ~np.all(front, axis=2) | ((vp.max(axis=2) >= allow_lo) & (vp.min(axis=2) <= allow_hi))   # (m, nz)
    out = np.tile(np.array([1, 0]), (len(src), 1))
    anyk = keep.any(axis=1)
    out[anyk, 0] = np.maximum(np.argmax(keep[anyk], axis=1) - 1, 0)
    out[anyk, 1] = np.minimum(nz - 1 - np.argmax(keep[anyk, ::-1], axis=1) + 1, nz - 1)
    return out


def _records(src, det, eu, ev, origin, spacing, shape, v, vs) -> np.ndarray:
    """(m, GATHER_REC) float64: a = (s - o) / h, n = e_u x e_v, e_u, e_v, D . n, D . e_u, D . e_v,
    the first and last z plane that can read the detector (:func:`plane_ranges`), 0."""
    n = np.cross(eu, ev)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    D = det - src
    rec = np.zeros((len(src), GATHER_REC))
    rec[:, 0:3] = (src - origin) / spacing
    rec[:, 3:6], rec[:, 6:9], rec[:, 9:12] = n, eu, ev
    rec[:, 12] = np.sum(D * n, 1)
    rec[:, 13] = np.sum(D * eu, 1)
    rec[:, 14] = np.sum(D * ev, 1)
    rec[:, 15:17] = plane_ranges(src, det, eu, ev, origin, spacing, shape, v, vs)
    return rec


def _monotone(c, name):
    """(centres increasing, flipped?) for strictly monotone centres; ValueError otherwise."""
    c = np.asarray(c, np.float64)
    if len(c) < 2:
        raise ValueError(f"{name} needs at least 2 cell centres for the voxel-driven backprojector, got {len(c)}")
    d = np.diff(c)
    if np.all(d > 0):
        return c, False
    if np.all(d < 0):
        return c[::-1].copy(), True
    raise ValueError(f"{name} must be strictly monotone (cell centres in order)")


def bracket_table(c) -> tuple[np.ndarray, float]:
    """For increasing centres ``c`` (n >= 2): (tab (T,) int32, inv_delta) with uniform bins of width
    delta = the smallest pitch from c[0]; tab[i] = the bracket k (c[k] <= bin start < c[k + 1], in
    [0, n - 2]) of bin i's start, so that any point of the bin lies in bracket tab[i] or the next
    (kernels/cone_gather.cl ``cell_coordinate``: O(1) instead of a search)."""
    c = np.asarray(c, np.float64)
    delta = float(np.min(np.diff(c)))
    T = int(np.ceil((c[-1] - c[0]) / delta)) + 1
    starts = c[0] + delta * np.arange(T)
    tab = np.clip(np.searchsorted(c, starts, side="right") - 1, 0, len(c) - 2)
    return tab.astype(np.int32), 1.0 / delta


def _prepare(projs, shape_zyx, origin_mm, spacing_mm, src, det_centre, e_u, e_v, u_mm, v_mm, v_scale):
    shape, origin, spacing = _check_shape(shape_zyx, origin_mm, spacing_mm)
    src, det, eu, ev, u, v = _check_frames(src, det_centre, e_u, e_v, u_mm, v_mm)
    m, n_rows, n_cols = len(src), len(v), len(u)
    projs = [_check_proj(p, m, n_rows, n_cols) for p in projs]
    u, flip_u = _monotone(u, "u_mm")
    v, flip_v = _monotone(v, "v_mm")
    vs = check_v_scale(v_scale, n_cols)
    if vs is not None and flip_u:
        vs = vs[::-1].copy()
    if flip_u:
        projs = [p[:, :, ::-1] for p in projs]
    if flip_v:
        projs = [p[:, ::-1, :] for p in projs]
    return shape, origin, spacing, (src, det, eu, ev), u, v, vs, projs


def gather_backproject(proj, shape_zyx, origin_mm, spacing_mm, src, det_centre, e_u, e_v, u_mm, v_mm, rt=None, *,
                       v_scale=None, proj2=None, chunk_views: int | None = None):
    """B proj (see the module docstring): (nz, ny, nx) float32 (mm x the units of ``proj``); with
    ``proj2`` (same shape) the pair (B proj, B proj2) from the same projections and weights.

    Raises ValueError for a wrong shape, a non-finite value, a non-positive spacing, cell centres
    that are not strictly monotone or fewer than 2 per axis; TypeError for a non-numeric array.
    """
    projs = (proj,) if proj2 is None else (proj, proj2)
    shape, origin, spacing, frames, u, v, vs, projs = _prepare(projs, shape_zyx, origin_mm, spacing_mm, src,
                                                               det_centre, e_u, e_v, u_mm, v_mm, v_scale)
    if chunk_views is not None and (int(chunk_views) != chunk_views or chunk_views < 1):
        raise ValueError(f"chunk_views must be an integer >= 1, got {chunk_views!r}")
    m, n_rows, n_cols = projs[0].shape
    nz, ny, nx = shape
    sums = [np.zeros(shape, np.float64) for _ in projs]
    if m == 0:
        return tuple(s.astype(np.float32) for s in sums) if proj2 is not None else sums[0].astype(np.float32)
    rt = rt or get_runtime()
    defines = {}
    extra = []
    if vs is not None:
        defines["CURVED"] = 1
        extra.append(rt.to_device(vs))
    if proj2 is not None:
        defines["PAIR"] = 1
    kern = rt.kernel("cone_gather.cl", "cone_gather", **defines)
    rec = _records(*frames, origin, spacing, shape, v, vs)
    u_buf, v_buf = rt.to_device(u), rt.to_device(v)
    tabs = []
    for c in (u, v):
        tab, inv = bracket_table(c)
        tabs += [rt.to_device(tab, np.int32), np.int32(len(tab)), np.float32(inv)]
    outs = [rt.empty(shape) for _ in projs]
    step = int(chunk_views or max(1, CHUNK_CELLS // (n_rows * n_cols)))
    for a in range(0, m, step):
        b = min(m, a + step)
        bufs = [rt.to_device(np.ascontiguousarray(p[a:b], np.float32)) for p in projs]
        pair = [bufs[1], outs[1]] if proj2 is not None else []
        kern(rt.queue, (nx, ny, nz), None, bufs[0], np.int32(nx), np.int32(ny), np.int32(nz),
             np.float32(spacing[0]), np.float32(spacing[1]), np.float32(spacing[2]),
             rt.to_device(rec[a:b]), np.int32(b - a), u_buf, v_buf, np.int32(n_cols), np.int32(n_rows),
             *tabs, *extra, *pair, outs[0])
        for s, o in zip(sums, outs, strict=True):
            s += rt.from_device(o, shape)
    out = tuple(s.astype(np.float32) for s in sums)
    return out if proj2 is not None else out[0]


def gather_backproject_reference(proj, shape_zyx, origin_mm, spacing_mm, src, det_centre, e_u, e_v, u_mm, v_mm,
                                 v_scale=None) -> np.ndarray:
    """:func:`gather_backproject` in float64 NumPy (for tests; small inputs): (nz, ny, nx) float64.

    Written from the formula (not from the kernel): the voxel's flat-plane point by intersecting
    the source-voxel line with the plane, its cell coordinates by ``np.interp`` on the centres
    (extrapolated with the end pitches), the bilinear read with zero outside the cells."""
    shape, origin, spacing, (src, det, eu, ev), u, v, vs, (y,) = _prepare(
        (proj,), shape_zyx, origin_mm, spacing_mm, src, det_centre, e_u, e_v, u_mm, v_mm, v_scale)
    y = np.asarray(y, np.float64)
    nz, ny, nx = shape
    zz, yy, xx = np.meshgrid(*(origin[k] + spacing[k] * np.arange(n) for k, n in ((2, nz), (1, ny), (0, nx))),
                             indexing="ij")
    p = np.stack([xx, yy, zz], -1).reshape(-1, 3)
    out = np.zeros(len(p))
    n_cols, n_rows = len(u), len(v)

    def coord(c, x):
        f = np.interp(x, c, np.arange(len(c)), left=np.nan, right=np.nan)
        lo, hi = x < c[0], x > c[-1]
        f[lo] = (x[lo] - c[0]) / (c[1] - c[0])
        f[hi] = len(c) - 1 + (x[hi] - c[-1]) / (c[-1] - c[-2])
        k = np.clip(np.floor(f).astype(int), 0, len(c) - 2)
        return f, c[k + 1] - c[k]

    for m in range(len(src)):
        n = np.cross(eu[m], ev[m])
        n /= np.linalg.norm(n)
        w = p - src[m]
        D = det[m] - src[m]
        wn, Dn = w @ n, D @ n
        ok = wn * Dn > 0
        t = np.where(ok, Dn / np.where(ok, wn, 1.0), 0.0)
        q = src[m] + t[:, None] * w - det[m]                # flat-plane point relative to the centre
        fc, du = coord(u, q @ eu[m])
        scale = np.ones(len(p)) if vs is None else np.interp(np.clip(fc, 0, n_cols - 1), np.arange(n_cols), vs)
        fr, dv = coord(v, (q @ ev[m]) / scale)
        ok &= (fc > -1) & (fc < n_cols) & (fr > -1) & (fr < n_rows)
        with np.errstate(divide="ignore", invalid="ignore"):          # wn = 0: not ok, weight unused
            weight = np.prod(spacing) * np.linalg.norm(w, axis=1) * Dn ** 2 / (du * dv * scale * np.abs(wn) ** 3)
        c0, r0 = np.floor(fc).astype(int), np.floor(fr).astype(int)
        a, b = fc - c0, fr - r0
        val = np.zeros(len(p))
        for j, wr in ((0, 1 - b), (1, b)):
            for i, wc in ((0, 1 - a), (1, a)):
                rr, cc = r0 + j, c0 + i
                inside = ok & (rr >= 0) & (rr < n_rows) & (cc >= 0) & (cc < n_cols)
                val[inside] += (wr * wc)[inside] * y[m, rr[inside], cc[inside]]
        with np.errstate(invalid="ignore"):
            out += np.where(ok, weight * val, 0.0)
    return out.reshape(shape)
