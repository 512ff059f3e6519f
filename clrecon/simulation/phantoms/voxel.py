"""4D voxel phantoms (``[phantom] kind = "voxel"``): XCAT or NIfTI frames, posed by blending frames.

The scene names a frame series (:mod:`clrecon.simulation.phantoms.frames`: XCAT attenuation
frames with their log, or a table of NIfTI volumes); every frame is the phantom at one
(cardiac phase c, respiratory amplitude a). The phantom at a projection's state is built from
the frames (``interpolation``; ``docs/voxel-phantoms.md`` "Between frames"):

- ``"nearest"``: the frame nearest in (c, a), distance ``sqrt(dc^2 + da^2)`` with the circular
  cardiac difference ``dc`` (ties: the lower frame index);
- ``"linear"``, frames on a (c, a) grid (every combination of the distinct phases and
  amplitudes exactly once): bilinear, circular in c between the two bracketing grid phases,
  linear in a between the bracketing amplitudes, constant beyond the first and last amplitude
  (no extrapolation); a single phase or amplitude drops that axis;
- ``"linear"``, any other set of frames (e.g. a 1-D trajectory in time): the two frames
  nearest in (c, a); the state is projected onto their segment (c of the second taken
  circularly closest to the first), ``t = clip(-(p1 - p).(p2 - p1) / |p2 - p1|^2, 0, 1)``,
  weights (1 - t, t) -- the two-nearest rule of the barycentric method.

Projection is linear in mu, so a blend of frames projects as the same blend of the frames'
projections: the source projects each needed frame once per chunk of views (Joseph's method,
:func:`clrecon.simulation.voxel_projector.project_volume`) and accumulates the weighted
projections; one frame is uploaded at a time and at most two are held in host memory.

Frame states (``timing``): ``"xcat"`` from the log's heart and breathing periods
(``c = (hrt_start_ph_index + t / hrt_period) mod 1``, ``a = (1 - cos 2 pi phi) / 2`` with
``phi = (resp_start_ph_index + t / resp_period) mod 1``, t = (k - 1) x time per frame);
``"table"`` the NIfTI table's columns; ``"scene"`` the scene's own signals at each frame's time
(``time_offset_s`` + the frame's time), the pose the analytic phantom would have at that time,
bound by :func:`clrecon.simulation.projector.phantom_for_scene`; ``"auto"`` = ``"xcat"`` for an
XCAT log with both periods, ``"table"`` for a table with phases, else ``"scene"``.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass
from typing import ClassVar

import numpy as np
from scipy import sparse

from clrecon.core.config import BOOL, F, Section, field_of, number_in, numbers_in, one_of, zero_or_in
from clrecon.core.conventions import MU_WATER_PER_MM, MU_WATER_RANGE_PER_MM, MU_WATER_WHY, circular_difference
from clrecon.core.errors import SceneError
from clrecon.simulation.phantoms import frames as fr
from clrecon.simulation.voxel_projector import project_volume

FORMATS = ("auto", "xcat", "nifti")
INTERPOLATIONS = ("nearest", "linear")
TIMINGS = ("auto", "xcat", "scene", "table")


@dataclass(frozen=True, kw_only=True)
class VoxelPhantomConfig(Section):
    """A 4D voxel phantom read from frames (``[phantom] kind = "voxel"``; docs/voxel-phantoms.md).

    ``frames`` is resolved against the scene file's folder when relative (``PATH_KEYS``).
    ``mu_water_per_mm = 0`` is replaced at construction by the frames' own water value (the
    XCAT log's ``Body (water)``) or 0.0193 /mm (NIfTI).
    """

    SECTION = "phantom"
    #: keys holding paths, resolved against the scene file's folder by the TOML loader
    PATH_KEYS: ClassVar[tuple] = ("frames",)

    kind: str = F("voxel", ("voxel", lambda x: x == "voxel"), "phantom source (registry PHANTOM_SOURCES)")
    frames: str = field_of("", "a path: an XCAT log, a NIfTI frames table (.toml/.csv) or a folder with one",
                           lambda x: isinstance(x, str) and x.strip() != "", "the frame series")
    format: str = F("auto", one_of(FORMATS), "frame format; auto: from the path (a *_log is XCAT)")
    interpolation: str = F("linear", one_of(INTERPOLATIONS), "the phantom between frames")
    timing: str = F("auto", one_of(TIMINGS), "where each frame's (cardiac phase, amplitude) comes from")
    time_offset_s: float = F(0.0, number_in(0.0, 86400.0, "s", "within a day"),
                             "timing = scene: the scene time of the first frame")
    values: str = F("hu", one_of(("hu", "mu")), "NIfTI voxel values: HU, or mu in 1/mm")
    mu_water_per_mm: float = F(0.0, zero_or_in(*MU_WATER_RANGE_PER_MM, "/mm", MU_WATER_WHY),
                               "attenuation of water (1/mm); 0: from the frames")
    byte_order: str = F("little", one_of(("little", "big")), "XCAT: byte order of the float32 frames")
    slice_direction: str = F("superior", one_of(("superior", "inferior")),
                             "XCAT: the direction in which slice numbers increase")
    centre_mm: tuple = F((0.0, 0.0, 0.0), numbers_in(3, -5000.0, 5000.0, "mm", "[x, y, z], a position in the "
                                                     "scanner; CT tables travel under 2 m"),
                         "XCAT: world position (LPS, mm) of the frames' centre")
    cardiac_motion: bool = F(True, BOOL, "the frames beat (false: posed at c = 0)")
    respiratory_motion: bool = F(True, BOOL, "the frames breathe (false: posed at a = 0.5)")

    def check(self) -> None:
        s = self.series()
        if self.mu_water_per_mm == 0.0:
            object.__setattr__(self, "mu_water_per_mm", float(s.mu_water_per_mm or MU_WATER_PER_MM))
        resolve_timing(self, s)

    def series(self) -> fr.FrameSeries:
        """The frame series (headers read and files checked; cached per file state)."""
        try:
            return fr.open_series(self.frames, self.format, byte_order=self.byte_order,
                                  slice_direction=self.slice_direction, centre_mm=self.centre_mm, values=self.values,
                                  mu_water_per_mm=self.mu_water_per_mm)
        except SceneError as e:
            msg = str(e)
            raise SceneError(msg if msg.startswith("phantom.") else f"phantom.frames: {msg}") from None

    def content_hash(self) -> str:
        """Fingerprint of the frame files (enters the projection store's content hash)."""
        return self.series().fingerprint()



def resolve_timing(cfg, series: fr.FrameSeries) -> str:
    """The timing a config means for a series (``"auto"`` resolved); SceneError when the
    series lacks what the timing needs."""
    t = cfg.timing
    where = f"phantom.timing = {t!r} ({series.header.name})"
    xl = series.xcat
    if t == "auto":
        if xl is not None:
            t = "xcat" if (xl.hrt_period_s and xl.resp_period_s and xl.time_per_frame_s) else "scene"
        else:
            t = "table" if series.cardiac is not None else "scene"
    if t == "xcat":
        if xl is None:
            raise SceneError(f"{where}: needs XCAT frames; NIfTI frames take 'table' or 'scene'")
        missing = [k for k, v in (("hrt_period", xl.hrt_period_s), ("resp_period", xl.resp_period_s),
                                  ("Time Per Frame", xl.time_per_frame_s)) if not v]
        if missing:
            raise SceneError(f"{where}: the log has no '{missing[0]} = ...' line; use timing = 'scene'")
    elif t == "table":
        if xl is not None:
            raise SceneError(f"{where}: needs a NIfTI frames table; XCAT frames take 'xcat' or 'scene'")
        if series.cardiac is None:
            raise SceneError(f"{where}: every row of the table needs cardiac_phase and resp_amplitude")
    elif t == "scene" and series.times_s is None:
        need = "a 'Time Per Frame = ...' line in the log" if xl is not None else "a time_s for every row"
        raise SceneError(f"{where}: needs {need}")
    return t


# ---------------------------------------------------------------------------------------
# frames -> weights
def is_grid(c, a) -> bool:
    """Whether the frame states (K,) are every combination of their distinct c and a exactly once."""
    cs, as_ = np.unique(c), np.unique(a)
    if len(cs) * len(as_) != len(c):
        return False
    pairs = set(zip(np.searchsorted(cs, c).tolist(), np.searchsorted(as_, a).tolist(), strict=True))
    return len(pairs) == len(c)


def _bracket_circular(grid, x):
    """Indices (i0, i1) into sorted circular ``grid`` and weight of i1, for values x (m,)."""
    n = len(grid)
    if n == 1:
        z = np.zeros(len(x), np.int64)
        return z, z, np.zeros(len(x))
    x = np.mod(x, 1.0)
    i1 = np.searchsorted(grid, x, side="right") % n
    i0 = (i1 - 1) % n
    span = np.mod(grid[i1] - grid[i0], 1.0)
    span = np.where(span == 0, 1.0, span)
    return i0, i1, np.mod(x - grid[i0], 1.0) / span


def _bracket_linear(grid, x):
    """Indices (i0, i1) into sorted ``grid`` and weight of i1, clamped at the ends."""
    n = len(grid)
    if n == 1:
        z = np.zeros(len(x), np.int64)
        return z, z, np.zeros(len(x))
    xc = np.clip(x, grid[0], grid[-1])
    i0 = np.clip(np.searchsorted(grid, xc, side="right") - 1, 0, n - 2)
    return i0, i0 + 1, (xc - grid[i0]) / (grid[i0 + 1] - grid[i0])


def frame_weights(fc, fa, c, a, interpolation: str):
    """Frames and weights for states (c, a): (index (m, J) int64, weight (m, J) float64), rows sum to 1.

    ``fc``, ``fa`` (K,) frame states; J = 1 (nearest), 2 (two-nearest) or 4 (grid). The
    rules are in the module docstring.
    """
    fc = np.asarray(fc, np.float64)
    fa = np.asarray(fa, np.float64)
    c = np.atleast_1d(np.asarray(c, np.float64))
    a = np.atleast_1d(np.asarray(a, np.float64))
    dc = circular_difference(fc[None, :], c[:, None])                  # (m, K) frame - state
    da = fa[None, :] - a[:, None]
    d2 = dc * dc + da * da
    if interpolation == "nearest" or len(fc) == 1:
        return np.argmin(d2, axis=1)[:, None], np.ones((len(c), 1))
    if is_grid(fc, fa):
        cs, as_ = np.unique(fc), np.unique(fa)
        lut = np.full((len(cs), len(as_)), -1, np.int64)
        lut[np.searchsorted(cs, fc), np.searchsorted(as_, fa)] = np.arange(len(fc))
        c0, c1, tc = _bracket_circular(cs, c)
        a0, a1, ta = _bracket_linear(as_, a)
        idx = np.stack([lut[c0, a0], lut[c1, a0], lut[c0, a1], lut[c1, a1]], 1)
        w = np.stack([(1 - tc) * (1 - ta), tc * (1 - ta), (1 - tc) * ta, tc * ta], 1)
        return idx, w
    order = np.argsort(d2, axis=1, kind="stable")[:, :2]
    r = np.arange(len(c))
    k1, k2 = order[:, 0], order[:, 1]
    p1 = np.stack([dc[r, k1], da[r, k1]], 1)                            # frame - state, circular
    p2 = p1 + np.stack([circular_difference(fc[k2], fc[k1]), fa[k2] - fa[k1]], 1)
    e = p2 - p1
    ee = np.einsum("ij,ij->i", e, e)
    with np.errstate(invalid="ignore", divide="ignore"):
        t = np.where(ee > 0, np.clip(-np.einsum("ij,ij->i", p1, e) / ee, 0.0, 1.0), 0.0)
    return np.stack([k1, k2], 1), np.stack([1.0 - t, t], 1)


def resample_matrix(x_out, h_out: float, origin: float, spacing: float, n_in: int, ss: int):
    """Sparse (n_out, n_in) operator: the mean of ``ss`` linear-interpolation samples per output voxel.

    Output voxel i (centre ``x_out[i]``, size ``h_out``) samples ``x_out[i] + ((j + 1/2)/ss - 1/2) h_out``,
    j < ss; a sample inside the input box (index in [-1/2, n_in - 1/2]) is interpolated
    linearly between input voxel centres (clamped to the edge voxels, as the projector does),
    outside it is 0.
    """
    x_out = np.asarray(x_out, np.float64)
    rows, cols, vals = [], [], []
    for j in range(ss):
        p = x_out + ((j + 0.5) / ss - 0.5) * h_out
        g = (p - origin) / spacing
        inside = (g >= -0.5) & (g <= n_in - 0.5)
        gc = np.clip(g, 0.0, n_in - 1)
        i0 = np.minimum(np.floor(gc).astype(np.int64), max(n_in - 2, 0))
        f = gc - i0
        i1 = np.minimum(i0 + 1, n_in - 1)
        r = np.arange(len(x_out))
        for idx, w in ((i0, 1.0 - f), (i1, f)):
            keep = inside & (w != 0)
            rows.append(r[keep])
            cols.append(idx[keep])
            vals.append(w[keep] / ss)
    m = sparse.coo_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                          shape=(len(x_out), n_in))
    return m.tocsr()


