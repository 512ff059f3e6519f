"""Projection store and simulation driver: reuse, partial needs, interruption, corruption."""

import h5py
import numpy as np
import pytest

from clrecon.config.scene import load_scene
from clrecon.core.errors import StoreError
from clrecon.scan.table import projection_table
from clrecon.simulation.simulate import simulate
from clrecon.simulation.store import ProjectionStore, default_cache_dir


@pytest.fixture(scope="module")
def scene():
    return load_scene("tiny")


@pytest.fixture(scope="module")
def pitch(scene):
    return scene.scan.pitches[0]


class FakeProjector:
    """Cheap stand-in for clrecon.simulation.projector.project: values encode index, angle, row, column.

    ``fail_after`` raises on that call (0-based) to simulate an interrupted run.
    """

    def __init__(self, fail_after=None):
        self.calls = 0
        self.projected = 0
        self.fail_after = fail_after

    def __call__(self, scene, table):
        if self.fail_after is not None and self.calls == self.fail_after:
            raise RuntimeError("projector died")
        self.calls += 1
        self.projected += len(table)
        r, c = scene.scanner.n_rows, scene.scanner.n_cols
        k = table.index[:, None, None].astype(np.float64)
        b = table.angle_rad[:, None, None]
        rows = np.arange(r)[None, :, None]
        cols = np.arange(c)[None, :, None].reshape(1, 1, c)
        val = 1.0 + 1e-3 * k + 0.1 * np.sin(b + 0.05 * cols) + 0.01 * rows + table.state_resp[:, None, None]
        return val.astype(np.float32)


def _files(d):
    return sorted(p.name for p in d.iterdir())


def test_simulate_all_then_reuse(scene, pitch, tmp_path):
    fake = FakeProjector()
    store = simulate(scene, pitch, cache_dir=tmp_path, projector=fake, chunk=50, progress=False)
    n = len(store)
    assert n == len(projection_table(scene, pitch)) and fake.projected == n
    assert (store.n_simulated, store.n_reused) == (n, 0)
    assert store.complete and store.path.exists() and not store.partial_path.exists()
    assert store.path.name == f"{scene.scan_hash(pitch)}.h5"
    data = store.read(0, n)
    np.testing.assert_array_equal(data, fake(scene, store.table))
    with h5py.File(store.path, "r") as f:
        assert bool(f.attrs["complete"]) and f.attrs["scan_hash"] == scene.scan_hash(pitch)
        assert f["present"][...].all()
    store.close()

    # Second run: nothing projected (a projector that fails would show it).
    again = simulate(scene, pitch, cache_dir=tmp_path, projector=FakeProjector(fail_after=0), progress=False)
    assert (again.n_simulated, again.n_reused) == (0, n)
    np.testing.assert_array_equal(again.read(0, n), data)
    np.testing.assert_array_equal(again.table.resp_amplitude, store.table.resp_amplitude)


def test_needed_subset_then_rest(scene, pitch, tmp_path):
    n = len(projection_table(scene, pitch))
    needed = np.zeros(n, dtype=bool)
    needed[100:200] = True
    fake = FakeProjector()
    store = simulate(scene, pitch, needed=needed, cache_dir=tmp_path, projector=fake, progress=False)
    assert fake.projected == 100 and store.n_simulated == 100
    assert not store.complete and store.state == "final"
    store.read(100, 200)
    with pytest.raises(StoreError, match="not simulated"):
        store.read(150, 250)
    store.close()
    store2 = simulate(scene, pitch, cache_dir=tmp_path, projector=FakeProjector(), chunk=64, progress=False)
    assert (store2.n_simulated, store2.n_reused) == (n - 100, 100)
    assert store2.complete
    ref = simulate(scene, pitch, cache_dir=tmp_path / "ref", projector=FakeProjector(), progress=False)
    np.testing.assert_array_equal(store2.read(0, n), ref.read(0, n))


def test_chunk_size_and_read_split_do_not_change_data(scene, pitch, tmp_path):
    a = simulate(scene, pitch, cache_dir=tmp_path / "a", projector=FakeProjector(), chunk=7, progress=False)
    b = simulate(scene, pitch, cache_dir=tmp_path / "b", projector=FakeProjector(), chunk=1000, progress=False)
    n = len(a)
    np.testing.assert_array_equal(a.read(0, n), b.read(0, n))
    noisy = a.read(0, n, noisy=True)
    assert not np.array_equal(noisy, a.read(0, n))
    split = np.concatenate([b.read(s, min(s + 37, n), noisy=True) for s in range(0, n, 37)])
    np.testing.assert_array_equal(noisy, split)


