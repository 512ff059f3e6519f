"""Stage ``mc_reconstruct`` (per pitch, with the ``mc`` method): motion-compensated FBP with a
registered (c, a) motion model, made from the barycentric first pass (docs/motion-model.md).

Per noise variant: the first pass ``recon/<pitch>/<variant>/barycentric`` is read back from the
writer's unit files, registered and fitted (``recon.mc.rounds`` rounds, each after the first on
the previous round's motion-compensated images, on a grid ``recon.mc.downsample`` times coarser
in-plane: :mod:`clrecon.reconstruction.motion.method`), and the model's basis fields are saved
as their own unit (``volumes.h5.units/mc/``, atomic, checksummed): a resumed run loads it
instead of registering again. Then one unit per (slab, variant): the slab's barycentric plan,
its plane rows (SSRB of every projection it uses onto global z planes, flat or cylindrical
detector, flying focal spot), and the kernel per target, written as
``recon/<pitch>/<variant>/mc`` one unit file per slab (resumable after kill -9 as
``reconstruct``'s). Timed as ``registration`` (with the rounds' backprojections), ``plane_rows``,
``mc_backproject``, ``write_volumes``; ``results.json["stages"]["registration"]["mc"]`` holds the
model's reference state, fit residuals and (for a simulated scan) its error against the
phantom's own motion.
"""

from __future__ import annotations

import time

import numpy as np

from clrecon.core import units
from clrecon.core.errors import ClreconError
from clrecon.core.progress import progress as progress_counter
from clrecon.core.resources import spawn_is_safe, spawned_pool
from clrecon.evaluation.motion_model import registration_error
from clrecon.outputs.volumes import pitch_key, recon_path
from clrecon.pipeline import work_units
from clrecon.pipeline.executors.base import Idle, Unit, Work
from clrecon.reconstruction import interpolation, rebin, reconstruct
from clrecon.reconstruction.motion import method as mcm
from clrecon.reconstruction.motion.model import FieldGrid, MotionModel
from clrecon.reconstruction.motion.registration import FLOW_BYTES_PER_VOXEL, registration_workers
from clrecon.scan import table as geometry

#: The method this stage makes.
NAME = "mc"
#: Plane rows of one slab stay within this many bytes (half the reconstruction's slab budget).
ROWS_BYTES = reconstruct.SLAB_BYTES / 2
FAULT = "mc-model"
#: Runs whose slices span less z than this (mm) are warned: on ``demo`` the registration of a run
#: of 16 mm erred by as much as the motion, of 32 mm by 0.66 of it in the heart, of 48-64 mm by
#: 0.5-0.64 (docs/motion-model.md "Without retuning: a paper-p010 slab").
THIN_Z_MM = 30.0


def z_extent_mm(slices_z) -> float:
    """The z the run's slices cover (mm): their span plus one slice spacing (0 for one slice)."""
    z = np.sort(np.asarray(slices_z, np.float64))
    return float(z[-1] - z[0] + np.median(np.diff(z))) if z.size > 1 else 0.0


def thin_warning(pk: str, slices_z) -> str | None:
    """One line for a run too thin in z to register its motion (:data:`THIN_Z_MM`), else None."""
    ext = z_extent_mm(slices_z)
    if ext >= THIN_Z_MM:
        return None
    return (f"[{pk}] mc: warning: the run's slices cover {ext:g} mm of z; below about {THIN_Z_MM:g} mm the "
            f"registration does not recover the motion (its model errs by as much as the motion), so mc's "
            f"volumes are not a measure of motion: run {THIN_Z_MM:g} mm or more of slices "
            f"(docs/motion-model.md \"Slab ends\")")


def skip(run) -> str | None:
    return None if NAME in run.methods else "the mc method is not asked for (recon.methods)"


#: A slab may grow past the rows budget while its plane rows stay within this factor of its first
#: slice's alone. The rows of one slice reach ``knobs.margin_mm`` beyond it on both sides, so where
#: one slice's rows already exceed the budget (paper-p010: 1.31 GB against 1.25) each further slice
#: adds little (8 slices: 1.11x one slice's); without it every slab held one slice and the same
#: projections were read, noised and rebinned once per slice (534 s of a paper-p010 slab's 2 803 s).
GROWTH = 1.5


def plane_row_slabs(table, scanner, cfg, slices_z, knobs, budget: float = ROWS_BYTES) -> list[tuple[int, int]]:
    """The run's slices cut into mc slabs: consecutive slice ranges whose plane rows ((P, planes, C)
    float32) stay within ``budget``, or within :data:`GROWTH` times the rows of the range's first
    slice where that is more."""
    w = rebin.slice_window_mm(scanner, cfg.object_radius_mm)
    per_proj = (int((2 * (w + knobs.plane_dz_mm)) / knobs.plane_dz_mm) + 2) * scanner.n_cols * 4
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


