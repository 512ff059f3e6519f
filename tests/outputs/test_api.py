"""The notebook API (``clrecon.load_scene / run / open_run``): docs/api.md runs, open_run is lazy."""

from __future__ import annotations

import json
import re
import time
from pathlib import Path

import h5py
import numpy as np
import pytest
from fake_run_dir import fake_scene, make_fake_run

import clrecon
from clrecon.api import _slices, _targets
from clrecon.core.errors import ClreconError, SceneError
from clrecon.outputs.rundir import RunDirectory
from clrecon.outputs.volumes import open_volumes, read_volume

pytest.importorskip("xarray")

DOC = Path(__file__).resolve().parents[2] / "docs" / "api.md"


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    d = tmp_path_factory.mktemp("run")
    make_fake_run(d, methods=("nearest", "local_linear"), pitches=(0.1,))
    return d


@pytest.fixture
def h5_reads(monkeypatch):
    """Names of the HDF5 datasets indexed (``Dataset.__getitem__``) while the fixture is active."""
    seen: list[str] = []
    orig = h5py.Dataset.__getitem__

    def spy(self, *args, **kwargs):
        seen.append(self.name)
        return orig(self, *args, **kwargs)

    monkeypatch.setattr(h5py.Dataset, "__getitem__", spy)
    return seen


def python_blocks(text: str) -> list[str]:
    return re.findall(r"^```python\n(.*?)^```", text, re.S | re.M)


def test_docs_example_runs(tmp_path, monkeypatch):
    """Every python block of docs/api.md, in order, in one namespace (tiny scene, a few seconds)."""
    monkeypatch.setenv("CLRECON_CACHE", str(tmp_path / "cache"))
    monkeypatch.setenv("CLRECON_NO_PROGRESS", "1")
    monkeypatch.chdir(tmp_path)
    blocks = python_blocks(DOC.read_text())
    assert len(blocks) >= 4
    ns: dict = {}
    t0 = time.perf_counter()
    for k, code in enumerate(blocks):
        exec(compile(code, f"{DOC}:block{k}", "exec"), ns)
    assert time.perf_counter() - t0 < 120  # a few seconds normally; generous on shared CPUs
    res = ns["result"]
    assert isinstance(res, clrecon.RunResult) and (tmp_path / res.path / "results.json").exists()
    assert res.results["request"]["methods"] == ["nearest"] and res.results["request"]["slices"] == [0, 1]
    assert list((tmp_path / "cache").glob("*.h5")), "the projection store went to $CLRECON_CACHE"
    assert ns["one"].shape == (1, 32, 32) and float(ns["one"].resp) == 0.25
    assert ns["target"].dims == ("y", "x") and float(ns["target"].cardiac) == 0.4  # the stacked block
    assert ns["err"].dims == ("variant", "cardiac", "resp", "z", "y", "x")


def test_open_run_is_lazy_and_reads_one_target(run_dir, h5_reads):
    ds = clrecon.open_run(run_dir)
    try:
        assert all(name.startswith("/axes/") for name in h5_reads), h5_reads  # no voxel read on open
        name = "nearest_p0.100_noisy"
        repr(ds)
        ds[name].attrs, ds[name].shape
        part = ds[name].isel(cardiac=1, resp=2)
        assert all(n.startswith("/axes/") for n in h5_reads)
        h5_reads.clear()
        values = part.values
        assert h5_reads == ["/recon/p0.100/noisy/nearest"]  # one hyperslab read, of that volume only
        with open_volumes(run_dir) as f:
            np.testing.assert_array_equal(values, read_volume(f, "recon/p0.100/noisy/nearest", (1, 2)))
    finally:
        ds.close()


