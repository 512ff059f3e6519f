"""Stage ``mc_reconstruct`` (per pitch, with the ``mc`` method): motion-compensated FBP with a
registered (c, a) motion model, made from the method's first pass (the registry's
``first_pass``, barycentric; docs/motion-model.md). The algorithm is
:mod:`clrecon.reconstruction.motion.mc_fbp`'s; this stage wires it to a run.

Per noise variant: the first pass ``recon/<pitch>/<variant>/<first pass>`` is read back from the
writer's unit files (unit by unit, onto the registration's grid) and the model fitted
(:func:`mc_fbp.fit_model`); it is saved as its own unit
(``volumes.h5.units/mc/``, atomic, checksummed: :mod:`clrecon.reconstruction.motion.persist`),
and a resumed run loads it instead of registering again. Then one unit per (slab, variant)
(:func:`mc_fbp.reconstruct_slab`, in this process or on a Dask worker:
:func:`clrecon.pipeline.work_units.mc_slab`), written as ``recon/<pitch>/<variant>/mc`` one unit
file per slab (resumable after kill -9 as ``reconstruct``'s). Timed as ``registration`` (with
the rounds' backprojections), ``plane_rows``, ``mc_backproject``, ``write_volumes``;
``results.json["stages"]["registration"]["mc"]`` holds the model's reference state, fit
residuals and (for a simulated scan) its error against the phantom's own motion.
"""

from __future__ import annotations

import time

import numpy as np

from clrecon.core.errors import ClreconError
from clrecon.core.progress import progress as progress_counter
from clrecon.evaluation.motion_model import registration_error
from clrecon.outputs.volumes import pitch_key, recon_path
from clrecon.pipeline import work_units
from clrecon.pipeline.executors.base import Idle, Unit, Work
from clrecon.reconstruction.motion import mc_fbp, persist
from clrecon.reconstruction.motion.method import basis_of
from clrecon.reconstruction.motion.model import MotionModel
from clrecon.scan import table as geometry

#: The method this stage makes.
NAME = mc_fbp.NAME
FAULT = "mc-model"


def skip(run) -> str | None:
    return None if NAME in run.methods else "the mc method is not asked for (recon.methods)"


def motion_scan(run, pitch, plan, store) -> mc_fbp.MCScan:
    """The scan as ``mc``'s model fit sees it (also the ``mcir`` stage's, which shares the model)."""
    if plan.pp is not None:
        table, ptab = plan.pp.table, plan.pp.plan_table
    else:
        table = geometry.cached_projection_table(run.scene, pitch)
        ptab = geometry.usable_table(run.scene, table)[0]
    return mc_fbp.MCScan(run.recon_cfg, run.scene.recon.mc_knobs, run.scene.scanner, table, ptab, store, run.slices_z,
                         run.targets, rt=run.rt, n_variants=len(run.variants))


def _note(run, pk: str, variant: str, info: dict, seconds: dict) -> None:
    mc = run.notes.get("registration", {}).get("mc", {})
    mc.setdefault(pk, {})[variant] = info
    run.note("registration", mc=mc)
    seconds[variant] = float(info.get("seconds", 0.0))


def motion_model(run, scan: mc_fbp.MCScan, pk: str, variant: str, seconds: dict) -> MotionModel:
    """The final round's model of ``variant``: loaded (a resumed run, or made by the other of the
    ``mc`` / ``mcir`` stages), or fitted and saved."""
    folder, stem = run.writer.units_dir / NAME, f"model~{pk}~{variant}"
    got = persist.load_model(folder, stem, basis_of(scan.knobs, *scan.shape))
    if got is not None:
        run.log(f"[{pk}] mc: motion model of {variant} loaded (resumed run)")
        _note(run, pk, variant, got[1], seconds)
        return got[0]
    t_start = time.perf_counter()
    path = recon_path(pk, variant, mc_fbp.FIRST_PASS)

    def first(reduce):  # read unit by unit onto the registration's grid: never held whole at full resolution
        return run.writer.read(path, reduce=reduce)

    warning = mc_fbp.thin_warning(pk, run.slices_z)
    if warning:
        run.log(warning)
    model, info = mc_fbp.fit_model(scan, first, variant, log=lambda line: run.log(f"[{pk}] mc: {line}"),
                                   progress=run.progress, label=pk)
    if warning:
        info["warning"] = warning
    if not run.scene.measured:
        t0 = time.perf_counter()
        info["error_against_phantom_motion"] = registration_error(run.scene, model, scan.pairs,
                                                                  run.mc_truth)
        info["error_seconds"] = round(time.perf_counter() - t0, 3)
    persist.save_model(folder, stem, model, info, FAULT)
    run.clock.add("registration", time.perf_counter() - t_start)
    _note(run, pk, variant, info, seconds)
    return model


