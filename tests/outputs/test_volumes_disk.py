"""Disk at its peak (issue 20, item 3): the run folder's volumes, written once, in place.

Each block is a compressed unit file written straight into ``volumes.d/<gen>/``; ``volumes.h5``
holds the axes and virtual datasets mapping those units, so assembling copies no data and the
disk never holds a block twice. These tests check that, that a moved or copied run folder still
reads, that a folder without its ``volumes.d`` says so in one line, that an earlier version's
single-file ``volumes.h5``, ``.npz`` units and interrupted per-dataset assembly (format 2) still
work, and that the projection store's units are compressed.
"""

from __future__ import annotations

import json
import os
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
    w.create("groundtruth", SHAPE, 6, blocks="targets")
    for t in range(6):
        i, j = divmod(t, 3)
        w.write_target("groundtruth", i, j, 3, _vol(9)[i, j])
    return w


def _expected(name: str) -> np.ndarray:
    k = 9 if name == "groundtruth" else NAMES.index(name)
    return _vol(k).astype(np.float16).astype(np.float32)


def _files(d):
    return sorted(str(p.relative_to(d)) for p in d.rglob("*") if p.is_file())


def test_the_units_are_the_result_assembly_copies_nothing_and_the_peak_is_the_result(tmp_path, monkeypatch):
    w = _fill(tmp_path)
    assert [p.name for p in w.units_dir.iterdir()] == ["run.json"]        # the units are in the result's folder
    unit_files = sorted(w.datasets_dir.glob("*.unit"))
    assert len(unit_files) == 2 * len(NAMES) + 6
    unit_bytes = sum(p.stat().st_size for p in unit_files)
    raw = (len(NAMES) + 1) * int(np.prod(SHAPE)) * 2
    assert unit_bytes < 0.8 * raw                      # units are written compressed
    before = {p.name: (p.stat().st_ino, p.stat().st_mtime_ns) for p in unit_files}
    mapped = []
    real = faults.point
    monkeypatch.setattr(faults, "point", lambda name: (mapped.append(name), real(name)))
    w.close()
    assert mapped.count("assemble-volumes") == len(NAMES) + 1 and mapped[-1] == "rename-volumes"
    after = {p.name: (p.stat().st_ino, p.stat().st_mtime_ns) for p in w.datasets_dir.iterdir()}
    assert after == before                              # no file written, moved or removed by the assembly
    assert not w.units_dir.exists() and not w.partial.exists()
    result = unit_bytes + w.path.stat().st_size
    peak = max(b for _, b in w.disk_trace)
    assert peak <= result + 4096, (peak, result, w.disk_trace)
    assert w.path.stat().st_size < 64 * 1024            # volumes.h5: axes and mappings only
    with open_volumes(tmp_path) as f:
        assert sorted(m for _, _, m in list_recons(f)) == [n.rsplit("/", 1)[1] for n in NAMES]
        for name in NAMES + ["groundtruth"]:
            assert f[name].is_virtual
            assert len(f[name].virtual_sources()) == (6 if name == "groundtruth" else 2)
            np.testing.assert_array_equal(read_volume(f, name), _expected(name), err_msg=name)


