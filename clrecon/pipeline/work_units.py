"""The work units a Dask worker computes for a run (the ``remote`` form of the stages' units,
:mod:`clrecon.pipeline.executors.dask`).

Each function is top-level (importable by name on the worker), takes small picklable
configs and paths, computes exactly what the same stage computes in one process (the same
functions on the same inputs, so the numbers are bit-identical) and returns ``(pieces,
seconds, counts)``: the pieces the stage's ``write`` takes (NumPy arrays, which the client
writes as unit files, :mod:`clrecon.core.units`, with the run's own writers), the stage
seconds and the work counts. Nothing is written here, so a worker killed mid-unit leaves
nothing behind: the scheduler gives the unit to another worker. The scan's projection table is
made on the worker (:func:`clrecon.scan.table.cached_projection_table`, once per worker process
and scan) rather than sent: it is deterministic (the client's is the same array), and a worker
that joins or restarts needs nothing but the scene.

The units:

- :func:`simulate_chunk`: one chunk of projections (one unit file of the store);
- :func:`reconstruct_slab`: one slab of slices x every method x every noise variant of one
  pitch (the slabs of :func:`clrecon.pipeline.slabs.plan_slabs`, as in one process; every
  step is per slice, per row or per target, so another cut would give the same bits too, but
  the same cut makes the same unit files);
- :func:`truth_target`: the ground truth and/or phantom truth of one target;
- :func:`mc_slab`: one slab of the ``mc`` method for one noise variant.

``CLRECON_FAULT=worker-unit:<n>`` (:mod:`clrecon.core.faults`) kills the worker process at the
start of its ``n``-th unit (the test of a worker that dies mid-unit).
"""

from __future__ import annotations

import os
import time

import numpy as np

from clrecon.core import faults
from clrecon.core.runtime import get_runtime
from clrecon.core.stage_times import StageTimes
from clrecon.evaluation import groundtruth
from clrecon.reconstruction import reconstruct
from clrecon.reconstruction.iterative import method as mcir
from clrecon.reconstruction.motion import mc_fbp
from clrecon.scan.table import cached_projection_table, usable_table
from clrecon.simulation.projector import project
from clrecon.simulation.store import ProjectionStore


def prepare_worker(device: str | None = None) -> str:
    """Build this worker process's OpenCL runtime once (the Dask worker plugin calls it at start).

    ``device`` (a ``CLRECON_DEVICE`` spec, e.g. ``nvidia:1``) overrides the worker's environment;
    without it the worker's own ``CLRECON_DEVICE`` (or PoCL) is used. Progress bars are turned
    off in workers. Returns the device description.
    """
    if device:
        os.environ["CLRECON_DEVICE"] = device
    os.environ["CLRECON_NO_PROGRESS"] = "1"
    return get_runtime().description


def simulate_chunk(scene, pitch: float, indices: np.ndarray) -> tuple[list, dict, dict]:
    """Line integrals of projections ``indices`` (increasing, (m,)) of the scan: one piece
    ``(indices, (m, R, C) float32)``."""
    faults.point("worker-unit")
    t0 = time.perf_counter()
    table = cached_projection_table(scene, pitch)
    data = np.ascontiguousarray(project(scene, table.take(np.asarray(indices, np.int64))), np.float32)
    return [(indices, data)], {"simulate": time.perf_counter() - t0}, {}


def reconstruct_slab(cfg, scene, pitch: float, cache_dir: str, plan, slices_z, targets, methods,
                     variants, sel) -> tuple[list, dict, dict]:
    """One slab of every planned method and variant, read from the finished projection store.

    ``plan`` is the client's plan of the slab's slices ``slices_z`` (mm; ``sel``: their indices
    in the run's slices), or None when the client did not keep it (over its plan budget): the
    worker then makes it with the same function (:func:`clrecon.reconstruction.reconstruct.plan`,
    deterministic). The store at ``cache_dir`` must be finished and readable from this worker (a
    shared folder on a cluster). Pieces: ``(sel, {(variant, method): (n_c', n_r', s, ny, nx)
    float32 HU})``, one per (variant, method) as in one process.
    """
    faults.point("worker-unit")
    times = StageTimes()
    table = cached_projection_table(scene, pitch)
    if plan is None:
        t0 = time.perf_counter()
        plan = reconstruct.plan(cfg, usable_table(scene, table)[0], np.asarray(slices_z), targets, methods)
        times.add("plan", time.perf_counter() - t0)
    store = ProjectionStore.open(scene, pitch, cache_dir=cache_dir, table=table, create=False)
    pieces: list = []
    try:
        reconstruct.reconstruct(cfg, store, plan, variants=variants, rt=get_runtime(), times=times,
                                on_slab=lambda zs, slab: pieces.append((sel[zs], slab)),
                                slab_size=max(1, len(plan.slices_z)))
    finally:
        store.close()
    return pieces, times.seconds, times.counts


