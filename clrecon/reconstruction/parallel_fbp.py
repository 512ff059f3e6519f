"""Fan-to-parallel rebinning and parallel-beam FBP (``recon.backprojector = "parallel-rebin"``).

After phase-space interpolation every view of a target's fan-beam sinogram stands for the
same target phase, so the two rays of a full 2 pi scan that cover one line (the direct and
the conjugate ray) measure the same thing and can be merged: the V fan views over 2 pi become
V/2 parallel views over pi, and a parallel-beam backprojection needs no per-voxel division or
distance weight (Kak & Slaney 1988, sec. 3.4.3 "re-sorting"; Herman 1980, ch. 10).

Steps, for a batch of fan sinograms (B, V, C) of line integrals on one geometry:

1. **rebin** (OpenCL ``kernels/parallel_beam.cl:rebin_parallel16``): parallel view i at
   theta_i = beta0 + pi/2 + i dbeta (dbeta = 2 pi / V, i < V/2), sample k at
   s_k = (k - (n_s - 1)/2) ds; its value is the mean of the direct ray (fan angle
   gamma_k = asin(s_k / SID), fan view index i + gamma_k / dbeta) and the conjugate ray
   (-gamma_k, fan view i + V/2 - gamma_k / dbeta), each bilinear in (view, column). The
   column of a fan angle comes from the detector's per-column fan angles ``fan_angles``
   (C,) by linear interpolation, so the same code serves a flat detector (gamma = atan(u/SDD),
   not equiangular: :func:`flat_fan_angles`) or any other detector whose columns' fan angles
   increase with the column index. Beyond the outer column centres the edge column is used,
   as the fan-beam kernel does.
2. **filter** (host, :mod:`scipy.fft`): each parallel row convolved with the band-limited ramp
   kernel h of K&S eq. (61) sampled at ds (``h(0) = 1/(4 ds^2)``, ``h(odd n) = -1/(n pi ds)^2``),
   times ds, windowed by :mod:`clrecon.reconstruction.filters` (the same windows as the fan
   path), zero-padded to >= 2 n_s - 1 (linear, not circular, convolution); no 1/2 factor
   (the parallel views cover pi once).
3. **backproject** (OpenCL ``backproject_parallel16x2``): ``mu = dtheta sum_i Q_i(x cos theta_i
   + y sin theta_i)``, linear in s, dtheta = pi / (V/2) = dbeta; 0 outside the FOV circle.

Sampling: ds is SID times the fan-angle step of the two middle columns over
:data:`S_OVERSAMPLE` = 2 (for today's flat detector tau / 2 to 1e-7, tau = the isocentre column pitch
col_pitch SID/SDD: with ds = tau the two interpolations in s, rebinning and
backprojection, blur the image visibly more than the direct path), and the s grid spans
the FOV circle plus one sample on either side, so every pixel inside the FOV reads two
samples in range. Accuracy and speed trade-offs (two interpolations instead of one: a
slightly smoother image) are measured in ``docs/fbp.md`` ("Parallel-rebin backprojector").

Shapes: fan sinograms (B, V, C) float32 view-major; parallel sinograms (B, V/2, n_s) float32;
images (B, ny, nx) float32 mu in 1/mm, ``img[y, x]``.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass

import numpy as np
import scipy.fft

from clrecon.core.runtime import get_runtime
from clrecon.reconstruction import fbp as fbp_mod
from clrecon.reconstruction.filters import FILTERS as _WINDOW_FUNCTIONS

_KERNEL_FILE = "parallel_beam.cl"
LANES = fbp_mod.BATCH_LANES
#: Work-group size and view chunk of the parallel backprojector (as the fan kernel's).
LOCAL_SIZE = fbp_mod.LOCAL_SIZE
VIEW_CHUNK = fbp_mod.VIEW_CHUNK
_REBIN_LOCAL = 64
#: Parallel samples per fan-angle step of the middle columns (ds = SID dgamma / S_OVERSAMPLE).
#: Measured on disks at demo's sampling (128^2 of 3 mm, 360 views x 240 columns of 3 mm), as
#: parallel - direct: 1 -> max 185 HU, RMS 21.5 HU; 2 -> max 85, RMS 13.7 (MAE vs the exact
#: image +0.3 HU); 4 -> max 111, RMS 16.8 (the ramp reaches frequencies the detector does not
#: sample); band-limiting the ramp to the detector's Nyquist at 2 smooths more (RMS 15.2).
S_OVERSAMPLE = 2


def flat_fan_angles(fan: fbp_mod.FanBeamGeometry) -> np.ndarray:
    """Fan angle of each column centre of the geometry's detector (rad), (C,) float64.

    Flat: gamma = atan(u / SDD). Cylindrical (equiangular): gamma_j = (j - centre_col) * col_pitch / SDD,
    the central column of an off-centre (quarter-offset) arc included. A phi flying focal spot
    (per-view source angle shifts) is refused: the rebinning assumes one source per view angle.
    """
    if fan.source_shifts:
        raise ValueError("parallel-rebin: a phi flying focal spot (per-view source shifts) is not supported; "
                         "use recon.backprojector = 'direct'")
    if fan.curved:
        return (np.arange(fan.n_cols, dtype=np.float64) - fan.centre_col) * fan.delta_gamma_rad
    return np.arctan(fan.col_coords_mm() / fan.sdd_mm)


@dataclass(frozen=True)
class ParallelGeometry:
    """The parallel-beam sampling a fan geometry is rebinned to, and the image grid.

    ``n_angles`` views at ``theta0_rad + i * dtheta_rad`` (i < n_angles, covering pi),
    ``n_s`` samples at ``(k - (n_s - 1)/2) * ds_mm``; image ``nx`` x ``ny`` of ``voxel_mm``;
    pixels with centres beyond ``fov_radius_mm`` are 0.
    """

    n_angles: int
    n_s: int
    ds_mm: float
    theta0_rad: float
    dtheta_rad: float
    nx: int
    ny: int
    voxel_mm: float
    fov_radius_mm: float

    def s_coords_mm(self) -> np.ndarray:
        """Sample positions s_k (mm), (n_s,) float64."""
        return (np.arange(self.n_s) - 0.5 * (self.n_s - 1)) * self.ds_mm

    def angles_rad(self) -> np.ndarray:
        """View angles theta_i (rad), (n_angles,) float64."""
        return self.theta0_rad + self.dtheta_rad * np.arange(self.n_angles)


def _check_fan_angles(fan: fbp_mod.FanBeamGeometry, fan_angles) -> np.ndarray:
    g = flat_fan_angles(fan) if fan_angles is None else np.asarray(fan_angles, np.float64)
    if g.shape != (fan.n_cols,) or not np.all(np.isfinite(g)):
        raise ValueError(f"fan_angles: expected {fan.n_cols} finite angles (rad), one per column, got shape {g.shape}")
    if np.any(np.diff(g) <= 0) or np.max(np.abs(g)) >= math.pi / 2:
        raise ValueError("fan_angles: must increase strictly with the column index and lie in (-pi/2, pi/2)")
    return g


def parallel_geometry(fan: fbp_mod.FanBeamGeometry, fan_angles=None,
                      oversample: int = S_OVERSAMPLE) -> ParallelGeometry:
    """The parallel sampling of :func:`rebin_table` for ``fan`` (module docstring: ds, n_s, theta).

    ``oversample``: parallel samples per fan-angle step of the middle columns (:data:`S_OVERSAMPLE`).
    """
    if fan.n_views % 2:
        raise ValueError(f"n_views = {fan.n_views}: fan-to-parallel rebinning needs an even number of views "
                         "(conjugate rays at view + V/2); use recon.backprojector = 'direct'")
    g = _check_fan_angles(fan, fan_angles)
    mid = fan.n_cols // 2
    if not (isinstance(oversample, (int, np.integer)) and oversample >= 1):
        raise ValueError(f"oversample = {oversample!r}: must be an integer >= 1")
    ds = fan.sid_mm * float(g[mid] - g[mid - 1]) / oversample
    fov = fan.fov_radius_mm
    n_half = math.ceil(fov / ds) + 1
    return ParallelGeometry(n_angles=fan.n_views // 2, n_s=2 * n_half + 1, ds_mm=ds,
                            theta0_rad=fan.beta0_rad + math.pi / 2, dtheta_rad=fan.delta_beta_rad,
                            nx=fan.nx, ny=fan.ny, voxel_mm=fan.voxel_mm, fov_radius_mm=fov)


def rebin_table(fan: fbp_mod.FanBeamGeometry, par: ParallelGeometry, fan_angles=None) -> np.ndarray:
    """Per s sample (view offset, padded column) of the direct and the conjugate ray, (n_s, 4) float64.

    Column ``c + 1`` of the padded fan row (:func:`clrecon.reconstruction.fbp.interleave_batch`,
    one edge replica either side) is column c; the fractional column of fan angle gamma is
    ``np.interp(gamma, fan_angles, arange(C))`` (edge column beyond the outer centres). View
    offsets are ``gamma / dbeta`` (+V if negative) and ``V/2 - gamma / dbeta``.
    """
    g = _check_fan_angles(fan, fan_angles)
    s = par.s_coords_mm()
    gamma = np.arcsin(np.clip(s / fan.sid_mm, -1.0, 1.0))
    cols = np.arange(fan.n_cols, dtype=np.float64)
    top = fan.n_cols + 1 - 2.0 ** -8  # so that floor + 1 stays inside the padded row
    col_d = np.clip(np.interp(gamma, g, cols) + 1.0, 0.0, top)
    col_c = np.clip(np.interp(-gamma, g, cols) + 1.0, 0.0, top)
    off_d = gamma / fan.delta_beta_rad
    off_d = np.where(off_d < 0, off_d + fan.n_views, off_d)
    off_c = 0.5 * fan.n_views - gamma / fan.delta_beta_rad
    return np.stack([off_d, col_d, off_c, col_c], axis=1)


def ramp_response(par: ParallelGeometry, window: str = "ram-lak", n_pad: int | None = None) -> np.ndarray:
    """Frequency response of the parallel ramp filter at spacing ds, (n_pad,) float64 in 1/mm (module docstring)."""
    if window not in _WINDOW_FUNCTIONS.names:
        raise ValueError(f"window = {window!r}: must be one of {', '.join(_WINDOW_FUNCTIONS.names)}")
    n_pad = padded_length(par.n_s) if n_pad is None else int(n_pad)
    ds = par.ds_mm
    k = np.arange(n_pad)
    n = np.where(k <= n_pad // 2, k, k - n_pad)
    h = np.zeros(n_pad)
    h[0] = 1.0 / (4.0 * ds * ds)
    odd = (n % 2) != 0
    h[odd] = -1.0 / (np.pi * n[odd] * ds) ** 2
    return scipy.fft.fft(h).real * ds * _WINDOW_FUNCTIONS[window](scipy.fft.fftfreq(n_pad))


def padded_length(n_s: int) -> int:
    """FFT length for filtering n_s samples: a fast length >= 2 n_s - 1."""
    return scipy.fft.next_fast_len(2 * n_s - 1, real=True)


def _tables(fan, par, fan_angles, rt):
    return (rt.to_device(rebin_table(fan, par, fan_angles).astype(np.float32)), rt.to_device(_trig_table(par)))


class ParallelFBP:
    """Rebin, filter and backproject fan sinograms already on the device (the reconstruction's path).

    Built once per (geometry, window, fan angles): holds the parallel geometry, the rebinning
    and trig tables on the device and the filter response. :meth:`images` takes a device buffer
    in :func:`clrecon.reconstruction.fbp.interleave_batch`'s layout (G, V, C + 2, 16) of
    *unfiltered* line integrals (as :func:`clrecon.reconstruction.interpolation.weights.apply_weights_interleaved`
    writes it) and returns mu images (16 G, ny, nx) float32. ``workers``: threads of the host
    filter's FFTs (default: every core, as the OpenCL kernels use them; rows are filtered
    independently, so the result does not depend on it).
    """

    def __init__(self, fan: fbp_mod.FanBeamGeometry, window: str = "ram-lak", *, fan_angles=None, runtime=None,
                 workers: int | None = None):
        self.fan = fan
        self.par = parallel_geometry(fan, fan_angles)
        self.rt = runtime or get_runtime()
        self.n_pad = padded_length(self.par.n_s)
        self.half = ramp_response(self.par, window, self.n_pad)[:self.n_pad // 2 + 1].astype(np.float32)
        self.workers = workers if workers is not None else (os.cpu_count() or 1)
        self._table, self._trig = _tables(fan, self.par, fan_angles, self.rt)

    def release(self) -> None:
        self._table.release()
        self._trig.release()

    def rebin(self, fan16, n_groups: int, wait_for=None):
        """Device buffer (G, V/2, n_s, 16) of parallel sinograms from fan16 (G, V, C + 2, 16); and its event."""
        rt, par, fan = self.rt, self.par, self.fan
        out = rt.empty((n_groups, par.n_angles, par.n_s, LANES))
        kern = rt.kernel(_KERNEL_FILE, "rebin_parallel16", _fast=True, **_defines())
        gx = -(-par.n_s // _REBIN_LOCAL) * _REBIN_LOCAL
        ev = kern(rt.queue, (gx, par.n_angles, n_groups), (_REBIN_LOCAL, 1, 1), fan16, self._table, out,
                  np.int32(fan.n_views), np.int32(fan.n_cols), np.int32(par.n_s), wait_for=wait_for)
        return out, ev

    def filter_interleaved(self, par16: np.ndarray, views_per_chunk: int = 64) -> np.ndarray:
        """Ramp-filter (G, V/2, n_s, 16) parallel sinograms along s (float32, a new array).

        ``views_per_chunk`` views at a time, so the padded work array and its spectrum stay at a
        few tens of MB (each row is filtered alone: the result does not depend on the chunking).
        """
        n_s = self.par.n_s
        out = np.empty(par16.shape, np.float32)
        work = np.zeros((par16.shape[0], views_per_chunk, self.n_pad, LANES), np.float32)
        for v0 in range(0, par16.shape[1], views_per_chunk):
            blk = par16[:, v0:v0 + views_per_chunk]
            w = work[:, :blk.shape[1]]
            w[:, :, :n_s] = blk  # samples n_s.. stay zero: the padding
            spec = scipy.fft.rfft(w, axis=2, workers=self.workers)
            spec *= self.half[:, None]
            out[:, v0:v0 + blk.shape[1]] = scipy.fft.irfft(spec, n=self.n_pad, axis=2, workers=self.workers)[:, :, :n_s]
        return out

    def backproject(self, filtered16, n_groups: int, wait_for=None) -> np.ndarray:
        """Backproject a device buffer (G, V/2, n_s, 16) of filtered parallel sinograms: (16 G, ny, nx) mu."""
        return _backproject_device(self.rt, self.par, self._trig, filtered16, n_groups, wait_for)

    def images(self, fan16, n_groups: int, wait_for=None) -> np.ndarray:
        """mu images (16 G, ny, nx) float32 of unfiltered fan sinograms on the device (class docstring)."""
        rt, par = self.rt, self.par
        d_par, ev = self.rebin(fan16, n_groups, wait_for)
        host = rt.from_device(d_par, (n_groups, par.n_angles, par.n_s, LANES), wait_for=[ev])
        d_par.release()
        d_f = rt.to_device(self.filter_interleaved(host))
        res = self.backproject(d_f, n_groups)
        d_f.release()
        return res


def _trig_table(par: ParallelGeometry) -> np.ndarray:
    """Per view (cos theta / ds, sin theta / ds), (n_angles, 2) float32, computed in float64."""
    th = par.angles_rad()
    return (np.stack([np.cos(th), np.sin(th)], axis=1) / par.ds_mm).astype(np.float32)


def _backproject_device(rt, par: ParallelGeometry, trig, filtered16, n_groups: int, wait_for=None) -> np.ndarray:
    kern = rt.kernel(_KERNEL_FILE, "backproject_parallel16x2", _fast=True, **_defines())
    shape = (n_groups * LANES, par.ny, par.nx)
    out = rt.empty(shape)
    lx, ly = LOCAL_SIZE
    gsize = (-(-par.nx // lx) * lx, -(-par.ny // ly) * ly, -(-n_groups // 2))
    ev = kern(rt.queue, gsize, LOCAL_SIZE + (1,), filtered16, trig, out, np.int32(par.nx), np.int32(par.ny),
              np.int32(par.n_angles), np.int32(par.n_s), np.float32(par.voxel_mm),
              np.float32(par.fov_radius_mm ** 2), np.float32(par.dtheta_rad), np.int32(n_groups), wait_for=wait_for)
    res = rt.from_device(out, shape, wait_for=[ev])
    out.release()
    return res


def _defines() -> dict:
    return {"LX": LOCAL_SIZE[0], "LY": LOCAL_SIZE[1], "VCHUNK": VIEW_CHUNK}


def _groups(a: np.ndarray) -> np.ndarray:
    """(B, ...) -> (G, ..., 16) interleaved batch-fastest, zero-padded to 16 G sinograms."""
    b = a.shape[0]
    g = -(-b // LANES)
    pad = np.zeros((g * LANES,) + a.shape[1:], np.float32)
    pad[:b] = a
    return np.ascontiguousarray(np.moveaxis(pad.reshape((g, LANES) + a.shape[1:]), 1, -1))


def _ungroup(a16: np.ndarray, b: int) -> np.ndarray:
    return np.moveaxis(a16, -1, 1).reshape((-1,) + a16.shape[1:-1])[:b]


def rebin_to_parallel(sino, fan: fbp_mod.FanBeamGeometry, *, fan_angles=None, runtime=None) -> np.ndarray:
    """Parallel sinograms (B, V/2, n_s) float32 of fan sinograms (B, V, C) (OpenCL; step 1 of the module docstring)."""
    a = fbp_mod._check_sinograms(sino, fan, "sino")
    p = ParallelFBP(fan, fan_angles=fan_angles, runtime=runtime)
    try:
        group = fbp_mod.interleave_batch(a)
        buf = p.rt.to_device(group)
        d_par, ev = p.rebin(buf, group.shape[0])
        res = p.rt.from_device(d_par, (group.shape[0], p.par.n_angles, p.par.n_s, LANES), wait_for=[ev])
        buf.release()
        d_par.release()
    finally:
        p.release()
    return _ungroup(res, a.shape[0])


def backproject_parallel(filtered, par: ParallelGeometry, *, runtime=None) -> np.ndarray:
    """Parallel backprojection (B, ny, nx) float32 of filtered parallel sinograms (B, n_angles, n_s) (OpenCL)."""
    a = np.ascontiguousarray(filtered, dtype=np.float32)
    if a.ndim != 3 or a.shape[1:] != (par.n_angles, par.n_s):
        raise ValueError(f"filtered: expected shape (B, {par.n_angles}, {par.n_s}), got {a.shape}")
    rt = runtime or get_runtime()
    trig = rt.to_device(_trig_table(par))
    out = np.empty((a.shape[0], par.ny, par.nx), np.float32)
    step = 2 * LANES
    try:
        for b0 in range(0, a.shape[0], step):
            group = _groups(a[b0:b0 + step])
            buf = rt.to_device(group)
            res = _backproject_device(rt, par, trig, buf, group.shape[0])
            buf.release()
            out[b0:b0 + step] = res[:min(step, a.shape[0] - b0)]
    finally:
        trig.release()
    return out


def fbp_parallel(sino, fan: fbp_mod.FanBeamGeometry, window: str = "ram-lak", *, fan_angles=None,
                 runtime=None) -> np.ndarray:
    """mu images (B, ny, nx) float32 (1/mm) of fan sinograms (B, V, C) of line integrals, by rebinning.

    The counterpart of :func:`clrecon.reconstruction.fbp.fbp` (same inputs and output; 0 outside
    the FOV circle).
    """
    a = fbp_mod._check_sinograms(sino, fan, "sino")
    if not np.all(np.isfinite(a)):
        raise ValueError("sino: contains NaN or infinite values")
    p = ParallelFBP(fan, window, fan_angles=fan_angles, runtime=runtime)
    out = np.empty((a.shape[0], fan.ny, fan.nx), np.float32)
    step = 2 * LANES
    try:
        for b0 in range(0, a.shape[0], step):
            group = fbp_mod.interleave_batch(a[b0:b0 + step])
            buf = p.rt.to_device(group)
            res = p.images(buf, group.shape[0])
            buf.release()
            out[b0:b0 + step] = res[:min(step, a.shape[0] - b0)]
    finally:
        p.release()
    return out
