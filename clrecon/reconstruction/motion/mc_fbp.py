"""The ``mc`` method on one scan (pitch) and noise variant: a motion model fitted in rounds, then
motion-compensated FBP slab by slab (docs/motion-model.md).

One entry point, :func:`reconstruct_mc`: the first pass (the volumes of the method the registry
names as ``mc``'s ``first_pass``, barycentric) in, ``mc``'s volumes out. Its two halves are
public because a pipeline runs them apart: :func:`fit_model` (the round loop; the stage saves
its model so that a resumed run does not register again) and :func:`reconstruct_slab` (the
final pass of one slab: the one body of the stage's work unit, in the run's process and on a
Dask worker, :func:`clrecon.pipeline.work_units.mc_slab`). :class:`MCScan` holds what they
share: the scan's tables, store, slices and targets, its slab cut
(:func:`clrecon.reconstruction.motion.memory.plane_row_slabs`), the registration's process pool,
and the plane rows of the last round kept for the final pass.

The steps themselves (registration, fit, plane rows, the kernel) are
:mod:`clrecon.reconstruction.motion.method`'s. Shapes: first pass and volumes (n_c, n_r, S, ny,
nx) HU float32, one slab's (n_c, n_r, s, ny, nx).
"""

from __future__ import annotations

import time

import numpy as np

from clrecon.core.progress import progress as progress_counter
from clrecon.core.resources import rss_mark, spawn_is_safe, spawned_pool
from clrecon.reconstruction import interpolation, reconstruct
from clrecon.reconstruction.motion import memory
from clrecon.reconstruction.motion import method as mcm
from clrecon.reconstruction.motion.backproject import PlaneRows
from clrecon.reconstruction.motion.model import FieldGrid, MotionModel
from clrecon.reconstruction.motion.registration import registration_workers

#: The method this module makes (its registry entry: :mod:`clrecon.reconstruction.interpolation.mc`).
NAME = "mc"
#: The method whose volumes ``mc`` starts from and whose plan (rows and weights) it backprojects.
FIRST_PASS = interpolation.first_pass(NAME)
#: Runs whose slices span less z than this (mm) are warned: on ``demo`` the registration of a run
#: of 16 mm erred by as much as the motion, of 32 mm by 0.66 of it in the heart, of 48-64 mm by
#: 0.5-0.64 (docs/results/mc-run.md "Without retuning: a paper-p010 slab").
THIN_Z_MM = 30.0


def z_extent_mm(slices_z) -> float:
    """The z the run's slices cover (mm): their span plus one slice spacing (0 for one slice)."""
    z = np.sort(np.asarray(slices_z, np.float64))
    return float(z[-1] - z[0] + np.median(np.diff(z))) if z.size > 1 else 0.0


def thin_warning(label: str, slices_z) -> str | None:
    """One line for a run too thin in z to register its motion (:data:`THIN_Z_MM`), else None;
    ``label`` (e.g. the pitch key) starts the line."""
    ext = z_extent_mm(slices_z)
    if ext >= THIN_Z_MM:
        return None
    return (f"[{label}] mc: warning: the run's slices cover {ext:g} mm of z; below about {THIN_Z_MM:g} mm the "
            f"registration does not recover the motion (its model errs by as much as the motion), so mc's "
            f"volumes are not a measure of motion: run {THIN_Z_MM:g} mm or more of slices "
            f"(docs/motion-model.md \"Slab ends\")")


