"""Small vector helpers for packed quadrics, shared by the projector and the voxeliser.

Arrays are float64 with the vector or matrix in the last axes; lengths in mm.
"""

from __future__ import annotations

import numpy as np

from clrecon.simulation.phantoms import layout as ph


def dot(a, b):
    return a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1] + a[..., 2] * b[..., 2]


def cross(a, b):
    return np.stack([a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1],
                     a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2],
                     a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]], -1)


def local_map(axes_flat, semi):
    """World -> normalised local map M = D^-1 R^T, (..., 3, 3), from packed AXES and SEMI."""
    R = axes_flat.reshape(axes_flat.shape[:-1] + (3, 3))
    return np.swapaxes(R, -1, -2) / semi[..., :, None]


def apply(M, v):
    return M[..., 0] * v[..., 0:1] + M[..., 1] * v[..., 1:2] + M[..., 2] * v[..., 2:3]


def box_half_extent(kind, axes_flat, semi):
    """World axis-aligned half extents (..., 3) of the unclipped primitives."""
    R = axes_flat.reshape(axes_flat.shape[:-1] + (3, 3))
    cols = R * semi[..., None, :]  # column k = axis k scaled by its semi-axis
    ell = np.sqrt((cols ** 2).sum(-1))
    cyl = np.sqrt((cols[..., :2] ** 2).sum(-1)) + np.abs(cols[..., 2])
    return np.where((kind == ph.KIND_CYLINDER)[..., None], cyl, ell)


def as_axis(a, name):
    a = np.asarray(a)
    if a.dtype.kind not in "fiu":
        raise TypeError(f"{name}: expected a real array, got dtype {a.dtype}")
    if a.ndim != 1 or a.size == 0:
        raise ValueError(f"{name} must be a non-empty 1-D array, got shape {a.shape}")
    return np.asarray(a, dtype=np.float64)
