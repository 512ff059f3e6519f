"""Multi-resolution 3D TV-L1 optical flow on the engine's OpenCL runtime (``kernels/flow.cl``).

A registration for the ``mc`` motion model (the beat step's by default, ``recon.mc.beat_registration``;
both steps' with ``recon.mc.registration = "tvl1"``; docs/results/mc-study.md "TV-L1 registration" and
"Which registration for which step"): the displacement u (mm) minimising

    E(u) = sum_c integral |grad u_c| dx  +  lambda integral |I1(x + u(x)) - I0(x)| dx

-- total variation of each component (piecewise smooth fields: the heart may slide against the
lung and the chest wall, where a Gaussian or window regulariser smears the motion across the
interface) and an L1 data term (robust to the streaks of a first-pass image and to the lung's
density change). Solved as Zach, Pock & Bischof (DAGM 2007) in the form of Sanchez,
Meinhardt-Llopis & Facciolo (IPOL 2013): per pyramid level coarse to fine, ``warps`` times the
moving image is warped by the current field and the data term linearised, then ``iterations``
alternations of a pointwise thresholding step and Chambolle's dual projection for the TV part
(in the Huber form with ``huber`` > 0: quadratic for small strain).

Conventions as :func:`clrecon.reconstruction.motion.registration.register`: volumes
``(nz, ny, nx)`` HU, spacing ``(dx, dy, dz)`` mm, result u ``(3, nz, ny, nx)`` float32 mm with
components (dx, dy, dz) on the fixed grid and ``moving(x + u(x)) ~ fixed(x)``. Images are clipped
to ``hu_window`` and scaled to [0, 1] (``lam`` is per unit of that scale).

Pyramid: level l has voxels of about ``min(spacing) * 2**l`` mm along each axis (an axis already
coarser keeps its voxels), made from the Gaussian-smoothed image (std ``0.8 sqrt(f**2 - 1)`` source
voxels for a size ratio f, as IPOL's cascade) by trilinear resampling of voxels spanning the same
extent (``flow_resample``); fields carry to the next level by the same resampling (mm need no
rescaling). Levels stop at ``levels`` or before an in-plane side falls under ``min_size``.

Memory at the finest level: 16 float32 volumes (fixed, moving, warped, residual, u x 3, dual x 9),
64 bytes per voxel (:data:`BYTES_PER_VOXEL`).
Deterministic: no random sampling and no reductions in the kernels (one work-item per output), so
a repeated call gives the same bits on one device.

Each kernel has a float64 NumPy reference here (``*_reference``), checked in
tests/reconstruction/test_flow.py and run under Oclgrind in tests/core/test_oclgrind.py.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.ndimage

from clrecon.core.runtime import aligned_empty, get_runtime

#: |grad I|^2 below which the thresholding step does not move u (normalised intensity per mm, squared).
EPS = 1e-12
#: Peak bytes per voxel of the finest level, host and device together on a CPU device: the two
#: normalised images (shared with the device, not copied), warped image, residual, u (3) and the
#: dual (9), float32. The coarser levels' smoothed copies come and go before it; the result (3
#: volumes) is read back after the dual and the images are released (measured against this:
#: docs/results/mc-study.md "TV-L1 registration").
BYTES_PER_VOXEL = 4 * 16


@dataclass(frozen=True, kw_only=True)
class TVL1Config:
    """Knobs of :func:`register_tvl1` (module docstring for the energy).

    lam : weight of the L1 data term (dimensionless: per unit of the normalised intensity, window = 1).
    theta : coupling of the thresholding and TV steps, in squared voxels of the level (the level's
        smallest spacing h: theta h**2 mm**2; IPOL's 0.3 pixel**2).
    huber : strain (dimensionless) below which the regulariser is quadratic (Huber-TV: smooth
        strain without TV's staircase; above it TV's linear growth lets interfaces slide); 0: TV.
    tau : dual step as a fraction of 1 / sum(1 / h**2) (h: the level's spacings, mm); 0.25 is the
        bound that guarantees convergence of the dual projection.
    warps : linearisations per pyramid level.
    iterations : thresholding + dual steps per warp.
    levels : most pyramid levels (1: the full grid only).
    min_size : smallest in-plane side of a level (voxels).
    hu_window : (lo, hi) HU the images are clipped to before scaling to [0, 1].
    """

    lam: float = 40.0
    theta: float = 0.3
    huber: float = 0.2
    tau: float = 0.25
    warps: int = 5
    iterations: int = 30
    levels: int = 5
    min_size: int = 16
    hu_window: tuple = (-900.0, 600.0)

    def __post_init__(self):
        if not (isinstance(self.huber, (int, float)) and math.isfinite(self.huber) and self.huber >= 0):
            raise ValueError(f"TVL1Config.huber = {self.huber!r}: must be a finite number >= 0")
        for name in ("lam", "theta", "tau"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ValueError(f"TVL1Config.{name} = {v!r}: must be a finite number > 0")
        if self.tau > 0.5:
            raise ValueError(f"TVL1Config.tau = {self.tau!r}: must be <= 0.5 (0.25 guarantees convergence)")
        for name, lo in (("warps", 1), ("iterations", 1), ("levels", 1), ("min_size", 2)):
            v = getattr(self, name)
            if not (isinstance(v, int) and not isinstance(v, bool) and v >= lo):
                raise ValueError(f"TVL1Config.{name} = {v!r}: must be an integer >= {lo}")
        lo, hi = self.hu_window
        if not lo < hi:
            raise ValueError(f"TVL1Config.hu_window = {self.hu_window!r}: must be (lo, hi) with lo < hi")


# -- the pyramid ----------------------------------------------------------------------------
def level_shapes(shape: tuple, spacing_mm: tuple, cfg: TVL1Config) -> list[tuple]:
    """Shapes (nz, ny, nx) of the pyramid's levels, finest first (module docstring)."""
    nz, ny, nx = shape
    hx, hy, hz = spacing_mm
    h0 = min(spacing_mm)
    out = [tuple(shape)]
    for level in range(1, cfg.levels):
        t = h0 * 2.0 ** level
        s = tuple(max(1, int(round(n * h / t))) if h < t else n for n, h in ((nz, hz), (ny, hy), (nx, hx)))
        if min(s[1], s[2]) < cfg.min_size or s == out[-1]:
            break
        out.append(s)
    return out


def level_spacing(shape: tuple, level_shape: tuple, spacing_mm: tuple) -> tuple:
    """(hx, hy, hz) mm of a level: the same extent in ``level_shape`` voxels."""
    nz, ny, nx = shape
    lz, ly, lx = level_shape
    hx, hy, hz = spacing_mm
    return (hx * nx / lx, hy * ny / ly, hz * nz / lz)


def level_theta(spacing_mm: tuple, cfg: TVL1Config) -> float:
    """The coupling theta (mm**2) on a level of spacings ``spacing_mm``: ``cfg.theta`` squared voxels."""
    return cfg.theta * min(spacing_mm) ** 2


def smoothing_sigmas(shape: tuple, level_shape: tuple) -> tuple:
    """Gaussian std (source voxels, per axis z, y, x) applied before resampling to ``level_shape``."""
    return tuple(0.8 * math.sqrt(max(n / m, 1.0) ** 2 - 1.0) for n, m in zip(shape, level_shape, strict=True))


# -- float64 NumPy references of the kernels ---------------------------------------------------
def _trilinear_reference(vol, fx, fy, fz):
    """``vol`` (nz, ny, nx) at fractional indices (arrays of one shape), clamped as the kernel."""
    v = np.asarray(vol, np.float64)
    nz, ny, nx = v.shape
    fx = np.clip(fx, 0, nx - 1)
    fy = np.clip(fy, 0, ny - 1)
    fz = np.clip(fz, 0, nz - 1)
    i0 = np.minimum(fx.astype(np.int64), max(nx - 2, 0))
    j0 = np.minimum(fy.astype(np.int64), max(ny - 2, 0))
    k0 = np.minimum(fz.astype(np.int64), max(nz - 2, 0))
    tx, ty, tz = fx - i0, fy - j0, fz - k0
    i1, j1, k1 = np.minimum(i0 + 1, nx - 1), np.minimum(j0 + 1, ny - 1), np.minimum(k0 + 1, nz - 1)

    def lerp_x(j, k):
        return (1 - tx) * v[k, j, i0] + tx * v[k, j, i1]

    return ((1 - tz) * ((1 - ty) * lerp_x(j0, k0) + ty * lerp_x(j1, k0))
            + tz * ((1 - ty) * lerp_x(j0, k1) + ty * lerp_x(j1, k1)))


def _central_reference(img, axis: int, h: float):
    """Central differences along ``axis`` of (nz, ny, nx), one-sided at the ends, 0 for one voxel."""
    a = np.asarray(img, np.float64)
    n = a.shape[axis]
    if n < 2:
        return np.zeros_like(a)
    idx = np.arange(n)
    hi, lo = np.minimum(idx + 1, n - 1), np.maximum(idx - 1, 0)
    shape = [1, 1, 1]
    shape[axis] = n
    return (np.take(a, hi, axis) - np.take(a, lo, axis)) / ((hi - lo).reshape(shape) * h)


def image_gradient_reference(img, spacing_mm) -> np.ndarray:
    """(3, nz, ny, nx): d/dx, d/dy, d/dz of ``img`` by :func:`_central_reference`."""
    hx, hy, hz = spacing_mm
    return np.stack([_central_reference(img, 2, hx), _central_reference(img, 1, hy), _central_reference(img, 0, hz)])


def forward_gradient_reference(f, spacing_mm) -> np.ndarray:
    """(3, nz, ny, nx) forward differences of ``f`` (nz, ny, nx), 0 on each axis' last index."""
    a = np.asarray(f, np.float64)
    out = np.zeros((3,) + a.shape)
    for c, (axis, h) in enumerate(((2, spacing_mm[0]), (1, spacing_mm[1]), (0, spacing_mm[2]))):
        d = np.diff(a, axis=axis) / h
        sl = [slice(None)] * 3
        sl[axis] = slice(0, a.shape[axis] - 1)
        out[c][tuple(sl)] = d
    return out


def divergence_reference(p, spacing_mm) -> np.ndarray:
    """Backward divergence of ``p`` (3, nz, ny, nx) (directions x, y, z): minus the adjoint of
    :func:`forward_gradient_reference`."""
    q = np.asarray(p, np.float64)
    out = np.zeros(q.shape[1:])
    for c, (axis, h) in enumerate(((2, spacing_mm[0]), (1, spacing_mm[1]), (0, spacing_mm[2]))):
        n = q.shape[1 + axis]
        if n < 2:
            continue
        a = np.moveaxis(q[c], axis, 0)
        d = np.empty_like(a)
        d[0] = a[0]
        d[1:n - 1] = a[1:n - 1] - a[0:n - 2]
        d[n - 1] = -a[n - 2]
        out += np.moveaxis(d, 0, axis) / h
    return out


def warp_reference(src, u, spacing_mm) -> np.ndarray:
    """``flow_warp``: src (nz, ny, nx) at x + u(x), u (3, nz, ny, nx) mm."""
    s = np.asarray(src, np.float64)
    u = np.asarray(u, np.float64)
    nz, ny, nx = s.shape
    k, j, i = np.meshgrid(np.arange(nz), np.arange(ny), np.arange(nx), indexing="ij")
    return _trilinear_reference(s, i + u[0] / spacing_mm[0], j + u[1] / spacing_mm[1], k + u[2] / spacing_mm[2])


def residual_reference(warped, fixed, u, spacing_mm) -> np.ndarray:
    """``flow_residual``: rho0 = Iw - I0 - grad(Iw) . u."""
    g = image_gradient_reference(warped, spacing_mm)
    return np.asarray(warped, np.float64) - np.asarray(fixed, np.float64) - (g * np.asarray(u, np.float64)).sum(0)


def primal_reference(u, p, warped, rho0, spacing_mm, lt: float, theta: float) -> np.ndarray:
    """``flow_primal``: the new u (3, nz, ny, nx) from u, p (9, nz, ny, nx), Iw and rho0."""
    u = np.asarray(u, np.float64)
    p = np.asarray(p, np.float64)
    g = image_gradient_reference(warped, spacing_mm)
    g2 = (g * g).sum(0)
    rho = np.asarray(rho0, np.float64) + (g * u).sum(0)
    safe = np.where(g2 > EPS, g2, 1.0)
    f = np.where(rho < -lt * g2, lt, np.where(rho > lt * g2, -lt, np.where(g2 > EPS, -rho / safe, 0.0)))
    return np.stack([u[c] + f * g[c] + theta * divergence_reference(p[3 * c:3 * c + 3], spacing_mm)
                     for c in range(3)])


def dual_reference(u, p, spacing_mm, s: float, eps: float) -> np.ndarray:
    """``flow_dual``: the new p (9, nz, ny, nx) (Huber-TV with ``eps``)."""
    p = np.asarray(p, np.float64)
    out = np.empty_like(p)
    for c in range(3):
        d = forward_gradient_reference(np.asarray(u, np.float64)[c], spacing_mm)
        q = (p[3 * c:3 * c + 3] + s * d) / (1.0 + s * eps)
        out[3 * c:3 * c + 3] = q / np.maximum(1.0, np.sqrt((q * q).sum(0)))
    return out


def resample_reference(src, shape: tuple) -> np.ndarray:
    """``flow_resample``: (..., mz, my, mx) onto (..., nz, ny, nx) voxels spanning the same extent."""
    s = np.asarray(src, np.float64)
    lead = s.shape[:-3]
    mz, my, mx = s.shape[-3:]
    nz, ny, nx = shape
    k, j, i = np.meshgrid(np.arange(nz), np.arange(ny), np.arange(nx), indexing="ij")
    fx = (i + 0.5) * (mx / nx) - 0.5
    fy = (j + 0.5) * (my / ny) - 0.5
    fz = (k + 0.5) * (mz / nz) - 0.5
    flat = s.reshape((-1, mz, my, mx))
    return np.stack([_trilinear_reference(v, fx, fy, fz) for v in flat]).reshape(lead + tuple(shape))


def normalise(vol, cfg: TVL1Config) -> np.ndarray:
    """``vol`` clipped to ``cfg.hu_window`` and scaled to [0, 1], float32 (page-aligned)."""
    lo, hi = cfg.hu_window
    out = aligned_empty(np.shape(vol), np.float32)
    np.clip(vol, lo, hi, out=out, casting="unsafe")
    out -= np.float32(lo)
    out *= np.float32(1.0 / (hi - lo))
    return out


def register_reference(fixed, moving, spacing_mm: tuple, cfg: TVL1Config | None = None) -> np.ndarray:
    """Float64 NumPy reference of :func:`register_tvl1` (the same steps, for small volumes)."""
    cfg = cfg or TVL1Config()
    f0, m0 = (normalise(v, cfg).astype(np.float64) for v in (fixed, moving))
    shape = f0.shape
    levels = level_shapes(shape, spacing_mm, cfg)
    u = None
    for ls in reversed(levels):
        h = level_spacing(shape, ls, spacing_mm)
        sig = smoothing_sigmas(shape, ls)
        i0, i1 = ((resample_reference(scipy.ndimage.gaussian_filter(v, sig, mode="nearest"), ls)
                   if ls != shape else v) for v in (f0, m0))
        u = np.zeros((3,) + ls) if u is None else resample_reference(u, ls)
        p = np.zeros((9,) + ls)
        theta = level_theta(h, cfg)
        s = cfg.tau / sum(1.0 / x ** 2 for x in h) / theta
        for _ in range(cfg.warps):
            w = warp_reference(i1, u, h)
            rho0 = residual_reference(w, i0, u, h)
            for _ in range(cfg.iterations):
                u = primal_reference(u, p, w, rho0, h, cfg.lam * theta, theta)
                p = dual_reference(u, p, h, s, cfg.huber)
    return u


# -- the OpenCL registration ---------------------------------------------------------------------
def check_pair(fixed, moving, spacing_mm, axes=(1, 2), too_small: str = "need at least 2 voxels along y and x"):
    """``(fixed, moving, spacing)`` of a registration, checked: two finite (nz, ny, nx) volumes of one
    shape with at least 2 voxels along each of ``axes`` (else ``too_small`` in the error) and three
    finite spacings > 0 (mm, x y z); one line naming what is wrong. Shared by this module and
    :mod:`clrecon.reconstruction.motion.lk`."""
    f = np.asarray(fixed)
    m = np.asarray(moving)
    if f.ndim != 3 or m.shape != f.shape:
        raise ValueError(f"fixed {f.shape} and moving {m.shape}: expected two (nz, ny, nx) volumes of one shape")
    if min(f.shape[a] for a in axes) < 2:
        raise ValueError(f"fixed {f.shape}: {too_small}")
    if not (np.all(np.isfinite(f)) and np.all(np.isfinite(m))):
        raise ValueError("fixed and moving must be finite")
    if len(spacing_mm) != 3 or not all(math.isfinite(s) and s > 0 for s in spacing_mm):
        raise ValueError(f"spacing_mm = {spacing_mm!r}: three finite spacings > 0 (x, y, z)")
    return f, m, tuple(float(s) for s in spacing_mm)


class _Kernels:
    """The kernels of ``flow.cl`` on one runtime (built once per runtime by :meth:`Runtime.kernel`)."""

    def __init__(self, rt):
        self.rt = rt
        self.warp = rt.kernel("flow.cl", "flow_warp", FLOW_EPS=EPS, BATCH=3)
        self.residual = rt.kernel("flow.cl", "flow_residual", FLOW_EPS=EPS, BATCH=3)
        self.primal = rt.kernel("flow.cl", "flow_primal", FLOW_EPS=EPS, BATCH=3)
        self.dual = rt.kernel("flow.cl", "flow_dual", FLOW_EPS=EPS, BATCH=3)
        self.resample3 = rt.kernel("flow.cl", "flow_resample", FLOW_EPS=EPS, BATCH=3)
        self.resample1 = rt.kernel("flow.cl", "flow_resample", FLOW_EPS=EPS, BATCH=1)

    def resample(self, src, src_shape, dst_shape, batch: int):
        """Device buffer of ``batch`` volumes ``dst_shape`` resampled from ``src`` (``batch`` x ``src_shape``)."""
        mz, my, mx = src_shape
        nz, ny, nx = dst_shape
        out = self.rt.empty((batch,) + tuple(dst_shape))
        kern = self.resample3 if batch == 3 else self.resample1
        kern(self.rt.queue, (nx, ny, nz * batch), None, src, out, *(np.int32(v) for v in (mx, my, mz, nx, ny, nz)))
        return out


def register_tvl1(fixed, moving, spacing_mm: tuple, cfg: TVL1Config | None = None, runtime=None) -> np.ndarray:
    """Displacement u with ``moving(x + u(x)) ~ fixed(x)`` on the fixed grid: (3, nz, ny, nx) float32 mm.

    ``fixed``, ``moving``: (nz, ny, nx) HU volumes on one grid, finite; ``spacing_mm``: (dx, dy, dz)
    mm; ``cfg``: :class:`TVL1Config`; ``runtime``: the OpenCL runtime (default :func:`get_runtime`).
    """
    cfg = cfg or TVL1Config()
    f, m, h0 = check_pair(fixed, moving, spacing_mm)
    rt = runtime or get_runtime()
    k = _Kernels(rt)
    shape = f.shape
    f0, m0 = normalise(f, cfg), normalise(m, cfg)
    levels = level_shapes(shape, h0, cfg)
    i32, f32 = np.int32, np.float32
    d_u = None
    prev = None
    for ls in reversed(levels):
        nz, ny, nx = ls
        h = level_spacing(shape, ls, h0)
        imgs = []
        for v in (f0, m0):
            if ls == shape:
                imgs.append(rt.share_with_device(v, "image"))
            else:
                sm = scipy.ndimage.gaussian_filter(v, smoothing_sigmas(shape, ls), mode="nearest")
                d_sm = rt.to_device(sm, np.float32, "image")
                del sm
                imgs.append(k.resample(d_sm, shape, ls, 1))
                rt.queue.finish()
                d_sm.release()
        d_i0, d_i1 = imgs
        n = nz * ny * nx
        if d_u is None:
            d_u = rt.empty((3,) + ls)
            rt.cl.enqueue_fill_buffer(rt.queue, d_u, f32(0.0), 0, 3 * n * 4)
        else:
            d_new = k.resample(d_u, prev, ls, 3)
            rt.queue.finish()
            d_u.release()
            d_u = d_new
        d_p = rt.empty((9,) + ls)
        rt.cl.enqueue_fill_buffer(rt.queue, d_p, f32(0.0), 0, 9 * n * 4)
        d_w = rt.empty(ls)
        d_rho = rt.empty(ls)
        dims = (i32(nx), i32(ny), i32(nz), f32(h[0]), f32(h[1]), f32(h[2]))
        gsize = (nx, ny, nz)
        theta = level_theta(h, cfg)
        s = f32(cfg.tau / sum(1.0 / x ** 2 for x in h) / theta)
        lt, theta, huber = f32(cfg.lam * theta), f32(theta), f32(cfg.huber)
        for _ in range(cfg.warps):
            k.warp(rt.queue, gsize, None, d_i1, d_u, d_w, *dims)
            k.residual(rt.queue, gsize, None, d_w, d_i0, d_u, d_rho, *dims)
            for _ in range(cfg.iterations):
                k.primal(rt.queue, gsize, None, d_u, d_p, d_w, d_rho, *dims, lt, theta)
                k.dual(rt.queue, gsize, None, d_u, d_p, *dims, s, huber)
        rt.queue.finish()
        for b in (d_p, d_w, d_rho, d_i0, d_i1):
            b.release()
        prev = ls
    u = rt.from_device(d_u, (3,) + shape)
    d_u.release()
    return u


# -- one launch of each kernel on host arrays (the tests' entry to the kernels) -------------------
def _launch(name: str, arrays: dict, shape: tuple, scalars: tuple, out: str, out_shape: tuple, runtime=None,
            batch: int = 3) -> np.ndarray:
    """Run kernel ``name`` once: ``arrays`` (argument order) uploaded as float32, ``out`` read back."""
    rt = runtime or get_runtime()
    kern = rt.kernel("flow.cl", name, FLOW_EPS=EPS, BATCH=batch)
    bufs = {}
    for key, a in arrays.items():
        if a is None:
            bufs[key] = rt.empty(out_shape)
        else:
            bufs[key] = rt.empty(np.shape(a))
            rt.cl.enqueue_copy(rt.queue, bufs[key], np.ascontiguousarray(a, np.float32))
    kern(rt.queue, shape, None, *bufs.values(), *scalars)
    res = rt.from_device(bufs[out], out_shape)
    for b in bufs.values():
        b.release()
    return res


def _dims(shape, spacing_mm):
    nz, ny, nx = shape
    return (np.int32(nx), np.int32(ny), np.int32(nz)) + tuple(np.float32(h) for h in spacing_mm)


def warp_cl(src, u, spacing_mm, runtime=None) -> np.ndarray:
    """``flow_warp`` once (float32): :func:`warp_reference`."""
    sh = np.shape(src)
    return _launch("flow_warp", {"src": src, "u": u, "out": None}, sh[::-1], _dims(sh, spacing_mm), "out", sh,
                   runtime)


def residual_cl(warped, fixed, u, spacing_mm, runtime=None) -> np.ndarray:
    """``flow_residual`` once (float32): :func:`residual_reference`."""
    sh = np.shape(warped)
    return _launch("flow_residual", {"w": warped, "f": fixed, "u": u, "rho": None}, sh[::-1],
                   _dims(sh, spacing_mm), "rho", sh, runtime)


def primal_cl(u, p, warped, rho0, spacing_mm, lt: float, theta: float, runtime=None) -> np.ndarray:
    """``flow_primal`` once (float32): :func:`primal_reference`."""
    sh = np.shape(warped)
    return _launch("flow_primal", {"u": u, "p": p, "w": warped, "rho": rho0}, sh[::-1],
                   _dims(sh, spacing_mm) + (np.float32(lt), np.float32(theta)), "u", (3,) + sh, runtime)


def dual_cl(u, p, spacing_mm, s: float, eps: float, runtime=None) -> np.ndarray:
    """``flow_dual`` once (float32): :func:`dual_reference`."""
    sh = np.shape(u)[1:]
    return _launch("flow_dual", {"u": u, "p": p}, sh[::-1], _dims(sh, spacing_mm) + (np.float32(s), np.float32(eps)),
                   "p",
                   (9,) + sh, runtime)


def resample_cl(src, shape: tuple, runtime=None) -> np.ndarray:
    """``flow_resample`` once (float32) on ``src`` (b, mz, my, mx), b in (1, 3): :func:`resample_reference`."""
    b, mz, my, mx = np.shape(src)
    nz, ny, nx = shape
    return _launch("flow_resample", {"src": src, "dst": None}, (nx, ny, nz * b),
                   tuple(np.int32(v) for v in (mx, my, mz, nx, ny, nz)), "dst", (b,) + tuple(shape), runtime, batch=b)
