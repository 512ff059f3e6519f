"""The ``mc`` method's steps: first pass -> registered motion model -> motion-compensated FBP.

docs/motion-model.md is the method's reference (what it assumes, its failure cases, its knobs);
:mod:`clrecon.reconstruction.motion.mc_fbp` runs these steps on a scan (its one entry point,
``reconstruct_mc``), :mod:`clrecon.pipeline.stages.mc_reconstruct` wires that to a run. Per
scan (pitch) and noise variant:

1. ``mc_fbp.fit_model``: :func:`register` registers the first pass (barycentric, the registry's
   ``Method.first_pass``; :func:`estimate.separable_parts`, Lucas-Kanade) on a grid
   ``downsample`` times coarser in-plane (:func:`factor`, :func:`downsample`) and fits the
   (c, a) motion model (:func:`model.fit_separable_model`); for each further round it backprojects
   every target with that model on the coarse grid (:func:`backproject_slab`), registers those
   images and fits again;
2. ``mc_fbp.reconstruct_slab``: per slab, :func:`refine` samples the model's basis fields onto the
   reconstruction grid on the planes the slab's voxels can reach (:func:`reach_planes`);
   :func:`slab_rows` rebins and filters every projection the slab's first-pass plan uses onto
   global z planes (:func:`backproject.plane_rows`: the
   pipeline's SSRB on every detector and focal-spot mode) and :func:`backproject_slab` runs the
   kernel per target.

Shapes: volumes (n_c, n_r, S, ny, nx) HU; fields (NB, 3, S, ny, nx) float32 mm; slots (T, S, V, K).
"""

from __future__ import annotations

import dataclasses
import time

import numpy as np

from clrecon.core.resources import rss_mark
from clrecon.core.runtime import aligned_empty, aligned_zeros
from clrecon.reconstruction import rebin
from clrecon.reconstruction.fbp import FanBeamGeometry
from clrecon.reconstruction.motion import backproject as mcb
from clrecon.reconstruction.motion import estimate
from clrecon.reconstruction.motion import slots as msl
from clrecon.reconstruction.motion.flow import TVL1Config
from clrecon.reconstruction.motion.lk import LKConfig
from clrecon.reconstruction.motion.model import FieldGrid, MotionBasis, MotionModel, fit_separable_model, sample
from clrecon.reconstruction.motion.registration import FlowConfig


def reference_index(cardiac, resp, knobs) -> tuple[int, int]:
    """(i, j): the targets nearest ``knobs.reference_cardiac_phase`` (circularly) and ``knobs.reference_amplitude``."""
    c = np.asarray(cardiac, np.float64)
    dc = np.abs((c - knobs.reference_cardiac_phase + 0.5) % 1.0 - 0.5)
    return int(np.argmin(dc)), int(np.argmin(np.abs(np.asarray(resp, np.float64) - knobs.reference_amplitude)))


#: The in-plane voxel (mm) of the grid the registrations' knobs were chosen on (``demo``'s): with
#: ``downsample = 0`` (auto) the registration works on the coarsest grid whose voxels are at most this.
REGISTRATION_VOXEL_MM = 3.0


def factor_of(nx: int, ny: int, voxel_mm: float, knobs) -> int:
    """The in-plane factor the registration works at on an (ny, nx) grid of ``voxel_mm`` voxels: the
    largest f <= ``knobs.downsample`` dividing nx and ny; ``downsample = 0`` (auto): the largest
    f <= min(4, :data:`REGISTRATION_VOXEL_MM` / voxel_mm) dividing them (at least 1)."""
    most = knobs.downsample or max(1, min(4, int(REGISTRATION_VOXEL_MM / voxel_mm + 1e-9)))
    return max(f for f in range(1, most + 1) if nx % f == 0 and ny % f == 0)


def factor(geom: FanBeamGeometry, knobs) -> int:
    """:func:`factor_of` the reconstruction grid ``geom``."""
    return factor_of(geom.nx, geom.ny, geom.voxel_mm, knobs)