def test_open_run_dims_coords_and_attrs(run_dir):
    with clrecon.open_run(run_dir) as ds, RunDirectory(run_dir) as run:
        assert tuple(ds.sizes) == ("cardiac", "resp", "z", "y", "x")
        assert dict(ds.sizes) == dict(zip(("cardiac", "resp", "z", "y", "x"), run.shape, strict=True))
        for dim, axis in (("cardiac", "cardiac_phase"), ("resp", "resp_amplitude"), ("z", "z_mm"), ("y", "y_mm"),
                          ("x", "x_mm")):
            np.testing.assert_array_equal(ds[dim].values, run.axes[axis])
        assert ds.z.attrs["units"] == "mm"
        assert set(ds.data_vars) == {"groundtruth", "phantom"} | {
            f"{m}_p0.100_{v}" for m in ("nearest", "local_linear") for v in ("noisy", "noise-free")}
        v = ds["local_linear_p0.100_noise-free"]
        assert v.dims == ("cardiac", "resp", "z", "y", "x") and v.dtype == np.float32
        assert (v.attrs["method"], v.attrs["pitch"], v.attrs["variant"], v.attrs["units"]) == (
            "local_linear", 0.1, "noise-free", "HU")
        met = json.loads(ds.attrs["metrics"])
        assert v.attrs["mae_hu_small"] == met["p0.100"]["noise-free"]["local_linear"]["small"]["mae_hu"]
        assert json.loads(ds.attrs["results"])["scene"]["name"] == "tiny"
        assert ds.attrs["has_cardiac"] == 1 and ds.attrs["has_resp"] == 1
        sel = ds["groundtruth"].sel(cardiac=0.45, resp=0.9, method="nearest")
        assert (float(sel.cardiac), float(sel.resp)) == (0.4, float(run.resp[2]))
        np.testing.assert_array_equal(sel.values, run.read("groundtruth", (1, 2)))
        # basic, strided, reversed and list selections agree with numpy on the full array
        full = run.read("phantom")
        np.testing.assert_array_equal(ds["phantom"].isel(z=slice(None, None, -3), x=[5, 1, 2]).values,
                                      full[:, :, ::-3][..., [5, 1, 2]])
        np.testing.assert_array_equal(ds["phantom"].values, full)


def test_open_run_without_cardiac_axis_keeps_five_dims(tmp_path):
    scene = fake_scene().replace(phantom={"cardiac_motion": False})
    make_fake_run(tmp_path, methods=("local_linear",), pitches=(0.1,), variants=("noise-free",), scene=scene)
    with h5py.File(tmp_path / "volumes.h5") as f:
        assert list(f["groundtruth"].attrs["dims"]) == ["resp", "z", "y", "x"]
    with clrecon.open_run(tmp_path) as ds:
        assert dict(ds.sizes)["cardiac"] == 1 and ds.cardiac.values.tolist() == [0.0]
        assert ds.attrs["has_cardiac"] == 0 and ds.attrs["has_resp"] == 1
        v = ds["local_linear_p0.100_noise-free"]
        assert v.dims == ("cardiac", "resp", "z", "y", "x")
        with open_volumes(tmp_path) as f:
            np.testing.assert_array_equal(v.isel(cardiac=0, resp=1).values,
                                          read_volume(f, "recon/p0.100/noise-free/local_linear", (0, 1)))
            np.testing.assert_array_equal(v.values, read_volume(f, "recon/p0.100/noise-free/local_linear"))


def test_open_run_bad_paths_are_one_line_errors(tmp_path):
    with pytest.raises(ClreconError, match="no such run directory") as e:
        clrecon.open_run(tmp_path / "nope")
    assert "\n" not in str(e.value)
    (tmp_path / "empty").mkdir()
    with pytest.raises(ClreconError, match="no volumes in this run directory"):
        clrecon.open_run(tmp_path / "empty")
    (tmp_path / "notes.txt").write_text("x")
    with pytest.raises(ClreconError, match="expected a run directory"):
        clrecon.open_run(tmp_path / "notes.txt")
    old = tmp_path / "old"
    old.mkdir()
    with h5py.File(old / "volumes.h5", "w") as f:
        f.attrs["format_version"] = 0
    with pytest.raises(ClreconError, match="volume format 0 .*re-run") as e:
        clrecon.open_run(old)
    assert "\n" not in str(e.value)