def test_interrupted_write_resumes_identically(scene, pitch, tmp_path):
    n = len(projection_table(scene, pitch))
    with pytest.raises(RuntimeError, match="projector died"):
        simulate(scene, pitch, cache_dir=tmp_path, projector=FakeProjector(fail_after=3), chunk=40, progress=False)
    # Nothing that looks finished: only the units folder, with the 3 finished chunks.
    h = scene.scan_hash(pitch)
    assert _files(tmp_path) == [f"{h}.h5.units"]
    assert len(_files(tmp_path / f"{h}.h5.units")) == 3
    half = ProjectionStore.open(scene, pitch, cache_dir=tmp_path)
    assert half.state == "partial" and not half.complete
    with pytest.raises(StoreError, match="not finished"):
        half.read(0, 10)

    fake = FakeProjector()
    resumed = simulate(scene, pitch, cache_dir=tmp_path, projector=fake, chunk=40, progress=False)
    assert (resumed.n_simulated, resumed.n_reused) == (n - 120, 120) and fake.projected == n - 120
    assert resumed.complete and _files(tmp_path) == [f"{h}.h5"]
    ref = simulate(scene, pitch, cache_dir=tmp_path / "ref", projector=FakeProjector(), chunk=40, progress=False)
    np.testing.assert_array_equal(resumed.read(0, n), ref.read(0, n))


def test_interrupting_an_extension_of_a_finished_store(scene, pitch, tmp_path):
    """Adding projections to an existing .h5 leaves the .h5 untouched until the new one is assembled."""
    n = len(projection_table(scene, pitch))
    needed = np.zeros(n, dtype=bool)
    needed[:50] = True
    simulate(scene, pitch, needed=needed, cache_dir=tmp_path, projector=FakeProjector(), progress=False)
    with pytest.raises(RuntimeError):
        simulate(scene, pitch, cache_dir=tmp_path, projector=FakeProjector(fail_after=1), chunk=30, progress=False)
    assert sorted(p.suffix for p in tmp_path.iterdir()) == [".h5", ".units"]
    store = simulate(scene, pitch, cache_dir=tmp_path, projector=FakeProjector(), progress=False)
    assert store.n_reused == 80 and store.complete


