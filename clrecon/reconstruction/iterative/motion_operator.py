"""The forward model through the motion model: reference volume (+ density term) -> warped -> projected.

Unknown ``X`` (K, nz, ny, nx) float32 on a :class:`~clrecon.reconstruction.iterative.geometry.VolumeGrid`:
``X[0]`` the attenuation (1/mm) at the model's reference state (c_ref, a_ref); with the density
term (K = 2) ``X[1]`` the change of attenuation per unit of amplitude, in the reference frame
(1/mm per unit of a). The volume at state s = (c, a) is

    f_s = W_s (X[0] + (a - a_ref) X[1])

and the views of the motion-state bin b (:mod:`clrecon.reconstruction.iterative.state_bins`)
see ``A_b f_{s_b}`` (A_b: the voxel projector over the bin's views). Two warps W_s
(docs/iterative.md "Forward model"):

- ``"pull"`` (intensity-preserving): ``f_s(y) = f_ref(x_r(y))`` with ``x_r(y) + u(x_r(y); s) = y``,
  i.e. :func:`~clrecon.reconstruction.iterative.warp.warp` by the inverse field ``v(y) = x_r(y) - y``
  (:func:`inverse_field`); a voxel keeps its value where it moves.
- ``"push"`` (mass-preserving): ``f_s = W_u^T f_ref`` (:func:`~clrecon.reconstruction.iterative.warp.warp_adjoint`
  by u(.; s) on the reference grid): each reference voxel's content is spread where it goes, so a
  region that expands gets less dense (1 / Jacobian), as lung tissue does when air comes in.

The adjoint runs the same steps backwards with the exact transposes (matched backprojector,
transposed warp), so ``<A W x, y> = <x, W^T A^T y>`` to float32 rounding (the dot-product test in
``tests/reconstruction/test_motion_operator.py``).

Ordered subsets: one subset per bin by default (a bin's views are spread over many beats and
breaths, so over gantry angles), visited in a fixed pseudo-random order (seed 0) so that
consecutive subsets sit at unrelated states.
"""

from __future__ import annotations

import numpy as np
import scipy.ndimage

from clrecon.reconstruction.iterative.operators import (
    BACKPROJECTORS,
    backproject_groups,
    chords_groups,
    project_groups,
    split_groups,
)
from clrecon.reconstruction.iterative.warp import invert_field, warp, warp_adjoint
from clrecon.reconstruction.motion.model import FieldGrid, MotionModel, sample

WARPS = ("pull", "push")
#: Fixed-point steps of the field inversion (as the motion-compensated backprojection's kernel).
INVERSION_STEPS = 10
#: HU range of the reference volume where the density term may be non-zero: lung parenchyma
#: (-950 to -500 HU in patients; the phantom's -760 to -840) with room for partial volume at its
#: edges. Elsewhere the body's tissue does not change density with breathing.
DENSITY_HU = (-980.0, -300.0)
#: Gaussian smoothing (voxels) of the density term after each epoch: the change of lung density
#: with breathing varies over centimetres, not voxels.
DENSITY_SIGMA_VOXELS = 1.0
#: Bytes of per-bin fields kept between uses at most (beyond it they are recomputed each time); a
#: run's slab keeps what its memory budget leaves of it (``method.field_cache_within``).
FIELD_CACHE_BYTES = 2 << 30


def model_on_grid(model: MotionModel, grid) -> MotionModel:
    """The model's fields resampled (trilinear, clamped at the model grid's edges) onto ``grid``'s
    voxel centres: a :class:`MotionModel` on the volume grid (same basis and reference)."""
    x, y, z = grid.coords()
    fg = FieldGrid(nx=max(2, grid.nx), ny=max(2, grid.ny), nz=max(2, grid.nz), voxel_mm=grid.voxel_mm,
                   z0_mm=grid.z0_mm, dz_mm=grid.dz_mm)
    same = (model.grid.nx, model.grid.ny, model.grid.nz, model.grid.voxel_mm, model.grid.z0_mm, model.grid.dz_mm) \
        == (grid.nx, grid.ny, grid.nz, grid.voxel_mm, grid.z0_mm, grid.dz_mm)
    if same:
        return model
    zz, yy, xx = np.meshgrid(z, y, x, indexing="ij")
    pts = np.stack([xx, yy, zz], -1)
    f = sample(model.fields, model.grid, pts).astype(np.float32)          # (NB, 3, nz, ny, nx)
    if grid.nz < 2 or grid.nx < 2 or grid.ny < 2:
        raise ValueError("model_on_grid: the volume grid needs >= 2 voxels per axis")
    return MotionModel(basis=model.basis, grid=fg, fields=f, reference=model.reference)


def inverse_field(u, spacing_mm, iterations: int = INVERSION_STEPS, rt=None) -> np.ndarray:
    """v with ``v(y) = -u(y + v(y))`` (so ``x_r = y + v(y)`` maps to ``y``): fixed-point iteration
    from v = -u (:func:`~clrecon.reconstruction.iterative.warp.invert_field`, one kernel launch).
    (3, nz, ny, nx) float32 mm."""
    return invert_field(np.asarray(u, np.float32), spacing_mm, int(iterations), rt=rt)


