"""Warp of a volume by a displacement field, and its exact transpose (``kernels/warp.cl``).

``warp(x, u, h)`` is the linear map W_u, ``(W_u x)(p) = x(p + u(p))``: each voxel centre p of
the grid samples x trilinearly at the point displaced by u(p). This is the motion model's
convention (:mod:`clrecon.reconstruction.motion.model`: ``u(x; s)`` takes a reference position
x to ``x + u(x; s)``, its position at state s): with u = u(.; s) on the reference grid,
``W_u f_s`` is the state-s volume f_s pulled back onto the reference (``f_ref(x) = f_s(x + u(x; s))``).
``warp_adjoint(g, u, h)`` applies W_u^T: every g[p] is scattered to the eight voxels around
``p + u(p)`` with the same weights, so that ``<W_u x, g> = <x, W_u^T g>``. Pushed this way, a
reference volume goes to state s conserving its sum (each voxel's weights add up to 1): a
mass-preserving warp, one of the two forward models issue 42 asks to compare.

Arrays: volumes (nz, ny, nx) float32 ``[z, y, x]``; u (3, nz, ny, nx) float32 mm, components
(dx, dy, dz) (LPS), on the same grid; spacing ``(hx, hy, hz)`` mm. Index coordinates
``p + u(p) / h`` are clamped to ``[0, n - 1]`` per axis (the volume extended by its edge
values, as :func:`clrecon.reconstruction.motion.model.sample` does); on a one-voxel axis both
weights fall on voxel 0. The transpose is a 64-bit fixed-point scatter
(:mod:`clrecon.reconstruction.iterative.fixed_point`): bit-identical whatever the order of the
work-items; ``|sum| <= sum|g|`` bounds every voxel, so the scale is ``2^S`` with
``sum|g| 2^S <= 2^61``.
"""

from __future__ import annotations

import numpy as np

from clrecon.core.runtime import get_runtime
from clrecon.reconstruction.iterative.fixed_point import scale_exponent, to_float, zero_accumulator


def _check(vol, u, spacing_mm, name):
    vol = np.asarray(vol)
    if vol.dtype.kind not in "fiu":
        raise TypeError(f"{name}: expected a real numeric array, got dtype {vol.dtype}")
    if vol.ndim != 3 or vol.size == 0:
        raise ValueError(f"{name} must be a non-empty (nz, ny, nx) array, got shape {vol.shape}")
    u = np.asarray(u)
    if u.dtype.kind not in "fiu":
        raise TypeError(f"u: expected a real numeric array, got dtype {u.dtype}")
    if u.shape != (3,) + vol.shape:
        raise ValueError(f"u must have shape (3,) + {name}.shape = {(3,) + vol.shape}, got {u.shape}")
    for a, what in ((vol, name), (u, "u")):
        bad = ~np.isfinite(a)
        if bad.any():
            idx = tuple(int(i) for i in np.argwhere(bad)[0])
            raise ValueError(f"{what} has a non-finite value at index {idx}")
    h = np.asarray(spacing_mm, np.float64)
    if h.shape != (3,) or not np.all(np.isfinite(h) & (h > 0)):
        raise ValueError(f"spacing_mm must be three finite numbers > 0 (hx, hy, hz), got {spacing_mm!r}")
    return vol, u, h


def _launch(rt, name, vol, u, h, *tail):
    nz, ny, nx = vol.shape
    kern = rt.kernel("warp.cl", name)
    src = rt.to_device(vol, np.float32, "volume")
    ub = rt.to_device(u, np.float32, "u")
    kern(rt.queue, (nx, ny, nz), None, src, ub, np.int32(nx), np.int32(ny), np.int32(nz),
         np.float32(h[0]), np.float32(h[1]), np.float32(h[2]), *tail)


def warp(x, u, spacing_mm, rt=None) -> np.ndarray:
    """W_u x: ``out[p] = x(p + u(p))``, trilinear, clamped (OpenCL). Returns (nz, ny, nx) float32."""
    x, u, h = _check(x, u, spacing_mm, "x")
    rt = rt or get_runtime()
    out = rt.empty(x.shape)
    _launch(rt, "warp_pull", x, u, h, out)
    return rt.from_device(out, x.shape)


