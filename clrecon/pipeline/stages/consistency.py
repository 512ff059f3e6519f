"""Stage ``consistency`` (per pitch, with the ``mc`` method): did ``mc`` help? A truth-free check.

After ``mc_reconstruct`` (``after``: its units are on disk), every 5D method's volumes of the
sampled slices are read back from the writer's unit files and projected at the states of the
sampled rows; the RMS residual of the rows against those predictions
(:func:`clrecon.evaluation.consistency.check`) is compared between ``mc`` and its first pass,
barycentric, and, in a run with ``mcir``, between ``mcir`` and ``mc``, per noise variant
(docs/consistency.md "Did it help? A truth-free check"). Methods
on other target grids (r4DCT, helical) are left out with the reason.
``results.json["consistency"][pitch]``, a report section and a log line per variant.
A run without ``mc`` skips it; the projections it reads are added to the plan's (plan stage).
"""

from __future__ import annotations

from clrecon.evaluation import consistency
from clrecon.outputs.volumes import pitch_key, recon_path
from clrecon.pipeline.executors.base import Idle
from clrecon.reconstruction import interpolation

#: The method whose help the stage judges (against its first pass, ``consistency.REFERENCE``).
METHOD = consistency.METHOD


def skip(run) -> str | None:
    return None if METHOD in run.methods else "the mc method is not asked for (recon.methods)"


def checked_methods(methods) -> tuple[tuple, dict]:
    """(the 5D methods on the (cardiac, amplitude) target lattice, {left-out method: why})."""
    keep, left = [], {}
    for m in methods:
        meth = interpolation.METHODS[m]
        if meth.target_grid == "5d":
            keep.append(m)
        else:
            left[m] = (f"target grid {meth.target_grid!r}: its volumes are not images at the (cardiac, amplitude) "
                       "targets, so they do not predict a row at its own state")
    return tuple(keep), left


def stage(run, pitch: float, plan, store):
    pk = pitch_key(pitch)
    rec = run.records["consistency"]
    if plan.pp is None:
        rec[pk] = {"skipped_because": "this pitch was reconstructed by an earlier run (resumed) and its projections "
                                      "were not opened again: run into a fresh output folder to check it"}
        run.log(f"[{pk}] consistency: skipped (resumed run, nothing reconstructed at this pitch)")
        return Idle()
    methods, left = checked_methods(run.methods)
    run.log(f"[{pk}] consistency: residual of the rows against {', '.join(methods)}")

    def volumes(variant, method, slices):
        return run.writer.read(recon_path(pk, variant, method), slices)

    res = consistency.check(store, plan.pp.plan_table, run.slices_z, run.recon_cfg, run.targets, run.variants,
                            tuple(run.scene.recon.small_fov_mm), volumes, methods, rt=run.rt)
    res["config"]["left_out"] = left
    rec[pk] = res
    for v, ver in res["verdict"].items():
        r = res["residual"][v]
        run.log(f"[{pk}] consistency {v}: " + ", ".join(f"{m} {e['rms_hu_mm']:.1f}/{e['heart_rms_hu_mm']:.1f}"
                                                        for m, e in r.items())
                + f" HU mm (all/heart); {ver.get('text', ver.get('null_because', ''))}"
                + (f"; {res['mcir_verdict'][v]['text']}" if "mcir_verdict" in res else ""))
    return res
