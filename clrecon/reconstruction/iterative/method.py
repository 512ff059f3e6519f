"""The ``mcir`` method: OS-SART on the cone-beam rows through ``mc``'s motion model (docs/iterative.md).

One entry point per slab, :func:`reconstruct_slab`: the scan's projections, ``mc``'s motion model
and the run's targets in, the targets' volumes of the slab's slices out. Per slab of slices
``a .. b-1`` (z from ``z_a`` to ``z_b``):

1. **views**: every view whose source lies within ``[z_a - w, z_b + w]``, w the cone's half-width
   at the far side of the reconstruction circle (:func:`geometry.half_cone_mm`): every view that
   sees a slice of the slab;
2. **volume**: the reconstruction's in-plane grid (subdivided ``voxel_factor`` times) on planes of
   ``plane_dz_mm`` covering every ray of those views (:func:`geometry.volume_grid`: their sources
   +- w), so that no used ray leaves the volume through an unmodelled object;
3. **bins**: the views grouped by motion state (``cardiac_bins`` x ``resp_bins``,
   :mod:`state_bins`), one ordered subset per bin;
4. **solve**: X = (reference attenuation, density term) by OS-SART (:mod:`sart`) through
   :class:`motion_operator.MotionConeOperator`, with the data residual per epoch, from zero or from
   a start image (``[recon.mcir] init``: the reference state's target of the first pass or of ``mc``,
   :func:`start_volume`);
5. **targets**: each target's state volume ``W_s (X[0] + (a - a_ref) X[1])`` sampled trilinearly at
   the slab's slices and the reconstruction grid's voxel centres, in HU.

The result is the same bits whatever the process (every sum is either fixed-point or in a fixed
order), so the stage's slab units may run anywhere. Volumes are (n_c, n_r, b - a, ny, nx) HU float32.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import scipy.ndimage

from clrecon.core.conventions import mu_to_hu, voxel_coords
from clrecon.core.resources import rss_mark
from clrecon.reconstruction.iterative import geometry as geo
from clrecon.reconstruction.iterative.motion_operator import FIELD_CACHE_BYTES, MotionConeOperator
from clrecon.reconstruction.iterative.sart import SARTConfig, os_sart
from clrecon.reconstruction.iterative.state_bins import bin_keys, state_bins
from clrecon.reconstruction.motion.model import MotionModel

#: The method this module makes (its registry entry: :mod:`clrecon.reconstruction.interpolation.mcir`).
NAME = "mcir"
#: Bytes one slab may take (:func:`memory_bytes`): the run's slices are cut into the fewest slabs under it.
SLAB_BYTES = 6 << 30


@dataclass(frozen=True)
class SlabSetup:
    """What one slab solves over: ``views`` (m,) table positions, ``grid`` the volume."""

    views: np.ndarray
    grid: geo.VolumeGrid


def slab_setup(scanner, recon, knobs, object_radius_mm: float, source_z_mm, slices_z) -> SlabSetup:
    """The views and the volume of the slab of slices ``slices_z`` (module docstring, steps 1-2).

    ``recon``: the scene's ``[recon]`` (nx, ny, voxel_mm); ``knobs``: its ``[recon.mcir]``;
    ``source_z_mm`` (n,) the scan's focal-spot z per view. ValueError when no view sees the slab.
    """
    z = np.asarray(slices_z, np.float64)
    src = np.asarray(source_z_mm, np.float64)
    w = geo.half_cone_mm(scanner, object_radius_mm)
    views = np.flatnonzero((src >= z.min() - w) & (src <= z.max() + w)).astype(np.int64)
    if views.size == 0:
        raise ValueError(f"mcir: no view's source lies within {w:.1f} mm of slices {z.min():g}..{z.max():g} mm")
    f = int(knobs.voxel_factor)
    grid = geo.volume_grid(scanner, recon.nx * f, recon.ny * f, recon.voxel_mm / f, src[views], object_radius_mm,
                           knobs.plane_dz_mm)
    return SlabSetup(views, grid)


def needed_projections(scanner, recon, knobs, object_radius_mm: float, table, slices_z) -> np.ndarray:
    """Projection numbers (``table.index``) of every view a run's slices ``slices_z`` make ``mcir``
    read (the union of its slabs' views: sources within the cone's far half-width of a slice)."""
    z = np.asarray(slices_z, np.float64)
    w = geo.half_cone_mm(scanner, object_radius_mm)
    src = np.asarray(table.source_z_mm, np.float64)
    return np.asarray(table.index)[(src >= z.min() - w) & (src <= z.max() + w)]


def memory_bytes(grid: geo.VolumeGrid, n_views: int, n_rows: int, n_cols: int, n_bins: int, density: bool,
                 n_basis: int, epochs: int = 1, largest_bin_views: int | None = None,
                 field_cache_bytes: int = FIELD_CACHE_BYTES) -> int:
    """Peak bytes of :func:`reconstruct_slab` (a model): the projections (4 B per ray), the unknown and
    its update (K volumes each), the warp fields kept per bin (3 volumes per bin, at most
    ``field_cache_bytes``; the others are made again at each use), the model on the grid (3 volumes per basis field,
    ``n_basis``) and 8 working volumes; SART's weights: with ``epochs`` > 1 the row weights of every
    ray (4 B) and the column weights of every bin (K volumes each), kept for the next epoch; with one
    epoch one bin's at a time (K volumes and 6 x 4 B per ray of the largest bin,
    ``largest_bin_views``, default ``n_views``: its data, residual, projection and weights). Measured
    against a run's trace in docs/iterative.md "Memory"."""
    nv = grid.nx * grid.ny * grid.nz
    k = 2 if density else 1
    ray = 4 * n_rows * n_cols
    if epochs > 1:
        weights = ray * n_views + 4 * nv * k * n_bins
    else:
        weights = 6 * ray * (n_views if largest_bin_views is None else largest_bin_views) + 4 * nv * k
    fields = min(int(field_cache_bytes), 3 * 4 * nv * n_bins)
    return int(ray * n_views + weights + 4 * nv * (3 * k + 3 * n_basis + 8) + fields)


