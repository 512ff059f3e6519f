"""Error metrics against ground truth (stage 9 of the pipeline).

Conventions (the paper's Table 2): absolute voxel-wise HU differences between a
reconstruction and the ground-truth CT of the same target, pooled over **all voxels of all
targets**, reported as mean ± standard deviation, in two fields of view:

- large FOV: the reconstruction circle (radius = the smaller of the scanner's field of view
  and half the image width), every slice;
- small FOV: an axial box around the heart (``recon.small_fov_mm``), every slice.

Volumes are arrays ``(n_cardiac, n_resp, nz, ny, nx)`` in HU.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from clrecon.core.conventions import voxel_coords


@dataclass(frozen=True, kw_only=True)
class MetricsConfig:
    """What the error metrics need: the in-plane grid and the two fields of view (mm).

    ``large_radius_mm`` is the reconstruction circle (the smaller of the scanner's field of
    view and half the image width); ``small_fov_mm`` = (x_min, x_max, y_min, y_max), LPS.
    """

    nx: int
    ny: int
    voxel_mm: float
    large_radius_mm: float
    small_fov_mm: tuple

    @classmethod
    def from_scene(cls, scene) -> MetricsConfig:
        rc = scene.recon
        return cls(nx=rc.nx, ny=rc.ny, voxel_mm=rc.voxel_mm, small_fov_mm=tuple(rc.small_fov_mm),
                   large_radius_mm=min(scene.scanner.fov_radius_mm, rc.fov_radius_mm))


def fov_masks(cfg: MetricsConfig) -> dict[str, np.ndarray]:
    """Boolean in-plane masks ``(ny, nx)`` for the ``large`` and ``small`` FOVs."""
    x = voxel_coords(cfg.nx, cfg.voxel_mm)
    y = voxel_coords(cfg.ny, cfg.voxel_mm)
    xx, yy = np.meshgrid(x, y)
    large = xx ** 2 + yy ** 2 <= cfg.large_radius_mm ** 2
    x0, x1, y0, y1 = cfg.small_fov_mm
    small = (xx >= x0) & (xx <= x1) & (yy >= y0) & (yy <= y1) & large
    return {"large": large, "small": small}


def abs_error_stats(recon: np.ndarray, truth: np.ndarray, mask2d: np.ndarray) -> dict:
    """Mean and std of |recon - truth| over the in-plane mask, all slices and targets.

    ``recon``/``truth``: (..., nz, ny, nx) HU, same shape. Accumulates in float64 per
    slice so that paper-size volumes do not need a float64 copy.
    """
    if recon.shape != truth.shape:
        raise ValueError(f"recon shape {recon.shape} != truth shape {truth.shape}")
    n = 0
    s1 = 0.0
    s2 = 0.0
    r2 = recon.reshape((-1,) + recon.shape[-2:])
    t2 = truth.reshape((-1,) + truth.shape[-2:])
    for a, b in zip(r2, t2, strict=True):
        d = np.abs(a[mask2d].astype(np.float64) - b[mask2d])
        n += d.size
        s1 += d.sum()
        s2 += (d * d).sum()
    mean = s1 / max(n, 1)
    var = max(s2 / max(n, 1) - mean * mean, 0.0)
    return {"mae_hu": float(mean), "std_hu": float(np.sqrt(var)), "n_voxels": int(n)}


class Table2:
    """Accumulates |recon - truth| per target; pooled and per-target MAE/std for both FOVs.

    Targets are added one at a time (``add(i, j, recon, truth)`` with (nz, ny, nx) HU
    volumes) so paper-size runs never hold more than one target's volumes. The absolute
    difference is formed once (float32) and summed in float64 over each FOV's voxels.
    """

    def __init__(self, cfg: MetricsConfig, n_cardiac: int, n_resp: int):
        self.flat = {fov: np.flatnonzero(m.ravel()) for fov, m in fov_masks(cfg).items()}
        self.sums = {fov: np.zeros((n_cardiac, n_resp, 2)) for fov in self.flat}
        self.count = {fov: np.zeros((n_cardiac, n_resp), np.int64) for fov in self.flat}

    def add(self, i: int, j: int, recon: np.ndarray, truth: np.ndarray, scratch: dict | None = None) -> None:
        """Target (i, j)'s sums. ``scratch``: a dictionary the caller keeps from call to call (and
        may share between accumulators); the differences are formed in arrays kept there instead
        of fresh ones. Fresh arrays of paper size are fresh pages (about 0.8 GB per volume here),
        whose first touch costs more than the arithmetic on a machine with dear page faults.
        Same values in arrays of the same shapes and layouts either way, so the same float64 sums,
        bit for bit (tests/evaluation/test_metrics.py)."""
        if recon.shape != truth.shape:
            raise ValueError(f"recon shape {recon.shape} != truth shape {truth.shape}")
        sc = {} if scratch is None else scratch

        def kept(name, shape, dtype, order="C"):
            a = sc.get(name)
            if a is None or a.shape != shape or a.dtype != dtype:
                a = sc[name] = np.empty(shape, dtype, order=order)
            return a

        nz = recon.shape[0]
        d = kept("diff", recon.shape, np.result_type(recon, truth))
        np.subtract(recon, truth, out=d)
        np.abs(d, out=d)
        d = d.reshape(nz, -1)
        for fov, idx in self.flat.items():
            # column-major, as NumPy lays out d[:, idx] (slices fastest): a float64 sum adds in
            # memory order, so the layout is part of the result's last bits
            g = kept(("fov", fov), (nz, idx.size), d.dtype, "F")
            np.take(d, idx, axis=1, out=g)
            x = kept(("fov64", fov), (nz, idx.size), np.float64, "F")
            np.copyto(x, g)
            s1 = x.sum()
            np.multiply(x, x, out=x)
            self.sums[fov][i, j] = (s1, x.sum())
            self.count[fov][i, j] = x.size

    def result(self) -> dict:
        """``{"large": {mae_hu, std_hu, n_voxels}, "small": {...}, "per_target": {fov: [[mae]]}}``."""
        out: dict = {}
        per: dict = {}
        for fov in self.flat:
            n = int(self.count[fov].sum())
            total = self.sums[fov].sum(axis=(0, 1))
            mean = total[0] / max(n, 1)
            out[fov] = {"mae_hu": float(mean),
                        "std_hu": float(np.sqrt(max(total[1] / max(n, 1) - mean * mean, 0.0))), "n_voxels": n}
            per[fov] = (self.sums[fov][..., 0] / np.maximum(self.count[fov], 1)).tolist()
        out["per_target"] = per
        return out


def table2(recon: np.ndarray, truth: np.ndarray, cfg: MetricsConfig) -> dict:
    """:class:`Table2` of whole (n_c, n_r, nz, ny, nx) HU arrays (the paper's Table 2 convention)."""
    if recon.shape != truth.shape:
        raise ValueError(f"recon shape {recon.shape} != truth shape {truth.shape}")
    acc = Table2(cfg, recon.shape[0], recon.shape[1])
    for i in range(recon.shape[0]):
        for j in range(recon.shape[1]):
            acc.add(i, j, recon[i, j], truth[i, j])
    return acc.result()


def blood_pool_volume_ml(volume_hu: np.ndarray, region: np.ndarray, voxel_ml: float,
                         threshold_hu: float = 220.0) -> float:
    """Volume (mL) of the voxels above ``threshold_hu`` inside ``region``.

    Used for the LV blood pool: contrast-enhanced blood (300-450 HU) against myocardium
    (80-100 HU); 220 HU is about midway. ``region`` (nz, ny, nx) bool is the true LV cavity
    at the target state dilated by a margin (:func:`clrecon.evaluation.groundtruth.lv_region_mask`), so
    contrast in the neighbouring chambers and the aorta, which touch the cavity, is not counted
    (a connected-component measure leaked into them and doubled the volume).
    """
    if volume_hu.shape != region.shape:
        raise ValueError(f"volume shape {volume_hu.shape} != region shape {region.shape}")
    return float(np.count_nonzero((volume_hu > threshold_hu) & region) * voxel_ml)
