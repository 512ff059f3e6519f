"""Disk at its peak (issue 20, item 3): the run folder's volumes, one compressed file per dataset.

``volumes.h5`` holds the axes and virtual datasets over ``volumes.d/<gen>/<name>.h5``; each
dataset file is assembled from its (compressed) units, fsync'd and renamed, and only then are
its units deleted, so the disk never holds the result twice. These tests check that
bookkeeping, that a moved or copied run folder still reads, that a folder without its
``volumes.d`` says so in one line, that an earlier version's single-file ``volumes.h5`` and
``.npz`` units still work, and that the projection store's units are compressed.
"""

from __future__ import annotations

import json
import shutil

import h5py
import numpy as np
import pytest
from fake_run_dir import make_fake_run

from clrecon.core import faults, units
from clrecon.core.errors import StoreError
from clrecon.outputs.rundir import RunDirectory, open_volume_store
from clrecon.outputs.volumes import VolumeWriter, list_recons, open_volumes, read_volume

NZ, NY, NX = 6, 64, 48
AXES = {"cardiac_phase": [0.0, 0.5], "resp_amplitude": [0.2, 0.4, 0.6], "z_mm": np.arange(NZ, dtype=float),
        "y_mm": np.arange(NY, dtype=float), "x_mm": np.arange(NX, dtype=float)}
SHAPE = (2, 3, NZ, NY, NX)
NAMES = [f"recon/p0.100/noise-free/m{k}" for k in range(4)]


def _vol(k: int) -> np.ndarray:
    """CT-like: smooth HU with some noise inside a circular field of view, zero outside (it compresses)."""
    rng = np.random.default_rng(k)
    z, y, x = np.meshgrid(np.arange(NZ), np.arange(NY), np.arange(NX), indexing="ij")
    v = 40.0 * np.round(25 * np.cos(y / 9.0 + k) * np.sin(x / 7.0)) + z
    v = np.broadcast_to(v, SHAPE) + rng.normal(0, 3, SHAPE)
    v[..., (y[0] - NY / 2) ** 2 + (x[0] - NX / 2) ** 2 > (NX / 2) ** 2] = 0.0
    return v.astype(np.float32)


def _fill(path, run_key="k", slabs=((0, 3), (3, 6)), compression="lzf") -> VolumeWriter:
    w = VolumeWriter(path / "volumes.h5", AXES, True, True, run_key=run_key, dtype="float16",
                     compression=compression)
    for k, name in enumerate(NAMES):
        w.create(name, SHAPE, NZ)
        for a, b in slabs:
            w.write(name, _vol(k)[:, :, a:b], np.arange(a, b))
    w.create("groundtruth", SHAPE, 6)
    for t in range(6):
        i, j = divmod(t, 3)
        w.write_target("groundtruth", i, j, 3, _vol(9)[i, j])
    return w


def _expected(name: str) -> np.ndarray:
    k = 9 if name == "groundtruth" else NAMES.index(name)
    return _vol(k).astype(np.float16).astype(np.float32)


def _files(d):
    return sorted(str(p.relative_to(d)) for p in d.rglob("*") if p.is_file())


def test_each_dataset_is_assembled_then_its_units_go_and_the_peak_is_result_plus_one_dataset(tmp_path, monkeypatch):
    w = _fill(tmp_path)
    unit_bytes = sum(p.stat().st_size for p in w.units_dir.glob("*.unit"))
    raw = (len(NAMES) + 1) * int(np.prod(SHAPE)) * 2
    assert unit_bytes < 0.8 * raw                      # units are written compressed
    seen = []
    real = faults.point

    def spy(name):
        if name == "rename-dataset":  # the k-th dataset's partial is complete: earlier datasets' units are gone
            left = {m["name"] for p, m in units.scan_units(w.units_dir)}
            finished = {str(p.name) for p in w.datasets_dir.glob("*.h5")}
            seen.append((left, finished))
            for f in finished:
                assert f[:-3].replace("~", "/") not in left, (f, left)
        real(name)

    monkeypatch.setattr(faults, "point", spy)
    w.close()
    assert len(seen) == len(NAMES) + 1
    assert [len(f) for _, f in seen] == list(range(len(NAMES) + 1))
    assert not w.units_dir.exists() and not w.partial.exists()
    sizes = {p.name: p.stat().st_size for p in w.datasets_dir.glob("*.h5")}
    result = sum(sizes.values()) + w.path.stat().st_size
    peak = max(b for _, b in w.disk_trace)
    assert peak <= result + max(sizes.values()) + 64 * 1024, (peak, result, w.disk_trace)
    with open_volumes(tmp_path) as f:
        assert sorted(m for _, _, m in list_recons(f)) == [n.rsplit("/", 1)[1] for n in NAMES]
        for name in NAMES + ["groundtruth"]:
            assert f[name].is_virtual
            np.testing.assert_array_equal(read_volume(f, name), _expected(name), err_msg=name)


