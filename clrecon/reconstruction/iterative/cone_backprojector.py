"""Matched cone-beam backprojector: the exact transpose of the voxel projector (``kernels/voxel_backproject.cl``).

:func:`clrecon.simulation.voxel_projector.project_volume` is a linear map A from a voxel volume
``mu[z, y, x]`` (1/mm) to line integrals ``proj[view, row, col]`` (dimensionless) with Joseph's
weights (a slab length in mm times bilinear fractions). :func:`backproject_volume` applies
A^T: ``vol[v] = sum over rays r of A[r, v] proj[r]`` (mm times the units of ``proj``), with the
same rays (the scan's own detector, flat or cylindrical through ``v_scale``; a flying focal spot
is one call per spot state with that state's frames and cells, as for the projector), so that
``<A x, y> = <x, A^T y>`` up to float32 rounding of the weights. It is the adjoint an iterative
solver needs (gradients of ||A x - y||^2, CG / LSQR on the normal equations, SART).

How: one work-item per ray walks it with the projector's own set-up and samples
(``kernels/joseph_ray.h``: clip to the box, dominant axis, slab range, in-plane coordinates per
plane) and scatters ``proj[r]`` times each of its
samples' four bilinear weights to the four voxels the projector reads. The scatter is a 64-bit
fixed-point sum (``kernels/fixed_add.h``): each float32 contribution ``c`` is rounded to the
integer ``rint(c 2^S)`` and added with 32-bit atomics and an exact carry; integer addition is
associative, so the result is **bit-identical whatever the order the work-items run in, the
chunking of the views and the executor** (float atomics would not be). The scale ``2^S`` is the
largest power of two with ``|spacing| sum|proj| 2^S <= 2^61``
(:mod:`clrecon.reconstruction.iterative.fixed_point`) (no voxel's sum can reach it:
one ray gives one voxel at most ``|spacing|`` mm, the norm of the voxel's diagonal), so it
depends on the call's data, not on its chunking; each contribution is quantised to ``2^-S``
(absolute), far below its float32 rounding unless ``proj`` spans more than ~2^30 in dynamic
range. Views split over several calls are summed by the caller, in the caller's order.

Memory: the device holds 8 bytes per voxel (the accumulator) and one chunk of views
(``CHUNK_CELLS`` cells, as the projector).
"""

from __future__ import annotations

import math

import numpy as np

from clrecon.core.runtime import get_runtime
from clrecon.reconstruction.iterative.fixed_point import scale_exponent, to_float, zero_accumulator
from clrecon.simulation.voxel_projector import (
    CHUNK_CELLS,
    MAX_VOXELS,
    _check_frames,
    _finite,
    _rays,
    _real,
    check_grid,
    check_v_scale,
    joseph_samples,
)


def _check_shape(shape_zyx, origin_mm, spacing_mm):
    shape = tuple(int(n) for n in np.asarray(shape_zyx).ravel())
    if len(shape) != 3 or any(n < 1 for n in shape) or any(int(n) != n for n in np.asarray(shape_zyx).ravel()):
        raise ValueError(f"shape_zyx must be three integers >= 1 (nz, ny, nx), got {shape_zyx!r}")
    if math.prod(shape) > MAX_VOXELS:
        raise ValueError(f"shape_zyx {shape} has {math.prod(shape)} voxels, more than the kernel's {MAX_VOXELS}")
    return (shape, *check_grid(origin_mm, spacing_mm))


def _check_proj(proj, m, n_rows, n_cols):
    proj = _real(proj, "proj")
    if proj.shape != (m, n_rows, n_cols):
        raise ValueError(f"proj must have shape (views, rows, cols) = {(m, n_rows, n_cols)}, got {proj.shape}")
    _finite(proj, "proj [view, row, col]")
    return proj


def backproject_volume(proj, shape_zyx, origin_mm, spacing_mm, src, det_centre, e_u, e_v, u_mm, v_mm, rt=None, *,
                       chunk_views: int | None = None, v_scale=None) -> np.ndarray:
    """A^T proj: the transpose of :func:`clrecon.simulation.voxel_projector.project_volume` (OpenCL).

    Parameters
    ----------
    proj : (m, n_rows, n_cols) real array
        Values on the rays, ``proj[view, row, col]`` (sent as float32; must be finite).
    shape_zyx : (nz, ny, nx)
        Shape of the volume.
    origin_mm, spacing_mm, src, det_centre, e_u, e_v, u_mm, v_mm, v_scale
        The geometry, exactly as for ``project_volume`` (origin and spacing in x, y, z order).
    rt : Runtime, optional
    chunk_views : int, optional
        Views per kernel launch (default: ``CHUNK_CELLS`` cells per launch). The result does
        not depend on it (fixed-point sum).

    Returns
    -------
    (nz, ny, nx) float32: ``sum_r A[r, v] proj[r]`` per voxel (mm x the units of ``proj``).

    Raises
    ------
    TypeError for a non-numeric array; ValueError for a wrong shape, a non-finite value (the
    message names the first one's index), a non-positive spacing.
    """
    return _backproject((proj,), shape_zyx, origin_mm, spacing_mm, src, det_centre, e_u, e_v, u_mm, v_mm, rt,
                        chunk_views=chunk_views, v_scale=v_scale)[0]


