"""Analytic fan-beam sinograms of uniform disks and the error measure of the FBP tests
(tests/reconstruction/test_fbp.py, test_parallel_fbp.py)."""

from __future__ import annotations

import numpy as np

from clrecon.core.conventions import detector_frames
from clrecon.reconstruction.fbp import FanBeamGeometry


def rel_max_err(a, ref) -> float:
    """max |a - ref| / max |ref| (absolute where ref is all zero)."""
    err = float(np.max(np.abs(np.asarray(a, np.float64) - ref)))
    scale = float(np.max(np.abs(ref)))
    return err / scale if scale > 0 else err


def disk_sinogram(geom: FanBeamGeometry, centre_mm, radius_mm: float, mu: float) -> np.ndarray:
    """Exact line integrals (V, C) of a uniform disk: mu * chord 2 sqrt(r^2 - d^2).

    d = perpendicular distance of the disk centre from the ray source -> detector cell,
    built from ``detector_frames`` (the conventions module), not from the backprojector.
    """
    b = geom.view_angles_rad()
    src, det, e_u, _ = detector_frames(b, np.zeros_like(b), geom.sid_mm, geom.sdd_mm)
    u = geom.col_coords_mm()
    cell = det[:, None, :2] + u[None, :, None] * e_u[:, None, :2]  # (V, C, 2)
    d = cell - src[:, None, :2]
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    rel = np.asarray(centre_mm, np.float64) - src[:, None, :2]
    dist = rel[..., 0] * d[..., 1] - rel[..., 1] * d[..., 0]
    return mu * 2.0 * np.sqrt(np.clip(radius_mm ** 2 - dist ** 2, 0.0, None))


def radius_map(geom: FanBeamGeometry, centre=(0.0, 0.0)) -> np.ndarray:
    x, y = geom.pixel_coords_mm()
    return np.hypot(x[None, :] - centre[0], y[:, None] - centre[1])
