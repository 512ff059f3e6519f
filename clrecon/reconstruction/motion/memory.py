"""How ``mc`` cuts a scan's slices into slabs, and the memory its work holds (the pre-flight's model).

:func:`plane_row_slabs` is the cut :func:`clrecon.reconstruction.motion.mc_fbp.MCScan` makes (one
work unit per slab and noise variant); :func:`working_bytes` what a run of ``mc`` at one pitch
adds to the process's memory (read by :func:`clrecon.pipeline.costs.run_costs`).
"""

from __future__ import annotations

import numpy as np

from clrecon.reconstruction import rebin, reconstruct
from clrecon.reconstruction.motion import flow, lk
from clrecon.reconstruction.motion import method as mcm
from clrecon.reconstruction.motion.confidence import (
    CHUNK_VOXELS,
    SHRINK_BYTES_PER_VOXEL,
    SHRINK_CHUNK_BYTES_PER_VOXEL,
)
from clrecon.reconstruction.motion.model import FIT_BLOCK
from clrecon.reconstruction.motion.registration import FLOW_BYTES_PER_VOXEL, registration_workers

#: A registration process's own resident set (interpreter, NumPy, SciPy, scikit-image), beside its
#: registration's ``FLOW_BYTES_PER_VOXEL`` while it registers and alone while it waits: a spawned
#: worker of the pool measured 72.6-72.8 MB after its imports and a small first registration, and
#: 72-91 MB between two registrations (what the allocator keeps of the last; the most on ``demo``'s
#: 16 x 128 x 128 grid), hence the most of those rounded up
#: (``benchmarks/studies/motion-model/registration_memory.py``; docs/results/code-history.md "One
#: Lucas-Kanade registration's memory").
WORKER_BYTES = 95_000_000
#: Bytes per (slice, view, target) of a slab's first-pass plan and slots: the plan's arrays (barycentric:
#: 3 neighbours of int64 index and float64 weight and an int8 branch, 49 bytes) and the slots' (3 of
#: int32 projection and float32 weight, 24 bytes) (:func:`plan_bytes`).
PLAN_BYTES = 73
#: Bytes per (slice, view, target) and SSRB candidate of that (slice, view) that the planning leaves
#: in the process beyond its arrays (its per-candidate work; the resident set after the plan,
#: measured on ``demo`` at pitches 0.10 and 0.02 and on ``paper-p010`` slabs of 8 and 32 slices:
#: docs/results/code-history.md "The first-pass plan's memory").
PLAN_CANDIDATE_BYTES = 10
#: Bytes the planning of a slab leaves whatever its size (the same measurements: 25-45 MB).
PLAN_FIXED_BYTES = 45_000_000
#: What ``mc``'s stage leaves in the process for the stages after it (not broken down: its kernels'
#: programs, the registration's modules and the allocator's retained blocks are the candidates), beyond the pre-flight's
#: ``PROCESS_GROWTH_BYTES``: on ``demo`` p0.10 the process held 0.368 GB after the reconstruction
#: stage and 0.495 GB when ``mcir``'s began (docs/results/iterative-study.md "7. Memory").
RESIDUE_BYTES = 127_000_000
#: Plane rows of one slab stay within this many bytes (half the reconstruction's slab budget).
ROWS_BYTES = reconstruct.SLAB_BYTES / 2
#: A slab may grow past the rows budget while its plane rows stay within this factor of its first
#: slice's alone. The rows of one slice reach ``knobs.margin_mm`` beyond it on both sides, so where
#: one slice's rows already exceed the budget (paper-p010: 1.31 GB against 1.25) each further slice
#: adds little (8 slices: 1.11x one slice's); without it every slab held one slice and the same
#: projections were read, noised and rebinned once per slice (534 s of a paper-p010 slab's 2 803 s).
GROWTH = 1.5


