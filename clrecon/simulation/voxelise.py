"""Supersampled point-sample voxeliser of packed quadric objects (``kernels/voxelise.cl``).

Used by :meth:`clrecon.simulation.phantoms.analytic.Phantom.voxelise` for the phantom truth
volumes and the ray-marching checks. Output mu (nz, ny, nx) float32 in 1/mm.
"""

from __future__ import annotations

import numpy as np

from clrecon.core.runtime import get_runtime
from clrecon.simulation import quadrics as q
from clrecon.simulation.phantoms import layout as ph

#: per object voxeliser record, float32; must match kernels/voxelise.cl
VREC = 64
#: cells per work-item (float vector width) of the voxeliser kernel
VW = 8


def voxel_records(objects) -> np.ndarray:
    """Voxeliser records (n_obj, VREC) float32 of packed objects (n_obj, STRIDE), world frame."""
    o = np.asarray(objects, dtype=np.float64)
    n = len(o)
    rec = np.zeros((n, VREC))
    kind = o[:, ph.KIND].astype(np.int64)
    c = o[:, ph.CENTRE]
    ext = q.box_half_extent(o[:, ph.KIND], o[:, ph.AXES], o[:, ph.SEMI])
    lo, hi = c - ext, c + ext
    nplanes = np.zeros(n, np.int64)
    for k in range(ph.N_PLANES):
        pn, pd = o[:, 17 + 4 * k:20 + 4 * k], o[:, 20 + 4 * k]
        on = np.any(pn != 0.0, axis=-1) | (pd < 0)   # n = 0, d < 0: empty (0 <= d fails)
        for j in range(4):
            rec[np.nonzero(on)[0], 20 + 4 * nplanes[on] + j] = np.concatenate([pn, pd[:, None]], -1)[on, j]
        nplanes += on
    flags = kind | (nplanes << 2)
    for k in range(ph.N_CUTS):
        mi, cs, ca, cm = ph.cut_fields(k)
        mode = o[:, mi].astype(np.int64)
        flags |= mode << (4 + 2 * k)
        rec[:, 28 + 12 * k:31 + 12 * k] = o[:, cs]
        rec[:, 31 + 12 * k:40 + 12 * k] = q.local_map(o[:, ca], o[:, cm]).reshape(n, 9)
        isect = mode == ph.CUT_INTERSECT
        ext2 = q.box_half_extent(np.full(n, ph.KIND_ELLIPSOID), o[:, ca], o[:, cm])
        lo = np.where(isect[:, None], np.maximum(lo, o[:, cs] - ext2), lo)
        hi = np.where(isect[:, None], np.minimum(hi, o[:, cs] + ext2), hi)
    rec[:, 0] = np.where((kind != ph.KIND_NONE) & (o[:, ph.MU] != 0), flags, 0)
    rec[:, 1] = o[:, ph.MU]
    rec[:, 2:8] = np.stack([lo[:, 0], hi[:, 0], lo[:, 1], hi[:, 1], lo[:, 2], hi[:, 2]], -1)
    rec[:, 8:11] = c
    rec[:, 11:20] = q.local_map(o[:, ph.AXES], o[:, ph.SEMI]).reshape(n, 9)
    return rec.astype(np.float32)


def _spacing(a, name):
    if len(a) < 2:
        return 1.0
    d = np.diff(a)
    if not np.allclose(d, d[0], rtol=1e-6, atol=1e-9) or d[0] <= 0:
        raise ValueError(f"{name} must be uniformly increasing")
    return float(d[0])


def voxelise_objects(objects, x_mm, y_mm, z_mm, supersample: int = 3, rt=None) -> np.ndarray:
    """Supersampled voxelisation of packed objects, mu (nz, ny, nx) float32 (1/mm).

    Parameters
    ----------
    objects : (n_obj, STRIDE) packed objects of one state.
    x_mm, y_mm, z_mm : voxel-centre coordinates (mm), uniformly spaced (a single value
        counts as a 1 mm thick voxel).
    supersample : int >= 1
        Point samples per axis per voxel (``supersample**3`` per voxel, regular sub-grid).
    """
    if int(supersample) != supersample or supersample < 1:
        raise ValueError(f"supersample must be an integer >= 1, got {supersample!r}")
    x, y, z = q.as_axis(x_mm, "x_mm"), q.as_axis(y_mm, "y_mm"), q.as_axis(z_mm, "z_mm")
    dx, dy, dz = _spacing(x, "x_mm"), _spacing(y, "y_mm"), _spacing(z, "z_mm")
    objs = np.asarray(objects, dtype=np.float64)
    if objs.ndim != 2 or objs.shape[1] != ph.STRIDE:
        raise ValueError(f"objects must have shape (n_obj, {ph.STRIDE}), got {objs.shape}")
    rec = voxel_records(objs)
    live = rec[:, 0] != 0
    # per-slice object lists: objects whose z range meets the slice
    zlo, zhi = rec[:, 6], rec[:, 7]
    inz = live[None, :] & (zhi[None, :] >= (z - 0.5 * dz)[:, None]) & (zlo[None, :] <= (z + 0.5 * dz)[:, None])
    counts = inz.sum(1).astype(np.int32)
    stride = max(int(counts.max()), 1)
    lists = np.zeros((len(z), stride), np.int32)
    order = np.argsort(~inz, axis=1, kind="stable")[:, :stride]
    lists[:] = order
    rt = rt or get_runtime()
    lx, ly = 8, 8
    kern = rt.kernel("voxelise.cl", "voxelise", VW=VW, SS=int(supersample), LX=lx, LY=ly)
    nx, ny, nz = len(x), len(y), len(z)
    nseg = -(-nx // VW)
    gx, gy = -(-nseg // lx) * lx, -(-ny // ly) * ly
    out_buf = rt.empty((nz, ny, nx))
    bufs = [rt.to_device(rec), rt.to_device(lists, np.int32), rt.to_device(counts, np.int32)]
    axes = [rt.to_device(a) for a in (x, y, z)]  # referenced until the result is read
    ev = kern(rt.queue, (gx, gy, nz), (lx, ly, 1), *bufs, np.int32(stride), *axes,
              np.float32(dx), np.float32(dy), np.float32(dz), np.int32(nx), np.int32(ny), np.int32(nz), out_buf)
    return rt.from_device(out_buf, (nz, ny, nx), wait_for=[ev])