def truth_target(gt_cfg, slices_z: np.ndarray, targets, k: int, which: tuple) -> tuple[list, dict, dict]:
    """The truths ``which`` (``"groundtruth"``, ``"phantom"``) of flat target ``k`` (cardiac-major).

    Pieces: ``(name, i, j, (nz, ny, nx) float32 HU)``; seconds: ``{"groundtruth"|"phantom_truth": s}``.
    """
    faults.point("worker-unit")
    rt = get_runtime()
    skip = set(range(len(targets.cardiac) * len(targets.resp))) - {k}
    out, seconds = [], {}
    if "groundtruth" in which:
        t0 = time.perf_counter()
        for i, j, vol in groundtruth.groundtruth_volumes(gt_cfg, slices_z, targets, rt=rt, skip=skip):
            out.append(("groundtruth", i, j, vol))
        seconds["groundtruth"] = time.perf_counter() - t0
    if "phantom" in which:
        t0 = time.perf_counter()
        for i, j, vol in groundtruth.phantom_truth_volumes(gt_cfg, slices_z, targets, rt=rt, skip=skip):
            out.append(("phantom", i, j, vol))
        seconds["phantom_truth"] = time.perf_counter() - t0
    return out, seconds, {}


def round_trip(x=None):
    """A task that does nothing (the bench's measure of the per-task overhead)."""
    return x


def mc_slab(cfg, scene, pitch: float, cache_dir: str, slices_z, a: int, b: int, targets, variant: str,
            model) -> tuple[list, dict, dict]:
    """One slab (slices ``a .. b-1`` of ``slices_z``) of the ``mc`` method for one noise variant with
    the fitted ``model`` (:class:`~clrecon.reconstruction.motion.model.MotionModel`): the body of the
    stage's unit in the run's process, :func:`clrecon.reconstruction.motion.mc_fbp.reconstruct_slab`,
    on the finished projection store at ``cache_dir``. Pieces: ``(slice indices, variant, (n_c,
    n_r, s, ny, nx) HU)``."""
    faults.point("worker-unit")
    times = StageTimes()
    table = cached_projection_table(scene, pitch)
    store = ProjectionStore.open(scene, pitch, cache_dir=cache_dir, table=table, create=False)
    try:
        scan = mc_fbp.MCScan(cfg, scene.recon.mc_knobs, scene.scanner, table, usable_table(scene, table)[0], store,
                             slices_z, targets, rt=get_runtime(), slabs=[(a, b)])
        hu = mc_fbp.reconstruct_slab(scan, a, b, variant, model, times)
    finally:
        store.close()
    return [(np.arange(a, b), variant, hu)], times.seconds, times.counts


def mcir_slab(cfg, scene, pitch: float, cache_dir: str, slices_z, a: int, b: int, targets, variant: str,
              model, start_hu=None) -> tuple[list, dict, dict]:
    """One slab (slices ``a .. b-1`` of ``slices_z``) of the ``mcir`` method for one noise variant with
    ``mc``'s ``model`` from ``start_hu`` (None: zero; else the slab's start image, (b - a, ny, nx) HU):
    the body of the stage's unit in the run's process,
    :func:`clrecon.reconstruction.iterative.method.reconstruct_slab_from_store`, on the finished
    projection store at ``cache_dir``. Pieces: ``(slice indices, variant, (n_c, n_r, s, ny, nx) HU, info)``."""
    faults.point("worker-unit")
    times = StageTimes()
    table = cached_projection_table(scene, pitch)
    store = ProjectionStore.open(scene, pitch, cache_dir=cache_dir, table=table, create=False)
    try:
        hu, info = mcir.reconstruct_slab_from_store(scene, cfg, usable_table(scene, table)[0], store, slices_z[a:b],
                                                    targets, variant, model, start_hu=start_hu, rt=get_runtime(),
                                                    times=times)
    finally:
        store.close()
    return [(np.arange(a, b), variant, hu, info)], times.seconds, times.counts
