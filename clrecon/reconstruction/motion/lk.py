"""Iterative Lucas-Kanade optical flow on the engine's OpenCL runtime (``kernels/lk.cl``).

An OpenCL port of scikit-image's ``optical_flow_ilk`` (Le Besnerais & Champagnat, ICIP 2005;
``skimage/registration/_optical_flow.py``, ``_optical_flow_utils.py``) with a flat window and no
prefilter -- the ``mc`` method's default breathing registration (``recon.mc.registration =
"lucas_kanade_cl"``) -- followed step for step so that its fields are scikit-image's to float32
rounding where the algorithm allows:

1. images: clipped to ``hu_window`` and divided by its width in float64, rounded to float32
   (:func:`clrecon.reconstruction.motion.registration.register`'s preparation for scikit-image);
2. pyramid (:func:`pyramid`, on the host with SciPy, the same calls as scikit-image's
   ``pyramid_reduce``, so the same bits): while the smallest side exceeds 32 voxels (at most 10
   levels), Gaussian smoothing (std 2/3 voxel, mode 'reflect') and linear resampling to
   ceil(n / 2) voxels per axis (grid mode, 'mirror');
3. per level, coarse to fine, from a zero flow on the coarsest: ``num_warp`` times
   - ``lk_warp``: the moving image at x + v(x) (linear, edge values beyond the grid);
   - ``lk_term``: the gradient g of the warped image (``np.gradient``), the error image
     e = g . v + reference - warped and the nine terms g_a g_b (a <= b) and g_a e;
   - ``lk_box`` three times per term: the mean over a window of 2 radius + 1 voxels along z, y
     then x, mirrored at the ends (``scipy.ndimage.uniform_filter``, mode 'mirror'), by SciPy's
     sliding sum along each line (float64 where the device has it, as SciPy; else compensated float32);
   - ``lk_solve``: v = A^-1 b per voxel (3 x 3, LU with partial pivoting), v = 0 where |det A| < 1e-14;
4. between levels (``lk_resize``): the flow on the finer grid by nearest neighbour
   (``scipy.ndimage.zoom``, order 0: index tables made on the host by SciPy itself) times the size
   ratio per axis.

Where the bits can differ from scikit-image's: the warp's interpolation (float32 here, float64 in
SciPy), the 3 x 3 solve (LAPACK's float32 LU in NumPy, whose operation order OpenBLAS chooses)
and, without float64 on the device, the window means; the gradient, the error image, the terms,
the window means in float64 and the flow resize are the same operations in NumPy's and SciPy's
order (the kernels do not contract into fma). Measured differences: docs/results/mc-study.md "Lucas-Kanade on
OpenCL".

Conventions as :func:`clrecon.reconstruction.motion.registration.register`: volumes ``(nz, ny,
nx)`` HU, spacing ``(dx, dy, dz)`` mm, result u ``(3, nz, ny, nx)`` float32 mm with components
(dx, dy, dz) on the fixed grid and ``moving(x + u(x)) ~ fixed(x)``. Internally flows are in
voxels with components in axis order (z, y, x), as scikit-image's.

Memory at the finest level: :data:`BYTES_PER_VOXEL`. Deterministic: no random sampling and no
reductions in the kernels (one owner per output: a work-item per voxel, or per line for the box
filter, in a fixed order), so a repeated call gives the same bits on one device. Each kernel has a
float64 NumPy reference here (``*_reference``), checked in tests/reconstruction/test_lk.py and run
under Oclgrind in tests/core/test_oclgrind.py.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.ndimage

from clrecon.core.runtime import aligned_empty, get_runtime
from clrecon.reconstruction.motion.flow import check_pair

#: Peak bytes per voxel of the finest level, host and device together on a CPU device: 16 float32
#: volumes -- the reference and moving images (shared with the device, not copied), the flow (3),
#: the warped image, the nine window sums, and one for a term and its box-filter passes (ping-pong
#: with the term's own slot of the sums) -- plus one for the coarser levels' images of both
#: pyramids (2 x (1/8 + 1/64 + ...) of a volume, 1.1 bytes per voxel), rounded up. The result
#: (3 volumes) is read back after the work buffers are released.
BYTES_PER_VOXEL = 4 * 17
#: |det A| below this: no flow at the voxel (scikit-image's guard, compared in float32; ``lk_solve``'s literal).
DET_MIN = 1e-14
#: The pyramid of scikit-image's ``_coarse_to_fine``: downscale 2, at most 10 levels, a new level
#: while the smallest side exceeds ``DOWNSCALE * MIN_SIZE``.
DOWNSCALE, MAX_LEVELS, MIN_SIZE = 2, 10, 16
#: The terms of the local system, in ``lk_term``'s order: A's (a, b) pairs, then b's axes.
A_PAIRS = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))


@dataclass(frozen=True, kw_only=True)
class LKConfig:
    """Knobs of :func:`register_lk` (scikit-image's ``optical_flow_ilk`` with a flat window, no prefilter).

    radius : window radius in voxels (the window is (2 radius + 1) voxels along every axis).
    num_warp : warps per pyramid level.
    hu_window : (lo, hi) HU the images are clipped to (and divided by hi - lo).
    """

    radius: int = 7
    num_warp: int = 10
    hu_window: tuple = (-900.0, 600.0)

    def __post_init__(self):
        for name in ("radius", "num_warp"):
            v = getattr(self, name)
            if not (isinstance(v, int) and not isinstance(v, bool) and v >= 1):
                raise ValueError(f"LKConfig.{name} = {v!r}: must be an integer >= 1")
        lo, hi = self.hu_window
        if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
            raise ValueError(f"LKConfig.hu_window = {self.hu_window!r}: must be finite (lo, hi) with lo < hi")


# -- the host's part: images, pyramid, resize tables -----------------------------------------------
def prepare(vol, hu_window: tuple) -> np.ndarray:
    """``vol`` clipped to ``hu_window`` and divided by its width (float64), as float32 (page-aligned);
    plane by plane (no whole float64 copy), the same bits as the whole-volume expression."""
    lo, hi = hu_window
    v = np.asarray(vol)
    out = aligned_empty(v.shape, np.float32)
    for k in range(v.shape[0]):
        out[k] = np.clip(np.asarray(v[k], np.float64), lo, hi) / (hi - lo)
    return out


def pyramid(img: np.ndarray) -> list[np.ndarray]:
    """scikit-image's ``_get_pyramid(img, 2, 10, 16)`` of a float32 volume, coarsest first, by the
    same SciPy calls as its ``pyramid_reduce`` (Gaussian std 2/3 voxel, mode 'reflect', truncated at
    4 std; linear ``zoom`` in grid mode, 'mirror', to ceil(n / 2); clipped to the smoothed range)."""
    levels = [img]
    count = 1
    while count < MAX_LEVELS and min(levels[-1].shape) > DOWNSCALE * MIN_SIZE:
        prev = levels[-1]
        sm = np.empty_like(prev)
        scipy.ndimage.gaussian_filter(prev, 2 * DOWNSCALE / 6.0, output=sm, mode="reflect", cval=0, truncate=4.0)
        shape = tuple(math.ceil(d / float(DOWNSCALE)) for d in prev.shape)
        zoom = [1 / f for f in np.divide(prev.shape, shape)]
        out = scipy.ndimage.zoom(sm, zoom, order=1, mode="mirror", cval=0, grid_mode=True)
        np.clip(out, np.min(sm), np.max(sm), out=out)
        del sm
        levels.append(out)
        count += 1
    return levels[::-1]


def resize_tables(src_shape: tuple, dst_shape: tuple) -> tuple[list[np.ndarray], tuple]:
    """Per axis (z, y, x): the source index of each destination index of scikit-image's
    ``_resize_flow`` (``scipy.ndimage.zoom``, order 0, 'nearest', by SciPy itself on an index line),
    and the float32 size ratios n / m its components are multiplied by."""
    idx = []
    for m, n in zip(src_shape, dst_shape, strict=True):
        line = scipy.ndimage.zoom(np.arange(m, dtype=np.float64), n / m, order=0, mode="nearest", prefilter=False)
        if line.shape != (n,):  # pragma: no cover - SciPy's output size is round(m * n / m) = n
            raise RuntimeError(f"resize table {m} -> {n}: SciPy gave {line.shape}")
        idx.append(line.astype(np.int32))
    scale = tuple(np.float32(n / m) for m, n in zip(src_shape, dst_shape, strict=True))
    return idx, scale


# -- float64 NumPy references of the kernels ---------------------------------------------------------
def warp_reference(src, v) -> np.ndarray:
    """``lk_warp``: ``src`` (nz, ny, nx) at x + v(x), v (3, nz, ny, nx) voxels (z, y, x), linear with
    the index clamped to the grid."""
    s = np.asarray(src, np.float64)
    v = np.asarray(v, np.float64)
    nz, ny, nx = s.shape
    k, j, i = np.meshgrid(np.arange(nz), np.arange(ny), np.arange(nx), indexing="ij")
    f = [np.clip(g + d, 0, n - 1) for g, d, n in ((k, v[0], nz), (j, v[1], ny), (i, v[2], nx))]
    lo = [np.minimum(np.floor(c).astype(np.int64), max(n - 2, 0)) for c, n in zip(f, s.shape, strict=True)]
    t = [c - a for c, a in zip(f, lo, strict=True)]
    hi = [np.minimum(a + 1, n - 1) for a, n in zip(lo, s.shape, strict=True)]
    out = np.zeros(s.shape)
    for cz in (0, 1):
        for cy in (0, 1):
            for cx in (0, 1):
                w = ((t[0] if cz else 1 - t[0]) * (t[1] if cy else 1 - t[1]) * (t[2] if cx else 1 - t[2]))
                out += w * s[(hi if cz else lo)[0], (hi if cy else lo)[1], (hi if cx else lo)[2]]
    return out


def term_reference(warped, ref, v, q: int) -> np.ndarray:
    """``lk_term`` term ``q`` (0-5: g_a g_b of :data:`A_PAIRS`; 6-8: g_(q-6) e), g = np.gradient(warped)."""
    w = np.asarray(warped, np.float64)
    g = np.gradient(w)
    if q < 6:
        a, b = A_PAIRS[q]
        return g[a] * g[b]
    e = sum(gc * vc for gc, vc in zip(g, np.asarray(v, np.float64), strict=True)) + np.asarray(ref, np.float64) - w
    return g[q - 6] * e


def box_reference(src, axis: int, radius: int) -> np.ndarray:
    """``lk_box``: the mean of 2 radius + 1 voxels along ``axis`` (0: z, 1: y, 2: x), mirrored at the ends
    (d c b | a b c d | c b a, repeatedly)."""
    a = np.asarray(src, np.float64)
    n = a.shape[axis]
    idx = np.arange(-radius, n + radius)
    if n == 1:
        idx = np.zeros_like(idx)
    else:
        p = 2 * n - 2
        idx = idx % p
        idx = np.where(idx < n, idx, p - idx)
    ext = np.cumsum(np.concatenate([np.zeros_like(np.take(a, [0], axis)), np.take(a, idx, axis)], axis), axis)
    size = 2 * radius + 1
    return (np.take(ext, np.arange(size, size + n), axis) - np.take(ext, np.arange(n), axis)) / size


def solve_reference(terms) -> np.ndarray:
    """``lk_solve``: v (3, nz, ny, nx) with A v = b per voxel (terms (9, ...) in ``lk_term``'s order),
    0 where |det A| < :data:`DET_MIN`."""
    t = np.asarray(terms, np.float64)
    A = np.empty(t.shape[1:] + (3, 3))
    for q, (a, b) in enumerate(A_PAIRS):
        A[..., a, b] = A[..., b, a] = t[q]
    b = np.moveaxis(t[6:9], 0, -1)[..., None]
    bad = np.abs(np.linalg.det(A)) < DET_MIN
    A[bad] = np.eye(3)
    b[bad] = 0.0
    return np.moveaxis(np.linalg.solve(A, b)[..., 0], -1, 0)


def resize_reference(v, shape: tuple) -> np.ndarray:
    """``lk_resize``: scikit-image's ``_resize_flow`` of v (3, mz, my, mx) onto ``shape`` (float64)."""
    v = np.asarray(v, np.float64)
    (iz, iy, ix), _ = resize_tables(v.shape[1:], shape)
    scale = [n / m for m, n in zip(v.shape[1:], shape, strict=True)]
    return np.stack([scale[c] * v[c][np.ix_(iz, iy, ix)] for c in range(3)])


# -- the OpenCL registration ---------------------------------------------------------------------------
def has_fp64(rt) -> bool:
    """Whether the device sums the box filter in float64 as SciPy does (``LK_DOUBLE``; else the
    compensated float32 sum)."""
    return "cl_khr_fp64" in rt.device.extensions


class _Kernels:
    """The kernels of ``lk.cl`` on one runtime (built once per runtime by :meth:`Runtime.kernel`)."""

    def __init__(self, rt):
        d = int(has_fp64(rt))
        self.warp = rt.kernel("lk.cl", "lk_warp", LK_DOUBLE=d)
        self.term = rt.kernel("lk.cl", "lk_term", LK_DOUBLE=d)
        self.box = rt.kernel("lk.cl", "lk_box", LK_DOUBLE=d)
        self.solve = rt.kernel("lk.cl", "lk_solve", LK_DOUBLE=d)
        self.resize = rt.kernel("lk.cl", "lk_resize", LK_DOUBLE=d)


def _solve_level(rt, k, d_ref, d_mov, d_v, shape, cfg: LKConfig) -> None:
    """``cfg.num_warp`` warps of scikit-image's ``_ilk`` on one level: d_v (3, shape) in place.
    Per term: ``lk_term`` into t, the box passes t -> the sums' slot q (z), slot q -> t (y), t -> slot q (x)."""
    nz, ny, nx = shape
    dims = (np.int32(nx), np.int32(ny), np.int32(nz))
    g = (nx, ny, nz)
    d_w, d_t, d_s = rt.empty(shape), rt.empty(shape), rt.empty((9,) + tuple(shape))
    r, zero = np.int32(cfg.radius), np.int32(0)
    try:
        for _ in range(cfg.num_warp):
            k.warp(rt.queue, g, None, d_mov, d_v, d_w, *dims)
            for q in range(9):
                slot = np.int32(q)
                k.term(rt.queue, g, None, d_w, d_ref, d_v, d_t, *dims, slot)
                k.box(rt.queue, (nx, ny), None, d_t, d_s, *dims, np.int32(0), r, zero, slot)
                k.box(rt.queue, (nx, nz), None, d_s, d_t, *dims, np.int32(1), r, slot, zero)
                k.box(rt.queue, (ny, nz), None, d_t, d_s, *dims, np.int32(2), r, zero, slot)
            k.solve(rt.queue, g, None, d_s, d_v, *dims)
        rt.queue.finish()
    finally:
        for b in (d_w, d_t, d_s):
            b.release()


def _resize(rt, k, d_src, src_shape, dst_shape):
    """Device buffer (3, dst_shape): ``lk_resize`` of d_src (3, src_shape) (:func:`resize_tables`)."""
    (iz, iy, ix), (sz, sy, sx) = resize_tables(src_shape, dst_shape)
    tables = [rt.to_device(t, np.int32, "resize table") for t in (iz, iy, ix)]
    out = rt.empty((3,) + tuple(dst_shape))
    mz, my, mx = src_shape
    nz, ny, nx = dst_shape
    k.resize(rt.queue, (nx, ny, nz), None, d_src, out, *tables,
             *(np.int32(v) for v in (mx, my, mz, nx, ny, nz)), sz, sy, sx)
    rt.queue.finish()
    for t in tables:
        t.release()
    return out


def register_lk(fixed, moving, spacing_mm: tuple, cfg: LKConfig | None = None, runtime=None) -> np.ndarray:
    """Displacement u with ``moving(x + u(x)) ~ fixed(x)`` on the fixed grid: (3, nz, ny, nx) float32 mm.

    ``fixed``, ``moving``: (nz, ny, nx) HU volumes on one grid, finite, at least 2 voxels along every
    axis; ``spacing_mm``: (dx, dy, dz) mm (the flow is found in voxels, as scikit-image's, and
    scaled to mm at the end); ``cfg``: :class:`LKConfig`; ``runtime``: the OpenCL runtime (default
    :func:`get_runtime`).
    """
    cfg = cfg or LKConfig()
    f, m, h = check_pair(fixed, moving, spacing_mm, axes=(0, 1, 2),
                         too_small="Lucas-Kanade needs at least 2 voxels along every axis (its gradient)")
    rt = runtime or get_runtime()
    k = _Kernels(rt)
    ref, mov = prepare(f, cfg.hu_window), prepare(m, cfg.hu_window)
    levels = list(zip(pyramid(ref), pyramid(mov), strict=True))
    d_v = None
    prev = None
    for i0, i1 in levels:
        shape = i0.shape
        if d_v is None:
            d_v = rt.empty((3,) + shape)
            rt.cl.enqueue_fill_buffer(rt.queue, d_v, np.float32(0.0), 0, 3 * i0.size * 4)
        else:
            d_new = _resize(rt, k, d_v, prev, shape)
            d_v.release()
            d_v = d_new
        if shape == ref.shape:
            d_ref, d_mov = rt.share_with_device(ref, "reference"), rt.share_with_device(mov, "moving")
        else:
            d_ref, d_mov = rt.to_device(i0, np.float32, "reference"), rt.to_device(i1, np.float32, "moving")
        _solve_level(rt, k, d_ref, d_mov, d_v, shape, cfg)
        d_ref.release()
        d_mov.release()
        prev = shape
    del levels
    n = ref.size
    out = np.empty((3,) + ref.shape, np.float32)
    for c in range(3):  # (dx, dy, dz) mm from the flow's (z, y, x) voxels, as registration._flow scales it
        rt.cl.enqueue_copy(rt.queue, out[c], d_v, src_offset=(2 - c) * n * 4)
        out[c] *= np.float32(h[c])
    d_v.release()
    return out


# -- one launch of each kernel on host arrays (the tests' entry to the kernels) -----------------------
def _launch(name: str, args: list, shape: tuple, out: int, out_shape: tuple, runtime=None,
            double: bool | None = None) -> np.ndarray:
    """Run kernel ``name`` once over ``shape`` (nz, ny, nx): ``args`` in order, arrays uploaded (float32, or
    int32 where they are), None an output buffer of ``out_shape``, scalars as given; argument ``out`` read
    back. ``double``: build with ``LK_DOUBLE`` (default: where the device has float64)."""
    rt = runtime or get_runtime()
    kern = rt.kernel("lk.cl", name, LK_DOUBLE=int(has_fp64(rt) if double is None else double))
    bufs, vals = [], []
    for a in args:
        if a is None:
            b = rt.empty(out_shape)
        elif isinstance(a, np.ndarray):
            dt = np.int32 if a.dtype.kind in "iu" else np.float32
            b = rt.empty(a.shape, dt)
            rt.cl.enqueue_copy(rt.queue, b, np.ascontiguousarray(a, dt))
        else:
            vals.append(a)
            continue
        bufs.append(b)
        vals.append(b)
    nz, ny, nx = shape
    kern(rt.queue, (nx, ny, nz), None, *vals)
    res = rt.from_device(vals[out], out_shape)
    for b in bufs:
        b.release()
    return res


def _dims(shape):
    nz, ny, nx = shape
    return (np.int32(nx), np.int32(ny), np.int32(nz))


def warp_cl(src, v, runtime=None) -> np.ndarray:
    """``lk_warp`` once (float32): :func:`warp_reference`."""
    sh = np.shape(src)
    return _launch("lk_warp", [np.asarray(src), np.asarray(v), None, *_dims(sh)], sh, 2, sh, runtime)


def term_cl(warped, ref, v, q: int, runtime=None) -> np.ndarray:
    """``lk_term`` once (float32): :func:`term_reference`."""
    sh = np.shape(warped)
    return _launch("lk_term", [np.asarray(warped), np.asarray(ref), np.asarray(v), None, *_dims(sh), np.int32(q)],
                   sh, 3, sh, runtime)


def box_cl(src, axis: int, radius: int, runtime=None, double: bool | None = None) -> np.ndarray:
    """``lk_box`` once (float32 in and out, slot 0): :func:`box_reference`; ``double``: the float64 sum
    (default where the device has float64) or the compensated float32 sum."""
    sh = np.shape(src)
    lines = [(sh[1], sh[2]), (sh[0], sh[2]), (sh[0], sh[1])][axis]  # the launch's (b, a): the other axes
    return _launch("lk_box", [np.asarray(src), None, *_dims(sh), np.int32(axis), np.int32(radius), np.int32(0),
                              np.int32(0)],
                   (1,) + lines, 1, sh, runtime, double)


def solve_cl(terms, runtime=None) -> np.ndarray:
    """``lk_solve`` once (float32): :func:`solve_reference`."""
    sh = np.shape(terms)[1:]
    return _launch("lk_solve", [np.asarray(terms), None, *_dims(sh)], sh, 1, (3,) + tuple(sh), runtime)


def resize_cl(v, shape: tuple, runtime=None) -> np.ndarray:
    """``lk_resize`` once (float32) of v (3, mz, my, mx) onto ``shape``: :func:`resize_reference`."""
    src = np.shape(v)[1:]
    (iz, iy, ix), scale = resize_tables(src, shape)
    args = [np.asarray(v), None, iz, iy, ix, *(np.int32(x) for x in (src[2], src[1], src[0]) + tuple(shape)[::-1]),
            *scale]
    return _launch("lk_resize", args, shape, 1, (3,) + tuple(shape), runtime)
