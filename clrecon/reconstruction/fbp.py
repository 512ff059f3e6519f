"""Fan-beam filtered backprojection for a flat detector, batched (the pipeline's FBP stage).

Takes a batch of in-plane fan-beam sinograms (line integrals of mu, dimensionless) that all
share one geometry -- every slice and every phase-space target of a reconstruction, after
SSRB and phase-space interpolation -- and returns mu images (1/mm) or HU.

Method: Kak & Slaney (1988), "Principles of Computerized Tomographic Imaging", sec. 3.4.2
(fan beam, equally spaced collinear detectors), full 2 pi scan:

1. cosine pre-weight  R'_j(u) = R_j(u) * SDD / sqrt(SDD^2 + u^2);
2. convolve each row with g = h / 2, h the discrete band-limited ramp kernel of K&S
   ch. 3 eq. (61) sampled at the column pitch *at the isocentre* tau = col_pitch*SID/SDD
   (``h(0) = 1/(4 tau^2)``, ``h(n odd) = -1/(n pi tau)^2``, ``h(n even) = 0``), optionally
   windowed (Shepp-Logan, Hann), by zero-padded FFT (length >= 2C - 1, so the circular
   convolution is the linear one for every output column);
3. backproject with the distance weight (SID/U)^2 and linear interpolation in u, times
   dbeta = 2 pi / V (kernel ``kernels/backproject.cl``).

Sampling the ramp kernel in space (rather than taking a naive ``|w|`` in frequency) keeps
its DC term right, so a uniform object has no offset (K&S ch. 3, discussion of eq. 61).

A cylindrical detector (``detector = "cylindrical"``) gives equiangular data (K&S sec. 3.4.1):
pre-weight D cos(gamma) (here cos(gamma) / SID: the 1 / D^2 of the backprojection weight is
folded in), kernel g(gamma) = 1/2 (gamma / sin gamma)^2 h(gamma) with h the same band-limited ramp
sampled at the angular pitch dgamma = col_pitch / SDD (so g(0) = 1/(8 dgamma^2),
g(n odd) = -1/(2 pi^2 sin^2(n dgamma))), times dgamma, and backprojection weight SID^2 / L^2
(L the distance from the source) at column atan(V/U) / dgamma + central_col
(``kernels/backproject.cl``, variant ``CURVED``). With a flying focal spot each view's source is
its focal spot (``source_shifts``): the trig table holds its angle and radius.

Conventions (``clrecon.core.conventions``): view j at beta_j = beta0 + 2 pi j / V, source at
(R cos b, R sin b), column j at u_j = (j - (C-1)/2) * col_pitch along (-sin b, cos b).
Images are ``img[y, x]`` with voxel centres from :func:`clrecon.core.conventions.voxel_coords`.
Pixels outside the scanner's FOV circle (radius :attr:`FanBeamGeometry.fov_radius_mm`: the
circle inside every view's fan; rays outside it are missing from some views) are set to 0.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.fft

from clrecon.core.conventions import MU_WATER_PER_MM, detector_coords, mu_to_hu, voxel_coords
from clrecon.core.detector import atan_defines, flat_fov_radius_mm
from clrecon.core.runtime import aligned_empty, get_runtime
from clrecon.reconstruction.filters import FILTERS as _WINDOW_FUNCTIONS
from clrecon.reconstruction.interpolation.apply import DeviceRows, apply_padded_interleaved, pad_interleaved

#: Ramp-filter windows, as in ``ReconConfig.filter`` (registry: :mod:`clrecon.reconstruction.filters`).
WINDOWS = _WINDOW_FUNCTIONS.names

#: Sinograms per batched-kernel work-item: the float16 vector width of the kernel.
BATCH_LANES = 16

#: Fixed local size (x, y) of both backprojection kernels (PoCL specialises per local size).
LOCAL_SIZE = (8, 8)

#: Views per barrier-separated chunk in the batched kernel (keeps a tile's rows in L1;
#: 8..32 measured within noise of each other on this machine, 4 was 2x slower).
VIEW_CHUNK = 16

_KERNEL_FILE = "backproject.cl"


@dataclass(frozen=True, kw_only=True)
class FanBeamGeometry:
    """In-plane fan-beam geometry of a full 2 pi scan on a flat detector, and the image grid.

    Parameters
    ----------
    sid_mm, sdd_mm : float
        Source-to-isocentre and source-to-detector distances (mm), ``sdd_mm > sid_mm``.
    n_cols : int
        Detector columns C (>= 2).
    col_pitch_mm : float
        Column pitch at the detector (mm).
    n_views : int
        Views V over 2 pi; view j is at ``beta0_rad + 2 pi j / V``.
    nx, ny : int
        Image size; images are ``img[y, x]``.
    voxel_mm : float
        Pixel size (mm); pixel centres are ``voxel_coords(n, voxel_mm)``.
    beta0_rad : float
        Gantry angle of view 0 (rad).
    detector : str
        ``"flat"`` (equispaced columns) or ``"cylindrical"`` (equiangular columns,
        :class:`clrecon.core.detector.CylindricalDetector`).
    central_col : float
        Cylindrical: 0-based fractional column of the central ray; -1: the middle.
    source_shifts : tuple
        Cylindrical with a flying focal spot: the cycle of per-view source shifts
        ``((dphi rad, drho mm), ...)``; view j uses entry ``j % len``; empty: none. The rows
        must then be on each spot's own equiangular fan (what SSRB gives).
    """

    sid_mm: float
    sdd_mm: float
    n_cols: int
    col_pitch_mm: float
    n_views: int
    nx: int
    ny: int
    voxel_mm: float
    beta0_rad: float = 0.0
    detector: str = "flat"
    central_col: float = -1.0
    source_shifts: tuple = ()

    def __post_init__(self):
        for name in ("sid_mm", "sdd_mm", "col_pitch_mm", "voxel_mm"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and v > 0):
                raise ValueError(f"{name} = {v!r}: must be a finite number > 0")
        for name, lo in (("n_cols", 2), ("n_views", 1), ("nx", 1), ("ny", 1)):
            v = getattr(self, name)
            if not (isinstance(v, (int, np.integer)) and not isinstance(v, bool) and v >= lo):
                raise ValueError(f"{name} = {v!r}: must be an integer >= {lo}")
        if not (isinstance(self.beta0_rad, (int, float)) and math.isfinite(self.beta0_rad)):
            raise ValueError(f"beta0_rad = {self.beta0_rad!r}: must be a finite number")
        if self.sdd_mm <= self.sid_mm:
            raise ValueError(f"sdd_mm = {self.sdd_mm!r}: must be greater than sid_mm = {self.sid_mm!r}")
        if self.detector not in ("flat", "cylindrical"):
            raise ValueError(f"detector = {self.detector!r}: must be one of flat, cylindrical")
        if self.detector == "flat" and (self.central_col != -1.0 or self.source_shifts):
            raise ValueError("central_col and source_shifts need detector = 'cylindrical'")
        if self.detector == "cylindrical":
            if self.central_col != -1.0 and not 0.0 <= self.central_col <= self.n_cols - 1:
                raise ValueError(f"central_col = {self.central_col!r}: must be -1 or in [0, {self.n_cols - 1}]")
            lo, hi = self.edge_gamma_rad()
            if min(-lo, hi) > 0.25 * math.pi or min(-lo, hi) <= 0:
                raise ValueError(f"the fan's shorter half ({math.degrees(min(-lo, hi)):.1f} deg) must be in "
                                 f"(0, 45] degrees")

    @classmethod
    def from_scene(cls, scene) -> FanBeamGeometry:
        """Geometry of a :class:`clrecon.config.scene.Scene`: its scanner, recon grid and start angle."""
        sc, rc = scene.scanner, scene.recon
        extra = {}
        if sc.detector != "flat":
            extra = {"detector": sc.detector, "central_col": sc.detector_model.central_col}
            if sc.flying_focal_spot != "none":
                states = [(float(a), float(r)) for a, r, _ in sc.ffs_shifts]
                # view j holds projections k = sign * j (mod N): with a gantry turning the other way
                # (scan.rotation = "decreasing") view j's focal-spot state is state (-j) mod cycle
                sign = getattr(scene.scan, "rotation_sign", 1)
                extra["source_shifts"] = tuple(states[(sign * j) % len(states)] for j in range(len(states)))
        return cls(sid_mm=sc.sid_mm, sdd_mm=sc.sdd_mm, n_cols=sc.n_cols, col_pitch_mm=sc.col_pitch_mm,
                   n_views=sc.views_per_rotation, nx=rc.nx, ny=rc.ny, voxel_mm=rc.voxel_mm,
                   beta0_rad=math.radians(scene.scan.start_angle_deg), **extra)

    # -- derived quantities -------------------------------------------------------------
    @property
    def curved(self) -> bool:
        return self.detector == "cylindrical"

    @property
    def centre_col(self) -> float:
        """0-based fractional column of the central ray."""
        return 0.5 * (self.n_cols - 1) if self.central_col == -1.0 else float(self.central_col)

    @property
    def delta_gamma_rad(self) -> float:
        """Cylindrical: angle between columns, col_pitch / SDD (rad)."""
        return self.col_pitch_mm / self.sdd_mm

    def edge_gamma_rad(self) -> tuple[float, float]:
        """Cylindrical: fan angles of the outer column edges (rad), (lowest, highest)."""
        c = self.centre_col
        return (-0.5 - c) * self.delta_gamma_rad, (self.n_cols - 0.5 - c) * self.delta_gamma_rad

    @property
    def fov_radius_mm(self) -> float:
        """Radius at the isocentre of the circle every column edge sees (mm).

        The flat detector's formula, :func:`clrecon.core.detector.flat_fov_radius_mm`; the
        cylindrical one's SID sin(min |gamma_edge|) (the shorter side of an off-centre fan), less
        the largest radial focal-spot shift's effect (none without a flying focal spot).
        """
        if not self.curved:
            return flat_fov_radius_mm(self.sid_mm, self.sdd_mm, self.n_cols * self.col_pitch_mm / 2.0)
        lo, hi = self.edge_gamma_rad()
        g = min(-lo, hi)
        if not self.source_shifts:
            return self.sid_mm * math.sin(g)
        # the spot's fan is the arc's seen from the spot: keep the circle every spot's fan covers
        # (d: the spot's in-plane offset from the focal centre, as CylindricalDetector.spot_inplane_mm)
        d = max(math.hypot(self.sid_mm - (self.sid_mm + r) * math.cos(a), (self.sid_mm + r) * math.sin(a))
                for a, r in self.source_shifts)
        return (self.sid_mm - d) * math.sin(g) - d

    @property
    def delta_beta_rad(self) -> float:
        """Angular step between views, 2 pi / V (rad)."""
        return 2.0 * math.pi / self.n_views

    @property
    def iso_col_pitch_mm(self) -> float:
        """Column pitch projected to the isocentre, tau = col_pitch * SID / SDD (mm)."""
        return self.col_pitch_mm * self.sid_mm / self.sdd_mm

    def view_angles_rad(self) -> np.ndarray:
        """Gantry angles beta_j (rad), shape (V,)."""
        return self.beta0_rad + self.delta_beta_rad * np.arange(self.n_views, dtype=np.float64)

    def source_angles_radii(self) -> tuple[np.ndarray, np.ndarray]:
        """Each view's source angle (rad) and radius (mm), (V,) each: the gantry angle and SID,
        shifted by the flying focal spot's cycle where there is one."""
        b = self.view_angles_rad()
        r = np.full(self.n_views, float(self.sid_mm))
        if self.source_shifts:
            sh = np.asarray(self.source_shifts, np.float64)[np.arange(self.n_views) % len(self.source_shifts)]
            b, r = b + sh[:, 0], r + sh[:, 1]
        return b, r

    def col_coords_mm(self) -> np.ndarray:
        """Column centres u_j at the detector (mm), shape (C,): flat, or the arc coordinate SDD gamma."""
        if self.curved:
            return (np.arange(self.n_cols) - self.centre_col) * self.col_pitch_mm
        return detector_coords(self.n_cols, self.col_pitch_mm)

    def col_gamma_rad(self) -> np.ndarray:
        """Fan angle of each column (rad), (C,): atan(u / SDD) flat, (c - central_col) dgamma cylindrical."""
        if self.curved:
            return (np.arange(self.n_cols) - self.centre_col) * self.delta_gamma_rad
        return np.arctan(self.col_coords_mm() / self.sdd_mm)

    def pixel_coords_mm(self) -> tuple[np.ndarray, np.ndarray]:
        """Pixel-centre coordinates ``(x (nx,), y (ny,))`` in mm."""
        return voxel_coords(self.nx, self.voxel_mm), voxel_coords(self.ny, self.voxel_mm)

    def fov_mask(self) -> np.ndarray:
        """Boolean (ny, nx): pixel centre inside the FOV circle (the pixels FBP fills)."""
        x, y = self.pixel_coords_mm()
        return x[None, :] ** 2 + y[:, None] ** 2 <= self.fov_radius_mm ** 2


