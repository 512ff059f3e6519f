"""Stage ``mcir_reconstruct`` (per pitch, with the ``mcir`` method): OS-SART on the cone-beam rows
through ``mc``'s motion model (docs/iterative.md). The algorithm is
:mod:`clrecon.reconstruction.iterative.method`'s; this stage wires it to a run.

The motion model is ``mc``'s, made once per (pitch, variant) whichever of the two stages comes
first (:func:`clrecon.pipeline.stages.mc_reconstruct.motion_model`: loaded from its unit when
``mc`` made it, or a resumed run; fitted from the barycentric first pass and saved otherwise).
Then one unit per (slab, variant) (:func:`clrecon.reconstruction.iterative.method.reconstruct_slab`,
in this process or on a Dask worker: :func:`clrecon.pipeline.work_units.mcir_slab`), written as
``recon/<pitch>/<variant>/mcir`` one unit file per slab (resumable after kill -9 as
``reconstruct``'s). Each unit logs the solver's residual per epoch; ``results.json["stages"]
["mcir"]`` holds every slab's solver history (residuals, why it stopped, seconds).
Timed as ``registration`` (the model, when this stage fits it) and ``mcir_solve``, ``write_volumes``.
"""

from __future__ import annotations

import numpy as np

from clrecon.outputs.volumes import pitch_key, recon_path
from clrecon.pipeline import work_units
from clrecon.pipeline.executors.base import Idle, Unit, Work
from clrecon.pipeline.stages import mc_reconstruct
from clrecon.reconstruction.iterative import method as mcir
from clrecon.reconstruction.motion import mc_fbp

#: The method this stage makes.
NAME = mcir.NAME
SLAB_BYTES = mcir.SLAB_BYTES


def skip(run) -> str | None:
    return None if NAME in run.methods else "the mcir method is not asked for (recon.methods)"


def slabs(run, table, n_basis: int) -> tuple[list[tuple[int, int]], int]:
    """The slice ranges ``(a, b)`` and the largest one's modelled bytes
    (:func:`clrecon.reconstruction.iterative.method.slab_plan` under :data:`SLAB_BYTES`)."""
    return mcir.slab_plan(run.scene.scanner, run.scene.recon, run.scene.recon.mcir, run.recon_cfg.object_radius_mm,
                          table, run.slices_z, n_basis, budget=SLAB_BYTES)


def slab_line(cuts, worst_bytes: int) -> str:
    """One line on the slab cut for the log: how many slabs of how many slices, the largest's
    modelled memory, and, where one slice alone is over :data:`SLAB_BYTES`, what that costs and what
    lowers it."""
    sizes = sorted({b - a for a, b in cuts})
    line = (f"{len(cuts)} slab{'s' * (len(cuts) != 1)} of {'/'.join(map(str, sizes))} slice(s), the largest "
            f"modelled at {worst_bytes / 1e9:.2f} GB")
    over = mcir.over_budget_note(worst_bytes, SLAB_BYTES)
    return f"{line}: {over}" if over else line


def start_method(run) -> str | None:
    """The method whose volumes OS-SART starts from (``[recon.mcir] init``): None ('zero'), the first
    pass ('first_pass'), ``mc`` ('mc'; 'auto' where the run has ``mc``), else the first pass."""
    init = run.scene.recon.mcir.init
    if init == "zero":
        return None
    if init == mc_fbp.NAME or (init == "auto" and mc_fbp.NAME in run.methods):
        return mc_fbp.NAME
    return mc_fbp.FIRST_PASS


def start_image(run, pk: str, variant: str, ref_ij, a: int, b: int) -> np.ndarray | None:
    """OS-SART's start for slices ``a .. b-1``: None (from zero), or the motion model's reference
    target ``ref_ij`` (:attr:`mc_fbp.MCScan.ref_ij`) of :func:`start_method`'s volumes, as its stage
    wrote them (read a unit at a time, only that target kept): (b - a, ny, nx) HU float32."""
    name = start_method(run)
    if name is None:
        return None

    def target(v):  # (n_c, n_r, s, ny, nx) -> (1, 1, s, ny, nx); a broadcast axis has length 1
        return v[min(ref_ij[0], v.shape[0] - 1), min(ref_ij[1], v.shape[1] - 1)][None, None]

    return run.writer.read(recon_path(pk, variant, name), np.arange(a, b), reduce=target)[0, 0]


def _unit(run, pitch: float, table, store, a: int, b: int, variant: str, model, ref_ij) -> Unit:
    pk = pitch_key(pitch)

    def here(emit, times):
        hu, info = mcir.reconstruct_slab_from_store(
            run.scene, run.recon_cfg, table, store, run.slices_z[a:b], run.targets, variant, model,
            start_hu=start_image(run, pk, variant, ref_ij, a, b), rt=run.rt,
            log=lambda line: run.log(f"[{pk}] mcir {variant} slices {a}..{b - 1}: {line}"), times=times,
            budget=SLAB_BYTES)
        emit((np.arange(a, b), variant, hu, info))

    def remote():
        return work_units.mcir_slab, (run.recon_cfg, run.scene, pitch, str(run.cache_path), run.slices_z, a, b,
                                      run.targets, variant, model, start_image(run, pk, variant, ref_ij, a, b))

    # drain_first: the previous slab's volumes are written before this slab's solve (one slab of output held)
    return Unit(here, None if run.scene.measured else remote,
                f"mcir slab of slices {a}..{b - 1} ({variant}) at pitch {pitch:g}", drain_first=True)


def stage(run, pitch: float, plan, store):
    pk = pitch_key(pitch)
    got = mc_reconstruct.models_to_do(run, pitch, plan, store, NAME)
    if isinstance(got, Idle):
        return got
    todo, scan, models, seconds = got
    run.note("mcir", start=start_method(run) or "zero")
    table = scan.plan_table  # the usable views (a measured scan's excluded ones left out)
    cuts, worst = slabs(run, table, max(m.fields.shape[0] for m in models.values()))
    run.log(f"[{pk}] mcir: {slab_line(cuts, worst)}")
    run.note("mcir", slab_cut={**run.notes.get("mcir", {}).get("slab_cut", {}),
                               pk: {"slabs": len(cuts), "largest_bytes": worst, "over_budget": worst > SLAB_BYTES}})
    units_ = [_unit(run, pitch, table, store, a, b, v, models[v], scan.ref_ij) for v in run.variants if todo[v].size
              for a, b in cuts if (~run.writer.done(recon_path(pk, v, NAME))[a:b]).any()]

    def write(piece) -> None:
        z, v, vol, info = piece
        run.writer.write(recon_path(pk, v, NAME), vol, z)
        hist = run.notes.get("mcir", {}).get("slabs", {})
        hist.setdefault(pk, {}).setdefault(v, {})[f"{int(z[0])}..{int(z[-1])}"] = info
        run.note("mcir", slabs=hist)

    n = sum(t.size for t in todo.values())
    return Work(units_, write, lambda times: mc_reconstruct.record_method_seconds(run, pk, NAME, times, seconds),
                progress=(f"mcir {pk}", n, "slices"), weight=lambda piece: len(piece[0]))