class MotionConeOperator:
    """A_b W_b over the views of motion-state bins (see the module docstring).

    ``backprojector``: SART's backprojection (:meth:`update_direction`, :meth:`col_sums`,
    :meth:`direction_and_col_sums`): ``"matched"`` the exact transpose (as :meth:`adjoint`, always
    matched), ``"voxel"`` the voxel-driven gather B ~ A^T
    (:mod:`~clrecon.reconstruction.iterative.cone_gather`); both through W^T.

    ``grid`` the volume grid; ``groups`` the scan's view groups
    (:func:`~clrecon.reconstruction.iterative.geometry.view_groups`);
    ``bins`` a :class:`~clrecon.reconstruction.iterative.state_bins.StateBins` over the same view
    positions; ``model`` a :class:`MotionModel` (resampled to ``grid`` here); ``warp_mode`` one of
    :data:`WARPS`; ``density``: whether X holds the density term (K = 2).
    """

    def __init__(self, grid, groups, bins, model: MotionModel, *, warp_mode: str = "pull", density: bool = True,
                 mu_water_per_mm: float = 0.0193, rt=None, order_seed: int = 0,
                 field_cache_bytes: int = FIELD_CACHE_BYTES, backprojector: str = "matched"):
        if warp_mode not in WARPS:
            raise ValueError(f"warp_mode = {warp_mode!r}: must be one of {WARPS}")
        if backprojector not in BACKPROJECTORS:
            raise ValueError(f"backprojector = {backprojector!r}: must be one of {BACKPROJECTORS}")
        self.backprojector = backprojector
        self.grid, self.rt, self.warp_mode, self.density = grid, rt, warp_mode, bool(density)
        self.model = model_on_grid(model, grid)
        self.a_ref = float(model.reference[1])
        self.bins = bins
        self._parts = [split_groups(groups, m) for m in bins.members]
        self._order = np.random.default_rng(order_seed).permutation(len(bins))
        self.n_subsets = len(bins)
        self.unknown_shape = ((2,) if self.density else (1,)) + grid.shape
        self._fields, self._budget = {}, int(field_cache_bytes)
        lo, hi = DENSITY_HU
        self._mu_range = (mu_water_per_mm * (1 + lo / 1000.0), mu_water_per_mm * (1 + hi / 1000.0))
        self._mask = None
        # the density term's step (update_direction, constrain): sum_b alpha_b g_b over an epoch,
        # and sum_b alpha_b^2 C_b (its diagonal scale), both in the reference frame
        self._gd = np.zeros(grid.shape, np.float64) if self.density else None
        self._hd = np.zeros(grid.shape, np.float64) if self.density else None
        self._epochs = 0

    # -- per bin ---------------------------------------------------------------------------
    def _bin(self, s: int) -> int:
        return int(self._order[s])

    def subset_rows(self, s: int) -> np.ndarray:
        return np.concatenate([p.rows for p in self._parts[self._bin(s)]])

    def alpha(self, b: int) -> float:
        return float(self.bins.states[b, 1]) - self.a_ref

    def field(self, c: float, a: float) -> np.ndarray:
        """The warp's field at state (c, a) on the grid: v (pull) or u (push), (3, nz, ny, nx) float32 mm."""
        u = self.model.displacement(c, a)
        if self.warp_mode == "push":
            return u
        return inverse_field(u, self.grid.spacing_mm, rt=self.rt)

    @property
    def fields_kept(self) -> int:
        """How many bins' fields the cache holds (the others are made again at each use)."""
        return len(self._fields)

    def _bin_field(self, b: int) -> np.ndarray:
        f = self._fields.get(b)
        if f is None:
            f = self.field(*self.bins.states[b])
            if (len(self._fields) + 1) * f.nbytes <= self._budget:
                self._fields[b] = f
        return f

    def to_state(self, vol, f) -> np.ndarray:
        """W_s vol for the field ``f`` of :meth:`field`."""
        h = self.grid.spacing_mm
        return warp(vol, f, h, rt=self.rt) if self.warp_mode == "pull" else warp_adjoint(vol, f, h, rt=self.rt)

    def from_state(self, g, f) -> np.ndarray:
        """W_s^T g."""
        h = self.grid.spacing_mm
        return warp_adjoint(g, f, h, rt=self.rt) if self.warp_mode == "pull" else warp(g, f, h, rt=self.rt)

    def state_volume(self, X, c: float, a: float) -> np.ndarray:
        """f_s at (c, a): (nz, ny, nx) float32 (1/mm)."""
        X = np.asarray(X, np.float32)
        vol = X[0] + (float(a) - self.a_ref) * X[1] if self.density else X[0]
        return self.to_state(np.ascontiguousarray(vol, np.float32), self.field(c, a))

    def update_direction(self, r, s: int) -> np.ndarray:
        """SART's update direction for subset s: W_b^T A_b^T r for the attenuation; the density term
        gets none per subset (its per-bin step, sign(alpha) times the residual, is noisy where
        |alpha| is small) but accumulates alpha_b W_b^T A_b^T r for one step per epoch (:meth:`constrain`)."""
        return self._as_direction(self.adjoint(r, s, kind=self.backprojector))

    def col_sums(self, w, s: int) -> np.ndarray:
        """|A_s|^T w (SART's C_s for the ray mask w); also accumulates the density step's scale."""
        return self._as_col_sums(self.adjoint(w, s, absolute=True, kind=self.backprojector), self._bin(s))

    def direction_and_col_sums(self, r, w, s: int) -> tuple[np.ndarray, np.ndarray]:
        """(:meth:`update_direction` (r, s), :meth:`col_sums` (w, s)), with their bookkeeping, from one
        pass of the backprojector over the bin's rays (its pair) and two transposed warps: the same
        values as the two calls (each backprojection the same bits)."""
        b = self._bin(s)
        f = self._bin_field(b)
        gr, gw = backproject_groups(r, self.grid, self._parts[b], self.rt, proj2=w, kind=self.backprojector)
        return (self._as_direction(self._lift(self.from_state(gr, f), b)),
                self._as_col_sums(self._lift(self.from_state(gw, f), b, absolute=True), b))

    def _as_direction(self, g) -> np.ndarray:
        """A lifted W^T A^T r as SART's direction: the density term's part goes to its per-epoch step."""
        if self.density:
            self._gd += g[1]              # alpha_b g_b
            g[1] = 0.0
        return g

    def _as_col_sums(self, c, b: int) -> np.ndarray:
        """A lifted |W^T A^T| w as SART's column sums, accumulating the density step's scale."""
        if self.density:
            self._hd += float(self.alpha(b)) ** 2 * c[0]
        return c

    def constrain(self, X, epoch_end: bool) -> None:
        """The density term's step and constraint, in place, at each epoch's end (after the first,
        which solves the attenuation alone): ``d += sum_b alpha_b g_b / sum_b alpha_b^2 C_b`` (a
        SIRT step over every bin, fitting the residual's dependence on the amplitude), smoothed
        by :data:`DENSITY_SIGMA_VOXELS` and kept only on the lung-like voxels of the current
        reference (:data:`DENSITY_HU`)."""
        if not self.density or not epoch_end:
            return
        self._epochs += 1
        if self._epochs >= 2:
            step = np.where(self._hd > 0, self._gd / np.maximum(self._hd, 1e-30), 0.0)
            X[1] += step.astype(np.float32)
        self._gd[:] = 0.0
        lo, hi = self._mu_range
        self._mask = ((X[0] >= lo) & (X[0] <= hi)).astype(np.float32)
        X[1] = scipy.ndimage.gaussian_filter(X[1], DENSITY_SIGMA_VOXELS, mode="nearest") * self._mask

    # -- the operator ------------------------------------------------------------------------
    def forward(self, X, s: int, *, absolute: bool = False) -> np.ndarray:
        """A_b W_b (X[0] + alpha_b X[1]) for the bin of subset s: (m_s, R, C) float32
        (``absolute``: |alpha_b|, for SART's row sums)."""
        b = self._bin(s)
        al = abs(self.alpha(b)) if absolute else self.alpha(b)
        vol = X[0] + al * X[1] if self.density else X[0]
        state = self.to_state(np.ascontiguousarray(vol, np.float32), self._bin_field(b))
        return project_groups(state, self.grid, self._parts[b], self.rt)

    def adjoint(self, r, s: int, *, absolute: bool = False, kind: str = "matched") -> np.ndarray:
        """W_b^T A_b^T r (and alpha_b times it for the density term): ``unknown_shape`` float32 (``kind``
        "voxel": B ~ A^T instead of the exact transpose, for SART's steps)."""
        b = self._bin(s)
        g = self.from_state(backproject_groups(r, self.grid, self._parts[b], self.rt, kind=kind), self._bin_field(b))
        return self._lift(g, b, absolute)

    def _lift(self, g, b: int, absolute: bool = False) -> np.ndarray:
        """A reference-frame volume g as the unknown's shape: (1, ...) or, with the density term,
        (g, alpha_b g) (``absolute``: |alpha_b|)."""
        if not self.density:
            return g[None]
        al = abs(self.alpha(b)) if absolute else self.alpha(b)
        return np.stack([g, al * g])

    def row_sums(self, s: int) -> np.ndarray:
        """|A_s| 1 (SART's R_s). The pull warp takes a volume of ones to ones (trilinear weights add up
        to 1, the edges clamped), so there R_s is each ray's chord through the grid's box
        (:func:`~clrecon.reconstruction.iterative.operators.chords_groups`), times 1 + |alpha_b| with the
        density term, without warping or projecting; the push warp projects its warped ones."""
        b = self._bin(s)
        if self.warp_mode == "pull":
            chords = chords_groups(self.grid, self._parts[b])
            return chords * np.float32(1.0 + abs(self.alpha(b))) if self.density else chords
        return self.forward(np.ones(self.unknown_shape, np.float32), s, absolute=True)

