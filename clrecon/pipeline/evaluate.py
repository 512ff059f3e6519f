"""The run's metrics stage: Table 2, the respiratory-only comparison and the motion metrics.

:func:`evaluate` reads one target's volumes at a time from the assembled volume file and feeds
one accumulator per (pitch, variant, method). At paper scale this stage reads every volume once
(paper-p010: 24 reconstructions x 50 targets of 110 x 512 x 512 float16, LZF) and took 329 s
on one core: h5py holds the GIL while it reads and decompresses, so threads do not overlap it.

**Processes.** The accumulators are independent, so the keys are split into groups and each
group beyond the first is accumulated in another process that opens the same file read-only:
the run's helper process (``pool``, lent by the executor, :mod:`clrecon.pipeline.executors.local`),
or ``processes`` spawned here (the benchmarks, the tests). Every accumulator still sees the same
arrays in the same target order, so its float64 sums, and the results, are bit for bit those of
one process (tests/evaluation/test_metrics_processes.py). A process that cannot start makes its group run
here, with the same numbers; an error inside one is raised as that error.

**Two truths.** Table 2 is against the ground-truth CT (the FBP of the frozen phantom's exact
line integrals: it shares FBP's resolution with the FBP methods). Each FOV's result also has
``mae_phantom_hu``, the MAE against the phantom itself voxelised at the target (no
reconstruction's resolution in it), so a method that is not an FBP (``mcir``'s voxel basis) is
also judged against a truth that does not favour FBP (docs/metrics.md).
"""

from __future__ import annotations

import os
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass

import h5py
import numpy as np

from clrecon.core.progress import progress as progress_counter
from clrecon.core.resources import spawn_is_safe, spawned_pool
from clrecon.evaluation import groundtruth, metrics, motion
from clrecon.outputs.rundir import REFERENCE_VOLUMES
from clrecon.outputs.volumes import pitch_key, read_volume, recon_path
from clrecon.reconstruction import interpolation, reconstruct
from clrecon.simulation.phantom_sources import phantom_from_config

#: The 5DCT methods, and those compared in the respiratory-only study (5DCT + the
#: cardiac-blind, respiratory-grid methods such as r4dct).
FIVE_D_METHODS = interpolation.five_d_methods()
#: The reference volumes' datasets: the ground-truth CT (Table 2's truth) and the phantom itself.
GROUND_TRUTH, PHANTOM_TRUTH = REFERENCE_VOLUMES
RESP_ONLY_METHODS = FIVE_D_METHODS + interpolation.resp_grid_methods()
#: Raw bytes of volumes read from which a second process pays for its start-up when none is
#: warm (the memory model's choice, :mod:`clrecon.pipeline.costs`). Spawning one and importing
#: the package costs about 2 s of CPU; the demo reads 1.3 GB in about 4 s; paper-p010 reads
#: 69 GB in 329 s. A run's warm helper process costs no start-up: used whatever the size.
PROCESS_MIN_BYTES = 4 * 1024 ** 3


def process_count(volume_bytes_read: int, warm: bool = False) -> int:
    """Processes the metrics of ``volume_bytes_read`` raw bytes are modelled to use: 2 with a warm
    helper (``warm``) or, on a machine with >= 2 cores where a child may be spawned, from
    :data:`PROCESS_MIN_BYTES`; else 1."""
    if warm:
        return 2
    return 2 if ((os.cpu_count() or 1) >= 2 and volume_bytes_read >= PROCESS_MIN_BYTES
                 and spawn_is_safe()) else 1


@dataclass
class _Context:
    """What every group's accumulation needs, built the same way in each process."""

    metrics_cfg: metrics.MetricsConfig
    masks: dict
    n_c: int
    n_r: int
    want_ro: bool
    regions: list | None
    voxel_ml: float
    want_mot: bool
    mcfg: motion.MotionConfig
    geoms: list | None

    def lv(self, vol, i, j):
        sl, sub = self.regions[i][j]  # the region's bounding box and the mask inside it
        return metrics.blood_pool_volume_ml(vol[sl], sub, self.voxel_ml)