def test_direct_chunk_copy_is_bit_identical_to_a_plain_write(tmp_path):
    a, b = tmp_path / "a", tmp_path / "b"
    _fill(a, slabs=((0, 2), (2, 5), (5, 6))).close()
    _fill(b, slabs=((0, 6),)).close()
    with open_volumes(a) as fa, open_volumes(b) as fb:
        for name in NAMES + ["groundtruth"]:
            assert fa[name][()].tobytes() == fb[name][()].tobytes() == _vol(
                9 if name == "groundtruth" else NAMES.index(name)).astype(np.float16).reshape(
                fa[name].shape).tobytes()


def test_uncompressed_volumes_hold_the_same_values_and_resume_over_compressed_units(tmp_path):
    """recon.volume_compression = "none" (auto on small runs): plain chunks, the same bytes read back;
    a run resumed with the other setting copies the earlier units in (decoded), values unchanged."""
    a, b = tmp_path / "lzf", tmp_path / "none"
    _fill(a).close()
    _fill(b, compression="none").close()
    with open_volumes(a) as fa, open_volumes(b) as fb:
        for name in NAMES + ["groundtruth"]:
            assert fa[name][()].tobytes() == fb[name][()].tobytes()
    for d, want in ((a, "lzf"), (b, None)):
        files = sorted((d / "volumes.d").rglob("*.h5"))
        assert len(files) == len(NAMES) + 1
        for p in files:
            with h5py.File(p, "r") as f:
                assert f["volume"].compression == want, p
    # units written compressed, assembled by an uncompressed writer (same run key): decoded, same values
    c = tmp_path / "mixed"
    _fill(c)
    w2 = VolumeWriter(c / "volumes.h5", AXES, True, True, run_key="k", dtype="float16", compression="none")
    assert w2.resumed
    for name in NAMES:
        w2.create(name, SHAPE, NZ)
    w2.create("groundtruth", SHAPE, 6)
    w2.close()
    with open_volumes(c) as fc, open_volumes(a) as fa:
        for name in NAMES + ["groundtruth"]:
            assert fc[name][()].tobytes() == fa[name][()].tobytes()
    with pytest.raises(ValueError, match="allowed lzf, none"):
        VolumeWriter(tmp_path / "x" / "volumes.h5", AXES, True, True, compression="gzip")


def test_a_moved_or_copied_run_folder_still_reads(tmp_path):
    src = tmp_path / "run"
    make_fake_run(src, methods=("nearest", "local_linear"), pitches=(0.1,))
    with RunDirectory(src) as r:
        before = {s.name: r.read(s) for s in r.sources}
    copy = tmp_path / "elsewhere" / "deeper" / "copy"
    shutil.copytree(src, copy)
    moved = tmp_path / "moved"
    src.rename(moved)
    for d in (copy, moved):
        with RunDirectory(d) as r:
            got = {s.name: r.read(s) for s in r.sources}
        assert got.keys() == before.keys()
        for k in got:
            np.testing.assert_array_equal(got[k], before[k], err_msg=f"{d}: {k}")
    shutil.rmtree(copy / "volumes.d")
    with pytest.raises(StoreError, match="dataset files are missing") as e:
        open_volume_store(copy)
    assert "\n" not in str(e.value) and "volumes.d/" in str(e.value)


def test_an_earlier_versions_single_file_volumes_still_reads(tmp_path):
    new = tmp_path / "new"
    make_fake_run(new, methods=("nearest",), pitches=(0.1,))
    old = tmp_path / "old"
    old.mkdir()
    shutil.copy(new / "results.json", old / "results.json")
    with h5py.File(new / "volumes.h5", "r") as f, h5py.File(old / "volumes.h5", "w") as g:  # format 1, by hand
        g.attrs["format_version"] = 1
        for k in f["axes"]:
            g[f"axes/{k}"] = f["axes"][k][()]
        names = []
        f.visititems(lambda n, o: names.append(n) if isinstance(o, h5py.Dataset) and not n.startswith("axes") else None)
        for n in names:
            ds = g.create_dataset(n, data=f[n][()], chunks=(1,) * (f[n].ndim - 2) + f[n].shape[-2:])
            for a in ("dims", "broadcast", "units", "done"):
                ds.attrs[a] = f[n].attrs[a]
    with RunDirectory(new) as a, RunDirectory(old) as b:
        assert [s.name for s in a.sources] == [s.name for s in b.sources]
        for s in a.sources:
            np.testing.assert_array_equal(a.read(s), b.read(s))
    with h5py.File(old / "volumes.h5", "a") as g:
        g.attrs["format_version"] = 7
    with pytest.raises(StoreError, match="volume format 7 is not 2"):
        open_volume_store(old)