class MCScan:
    """One scan as ``mc`` sees it: what :func:`fit_model` and :func:`reconstruct_slab` share.

    ``cfg``: the :class:`~clrecon.reconstruction.reconstruct.ReconstructionConfig`; ``knobs``: the
    scene's ``[recon.mc]``; ``table``: the scan's whole projection table, ``plan_table`` its
    usable rows (what the first pass planned with); ``store``: the projection store
    (``read_indices``; a noisy variant draws the run's noise); ``slices_z`` (S,) mm; ``targets``:
    the run's ``Targets``; ``slabs``: the slice ranges ``(a, b)`` (default
    :func:`memory.plane_row_slabs`); ``n_variants``: the noise variants the run makes (the rows kept
    for the final pass of each must fit ``memory.ROWS_BYTES`` together). Holds the registration's
    process pool once made (:meth:`close` ends it; also a context manager) and the plane rows of
    the last round's slab where they are kept for the final pass.
    """

    def __init__(self, cfg, knobs, scanner, table, plan_table, store, slices_z, targets, *, rt=None, slabs=None,
                 n_variants: int = 1):
        self.cfg, self.knobs, self.scanner = cfg, knobs, scanner
        self.table, self.plan_table, self.store = table, plan_table, store
        self.slices_z = np.asarray(slices_z)
        self.targets, self.rt, self.n_variants = targets, rt, int(n_variants)
        self.slabs = (list(slabs) if slabs is not None
                      else memory.plane_row_slabs(plan_table, scanner, cfg, self.slices_z, knobs))
        self.pairs = targets.pairs
        self.shape = targets.shape
        self.f = mcm.factor(cfg.fbp, knobs)
        self.coarse = mcm.coarse_geometry(cfg.fbp, self.f)
        self.ref_ij = mcm.reference_index(targets.cardiac, targets.resp, knobs)
        self.kept: dict = {}  # (a, b, variant) -> plane rows of the last round's slab, for the final pass
        self.workers = 1  # registrations at once (registration_workers), set when the pool is made
        self._pool = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def pool(self, grid: FieldGrid):
        """The process pool the registrations run in (made once per scan), or None: one core, a
        script without a ``__main__`` guard (:func:`spawn_is_safe`), memory for one only, or no step
        registering with scikit-image's Lucas-Kanade (:func:`method.uses_pool`; the default's steps run
        in the process)."""
        if not mcm.uses_pool(self.knobs):
            return None
        if self._pool is None:
            n = registration_workers(grid.nx * grid.ny * grid.nz)
            self._pool = (spawned_pool(n) if n > 1 and spawn_is_safe() else None) or False
            self.workers = n if self._pool else 1
        return self._pool or None

    def close(self) -> None:
        """End the registration's process pool (a later registration makes another)."""
        if self._pool:
            self._pool.shutdown()
        self._pool = None

    def first_pass_plan(self, a: int, b: int):
        """The first pass's ``MethodPlan`` of slices ``a .. b-1``: the rows and weights ``mc`` moves."""
        p = reconstruct.plan(self.cfg, self.plan_table, self.slices_z[a:b], self.targets, (FIRST_PASS,))
        return p.methods[FIRST_PASS]

    def rows(self, a: int, b: int, variant: str, plan) -> PlaneRows:
        """The plane rows of slices ``a .. b-1`` that ``plan`` (:meth:`first_pass_plan`) uses: kept
        from the last round (and handed over once), or read, noised and rebinned now, on the planes
        within the margin of the run's slices (:func:`method.slab_rows`: the same for any cut)."""
        kept = self.kept.pop((a, b, variant), None)
        if kept is not None:
            return kept
        return mcm.slab_rows(self.store, self.table, self.scanner, self.cfg, variant, self.slices_z,
                             mcm.slab_projections(plan), self.knobs, rt=self.rt)


def fit_steps(scan: MCScan) -> int:
    """The steps :func:`fit_model` counts: one per registration and one per target of each slab
    backprojected in the rounds after the first."""
    nc, nr = scan.shape
    return scan.knobs.rounds * ((nc - 1) + (nr - 1)) + (scan.knobs.rounds - 1) * len(scan.pairs) * len(scan.slabs)