def bin_counts(table, knobs, views=None) -> np.ndarray:
    """The number of views in each motion-state bin the views of ``table`` (or its positions
    ``views``) fill (:func:`state_bins`' bins; empty bins are not listed)."""
    c, a = table.cardiac_phase, table.resp_amplitude
    if views is not None:
        c, a = c[views], a[views]
    return np.unique(bin_keys(c, a, knobs.cardiac_bins, knobs.resp_bins), return_counts=True)[1]


def n_bins(table, knobs, views=None) -> int:
    """The motion-state bins the views of ``table`` (or its positions ``views``) fill (empty bins cost
    nothing): the number of :func:`state_bins`' bins."""
    return int(bin_counts(table, knobs, views).size)


def field_cache_within(rest_bytes: int, budget: float) -> int:
    """The field cache (bytes) that keeps a slab whose other arrays model ``rest_bytes`` within
    ``budget``: what is left of it, at most ``motion_operator.FIELD_CACHE_BYTES``, at least 0 (then
    every bin's field is made again at each use: the same values, more time)."""
    return int(max(0.0, min(float(FIELD_CACHE_BYTES), float(budget) - float(rest_bytes))))


def slab_memory(scanner, recon, knobs, object_radius_mm: float, table, slices_z, n_basis: int,
                budget: float | None = None) -> tuple[int, int]:
    """``(bytes, field cache bytes)`` of the slab of slices ``slices_z`` (mm) over the views of
    ``table`` (the scan's usable views, a :class:`~clrecon.scan.table.ProjectionTable`): its own
    views, volume and filled bins (:func:`slab_setup`), with the field cache that keeps it within
    ``budget`` (:func:`field_cache_within`; default :data:`SLAB_BYTES`); the bytes are over
    ``budget`` only where the slab's other arrays alone are."""
    st = slab_setup(scanner, recon, knobs, object_radius_mm, table.source_z_mm, slices_z)
    return _fitted_memory(scanner, knobs, st, bin_counts(table, knobs, st.views), n_basis, budget)