def warp_adjoint(g, u, spacing_mm, rt=None) -> np.ndarray:
    """W_u^T g: each ``g[p]`` scattered with the trilinear weights of ``p + u(p)`` (OpenCL,
    bit-deterministic fixed-point sum). Returns (nz, ny, nx) float32."""
    g, u, h = _check(g, u, spacing_mm, "g")
    g32 = np.ascontiguousarray(g, np.float32)
    S = scale_exponent(float(np.abs(g32, dtype=np.float64).sum()))
    if not np.any(g32):
        return np.zeros(g.shape, np.float32)
    rt = rt or get_runtime()
    acc = zero_accumulator(rt, g.size)
    _launch(rt, "warp_push", g32, u, h, np.float32(2.0 ** S), acc)
    return to_float(rt.from_device(acc, (g.size, 2), np.uint32), S, g.shape)


def invert_field(u, spacing_mm, steps: int, rt=None) -> np.ndarray:
    """v with ``v(p) = -u(p + v(p))`` (the point ``p + v(p)`` moves to p under u): fixed-point
    iteration from ``v = -u(p)``, ``steps`` times ``v <- -u(p + v(p))`` with u sampled as :func:`warp`
    samples (trilinear, clamped), in one kernel launch. Converges where u's Jacobian norm is
    below 1 (smooth fields). Returns (3, nz, ny, nx) float32 mm."""
    u = np.asarray(u)
    if u.ndim != 4 or u.shape[0] != 3 or u.size == 0:
        raise ValueError(f"u must be a non-empty (3, nz, ny, nx) array, got shape {u.shape}")
    _, u, h = _check(u[0], u, spacing_mm, "u[0]")
    if not (isinstance(steps, (int, np.integer)) and 0 <= steps <= 1000):
        raise ValueError(f"steps = {steps!r}: must be an integer in [0, 1000]")
    rt = rt or get_runtime()
    nz, ny, nx = u.shape[1:]
    kern = rt.kernel("warp.cl", "invert_field")
    ub = rt.to_device(u, np.float32, "u")
    out = rt.empty(u.shape)
    kern(rt.queue, (nx, ny, nz), None, ub, np.int32(nx), np.int32(ny), np.int32(nz), np.float32(h[0]),
         np.float32(h[1]), np.float32(h[2]), np.int32(steps), out)
    return rt.from_device(out, u.shape)


# ---------------------------------------------------------------------------------------
def _weights_reference(u, h, shape):
    """Per voxel p (flattened) the eight (index (8, N), weight (8, N)) pairs, float64."""
    nz, ny, nx = shape
    zz, yy, xx = np.meshgrid(np.arange(nz), np.arange(ny), np.arange(nx), indexing="ij")
    axes = []
    for grid, n, comp in ((xx, nx, 0), (yy, ny, 1), (zz, nz, 2)):
        g = np.clip(grid + np.asarray(u[comp], np.float64) / h[comp], 0, n - 1).ravel()
        i0 = np.minimum(np.floor(g).astype(np.int64), max(n - 2, 0))
        f = g - i0
        i1 = np.minimum(i0 + 1, n - 1)
        axes.append(((i0, 1 - f), (i1, f)))
    idx, wts = [], []
    for (iz, wz) in axes[2]:
        for (iy, wy) in axes[1]:
            for (ix, wx) in axes[0]:
                idx.append((iz * ny + iy) * nx + ix)
                wts.append(wz * wy * wx)
    return np.array(idx), np.array(wts)


def warp_reference(x, u, spacing_mm) -> np.ndarray:
    """:func:`warp` in float64 NumPy (for tests). Returns (nz, ny, nx) float64."""
    x, u, h = _check(x, u, spacing_mm, "x")
    idx, w = _weights_reference(u, h, x.shape)
    return (np.asarray(x, np.float64).ravel()[idx] * w).sum(0).reshape(x.shape)


def warp_adjoint_reference(g, u, spacing_mm) -> np.ndarray:
    """:func:`warp_adjoint` in float64 NumPy (for tests). Returns (nz, ny, nx) float64."""
    g, u, h = _check(g, u, spacing_mm, "g")
    idx, w = _weights_reference(u, h, g.shape)
    out = np.zeros(g.size)
    np.add.at(out, idx.ravel(), (w * np.asarray(g, np.float64).ravel()[None]).ravel())
    return out.reshape(g.shape)


def invert_field_reference(u, spacing_mm, steps: int) -> np.ndarray:
    """:func:`invert_field` in float64 NumPy (for tests): ``steps`` rounds of :func:`warp_reference`
    of u's components by the current v. Returns (3, nz, ny, nx) float64."""
    u64 = np.asarray(u, np.float64)
    v = -u64
    for _ in range(int(steps)):
        v = -np.stack([warp_reference(u64[k], v, spacing_mm) for k in range(3)])
    return v