def backproject_pair(proj, proj2, shape_zyx, origin_mm, spacing_mm, src, det_centre, e_u, e_v, u_mm, v_mm, rt=None,
                     *, chunk_views: int | None = None, v_scale=None) -> tuple[np.ndarray, np.ndarray]:
    """(A^T proj, A^T proj2) for two arrays on the same rays, in one walk of the rays (kernel
    variant ``PAIR``): each result is bit-identical to :func:`backproject_volume` of that array
    alone (each has its own fixed-point scale). Arguments and errors as :func:`backproject_volume`;
    ``proj2`` has the shape of ``proj``. It shares the ray set-up and the sample weights, not the
    scatters, which are the cost: about two calls' time (docs/results/iterative-study.md
    "9. Backprojectors"). SART's first visit of a subset needs both its update and its column sums."""
    return _backproject((proj, proj2), shape_zyx, origin_mm, spacing_mm, src, det_centre, e_u, e_v, u_mm, v_mm, rt,
                        chunk_views=chunk_views, v_scale=v_scale)


def _backproject(projs, shape_zyx, origin_mm, spacing_mm, src, det_centre, e_u, e_v, u_mm, v_mm, rt, *,
                 chunk_views, v_scale) -> tuple:
    """A^T of one or two arrays on the same rays (the ``PAIR`` kernel for two); a tuple of volumes."""
    shape, origin, spacing = _check_shape(shape_zyx, origin_mm, spacing_mm)
    src, det, eu, ev, u, v = _check_frames(src, det_centre, e_u, e_v, u_mm, v_mm)
    m, n_rows, n_cols = len(src), len(v), len(u)
    projs32 = [np.ascontiguousarray(_check_proj(p, m, n_rows, n_cols), np.float32) for p in projs]
    if chunk_views is not None and (int(chunk_views) != chunk_views or chunk_views < 1):
        raise ValueError(f"chunk_views must be an integer >= 1, got {chunk_views!r}")
    exps = [scale_exponent(float(np.linalg.norm(spacing)) * float(np.abs(p, dtype=np.float64).sum()))
            for p in projs32]
    nz, ny, nx = shape
    live = [k for k, p in enumerate(projs32) if m > 0 and np.any(p)]
    out = [np.zeros(shape, np.float32) for _ in projs32]
    if not live:
        return tuple(out)
    rt = rt or get_runtime()
    defines = {"PAIR": 1} if len(live) == 2 else {}
    extra = []
    if v_scale is not None:
        defines["CURVED"] = 1
        extra = [rt.to_device(check_v_scale(v_scale, n_cols))]
    kern = rt.kernel("voxel_backproject.cl", "voxel_backproject", **defines)
    views = np.concatenate([(src - origin) / spacing, det - src, eu, ev], axis=1)
    accs = [zero_accumulator(rt, nz * ny * nx) for _ in live]
    scales = [np.float32(2.0 ** exps[k]) for k in live]
    u_buf, v_buf = rt.to_device(u), rt.to_device(v)
    step = int(chunk_views or max(1, CHUNK_CELLS // (n_rows * n_cols)))
    for a in range(0, m, step):
        b = min(m, a + step)
        view_buf = rt.to_device(views[a:b])
        bufs = [rt.to_device(projs32[k][a:b]) for k in live]
        tail = [bufs[1], scales[1], accs[1]] if len(live) == 2 else []
        kern(rt.queue, (n_cols, n_rows, b - a), None, bufs[0], np.int32(nx), np.int32(ny), np.int32(nz),
             np.float32(spacing[0]), np.float32(spacing[1]), np.float32(spacing[2]),
             view_buf, u_buf, v_buf, np.int32(n_cols), np.int32(n_rows), *extra, scales[0], accs[0], *tail)
    for k, acc in zip(live, accs, strict=True):
        out[k] = to_float(rt.from_device(acc, (nz * ny * nx, 2), np.uint32), exps[k], shape)
    return tuple(out)


# ---------------------------------------------------------------------------------------
def backproject_volume_reference(proj, shape_zyx, origin_mm, spacing_mm, src, det_centre, e_u, e_v, u_mm, v_mm,
                                 v_scale=None) -> np.ndarray:
    """:func:`backproject_volume` in float64 NumPy (for tests; small inputs).

    The transpose of :func:`clrecon.simulation.voxel_projector.project_volume_reference`,
    written as its scatter: the same rays and planes, ``np.add.at`` of ``proj[r]`` times each
    sample's four weights. Returns (nz, ny, nx) float64.
    """
    shape, origin, spacing = _check_shape(shape_zyx, origin_mm, spacing_mm)
    src, det, eu, ev, u, v = _check_frames(src, det_centre, e_u, e_v, u_mm, v_mm)
    y = np.asarray(_check_proj(proj, len(src), len(v), len(u)), np.float64).ravel()
    vol = np.zeros(shape, np.float64)
    n = np.array(shape[::-1])                          # (nx, ny, nz)
    volx = np.transpose(vol, (2, 1, 0))                # a view: volx[ix, iy, iz]
    a, b, length = _rays(src, det, eu, ev, u, v, origin, spacing, v_scale)
    step, samples = joseph_samples(a, b, length, n)
    ys = y * length / step
    for k, i, rays, w, j0, j1, l0, l1, fj, fl in samples:
        c = ys[rays] * w
        plane = np.moveaxis(volx, k, 0)[i]             # plane[g_j, g_l], a view of vol
        np.add.at(plane, (j0, l0), c * (1 - fj) * (1 - fl))
        np.add.at(plane, (j1, l0), c * fj * (1 - fl))
        np.add.at(plane, (j0, l1), c * (1 - fj) * fl)
        np.add.at(plane, (j1, l1), c * fj * fl)
    return vol
