"""Pre-flight: before any work, the run's modelled peak memory and disk need against the machine.

:func:`check` compares :func:`clrecon.pipeline.costs.run_costs` (narrowed to the run's
methods, targets, slices and pitches) with what is free: disk at the projection-store folder
and at the run directory (``shutil.disk_usage`` of the nearest existing folder; one sum when
both are on one file system) and available memory (``MemAvailable`` of ``/proc/meminfo``, else
``os.sysconf``). Beyond it: one :class:`~clrecon.core.errors.ClreconError` line naming both
numbers and the override (``--force`` / ``force=True``).

Disk need, from the crash-safe layout (:mod:`clrecon.core.units`), walked in the order the run
writes (:func:`clrecon.pipeline.costs.disk_model`): per pitch, the compressed projection units of
the needed projections and the store assembled from them (an unfinished old ``.h5`` copied,
plus the new projections), or nothing when the existing store is complete; then the compressed
volume units, which are the result (``volumes.h5`` maps them in place: no assembly transient),
less the units and dataset files an interrupted run already left. Compressed sizes are the raw
ones over ``costs.PROJECTION_RATIO`` and ``costs.VOLUME_RATIO`` (2.0 each, below what the
paper scenes measure). On one file system the check is against the largest growth at any
instant (``disk_peak``): the store's assembly transient is over before the volumes are
written. The truth cache
(:mod:`clrecon.evaluation.truth_cache`) hard-links the truth units, so it costs nothing more
at the peak; where the cache is on another file system the link is a copy, and the two truth
volumes are counted at the cache too.
"""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

from clrecon.core.errors import ClreconError
from clrecon.core.resources import folder_bytes, format_bytes, peak_rss_bytes, rss_bytes
from clrecon.core.runtime import get_runtime
from clrecon.pipeline.costs import disk_model

#: What the process grows by after the pre-flight beyond the arrays :func:`clrecon.pipeline.costs.run_costs`
#: models: kernels built or loaded from the cache, modules imported on first use (scikit-image for
#: ``mc``'s ``lucas_kanade``, matplotlib for the report's figures), the allocator's small blocks
#: (measured on ``tiny`` with ``mc``, scikit-image's Lucas-Kanade then, warm kernel cache:
#: docs/results/code-history.md "The mc working set against the measured peak").
PROCESS_GROWTH_BYTES = 100_000_000


def free_disk_bytes(path: Path) -> int:
    """Free bytes of the file system holding ``path`` (or its nearest existing parent)."""
    p = Path(path).expanduser().absolute()
    while not p.exists() and p != p.parent:
        p = p.parent
    return int(shutil.disk_usage(p).free)


def _device(path: Path) -> int:
    p = Path(path).expanduser().absolute()
    while not p.exists() and p != p.parent:
        p = p.parent
    return os.stat(p).st_dev


def available_memory_bytes() -> int:
    """MemAvailable from /proc/meminfo; else free pages x page size."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return int(os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE"))


def _left_by_interrupted_run(out_dir: Path) -> int:
    """Bytes of volume units and dataset files an interrupted run left in ``out_dir`` (kept on resume)."""
    units_dir = Path(out_dir) / "volumes.h5.units"
    total = folder_bytes(units_dir)
    try:
        gen = json.loads((units_dir / "run.json").read_text()).get("datasets")
    except (OSError, ValueError):
        gen = None
    if gen:
        total += folder_bytes(Path(out_dir) / "volumes.d" / gen)
    return total


def needs(scene, costs: dict, cache_dir: Path, out_dir: Path) -> dict:
    """Bytes this run needs: ``memory`` (the modelled peak of the run's work, this process's resident
    set now and :data:`PROCESS_GROWTH_BYTES`, or the process's peak so far where that is more),
    ``cache_disk``, ``out_disk``."""
    import h5py

    existing: dict = {}
    for p in costs["projections_needed"]:
        h = Path(cache_dir) / f"{scene.scan_hash(p)}.h5"
        existing[p] = h.stat().st_size if h.exists() else 0
        if existing[p]:
            try:
                with h5py.File(h, "r") as f:
                    if bool(f.attrs.get("complete")):
                        existing[p] = None
            except OSError:
                pass
    disk = disk_model(costs, existing, present_out=_left_by_interrupted_run(out_dir),
                      truth_copies=_device(cache_dir) != _device(out_dir))  # the truth cache copies, not links
    # the model is what the run's arrays add to the process; the process itself (interpreter, libraries,
    # the OpenCL driver: 0.2-0.4 GiB by driver, most of a small run's peak) is measured now, after the
    # imports and the OpenCL runtime (docs/measured-data.md), and grows by PROCESS_GROWTH_BYTES later;
    # a peak the process already reached (the driver's probe) counts where it is larger
    memory = max(peak_rss_bytes(), costs["peak_memory_bytes"] + rss_bytes() + PROCESS_GROWTH_BYTES)
    return {"memory": memory, **disk}


def check_device(costs: dict, max_alloc_bytes: int, device: str = "the OpenCL device") -> None:
    """Raise a one-line :class:`ClreconError` when one of the run's device buffers that cannot be split
    (:func:`clrecon.pipeline.costs.device_buffers`) is above the device's largest allocation."""
    for what, b in sorted(costs.get("device_buffers", {}).items(), key=lambda kv: -kv[1]):
        if b > max_alloc_bytes:
            raise ClreconError(f"pre-flight: {what} need one device buffer of {format_bytes(b)}, above the "
                               f"largest allocation of {device} ({format_bytes(max_alloc_bytes)}, "
                               f"CL_DEVICE_MAX_MEM_ALLOC_SIZE); "
                               f"use a smaller recon.nx/ny, fewer detector columns or views, or a device with a "
                               f"larger allocation limit (CLRECON_DEVICE)")


def check(scene, costs: dict, cache_dir: Path, out_dir: Path, rt=None) -> dict:
    """Raise a one-line :class:`ClreconError` when the run will not fit; returns the needs.

    ``rt``: the OpenCL runtime whose device buffers the run uses (default: the process's,
    :func:`clrecon.core.runtime.get_runtime`)."""
    if rt is None:
        rt = get_runtime()
    check_device(costs, rt.max_alloc_bytes, repr(rt.device.name))
    need = needs(scene, costs, cache_dir, out_dir)
    force = "pass --force (clrecon run) or force=True (clrecon.api.run) to run anyway"
    mem = available_memory_bytes()
    if need["memory"] > mem:
        raise ClreconError(f"pre-flight: the run needs about {format_bytes(need['memory'])} of memory (modelled "
                           f"peak), the machine has {format_bytes(mem)} available; narrow --slices/--targets/--methods "
                           f"or {force}")
    disks = [("the projection store", cache_dir, need["cache_disk"]), ("the run directory", out_dir, need["out_disk"])]
    if _device(cache_dir) == _device(out_dir):
        disks = [(f"the projection store and the run directory ({cache_dir})", out_dir, need["disk_peak"])]
    for what, path, b in disks:
        free = free_disk_bytes(path)
        if b > free:
            raise ClreconError(f"pre-flight: {what} needs about {format_bytes(b)} of disk, {path} has "
                               f"{format_bytes(free)} free; free some space, narrow the run or {force}")
    return need