def _bytes_per_projection(scanner, window_mm: float, knobs) -> int:
    """Bytes of one projection's plane rows ((planes, n_cols) float32) for an SSRB window of ``window_mm``.
    ``knobs``: ``[recon.mc]`` resolved (``ReconConfig.mc_knobs``: its ``plane_dz_mm`` > 0)."""
    if not knobs.plane_dz_mm > 0:
        raise ValueError(f"plane_dz_mm = {knobs.plane_dz_mm!r}: 0 (auto) must be resolved first "
                         "(ReconConfig.mc_knobs)")
    return (int((2 * (window_mm + knobs.plane_dz_mm)) / knobs.plane_dz_mm) + 2) * scanner.n_cols * 4


def plan_bytes(slices: int, views_per_rotation: int, n_targets: int, candidates: float) -> int:
    """Modelled bytes of one slab's first-pass plan and slots while ``mc`` uses them: ``slices`` x
    ``views_per_rotation`` x ``n_targets`` elements of :data:`PLAN_BYTES` and :data:`PLAN_CANDIDATE_BYTES`
    per SSRB candidate (``candidates`` per (slice, view): the SSRB window's turns, 2 w / feed), and
    :data:`PLAN_FIXED_BYTES`."""
    return int(PLAN_FIXED_BYTES + slices * views_per_rotation * n_targets
               * (PLAN_BYTES + PLAN_CANDIDATE_BYTES * candidates))


def plane_row_slabs(table, scanner, cfg, slices_z, knobs, budget: float | None = None) -> list[tuple[int, int]]:
    """Consecutive slice ranges whose plane rows ((P, planes, C) float32) stay within ``budget``
    (default :data:`ROWS_BYTES`), or within :data:`GROWTH` times the rows of the range's first slice
    where that is more."""
    budget = ROWS_BYTES if budget is None else budget
    w = rebin.slice_window_mm(scanner, cfg.object_radius_mm)
    per_proj = _bytes_per_projection(scanner, w, knobs)
    z = np.sort(np.asarray(table.source_z_mm, np.float64))
    reach = w + knobs.margin_mm

    def rows_bytes(a, b):
        lo, hi = slices_z[a] - reach, slices_z[b - 1] + reach
        return (np.searchsorted(z, hi, side="right") - np.searchsorted(z, lo)) * per_proj

    out, a = [], 0
    for b in range(1, len(slices_z) + 1):
        if b - 1 > a and rows_bytes(a, b) > max(budget, GROWTH * rows_bytes(a, a + 1)):
            out.append((a, b - 1))
            a = b - 1
    out.append((a, len(slices_z)))
    return out


