"""Cone-beam forward projector of a voxel volume (Joseph's method, ``kernels/voxel_project.cl``).

``project_volume`` returns ``proj[view, row, col]`` = the line integral of a voxel volume
``mu[z, y, x]`` (float32, 1/mm) along the half-line from each view's source through the
centre of each detector cell (dimensionless, float32), with the same per-view frames as the
analytic projector :func:`clrecon.simulation.projector.project_views`. It is the forward
model for iterative reconstruction and for projecting volumes that have no analytic form;
the analytic projector stays the exact reference for simulated data.

Why Joseph and not Siddon: Siddon's exact intersection lengths make the projection the
integral of a piecewise-*constant* volume, so it jumps whenever a ray crosses a voxel
boundary (as a function of the ray's position) and aliases into high-frequency patterns on
fine detectors. Joseph's method interpolates (one sample per voxel-centre plane along the
ray's dominant axis, bilinear in the other two axes): the projection is a continuous function
of the geometry, its sampling density is fixed (one sample per plane, every voxel along the
way is touched), and each sample is four contiguous-ish reads with no per-step branching,
which suits a one-work-item-per-ray kernel. It is the usual choice of the forward projector
in iterative CT (e.g. ASTRA's and TIGRE's interpolated projectors).

The algorithm (written once here; the kernel and :func:`project_volume_reference` follow it):

- index coordinates ``g = (p - origin) / spacing``: voxel ``[iz, iy, ix]`` is centred on
  ``g = (ix, iy, iz)``, the volume's box is ``g in [-1/2, n - 1/2]`` per axis, mu = 0 outside;
- the ray ``p(t) = s + t d``, ``d = (det - s) + u e_u + v e_v``, ``t >= 0``, is clipped to the
  box; the dominant axis ``k`` is the largest ``|d_k / spacing_k|`` (ties: x, then y, then z);
- slab ``i`` (``|g_k - i| <= 1/2``) contributes ``w_i f_i``: ``w_i`` the length (mm) of the
  clipped ray inside the slab, ``f_i`` the bilinear interpolation of mu at the ray's crossing
  of the plane ``g_k = i``, index coordinates clamped to ``[0, n - 1]`` (so edge voxels extend
  over the half-voxel border of the box). Interior slabs have ``w_i = spacing_k |d| / |d_k|``;
  only the first and last are partial, hence a uniform volume projects to mu x the exact
  chord through the box.

Memory: the whole volume is uploaded once per call and must fit on the device (4 bytes per
voxel). Views are processed in chunks of at most ``CHUNK_CELLS`` output cells (64 MiB of
float32 on the device, two chunks in flight); the frames are host arrays, so a caller with
more views than fit in host memory calls this once per slice of views (``out=`` writes into
its own array).
"""

from __future__ import annotations

import numpy as np

from clrecon.core.runtime import get_runtime

#: per-view record sent to the kernel (float32): a = (s - origin)/spacing, D = det - s, e_u, e_v
VIEW_REC = 12
#: output cells per kernel launch (bounds the device memory of one chunk: 64 MiB of float32)
CHUNK_CELLS = 1 << 24
#: the kernel addresses voxels with 32-bit ints
MAX_VOXELS = 2 ** 31 - 1


# ---------------------------------------------------------------------------------------
# input checks (shared by the kernel wrapper and the reference)
def _real(a, name):
    a = np.asarray(a)
    if a.dtype.kind not in "fiu":
        raise TypeError(f"{name}: expected a real numeric array, got dtype {a.dtype}")
    return a


def _finite(a, name):
    bad = ~np.isfinite(a)
    if bad.any():
        idx = tuple(int(i) for i in np.argwhere(bad)[0])
        raise ValueError(f"{name} has a non-finite value {a[idx]!r} at index {idx}")


def _check_volume(mu, origin_mm, spacing_mm):
    mu = _real(mu, "mu")
    if mu.ndim != 3 or mu.size == 0:
        raise ValueError(f"mu must be a non-empty (nz, ny, nx) array, got shape {mu.shape}")
    if mu.size > MAX_VOXELS:
        raise ValueError(f"mu has {mu.size} voxels, more than the kernel's {MAX_VOXELS}")
    _finite(mu, "mu [z, y, x]")
    if mu.dtype.itemsize > 4 and np.abs(mu).max() > np.finfo(np.float32).max:
        raise ValueError(f"mu has a voxel of magnitude {np.abs(mu).max():.3g}, beyond float32")
    return (mu, *check_grid(origin_mm, spacing_mm))