def test_slabs_of_any_size_read_back_bit_identical_to_one_slab(tmp_path):
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
    a run resumed with the other setting maps the earlier (compressed) units as they are, values unchanged."""
    a, b = tmp_path / "lzf", tmp_path / "none"
    _fill(a).close()
    _fill(b, compression="none").close()
    with open_volumes(a) as fa, open_volumes(b) as fb:
        for name in NAMES + ["groundtruth"]:
            assert fa[name][()].tobytes() == fb[name][()].tobytes()
    for d, want in ((a, "lzf"), (b, None)):
        files = sorted((d / "volumes.d").rglob("*.unit"))
        assert len(files) == 2 * len(NAMES) + 6
        for p in files:
            with h5py.File(p, "r") as f:
                assert f["data"].compression == want, p
    # units written compressed, assembled by an uncompressed writer (same run key): decoded, same values
    c = tmp_path / "mixed"
    _fill(c)
    w2 = VolumeWriter(c / "volumes.h5", AXES, True, True, run_key="k", dtype="float16", compression="none")
    assert w2.resumed
    for name in NAMES:
        w2.create(name, SHAPE, NZ)
    w2.create("groundtruth", SHAPE, 6, blocks="targets")
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
    with pytest.raises(StoreError, match="read from files missing") as e:
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
    with pytest.raises(StoreError, match="volume format 7 is not 3"):
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
    assert all(p.read_bytes()[:8] == units.H5_MAGIC for p in w.datasets_dir.glob("*.unit"))  # rewritten once
    assert len(list(w.datasets_dir.glob("*.unit"))) == 2
    with open_volumes(tmp_path) as f:
        assert f[NAMES[0]][()].tobytes() == vol.tobytes()


def _format2_dataset_file(path, name, vol16, done, run_key="k"):
    """A dataset file as an earlier version's assembly (format 2) left it: ``/volume`` with its ``done`` mask."""
    with h5py.File(path, "w") as f:
        f.attrs.update({"format_version": 2, "run_key": run_key, "name": name})
        ds = f.create_dataset("volume", data=np.where(np.isnan(vol16), 0, vol16).astype(np.float16),
                              chunks=(1,) * (vol16.ndim - 2) + vol16.shape[-2:], **units.VOLUME_FILTERS)
        ds.attrs["done"] = np.asarray(done, np.uint8)


def test_an_earlier_versions_interrupted_per_dataset_assembly_resumes(tmp_path):
    """Format 2 left two dataset files (one only partly done, the slices 0-2) and the other units
    in volumes.h5.units/: the resumed run maps the files' finished blocks, moves the units into
    place, computes only what is missing, and reads back exactly the uninterrupted values."""
    w = _fill(tmp_path)
    w.abort()
    gen_dir = w.datasets_dir
    old_units = tmp_path / "volumes.h5.units"
    for p in gen_dir.glob("*.unit"):                    # where format 2 kept them
        os.replace(p, old_units / p.name)
    full0, gt = _expected(NAMES[0]).astype(np.float16), _expected("groundtruth").astype(np.float16)
    part0 = full0.copy()
    part0[:, :, 3:] = 0                                  # the unfinished slices of a partly done file
    _format2_dataset_file(w.dataset_path(NAMES[0]), NAMES[0], part0, [1, 1, 1, 0, 0, 0])
    _format2_dataset_file(w.dataset_path("groundtruth"), "groundtruth", gt, [1, 0, 1, 1, 0, 1])
    for p in list(old_units.glob("*.unit")):            # their units were dropped after the file was renamed
        m = units.read_meta(p)
        if (m["name"] == NAMES[0] and m["z"][0] == 0) or (m["name"] == "groundtruth" and m["target"] in (0, 2, 3, 5)):
            p.unlink()
    w2 = VolumeWriter(tmp_path / "volumes.h5", AXES, True, True, run_key="k", dtype="float16")
    assert w2.resumed and w2.datasets_dir == gen_dir
    assert [p.name for p in old_units.iterdir()] == ["run.json"]  # the units moved into the result's folder
    for name in NAMES:
        w2.create(name, SHAPE, NZ)
        assert w2.done(name).all()
    w2.create("groundtruth", SHAPE, 6, blocks="targets")
    assert w2.done("groundtruth").all()
    assert sum(len(v) for v in w2._units.values()) == 2 * len(NAMES) - 1 + 2
    w2.close()
    assert w2.units_written == {"recon": 0, "truth": 0}
    with open_volumes(tmp_path) as f:
        assert len(f[NAMES[0]].virtual_sources()) == 2 and len(f["groundtruth"].virtual_sources()) == 4 + 2
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