def _fitted_memory(scanner, knobs, st: SlabSetup, counts, n_basis: int, budget: float | None) -> tuple[int, int]:
    """:func:`slab_memory` of the slab ``st`` whose filled bins hold ``counts`` views each."""
    budget = SLAB_BYTES if budget is None else budget

    def model(cache):
        return memory_bytes(st.grid, st.views.size, scanner.n_rows, scanner.n_cols, counts.size, knobs.density,
                            n_basis, epochs=knobs.epochs, largest_bin_views=int(counts.max()) if counts.size else 0,
                            field_cache_bytes=cache)

    cache = field_cache_within(model(0), budget)
    return model(cache), cache


def slab_memory_bytes(scanner, recon, knobs, object_radius_mm: float, table, slices_z, n_basis: int,
                      budget: float | None = None) -> int:
    """The bytes of :func:`slab_memory`."""
    return slab_memory(scanner, recon, knobs, object_radius_mm, table, slices_z, n_basis, budget)[0]


def slab_plan(scanner, recon, knobs, object_radius_mm: float, table, slices_z, n_basis: int,
              budget: float = SLAB_BYTES) -> tuple[list[tuple[int, int]], int]:
    """The slice ranges ``(a, b)`` of ``slices_z`` the stage solves one at a time, and the largest
    one's :func:`slab_memory_bytes`: the fewest equal slabs whose :func:`slab_memory_bytes` (with the
    field cache fitted to ``budget``) is under ``budget``, else one slice each."""
    z = np.asarray(slices_z, np.float64)
    n = len(z)
    sizes: dict = {}

    def size(a, b):  # each slab sized once, whichever cut tries it
        if (a, b) not in sizes:
            sizes[a, b] = slab_memory_bytes(scanner, recon, knobs, object_radius_mm, table, z[a:b], n_basis, budget)
        return sizes[a, b]

    singles = [(a, a + 1) for a in range(n)]
    cuts = singles
    if all(size(a, b) <= budget for a, b in singles):  # else no cut fits: one slice alone does not
        for k in range(1, n + 1):
            step = -(-n // k)
            trial = [(a, min(n, a + step)) for a in range(0, n, step)]
            if all(size(a, b) <= budget for a, b in trial):
                cuts = trial
                break
    return cuts, int(max(size(a, b) for a, b in cuts))


def over_budget_note(largest_bytes: int, budget: float | None = None) -> str:
    """What a slab cut whose largest slab models ``largest_bytes`` costs, where that is over ``budget``
    (default :data:`SLAB_BYTES`; then one slice alone is over it: :func:`slab_plan` solves every slice
    on its own), and what lowers it; '' where it is not over."""
    budget = SLAB_BYTES if budget is None else budget
    if largest_bytes <= budget:
        return ""
    return (f"one slice alone is over the {budget / 2**30:g} GiB slab budget ({largest_bytes / 1e9:.2f} GB "
            "modelled), so every slice is solved on its own over the views it shares with its neighbours (slow); "
            "a coarser grid ([recon] nx, ny or [recon.mcir] plane_dz_mm) lowers it (the warp fields kept are "
            "already what the budget leaves)")


def run_memory_bytes(scanner, recon, knobs, object_radius_mm: float, table, slices_z, n_basis: int) -> int:
    """The modelled peak of a run's ``mcir`` stage (bytes) on the slices ``slices_z`` (mm) of a scan
    whose usable views are ``table``: the largest slab of :func:`slab_plan` (the same cut and the
    same views, volumes and bins as the stage's)."""
    return slab_plan(scanner, recon, knobs, object_radius_mm, table, slices_z, n_basis)[1]


def target_slices(vol, grid: geo.VolumeGrid, slices_z, nx: int, ny: int, voxel_mm: float) -> np.ndarray:
    """Trilinear samples of a grid volume (nz, ny', nx') at planes ``slices_z`` and the
    reconstruction grid's voxel centres: (S, ny, nx) float64."""
    xo, yo = voxel_coords(nx, voxel_mm), voxel_coords(ny, voxel_mm)
    iz = (np.asarray(slices_z, np.float64) - grid.z0_mm) / grid.dz_mm
    ix = (xo - grid.origin_mm[0]) / grid.voxel_mm
    iy = (yo - grid.origin_mm[1]) / grid.voxel_mm
    Z, Y, X = np.meshgrid(iz, iy, ix, indexing="ij")
    return scipy.ndimage.map_coordinates(np.asarray(vol, np.float64), [Z, Y, X], order=1, mode="nearest")


def start_volume(start_hu, grid: geo.VolumeGrid, slices_z, voxel_mm: float, mu_water_per_mm: float) -> np.ndarray:
    """OS-SART's start on the iterative volume: an image of the reference state on the run's grid,
    ``start_hu`` (s, ny, nx) HU at slices ``slices_z`` (s,) mm and in-plane voxels of ``voxel_mm``,
    sampled trilinearly at ``grid``'s voxel centres and converted to attenuation (1/mm, >= 0):
    (nz, ny', nx') float32. Beyond the slices (the volume reaches the cone's half-width further)
    and the image's edge the nearest slice's and pixel's values are repeated: the body goes on
    there, and the solver corrects what the data see."""
    img = np.asarray(start_hu, np.float64)
    z = np.asarray(slices_z, np.float64)
    if img.ndim != 3 or img.shape[0] != z.size:
        raise ValueError(f"start_hu: expected (s, ny, nx) with s = {z.size} slices, got {img.shape}")
    ny, nx = img.shape[1:]
    xs, ys, zs = grid.coords()
    kz = np.interp(zs, z, np.arange(z.size))  # fractional slice index per plane (a run's slices increase)
    kx = (xs - voxel_coords(nx, voxel_mm)[0]) / voxel_mm
    ky = (ys - voxel_coords(ny, voxel_mm)[0]) / voxel_mm
    Z, Y, X = np.meshgrid(kz, ky, kx, indexing="ij")
    hu = scipy.ndimage.map_coordinates(img, [Z, Y, X], order=1, mode="nearest")
    return np.maximum(mu_water_per_mm * (1.0 + hu / 1000.0), 0.0).astype(np.float32)


def reconstruct_slab(scanner, recon, knobs, object_radius_mm: float, mu_water_per_mm: float, table, projections,
                     slices_z, targets, model: MotionModel, *, start_hu=None, rt=None,
                     log=None, budget: float | None = None) -> tuple[np.ndarray, dict]:
    """``mcir``'s volumes of the slab of slices ``slices_z`` (s,) mm: (n_c, n_r, s, ny, nx) HU float32.

    ``table``: the whole scan's :class:`~clrecon.scan.table.ProjectionTable`; ``projections(views)``
    returns the projections (m, n_rows, n_cols) float32 of table positions ``views`` (sorted; the
    noise variant's); ``targets``: the run's ``Targets``; ``model``: ``mc``'s motion model (any grid:
    resampled to the volume); ``start_hu``: None (start from zero) or the reference state's image
    (s, ny, nx) HU at ``slices_z`` (:func:`start_volume`; the density term starts at zero).
    ``log(line)``: the solver's residual per epoch. ``budget``: the slab's memory budget (bytes,
    default :data:`SLAB_BYTES`); the warp fields kept between uses are what the rest of the slab
    leaves of it (:func:`slab_memory`; the others are made again: the same values). Returns
    (volumes, info: the views, the volume grid, the bins, the field cache, SART's history, seconds).
    """
    t0 = time.perf_counter()
    setup = slab_setup(scanner, recon, knobs, object_radius_mm, table.source_z_mm, slices_z)
    _, cache = _fitted_memory(scanner, knobs, setup, bin_counts(table, knobs, setup.views), model.basis.size, budget)
    sub = table.take(setup.views)
    proj = np.asarray(projections(setup.views), np.float32)
    rss_mark(f"mcir: the projections of {setup.views.size} views ({proj.nbytes / 1e9:.3f} GB)")
    groups = geo.view_groups(scanner, sub)
    bins = state_bins(sub.cardiac_phase, sub.resp_amplitude, knobs.cardiac_bins, knobs.resp_bins)
    op = MotionConeOperator(setup.grid, groups, bins, model, warp_mode=knobs.warp, density=knobs.density,
                            backprojector=knobs.backprojector, field_cache_bytes=cache,
                            mu_water_per_mm=mu_water_per_mm, rt=rt)
    rss_mark(f"mcir: the operator on {setup.grid.nz} x {setup.grid.ny} x {setup.grid.nx} voxels, {len(bins)} bins")
    cfg = SARTConfig(epochs=knobs.epochs, relaxation=knobs.relaxation, decay=knobs.decay, tol=knobs.tol)
    t1 = time.perf_counter()
    x0 = np.zeros(op.unknown_shape, np.float32)
    if start_hu is not None:
        x0[0] = start_volume(start_hu, setup.grid, slices_z, recon.voxel_mm, mu_water_per_mm)
    X, hist = os_sart(op, lambda s: proj[op.subset_rows(s)], x0, cfg, log=log)
    rss_mark("mcir: the solve")
    t2 = time.perf_counter()
    nc, nr = targets.shape
    out = np.empty((nc, nr, len(slices_z), recon.ny, recon.nx), np.float32)
    for i, c in enumerate(targets.cardiac):
        for j, a in enumerate(targets.resp):
            vol = op.state_volume(X, c, a)
            out[i, j] = mu_to_hu(target_slices(vol, setup.grid, slices_z, recon.nx, recon.ny, recon.voxel_mm),
                                 mu_water_per_mm)
    rss_mark("mcir: the targets")
    info = {"views": int(setup.views.size), "grid": [setup.grid.nz, setup.grid.ny, setup.grid.nx],
            "plane_dz_mm": setup.grid.dz_mm, "voxel_mm": setup.grid.voxel_mm, "bins": len(bins),
            "field_cache_bytes": cache, "fields_kept": op.fields_kept,
            "sart": hist.as_dict(), "seconds": {"setup": round(t1 - t0, 3), "solve": round(t2 - t1, 3),
                                                "targets": round(time.perf_counter() - t2, 3)}}
    return out, info


def reconstruct_slab_from_store(scene, cfg, table, store, slices_z, targets, variant: str, model: MotionModel, *,
                                start_hu=None, rt=None, log=None, times=None,
                                budget: float | None = None) -> tuple[np.ndarray, dict]:
    """:func:`reconstruct_slab` of a run: the one body of the stage's unit, in the run's process and
    on a Dask worker. ``scene`` gives the scanner, ``[recon]`` and ``[recon.mcir]``; ``cfg`` the
    :class:`~clrecon.reconstruction.reconstruct.ReconstructionConfig` (radius, mu_water); ``table``
    the scan's usable views; ``store`` the projection store (``read_indices``; ``variant`` "noisy"
    draws the run's noise); ``start_hu`` and ``budget`` as :func:`reconstruct_slab`'s. ``times``: optional
    ``StageTimes`` given ``mcir_solve`` and ``method:mcir:<variant>`` seconds."""
    t0 = time.perf_counter()
    out = reconstruct_slab(scene.scanner, scene.recon, scene.recon.mcir, cfg.object_radius_mm, cfg.mu_water_per_mm,
                           table, lambda views: store.read_indices(table.index[views], noisy=variant == "noisy"),
                           slices_z, targets, model, start_hu=start_hu, rt=rt, log=log, budget=budget)
    if times is not None:
        times.add("mcir_solve", time.perf_counter() - t0)
        times.add(f"method:{NAME}:{variant}", time.perf_counter() - t0)
    return out
