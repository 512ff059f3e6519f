"""A motion model of the thorax as a smooth function of (cardiac phase c, respiratory amplitude a).

Displacement fields from a reference state to other states (registered from a first-pass 5D
reconstruction, :mod:`clrecon.reconstruction.motion.registration`, or the phantom's true
motion) are fitted voxel by voxel, in 3D, as

    u(x; c, a) = U_0(x) + sum_{p=1..P} a^p U_p(x)
                 + sum_{h=1..H} [cos(2 pi h c) U_ch(x) + sin(2 pi h c) U_sh(x)]

-- Low et al.'s breathing model X = X0 + alpha v (the amplitude term; the airflow term beta f is
not used: the phantom's motion depends on the amplitude only, docs/motion-model.md
"Assumptions") plus a periodic cardiac term of H harmonics, additive in the two motions. The
fit is linear least squares over the registered states with a small ridge (every voxel shares
one design matrix), :data:`FIT_BLOCK` columns at a time. docs/motion-model.md "The method" (step 3).

Fields are float32 arrays (..., 3, nz, ny, nx): components (dx, dy, dz) in mm, LPS, on the grid
of voxel centres of the reconstruction in-plane (``voxel_coords(nx, voxel_mm)``) and on
``nz`` planes ``z0_mm + k dz_mm`` along z. A field u(x; s) maps the reference position x to
``x + u(x; s)``, the position at state s.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.ndimage

from clrecon.core.conventions import voxel_coords

#: Columns (voxel components) of the fit worked on at once: the fit is float64 within a block of
#: n states x FIT_BLOCK columns (with its projection and residual: about 4 such arrays, 0.1 GB for
#: 50 states), never over the whole field, which for 50 states of a 512 x 512 x 8 grid would be
#: four float64 copies of 1.26 GB of float32 fields. Each column is fitted on its own, so the
#: coefficients do not depend on the block.
FIT_BLOCK = 1 << 16


@dataclass(frozen=True, kw_only=True)
class MotionBasis:
    """The functions of (c, a) the model is linear in.

    ``resp_degree``: powers a, a^2, .. a^P of the amplitude (P >= 0); ``cardiac_harmonics``: H
    harmonics of the cardiac phase (H >= 0). Function 0 is the constant.
    """

    resp_degree: int = 1
    cardiac_harmonics: int = 2

    def __post_init__(self):
        for name in ("resp_degree", "cardiac_harmonics"):
            v = getattr(self, name)
            if not (isinstance(v, (int, np.integer)) and not isinstance(v, bool) and 0 <= v <= 8):
                raise ValueError(f"{name} = {v!r}: must be an integer in [0, 8]")

    @property
    def size(self) -> int:
        """Number of basis functions NB (the constant included)."""
        return 1 + self.resp_degree + 2 * self.cardiac_harmonics

    @property
    def names(self) -> tuple:
        out = ["1"] + [f"a^{p}" for p in range(1, self.resp_degree + 1)]
        for h in range(1, self.cardiac_harmonics + 1):
            out += [f"cos{h}c", f"sin{h}c"]
        return tuple(out)

    def values(self, c, a) -> np.ndarray:
        """Basis values at states (c, a), each (n,) or scalar: (n, NB) float64."""
        c = np.atleast_1d(np.asarray(c, np.float64))
        a = np.atleast_1d(np.asarray(a, np.float64))
        if c.shape != a.shape or c.ndim != 1:
            raise ValueError(f"c and a must be 1-D of equal length, got {c.shape} and {a.shape}")
        if not (np.all(np.isfinite(c)) and np.all(np.isfinite(a))):
            raise ValueError("c and a must be finite")
        cols = [np.ones_like(c)] + [a ** p for p in range(1, self.resp_degree + 1)]
        for h in range(1, self.cardiac_harmonics + 1):
            cols += [np.cos(2 * np.pi * h * c), np.sin(2 * np.pi * h * c)]
        return np.stack(cols, axis=1)


@dataclass(frozen=True, kw_only=True)
class FieldGrid:
    """Grid of a motion field: the reconstruction's in-plane voxel centres and uniform z planes.

    ``nx``, ``ny``, ``voxel_mm``: as the reconstruction (``voxel_coords``); ``z0_mm`` and ``dz_mm``:
    plane k at ``z0_mm + k dz_mm``, ``nz`` planes (``nz >= 2``, ``dz_mm > 0``). A subclass may allow
    fewer voxels per axis (``MIN_SIZE``).
    """

    #: Fewest voxels along each axis (a field is interpolated between two planes at least).
    MIN_SIZE = 2

    nx: int
    ny: int
    nz: int
    voxel_mm: float
    z0_mm: float
    dz_mm: float

    def __post_init__(self):
        lo = self.MIN_SIZE
        for name in ("nx", "ny", "nz"):
            v = getattr(self, name)
            if not (isinstance(v, (int, np.integer)) and not isinstance(v, bool) and v >= lo):
                raise ValueError(f"{name} = {v!r}: must be an integer >= {lo}")
        for name in ("voxel_mm", "dz_mm"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ValueError(f"{name} = {v!r}: must be a finite number > 0")
        if not math.isfinite(self.z0_mm):
            raise ValueError(f"z0_mm = {self.z0_mm!r}: must be finite")

    @classmethod
    def of_slices(cls, nx: int, ny: int, voxel_mm: float, slices_z_mm) -> FieldGrid:
        """The grid of a volume whose slices ``slices_z_mm`` are uniformly spaced (ValueError otherwise)."""
        z = np.asarray(slices_z_mm, np.float64)
        if z.ndim != 1 or z.size < 2:
            raise ValueError(f"slices_z_mm: need >= 2 slices, got shape {z.shape}")
        dz = np.diff(z)
        if not np.allclose(dz, dz[0], rtol=1e-6, atol=1e-9) or dz[0] <= 0:
            raise ValueError("slices_z_mm: must be increasing and uniformly spaced")
        return cls(nx=int(nx), ny=int(ny), nz=int(z.size), voxel_mm=float(voxel_mm), z0_mm=float(z[0]),
                   dz_mm=float(dz[0]))

    @property
    def shape(self) -> tuple:
        return (self.nz, self.ny, self.nx)

    def coords(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(x (nx,), y (ny,), z (nz,)) voxel-centre coordinates, mm."""
        return (voxel_coords(self.nx, self.voxel_mm), voxel_coords(self.ny, self.voxel_mm),
                self.z0_mm + self.dz_mm * np.arange(self.nz))

    def index_of(self, points) -> np.ndarray:
        """Fractional (iz, iy, ix) indices of points (..., 3) = (x, y, z) mm: (3, ...) float64."""
        p = np.asarray(points, np.float64)
        return np.stack([(p[..., 2] - self.z0_mm) / self.dz_mm,
                         p[..., 1] / self.voxel_mm + 0.5 * (self.ny - 1),
                         p[..., 0] / self.voxel_mm + 0.5 * (self.nx - 1)])