def test_corrupt_file_raises_store_error(scene, pitch, tmp_path):
    store = simulate(scene, pitch, cache_dir=tmp_path, projector=FakeProjector(), progress=False)
    store.close()
    path = store.path
    size = path.stat().st_size
    with open(path, "r+b") as f:
        f.truncate(size // 3)
    with pytest.raises(StoreError) as e:
        simulate(scene, pitch, cache_dir=tmp_path, projector=FakeProjector(), progress=False)
    msg = str(e.value)
    assert str(path) in msg and "\n" not in msg
    path.write_bytes(b"not an HDF5 file at all")
    with pytest.raises(StoreError, match="corrupt"):
        ProjectionStore.open(scene, pitch, cache_dir=tmp_path)


def test_wrong_hash_inside_is_corrupt(scene, pitch, tmp_path):
    store = simulate(scene, pitch, cache_dir=tmp_path, projector=FakeProjector(), progress=False)
    store.close()
    with h5py.File(store.path, "r+") as f:
        f.attrs["scan_hash"] = "0123456789abcdef"
    with pytest.raises(StoreError, match="scan hash"):
        ProjectionStore.open(scene, pitch, cache_dir=tmp_path)


def test_torn_assembly_partial_is_discarded(scene, pitch, tmp_path):
    """A .partial is only ever an assembly in progress: the next open discards it and rebuilds."""
    (tmp_path / f"{scene.scan_hash(pitch)}.h5.partial").write_bytes(b"garbage")
    with pytest.warns(UserWarning, match="unfinished assembly"):
        store = simulate(scene, pitch, cache_dir=tmp_path, projector=FakeProjector(), progress=False)
    assert store.complete and store.n_simulated == len(store)


def test_damaged_unit_is_detected_and_redone(scene, pitch, tmp_path):
    n = len(projection_table(scene, pitch))
    with pytest.raises(RuntimeError, match="projector died"):
        simulate(scene, pitch, cache_dir=tmp_path, projector=FakeProjector(fail_after=3), chunk=40, progress=False)
    folder = tmp_path / f"{scene.scan_hash(pitch)}.h5.units"
    unit = sorted(folder.iterdir())[1]
    raw = bytearray(unit.read_bytes())
    raw[len(raw) // 2] ^= 0xFF                                   # one flipped byte in the data
    unit.write_bytes(bytes(raw))
    (folder / ".p000000120-000000159.123.tmp").write_bytes(b"torn")  # a unit killed mid-write
    fake = FakeProjector()
    with pytest.warns(UserWarning, match="damaged unit"):
        resumed = simulate(scene, pitch, cache_dir=tmp_path, projector=fake, chunk=40, progress=False)
    assert (resumed.n_simulated, resumed.n_reused) == (n - 80, 80)  # the damaged chunk is simulated again
    assert resumed.complete and _files(tmp_path) == [f"{scene.scan_hash(pitch)}.h5"]
    ref = simulate(scene, pitch, cache_dir=tmp_path / "ref", projector=FakeProjector(), chunk=40, progress=False)
    np.testing.assert_array_equal(resumed.read(0, n), ref.read(0, n))


def test_stale_table_is_resimulated(scene, pitch, tmp_path):
    store = simulate(scene, pitch, cache_dir=tmp_path, projector=FakeProjector(), progress=False)
    store.close()
    with h5py.File(store.path, "r+") as f:
        f["table/state_resp"][0] += 0.5
    with pytest.warns(UserWarning, match="stale"):
        again = simulate(scene, pitch, cache_dir=tmp_path, projector=FakeProjector(), progress=False)
    assert again.n_simulated == len(again)


def test_open_without_store_and_bad_arguments(scene, pitch, tmp_path):
    with pytest.raises(StoreError, match="run simulate first"):
        ProjectionStore.open(scene, pitch, cache_dir=tmp_path, create=False)
    n = len(projection_table(scene, pitch))
    with pytest.raises(TypeError, match="boolean"):
        simulate(scene, pitch, needed=np.arange(n), cache_dir=tmp_path, projector=FakeProjector())
    with pytest.raises(ValueError, match="shape"):
        simulate(scene, pitch, needed=np.ones(n + 1, bool), cache_dir=tmp_path, projector=FakeProjector())
    quiet = scene.replace(noise={"enabled": False})
    store = simulate(quiet, pitch, cache_dir=tmp_path, projector=FakeProjector(), progress=False)
    with pytest.raises(ValueError, match="noise"):
        store.read(0, 4, noisy=True)
    with pytest.raises(ValueError, match="range"):
        store.read(5, n + 1)


def test_noise_settings_do_not_change_the_store(scene, pitch, tmp_path):
    """Noise is applied on read: a new noise seed reuses the same store."""
    simulate(scene, pitch, cache_dir=tmp_path, projector=FakeProjector(), progress=False)
    other = scene.replace(noise={"seed": 99})
    store = simulate(other, pitch, cache_dir=tmp_path, projector=FakeProjector(fail_after=0), progress=False)
    assert store.n_simulated == 0


def test_default_cache_dir(monkeypatch, tmp_path):
    monkeypatch.setenv("CLRECON_CACHE", str(tmp_path / "c"))
    assert default_cache_dir() == tmp_path / "c"
    monkeypatch.delenv("CLRECON_CACHE")
    assert default_cache_dir().name == "clrecon"


def test_hash_covers_the_signal_trace(scene, pitch):
    """Same pitch, but a longer scan at another pitch lengthens the trace -> another store."""
    long_coverage = scene.replace(scan={"coverage_mm": 400.0})
    both = long_coverage.replace(scan={"pitches": [pitch, pitch / 2]})
    assert both.scan.duration_s(both.scanner, pitch / 2) > 60.0  # the 60 s trace no longer suffices
    assert both.scan_hash(pitch) != long_coverage.scan_hash(pitch)
    # Short scans all use the 60 s trace: adding a pitch does not change the store.
    assert scene.replace(scan={"pitches": [pitch, 0.5]}).scan_hash(pitch) == scene.scan_hash(pitch)


def test_units_are_compressed_and_their_chunks_go_into_the_store_as_they_are(scene, pitch, tmp_path, monkeypatch):
    """Disk (issue 20): units compressed like the store; the assembly copies their whole chunks, bit-identical."""
    from clrecon.core import units
    from clrecon.simulation import store as store_mod

    r, c = scene.scanner.n_rows, scene.scanner.n_cols
    rc = min(store_mod.ROW_CHUNK, r)
    monkeypatch.setattr(store_mod, "CHUNK_BYTES", 8 * rc * c * 4)   # 8 projections per chunk: units straddle chunks
    row_blocks = -(-r // rc)                                         # chunks per 8 projections (rows in blocks)
    h = scene.scan_hash(pitch)
    with pytest.raises(RuntimeError, match="projector died"):
        simulate(scene, pitch, cache_dir=tmp_path / "a", projector=FakeProjector(fail_after=3), chunk=42,
                 progress=False)
    unit_files = sorted((tmp_path / "a" / f"{h}.h5.units").glob("*.unit"))
    assert len(unit_files) == 3
    assert sum(p.stat().st_size for p in unit_files) < 0.8 * 3 * 42 * r * c * 4   # compressed
    arrays, meta = units.read_unit(unit_files[1])                                  # indices 42..83
    assert (len(arrays["head"]), len(arrays["data"]), len(arrays["tail"])) == (6, 32, 4)
    a = simulate(scene, pitch, cache_dir=tmp_path / "a", projector=FakeProjector(), chunk=42, progress=False)
    # 4 or 5 whole blocks of 8 projections in a 42-projection unit, each of row_blocks chunks
    assert a.complete and a.chunks_copied >= 4 * row_blocks * (len(a) // 42 - 1)
    with h5py.File(a.path, "r") as f:
        assert f["projections"].chunks == (8, rc, c)

    def decoded(ds, uf, first):  # the same store with every unit decoded and compressed by the store itself
        rows = np.concatenate([uf["head"][()], uf["data"][()], uf["tail"][()]])
        ds[first:first + len(rows)] = rows
        return 0

    monkeypatch.setattr(store_mod.ProjectionStore, "_copy_aligned", staticmethod(decoded))
    b = simulate(scene, pitch, cache_dir=tmp_path / "b", projector=FakeProjector(), chunk=42, progress=False)
    assert b.chunks_copied == 0
    n = len(a)
    # values bit-identical (LZF's compressed bytes themselves are not reproducible: its hash table
    # starts uninitialised, so the same chunk may compress to other, equally valid bytes)
    assert a.read(0, n).tobytes() == b.read(0, n).tobytes()


def test_an_earlier_versions_npz_units_are_assembled(scene, pitch, tmp_path):
    """Units left by an interrupted run of an earlier clrecon (uncompressed .npz) still resume."""
    from clrecon.core import units

    n = len(projection_table(scene, pitch))
    st = ProjectionStore.open(scene, pitch, cache_dir=tmp_path)
    data = FakeProjector()(scene, projection_table(scene, pitch))
    units.write_unit(st.units_path, "p000000000-000000099", {"indices": np.arange(100), "data": data[:100]},
                     {"scan_hash": st.scan_hash, "indices": list(range(100))}, "simulate")   # compress=None: .npz
    resumed = simulate(scene, pitch, cache_dir=tmp_path, projector=FakeProjector(), progress=False)
    assert (resumed.n_simulated, resumed.n_reused) == (n - 100, 100)
    np.testing.assert_array_equal(resumed.read(0, n), data)


def test_the_default_projectors_blocks_of_chunks_give_the_same_store(scene, pitch, tmp_path):
    """The default projector runs on blocks of up to BLOCK_CHUNKS chunks (the phantom posed once
    per block); the store is bit-identical to one projected chunk by chunk, with a unit per chunk."""
    from clrecon.simulation import simulate as simulate_mod
    from clrecon.simulation.projector import project

    calls = []

    def per_chunk(sc, table):
        calls.append(len(table))
        return project(sc, table)

    n = len(projection_table(scene, pitch))
    blocked = simulate(scene, pitch, cache_dir=tmp_path / "blocked", chunk=16, progress=False)
    chunked = simulate(scene, pitch, cache_dir=tmp_path / "chunked", projector=per_chunk, chunk=16, progress=False)
    assert max(calls) == 16 and sum(calls) == n
    assert simulate_mod.BLOCK_CHUNKS > 1
    np.testing.assert_array_equal(blocked.read(0, n), chunked.read(0, n))
