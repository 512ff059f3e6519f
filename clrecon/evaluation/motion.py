"""Motion metrics beyond MAE (stage 9 of the pipeline, beside :mod:`clrecon.evaluation.metrics`).

The MAE cannot tell a smoothed-but-biased image from a sharp-but-noisy one, nor say where a
moving cardiac target ends up. Per reconstructed volume of one target (c*, a*),
``(nz, ny, nx)`` float HU on the grid ``(z_mm, y_mm, x_mm)`` of voxel centres, against the
ground-truth CT of the same target and the phantom's own geometry at (c*, a*):

- **edge width** (mm): the 10-90 % distance of the LV blood-pool -> myocardium transition,
  on ``n_profiles`` radial in-plane profiles from the LV cavity centre in the slice nearest
  it (bilinear interpolation, ``profile_step_mm`` apart); levels from the phantom's HU table
  (blood ``hu_blood``, myocardium ``hu_myocardium``): 90 % = lo + 0.9 (hi - lo), 10 % =
  lo + 0.1 (hi - lo). A profile counts only where the phantom's own ray leaves the cavity
  through the LV wall (not the mitral plane, not the lesion), and the image then has a
  downward crossing of the midpoint level within ``edge_search_mm`` of the true boundary,
  the 90 % level within ``max_edge_width_mm`` before it and the 10 % level within
  ``max_edge_width_mm`` after it. Per target: the median over the valid profiles, and their count.
- **LV blood-pool volume error** (mL): :func:`~clrecon.evaluation.metrics.blood_pool_volume_ml`
  (voxels > 220 HU inside the true cavity grown by 6 mm) of the reconstruction minus that of
  the ground-truth CT; and minus the phantom's analytic volume when the slab holds the whole
  cavity (else not reported).
- **target localisation error** (mm, vector and norm): the centroid of the LV-wall lesion in
  a box of half-size ``lesion_box_mm`` around its true centre, weighted by ``max(v - T, 0)``
  with ``T = lesion_threshold_hu`` (between the contrast blood and the lesion: the background
  is subtracted by T and every neighbour below it weighs nothing), minus the true centre.
  Not measured when the slab does not hold the whole lesion or nothing in the box exceeds T.
- **noise standard deviation** (HU): the population std of ``recon - truth`` over a cylinder
  of radius ``noise_radius_mm`` about ``noise_centre_mm`` through every slice: by default
  inside the descending aorta, which is static, uniform (400 HU) and crosses every slab. On
  a noise-free reconstruction it is the motion / interpolation floor.

Everything here is NumPy on arrays; :func:`target_geometry` is the one function that asks the
phantom (and the LV-region voxeliser) what is true at a target. Unmeasurable values are NaN
here and ``None`` in ``results.json``. Definitions: docs/metrics.md "Motion metrics".
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from clrecon.core.conventions import voxel_coords
from clrecon.evaluation import groundtruth, metrics
from clrecon.simulation.phantoms import analytic


@dataclass(frozen=True, kw_only=True)
class MotionConfig:
    """What the motion metrics need: the grid and the metric settings. Lengths in mm, levels in HU.

    ``x_mm``, ``y_mm``, ``z_mm``: voxel-centre coordinates (ascending, uniform) of the volumes;
    ``voxel_ml``: one voxel's volume (mL). Edge: ``hu_blood`` / ``hu_myocardium`` the levels
    (the phantom's table), ``n_profiles`` directions, samples every ``profile_step_mm`` out to
    ``profile_length_mm``, ``edge_search_mm`` window about the true boundary,
    ``max_edge_width_mm`` the widest clean edge, ``wall_check_mm`` the blood before and the
    myocardium after the true boundary a profile needs. Lesion: ``lesion_radius_mm``,
    ``lesion_threshold_hu`` (T), ``lesion_box_mm`` (box half-size). Noise: the cylinder
    ``noise_centre_mm`` (x, y), ``noise_radius_mm``. LV volume: ``lv_threshold_hu``,
    ``lv_margin_mm`` (the region's growth).
    """

    x_mm: tuple
    y_mm: tuple
    z_mm: tuple
    voxel_ml: float
    hu_blood: float = analytic.P["hu_blood_left"]
    hu_myocardium: float = analytic.P["hu_myocardium"]
    n_profiles: int = 16
    profile_length_mm: float = 60.0
    profile_step_mm: float = 0.25
    edge_search_mm: float = 8.0
    max_edge_width_mm: float = 15.0
    wall_check_mm: float = 4.0
    lesion_radius_mm: float = analytic.P["lesion_radius"]
    lesion_threshold_hu: float = analytic.P["hu_blood_left"] + 150.0
    lesion_box_mm: float = analytic.P["lesion_radius"] + 8.0
    noise_centre_mm: tuple = (analytic.P["desc_aorta_x"], analytic.P["desc_aorta_y"])
    noise_radius_mm: float = analytic.P["desc_aorta_radius"] - 4.0
    lv_threshold_hu: float = 220.0
    lv_margin_mm: float = 6.0

    @classmethod
    def from_grid(cls, x_mm, y_mm, z_mm, slice_mm: float | None = None, **kw) -> MotionConfig:
        """From the axes of the volumes; ``slice_mm`` (used when there is one slice) sets the voxel depth."""
        x, y, z = (tuple(float(v) for v in np.asarray(a, float)) for a in (x_mm, y_mm, z_mm))
        dz = abs(z[1] - z[0]) if len(z) > 1 else float(slice_mm or 1.0)
        return cls(x_mm=x, y_mm=y, z_mm=z, voxel_ml=abs(x[1] - x[0]) * abs(y[1] - y[0]) * dz / 1000.0, **kw)

    @classmethod
    def from_scene(cls, scene, slices_z, **kw) -> MotionConfig:
        """For the volumes of a run of ``scene`` at the slice positions ``slices_z`` (mm)."""
        rc = scene.recon
        return cls.from_grid(voxel_coords(rc.nx, rc.voxel_mm), voxel_coords(rc.ny, rc.voxel_mm), slices_z,
                             slice_mm=rc.slice_mm, **kw)

    @property
    def levels(self) -> tuple[float, float, float]:
        """(90 %, 50 %, 10 %) levels (HU) of the blood -> myocardium transition."""
        hi, lo = self.hu_blood, self.hu_myocardium
        return lo + 0.9 * (hi - lo), lo + 0.5 * (hi - lo), lo + 0.1 * (hi - lo)

    def directions(self) -> np.ndarray:
        """Unit in-plane directions (n_profiles, 2) (x, y), the k-th at angle 2 pi k / n from +x."""
        t = 2.0 * np.pi * np.arange(self.n_profiles) / self.n_profiles
        return np.stack([np.cos(t), np.sin(t)], -1)

    def radii(self) -> np.ndarray:
        """Sample radii (n_samples,) mm along every profile, from 0 to ``profile_length_mm``."""
        return np.arange(0.0, self.profile_length_mm + 0.5 * self.profile_step_mm, self.profile_step_mm)


# ---------------------------------------------------------------------------------------------
# edge width
def bilinear(img: np.ndarray, x_mm, y_mm, px, py) -> np.ndarray:
    """``img`` (ny, nx) at points (px, py) mm (any equal shapes) by bilinear interpolation; NaN outside.

    ``x_mm`` (nx,), ``y_mm`` (ny,): ascending, uniformly spaced voxel centres.
    """
    x, y = np.asarray(x_mm, float), np.asarray(y_mm, float)
    fx = (np.asarray(px, float) - x[0]) / (x[1] - x[0])
    fy = (np.asarray(py, float) - y[0]) / (y[1] - y[0])
    ok = (fx >= 0) & (fx <= len(x) - 1) & (fy >= 0) & (fy <= len(y) - 1)
    fx, fy = np.where(ok, fx, 0.0), np.where(ok, fy, 0.0)
    i0 = np.minimum(np.floor(fx).astype(np.int64), len(x) - 2)
    j0 = np.minimum(np.floor(fy).astype(np.int64), len(y) - 2)
    tx, ty = fx - i0, fy - j0
    im = np.asarray(img, np.float64)
    v = ((1 - ty) * ((1 - tx) * im[j0, i0] + tx * im[j0, i0 + 1])
         + ty * ((1 - tx) * im[j0 + 1, i0] + tx * im[j0 + 1, i0 + 1]))
    return np.where(ok, v, np.nan)


def radial_profiles(img: np.ndarray, cfg: MotionConfig, centre_xy) -> np.ndarray:
    """HU along the ``cfg.n_profiles`` radial profiles from ``centre_xy`` (mm), (n_profiles, n_samples).

    ``img`` (ny, nx) one slice; samples at :meth:`MotionConfig.radii`; NaN outside the grid.
    """
    d, r = cfg.directions(), cfg.radii()
    px = centre_xy[0] + d[:, :1] * r
    py = centre_xy[1] + d[:, 1:] * r
    return bilinear(img, cfg.x_mm, cfg.y_mm, px, py)


def _crossing(r, f, i, level) -> float:
    """Radius where f crosses ``level`` between samples i and i + 1 (linear)."""
    return float(r[i] + (f[i] - level) / (f[i] - f[i + 1]) * (r[i + 1] - r[i]))


def edge_width_10_90(profile, r_mm, hi_hu: float, lo_hu: float, expected_mm: float | None = None,
                     search_mm: float = 8.0, max_width_mm: float = 15.0) -> float:
    """10-90 % width (mm) of a falling edge from ``hi_hu`` to ``lo_hu`` on one profile; NaN if none is clean.

    ``profile`` (n,) HU at radii ``r_mm`` (n,) ascending. The edge is the downward crossing of
    the midpoint level nearest ``expected_mm`` within ``search_mm`` (the first one from the
    start when ``expected_mm`` is None); from it, the last crossing of the 90 % level before and
    the first crossing of the 10 % level after, each within ``max_width_mm`` and with no NaN on
    the way. Crossings are located by linear interpolation between samples.
    """
    f = np.asarray(profile, np.float64)
    r = np.asarray(r_mm, np.float64)
    l90, mid, l10 = lo_hu + 0.9 * (hi_hu - lo_hu), lo_hu + 0.5 * (hi_hu - lo_hu), lo_hu + 0.1 * (hi_hu - lo_hu)
    down = np.flatnonzero((f[:-1] >= mid) & (f[1:] < mid))  # NaN compares False: never a crossing
    if expected_mm is not None:
        if not np.isfinite(expected_mm):
            return math.nan
        rc = np.array([_crossing(r, f, i, mid) for i in down])
        near = np.flatnonzero(np.abs(rc - expected_mm) <= search_mm) if down.size else down
        if near.size == 0:
            return math.nan
        k = int(down[near[np.argmin(np.abs(rc[near] - expected_mm))]])
    else:
        if down.size == 0:
            return math.nan
        k = int(down[0])
    r_mid = _crossing(r, f, k, mid)
    # 90 %: the last sample >= l90 at or before k; 10 %: the first sample <= l10 after k
    i = k
    while i >= 0 and np.isfinite(f[i]) and f[i] < l90 and r_mid - r[i] <= max_width_mm:
        i -= 1
    if i < 0 or not np.isfinite(f[i]) or f[i] < l90:
        return math.nan
    r90 = _crossing(r, f, i, l90) if f[i + 1] < l90 else float(r[i])
    j = k + 1
    while j < len(f) and np.isfinite(f[j]) and f[j] > l10 and r[j] - r_mid <= max_width_mm:
        j += 1
    if j >= len(f) or not np.isfinite(f[j]) or f[j] > l10:
        return math.nan
    r10 = _crossing(r, f, j - 1, l10)
    w = r10 - r90
    return float(w) if 0.0 <= w <= max_width_mm else math.nan


def nearest_slice(cfg: MotionConfig, z: float) -> int:
    """Index of the slice whose centre is nearest ``z`` (mm)."""
    return int(np.argmin(np.abs(np.asarray(cfg.z_mm) - z)))


def edge_widths(volume: np.ndarray, cfg: MotionConfig, centre_mm, expected_mm=None) -> np.ndarray:
    """10-90 % widths (mm) of the ``cfg.n_profiles`` radial profiles, (n_profiles,) float64, NaN = skipped.

    ``volume`` (nz, ny, nx) HU; profiles from ``centre_mm`` (x, y, z) in the slice nearest its z;
    ``expected_mm`` (n_profiles,): the true boundary radius per profile (NaN: the profile does
    not cross a clean blood -> myocardium boundary), or None to take the first edge.
    """
    img = np.asarray(volume)[nearest_slice(cfg, centre_mm[2])]
    prof = radial_profiles(img, cfg, centre_mm[:2])
    r = cfg.radii()
    exp = [None] * cfg.n_profiles if expected_mm is None else list(np.asarray(expected_mm, float))
    return np.array([edge_width_10_90(prof[k], r, cfg.hu_blood, cfg.hu_myocardium, exp[k], cfg.edge_search_mm,
                                      cfg.max_edge_width_mm) for k in range(cfg.n_profiles)])


def edge_width_summary(widths) -> tuple[float, int]:
    """(median over the valid profiles (NaN if none), number of valid profiles)."""
    w = np.asarray(widths, float)
    w = w[np.isfinite(w)]
    return (float(np.median(w)) if w.size else math.nan), int(w.size)


# ---------------------------------------------------------------------------------------------
# target localisation
def lesion_centroid(volume: np.ndarray, cfg: MotionConfig, around_mm, threshold_hu: float | None = None,
                    half_box_mm: float | None = None) -> np.ndarray:
    """Threshold-weighted centroid (x, y, z) mm of the bright blob in a box around ``around_mm``; NaN if none.

    ``volume`` (nz, ny, nx) HU. The box holds the voxel centres within ``half_box_mm``
    (default ``cfg.lesion_box_mm``) of ``around_mm`` along each axis; weights
    ``max(v - T, 0)``, ``T = threshold_hu`` (default ``cfg.lesion_threshold_hu``): the background
    is subtracted by the threshold, so that everything below it weighs nothing.
    """
    T = cfg.lesion_threshold_hu if threshold_hu is None else threshold_hu
    h = cfg.lesion_box_mm if half_box_mm is None else half_box_mm
    axes = [np.asarray(a, float) for a in (cfg.z_mm, cfg.y_mm, cfg.x_mm)]
    c = (around_mm[2], around_mm[1], around_mm[0])
    sel = [np.flatnonzero(np.abs(a - ci) <= h) for a, ci in zip(axes, c, strict=True)]
    if any(s.size == 0 for s in sel):
        return np.full(3, np.nan)
    sub = np.asarray(volume)[np.ix_(*sel)].astype(np.float64)
    w = np.clip(sub - T, 0.0, None)
    tot = w.sum()
    if not tot > 0:
        return np.full(3, np.nan)
    zc = (w.sum(axis=(1, 2)) @ axes[0][sel[0]]) / tot
    yc = (w.sum(axis=(0, 2)) @ axes[1][sel[1]]) / tot
    xc = (w.sum(axis=(0, 1)) @ axes[2][sel[2]]) / tot
    return np.array([xc, yc, zc])


def lesion_in_slab(cfg: MotionConfig, centre_mm) -> bool:
    """True when the whole lesion (radius ``cfg.lesion_radius_mm``) lies between the first and last slice centres."""
    z = np.asarray(cfg.z_mm)
    r = cfg.lesion_radius_mm
    return bool(z.min() <= centre_mm[2] - r and centre_mm[2] + r <= z.max())


def target_error(volume: np.ndarray, cfg: MotionConfig, true_centre_mm) -> np.ndarray:
    """Localisation error (dx, dy, dz) mm = lesion centroid - true centre; NaN when not measurable."""
    if not lesion_in_slab(cfg, true_centre_mm):
        return np.full(3, np.nan)
    return lesion_centroid(volume, cfg, true_centre_mm) - np.asarray(true_centre_mm, float)


# ---------------------------------------------------------------------------------------------
# noise and LV volume
def noise_region_mask(cfg: MotionConfig) -> np.ndarray:
    """In-plane (ny, nx) bool: voxel centres within ``noise_radius_mm`` of ``noise_centre_mm``."""
    xx, yy = np.meshgrid(np.asarray(cfg.x_mm), np.asarray(cfg.y_mm))
    cx, cy = cfg.noise_centre_mm
    return (xx - cx) ** 2 + (yy - cy) ** 2 <= cfg.noise_radius_mm ** 2


def noise_std(recon: np.ndarray, truth: np.ndarray, mask2d: np.ndarray) -> float:
    """Population std (HU) of ``recon - truth`` over the in-plane mask in every slice; NaN if the mask is empty.

    ``recon``, ``truth`` (nz, ny, nx) HU; ``mask2d`` (ny, nx) bool. float64 sums.
    """
    if recon.shape != truth.shape:
        raise ValueError(f"recon shape {recon.shape} != truth shape {truth.shape}")
    d = (np.asarray(recon)[:, mask2d].astype(np.float64) - np.asarray(truth)[:, mask2d])
    return float(d.std()) if d.size else math.nan


def crop_to_mask(mask: np.ndarray):
    """(slices, sub-mask): the bounding box of a bool mask (nz, ny, nx) and the mask inside it (small to keep)."""
    idx = np.nonzero(mask)
    if idx[0].size == 0:
        return (slice(0, 0),) * mask.ndim, np.zeros((0,) * mask.ndim, bool)
    sl = tuple(slice(int(i.min()), int(i.max()) + 1) for i in idx)
    return sl, mask[sl].copy()


def lv_volume_ml(volume: np.ndarray, region, cfg: MotionConfig) -> float:
    """LV blood-pool volume (mL) of ``volume`` (nz, ny, nx) HU in a cropped region ``(slices, sub-mask)``."""
    sl, sub = region
    return metrics.blood_pool_volume_ml(np.asarray(volume)[sl], sub, cfg.voxel_ml, cfg.lv_threshold_hu)


# ---------------------------------------------------------------------------------------------
# what is true at a target (the one place that asks the phantom)
@dataclass(frozen=True)
class TargetGeometry:
    """The phantom's truth at one target, what the metrics of every method at it compare against.

    ``lv_centre_mm``, ``lesion_centre_mm``: (3,) mm; ``edge_expected_mm``: (n_profiles,) true
    cavity boundary radius per profile (NaN: not a clean wall crossing); ``lv_region``: the
    cropped LV region ``(slices, sub-mask)``; ``lv_true_ml``: the analytic LV volume, NaN when
    the slab does not hold the whole cavity.
    """

    lv_centre_mm: np.ndarray
    lesion_centre_mm: np.ndarray
    edge_expected_mm: np.ndarray
    lv_region: tuple
    lv_true_ml: float


def offers_truth(phantom) -> bool:
    """Whether the phantom source knows what the motion metrics compare against (the analytic
    thorax's labelled LV cavity and myocardium; a voxel phantom has none). The lesion is optional:
    without it the localisation error is not measured."""
    names = getattr(phantom, "names", ())
    return "lv_blood" in names and "lv_myocardium" in names and hasattr(phantom, "lv_blood_volume_ml")


def ellipsoid_z_extent(obj_row) -> tuple[float, float]:
    """(z_min, z_max) mm of a packed ellipsoid row (clip planes ignored: a bound on the clipped object)."""
    o = np.asarray(obj_row, float)
    R = o[analytic.AXES].reshape(3, 3)
    ext = float(np.sqrt((R[2] ** 2) @ o[analytic.SEMI] ** 2))
    zc = float(o[analytic.CENTRE][2])
    return zc - ext, zc + ext


def expected_edges(objs, names, cfg: MotionConfig, centre_mm) -> np.ndarray:
    """True boundary radius (mm) of the LV cavity along each profile, (n_profiles,); NaN where not clean.

    ``objs`` (n_obj, STRIDE) packed phantom at the target, ``names`` its object names. Along
    each profile (in the plane of the slice nearest ``centre_mm``) the ray must start in the
    blood pool, leave it after at least ``wall_check_mm``, and then run through LV myocardium
    only (not the lesion, not out through the mitral plane) for ``wall_check_mm``.
    """
    z = cfg.z_mm[nearest_slice(cfg, centre_mm[2])]
    d, r = cfg.directions(), cfg.radii()
    pts = np.stack([centre_mm[0] + d[:, :1] * r, centre_mm[1] + d[:, 1:] * r, np.full((len(d), len(r)), z)], -1)
    blood = analytic.inside(objs[names.index("lv_blood")], pts)
    myo = analytic.inside(objs[names.index("lv_myocardium")], pts) & ~blood
    if "lesion" in names:
        myo &= ~analytic.inside(objs[names.index("lesion")], pts)
    out = np.full(len(d), np.nan)
    for k in range(len(d)):
        if not blood[k, 0]:
            continue
        exit_ = int(np.argmin(blood[k]))  # first sample outside the blood pool
        if exit_ == 0 or r[exit_] < cfg.wall_check_mm:
            continue
        wall = (r >= r[exit_]) & (r <= r[exit_] + cfg.wall_check_mm)
        if myo[k, wall].all():
            out[k] = 0.5 * (r[exit_ - 1] + r[exit_])
    return out


def target_geometry(phantom, c: float, a: float, cfg: MotionConfig, rt=None) -> TargetGeometry:
    """The phantom's truth at target (c, a) for :class:`MotionMetrics` (voxelises the LV region)."""
    objs = phantom.objects(c, a)
    names = list(phantom.names)
    lv = objs[names.index("lv_blood"), analytic.CENTRE].copy()
    lesion = objs[names.index("lesion"), analytic.CENTRE].copy() if "lesion" in names else np.full(3, np.nan)
    mask = groundtruth.lv_region_mask(phantom, c, a, np.asarray(cfg.x_mm), np.asarray(cfg.y_mm),
                                      np.asarray(cfg.z_mm), margin_mm=cfg.lv_margin_mm, rt=rt)
    z = np.asarray(cfg.z_mm)
    dz = cfg.voxel_ml * 1000.0 / abs((cfg.x_mm[1] - cfg.x_mm[0]) * (cfg.y_mm[1] - cfg.y_mm[0]))  # voxel depth
    lo, hi = ellipsoid_z_extent(objs[names.index("lv_blood")])
    covered = z.min() - dz / 2 <= lo and hi <= z.max() + dz / 2
    true_ml = float(phantom.lv_blood_volume_ml(c)) if covered else math.nan
    return TargetGeometry(lv_centre_mm=lv, lesion_centre_mm=lesion,
                          edge_expected_mm=expected_edges(objs, names, cfg, lv),
                          lv_region=crop_to_mask(mask), lv_true_ml=true_ml)


# ---------------------------------------------------------------------------------------------
def _clean(x):
    """NaN -> None, numpy -> python, recursively (for results.json)."""
    if isinstance(x, dict):
        return {k: _clean(v) for k, v in x.items()}
    if isinstance(x, np.ndarray):
        return _clean(x.tolist())
    if isinstance(x, (list, tuple)):
        return [_clean(v) for v in x]
    if isinstance(x, (float, np.floating)):
        return float(x) if math.isfinite(x) else None
    if isinstance(x, np.integer):
        return int(x)
    return x


def _mean(a) -> float:
    a = np.asarray(a, float)
    a = a[np.isfinite(a)]
    return float(a.mean()) if a.size else math.nan


class MotionMetrics:
    """Accumulates the four motion metrics of one (pitch, variant, method) target by target.

    ``add(i, j, recon, truth, geom, truth_lv_ml)`` with (nz, ny, nx) HU volumes of target
    (i, j), its :class:`TargetGeometry` and the ground truth's LV volume (mL); ``truth=None``
    measures the ground truth itself (the reference row: no noise and no volume error vs itself).
    """

    def __init__(self, cfg: MotionConfig, n_cardiac: int, n_resp: int):
        self.cfg = cfg
        self.mask2d = noise_region_mask(cfg)
        shape = (n_cardiac, n_resp)
        self.edge = np.full(shape, np.nan)
        self.n_prof = np.zeros(shape, np.int64)
        self.lv_err = np.full(shape, np.nan)
        self.lv_ml = np.full(shape, np.nan)
        self.lv_err_true = np.full(shape, np.nan)
        self.vec = np.full(shape + (3,), np.nan)
        self.noise = np.full(shape, np.nan)
        self.reference = False

    def add(self, i: int, j: int, recon: np.ndarray, truth: np.ndarray | None, geom: TargetGeometry,
            truth_lv_ml: float = math.nan) -> None:
        cfg = self.cfg
        self.edge[i, j], self.n_prof[i, j] = edge_width_summary(
            edge_widths(recon, cfg, geom.lv_centre_mm, geom.edge_expected_mm))
        v = lv_volume_ml(recon, geom.lv_region, cfg)
        self.lv_ml[i, j] = v
        self.lv_err_true[i, j] = v - geom.lv_true_ml
        self.vec[i, j] = target_error(recon, cfg, geom.lesion_centre_mm)
        if truth is None:
            self.reference = True
        else:
            self.lv_err[i, j] = v - truth_lv_ml
            self.noise[i, j] = noise_std(recon, truth, self.mask2d)

    def result(self) -> dict:
        """The ``results.json["motion"][pitch][variant][method]`` entry (None = not measurable)."""
        norm = np.linalg.norm(self.vec, axis=-1)
        covered = bool(np.isfinite(self.lv_err_true).all())
        out = {
            "edge_width_mm": {"mean": _mean(self.edge), "per_target": self.edge,
                              "valid_profiles_per_target": self.n_prof, "profiles": self.cfg.n_profiles},
            "lv_volume_error_ml": {
                "mean": None if self.reference else _mean(self.lv_err),
                "mean_abs": None if self.reference else _mean(np.abs(self.lv_err)),
                "per_target": None if self.reference else self.lv_err,
                "volume_ml_per_target": self.lv_ml,
                "vs_analytic": {"slab_covers_lv": covered, "mean": _mean(self.lv_err_true),
                                "per_target": self.lv_err_true}},
            "target_error_mm": {"mean": _mean(norm), "per_target": norm, "vector_per_target": self.vec,
                                "found": int(np.isfinite(norm).sum()), "of": int(norm.size)},
            "noise_std_hu": None if self.reference else {"mean": _mean(self.noise), "per_target": self.noise},
        }
        return _clean(out)


def definitions(cfg: MotionConfig) -> dict:
    """The settings the metrics ran with (for ``results.json`` and the report)."""
    l90, mid, l10 = cfg.levels
    return {"edge": {"levels_hu": [l90, mid, l10], "profiles": cfg.n_profiles, "step_mm": cfg.profile_step_mm,
                     "search_mm": cfg.edge_search_mm, "max_width_mm": cfg.max_edge_width_mm,
                     "where": "slice nearest the LV cavity centre, radial profiles from it"},
            "lv_volume": {"threshold_hu": cfg.lv_threshold_hu, "region_margin_mm": cfg.lv_margin_mm},
            "lesion": {"radius_mm": cfg.lesion_radius_mm, "threshold_hu": cfg.lesion_threshold_hu,
                       "half_box_mm": cfg.lesion_box_mm},
            "noise": {"centre_mm": list(cfg.noise_centre_mm), "radius_mm": cfg.noise_radius_mm,
                      "region": "cylinder through every slice (default: inside the descending aorta)"}}
