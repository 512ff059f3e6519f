"""What a run does per pitch and per target, shared by the single-process path and Dask.

:mod:`clrecon.pipeline.run` and :mod:`clrecon.pipeline.distributed` must cut the same units
and write the same files, so the decisions live here once: which datasets a pitch declares
(r4dct and helical stored once, ``broadcast``), which (methods, slices) are still to do, the
slab-by-slab planning with its slab size, and taking truths from the truth cache.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from clrecon.core.progress import progress as progress_counter
from clrecon.evaluation.truth_cache import TruthCache
from clrecon.outputs.volumes import VolumeWriter, recon_path
from clrecon.reconstruction import interpolation, rebin, reconstruct
from clrecon.reconstruction.diagnostics import combine as combine_diagnostics
from clrecon.reconstruction.diagnostics import weight_diagnostics
from clrecon.scan import sampling as sampling_mod
from clrecon.scan import table as geometry

#: target grid of a method -> the target axes its volume stands for (stored at length 1)
BROADCAST = {"resp": ("cardiac",), "none": ("cardiac", "resp")}


def declare_recon(writer: VolumeWriter, pk: str, methods, variants, full_shape: tuple, n_slices: int) -> None:
    """Declare the reconstruction datasets of one pitch (r4dct once per amplitude, helical once)."""
    for m in methods:
        bc = BROADCAST.get(interpolation.METHODS[m].target_grid, ())
        for v in variants:
            writer.create(recon_path(pk, v, m), full_shape, n_slices, broadcast=bc)


def unfinished(writer: VolumeWriter, pk: str, variants, methods) -> tuple[tuple, np.ndarray]:
    """(methods with an unfinished unit, slice indices one of them lacks) of one pitch.

    A resumed run redoes only the units (slab x variant x method) not yet written: the methods
    with an unfinished unit, on the slices one of them lacks.
    """
    run_methods = tuple(m for m in methods if not all(writer.done(recon_path(pk, v, m)).all() for v in variants))
    todo = np.flatnonzero(~np.logical_and.reduce(
        [writer.done(recon_path(pk, v, m)) for v in variants for m in run_methods] or [True]))
    return run_methods, todo


def fixed_methods(methods) -> tuple:
    """Of ``methods``, those ``reconstruct`` makes with a pitch's plan: not ``cv_tuned`` (planned apart
    once its kernel is chosen), not a second-pass method (``mc``, ``mcir``)."""
    tuned = interpolation.cv_tuned.NAME
    return tuple(m for m in methods if m != tuned and m not in interpolation.second_pass_methods())


def planned_methods(methods) -> tuple:
    """The methods a pitch's plan is made for: :func:`fixed_methods`, and the first pass of a
    second-pass method (``mc``: barycentric, ``Method.first_pass``) still to do (its rows and weights,
    and the projections it reads)."""
    fixed = fixed_methods(methods)
    for m in interpolation.second_pass_methods(methods):
        if interpolation.first_pass(m) not in fixed:
            fixed += (interpolation.first_pass(m),)
    return fixed


def candidates_per_slice(table, slices_z, cfg) -> np.ndarray:
    """Projections within each slice's candidate window (|slice z - source z| <= the window), (S,) int64.

    The window is the plan's (``cfg.candidate_window_mm``, or the SSRB-exact one). A slice's
    rebinned rows are about proportional to it (the plan keeps a fixed share of the candidates
    of every view), so it scales one planned slice's sizes to every other slice.
    """
    w = cfg.candidate_window_mm or rebin.slice_window_mm(cfg.scanner, cfg.object_radius_mm)
    z = np.sort(np.asarray(table.source_z_mm, np.float64))
    zs = np.asarray(slices_z, np.float64)
    return (np.searchsorted(z, zs + w, side="right") - np.searchsorted(z, zs - w, side="left")).astype(np.int64)


def reconstruction_slabs(bytes_per_slice, budget: float = reconstruct.SLAB_BYTES) -> list[tuple[int, int]]:
    """The slices to reconstruct cut into slabs: consecutive (a, b) ranges whose summed
    ``bytes_per_slice`` (S,) (each slice's working set) stay within ``budget`` (>= 1 slice each).

    Slabs of a helical scan's end slices (few candidate turns) hold more slices than the
    interior ones, so every slab's working set, not only the first's, is within the budget.
    """
    out, a, acc = [], 0, 0.0
    for k, b in enumerate(np.asarray(bytes_per_slice, float)):
        if k > a and acc + b > budget:
            out.append((a, k))
            a, acc = k, 0.0
        acc += b
    if len(bytes_per_slice):
        out.append((a, len(bytes_per_slice)))
    return out


def plan_slabs(cfg, table, slices_z, todo, targets, methods, n_variants, progress, plan_table=None,
               volume_itemsize: int = 4):
    """Plan the slices ``todo`` slab by slab: ``(slabs, plans, needed, diagnostics_parts, plan_seconds)``.

    The slab sizes come from the plan of the densest slice (the most candidates, an interior
    slice of a helical scan), scaled to every slice by its candidate count
    (:func:`candidates_per_slice`), and are cut so that each slab's working set stays within
    :data:`clrecon.reconstruction.reconstruct.SLAB_BYTES` (:func:`reconstruction_slabs`); so a paper-scale
    scan never holds the plan of every slice at once. (The first slice is no probe: at a scan's
    end it has far fewer rows than inside; docs/results/code-history.md "Slabs sized from the densest slice".)
    Each slab is planned to find the projections the reconstruction needs (``needed``, (n,)
    bool) and its weight diagnostics; the plans are kept for the reconstruction while they
    fit in :data:`clrecon.reconstruction.reconstruct.KEEP_PLANS_BYTES` (``plans[k]`` is None
    where a slab must be planned again). ``slabs``: (a, b) ranges into ``todo``.
    ``volume_itemsize``: bytes per voxel of ``recon.volume_dtype`` (the finished slab the writer holds).
    ``plan_seconds``: method -> seconds, each slab's planning summed.
    """
    ptab = table if plan_table is None else plan_table  # the usable rows (recorded traces leave some out)
    counts = candidates_per_slice(ptab, slices_z[todo], cfg)
    dense = int(np.argmax(counts)) if todo.size else 0
    probe = reconstruct.plan(cfg, ptab, slices_z[todo[dense:dense + 1]], targets, methods)
    rows, n_t, plan_b = reconstruct.probe_sizes(probe)
    share = counts / max(int(counts[dense]) if todo.size else 1, 1)  # each slice's rows and plan vs the probe's
    per_slice = reconstruct.slab_bytes_per_slice(rows * share, cfg.scanner.n_cols, n_variants, n_t,
                                                 cfg.fbp.ny, cfg.fbp.nx, plan_b * share, volume_itemsize)
    slabs = reconstruction_slabs(per_slice)
    needed = np.zeros(len(table), bool)
    plans, parts, plan_s, kept = [], [], {}, 0
    bar = progress_counter(len(slabs), "plan", progress and len(slabs) > 1, "slabs")
    for a, b in slabs:
        p = reconstruct.plan(cfg, ptab, slices_z[todo[a:b]], targets, methods)
        for m, sec in p.method_seconds.items():
            plan_s[m] = plan_s.get(m, 0.0) + sec
        needed |= p.needed_projections(len(table))
        parts.append((weight_diagnostics(p, table, targets), b - a))
        size = reconstruct.plan_bytes(p)
        plans.append(p if kept + size <= reconstruct.KEEP_PLANS_BYTES else None)
        kept += size if plans[-1] is not None else 0
        bar.update(1)
    bar.close()
    return slabs, plans, needed, parts, plan_s


@dataclass
class PitchSlabs:
    """One pitch's slices cut into slabs, with each slab's weights (:func:`plan_pitch`): its tables,
    the slabs and their :class:`~clrecon.reconstruction.reconstruct.SlabWeights`, the projections
    they read, and what the planning records; what both paths record and reconstruct from."""

    table: object              # ProjectionTable of the scan
    plan_table: object         # its usable rows (geometry.usable_table): what every plan is made from
    excluded: dict             # reason -> views left out (lost / invalid recorded-trace stretches)
    slabs: list                # (a, b) ranges into the slices still to do
    plans: list                # per slab: its SlabWeights, or None (made again when its turn comes)
    needed: np.ndarray         # (n,) bool: projections the reconstruction reads
    diagnostics: dict          # weight diagnostics of every slab, combined
    sampling: dict             # phase-space sampling summary of the requested slices
    method_plan_seconds: dict  # method -> planning seconds
    signals_seconds: float     # building the projection table
    plan_seconds: float        # the whole planning pass (wall)


def plan_pitch(scene, cfg, pitch: float, slices_z, todo, targets, methods, n_variants, progress) -> PitchSlabs:
    """The projection table, the slab-by-slab plans (:func:`plan_slabs`), the diagnostics and the
    sampling summary of one pitch, for the slices ``todo`` of ``slices_z``."""
    t0 = time.perf_counter()
    table = geometry.cached_projection_table(scene, pitch)
    ptab, excluded = geometry.usable_table(scene, table)
    t1 = time.perf_counter()
    slabs, plans, needed, parts, plan_s = plan_slabs(cfg, table, slices_z, todo, targets, methods, n_variants,
                                                     progress, plan_table=ptab,
                                                     volume_itemsize=np.dtype(scene.recon.volume_dtype).itemsize)
    t2 = time.perf_counter()
    # the candidates the plan uses: the run's window and max_turns, not the SSRB-exact default
    sampling = sampling_mod.sampling_summary(
        ptab, reconstruct.limit_turns(rebin.candidate_groups(ptab, slices_z, scene.scanner, cfg.object_radius_mm,
                                                             cfg.candidate_window_mm), cfg.max_turns))
    return PitchSlabs(table=table, plan_table=ptab, excluded=excluded, slabs=slabs, plans=plans, needed=needed,
                     diagnostics=combine_diagnostics(parts),
                     sampling=sampling, method_plan_seconds=plan_s, signals_seconds=t1 - t0, plan_seconds=t2 - t1)


def declare_truths(writer: VolumeWriter, full_shape: tuple, n_targets: int, truths: TruthCache,
                   names=("groundtruth", "phantom")) -> None:
    """Declare the truth datasets and take every one of their units the truth cache holds."""
    for name in names:
        writer.create(name, full_shape, n_targets, blocks="targets")
    adopt_cached_truths(writer, truths, n_targets, names)


def adopt_cached_truths(writer: VolumeWriter, truths: TruthCache, n_targets: int,
                        names=("groundtruth", "phantom")) -> None:
    """Take every not-yet-done truth unit the truth cache holds (a damaged one is dropped)."""
    for name in names:
        for k in np.flatnonzero(~writer.done(name)):
            hit = truths.find(writer.target_stem(name, int(k)))
            if hit is not None and not writer.adopt_target(name, int(k), hit, truths.link):
                truths.drop(hit)