def test_an_earlier_versions_npz_units_resume(tmp_path):
    w = VolumeWriter(tmp_path / "volumes.h5", AXES, True, True, run_key="k", dtype="float16")
    w.create(NAMES[0], SHAPE, NZ)
    vol = _vol(0).astype(np.float16)
    meta = {"name": NAMES[0], "shape": list(SHAPE), "z": [0, 1, 2]}
    units.write_unit(w.units_dir, "recon~p0.100~noise-free~m0.z00000-00002", {"data": vol[:, :, :3]}, meta, "recon")
    assert units.read_unit(next(w.units_dir.glob("*.unit")))[1] == meta  # an .npz (compress=None)
    w.abort()
    w = VolumeWriter(tmp_path / "volumes.h5", AXES, True, True, run_key="k", dtype="float16")
    assert w.resumed
    w.create(NAMES[0], SHAPE, NZ)
    assert w.done(NAMES[0]).tolist() == [True] * 3 + [False] * 3
    w.write(NAMES[0], _vol(0)[:, :, 3:], np.arange(3, 6))
    assert w.units_written["recon"] == 1
    w.close()
    with open_volumes(tmp_path) as f:
        assert f[NAMES[0]][()].tobytes() == vol.tobytes()


def test_a_resumed_run_keeps_its_assembled_datasets(tmp_path, monkeypatch):
    w = _fill(tmp_path)

    def die(name):
        if name == "rename-dataset" and len(list(w.datasets_dir.glob("*.h5"))) == 2:
            raise KeyboardInterrupt  # (a SIGKILL here is tests/test_crash.py's rename-dataset case)

    monkeypatch.setattr(faults, "point", die)
    with pytest.raises(KeyboardInterrupt):
        w.close()
    w.abort()
    monkeypatch.setattr(faults, "point", lambda name: None)
    w2 = VolumeWriter(tmp_path / "volumes.h5", AXES, True, True, run_key="k", dtype="float16")
    assert w2.resumed and w2.datasets_dir == w.datasets_dir
    for name in NAMES:
        w2.create(name, SHAPE, NZ)
        assert w2.done(name).all()
    w2.create("groundtruth", SHAPE, 6)
    assert w2.done("groundtruth").all()
    assert sum(len(v) for v in w2._units.values()) == 2 * 2 + 6  # the first two datasets' units are gone
    w2.close()
    with open_volumes(tmp_path) as f:
        for name in NAMES + ["groundtruth"]:
            np.testing.assert_array_equal(read_volume(f, name), _expected(name), err_msg=name)


def test_a_different_request_keeps_the_earlier_result_readable_until_it_replaces_it(tmp_path):
    _fill(tmp_path, run_key="first").close()
    first = json.dumps(sorted(_files(tmp_path)))
    w = VolumeWriter(tmp_path / "volumes.h5", AXES, True, True, run_key="second", dtype="float16")
    w.create(NAMES[0], SHAPE, NZ)
    w.write(NAMES[0], _vol(5), np.arange(NZ))
    with open_volumes(tmp_path) as f:  # the first result, intact
        np.testing.assert_array_equal(read_volume(f, NAMES[1]), _expected(NAMES[1]))
    w.close()
    assert len(list((tmp_path / "volumes.d").iterdir())) == 1   # the first result's files are gone
    with open_volumes(tmp_path) as f:
        assert [m for _, _, m in list_recons(f)] == ["m0"]
        np.testing.assert_array_equal(read_volume(f, NAMES[0]), _vol(5).astype(np.float16).astype(np.float32))
    assert first != json.dumps(sorted(_files(tmp_path)))


def test_compressed_units_round_trip_and_are_detected_when_damaged(tmp_path):
    arr = np.repeat(np.arange(40, dtype=np.float32) / 8, 100).reshape(40, 100)
    p = units.write_unit(tmp_path, "u", {"data": arr, "idx": np.arange(40)}, {"a": 1}, "simulate",
                         compress={"data": (8, 100)})
    assert p.read_bytes()[:8] == units.H5_MAGIC and p.stat().st_size < arr.nbytes
    got, meta = units.read_unit(p)
    assert meta == {"a": 1} and got["data"].tobytes() == arr.tobytes() and got["idx"].tolist() == list(range(40))
    raw = bytearray(p.read_bytes())
    raw[len(raw) // 2] ^= 0xFF
    p.write_bytes(bytes(raw))
    with pytest.warns(UserWarning, match="damaged unit file"):
        assert units.scan_units(tmp_path) == []