def _context(scene, targets, slices_z, methods, phantom) -> _Context:
    metrics_cfg = metrics.MetricsConfig.from_scene(scene)
    want_ro = (any(m in methods for m in interpolation.resp_grid_methods())
               and scene.has_cardiac and scene.has_respiratory and groundtruth.offers_lv_region(phantom))
    rc = scene.recon
    if hasattr(phantom, "prefetch"):  # every target's pose in one vectorised call
        phantom.prefetch(targets.pairs[:, 0], targets.pairs[:, 1])
    x, y = reconstruct.voxel_coords(rc.nx, rc.voxel_mm), reconstruct.voxel_coords(rc.ny, rc.voxel_mm)
    voxel_ml = rc.voxel_mm ** 2 * (abs(slices_z[1] - slices_z[0]) if len(slices_z) > 1 else rc.slice_mm) / 1000.0
    # each target's LV region cropped to its bounding box: the same voxels counted (none lies outside
    # it), without a full-size mask per target (paper-p010: 50 x 29 MB in each metrics process)
    regions = ([[motion.crop_to_mask(groundtruth.lv_region_mask(phantom, c, a, x, y, slices_z))
                 for a in targets.resp] for c in targets.cardiac] if want_ro else None)
    # motion metrics (the analytic phantom knows its LV and lesion): the phantom's truth per target
    # (small: the LV region cropped) and the ground truth's own reference row
    want_mot = motion.offers_truth(phantom)
    mcfg = motion.MotionConfig.from_scene(scene, slices_z)
    geoms = ([[motion.target_geometry(phantom, c, a, mcfg) for a in targets.resp] for c in targets.cardiac]
             if want_mot else None)
    n_c, n_r = targets.shape
    return _Context(metrics_cfg, metrics.fov_masks(metrics_cfg), n_c, n_r, want_ro, regions, voxel_ml, want_mot,
                    mcfg, geoms)


def _accumulate(ctx: _Context, f, keys, bar=None) -> dict:
    """Accumulators of ``keys`` over every target, in target order, and the ground truth's reference.

    Each target's ground truth is read once for all the keys (it was read once per method,
    variant and pitch: half of the metrics' reads).
    """
    n_c, n_r = ctx.n_c, ctx.n_r
    mot_gt = motion.MotionMetrics(ctx.mcfg, n_c, n_r)
    lv_gt = np.zeros((n_c, n_r))
    acc = {k: metrics.Table2(ctx.metrics_cfg, n_c, n_r) for k in keys}
    # the same sums against the phantom itself (voxelised at the target), where the run has it
    has_phantom = PHANTOM_TRUTH in f
    acc_ph = {k: metrics.Table2(ctx.metrics_cfg, n_c, n_r) for k in keys} if has_phantom else {}
    macc = {k: motion.MotionMetrics(ctx.mcfg, n_c, n_r) for k in keys} if ctx.want_mot else {}
    ro_mae = {k: np.zeros((n_c, n_r)) for k in keys}
    ro_lv = {k: np.zeros((n_c, n_r)) for k in keys}
    scratch: dict = {}  # the Table-2 differences' arrays, kept for every key and target
    for i in range(n_c):
        for j in range(n_r):
            truth = read_volume(f, GROUND_TRUTH, (i, j))
            phantom = read_volume(f, PHANTOM_TRUTH, (i, j)) if has_phantom else None
            if ctx.want_mot:
                mot_gt.add(i, j, truth, None, ctx.geoms[i][j])
            if ctx.want_ro:
                lv_gt[i, j] = ctx.lv(truth, i, j)
            for k in keys:
                pk, v, m = k
                vol = read_volume(f, recon_path(pk, v, m), (i, j))
                acc[k].add(i, j, vol, truth, scratch)
                if has_phantom:
                    acc_ph[k].add(i, j, vol, phantom, scratch)
                if ctx.want_mot:
                    macc[k].add(i, j, vol, truth, ctx.geoms[i][j], mot_gt.lv_ml[i, j])
                if ctx.want_ro and m in RESP_ONLY_METHODS:
                    ro_mae[k][i, j] = metrics.abs_error_stats(vol, truth, ctx.masks["small"])["mae_hu"]
                    ro_lv[k][i, j] = ctx.lv(vol, i, j)
                if bar is not None:
                    bar.update(1)
            del truth, phantom
    return {"acc": acc, "acc_phantom": acc_ph, "macc": macc, "ro_mae": ro_mae, "ro_lv": ro_lv, "mot_gt": mot_gt,
            "lv_gt": lv_gt}


def _accumulate_in_process(path: str, scene, targets, slices_z, methods, keys) -> dict:
    """:func:`_accumulate` of ``keys`` in a spawned process, on the volume file at ``path``."""
    ctx = _context(scene, targets, np.asarray(slices_z), methods, phantom_from_config(scene.phantom))
    with h5py.File(path, "r") as f:
        out = _accumulate(ctx, f, keys)
    out.pop("mot_gt")
    out.pop("lv_gt")
    return out


def _groups(keys: list, n: int) -> list[list]:
    """``keys`` in ``n`` groups of (nearly) equal size, each in the original order."""
    n = max(1, min(n, len(keys)))
    return [[keys[i] for i in idx] for idx in np.array_split(np.arange(len(keys)), n) if len(idx)]


