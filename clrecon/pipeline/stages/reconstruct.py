"""Stage ``reconstruct`` (per pitch): every method and noise variant of the slices still to do,
slab by slab (:func:`clrecon.reconstruction.reconstruct.reconstruct`: read the candidate
projections, draw their noise, rebin (SSRB), interpolate in phase space, FBP).

Each slab is one unit; the volumes of each (variant, method) are written as soon as they are
made, one unit file per slab (``recon/<pitch>/<variant>/<method>`` of ``volumes.h5``). The
cv_tuned method is planned per variant with the kernel the truth-free stage chose.
"""

from __future__ import annotations

import dataclasses
import time

from clrecon.evaluation import truth_free
from clrecon.outputs.volumes import pitch_key, recon_path
from clrecon.pipeline import slabs as slabs_mod
from clrecon.pipeline import work_units
from clrecon.pipeline.context import TUNED
from clrecon.pipeline.executors.base import Idle, Unit, Work
from clrecon.reconstruction import reconstruct


def _tuned_cfg(cfg, choice: dict):
    """The reconstruction config of cv_tuned with the kernel chosen for one variant."""
    kern = truth_free.Kernel.from_dict(choice["kernel"])
    return dataclasses.replace(cfg, tuned=(kern.method, tuple(sorted(
        (k, x) for k, x in kern.to_dict().items() if k != "method"))))


def _slab(run, plan, store, tuning, k: int, sel):
    """One slab (``sel``: slice indices) of every method and variant, in this process."""
    cfg, pp = run.recon_cfg, plan.pp

    def here(emit, times):
        def on_slab(zs, slab):
            emit((sel[zs], slab))

        plan_k, pp.plans[k] = pp.plans[k], None
        if plan_k is None:  # not kept (the plans of the whole scan were over the budget): made again
            t0 = time.perf_counter()
            plan_k = reconstruct.plan(cfg, pp.plan_table, run.slices_z[sel], run.targets,
                                      slabs_mod.planned_methods(plan.methods))
            times.add("plan", time.perf_counter() - t0)
            for m, sec in plan_k.method_seconds.items():
                plan.plan_seconds[m] = plan.plan_seconds.get(m, 0.0) + sec
        if plan.fixed_methods:
            reconstruct.reconstruct(cfg, store, plan_k, variants=run.variants, rt=run.rt, times=times,
                                    on_slab=on_slab, slab_size=len(sel))
        del plan_k
        for v in run.variants if TUNED in plan.methods else ():  # cv_tuned: the kernel chosen for this variant
            t0 = time.perf_counter()
            cfg_v = _tuned_cfg(cfg, tuning["choice"][v])
            plan_v = reconstruct.plan(cfg_v, pp.plan_table, run.slices_z[sel], run.targets, (TUNED,))
            times.add("plan", time.perf_counter() - t0)
            plan.plan_seconds[TUNED] = plan.plan_seconds.get(TUNED, 0.0) + plan_v.method_seconds[TUNED]
            reconstruct.reconstruct(cfg_v, store, plan_v, variants=(v,), rt=run.rt, times=times, on_slab=on_slab,
                                    slab_size=len(sel))

    def remote():
        plan_k, pp.plans[k] = pp.plans[k], None
        return work_units.reconstruct_slab, (cfg, run.scene, plan.pitch, str(run.cache_path), plan_k,
                                             run.slices_z[sel], run.targets, slabs_mod.planned_methods(plan.methods),
                                             run.variants, sel)

    return Unit(here, None if TUNED in plan.methods else remote,
                f"reconstruction slab of slices {sel[0]}..{sel[-1]} at pitch {plan.pitch:g}")


def stage(run, pitch: float, plan, store, tuning):
    if plan.pp is None:
        return Idle()
    pk, n_out = pitch_key(pitch), len(run.variants) * len(plan.methods)

    def prepare(piece):
        """The finished slab in the volume dtype, made here (the run's thread) so that the writer
        thread holds only that copy, not the float32 images (Work.prepare)."""
        z, slab = piece
        return z, {key: run.writer.as_stored(vol) for key, vol in slab.items()}

    def write(piece) -> None:
        z, slab = piece
        for (v, m), vol in slab.items():  # r4dct (1, n_r), helical (1, 1): stored as they are
            run.writer.write(recon_path(pk, v, m), vol, z)

    def finish(times):
        """A method's cost per variant: its interpolation + FBP of that variant plus its whole plan
        (made once for every variant: a run of one variant pays it in full)."""
        plan_s = plan.plan_seconds
        for key, sec in times.seconds.items():
            if key.startswith("plan:"):
                m = key.split(":", 1)[1]
                plan_s[m] = plan_s.get(m, 0.0) + sec
        run.records["method_plan_seconds"][pk] = {m: round(sec, 3) for m, sec in plan_s.items()}
        per = run.records["method_seconds"].setdefault(pk, {})
        for key, sec in times.seconds.items():
            if key.startswith("method:"):
                _, m, v = key.split(":")
                per.setdefault(v, {})[m] = round(sec + plan_s.get(m, 0.0), 3)
        counts = run.records["counts"]
        for key, n in times.counts.items():
            counts[key] = counts.get(key, 0) + n
        if hasattr(store, "close"):
            store.close()
        return pk

    units = [_slab(run, plan, store, tuning, k, plan.todo[a:b]) for k, (a, b) in enumerate(plan.pp.slabs)]
    return Work(units, write, finish, progress=(f"reconstruct {pk}", plan.todo.size * n_out, "slice-volumes"),
                weight=lambda piece: len(piece[0]) * len(piece[1]), prepare=prepare)