def working_bytes(scanner, window_mm: float, knobs, z_extent_mm: float, feed_mm: float, n_var: int,
                  n_targets: int, nz: int, ny: int, nx: int) -> int:
    """Modelled memory of the stage at one pitch (bytes), beside the process's baseline.

    The plane rows of a slab ((planes, n_cols) float32 per projection it uses, the projections
    within the SSRB window plus ``knobs.margin_mm`` of its slices: at most ``ROWS_BYTES``, or
    ``GROWTH`` times one slice's where that is more), kept for
    the final pass for every noise variant (when they fit ``ROWS_BYTES``) plus one variant's copy on
    the device (host memory on a CPU driver); the first pass of one variant, the previous round's
    images and the slab's output, float32 (3 x targets x slices x ny x nx); the registration's
    fields (13 registrations and the model's basis, 3 components each, at the registration's
    grid); the raw rows read for the plane rows (``method.READ_CHUNK_BYTES`` at a time, with their
    covering range and SSRB rows: 3 chunks); the registration processes' working sets
    (``FLOW_BYTES_PER_VOXEL`` per voxel each, one per core up to ``MAX_WORKERS``: 2 x 79 MB on
    ``demo`` with 2 cores, in processes of their own). ``demo`` (pitch 0.02, 2 variants): 1.36 GB
    without the last two, on top of the run's 1.44 GB modelled before it
    (:func:`clrecon.pipeline.costs.run_costs`): 2.81 GB against a peak RSS of 2.65 GB measured
    (2026-12-06, the whole run, Intel's runtime; 1.25 GB without ``mc``)."""
    w = window_mm  # the SSRB slice window (reconstruction.rebin.slice_window_mm)
    per_proj = (int((2 * (w + knobs.plane_dz_mm)) / knobs.plane_dz_mm) + 2) * scanner.n_cols * 4
    n_proj = (z_extent_mm + 2 * (w + knobs.margin_mm)) / feed_mm * scanner.views_per_rotation
    one_slice = 2 * (w + knobs.margin_mm) / feed_mm * scanner.views_per_rotation * per_proj
    rows = min(max(ROWS_BYTES, GROWTH * one_slice), n_proj * per_proj)  # plane_row_slabs' limit
    kept = n_var * rows if n_var * rows <= ROWS_BYTES else 0.0
    f = max(1, knobs.downsample)
    volumes = 3 * n_targets * nz * ny * nx * 4
    n_reg = nz * (ny // f) * (nx // f)
    fields = (13 + 1 + 2 * knobs.resp_degree + 2 * knobs.cardiac_harmonics) * 3 * n_reg * 4
    # the registration processes (one per core, at most MAX_WORKERS: the most the run starts)
    flows = registration_workers(n_reg, available_bytes=1 << 62) * FLOW_BYTES_PER_VOXEL * n_reg
    # the raw detector rows a slab's plane rows are made from, one chunk at a time, with the chunk's
    # covering range of the store and its SSRB rows (measured on a paper-p010 slice: 2.9 chunks of 128 MiB)
    read = 3 * min(mcm.READ_CHUNK_BYTES, n_proj * scanner.n_rows * scanner.n_cols * 4)
    return int(kept + rows + volumes + fields + flows + read)


def _model_path(run, pk: str, variant: str):
    folder = run.writer.units_dir / "mc"
    hits = sorted(folder.glob(f"model~{pk}~{variant}.*{units.SUFFIX}")) if folder.is_dir() else []
    return folder, hits


def _load_model(run, pk: str, variant: str) -> tuple[MotionModel, dict] | None:
    folder, hits = _model_path(run, pk, variant)
    for p in hits:
        try:
            arrays, meta = units.read_unit(p)
        except (OSError, ValueError, KeyError, EOFError):
            p.unlink(missing_ok=True)  # damaged: registered again
            continue
        model = MotionModel(basis=mcm.basis_of(run.scene.recon.mc, *run.targets.shape), grid=FieldGrid(**meta["grid"]),
                            fields=arrays["fields"], reference=tuple(meta["reference"]))
        return model, meta["info"]
    return None


def _save_model(run, pk: str, variant: str, model: MotionModel, info: dict) -> None:
    folder, _ = _model_path(run, pk, variant)
    g = model.grid
    meta = {"grid": {"nx": g.nx, "ny": g.ny, "nz": g.nz, "voxel_mm": g.voxel_mm, "z0_mm": g.z0_mm, "dz_mm": g.dz_mm},
            "reference": list(model.reference), "info": info}
    units.write_unit(folder, f"model~{pk}~{variant}", {"fields": np.ascontiguousarray(model.fields)}, meta, FAULT)


class _Pitch:
    """What every unit of one pitch shares: tables, slabs, models, the last plane rows built."""

    def __init__(self, run, pitch, plan, store):
        self.run, self.pitch, self.pk = run, pitch, pitch_key(pitch)
        self.knobs, self.cfg = run.scene.recon.mc, run.recon_cfg
        if plan.pp is not None:
            self.table, self.ptab = plan.pp.table, plan.pp.plan_table
        else:
            self.table = geometry.cached_projection_table(run.scene, pitch)
            self.ptab = geometry.usable_table(run.scene, self.table)[0]
        self.store = store
        self.slabs = plane_row_slabs(self.ptab, run.scene.scanner, self.cfg, run.slices_z, self.knobs)
        self.pairs = run.targets.pairs
        self.shape = run.targets.shape
        self.f = mcm.factor(self.cfg.fbp, self.knobs)
        self.coarse = mcm.coarse_geometry(self.cfg.fbp, self.f)
        self.ref_ij = mcm.reference_index(run.targets.cardiac, run.targets.resp, self.knobs)
        self.kept: dict = {}  # (slab, variant) -> plane rows of the last round's slab, for the final pass
        self.seconds: dict = {}  # variant -> the model's seconds
        self.workers = 1  # registrations at once (registration_workers), set when a model is registered
        self._pool = None

    def pool(self, grid: FieldGrid):
        """The process pool the registrations run in (made once per pitch), or None: one core, a
        script without a ``__main__`` guard (:func:`spawn_is_safe`), or memory for one only."""
        if self._pool is None:
            n = registration_workers(grid.nx * grid.ny * grid.nz)
            self._pool = (spawned_pool(n) if n > 1 and spawn_is_safe() else None) or False
            self.workers = n if self._pool else 1
        return self._pool or None

    def close(self) -> None:
        if self._pool:
            self._pool.shutdown()
        self._pool = None

    def bary_plan(self, a: int, b: int):
        p = reconstruct.plan(self.cfg, self.ptab, self.run.slices_z[a:b], self.run.targets, ("barycentric",))
        return p.methods["barycentric"]

    def rows(self, k: int, variant: str, bary):
        a, b = self.slabs[k]
        kept = self.kept.pop((k, variant), None)
        if kept is not None:
            return kept
        return mcm.slab_rows(self.store, self.table, self.run.scene.scanner, self.cfg, variant,
                             self.run.slices_z[a:b], mcm.slab_projections(bary), self.knobs, rt=self.run.rt)

    def model(self, variant: str) -> MotionModel:
        """The final round's model of ``variant`` on the coarse grid: loaded, or registered and saved."""
        run, knobs, clock = self.run, self.knobs, self.run.clock
        got = _load_model(run, self.pk, variant)
        if got is not None:
            run.log(f"[{self.pk}] mc: motion model of {variant} loaded (resumed run)")
            self._note(variant, got[1])
            return got[0]
        t_start = time.perf_counter()
        nc, nr = self.shape
        grid = mcm.field_grid(self.coarse, run.slices_z)
        first = mcm.downsample(run.writer.read(recon_path(self.pk, variant, "barycentric")), self.f)
        first = np.broadcast_to(first, (nc, nr) + first.shape[2:])
        warning = thin_warning(self.pk, run.slices_z)
        if warning:
            run.log(warning)
        run.log(f"[{self.pk}] mc: registering {variant} (round 1 of {knobs.rounds}, "
                f"{nc - 1 + nr - 1} registrations on {grid.nx} x {grid.ny} x {grid.nz})")
        n_reg = (nc - 1) + (nr - 1)
        bar = progress_counter(knobs.rounds * n_reg + (knobs.rounds - 1) * len(self.pairs) * len(self.slabs),
                               f"mc model {self.pk} {variant}", run.progress, "steps")
        pool = self.pool(grid)
        model, info = mcm.register(first, self.ref_ij, grid, self.pairs, knobs, progress=bar, pool=pool)
        rounds = [info]
        for r in range(2, knobs.rounds + 1):
            t0 = time.perf_counter()
            imgs = np.empty((len(self.pairs), len(run.slices_z), self.coarse.ny, self.coarse.nx), np.float32)
            for k, (a, b) in enumerate(self.slabs):
                bary = self.bary_plan(a, b)
                rows = self.rows(k, variant, bary)
                imgs[:, a:b] = mcm.backproject_slab(rows, bary, model, self.table, run.slices_z[a:b], self.coarse,
                                                    self.pairs, self.cfg.mu_water_per_mm, knobs, rt=run.rt,
                                                    progress=bar)
                if len(self.slabs) == 1 and rows.rows.nbytes * len(run.variants) <= ROWS_BYTES:
                    self.kept[(k, variant)] = rows  # the final pass's rows (one slab, every variant's within budget)
            t_bp = time.perf_counter() - t0
            run.log(f"[{self.pk}] mc: registering {variant} (round {r} of {knobs.rounds})")
            model, info = mcm.register(imgs.reshape((nc, nr) + imgs.shape[1:]), self.ref_ij, grid, self.pairs, knobs,
                                       progress=bar, pool=pool)
            rounds.append(dict(info, backproject_seconds=t_bp))
        bar.close()
        info = {"rounds": [{k: round(v, 3) for k, v in x.items()} for x in rounds],
                "reference": list(model.reference), "registration_grid": [grid.nz, grid.ny, grid.nx],
                "registration_workers": self.workers,
                "basis": list(model.basis.names),
                "seconds": round(time.perf_counter() - t_start, 3)}
        if warning:
            info["warning"] = warning
        if not run.scene.measured:
            t0 = time.perf_counter()
            info["error_against_phantom_motion"] = registration_error(run.scene, model, self.pairs, run.mc_truth)
            info["error_seconds"] = round(time.perf_counter() - t0, 3)
        _save_model(run, self.pk, variant, model, info)
        clock.add("registration", time.perf_counter() - t_start)
        self._note(variant, info)
        return model

    def _note(self, variant: str, info: dict) -> None:
        mc = self.run.notes.get("registration", {}).get("mc", {})
        mc.setdefault(self.pk, {})[variant] = info
        self.run.note("registration", mc=mc)
        self.seconds[variant] = float(info.get("seconds", 0.0))


def _slab_unit(ctx: _Pitch, k: int, variant: str, model: MotionModel) -> Unit:
    run = ctx.run
    a, b = ctx.slabs[k]
    sel = np.arange(a, b)
    nc, nr = ctx.shape

    def here(emit, times):
        t0 = time.perf_counter()
        bary = ctx.bary_plan(a, b)
        rows = ctx.rows(k, variant, bary)
        t1 = time.perf_counter()
        full = mcm.refine(model, ctx.cfg.fbp)
        hu = mcm.backproject_slab(rows, bary, full, ctx.table, run.slices_z[a:b], ctx.cfg.fbp, ctx.pairs,
                                  ctx.cfg.mu_water_per_mm, ctx.knobs, rt=run.rt)
        t2 = time.perf_counter()
        times.add("plane_rows", t1 - t0)
        times.add("mc_backproject", t2 - t1)
        times.add(f"method:{NAME}:{variant}", t2 - t0)
        emit((sel, variant, hu.reshape((nc, nr) + hu.shape[1:])))

    def remote():
        g = model.grid
        return work_units.mc_slab, (ctx.cfg, run.scene, ctx.pitch, str(run.cache_path), run.slices_z, a, b,
                                    run.targets, variant, np.asarray(model.fields),
                                    (g.nx, g.ny, g.nz, g.voxel_mm, g.z0_mm, g.dz_mm), tuple(model.reference))

    return Unit(here, None if run.scene.measured else remote,
                f"mc slab of slices {a}..{b - 1} ({variant}) at pitch {ctx.pitch:g}")


def stage(run, pitch: float, plan, store):
    pk = pitch_key(pitch)
    for v in run.variants:
        run.writer.create(recon_path(pk, v, NAME), run.full_shape, len(run.slices_z))
    todo = {v: np.flatnonzero(~run.writer.done(recon_path(pk, v, NAME))) for v in run.variants}
    if not any(t.size for t in todo.values()):
        return Idle(pk)
    if store is None or isinstance(store, Idle):
        raise ClreconError(f"[{pk}] mc: the projection store of this pitch is not open (no slice left to plan?)")
    if interpolation.METHODS["barycentric"].target_grid != "5d":  # pragma: no cover - a registry invariant
        raise ClreconError("mc: the barycentric first pass must be a 5-D method")
    ctx = _Pitch(run, pitch, plan, store)
    try:
        models = {v: ctx.model(v) for v in run.variants if todo[v].size}
    finally:
        ctx.close()
    units_ = [_slab_unit(ctx, k, v, models[v]) for v in run.variants if todo[v].size
              for k, (a, b) in enumerate(ctx.slabs) if (~run.writer.done(recon_path(pk, v, NAME))[a:b]).any()]

    def write(piece) -> None:
        z, v, vol = piece
        run.writer.write(recon_path(pk, v, NAME), vol, z)

    def finish(times):
        per = run.records["method_seconds"].setdefault(pk, {})
        for key, sec in times.seconds.items():
            if key.startswith(f"method:{NAME}:"):
                v = key.split(":")[2]
                per.setdefault(v, {})[NAME] = round(sec + ctx.seconds.get(v, 0.0), 3)
        return pk

    n = sum(t.size for t in todo.values())
    return Work(units_, write, finish, progress=(f"mc {pk}", n, "slices"), weight=lambda piece: len(piece[0]))