def test_load_scene_overrides():
    s = clrecon.load_scene("tiny", recon={"nz": 4, "nx": 8}, recon__nx=16, noise__seed=3, **{"scan.pitches": [0.1]})
    assert (s.recon.nz, s.recon.nx, s.noise.seed, s.scan.pitches) == (4, 16, 3, (0.1,))
    assert s == clrecon.load_scene("tiny").replace(recon={"nz": 4, "nx": 16}, noise={"seed": 3})
    assert clrecon.load_scene(s) is s
    with pytest.raises(SceneError, match="recon.nzz: unknown key; did you mean 'nz'"):
        clrecon.load_scene("tiny", recon__nzz=4)
    with pytest.raises(SceneError, match="did you mean 'recon'"):
        clrecon.load_scene("tiny", recn={"nz": 4})
    with pytest.raises(SceneError, match="recon.nz = 0"):
        clrecon.load_scene("tiny", recon={"nz": 0})
    with pytest.raises(SceneError, match="expected a dict"):
        clrecon.load_scene("tiny", recon=4)


def test_overrides_reach_a_table_inside_a_section():
    """``recon__mc__rounds`` (a sweep's grid key) sets one key of ``[recon.mc]``; the table's other
    keys keep the scene's values, also through a dict."""
    base = clrecon.load_scene("tiny", recon__mc__margin_mm=30.0)
    assert base.recon.mc.margin_mm == 30.0 and base.recon.mc.rounds == 2
    s = clrecon.load_scene(base, recon__mc__rounds=1, **{"recon.mc.flow_radius": 5})
    assert (s.recon.mc.rounds, s.recon.mc.flow_radius, s.recon.mc.margin_mm) == (1, 5, 30.0)
    assert clrecon.load_scene(base, recon={"mc": {"rounds": 1}}).recon.mc.margin_mm == 30.0
    with pytest.raises(SceneError, match="recon.mc.rounds = 9"):
        clrecon.load_scene("tiny", recon__mc__rounds=9)
    with pytest.raises(SceneError, match="SECTION__TABLE__KEY"):
        clrecon.load_scene("tiny", recon__mc__rounds__x=1)


def test_run_arguments():
    assert _targets(None) == (None, None)
    assert _targets(([0, 0.4], None)) == ([0.0, 0.4], None)
    assert _targets({"resp": 0.25}) == (None, [0.25])
    with pytest.raises(ClreconError, match="unknown key 'card'"):
        _targets({"card": [0.1]})
    with pytest.raises(ClreconError, match="cardiac_list, resp_list"):
        _targets([0.1, 0.2, 0.3])
    assert _slices((0, 1), 4) == (0, 1) and _slices(slice(1, None), 4) == (1, 4) and _slices(None, 4) is None
    with pytest.raises(ClreconError, match="step 1"):
        _slices(slice(0, 4, 2), 4)


def test_run_directory_reader(run_dir, h5_reads):
    with RunDirectory(run_dir) as run:
        assert h5_reads == []  # axes and sources are read when first asked for
        assert run.shape == (3, 3, 10, 36, 40) and run.results["scene"]["name"] == "tiny"
        assert [s.label for s in run.sources][:2] == ["groundtruth", "phantom"]
        src = run.resolve()
        assert (src.method, src.pitch_key, src.variant, src.name) == ("local_linear", "p0.100", "noisy",
                                                                      "local_linear_p0.100_noisy")
        with pytest.raises(ClreconError, match="it has groundtruth, phantom; p0.100/noise-free"):
            run.resolve(method="bin")
        plane = run.read_part("groundtruth", cardiac=1, resp=0, y=7)
        np.testing.assert_array_equal(plane, run.read("groundtruth", (1, 0))[:, 7, :])
        assert run.pitches() == ["p0.100"] and run.dims(src) == ("cardiac", "resp", "z", "y", "x")
    assert not run.h5  # closed