def _slab_slices(rows_per_mm: float, reach_mm: float, slice_mm: float, nz: int) -> int:
    """Slices of the largest slab :func:`plane_row_slabs` cuts: its rows (``rows_per_mm`` bytes per mm of
    z, over its slices' span plus ``reach_mm`` on both sides) within the larger of :data:`ROWS_BYTES`
    and :data:`GROWTH` times one slice's."""
    limit = max(ROWS_BYTES, GROWTH * 2 * reach_mm * rows_per_mm)
    if slice_mm <= 0:
        return nz
    return int(min(nz, max(1, 1 + (limit / rows_per_mm - 2 * reach_mm) // slice_mm)))


def slab_model_planes(s: int, slice_mm: float, margin_mm: float, nz: int) -> int:
    """Model planes :func:`method.refine` holds for a slab of ``s`` slices ``slice_mm`` apart (the model's
    planes are the slices'): its slices and ``margin_mm`` (the knob that bounds the largest z
    displacement) on both sides, with :func:`method.reach_planes`' 4 planes of trilinear neighbour
    and rounding; at most the model's ``nz``. A model that moves points further than ``margin_mm``
    in z holds more planes than this counts."""
    if slice_mm <= 0:
        return nz
    return int(min(nz, s + 2 * np.ceil(margin_mm / slice_mm) + 4))


def model_bytes(knobs, n_cardiac: int, n_resp: int, nz: int, ny: int, nx: int, *, voxel_mm: float) -> int:
    """Bytes of one fitted motion model (:class:`~clrecon.reconstruction.motion.model.MotionModel`): its
    basis fields, 3 components float32 each, on the registration grid (``nz`` planes, the
    reconstruction's ``ny`` x ``nx`` in-plane grid of ``voxel_mm`` voxels coarsened by
    :func:`method.factor_of`)."""
    f = mcm.factor_of(nx, ny, voxel_mm, knobs)
    return mcm.basis_of(knobs, n_cardiac, n_resp).size * 3 * nz * (ny // f) * (nx // f) * 4


def working_parts(scanner, window_mm: float, knobs, z_extent_mm: float, feed_mm: float, n_var: int,
                  n_cardiac: int, n_resp: int, nz: int, ny: int, nx: int,
                  max_projections: int | None = None, unit_slices: int | None = None, *,
                  voxel_mm: float) -> dict[str, int]:
    """Modelled bytes of ``mc`` at one pitch beside the process's baseline, by part of its work.

    ``voxel_mm``: the reconstruction grid's in-plane voxel (the registration grid's factor,
    :func:`method.factor_of`, depends on it where ``knobs.downsample`` is 0, auto).

    The parts in the process follow one another (the largest, with what runs beside it in other
    processes, is the method's peak, :func:`working_bytes`): ``registering`` with ``registration
    processes`` at their peak beside it, ``fit`` and ``round backprojection`` with ``idle registration
    processes`` (the pool lives until every variant's model is fitted), ``final pass`` alone.

    - ``fit`` (each round's registration and model fit, :func:`mc_fbp.fit_model`): the first pass
      on the registration grid (targets x slices x ny x nx float32, ``downsample`` times smaller
      in-plane where the registration works coarser: read back a unit of ``unit_slices`` slices at
      a time and block-averaged, so the full-resolution stack is never held), and the larger of that
      read (one unit twice: its file's bytes and its array; the whole first pass for ``unit_slices``
      None) and the rest: the previous round's images on the registration grid (rounds after the first), the
      plane rows kept for the final pass (every variant's, where kept), the registration's fields on
      its grid (``estimate.separable_parts``: n_resp + n_cardiac fields of 3 components float32, the
      respiratory averages float32, the cardiac ones float64 and their float32 copy), one
      registration's own where it runs in this process, the old and new model (2 x basis size
      fields) and the fit's float64 block (``model.FIT_BLOCK``; the targets' fields are summed a
      block at a time, ``model.fit_separable_model``); or, where larger, ``registering`` and the
      shrinking of a step's fields towards zero (``knobs.shrink``, :func:`estimate.shrunk`, after the
      step's registrations: a copy of its fields, the cardiac step's averages once more in float32,
      and one field's ``confidence.shrink_field``: ``SHRINK_BYTES_PER_VOXEL`` per voxel of the
      registration grid and ``SHRINK_CHUNK_BYTES_PER_VOXEL`` per voxel of one chunk);
    - ``registering`` (while the registration processes run): the first pass, the round's images, the
      kept rows, the registration's fields and averages, the previous round's model (the new model
      and the fit's block are made once the registrations are done);
    - ``round backprojection`` (rounds after the first, per slab): the first pass and the earlier slabs' images,
      the rows kept for other variants, the slab's first-pass plan and slots (:func:`plan_bytes`), the
      model, the slab's plane rows, and the larger of what their making and their use add: the raw
      rows being read (3 chunks of ``READ_CHUNK_BYTES``: the chunk, its covering range and its SSRB
      rows), or the model's copy on the device (host memory on a CPU driver; the rows, page-aligned,
      are read in place there) and the slab's images;
    - ``final pass`` (per slab and variant, :func:`mc_fbp.reconstruct_slab`): the plane rows (every
      variant's where kept), the plan and slots, every variant's model, the model refined to the
      reconstruction grid on the planes the slab reaches (:func:`slab_model_planes`; a copy of the
      model's own planes where the grids coincide), and the larger of the read (rows not kept) or
      the slab's output (one slab: a slab waits for the previous one's write, ``Unit.drain_first``).
      The rows and the refined planes are page-aligned and read in place on a CPU device (no device
      copy); a GPU's copies are not host memory;
    - ``registration processes`` (a scikit-image Lucas-Kanade step, ``lucas_kanade``,
      :func:`method.uses_pool`): ``FLOW_BYTES_PER_VOXEL`` per voxel of the registration grid and
      :data:`WORKER_BYTES` in each, one per core up to
      ``MAX_WORKERS``, all at their peak at once (a step's registrations start together and are of
      one size) (none below ``POOL_MIN_VOXELS``: the registrations then run in the process, and
      ``fit`` and ``registering`` hold one's ``FLOW_BYTES_PER_VOXEL``). A TV-L1 step runs in the
      process on the OpenCL device (no pool): ``fit`` holds one registration's ``flow.BYTES_PER_VOXEL``
      (an OpenCL Lucas-Kanade step, ``lucas_kanade_cl``, likewise its ``lk.BYTES_PER_VOXEL``)
      (the larger of the two where the other step runs in the process too); with no scikit-image
      step (the default: OpenCL Lucas-Kanade and TV-L1) this part is 0;
    - ``idle registration processes``: :data:`WORKER_BYTES` in each, between registrations.

    The plane rows of a slab: (planes, n_cols) float32 per projection its first-pass plan uses (those
    within the SSRB window of its slices; at most ``max_projections``, the scan's);
    the slab holds as many slices as :func:`plane_row_slabs` lets it (which counts the projections within
    ``knobs.margin_mm`` more).
    The model against measured peaks: docs/results/code-history.md "The mc working set against the
    measured peak".
    """
    w = window_mm  # the SSRB slice window (reconstruction.rebin.slice_window_mm)
    n_targets = n_cardiac * n_resp
    per_proj = _bytes_per_projection(scanner, w, knobs)  # the cut's (plane_row_slabs')
    # the rows' own: at most floor(2 (w + dz) / dz) + 1 planes a projection (backproject.plane_range)
    per_row = (int(2 * (w + knobs.plane_dz_mm) / knobs.plane_dz_mm) + 1) * scanner.n_cols * 4
    reach = w + knobs.margin_mm
    rows_per_mm = scanner.views_per_rotation * per_proj / feed_mm
    slice_mm = z_extent_mm / (nz - 1) if nz > 1 else 0.0
    s = _slab_slices(rows_per_mm, reach, slice_mm, nz)
    # the rows are those of the projections the slab's first-pass plan uses (within the SSRB window of
    # its slices), each on the planes within ``margin_mm``; the cut above counts the margin's too
    n_proj = ((s - 1) * slice_mm + 2 * w) / feed_mm * scanner.views_per_rotation
    if max_projections is not None:
        n_proj = min(n_proj, max_projections)
    rows = n_proj * per_row
    one_slab = s >= nz
    # kept for the final pass where the scan is one slab and every variant's rows fit ROWS_BYTES (mc_fbp.fit_model);
    # the modelled rows err high by up to a rotation's: where they may or may not fit, at most the budget
    rotation = scanner.views_per_rotation * per_row
    if not one_slab or n_var * max(rows - rotation, 0.0) > ROWS_BYTES:
        kept = 0.0
    else:
        kept = min(n_var * rows, ROWS_BYTES)
    f = mcm.factor_of(nx, ny, voxel_mm, knobs)
    cny, cnx = ny // f, nx // f
    n_reg = nz * cny * cnx
    vox = ny * nx
    first = n_targets * n_reg * 4  # the first pass on the registration grid
    unit = n_targets * min(nz, unit_slices or nz) * vox * 4  # one unit file of the first pass, full resolution
    read_first = 2 * unit  # its file's bytes and its array (then its float64 block means, 2 / f**2 of it)
    imgs = n_targets * n_reg * 4 if knobs.rounds > 1 else 0
    fld = 3 * n_reg * 4  # one field on the registration grid
    nb = mcm.basis_of(knobs, n_cardiac, n_resp).size  # the model's basis fields
    fit_block = (4 * n_targets + nb) * FIT_BLOCK * 8
    registration = (n_resp + n_cardiac) * fld + n_resp * n_reg * 4 + n_cardiac * n_reg * (8 + 4)
    plan = plan_bytes(s, scanner.views_per_rotation, n_targets, 2 * w / feed_mm)
    read = 3 * min(mcm.READ_CHUNK_BYTES, n_proj * scanner.n_rows * scanner.n_cols * 4)
    # a scikit-image Lucas-Kanade step runs in a pool (1 worker: in this process); a TV-L1 or OpenCL
    # Lucas-Kanade step in this process on the OpenCL device. The steps run one after the other: the
    # process holds the larger of its steps' own.
    workers = registration_workers(n_reg, available_bytes=1 << 62) if mcm.uses_pool(knobs) else 0
    in_process = {flow.TVL1Config: flow.BYTES_PER_VOXEL, lk.LKConfig: lk.BYTES_PER_VOXEL}
    own = [in_process[type(c)] for c in (mcm.flow_of(knobs, s) for s in mcm.STEPS) if type(c) in in_process]
    if mcm.uses_pool(knobs) and workers <= 1:
        own.append(FLOW_BYTES_PER_VOXEL)
    registration += max(own, default=0) * n_reg
    fit = first + max(read_first, imgs + kept + registration + 2 * nb * fld + fit_block)
    registering = first + imgs + kept + registration + nb * fld  # the new model and the block come after
    # after a step's registrations (the pool idle), estimate.shrunk: a copy of the step's fields (the
    # cardiac step also its averages' float32 copy) and one field's confidence.shrink_field at a time
    shrink = (max(n_resp * fld, n_cardiac * (fld + n_reg * 4)) + SHRINK_BYTES_PER_VOXEL * n_reg
              + SHRINK_CHUNK_BYTES_PER_VOXEL * min(n_reg, CHUNK_VOXELS)) if knobs.shrink else 0
    # while a slab's rows are read, the raw rows of the read; while it is backprojected, the model's device
    # copy and the images (never both at once). The rows are read in place on a CPU device (page-aligned,
    # backproject.MCBackprojector); the round's images, np.empty, are touched slab by slab
    slab_imgs = n_targets * s * cny * cnx * 4
    rounds = (first + max(imgs - slab_imgs, 0) + max(kept - rows, 0) + rows + plan + nb * fld
              + max(read, nb * fld + slab_imgs)) if knobs.rounds > 1 else 0
    # the model on the reconstruction grid, on the slab's planes (a copy of the model's own where f = 1)
    planes = slab_model_planes(s, slice_mm, knobs.margin_mm, nz)
    # the slab's planes on the host (page-aligned: read in place on a CPU device, no device copy)
    refined = nb * 3 * planes * vox * 4
    final = ((kept if kept else rows) + plan + n_var * nb * fld + refined
             + max(0 if kept else read, n_targets * s * vox * 4))
    pool = workers if workers > 1 else 0
    return {"fit": int(max(fit, registering + shrink)), "registering": int(registering),
            "round backprojection": int(rounds),
            "final pass": int(final),
            "registration processes": int(pool * (FLOW_BYTES_PER_VOXEL * n_reg + WORKER_BYTES)),
            "idle registration processes": int(pool * WORKER_BYTES)}


def working_bytes(scanner, window_mm: float, knobs, z_extent_mm: float, feed_mm: float, n_var: int,
                  n_cardiac: int, n_resp: int, nz: int, ny: int, nx: int, max_projections: int | None = None,
                  unit_slices: int | None = None, *, voxel_mm: float) -> int:
    """Modelled memory of ``mc`` at one pitch (bytes), beside the process's baseline: the largest
    part of :func:`working_parts` in the process with its registration processes beside it (at their
    peak beside ``registering``, idle beside ``fit`` and ``round backprojection``)."""
    p = working_parts(scanner, window_mm, knobs, z_extent_mm, feed_mm, n_var, n_cardiac, n_resp, nz, ny, nx,
                      max_projections, unit_slices, voxel_mm=voxel_mm)
    idle = p["idle registration processes"]
    return max(p["registering"] + p["registration processes"], p["fit"] + idle, p["round backprojection"] + idle,
               p["final pass"])