def sample(fields, grid: FieldGrid, points) -> np.ndarray:
    """Trilinear samples of fields (..., nz, ny, nx) at points (m..., 3) mm: (..., m...) float64.

    Indices are clamped to the grid (the field is extended by its edge values), as the kernel
    of :mod:`clrecon.reconstruction.motion.backproject` does.
    """
    f = np.asarray(fields)
    lead = f.shape[:-3]
    idx = grid.index_of(points)
    for k, n in enumerate(grid.shape):
        np.clip(idx[k], 0.0, n - 1, out=idx[k])
    flat = f.reshape((-1,) + grid.shape)
    out = np.stack([scipy.ndimage.map_coordinates(np.asarray(g, np.float64), idx, order=1, mode="nearest")
                    for g in flat])
    return out.reshape(lead + idx.shape[1:])


@dataclass(frozen=True, kw_only=True)
class MotionModel:
    """u(x; c, a) = sum_b B_b(c, a) U_b(x): ``fields`` (NB, 3, nz, ny, nx) float32 mm on ``grid``.

    ``reference``: the state (c, a) the fields start from; ``basis``: the functions B_b.
    """

    basis: MotionBasis
    grid: FieldGrid
    fields: np.ndarray
    reference: tuple

    def __post_init__(self):
        f = np.asarray(self.fields)
        want = (self.basis.size, 3) + self.grid.shape
        if f.shape != want:
            raise ValueError(f"fields: expected shape {want} = (NB, 3, nz, ny, nx), got {f.shape}")
        if f.dtype != np.float32 or not np.all(np.isfinite(f)):
            raise ValueError("fields: must be finite float32")

    def displacement(self, c: float, a: float) -> np.ndarray:
        """u(x; c, a) on the grid, (3, nz, ny, nx) float32 mm."""
        b = self.basis.values(c, a)[0].astype(np.float32)
        return np.tensordot(b, self.fields, axes=(0, 0))

    def inverse_points(self, points, c: float, a: float, iterations: int = 10) -> np.ndarray:
        """Reference positions x_r with ``x_r + u(x_r; c, a) = points`` (..., 3) mm, float64.

        Fixed-point iteration ``x_r <- points - u(x_r)`` from ``x_r = points`` with trilinear
        samples (converges where the field's Jacobian norm is below 1: smooth fields). The
        kernel of :mod:`clrecon.reconstruction.motion.backproject` runs the same iteration.
        """
        p = np.asarray(points, np.float64)
        u_t = self.displacement(c, a)
        xr = p.copy()
        for _ in range(int(iterations)):
            xr = p - np.moveaxis(sample(u_t, self.grid, xr), 0, -1)
        return xr