def fit_model(scan: MCScan, first_pass, variant: str, *, log=None, progress: bool = False,
              label: str = "") -> tuple[MotionModel, dict]:
    """The motion model of one noise variant on the registration's grid, after ``knobs.rounds`` rounds.

    Round 1 registers ``first_pass`` ((n_c, n_r, S, ny, nx) HU on the reconstruction grid, or
    broadcastable to it: downsampled ``knobs.downsample`` times in-plane here; or a callable
    ``read(reduce)`` that returns it with ``reduce`` applied to each block of slices as it is read,
    so that where the registration works coarser the full-resolution first pass is never held
    whole, e.g. ``VolumeWriter.read``'s ``reduce``) and fits the
    (c, a) model (:func:`method.register`); each further round backprojects every target of every
    slab with that model on the coarse grid (:func:`method.backproject_slab`), registers those
    images and fits again. Where the scan is one slab and every variant's rows fit
    ``memory.ROWS_BYTES``, the last round's rows are kept for :func:`reconstruct_slab`.
    ``log(line)``: one line per round; ``progress``: show a counter of :func:`fit_steps` steps
    labelled ``label``. Returns (model, info: per-round seconds and fit residuals, the reference
    state, each step's registration, the registration grid and workers, the basis, the total seconds).
    """
    t_start = time.perf_counter()
    rss_mark(f"mc {variant}: before the fit")
    knobs, cfg = scan.knobs, scan.cfg
    say = log or (lambda line: None)
    nc, nr = scan.shape
    grid = mcm.field_grid(scan.coarse, scan.slices_z)
    if callable(first_pass):
        first = first_pass(lambda v: mcm.downsample(v, scan.f))
    else:
        first = mcm.downsample(first_pass, scan.f)
    first = np.broadcast_to(first, (nc, nr) + first.shape[2:])
    say(f"registering {variant} (round 1 of {knobs.rounds}, "
        f"{nc - 1 + nr - 1} registrations on {grid.nx} x {grid.ny} x {grid.nz})")
    bar = progress_counter(fit_steps(scan), f"mc model {label} {variant}", progress, "steps")
    pool = scan.pool(grid)
    model, info = mcm.register(first, scan.ref_ij, grid, scan.pairs, knobs, progress=bar, pool=pool)
    rss_mark(f"mc {variant}: round 1's registration and fit")
    rounds = [info]
    keep = len(scan.slabs) == 1
    for r in range(2, knobs.rounds + 1):
        t0 = time.perf_counter()
        imgs = np.empty((len(scan.pairs), len(scan.slices_z), scan.coarse.ny, scan.coarse.nx), np.float32)
        for a, b in scan.slabs:
            plan = scan.first_pass_plan(a, b)
            rows = scan.rows(a, b, variant, plan)
            imgs[:, a:b] = mcm.backproject_slab(rows, plan, model, scan.table, scan.slices_z[a:b], scan.coarse,
                                                scan.pairs, cfg.mu_water_per_mm, knobs, rt=scan.rt, progress=bar)
            if keep and rows.rows.nbytes * scan.n_variants <= memory.ROWS_BYTES:
                scan.kept[(a, b, variant)] = rows  # the final pass's rows (one slab, every variant's within budget)
            rss_mark(f"mc {variant}: round {r}'s backprojection of slices {a}..{b - 1} "
                     f"(rows {rows.rows.nbytes / 1e9:.3f} GB)")
            # let go of the slab's rows and plan before the next slab's are made and through the round's
            # registrations (memory.working_parts counts one slab's); kept rows stay in scan.kept
            del rows, plan
        t_bp = time.perf_counter() - t0
        say(f"registering {variant} (round {r} of {knobs.rounds})")
        model, info = mcm.register(imgs.reshape((nc, nr) + imgs.shape[1:]), scan.ref_ij, grid, scan.pairs, knobs,
                                   progress=bar, pool=pool)
        rss_mark(f"mc {variant}: round {r}'s registration and fit")
        rounds.append(dict(info, backproject_seconds=t_bp))
    bar.close()
    info = {"rounds": [{k: round(v, 3) for k, v in x.items()} for x in rounds],
            "reference": list(model.reference), "registrations": mcm.registrations(knobs),
            "registration_grid": [grid.nz, grid.ny, grid.nx],
            "registration_workers": scan.workers,
            "basis": list(model.basis.names),
            "seconds": round(time.perf_counter() - t_start, 3)}
    return model, info


