"""Stage ``truth`` (once per run, not for a measured scan): the ground truth and the phantom truth
of every target (:mod:`clrecon.evaluation.groundtruth`), each target one unit file.

They depend on the phantom, the detector, the grid and the targets, never on the projections
or the reconstruction, so an overlapping executor computes them beside the reconstruction
(``Stage.beside``); the targets an earlier run computed come from the truth cache
(:class:`clrecon.evaluation.truth_cache.TruthCache`), and an interrupted run's finished targets stay.
"""

from __future__ import annotations

import time

import numpy as np

from clrecon.core.runtime import get_runtime
from clrecon.evaluation import groundtruth
from clrecon.evaluation.truth_cache import TruthCache, truth_key
from clrecon.outputs.volumes import VolumeWriter
from clrecon.pipeline import slabs as slabs_mod
from clrecon.pipeline import work_units
from clrecon.pipeline.executors.base import Unit, Work

#: The truth datasets, in the order they are computed, and the parts they are timed under.
NAMES = {"groundtruth": "groundtruth", "phantom": "phantom_truth"}
#: The measured scan's reason for no truth and no metrics.
MEASURED = "measured scan: no ground truth exists, so no error against truth"


def skip(run) -> str | None:
    return MEASURED if run.scene.measured else None


def working_bytes(nz: int, views: int, cols: int, ny: int, nx: int) -> int:
    """Modelled memory of the truths beside the run at one target (bytes): per FBP batch of slices
    its in-plane sinograms, their filtered copy and the interleaved launch (3 x batch x V x C
    floats), and the target's volume. The model against a measured peak:
    docs/results/code-history.md "The truths' working set"."""
    b = min(nz, groundtruth.BATCH_SLICES)
    return int(3 * b * views * cols * 4 + nz * ny * nx * 4)


def _dataset(cfg, run, name: str, skip_k: set) -> Unit:
    """Every not-yet-done target of one truth dataset, in this process (one generator: the phantom posed once)."""
    make = groundtruth.groundtruth_volumes if name == "groundtruth" else groundtruth.phantom_truth_volumes

    def here(emit, times):
        t0 = time.perf_counter()
        for i, j, vol in make(cfg, run.slices_z, run.targets, rt=get_runtime(), skip=skip_k):
            emit((name, i, j, vol))
        times.add(NAMES[name], time.perf_counter() - t0)

    return Unit(here, None, f"{name} targets")


def _target(cfg, run, k: int, which: tuple) -> Unit:
    """The truths ``which`` of flat target ``k``, for a worker elsewhere."""
    def here(emit, times):
        pieces, seconds, _ = work_units.truth_target(cfg, run.slices_z, run.targets, k, which)
        for p in pieces:
            emit(p)
        for key, sec in seconds.items():
            times.add(key, sec)

    return Unit(here, lambda: (work_units.truth_target, (cfg, run.slices_z, run.targets, k, which)),
                f"truth of target {k} ({', '.join(which)})")


def all_cached(cache_path, scene, slices_z, targets) -> bool:
    """Whether the truth cache holds every target's unit of both truths for this scene, slices and
    targets (then the stage computes nothing: the pre-flight leaves its working set out). A damaged
    cached unit is found only when it is read; the stage then computes that target again."""
    truths = TruthCache(cache_path, truth_key(scene, slices_z, targets))
    n_t = int(np.prod(targets.shape))
    return all(truths.find(VolumeWriter.target_stem(name, k)) is not None for name in NAMES for k in range(n_t))


def stage(run, pitch=None) -> Work:
    run.log("ground truth")
    cfg = groundtruth.GroundTruthConfig.from_scene(run.scene)
    truths = TruthCache(run.cache_path, truth_key(run.scene, run.slices_z, run.targets))
    n_t, n_r = run.n_targets, run.targets.shape[1]
    slabs_mod.declare_truths(run.writer, run.full_shape, n_t, truths)  # taking those an earlier run computed
    done = {name: run.writer.done(name) for name in NAMES}
    if run.fine_units:
        units = [_target(cfg, run, k, which) for k in range(n_t)
                 if (which := tuple(n for n in NAMES if not done[n][k]))]
    else:
        units = [_dataset(cfg, run, name, {int(k) for k in np.flatnonzero(done[name])}) for name in NAMES
                 if not done[name].all()]

    def write(piece) -> None:
        name, i, j, vol = piece
        truths.put(run.writer.write_target(name, i, j, n_r, vol))

    todo = sum(int((~d).sum()) for d in done.values())
    return Work(units, write, progress=("ground truth", todo, "targets"))