def coarse_geometry(geom: FanBeamGeometry, f: int) -> FanBeamGeometry:
    """``geom`` with ``f`` times fewer, ``f`` times larger voxels in-plane (the same field of view)."""
    return dataclasses.replace(geom, nx=geom.nx // f, ny=geom.ny // f, voxel_mm=geom.voxel_mm * f) if f > 1 else geom


def downsample(volumes, f: int) -> np.ndarray:
    """Block means of ``f x f`` voxels in-plane of (..., ny, nx): the voxel centres of :func:`coarse_geometry`."""
    v = np.asarray(volumes, np.float32)
    if f == 1:
        return v
    ny, nx = v.shape[-2:]
    return v.reshape(v.shape[:-2] + (ny // f, f, nx // f, f)).mean(axis=(-3, -1), dtype=np.float64).astype(np.float32)


def field_grid(geom: FanBeamGeometry, slices_z) -> FieldGrid:
    return FieldGrid.of_slices(geom.nx, geom.ny, geom.voxel_mm, slices_z)


def basis_of(knobs, n_cardiac: int, n_resp: int) -> MotionBasis:
    """The model's basis: ``knobs``' degree and harmonics, at most what the targets determine (n_c
    cardiac targets fix 1 + 2 H <= n_c periodic coefficients, n_r amplitudes a polynomial of degree < n_r)."""
    return MotionBasis(resp_degree=min(knobs.resp_degree, n_resp - 1),
                       cardiac_harmonics=min(knobs.cardiac_harmonics, (n_cardiac - 1) // 2))


def flow_of(knobs, step: str = "breathing") -> FlowConfig | TVL1Config | LKConfig:
    """The registration of the separable scheme's ``step`` (``"breathing"``: ``knobs.registration``;
    ``"beat"``: ``knobs.beat_registration``), with its knobs (``lucas_kanade_cl``: the Lucas-Kanade
    knobs ``flow_radius`` and ``flow_warps``, as ``lucas_kanade``)."""
    if step not in STEPS:
        raise ValueError(f"step = {step!r}: one of {STEPS}")
    name = registrations(knobs)[step]
    if name == "tvl1":
        return TVL1Config()
    if name == "lucas_kanade_cl":
        return LKConfig(radius=knobs.flow_radius, num_warp=knobs.flow_warps)
    return FlowConfig(radius=knobs.flow_radius, num_warp=knobs.flow_warps)


#: The separable registration's steps (:mod:`clrecon.reconstruction.motion.estimate`), in their order.
STEPS = ("breathing", "beat")


def registrations(knobs) -> dict:
    """``{step: registration name}`` of :data:`STEPS` (``knobs.registration``, ``knobs.beat_registration``)."""
    return {"breathing": knobs.registration, "beat": knobs.beat_registration}


def uses_library(knobs) -> bool:
    """Whether a step registers with scikit-image's Lucas-Kanade (the ``motion`` extra); TV-L1 and the
    OpenCL Lucas-Kanade (``lucas_kanade_cl``) run on the engine's OpenCL runtime."""
    return any(isinstance(flow_of(knobs, s), FlowConfig) for s in STEPS)


def uses_pool(knobs) -> bool:
    """Whether a step's registrations may run in a process pool: scikit-image's Lucas-Kanade's do (one
    per core); TV-L1's and the OpenCL Lucas-Kanade's run in the run's process on the OpenCL device,
    which uses every core itself."""
    return uses_library(knobs)


def register(volumes, ref_ij, grid: FieldGrid, pairs, knobs, progress=None, pool=None) -> tuple[MotionModel, dict]:
    """One round: the separable registration of ``volumes`` (n_c, n_r, nz, ny, nx) HU on ``grid`` and
    the model fitted to it. Returns (model, info: seconds and the fit's RMS residual, mm).
    ``progress``: optional ``update(n)`` counter, one step per registration; ``pool``: optional
    process pool running each step's registrations at once (the same fields, bit for bit)."""
    t0 = time.perf_counter()
    parts = estimate.separable_parts(volumes, tuple(ref_ij), grid, flow_of(knobs, "breathing"), progress=progress,
                                     pool=pool, shrink=shrink_of(knobs), beat_cfg=flow_of(knobs, "beat"))
    rss_mark("mc: the registrations (separable_parts)")
    t1 = time.perf_counter()
    nr = volumes.shape[1]
    ref = tuple(map(float, pairs[ref_ij[0] * nr + ref_ij[1]]))
    model, rms = fit_separable_model(parts["cardiac"], parts["resp"], pairs, basis_of(knobs, *volumes.shape[:2]),
                                     grid, ref)
    info = {"registration_seconds": t1 - t0, "fit_seconds": time.perf_counter() - t1,
            "fit_rms_mm": float(np.sqrt(np.mean(rms ** 2)))}
    if parts.get("shrink"):  # the fields' mean gain (1: unchanged) and the least of them (none: one target)
        gains = [x["mean_gain"] for x in parts["shrink"]]
        info.update(shrink_mean_gain=float(np.mean(gains)), shrink_min_gain=float(np.min(gains)))
    return model, info


def shrink_of(knobs) -> tuple | None:
    """(window radius, HU window) of the shrinkage towards zero (``knobs.shrink``), or None when off.
    The window is the Lucas-Kanade registration's (``flow_radius``; TV-L1's fields are judged in the same window)."""
    if not knobs.shrink:
        return None
    return knobs.flow_radius, FlowConfig().hu_window


#: Slack on :func:`reach_mm`'s bound for the float32 rounding of the kernel's sums and
#: interpolations: this share of the bound and of the sum of its terms' magnitudes (the rounding
#: of sum_b B_b U_b is a few ulps of the latter).
REACH_SLACK = 1e-4


def reach_mm(model: MotionModel, pairs) -> float:
    """A bound (mm) on |z_r - z| of the kernel's reference positions x_r = x - u_t(x_r) for the
    targets ``pairs`` (T, 2) (c, a): the largest |u_t,z| = |sum_b B_b(t) U_b,z| over the model's grid
    points and the targets (each step of the inversion moves z by a trilinear sample of u_t,z,
    within the grid points' range), with :data:`REACH_SLACK`. It holds on any finer in-plane grid
    too (:func:`refine`'s samples interpolate the same grid points, and u_t is linear in the fields).
    One target's z field at a time."""
    pairs = np.asarray(pairs, np.float64).reshape(-1, 2)
    tb = model.basis.values(pairs[:, 0], pairs[:, 1]).astype(np.float32)  # (T, NB)
    uz = model.fields[:, 2]  # (NB, nz, ny, nx)
    worst = 0.0
    for b in tb:
        worst = max(worst, float(np.abs(np.tensordot(b, uz, axes=(0, 0))).max()))
    terms = float(np.dot(np.abs(tb).max(axis=0), [float(np.abs(uz[k]).max()) for k in range(len(uz))]))
    return worst * (1.0 + REACH_SLACK) + REACH_SLACK * terms


def reach_planes(grid: FieldGrid, slab_z, reach: float) -> tuple[int, int]:
    """Planes ``[k0, k1)`` of ``grid`` the kernel reads for slices ``slab_z`` whose reference
    positions lie within ``reach`` mm of them in z: the planes around ``z +- reach`` that its
    trilinear reads (floor and floor + 1, with the grid's clamp to its end planes), one more on
    each side for the float32 rounding of the plane coordinate; at least 2 planes."""
    z = np.asarray(slab_z, np.float64)
    lo = (float(z.min()) - reach - grid.z0_mm) / grid.dz_mm
    hi = (float(z.max()) + reach - grid.z0_mm) / grid.dz_mm
    k0 = min(max(int(np.floor(lo)) - 1, 0), grid.nz - 2)
    k1 = min(max(int(np.floor(hi)) + 3, k0 + 2), grid.nz)
    return k0, k1


def refine(model: MotionModel, geom: FanBeamGeometry, slab_z=None, pairs=None) -> MotionModel | mcb.ModelWindow:
    """The model's basis fields sampled (trilinearly, edge-extended) onto ``geom``'s in-plane grid.

    With ``slab_z`` (the slab's slice z, mm) and ``pairs`` (its targets (c, a)), only the planes
    their voxels can reach (:func:`reach_planes` of :func:`reach_mm`), as a
    :class:`~clrecon.reconstruction.motion.backproject.ModelWindow` of the whole refined model
    (where the grids coincide: a copy of those planes of the model itself), page-aligned so that a
    CPU device reads it in place (the model, made elsewhere, would be copied to the device whole):
    the kernel's images are the same bits as with every plane. Without
    ``slab_z``, every plane (the model itself where the grids coincide: nothing is copied). Refined
    plane by plane: a plane depends on the model only, not on the planes kept; every plane is
    sampled for the whole model's displacement margin (curved detectors' kernel build), one plane
    held at a time.
    """
    g = model.grid
    same = (g.nx, g.ny) == (geom.nx, geom.ny)
    if same and slab_z is None:
        return model
    fine = g if same else FieldGrid(nx=geom.nx, ny=geom.ny, nz=g.nz, voxel_mm=geom.voxel_mm, z0_mm=g.z0_mm,
                                    dz_mm=g.dz_mm)
    k0, k1 = (0, g.nz) if slab_z is None else reach_planes(fine, slab_z, reach_mm(model, pairs))
    if same:  # the slab's planes of the model itself
        held = dataclasses.replace(g, nz=k1 - k0, z0_mm=float(g.coords()[2][k0]))
        planes = aligned_empty(model.fields[:, :, k0:k1].shape, np.float32)  # read in place on a CPU device
        planes[...] = model.fields[:, :, k0:k1]
        return mcb.ModelWindow(model=MotionModel(basis=model.basis, grid=held, fields=planes,
                                                 reference=model.reference),
                               whole=g, first=k0, margin_mm=mcb.displacement_margin_mm(model.fields))
    x, y, z = fine.coords()
    Y, X = np.meshgrid(y, x, indexing="ij")
    out = aligned_empty((model.basis.size, 3, k1 - k0, geom.ny, geom.nx), np.float32)  # read in place on a CPU device
    flat = model.fields.reshape((-1,) + g.shape)
    margin = 0.0
    need_margin = slab_z is not None and geom.curved and model.basis.size > 1
    for k, zk in enumerate(z):  # slice by slice: the points of a paper-scale grid would be GBs
        if not (k0 <= k < k1 or need_margin):
            continue
        pts = np.stack([X, Y, np.full_like(X, zk)], -1)
        plane = sample(flat, g, pts).reshape(model.basis.size, 3, geom.ny, geom.nx).astype(np.float32)
        if need_margin:
            margin = max(margin, mcb.displacement_margin_mm(plane))
        if k0 <= k < k1:
            out[:, :, k - k0] = plane
    if slab_z is None:
        return MotionModel(basis=model.basis, grid=fine, fields=out, reference=model.reference)
    held = dataclasses.replace(fine, nz=k1 - k0, z0_mm=float(z[k0]))
    return mcb.ModelWindow(model=MotionModel(basis=model.basis, grid=held, fields=out, reference=model.reference),
                           whole=fine, first=k0, margin_mm=margin)


def slab_projections(bary_plan) -> np.ndarray:
    """The projections a slab's barycentric plan (``MethodWeights``) gives a non-zero weight, sorted."""
    return np.unique(bary_plan.proj_index[bary_plan.weight != 0]).astype(np.int64)


#: Bytes of raw detector rows read at once for a slab's plane rows: the read (with its noise) and
#: its SSRB rows are made chunk by chunk into the slab's array, so the raw rows of a whole slab are
#: never held at once (docs/results/code-history.md "Plane rows read in chunks").
READ_CHUNK_BYTES = 128 << 20


def slab_rows(store, table, scanner, cfg, variant: str, run_z, proj_ids, knobs, rt=None) -> mcb.PlaneRows:
    """Filtered SSRB rows of ``proj_ids`` (a slab's projections) on the global planes within their
    SSRB windows and within ``knobs.margin_mm`` of the run's slices ``run_z`` (mm).

    The run's slices, not the slab's: a projection then has the same planes (``plane_first``,
    ``plane_count``) in every slab of any cut, and so the kernel's plane coordinate (relative to
    ``plane_first``, rounded in float32) and its clamp are the same bits; planes cut to a slab's
    own margin made a run cut into other slabs give other volumes. At most a whole window of planes
    a projection either way (what the memory model counts, ``memory.working_parts``).
    ``store``: the scan's projection store (``read_indices``; a noisy variant draws the run's
    noise); ``table``: the scan's whole projection table; ``cfg``: the ReconstructionConfig.
    Read and rebinned :data:`READ_CHUNK_BYTES` of raw rows at a time; a projection's rows do not
    depend on the chunk it is in (its noise is keyed by its cells, SSRB and the ramp filter work
    row by row), so the result is the same bits for any chunk size.
    """
    w = rebin.slice_window_mm(scanner, cfg.object_radius_mm)
    dz = knobs.plane_dz_mm
    lo, hi = rebin.ssrb_row_range(np.array([-w - dz, w + dz]), scanner)
    z = np.asarray(run_z, np.float64)
    z_lo, z_hi = float(z.min()) - knobs.margin_mm, float(z.max()) + knobs.margin_mm
    ids = np.asarray(proj_ids, np.int64)
    first, count = mcb.plane_range(table.source_z_mm[ids], w, dz, z_lo, z_hi)
    # page-aligned: the backprojector reads it in place on a CPU device (no device copy, mcb.MCBackprojector)
    out = aligned_zeros((ids.size, int(count.max()) if ids.size else 1, scanner.n_cols), np.float32)
    step = max(1, int(READ_CHUNK_BYTES // ((hi - lo) * scanner.n_cols * 4)))
    for i0 in range(0, ids.size, step):
        part = ids[i0:i0 + step]
        proj = store.read_indices(part, noisy=(variant == "noisy"), rows=(lo, hi))
        pr = mcb.plane_rows(proj, table, part, scanner, cfg.fbp, cfg.filter, plane_dz_mm=dz, z_lo_mm=z_lo,
                            z_hi_mm=z_hi, object_radius_mm=cfg.object_radius_mm, first_row=lo, rt=rt)
        del proj
        out[i0:i0 + part.size, :pr.rows.shape[1]] = pr.rows
    return mcb.PlaneRows(rows=out, plane_first=first.astype(np.int32), plane_count=count.astype(np.int32),
                         projection=ids, proj_z_mm=table.source_z_mm[ids], plane_dz_mm=float(dz), window_mm=float(w))


def backproject_slab(rows: mcb.PlaneRows, bary_plan, model: MotionModel | mcb.ModelWindow, table, slab_z,
                     geom: FanBeamGeometry, pairs, mu_water: float, knobs, rt=None, progress=None) -> np.ndarray:
    """Motion-compensated FBP of every target of one slab: HU (T, s, ny, nx) float32.

    ``bary_plan``: the slab's barycentric ``MethodWeights`` (S, V, T, K) (the rows and weights each
    target uses); ``model`` on ``geom``'s in-plane grid (a coarse ``geom`` for the rounds before
    the last), or a ``ModelWindow`` of it (:func:`refine` of the slab); ``pairs`` (T, 2) the
    targets (c, a); ``progress``: optional ``update(n)``, one step per target.
    """
    sp, sw = msl.plan_slots(bary_plan.proj_index, bary_plan.weight, rows)
    pb = model.basis.values(table.cardiac_phase[rows.projection], table.resp_amplitude[rows.projection])
    out = np.empty((len(pairs), len(slab_z), geom.ny, geom.nx), np.float32)
    cfg = mcb.MCConfig(taper_mm=knobs.taper_mm)
    with mcb.MCBackprojector(rows, pb, model, slab_z, geom, cfg, runtime=rt) as bp:
        for t, tgt in enumerate(pairs):
            mu = bp(sp[t], sw[t], tuple(tgt))
            out[t] = 1000.0 * (mu - mu_water) / mu_water
            if progress is not None:
                progress.update(1)
    return out