def _spacing(a) -> float:
    a = np.asarray(a, np.float64)
    return float(a[1] - a[0]) if a.size > 1 else 1.0


# ---------------------------------------------------------------------------------------
class VoxelPhantom:
    """A 4D voxel phantom: a frame series posed by blending frames (module docstring).

    Parameters
    ----------
    cfg : VoxelPhantomConfig

    Attributes
    ----------
    series : frames.FrameSeries (files, grid; :attr:`geometry`)
    timing : the resolved timing (``"xcat"``, ``"table"`` or ``"scene"``)
    needs_scene_states : True when the frame states come from the scene's signals; then
        :func:`clrecon.simulation.projector.phantom_for_scene` binds them (:meth:`with_states`).
    frame_times_s : (K,) frame times (s, scene clock: ``time_offset_s`` added) or None
    """

    #: what the projector dispatches on: this source projects itself (``project``)
    carries_projector = True

    def __init__(self, cfg: VoxelPhantomConfig):
        self.cfg = cfg
        self.series = cfg.series()
        self.geometry = self.series.geometry
        self.timing = resolve_timing(cfg, self.series)
        s = self.series
        self.frame_times_s = None if s.times_s is None else s.times_s + cfg.time_offset_s
        self.needs_scene_states = self.timing == "scene"
        self._c = self._a = None
        if self.timing == "table":
            self._c, self._a = s.cardiac.copy(), s.resp.copy()
        elif self.timing == "xcat":
            xl = s.xcat
            t = s.times_s
            self._c = np.mod(xl.hrt_start_phase + t / xl.hrt_period_s, 1.0)
            self._a = fr.xcat_amplitude(np.mod(xl.resp_start_phase + t / xl.resp_period_s, 1.0))

    def __repr__(self) -> str:
        g = self.geometry
        return f"VoxelPhantom({self.series.format}, {self.series.n_frames} frames of {g.shape}, {self.cfg.frames!r})"

    @property
    def n_frames(self) -> int:
        return self.series.n_frames

    @property
    def frame_states(self) -> tuple[np.ndarray, np.ndarray]:
        """(c (K,), a (K,)) of the frames."""
        if self._c is None:
            raise SceneError(f"phantom.timing = 'scene' ({self.series.header.name}): the frame states come from the "
                             f"scene's signals; build the source with projector.phantom_for_scene(scene)")
        return self._c, self._a

    def with_states(self, c, a) -> VoxelPhantom:
        """A copy whose frames are at the states ``c``, ``a`` (K,) each."""
        c = np.asarray(c, np.float64).reshape(-1)
        a = np.asarray(a, np.float64).reshape(-1)
        if c.shape != (self.n_frames,) or a.shape != c.shape:
            raise ValueError(f"need {self.n_frames} frame states, got shapes {c.shape}, {a.shape}")
        out = copy.copy(self)
        out._c, out._a = c.copy(), a.copy()
        out.needs_scene_states = False
        return out

    def weights(self, c, a):
        """Frames and blending weights for states (c, a) (m,): (index (m, J), weight (m, J))."""
        fc, fa = self.frame_states
        return frame_weights(fc, fa, c, a, self.cfg.interpolation)

    def frame(self, k: int) -> np.ndarray:
        """Frame k (0-based), mu (nz, ny, nx) float32 1/mm, read-only (held in the frame cache)."""
        return fr.load_frame(self.series, int(k))

    def volume(self, c: float, a: float) -> np.ndarray:
        """The phantom at one state on the frames' grid, mu (nz, ny, nx) float32 (the blend of frames)."""
        idx, w = self.weights([c], [a])
        out = np.zeros(self.geometry.shape, np.float32)
        for k, wk in zip(idx[0], w[0], strict=True):
            if wk > 0:
                out += np.float32(wk) * self.frame(k)
        return out

    # -- projection ------------------------------------------------------------------------
    def project(self, c, a, src, det_centre, e_u, e_v, u_mm, v_mm, rt=None, out=None, v_scale=None) -> np.ndarray:
        """Line integrals of the phantom posed at per-view states (c, a) (m,), (m, n_rows, n_cols) float32.

        Views are grouped by the frames they need; each frame is loaded (lazily, at most two in
        memory), uploaded and projected once for the views that use it, and its projection is
        added with the views' weights. Frames are visited in index order.
        """
        src = np.asarray(src, np.float64)
        m = len(src)
        shape = (m, len(v_mm), len(u_mm))
        if out is None:
            out = np.zeros(shape, np.float32)
        else:
            if out.shape != shape or out.dtype != np.float32:
                raise ValueError(f"out must be a float32 array of shape {shape}")
            out[...] = 0.0
        if m == 0:
            return out
        idx, w = self.weights(c, a)
        g = self.geometry
        det, eu, ev = (np.asarray(x, np.float64) for x in (det_centre, e_u, e_v))
        live = w > 0
        for k in np.unique(idx[live]):
            sel = live & (idx == k)
            views = np.flatnonzero(sel.any(axis=1))
            wk = (w * sel).sum(axis=1)[views].astype(np.float32)
            p = project_volume(self.frame(k), g.origin_mm, g.spacing_mm, src[views], det[views], eu[views], ev[views],
                               u_mm, v_mm, rt=rt, v_scale=v_scale)
            if len(views) == m and np.all(wk == 1.0):
                out += p
            else:
                out[views] += wk[:, None, None] * p
        return out

    # -- truth -----------------------------------------------------------------------------
    def voxelise(self, c: float, a: float, x_mm, y_mm, z_mm, supersample: int = 2, rt=None) -> np.ndarray:
        """The phantom at (c, a) resampled to a grid of voxel centres, mu (nz, ny, nx) float32 (1/mm).

        Each output voxel is the mean of ``supersample**3`` trilinear samples of the blended
        frames on a regular sub-grid of the voxel (a single-value axis counts as 1 mm);
        0 (air) outside the frames' box. Separable: one sparse operator per axis
        (:func:`resample_matrix`). ``rt`` is unused (host NumPy/SciPy).
        """
        if int(supersample) != supersample or supersample < 1:
            raise ValueError(f"supersample must be an integer >= 1, got {supersample!r}")
        x, y, z = (np.atleast_1d(np.asarray(v, np.float64)) for v in (x_mm, y_mm, z_mm))
        g = self.geometry
        nz, ny, nx = g.shape
        mx = resample_matrix(x, _spacing(x), g.origin_mm[0], g.spacing_mm[0], nx, supersample)
        my = resample_matrix(y, _spacing(y), g.origin_mm[1], g.spacing_mm[1], ny, supersample)
        mz = resample_matrix(z, _spacing(z), g.origin_mm[2], g.spacing_mm[2], nz, supersample)
        used = np.unique(mz.indices)
        mz_used = mz[:, used]
        idx, w = self.weights([c], [a])
        out = np.zeros((len(z), len(y), len(x)))
        for k, wk in zip(idx[0], w[0], strict=True):
            if wk <= 0 or not len(used):
                continue
            vol = self.frame(k)[used].astype(np.float64)                    # only the slices the grid needs
            t = mz_used @ vol.reshape(len(used), -1)                        # (nz_o, ny * nx)
            t = t.reshape(len(z), ny, nx).transpose(1, 0, 2).reshape(ny, -1)
            t = (my @ t).reshape(len(y), len(z), nx).transpose(1, 0, 2)     # (nz_o, ny_o, nx)
            t = (mx @ t.reshape(-1, nx).T).T.reshape(len(z), len(y), len(x))
            out += wk * t
        return out.astype(np.float32)


__all__ = ["VoxelPhantom", "VoxelPhantomConfig", "frame_weights", "is_grid", "resample_matrix", "resolve_timing"]