# ---------------------------------------------------------------------------------------
# filtering (host, NumPy/SciPy: cheap next to backprojection)
def _check_sinograms(sino, geom: FanBeamGeometry, name: str) -> np.ndarray:
    a = np.asarray(sino)
    if a.dtype.kind not in "fiu":
        raise TypeError(f"{name}: expected a real numeric array, got dtype {a.dtype}")
    if a.ndim != 3 or a.shape[1:] != (geom.n_views, geom.n_cols):
        raise ValueError(f"{name}: expected shape (B, {geom.n_views}, {geom.n_cols}) = (batch, views, columns), "
                         f"got {a.shape}" + ("; add a batch axis with sino[None]" if a.ndim == 2 else ""))
    return np.ascontiguousarray(a, dtype=np.float32)


def padded_length(n_cols: int) -> int:
    """FFT length for filtering C columns: a fast length >= 2C - 1 (no circular wrap-around)."""
    return scipy.fft.next_fast_len(2 * n_cols - 1, real=False)


def ramp_filter_response(geom: FanBeamGeometry, window: str = "ram-lak", n_pad: int | None = None) -> np.ndarray:
    """Frequency response of the fan-beam filter g = h/2, shape (n_pad,) float64, in 1/mm.

    ``h`` is the band-limited ramp kernel of Kak & Slaney eq. (61) sampled at the
    isocentre column pitch tau, its FFT multiplied by tau (the ``ds`` of the convolution
    integral) and by the window: Ram-Lak 1, Shepp-Logan ``sinc(f)``, Hann
    ``(1 + cos 2 pi f) / 2``, with ``f`` in cycles per sample (Nyquist 0.5). The kernel is
    real and even, so its transform is real.
    """
    if window not in WINDOWS:
        raise ValueError(f"window = {window!r}: must be one of {', '.join(WINDOWS)}")
    n_pad = padded_length(geom.n_cols) if n_pad is None else int(n_pad)
    if n_pad < 2 * geom.n_cols - 1:
        raise ValueError(f"n_pad = {n_pad}: must be >= 2 * n_cols - 1 = {2 * geom.n_cols - 1}")
    k = np.arange(n_pad)
    n = np.where(k <= n_pad // 2, k, k - n_pad).astype(np.float64)  # signed tap offsets
    if geom.curved:
        # equiangular (K&S sec. 3.4.1): g(n a) = 1/2 (n a / sin n a)^2 h(n a), h the ramp at pitch a
        a = geom.delta_gamma_rad
        if (n_pad // 2) * a >= math.pi:
            raise ValueError(f"n_pad = {n_pad}: the kernel's taps must stay below pi in fan angle")
        g = np.zeros(n_pad)
        g[0] = 1.0 / (8.0 * a * a)
        odd = (n.astype(np.int64) % 2) != 0
        g[odd] = -0.5 / (np.pi * np.sin(n[odd] * a)) ** 2
        response = scipy.fft.fft(g).real * a
        return response * _WINDOW_FUNCTIONS[window](scipy.fft.fftfreq(n_pad))
    tau = geom.iso_col_pitch_mm
    h = np.zeros(n_pad)
    h[0] = 1.0 / (4.0 * tau * tau)
    odd = (n.astype(np.int64) % 2) != 0
    h[odd] = -1.0 / (np.pi * n[odd] * tau) ** 2
    response = scipy.fft.fft(h).real * tau
    f = scipy.fft.fftfreq(n_pad)
    response *= _WINDOW_FUNCTIONS[window](f)  # clrecon.reconstruction.filters
    return 0.5 * response  # g = h / 2 for the full 2 pi fan-beam scan (K&S sec. 3.4.2)


def cosine_weights(geom: FanBeamGeometry) -> np.ndarray:
    """Fan-beam pre-weight per column, shape (C,) float64.

    Flat: SDD / sqrt(SDD^2 + u^2). Cylindrical: cos(gamma) / SID, K&S's D cos(gamma) times the
    1 / D^2 that turns the kernel's weight SID^2 / L^2 into 1 / L^2 (with a flying focal spot the
    nominal SID: the spot radii differ from it by |drho| / SID, 1.7e-3 at 1 mm, alternating in
    sign from view to view).
    """
    if geom.curved:
        return np.cos(geom.col_gamma_rad()) / geom.sid_mm
    u = geom.col_coords_mm()
    return geom.sdd_mm / np.sqrt(geom.sdd_mm ** 2 + u ** 2)


def filter_sinograms(sino, geom: FanBeamGeometry, window: str = "ram-lak", *, rows_per_chunk: int = 2048,
                     workers: int | None = None) -> np.ndarray:
    """Cosine-weight and ramp-filter fan-beam sinograms.

    Parameters
    ----------
    sino : array_like, shape (B, V, C)
        Line integrals of mu (dimensionless), view-major, column fastest.
    geom : FanBeamGeometry
    window : str
        One of :data:`WINDOWS` (:mod:`clrecon.reconstruction.filters`).
    rows_per_chunk : int
        Detector rows filtered per FFT call (bounds the padded work array, ~8 kB a row).
    workers : int, optional
        Threads for ``scipy.fft`` (default: one).

    Returns
    -------
    ndarray, shape (B, V, C), float32
        Filtered projections Q in 1/mm, ready for :func:`backproject`.

    Notes
    -----
    Each row is filtered alone (a real FFT of the zero-padded row, times the real, even
    response, inverse real FFT), so a row's result does not depend on the rows filtered with
    it: the reconstruction gives the same bits whatever its slab size or worker count.
    (Two rows in one complex FFT, ``a + i b``, would make a row's last bits depend on its
    partner: docs/results/code-history.md "Ramp filter: one row per FFT".)
    """
    a = _check_sinograms(sino, geom, "sino")
    return filter_rows(a.reshape(-1, geom.n_cols), geom, window, rows_per_chunk=rows_per_chunk,
                       workers=workers).reshape(a.shape)


def filter_rows(rows, geom: FanBeamGeometry, window: str = "ram-lak", *, out: np.ndarray | None = None,
                rows_per_chunk: int = 2048, workers: int | None = None) -> np.ndarray:
    """:func:`filter_sinograms` of detector rows (R, C) of any views: the filter acts per row.

    Cosine weighting and ramp filtering are linear and act on each row alone, so they
    commute with any weighted sum of rows of the same view: :mod:`clrecon.reconstruction.reconstruct`
    filters the rebinned rows once and interpolates filtered rows for every method.
    ``out`` may be ``rows`` itself (float32, C-contiguous): filtered in place.
    """
    a = np.asarray(rows)
    if a.ndim != 2 or a.shape[1] != geom.n_cols:
        raise ValueError(f"rows: expected shape (R, {geom.n_cols}), got {a.shape}")
    a = np.ascontiguousarray(a, dtype=np.float32)
    n_pad = padded_length(geom.n_cols)
    response = ramp_filter_response(geom, window, n_pad).astype(np.float32)
    weights = cosine_weights(geom).astype(np.float32)
    if not np.all(np.isfinite(a)):
        raise ValueError("sino: contains NaN or infinite values (photon starvation must be handled "
                         "before FBP, e.g. by clipping counts before the log)")
    c = geom.n_cols
    rows = a
    if out is None:
        out = np.empty_like(rows)
    elif out.shape != rows.shape or out.dtype != np.float32 or not out.flags.c_contiguous:
        raise ValueError(f"out: expected a C-contiguous float32 array of shape {rows.shape}")
    chunk = max(1, int(rows_per_chunk))
    half = response[:n_pad // 2 + 1]  # the response is real and even: its rfft half
    # Columns c.. stay zero for the whole loop (the zero padding): only the first c are written.
    work = np.zeros((chunk, n_pad), np.float32)
    for r0 in range(0, rows.shape[0], chunk):
        block = rows[r0:r0 + chunk]
        m = block.shape[0]
        w = work[:m]
        np.multiply(block, weights, out=w[:, :c])
        spec = scipy.fft.rfft(w, axis=1, workers=workers)
        spec *= half
        out[r0:r0 + m] = scipy.fft.irfft(spec, n=n_pad, axis=1, overwrite_x=True, workers=workers)[:, :c]
    return out


# ---------------------------------------------------------------------------------------
# backprojection (OpenCL)
def _trig_table(geom: FanBeamGeometry) -> np.ndarray:
    """Per-view (cos b / R, sin b / R), shape (V, 2) float32, computed in float64: b, R the
    view's source angle and radius (gantry angle and SID without a flying focal spot)."""
    if geom.source_shifts:
        b, r = geom.source_angles_radii()
        return (np.stack([np.cos(b), np.sin(b)], axis=1) / r[:, None]).astype(np.float32)
    b = geom.view_angles_rad()
    return (np.stack([np.cos(b), np.sin(b)], axis=1) / geom.sid_mm).astype(np.float32)


def view_table(geom: FanBeamGeometry) -> np.ndarray:
    """The backprojection kernels' per-view table (V, 2) float32: (cos b / R, sin b / R) of each
    view's source angle b and radius R (``kernels/fan_column.h``)."""
    return _trig_table(geom)


def _geometry_args(geom: FanBeamGeometry) -> tuple:
    """Scalar kernel arguments in the order of GEOMETRY_ARGS in backproject.cl."""
    if geom.curved:
        return (np.int32(geom.nx), np.int32(geom.ny), np.int32(geom.n_views), np.int32(geom.n_cols),
                np.float32(geom.voxel_mm), np.float32(1.0 / geom.delta_gamma_rad),
                np.float32(geom.fov_radius_mm ** 2), np.float32(geom.delta_beta_rad), np.float32(geom.centre_col))
    return (np.int32(geom.nx), np.int32(geom.ny), np.int32(geom.n_views), np.int32(geom.n_cols),
            np.float32(geom.voxel_mm), np.float32(geom.sdd_mm / geom.col_pitch_mm),
            np.float32(geom.fov_radius_mm ** 2), np.float32(geom.delta_beta_rad))


def _atan_t_max(geom: FanBeamGeometry) -> float:
    """The largest |tan gamma| of a pixel inside the FOV (a little margin), <= 1."""
    r = geom.fov_radius_mm
    rmin = geom.sid_mm - max((abs(s[1]) for s in geom.source_shifts), default=0.0)
    return min(1.0, round(1.02 * math.tan(math.asin(min(1.0, r / rmin))), 6))


def _defines(geom: FanBeamGeometry | None = None) -> dict:
    d = {"LX": LOCAL_SIZE[0], "LY": LOCAL_SIZE[1], "VCHUNK": VIEW_CHUNK}
    if geom is not None and geom.curved:
        d["CURVED"] = 1
        d.update(atan_defines(_atan_t_max(geom), 1.0 / geom.delta_gamma_rad))  # the polynomial gives atan / dgamma
    return d


def _global_size(geom: FanBeamGeometry, depth: int) -> tuple:
    lx, ly = LOCAL_SIZE
    return (-(-geom.nx // lx) * lx, -(-geom.ny // ly) * ly, depth)


def interleave_batch(filtered: np.ndarray) -> np.ndarray:
    """(B, V, C) -> (G, V, C + 2, 16) float32, the batched kernel's layout.

    Sinograms are zero-padded to G = ceil(B / 16) groups of 16 and interleaved batch-
    fastest; each row gets one replica of its edge column on either side, so that the
    kernel reads both taps of any pixel inside the FOV without a clamp (same values as
    clamping the column index to [0, C - 1]).
    """
    b, v, c = filtered.shape
    groups = -(-b // BATCH_LANES)
    out = np.zeros((groups, v, c + 2, BATCH_LANES), np.float32)
    full = b // BATCH_LANES
    if full:
        out[:full, :, 1:c + 1, :] = filtered[:full * BATCH_LANES].reshape(full, BATCH_LANES, v, c).transpose(0, 2, 3, 1)
    if b > full * BATCH_LANES:
        out[full, :, 1:c + 1, :b - full * BATCH_LANES] = np.moveaxis(filtered[full * BATCH_LANES:], 0, -1)
    out[:, :, 0] = out[:, :, 1]
    out[:, :, c + 1] = out[:, :, c]
    return out


#: Groups of 16 sinograms per backprojection launch: one pair, which the kernel backprojects
#: together. Measured on the 2-core machine (same load, alternating): 2 groups per launch
#: 10.7 G updates/s at 128^2 (8.3 with 8, 6.6 with 45 groups: the larger interleaved buffer
#: falls out of cache between being written and being read) and 10.0 at 512^2 (8.7 with 4).
LAUNCH_GROUPS = 2
#: Upper bound on the interleaved sinograms of one launch (bytes); binds only for huge rows.
LAUNCH_BYTES = 256 << 20


def groups_per_launch(geom: FanBeamGeometry) -> int:
    """Groups of 16 sinograms per backprojection launch: :data:`LAUNCH_GROUPS`, within :data:`LAUNCH_BYTES`."""
    per_group = geom.n_views * (geom.n_cols + 2) * BATCH_LANES * 4
    return max(1, min(LAUNCH_GROUPS, int(LAUNCH_BYTES // per_group)))


def backproject_interleaved(sino16, n_groups: int, geom: FanBeamGeometry, *, runtime=None,
                            wait_for=None, out_buf=None, out=None) -> np.ndarray:
    """Backproject ``n_groups`` groups already on the device in :func:`interleave_batch`'s layout.

    ``sino16`` is a device buffer of (n_groups, V, C + 2, 16) float32 (e.g. written by
    :func:`clrecon.reconstruction.interpolation.weights.apply_weights_interleaved`); returns (16 n_groups, ny, nx)
    float32 as :func:`backproject`.

    ``out_buf`` (a device buffer of at least 16 n_groups ny nx floats) and ``out`` (a C-contiguous
    float32 host array of at least 16 n_groups images of (ny, nx)): scratch the caller keeps
    from launch to launch instead of fresh memory each time (first touches cost about 0.7 ms
    per MB on the 2-core machine); the result is then ``out[:16 n_groups]``.
    """
    rt = runtime or get_runtime()
    kern = rt.kernel(_KERNEL_FILE, "backproject_batched16x2", _fast=True, **_defines(geom))
    trig = rt.to_device(_trig_table(geom))
    shape = (n_groups * BATCH_LANES, geom.ny, geom.nx)
    nbytes = int(np.prod(shape)) * 4
    if out_buf is not None and out_buf.size < nbytes:
        raise ValueError(f"out_buf: a buffer of {out_buf.size} bytes, the launch writes {nbytes}")
    d_out = rt.empty(shape) if out_buf is None else out_buf
    ev = kern(rt.queue, _global_size(geom, -(-n_groups // 2)), LOCAL_SIZE + (1,), sino16, trig, d_out,
              *_geometry_args(geom), np.int32(n_groups), wait_for=wait_for)
    if out is None:
        res = rt.from_device(d_out, shape, wait_for=[ev])
    else:
        fits = out.dtype == np.float32 and out.shape[1:] == shape[1:] and out.shape[0] >= shape[0]
        if not (fits and out.flags.c_contiguous):
            raise ValueError(f"out: expected a C-contiguous float32 array of >= {shape[0]} images of "
                             f"{shape[1:]}, got {out.dtype} {out.shape}")
        res = out[:shape[0]]
        rt.cl.enqueue_copy(rt.queue, res, d_out, wait_for=[ev])
    if out_buf is None:
        d_out.release()
    trig.release()
    return res


def backproject(filtered, geom: FanBeamGeometry, *, runtime=None) -> np.ndarray:
    """Distance-weighted fan-beam backprojection of filtered projections (OpenCL, batched).

    Parameters
    ----------
    filtered : array_like, shape (B, V, C)
        Filtered projections Q (1/mm), e.g. from :func:`filter_sinograms`.
    geom : FanBeamGeometry
    runtime : clrecon.core.runtime.Runtime, optional
        Defaults to :func:`clrecon.core.runtime.get_runtime`.

    Returns
    -------
    ndarray, shape (B, ny, nx), float32
        ``dbeta * sum_j (SID/U_j)^2 Q_j(u_j)`` (1/mm when Q is filtered line integrals);
        0 outside the FOV circle.

    Notes
    -----
    Sinograms go to the device in groups of 16, interleaved as [view][column][batch] so
    that each interpolation tap is one float16 load (:func:`interleave_batch`); a batch
    that is not a multiple of 16 is zero-padded. One kernel launch takes
    :func:`groups_per_launch` groups (two: the kernel does them together).
    """
    a = _check_sinograms(filtered, geom, "filtered")
    rt = runtime or get_runtime()
    b = a.shape[0]
    out = np.empty((b, geom.ny, geom.nx), np.float32)
    step = groups_per_launch(geom) * BATCH_LANES
    for b0 in range(0, b, step):
        group = interleave_batch(a[b0:b0 + step])
        sino_buf = rt.to_device(group)
        res = backproject_interleaved(sino_buf, group.shape[0], geom, runtime=rt)
        n = min(step, b - b0)
        out[b0:b0 + n] = res[:n]
        sino_buf.release()
    return out


# ---------------------------------------------------------------------------------------
def fbp(sino, geom: FanBeamGeometry, window: str = "ram-lak", *, runtime=None) -> np.ndarray:
    """Fan-beam FBP of line-integral sinograms.

    Parameters
    ----------
    sino : array_like, shape (B, V, C)
        Line integrals of mu (dimensionless) of a full 2 pi scan, e.g. SSRB-rebinned rows.
    geom : FanBeamGeometry
    window : str
        One of :data:`WINDOWS` (:mod:`clrecon.reconstruction.filters`).
    runtime : clrecon.core.runtime.Runtime, optional

    Returns
    -------
    ndarray, shape (B, ny, nx), float32
        mu in 1/mm, ``img[y, x]``; 0 outside the FOV circle.

    Notes
    -----
    Works through the batch one backprojection launch at a time (:func:`groups_per_launch`
    groups of 16): the launch's rows are filtered into one page-aligned host array that a CPU
    device reads in place, put into the backprojector's interleaved layout on the device (the
    interpolation kernel with one slot of weight 1 per view:
    :func:`clrecon.reconstruction.interpolation.apply.apply_padded_interleaved`), and
    backprojected into kept device and host buffers; the host memory beyond input and output
    stays at a few times V*C*128 bytes. The images are those of :func:`backproject` of
    :func:`filter_sinograms`, bit for bit (``0 + 1 * q`` is ``q``; a -0 becomes +0, which adds
    nothing different to a sum that starts at +0), without the host's interleaving copy and
    upload (the ground truth's FBP, 5 500 images at paper-p010: docs/fbp.md, "Fan-beam FBP").
    """
    if window not in WINDOWS:
        raise ValueError(f"window = {window!r}: must be one of {', '.join(WINDOWS)}")
    a = _check_sinograms(sino, geom, "sino")
    rt = runtime or get_runtime()
    B, V, C = a.shape
    out = np.empty((B, geom.ny, geom.nx), np.float32)
    step = groups_per_launch(geom) * BATCH_LANES
    n = min(step, B)
    if n == 0:
        return out
    G = -(-n // BATCH_LANES)
    rows = aligned_empty((n * V, C))
    # one slot per (sinogram, view): its own filtered row, weight 1
    ident = np.arange(n * V, dtype=np.int32).reshape(n, V, 1)
    d_sino = rt.empty((G, V, C + 2, BATCH_LANES))
    d_img = rt.empty((G * BATCH_LANES, geom.ny, geom.nx))
    host = np.empty((G * BATCH_LANES, geom.ny, geom.nx), np.float32)
    try:
        for b0 in range(0, B, step):
            m = min(step, B - b0)
            filter_rows(a[b0:b0 + m].reshape(m * V, C), geom, window, out=rows[:m * V])
            idx, wgt = pad_interleaved(ident[:m], np.ones((m, V, 1), np.float32))
            d_rows = DeviceRows(rows[:m * V], rt=rt, share=True)
            try:
                buf, g = apply_padded_interleaved(d_rows, idx, wgt, m, rt=rt, out=d_sino)
                res = backproject_interleaved(buf, g, geom, runtime=rt, out_buf=d_img, out=host)
            finally:
                d_rows.release()
            out[b0:b0 + m] = res[:m]
    finally:
        d_sino.release()
        d_img.release()
    return out


def fbp_hu(sino, geom: FanBeamGeometry, window: str = "ram-lak", mu_water: float = MU_WATER_PER_MM, *,
           runtime=None) -> np.ndarray:
    """:func:`fbp` in Hounsfield units (B, ny, nx) float32; pixels outside the FOV are -1000.

    ``mu_water`` (1/mm) is the scene's water attenuation (``PhantomConfig.mu_water_per_mm``).
    """
    return mu_to_hu(fbp(sino, geom, window, runtime=runtime), mu_water).astype(np.float32)


def fbp_batched(sino: np.ndarray, geom: FanBeamGeometry, window: str, mu_water: float, batch: int = 64, *,
                runtime=None) -> np.ndarray:
    """FBP in HU of (B, V, C) sinograms in batches of ``batch`` (bounded memory)."""
    out = np.empty((sino.shape[0], geom.ny, geom.nx), np.float32)
    for b0 in range(0, sino.shape[0], batch):
        out[b0:b0 + batch] = fbp_hu(sino[b0:b0 + batch], geom, window, mu_water, runtime=runtime)
    return out