def evaluate(scene, f, targets, slices_z, pitches, variants, methods, phantom, progress: bool = False,
             info: dict | None = None, pool=None, processes: int = 1):
    """Table-2 metrics, the respiratory-only comparison and the motion metrics per pitch/variant/method.

    Reads one target's volumes at a time from the (open) volume file ``f``. Returns
    ``(metrics, respiratory_only, motion)``; ``motion[pitch][variant][method]`` is
    :meth:`clrecon.evaluation.motion.MotionMetrics.result`, with a ``groundtruth`` reference entry.
    ``phantom`` is the scene's phantom source, built once by the caller (the LV-based parts need
    one that :func:`clrecon.evaluation.groundtruth.offers_lv_region`). ``progress``: a counter
    with an ETA over the volumes read. ``info``: a dictionary that receives ``processes``, the
    number of processes the accumulation ran in (module docstring). ``pool``: the run's warm
    one-worker helper process for a second group (it is left running); else ``processes``
    groups, those beyond the first in processes spawned here.
    """
    ctx = _context(scene, targets, slices_z, methods, phantom)
    n_c, n_r = targets.shape
    keys = [(pitch_key(p), v, m) for p in pitches for v in variants for m in methods]
    groups = _groups(keys, 2 if pool is not None else max(1, int(processes)))  # the helper is one worker
    own_pool = pool is None
    if own_pool:
        pool = spawned_pool(len(groups) - 1) if len(groups) > 1 else None
    elif len(groups) < 2:
        pool = None
    futures = []
    if pool is not None:
        try:
            futures = [(g, pool.submit(_accumulate_in_process, f.filename, scene, targets, np.asarray(slices_z),
                                       tuple(methods), g)) for g in groups[1:]]
        except RuntimeError:  # the pool broke while starting: every group here
            futures = []
    here = [k for g in ([groups[0]] + ([] if futures else groups[1:])) for k in g]
    bar = progress_counter(len(keys) * n_c * n_r, "metrics", progress, "volumes")
    res = _accumulate(ctx, f, here, bar)
    processes = 1
    for g, fut in futures:
        try:
            part = fut.result()  # an error in the group's work is raised here as itself
            processes += 1
        except BrokenProcessPool:  # the process died or could not start: its group here
            part = _accumulate(ctx, f, g)
        for name in ("acc", "acc_phantom", "macc", "ro_mae", "ro_lv"):
            res[name].update(part[name])
        bar.update(len(g) * n_c * n_r)
    if pool is not None and own_pool:
        pool.shutdown(wait=True, cancel_futures=True)
    bar.close()
    if info is not None:
        info["processes"] = processes
    return _tables(ctx, res, targets, pitches, variants, methods)


def _tables(ctx: _Context, res: dict, targets, pitches, variants, methods):
    acc, macc, ro_mae, ro_lv = res["acc"], res["macc"], res["ro_mae"], res["ro_lv"]
    lv_gt = res["lv_gt"]
    mot_ref = res["mot_gt"].result()
    met: dict = {}
    resp_only: dict = {}
    mot: dict = {}
    for pitch in pitches:
        pk = pitch_key(pitch)
        met[pk] = {}
        resp_only[pk] = {}
        if ctx.want_mot:
            mot[pk] = {}
        for v in variants:
            met[pk][v] = {m: _with_phantom(acc[(pk, v, m)].result(), res["acc_phantom"].get((pk, v, m)))
                          for m in methods}
            if ctx.want_mot:
                mot[pk][v] = {"groundtruth": mot_ref}
                mot[pk][v].update({m: macc[(pk, v, m)].result() for m in methods})
            if ctx.want_ro:
                rows = []
                for i, c in enumerate(targets.cardiac):
                    row = {"cardiac_phase": c, "small_fov_mae_hu": {},
                           "lv_volume_ml": {"groundtruth": lv_gt[i].tolist()},
                           "lv_volume_spread_ml": {"groundtruth": _spread(lv_gt[i])}}
                    for m in [x for x in methods if x in RESP_ONLY_METHODS]:
                        row["small_fov_mae_hu"][m] = float(ro_mae[(pk, v, m)][i].mean())
                        row["lv_volume_ml"][m] = ro_lv[(pk, v, m)][i].tolist()
                        row["lv_volume_spread_ml"][m] = _spread(ro_lv[(pk, v, m)][i])
                    rows.append(row)
                resp_only[pk][v] = rows
    return met, resp_only, mot


def _with_phantom(table: dict, acc_phantom) -> dict:
    """Table 2's result with each FOV's ``mae_phantom_hu``: the MAE against the phantom voxelised at
    the target (:func:`clrecon.evaluation.groundtruth.phantom_truth_volumes`) beside the one against
    the ground-truth CT, where the run has the phantom truth."""
    if acc_phantom is not None:
        ph = acc_phantom.result()
        for fov in ph:
            if fov != "per_target":
                table[fov]["mae_phantom_hu"] = ph[fov]["mae_hu"]
    return table


def _spread(values) -> float:
    v = np.asarray(values, float)
    return float(v.max() - v.min()) if v.size else 0.0