def check_grid(origin_mm, spacing_mm) -> tuple[np.ndarray, np.ndarray]:
    """``origin_mm`` and ``spacing_mm`` as float64 (x, y, z) triples: finite, spacing > 0 (else ValueError)."""
    origin = np.asarray(_real(origin_mm, "origin_mm"), np.float64)
    spacing = np.asarray(_real(spacing_mm, "spacing_mm"), np.float64)
    if origin.shape != (3,) or spacing.shape != (3,):
        raise ValueError(f"origin_mm and spacing_mm must be (x, y, z) triples, got shapes {origin.shape}, "
                         f"{spacing.shape}")
    _finite(origin, "origin_mm")
    if not np.all(np.isfinite(spacing) & (spacing > 0)):
        raise ValueError(f"spacing_mm must be finite and > 0, got {spacing.tolist()}")
    return origin, spacing


def check_v_scale(v_scale, n_cols: int):
    """A cylindrical detector's per-column row scale (flat-equivalent cells ``(u[c], v[r] * v_scale[c])``)
    as float64 (n_cols,): finite and > 0 (else ValueError); None stays None (a flat detector)."""
    if v_scale is None:
        return None
    vs = np.asarray(v_scale, np.float64)
    if vs.shape != (n_cols,) or not np.all(np.isfinite(vs)) or np.any(vs <= 0):
        raise ValueError(f"v_scale must be {n_cols} finite numbers > 0, got shape {vs.shape}")
    return vs


def _check_frames(src, det_centre, e_u, e_v, u_mm, v_mm):
    src = _real(src, "src")
    if src.ndim != 2 or src.shape[1] != 3:
        raise ValueError(f"src must have shape (m, 3), got {src.shape}")
    m = src.shape[0]
    out = []
    for name, a in (("src", src), ("det_centre", det_centre), ("e_u", e_u), ("e_v", e_v)):
        a = _real(a, name)
        if a.shape != (m, 3):
            raise ValueError(f"{name} must have shape ({m}, 3), got {a.shape}")
        _finite(a, name)
        out.append(np.asarray(a, np.float64))
    for name, a in (("u_mm", u_mm), ("v_mm", v_mm)):
        a = _real(a, name)
        if a.ndim != 1 or a.size == 0:
            raise ValueError(f"{name} must be a non-empty 1-D array, got shape {a.shape}")
        _finite(a, name)
        out.append(np.asarray(a, np.float64))
    return out