def _slab_unit(run, pitch: float, scan: mc_fbp.MCScan, a: int, b: int, variant: str, model: MotionModel) -> Unit:
    def here(emit, times):
        # the targets of the slab counted with an ETA: one slab of a whole paper-scale scan takes tens of
        # minutes, and the stage's own counter moves only when a slab is done
        with progress_counter(len(scan.pairs), f"mc {pitch_key(pitch)} slices {a}..{b - 1} ({variant})",
                              run.progress, "targets") as bar:
            emit((np.arange(a, b), variant, mc_fbp.reconstruct_slab(scan, a, b, variant, model, times, bar)))

    def remote():
        return work_units.mc_slab, (run.recon_cfg, run.scene, pitch, str(run.cache_path), run.slices_z, a, b,
                                    run.targets, variant, model)

    # drain_first: the previous slab's volumes are written before this slab's rows are made (the memory
    # model's final pass holds one slab of output, memory.working_parts)
    return Unit(here, None if run.scene.measured else remote,
                f"mc slab of slices {a}..{b - 1} ({variant}) at pitch {pitch:g}", drain_first=True)


def models_to_do(run, pitch: float, plan, store, name: str):
    """The shared start of the ``mc`` and ``mcir`` stages: declare method ``name``'s datasets of the
    pitch and find the slices left. Returns ``Idle`` when none is, else ``(todo, scan, models,
    seconds)``: the slice indices left per variant, the :class:`mc_fbp.MCScan`, the motion model
    of every variant with work left (:func:`motion_model`) and the models' seconds per variant."""
    pk = pitch_key(pitch)
    for v in run.variants:
        run.writer.create(recon_path(pk, v, name), run.full_shape, len(run.slices_z))
    todo = {v: np.flatnonzero(~run.writer.done(recon_path(pk, v, name))) for v in run.variants}
    if not any(t.size for t in todo.values()):
        return Idle(pk)
    if store is None or isinstance(store, Idle):
        raise ClreconError(f"[{pk}] {name}: the projection store of this pitch is not open (no slice left to plan?)")
    scan = motion_scan(run, pitch, plan, store)
    seconds: dict = {}  # variant -> the model's seconds
    with scan:  # the registration's process pool ends with the models
        models = {v: motion_model(run, scan, pk, v, seconds) for v in run.variants if todo[v].size}
    return todo, scan, models, seconds


def record_method_seconds(run, pk: str, name: str, times, seconds: dict) -> str:
    """``method_seconds`` of method ``name`` per variant: its units' ``method:<name>:<variant>``
    seconds plus its model's (``seconds``); returns ``pk`` (a stage's ``finish``)."""
    per = run.records["method_seconds"].setdefault(pk, {})
    for key, sec in times.seconds.items():
        if key.startswith(f"method:{name}:"):
            v = key.split(":")[2]
            per.setdefault(v, {})[name] = round(sec + seconds.get(v, 0.0), 3)
    return pk


def stage(run, pitch: float, plan, store):
    pk = pitch_key(pitch)
    got = models_to_do(run, pitch, plan, store, NAME)
    if isinstance(got, Idle):
        return got
    todo, scan, models, seconds = got
    units_ = [_slab_unit(run, pitch, scan, a, b, v, models[v]) for v in run.variants if todo[v].size
              for a, b in scan.slabs if (~run.writer.done(recon_path(pk, v, NAME))[a:b]).any()]

    def write(piece) -> None:
        z, v, vol = piece
        run.writer.write(recon_path(pk, v, NAME), vol, z)

    n = sum(t.size for t in todo.values())
    return Work(units_, write, lambda times: record_method_seconds(run, pk, NAME, times, seconds),
                progress=(f"mc {pk}", n, "slices"), weight=lambda piece: len(piece[0]))