# ----------------------------------------------------------------------------------------
# open_run(path, stacked=True): one lazy 8-D DataArray
STACK_DIMS = ("method", "pitch", "variant", "cardiac", "resp", "z", "y", "x")


def test_open_run_stacked_is_lazy_and_labelled(run_dir, h5_reads):
    da = clrecon.open_run(run_dir, stacked=True)
    try:
        assert all(name.startswith("/axes/") for name in h5_reads), h5_reads  # no voxel read on open
        assert da.dims == STACK_DIMS and da.dtype == np.float32 and da.attrs["units"] == "HU"
        with RunDirectory(run_dir) as run:
            assert da.shape == (2, 1, 2) + run.shape
        assert da.method.values.tolist() == ["nearest", "local_linear"]
        assert da.pitch.values.tolist() == [0.1] and da.pitch_key.values.tolist() == ["p0.100"]
        assert da.variant.values.tolist() == ["noisy", "noise-free"] and bool(da.stored.all())
        met = json.loads(da.attrs["metrics"])
        assert float(da.mae_hu_small.sel(method="local_linear", variant="noise-free", pitch=0.1)) == (
            met["p0.100"]["noise-free"]["local_linear"]["small"]["mae_hu"])
        sel = da.sel(method="local_linear", variant="noisy")  # the spelling: method= is the dimension
        assert sel.dims == ("pitch", "cardiac", "resp", "z", "y", "x")
        part = sel.isel(pitch=0, cardiac=1, resp=2, z=slice(2, 5))
        repr(da), repr(part)
        assert all(n.startswith("/axes/") for n in h5_reads), h5_reads  # selections stay lazy
        values = part.values
        assert h5_reads[-1:] == ["/recon/p0.100/noisy/local_linear"]
        assert [n for n in h5_reads if not n.startswith("/axes/")] == ["/recon/p0.100/noisy/local_linear"]
        with open_volumes(run_dir) as f:
            np.testing.assert_array_equal(values, read_volume(f, "recon/p0.100/noisy/local_linear", (1, 2))[2:5])
        # the same through plain xarray spellings, and against the Dataset
        with clrecon.open_run(run_dir) as ds:
            for m in ("nearest", "local_linear"):
                for v in ("noisy", "noise-free"):
                    np.testing.assert_array_equal(da.sel({"method": m, "variant": v, "pitch": 0.1}).values,
                                                  ds[f"{m}_p0.100_{v}"].values)
            np.testing.assert_array_equal(da.loc[{"method": "nearest", "variant": "noisy"}].isel(pitch=0).values,
                                          ds["nearest_p0.100_noisy"].values)
            err = (da.sel(method="nearest", pitch=0.1) - ds["groundtruth"]).isel(z=0)
            assert err.dims == ("variant", "cardiac", "resp", "y", "x")
            np.testing.assert_array_equal(err.sel(variant="noisy").values,
                                          (ds["nearest_p0.100_noisy"] - ds["groundtruth"]).isel(z=0).values)
        # lookup= is xarray's inexact lookup while method= names the method
        near = da.sel(method="nearest", variant="noisy", cardiac=0.38, resp=0.3, lookup="nearest")
        assert near.dims == ("pitch", "z", "y", "x") and float(near.cardiac) == 0.4
        # once the method dimension is gone, method= is xarray's lookup mode again
        again = da.sel(method="nearest", variant="noisy", pitch=0.1).sel(cardiac=0.38, resp=0.3, method="nearest")
        np.testing.assert_array_equal(again.values, near.isel(pitch=0).values)
        both = da.sel(method=["local_linear", "nearest"])
        assert both.method.values.tolist() == ["local_linear", "nearest"] and both.dims == STACK_DIMS
        with pytest.raises(KeyError):
            da.sel(method="bin")
        # dask on request: the same values
        np.testing.assert_array_equal(da.chunk({"method": 1}).isel(z=0).values, da.isel(z=0).values)
    finally:
        da.close()


