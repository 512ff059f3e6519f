"""The volume units written behind the reconstruction (clrecon.core.write_behind): in order,
one in flight, errors raised in the run's thread, the same units as the foreground path."""

import threading
import time

import numpy as np
import pytest
from run_compare import QUIET, assert_identical, reference_run

from clrecon.config.overrides import load_scene as api_load_scene
from clrecon.config.scene import load_scene
from clrecon.core import units, write_behind
from clrecon.outputs.volumes import VolumeWriter
from clrecon.pipeline import costs
from clrecon.pipeline.run import run
from clrecon.pipeline.stages import truth as truth_stage
from clrecon.reconstruction import reconstruct
from clrecon.simulation import store as store_mod
from clrecon.simulation.simulate import simulate


def test_calls_run_in_order_one_in_flight():
    wb = write_behind.WriteBehind(background=True)
    log, active, most = [], [0], [0]
    lock = threading.Lock()

    def job(k):
        with lock:
            active[0] += 1
            most[0] = max(most[0], active[0])
        time.sleep(0.02)
        log.append((k, threading.current_thread().name))
        with lock:
            active[0] -= 1

    for k in range(6):
        wb.submit(job, k)
        assert active[0] <= 1
    wb.drain()
    wb.close()
    assert [k for k, _ in log] == list(range(6))
    assert most[0] == 1 and {name.split("_")[0] for _, name in log} == {"clrecon-write"}
    assert wb.beside_seconds >= 6 * 0.02 and wb.wait_seconds <= wb.beside_seconds + 0.5


def test_submit_waits_for_the_previous_call():
    wb = write_behind.WriteBehind(background=True)
    done = threading.Event()
    wb.submit(lambda: (time.sleep(0.2), done.set()))
    assert not done.is_set()  # the caller went on while the first call runs
    wb.submit(lambda: None)
    assert done.is_set()  # ... and the second submit waited for it
    wb.close()


def test_an_error_in_the_thread_is_raised_at_the_next_submit_and_at_drain():
    wb = write_behind.WriteBehind(background=True)
    ran = []
    wb.submit(lambda: (_ for _ in ()).throw(OSError("disk full")))
    with pytest.raises(OSError, match="disk full"):
        wb.submit(ran.append, 1)
    assert ran == []  # the call after a failed one is not started
    wb.submit(lambda: (_ for _ in ()).throw(ValueError("bad unit")))
    with pytest.raises(ValueError, match="bad unit"):
        wb.drain()
    wb.submit(lambda: (_ for _ in ()).throw(ValueError("during clean-up")))
    wb.close()  # the clean-up of a failing run raises nothing of its own


def test_foreground_mode_runs_each_call_at_once():
    wb = write_behind.WriteBehind(background=False)
    seen = []
    wb.submit(lambda: seen.append(threading.current_thread() is threading.main_thread()))
    assert seen == [True] and not wb.background
    with pytest.raises(OSError, match="now"):
        wb.submit(lambda: (_ for _ in ()).throw(OSError("now")))
    wb.close()


def test_memory_model_counts_the_held_slab():
    """The slab rule holds the finished slab being written (in the volume dtype, with its
    compressed image) beside the images being made; an overlapping executor adds one target's
    truth working set beside the reconstruction; the serial one does not."""
    sc = load_scene("paper-p010")  # recon.volume_dtype float16
    on = costs.run_costs(sc)
    off = costs.run_costs(sc, overlap=False)
    rc, scn = sc.recon, sc.scanner
    per16 = reconstruct.slab_bytes_per_slice(1000.0, scn.n_cols, 2, 50, rc.ny, rc.nx, volume_itemsize=2)
    per32 = reconstruct.slab_bytes_per_slice(1000.0, scn.n_cols, 2, 50, rc.ny, rc.nx, volume_itemsize=4)
    assert per32 - per16 == 50 * rc.ny * rc.nx * 6  # the dtype copy and its compressed image twice, 2 B each
    assert per16 - reconstruct.slab_bytes_per_slice(0.0, scn.n_cols, 2, 50, rc.ny, rc.nx, volume_itemsize=2) \
        == 1000 * scn.n_cols * 4 * 2
    truths = truth_stage.working_bytes(rc.nz, scn.views_per_rotation, scn.n_cols, rc.ny, rc.nx)
    # paper-p010: the reconstruction's peak is the larger (not the metrics'): the truths add in full
    assert on["peak_memory_bytes"] == off["peak_memory_bytes"] + truths


def test_the_writer_is_handed_the_stored_copy(tmp_path, monkeypatch):
    """The reconstruction's slabs reach the writer already in the volume dtype, converted after the
    previous write finished (so the writer thread never holds float32 images): every array
    VolumeWriter.write receives from the reconstruction is C-contiguous float16 on a float16 run,
    and no write is in flight when a conversion starts."""
    seen, converting_while_writing = [], []
    busy = threading.Event()
    real_write, real_stored = VolumeWriter.write, VolumeWriter.as_stored

    def write(self, name, vol, z):
        if name.startswith("recon/"):
            seen.append((vol.dtype, vol.flags.c_contiguous))
        busy.set()
        try:
            time.sleep(0.05)  # a slow disk: the next slab is made meanwhile
            real_write(self, name, vol, z)
        finally:
            busy.clear()

    def as_stored(self, vol):
        if threading.current_thread() is threading.main_thread():
            converting_while_writing.append(busy.is_set())
        return real_stored(self, vol)

    monkeypatch.setattr(VolumeWriter, "write", write)
    monkeypatch.setattr(VolumeWriter, "as_stored", as_stored)
    run(api_load_scene("tiny", recon__volume_dtype="float16"), tmp_path / "run", cache_dir=tmp_path / "cache",
        executor="local", **QUIET)
    assert seen and all(dt == np.float16 and c for dt, c in seen)
    assert converting_while_writing and not any(converting_while_writing)