# ---------------------------------------------------------------------------------------
def project_volume(mu, origin_mm, spacing_mm, src, det_centre, e_u, e_v, u_mm, v_mm, rt=None, *,
                   chunk_views: int | None = None, out=None, v_scale=None) -> np.ndarray:
    """Line integrals of a voxel volume on a flat detector (Joseph's method, OpenCL).

    Parameters
    ----------
    mu : (nz, ny, nx) real array
        Attenuation (1/mm), ``mu[iz, iy, ix]``; sent to the device as float32. Must be finite.
    origin_mm : (3,)
        Centre ``(x0, y0, z0)`` (mm) of voxel ``[0, 0, 0]``; note the order x, y, z.
    spacing_mm : (3,)
        Voxel size ``(dx, dy, dz)`` (mm), each > 0.
    src, det_centre, e_u, e_v : (m, 3) float32 or float64 arrays
        Per-view source, detector centre, column and row directions (mm), as returned by
        :func:`clrecon.core.conventions.detector_frames`.
    u_mm : (n_cols,) column centres; v_mm : (n_rows,) row centres (mm).
    rt : Runtime, optional
        OpenCL runtime (default :func:`clrecon.core.runtime.get_runtime`).
    chunk_views : int, optional
        Views per kernel launch (default: ``CHUNK_CELLS`` output cells per launch).
    out : (m, n_rows, n_cols) C-contiguous float32 array, optional
        Written in place and returned.
    v_scale : (n_cols,) array, optional
        Cells at the flat-equivalent points ``(u[c], v[r] * v_scale[c])`` of a cylindrical
        detector (:meth:`clrecon.core.detector.CylindricalDetector.ray_cells`; kernel variant
        ``CURVED``); None: flat cells.

    Returns
    -------
    (m, n_rows, n_cols) float32 line integrals (dimensionless), ``proj[view, row, col]``.

    Raises
    ------
    TypeError for a non-numeric array, ValueError for a wrong shape, a non-finite voxel (the
    message names the first one's ``[z, y, x]`` index), a non-positive spacing.
    """
    mu, origin, spacing = _check_volume(mu, origin_mm, spacing_mm)
    src, det, eu, ev, u, v = _check_frames(src, det_centre, e_u, e_v, u_mm, v_mm)
    m = len(src)
    shape = (m, len(v), len(u))
    if out is None:
        out = np.empty(shape, np.float32)
    elif out.shape != shape or out.dtype != np.float32 or not out.flags.c_contiguous:
        raise ValueError(f"out must be a C-contiguous float32 array of shape {shape}")
    if m == 0:
        return out
    if chunk_views is not None and (int(chunk_views) != chunk_views or chunk_views < 1):
        raise ValueError(f"chunk_views must be an integer >= 1, got {chunk_views!r}")
    rt = rt or get_runtime()
    nz, ny, nx = mu.shape
    views = np.concatenate([(src - origin) / spacing, det - src, eu, ev], axis=1)      # (m, VIEW_REC)
    n_rows, n_cols = len(v), len(u)
    extra = []
    if v_scale is not None:
        vs = check_v_scale(v_scale, n_cols)
        kern = rt.kernel("voxel_project.cl", "voxel_project", CURVED=1)
        extra = [rt.to_device(vs)]
    else:
        kern = rt.kernel("voxel_project.cl", "voxel_project")
    mu_buf = rt.to_device(mu, np.float32, "mu")
    u_buf, v_buf = rt.to_device(u), rt.to_device(v)
    step = int(chunk_views or max(1, CHUNK_CELLS // (n_rows * n_cols)))
    pending = []
    for a in range(0, m, step):
        b = min(m, a + step)
        view_buf = rt.to_device(views[a:b])
        out_buf = rt.empty((b - a, n_rows, n_cols))
        ev_k = kern(rt.queue, (n_cols, n_rows, b - a), None, mu_buf, np.int32(nx), np.int32(ny), np.int32(nz),
                    np.float32(spacing[0]), np.float32(spacing[1]), np.float32(spacing[2]),
                    view_buf, u_buf, v_buf, np.int32(n_cols), np.int32(n_rows), *extra, out_buf)
        copy = rt.cl.enqueue_copy(rt.queue, out[a:b], out_buf, wait_for=[ev_k], is_blocking=False)
        pending.append((copy, view_buf, out_buf))       # buffers stay referenced until copied
        if len(pending) > 1:                            # at most two chunks in flight
            pending.pop(0)[0].wait()
    for p in pending:
        p[0].wait()
    return out


# ---------------------------------------------------------------------------------------
def _rays(src, det, eu, ev, u, v, origin, spacing, v_scale=None):
    """Per ray (flattened view, row, col): a (R, 3), b (R, 3) in index units and |d| (R,) mm."""
    vv = v[:, None] * (np.ones(len(u)) if v_scale is None else np.asarray(v_scale, np.float64))[None, :]
    d = (det - src)[:, None, None, :] + u[None, None, :, None] * eu[:, None, None, :] \
        + vv[None, :, :, None] * ev[:, None, None, :]
    d = d.reshape(-1, 3)
    a = np.repeat((src - origin) / spacing, len(u) * len(v), axis=0)
    return a, d / spacing, np.linalg.norm(d, axis=-1)


def _clip(a, b, n):
    """Clipped parameter range [t0, t1] (R,) of the half-lines t >= 0 and a hit mask."""
    t0 = np.zeros(len(a))
    t1 = np.full(len(a), np.inf)
    hit = np.ones(len(a), bool)
    for k in range(3):
        lo, hi = -0.5 - a[:, k], n[k] - 0.5 - a[:, k]
        par = b[:, k] == 0.0
        with np.errstate(divide="ignore", invalid="ignore"):
            ta, tb = lo / b[:, k], hi / b[:, k]
        t0 = np.where(par, t0, np.maximum(t0, np.minimum(ta, tb)))
        t1 = np.where(par, t1, np.minimum(t1, np.maximum(ta, tb)))
        hit &= ~(par & ((lo > 0) | (hi < 0)))
    return t0, t1, hit & (t1 > t0)


def _dominant(b):
    """Dominant axis (R,) int: the largest |b_k|, ties to the lower axis (argmax takes the first)."""
    return np.argmax(np.abs(b), axis=-1)


def ray_samples(origin_mm, spacing_mm, shape_zyx, src, det_centre, e_u, e_v, u_mm, v_mm) -> np.ndarray:
    """Number of plane samples (slabs with a piece of ray) per ray, (m, n_rows, n_cols) int64.

    Host float64, for throughput counts (each sample reads four voxels).
    """
    origin = np.asarray(origin_mm, np.float64)
    spacing = np.asarray(spacing_mm, np.float64)
    src, det, eu, ev, u, v = _check_frames(src, det_centre, e_u, e_v, u_mm, v_mm)
    n = np.asarray(shape_zyx)[::-1]
    a, b, _ = _rays(src, det, eu, ev, u, v, origin, spacing)
    t0, t1, hit = _clip(a, b, n)
    k = _dominant(b)
    r = np.arange(len(a))
    ga, gb = a[r, k] + b[r, k] * np.where(hit, t0, 0), a[r, k] + b[r, k] * np.where(hit, t1, 0)
    lo = np.clip(np.floor(np.minimum(ga, gb) + 0.5), 0, n[k] - 1)
    hi = np.clip(np.floor(np.maximum(ga, gb) + 0.5), 0, n[k] - 1)
    return np.where(hit, hi - lo + 1, 0).astype(np.int64).reshape(len(src), len(v), len(u))


def chord_lengths(origin_mm, spacing_mm, shape_zyx, src, det_centre, e_u, e_v, u_mm, v_mm, v_scale=None,
                  *, chunk_rays: int = 1 << 20) -> np.ndarray:
    """Each ray's length (mm) inside the volume's box [-1/2, n - 1/2] (index units): the projection
    of a volume of ones, ``project_volume(ones)``, without walking the ray (host float64).

    Joseph's slab weights of one ray add up to the clipped range of its dominant axis and each
    sample's bilinear weights to 1, so the projector gives a uniform volume of ones exactly this
    chord, to float32 rounding (tested). Arguments as :func:`project_volume` (``v_scale``: a
    cylindrical detector's cells); rays are taken ``chunk_rays`` at a time (the float64 arrays of
    a chunk: ~100 bytes a ray). Returns (m, n_rows, n_cols) float32; 0 where a ray misses.
    """
    origin, spacing = check_grid(origin_mm, spacing_mm)
    src, det, eu, ev, u, v = _check_frames(src, det_centre, e_u, e_v, u_mm, v_mm)
    v_scale = check_v_scale(v_scale, len(u))
    n = np.asarray(shape_zyx)[::-1]
    out = np.zeros((len(src), len(v), len(u)), np.float32)
    step = max(1, int(chunk_rays) // max(1, len(u) * len(v)))
    for a0 in range(0, len(src), step):
        sl = slice(a0, min(len(src), a0 + step))
        a, b, length = _rays(src[sl], det[sl], eu[sl], ev[sl], u, v, origin, spacing, v_scale)
        t0, t1, hit = _clip(a, b, n)
        out[sl] = np.where(hit, (t1 - t0) * length, 0.0).reshape(-1, len(v), len(u))
    return out


def joseph_samples(a, b, length, n):
    """The float64 Joseph samples of rays ``p(t) = a + t b`` (voxel units) through a grid of ``n`` =
    (nx, ny, nz) voxels, as :func:`project_volume` takes them: the walk both float64 references share.

    ``a``, ``b`` (R, 3) and ``length`` (R,) mm per unit of t, from :func:`_rays`. Returns
    ``(step, samples)``. ``step`` (R,): ``|b|`` along each ray's dominant axis (1 for a ray that
    misses). ``samples``: an iterator of ``(k, i, rays, w, j0, j1, l0, l1, fj, fl)``: rays ``rays``
    (int64) cross plane ``i`` of their dominant axis ``k`` over ``w`` of a plane, at the bilinear
    position between voxels ``j0``/``j1`` and ``l0``/``l1`` of the other two axes (j < l) with
    fractions ``fj``, ``fl``. Ray r's line integral is ``length[r] / step[r]`` (mm per plane) times
    the sum, plane by plane in increasing ``i``, of ``w`` times the plane's bilinear value there.
    """
    t0, t1, hit = _clip(a, b, n)
    hit &= length > 0
    k_all = _dominant(b)
    step = np.ones(len(a))
    parts = []
    for k in range(3):
        sel = np.nonzero(hit & (k_all == k))[0]
        if len(sel):
            step[sel] = np.abs(b[sel, k])
            parts.append((k, sel))

    def samples():
        for k, sel in parts:
            j, l = [ax for ax in range(3) if ax != k]
            ak, bk = a[sel, k], b[sel, k]
            ga, gb = ak + bk * t0[sel], ak + bk * t1[sel]
            glo = np.clip(np.minimum(ga, gb), -0.5, n[k] - 0.5)
            ghi = np.clip(np.maximum(ga, gb), -0.5, n[k] - 0.5)
            rj, rl = b[sel, j] / bk, b[sel, l] / bk
            cj, cl = a[sel, j] - rj * ak, a[sel, l] - rl * ak
            for i in range(n[k]):
                w = np.minimum(i + 0.5, ghi) - np.maximum(i - 0.5, glo)
                on = w > 0
                if not on.any():
                    continue
                gj = np.clip(cj[on] + rj[on] * i, 0, n[j] - 1)
                gl = np.clip(cl[on] + rl[on] * i, 0, n[l] - 1)
                j0 = np.minimum(np.floor(gj).astype(np.int64), max(n[j] - 2, 0))
                l0 = np.minimum(np.floor(gl).astype(np.int64), max(n[l] - 2, 0))
                j1, l1 = np.minimum(j0 + 1, n[j] - 1), np.minimum(l0 + 1, n[l] - 1)
                yield k, i, sel[on], w[on], j0, j1, l0, l1, gj - j0, gl - l0

    return step, samples()


def project_volume_reference(mu, origin_mm, spacing_mm, src, det_centre, e_u, e_v, u_mm, v_mm,
                             v_scale=None) -> np.ndarray:
    """:func:`project_volume` in float64 NumPy, the same algorithm (for tests; small inputs).

    Vectorised over rays: for each dominant axis, one pass over its planes for all rays of
    that axis at once (:func:`joseph_samples`). Memory ~ 100 bytes per ray. Same parameters and
    checks as :func:`project_volume`; returns (m, n_rows, n_cols) float64.
    """
    mu, origin, spacing = _check_volume(mu, origin_mm, spacing_mm)
    src, det, eu, ev, u, v = _check_frames(src, det_centre, e_u, e_v, u_mm, v_mm)
    vol = np.asarray(mu, np.float64)
    n = np.array(vol.shape[::-1])                      # (nx, ny, nz)
    volx = np.transpose(vol, (2, 1, 0))                # volx[ix, iy, iz]
    a, b, length = _rays(src, det, eu, ev, u, v, origin, spacing, v_scale)
    step, samples = joseph_samples(a, b, length, n)
    acc = np.zeros(len(a))
    for k, i, rays, w, j0, j1, l0, l1, fj, fl in samples:
        plane = np.moveaxis(volx, k, 0)[i]             # plane[g_j, g_l] (j < l)
        m0 = plane[j0, l0] + fj * (plane[j1, l0] - plane[j0, l0])
        m1 = plane[j0, l1] + fj * (plane[j1, l1] - plane[j0, l1])
        acc[rays] += w * (m0 + fl * (m1 - m0))
    return (acc * length / step).reshape(len(src), len(v), len(u))