def test_open_run_stacked_absent_combination_is_nan(tmp_path):
    make_fake_run(tmp_path, methods=("nearest", "local_linear"), pitches=(0.02, 0.1), variants=("noisy",))
    with h5py.File(tmp_path / "volumes.h5", "a") as f:
        del f["recon/p0.020/noisy/nearest"]  # a run that lacks one (method, pitch, variant)
    with clrecon.open_run(tmp_path, stacked=True) as da:
        assert da.sizes["pitch"] == 2 and da.pitch.values.tolist() == [0.02, 0.1]
        assert da.stored.values[:, :, 0].tolist() == [[False, True], [True, True]]
        assert np.isnan(da.sel(method="nearest", pitch=0.02).values).all()
        assert np.isnan(da.mae_hu_large.sel(method="nearest", pitch=0.02)).all()
        assert not np.isnan(da.sel(method="nearest", pitch=0.1).values).any()
    make_fake_run(tmp_path / "refs", methods=("nearest",), pitches=(0.1,))
    with h5py.File(tmp_path / "refs" / "volumes.h5", "a") as f:
        del f["recon"]
    with pytest.raises(ClreconError, match="no reconstructions in this run directory to stack") as e:
        clrecon.open_run(tmp_path / "refs", stacked=True)
    assert "\n" not in str(e.value)


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    """A real tiny run with the broadcast-stored methods: r4dct (once per amplitude), helical (once)."""
    d = tmp_path_factory.mktemp("tiny")
    res = clrecon.run("tiny", out=d / "run", cache=d / "cache", methods=["local_linear", "r4dct", "helical"],
                      slices=(0, 1))
    return res.path


def test_open_run_stacked_broadcasts_r4dct_and_helical(tiny_run, h5_reads):
    with h5py.File(tiny_run / "volumes.h5") as f:  # as stored: r4dct (1, n_r, ...), helical (1, 1, ...)
        assert list(f["recon/p0.100/noisy/r4dct"].attrs["broadcast"]) == ["cardiac"]
        assert list(f["recon/p0.100/noisy/helical"].attrs["broadcast"]) == ["cardiac", "resp"]
    h5_reads.clear()
    with clrecon.open_run(tiny_run, stacked=True) as da, RunDirectory(tiny_run) as run:
        assert da.dims == STACK_DIMS and da.sizes["cardiac"] == 2 and da.sizes["resp"] == 2
        assert set(da.method.values) == {"local_linear", "r4dct", "helical"} and bool(da.stored.all())
        h5_reads.clear()
        r4 = da.sel(method="r4dct", variant="noisy").values  # (pitch, cardiac, resp, z, y, x)
        # the one stored copy read once, repeated along cardiac only in the returned values
        assert [n for n in h5_reads if not n.startswith("/axes/")] == ["/recon/p0.100/noisy/r4dct"]
        assert r4.shape == (1, 2, 2, 1, 32, 32) and np.array_equal(r4[:, 0], r4[:, 1])
        np.testing.assert_array_equal(r4[0], run.read("recon/p0.100/noisy/r4dct"))
        hel = da.sel(method="helical", variant="noise-free", pitch=0.1).values
        assert (hel == hel[:1, :1]).all()
        np.testing.assert_array_equal(hel, run.read("recon/p0.100/noise-free/helical"))
        ll = da.sel(method="local_linear", variant="noisy", pitch=0.1, cardiac=0.4, resp=0.75)
        np.testing.assert_array_equal(ll.values, run.read("recon/p0.100/noisy/local_linear", (1, 1)))
        # a target of the broadcast methods is the same volume whatever the cardiac phase asked for
        np.testing.assert_array_equal(da.sel(method="r4dct", cardiac=0.0).values, da.sel(method="r4dct",
                                                                                           cardiac=0.4).values)
    assert not run.h5