def fit_motion_model(displacements, states, basis: MotionBasis, grid: FieldGrid, reference: tuple,
                     ridge: float = 1e-6) -> tuple[MotionModel, np.ndarray]:
    """Least-squares fit of the model to displacement fields at known states.

    Parameters
    ----------
    displacements : (n, 3, nz, ny, nx) array
        u(x; s_i) from the reference state, mm, on ``grid``.
    states : (n, 2) array
        (c, a) of each field.
    basis, grid, reference
        See :class:`MotionModel`.
    ridge : float
        Tikhonov weight relative to the design matrix's largest squared singular value (keeps
        a basis the states cannot separate -- e.g. more harmonics than distinct phases -- from
        blowing up; the coefficients of well-sampled functions move by ~ridge relative).

    Returns
    -------
    (MotionModel, residual_rms_mm (n,) float64): the model and each state's RMS fit residual
    (mm, over the grid and the three components).
    """
    d = np.asarray(displacements, np.float32)
    s = np.asarray(states, np.float64)
    if s.ndim != 2 or s.shape[1] != 2:
        raise ValueError(f"states: expected shape (n, 2) = (c, a) rows, got {s.shape}")
    if d.shape != (len(s), 3) + grid.shape:
        raise ValueError(f"displacements: expected shape {(len(s), 3) + grid.shape}, got {d.shape}")
    flat = d.reshape(len(s), -1)
    return _fit(lambda j0, j1: flat[:, j0:j1], flat.shape[1], s, basis, grid, reference, ridge)


def fit_separable_model(cardiac, resp, states, basis: MotionBasis, grid: FieldGrid, reference: tuple,
                        ridge: float = 1e-6) -> tuple[MotionModel, np.ndarray]:
    """:func:`fit_motion_model` of the fields ``cardiac[i] + resp[j]`` of every state (i, j), cardiac-major
    (``states`` (n_c n_r, 2) in that order), without holding those n_c n_r fields: each block of
    columns is summed when it is fitted (float32, as the whole sum would be: the same bits).

    ``cardiac`` (n_c, 3, nz, ny, nx) and ``resp`` (n_r, 3, nz, ny, nx) float32 mm on ``grid``
    (:func:`clrecon.reconstruction.motion.estimate.separable_parts`).
    """
    card = np.asarray(cardiac, np.float32)
    res = np.asarray(resp, np.float32)
    s = np.asarray(states, np.float64)
    if card.shape[1:] != (3,) + grid.shape or res.shape[1:] != (3,) + grid.shape:
        raise ValueError(f"cardiac {card.shape} and resp {res.shape}: expected (n, 3) + {grid.shape} each")
    if s.ndim != 2 or s.shape != (len(card) * len(res), 2):
        raise ValueError(f"states: expected shape ({len(card) * len(res)}, 2) = (c, a) rows, got {s.shape}")
    c2, r2 = card.reshape(len(card), -1), res.reshape(len(res), -1)
    return _fit(lambda j0, j1: (c2[:, None, j0:j1] + r2[None, :, j0:j1]).reshape(len(s), -1), c2.shape[1], s,
                basis, grid, reference, ridge)


def _fit(columns, n_columns: int, s, basis: MotionBasis, grid: FieldGrid, reference: tuple, ridge: float):
    """The fit of :func:`fit_motion_model` on ``columns(j0, j1)`` ((n, j1 - j0) float32, the fields' columns
    j0 .. j1-1 of ``n_columns``), :data:`FIT_BLOCK` columns at a time."""
    if len(s) < basis.size:
        raise ValueError(f"{len(s)} states cannot fit {basis.size} basis functions {basis.names}")
    B = basis.values(s[:, 0], s[:, 1])                         # (n, NB)
    lam = float(ridge) * float(np.linalg.norm(B, 2)) ** 2
    solve = np.linalg.solve(B.T @ B + lam * np.eye(basis.size), B.T)   # (NB, n)
    coef = np.empty((basis.size, n_columns), np.float32)
    sq = np.zeros(len(s), np.float64)
    for j in range(0, n_columns, FIT_BLOCK):  # float64 a block of columns at a time (module docstring)
        block = columns(j, min(j + FIT_BLOCK, n_columns)).astype(np.float64)
        c = solve @ block
        sq += ((block - B @ c) ** 2).sum(axis=1)
        coef[:, j:j + FIT_BLOCK] = c
    rms = np.sqrt(sq / max(1, n_columns))
    fields = coef.reshape((basis.size, 3) + grid.shape)
    return MotionModel(basis=basis, grid=grid, fields=fields, reference=tuple(map(float, reference))), rms