def model_of(scan: MCScan, fields, grid: FieldGrid, reference) -> MotionModel:
    """A model of ``scan``'s basis (:func:`method.basis_of` of its knobs and targets) from stored ``fields``."""
    return MotionModel(basis=mcm.basis_of(scan.knobs, *scan.shape), grid=grid, fields=np.asarray(fields, np.float32),
                       reference=tuple(reference))


def reconstruct_slab(scan: MCScan, a: int, b: int, variant: str, model: MotionModel, times=None,
                     progress=None) -> np.ndarray:
    """``mc``'s volumes of slices ``a .. b-1`` for one variant: (n_c, n_r, b - a, ny, nx) HU float32.

    The slab's first-pass plan, its plane rows (:meth:`MCScan.rows`), ``model`` refined to the
    reconstruction grid on the planes the slab's voxels reach (:func:`method.refine`: the same bits
    as every plane) and the motion-compensated backprojection of every target. ``times``: optional
    ``StageTimes`` given ``plane_rows``, ``mc_backproject`` and ``method:mc:<variant>`` seconds;
    ``progress``: optional ``update(n)`` counter, one step per target backprojected.
    The same bits for any slab cut and in any process: a projection's plane rows are on the planes
    within the margin of the run's slices, whatever the slab (:meth:`MCScan.rows`).
    """
    t0 = time.perf_counter()
    plan = scan.first_pass_plan(a, b)
    rows = scan.rows(a, b, variant, plan)
    t1 = time.perf_counter()
    geom = scan.cfg.fbp
    slab_z = scan.slices_z[a:b]
    refined = mcm.refine(model, geom, slab_z, scan.pairs)  # the planes the slab reaches
    hu = mcm.backproject_slab(rows, plan, refined, scan.table, slab_z, geom, scan.pairs,
                              scan.cfg.mu_water_per_mm, scan.knobs, rt=scan.rt, progress=progress)
    t2 = time.perf_counter()
    if times is not None:
        times.add("plane_rows", t1 - t0)
        times.add("mc_backproject", t2 - t1)
        times.add(f"method:{NAME}:{variant}", t2 - t0)
    rss_mark(f"mc {variant}: final pass of slices {a}..{b - 1} (rows {rows.rows.nbytes / 1e9:.3f} GB)")
    return hu.reshape(scan.shape + hu.shape[1:])


def reconstruct_mc(scan: MCScan, first_pass, variant: str, *, model: MotionModel | None = None, log=None,
                   progress: bool = False) -> tuple[np.ndarray, MotionModel, dict]:
    """``mc``'s volumes of every slice of ``scan`` for one noise variant: (n_c, n_r, S, ny, nx) HU float32.

    ``first_pass``: the :data:`FIRST_PASS` method's volumes of the variant (n_c, n_r, S, ny, nx) HU;
    ``model``: a model fitted before (then ``first_pass`` is not read), else :func:`fit_model`
    fits it (``log``, ``progress`` as there). Returns (volumes, model, info: :func:`fit_model`'s,
    or ``{}`` for a model given).
    """
    info: dict = {}
    if model is None:
        try:
            model, info = fit_model(scan, first_pass, variant, log=log, progress=progress)
        finally:
            scan.close()
    out = np.empty(scan.shape + (len(scan.slices_z), scan.cfg.fbp.ny, scan.cfg.fbp.nx), np.float32)
    for a, b in scan.slabs:
        out[:, :, a:b] = reconstruct_slab(scan, a, b, variant, model)
    return out, model, info
