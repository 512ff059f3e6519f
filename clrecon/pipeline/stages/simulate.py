"""Stage ``simulate`` (per pitch): the projections the plan needs, into the scan's projection store.

Only the needed projections that the store lacks are projected (a second run of the same scan
reuses them), in blocks of whole chunks of :data:`clrecon.simulation.simulate.CHUNK` (one unit
file each; one unit per chunk when the units go to workers elsewhere); a measured scan's
files are imported instead (:func:`clrecon.simulation.measured.import_series`, in this
process). The store keeps noise-free line integrals: noise is drawn when the reconstruction
reads them (its ``noise`` part).
"""

from __future__ import annotations

import contextlib
import time

from clrecon.outputs.volumes import pitch_key
from clrecon.pipeline import work_units
from clrecon.pipeline.executors.base import Idle, Unit, Work
from clrecon.simulation import measured
from clrecon.simulation import simulate as sim
from clrecon.simulation.projector import project
from clrecon.simulation.store import ProjectionStore


def _record(run, pk: str, store, total: int, needed, simulated: int, reused: int, pw) -> None:
    run.records["sim_info"][pk] = {
        "projections_total": total, "projections_needed": int(needed.sum()), "projections_simulated": simulated,
        "projections_reused": reused, "store": str(getattr(store, "path", "")), "slabs": len(pw.pp.slabs),
        "slab_slices": [int(b - a) for a, b in pw.pp.slabs]}


def stage(run, pitch: float, plan):
    pk, scene = pitch_key(pitch), run.scene
    if plan.pp is None:  # nothing to reconstruct at this pitch (a resumed run)
        run.records["sim_info"][pk] = {"projections_total": scene.scan.projection_count(scene.scanner, pitch),
                                       "projections_needed": 0, "projections_simulated": 0, "projections_reused": 0,
                                       "store": ""}
        return Idle()
    table = plan.pp.table
    if scene.measured:  # its files are read into the store instead (same store, same units)
        store = measured.import_series(scene, pitch, needed=plan.needed, cache_dir=run.cache_path,
                                       progress=run.progress)
        _record(run, pk, store, len(table), plan.needed, int(store.n_simulated), int(store.n_reused), plan)
        run.records["units_written"]["projections"] += int(getattr(store, "units_written", 0))
        return store
    store = ProjectionStore.open(scene, pitch, cache_dir=run.cache_path, table=table)
    missing = store.missing(plan.needed)
    reused = int(store.n_reused)
    writing = contextlib.ExitStack()
    if missing.size or store.state != "final":  # a .partial with nothing missing still goes through writing()
        writing.enter_context(store.writing())
    per = sim.CHUNK if run.fine_units else sim.block_size(scene, sim.CHUNK)

    def block(idx):
        def here(emit, times):
            t0 = time.perf_counter()
            data = project(scene, table.take(idx))
            times.add("simulate", time.perf_counter() - t0)
            emit((idx, data))
        return Unit(here, lambda: (work_units.simulate_chunk, (scene, pitch, idx)),
                    f"projections {idx[0]}..{idx[-1]} of pitch {pitch:g}")

    def write(piece) -> None:
        idx, data = piece
        sim.write_block(store, idx, data, sim.CHUNK)

    def finish(times):
        writing.close()  # assembles <hash>.h5 and removes its unit files
        if run.fine_units:
            store.close()  # the workers read it
        _record(run, pk, store, len(table), plan.needed, int(missing.size), reused, plan)
        run.records["units_written"]["projections"] += int(store.units_written)
        return store

    return Work([block(missing[lo:lo + per]) for lo in range(0, missing.size, per)], write, finish,
                lambda e: writing.__exit__(type(e), e, e.__traceback__),
                (f"simulate {scene.name} pitch {pitch:g}", int(missing.size), "proj"), lambda piece: len(piece[0]))