@pytest.fixture(scope="module")
def foreground(tmp_path_factory):
    """tiny with every unit written in the run's thread (the serial executor)."""
    return reference_run(tmp_path_factory, {}, executor="serial")[:2]


def test_units_written_behind_hold_the_same_values(tmp_path, foreground, monkeypatch):
    threads = []
    real = VolumeWriter.write

    def spy(self, *a, **k):
        threads.append(threading.current_thread().name)
        return real(self, *a, **k)

    monkeypatch.setattr(VolumeWriter, "write", spy)
    res = run(load_scene("tiny"), tmp_path, cache_dir=tmp_path / "cache", executor="local", **QUIET)
    assert_identical(tmp_path, foreground, ("metrics", "respiratory_only", "motion", "diagnostics", "sampling"))
    # every unit's values (LZF's bytes are not reproducible: h5py's liblzf leaves its hash table
    # uninitialised, so the units' BLAKE2b names may differ; the values may not)
    def unit_values(root):
        return {p.name.rsplit(".", 2)[0]: units.read_unit(p)[0]["data"].tobytes()
                for p in root.glob("volumes.d/*/recon~*")}

    got, want = unit_values(tmp_path), unit_values(foreground[0])
    assert got.keys() == want.keys() and len(got) > 1 and all(got[k] == want[k] for k in got)
    assert len(threads) == len(got) and all(t.startswith("clrecon-write") for t in threads)
    st = res["stages"]["write_volumes"]
    assert st["beside_seconds"] > 0 and "beside_seconds" not in foreground[1]["stages"]["write_volumes"]


def test_a_failing_write_fails_the_run_with_its_error(tmp_path, monkeypatch):
    def broken(self, *a, **k):
        raise OSError("no space left on device (test)")

    monkeypatch.setattr(VolumeWriter, "write", broken)
    with pytest.raises(OSError, match="no space left"):
        run(load_scene("tiny"), tmp_path, cache_dir=tmp_path / "cache", **QUIET)
    assert not (tmp_path / "results.json").exists() and not (tmp_path / "volumes.h5").exists()


def test_projection_units_written_behind_hold_the_same_projections(tmp_path, monkeypatch):
    """simulate(): each block's units written by the thread while the next block is projected."""
    sc = load_scene("tiny")
    pitch = sc.scan.pitches[0]
    threads = []
    real = store_mod.ProjectionStore.write

    def spy(self, *a, **k):
        threads.append(threading.current_thread().name)
        return real(self, *a, **k)

    got = {}
    for mode in ("0", "1"):
        monkeypatch.setattr(store_mod.ProjectionStore, "write", spy)
        threads.clear()
        st = simulate(sc, pitch, cache_dir=tmp_path / mode, chunk=8, progress=False, write_behind_thread=mode == "1")
        assert st.n_simulated == len(st) and st.complete
        got[mode] = (st.read(0, len(st)), list(threads))
        st.close()
    assert len(got["1"][1]) > 2 and all(t.startswith("clrecon-write") for t in got["1"][1])
    assert all(t == "MainThread" for t in got["0"][1])
    assert got["0"][0].tobytes() == got["1"][0].tobytes()


def test_a_failing_projection_write_fails_the_simulation(tmp_path, monkeypatch):
    def broken(self, *a, **k):
        raise OSError("store disk full (test)")

    monkeypatch.setattr(store_mod.ProjectionStore, "write", broken)
    sc = load_scene("tiny")
    with pytest.raises(OSError, match="store disk full"):
        simulate(sc, sc.scan.pitches[0], cache_dir=tmp_path, chunk=8, progress=False)


@pytest.mark.parametrize("drain_first", [False, True])
def test_a_unit_that_drains_first_starts_after_the_write_in_flight(drain_first):
    """``Unit.drain_first`` (``mc``'s slabs): the previous unit's piece is written before the unit
    starts, so the two are never held at once; without it the write runs beside the next unit."""
    from collections import namedtuple

    from clrecon.pipeline.executors.base import Executor, Unit, Work

    ex = Executor()
    ex.writer = write_behind.WriteBehind(background=True)
    ex.run_ctx = namedtuple("Run", "progress")(False)
    ex.done = {}
    written, seen = [], []

    def write(piece):
        time.sleep(0.3)
        written.append(piece)

    def unit(k):
        def here(emit, times):
            seen.append(len(written))  # the pieces on disk when the unit starts
            emit(k)
        return Unit(here, None, f"unit {k}", drain_first=drain_first)

    stage = namedtuple("Stage", "name write_part rest")("demo-stage", None, None)
    ex.start_work((stage, None), Work([unit(k) for k in range(3)], write), time.perf_counter(), 0.0)
    ex.writer.close()
    assert written == [0, 1, 2]
    # drained: every earlier piece written; else the previous one still in flight (0.3 s)
    assert seen == ([0, 1, 2] if drain_first else [0, 0, 1])
