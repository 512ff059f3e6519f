"""Pre-flight: the run's modelled memory and disk need against the machine, before any work."""

import re

import numpy as np
import pytest

from clrecon import api
from clrecon.cli import main
from clrecon.config.scene import load_scene
from clrecon.core.errors import ClreconError
from clrecon.core.resources import format_bytes
from clrecon.pipeline import preflight, slabs
from clrecon.pipeline.context import resolve_targets
from clrecon.pipeline.costs import PROJECTION_RATIO, VOLUME_RATIO, disk_model, kept_plans_bytes, run_costs, scene_costs
from clrecon.pipeline.run import run
from clrecon.reconstruction import reconstruct
from clrecon.scan.table import cached_projection_table

GiB = 1024 ** 3
QUIET = dict(progress=False, log=lambda *a: None)


@pytest.fixture
def roomy(monkeypatch):
    monkeypatch.setattr(preflight, "available_memory_bytes", lambda: 64 * GiB)
    monkeypatch.setattr(preflight, "free_disk_bytes", lambda path: 500 * GiB)


def test_huge_volume_is_a_one_line_error_not_a_memory_error(tmp_path, roomy, capsys):
    toml = tmp_path / "huge.toml"
    src = load_scene("tiny").source
    # the largest grid the scene checks let through (4000^2 x 400 slices of 0.5 x 0.5 x 5 mm): ~190 GiB modelled
    text = (open(src).read().replace("nx = 32", "nx = 4000").replace("ny = 32", "ny = 4000")
            .replace("voxel_mm = 12.0", "voxel_mm = 0.5").replace("nz = 2\n", "nz = 400\n"))
    toml.write_text(text.replace('name = "tiny"', 'name = "huge"'))
    rc = main(["run", "--scene", str(toml), "--out", str(tmp_path / "run"), "--cache", str(tmp_path / "c"),
               "--no-progress"])
    err = capsys.readouterr().err
    assert rc == 2 and err.count("\n") == 1, err
    assert err.startswith("clrecon: error: pre-flight:") and "of memory" in err
    assert "64.0 GiB available" in err and "--force" in err and "force=True" in err
    assert not (tmp_path / "run" / "volumes.h5.units").exists()   # nothing was started


def test_not_enough_memory_then_force(tmp_path, monkeypatch):
    need = run_costs(load_scene("tiny"), methods=["nearest"])["peak_memory_bytes"]
    monkeypatch.setattr(preflight, "available_memory_bytes", lambda: need // 2)
    with pytest.raises(ClreconError, match=r"pre-flight: the run needs about .* of memory .* available") as e:
        api.run("tiny", tmp_path / "run", methods="nearest", cache=tmp_path / "c", report=False)
    assert "\n" not in str(e.value) and "force=True" in str(e.value)
    res = api.run("tiny", tmp_path / "run", methods="nearest", cache=tmp_path / "c", report=False, force=True)
    assert res.results["preflight"]["forced"] is True


def test_not_enough_disk_names_both_numbers(tmp_path, monkeypatch, capsys):
    """At KiB-MiB sizes both numbers show (the issue's "needs about 0.00 GiB ... has 0.00 GiB free")."""
    monkeypatch.setattr(preflight, "available_memory_bytes", lambda: 64 * GiB)
    monkeypatch.setattr(preflight, "free_disk_bytes", lambda path: 900 * 1024)
    argv = ["run", "--scene", "tiny", "--methods", "nearest", "--out", str(tmp_path / "run"),
            "--cache", str(tmp_path / "c"), "--no-progress"]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "of disk" in err and "has 900 KiB free" in err and "--force" in err
    need = re.search(r"needs about ([0-9.]+) (KiB|MiB) of disk", err)
    assert need and float(need.group(1)) > 0, err
    assert main(argv + ["--force"]) == 0


@pytest.mark.parametrize("n, text", [(0, "0 B"), (1000, "1000 B"), (1536, "1.50 KiB"), (900 * 1024, "900 KiB"),
                                     (1023.9 * 1024, "1024 KiB"), (9.996 * 1024 ** 2, "10.0 MiB"),
                                     (64 * GiB, "64.0 GiB"), (123.4 * GiB, "123 GiB"), (146 * 1024 ** 5, "146 PiB")])
def test_bytes_show_three_significant_figures(n, text):
    assert format_bytes(n) == text


def test_separate_file_systems_are_checked_separately(tmp_path, monkeypatch):
    scene = load_scene("tiny")
    costs = run_costs(scene)
    monkeypatch.setattr(preflight, "available_memory_bytes", lambda: 64 * GiB)
    monkeypatch.setattr(preflight, "_device", lambda p: 1 if "cache" in str(p) else 2)
    need = preflight.needs(scene, costs, tmp_path / "cache", tmp_path / "out")
    # compressed units and the store assembled from them coexist; the truth cache copies the two
    # truth volumes where it cannot hard-link (another file system)
    store = costs["needed_store_bytes"] / PROJECTION_RATIO
    assert costs["volume_compression"] == "none"  # tiny's volumes are far below AUTO_COMPRESS_BYTES: raw
    truths = costs["truth_bytes"]
    assert need["cache_disk"] == int(max(2 * store, store + truths))
    # the volumes, nothing more: their units are the result
    assert need["out_disk"] == int(costs["volume_bytes"])   # the units are the result: no assembly transient
    free = {"cache": need["cache_disk"] - 1, "out": 10 * GiB}
    monkeypatch.setattr(preflight, "free_disk_bytes", lambda p: free["cache" if "cache" in str(p) else "out"])
    with pytest.raises(ClreconError, match="the projection store needs"):
        preflight.check(scene, costs, tmp_path / "cache", tmp_path / "out")
    free["cache"] = 10 * GiB
    preflight.check(scene, costs, tmp_path / "cache", tmp_path / "out")


def test_costs_follow_the_narrowing_and_bound_what_is_written(tmp_path, roomy):
    scene = load_scene("tiny")
    full = scene_costs(scene)
    narrow = run_costs(scene, methods=["nearest", "helical"], n_cardiac=1, n_resp=2, slices_z=np.array([0.0]))
    assert narrow["volume_bytes"] < full["volume_bytes"] and narrow["peak_memory_bytes"] < full["peak_memory_bytes"]
    # 2 variants x (nearest on the full 1 x 2 grid + helical stored once = 1/2 of it) + 2 truths
    assert narrow["n_volumes"] == 2 * (1 + 0.5) + 2
    res = run(scene, tmp_path / "run", methods=["nearest", "helical"], cardiac=[0.0], slice_range=(0, 1),
              cache_dir=tmp_path / "c", report=False, **QUIET)
    run_dir = tmp_path / "run"
    written = (run_dir / "volumes.h5").stat().st_size + sum(p.stat().st_size for p in run_dir.rglob("volumes.d/*/*"))
    assert written <= narrow["volume_bytes"] * 1.1 + 200_000           # + HDF5 metadata and axes
    store = res["stages"]["simulate"]["per_pitch"]["p0.100"]
    assert store["projections_needed"] <= narrow["projections_needed"][0.1]
    need = res["preflight"]["needs_bytes"]
    assert need["out_disk"] == narrow["out_disk"]
    # the model plus the process as the pre-flight measured it, which is below the run's own peak
    assert narrow["peak_memory_bytes"] + preflight.PROCESS_GROWTH_BYTES < need["memory"]
    assert need["memory"] <= max(res["peak_rss_bytes"], narrow["peak_memory_bytes"] + preflight.PROCESS_GROWTH_BYTES
                                 + res["peak_rss_bytes"])
    if store["projections_needed"] == store["projections_total"]:  # the store is complete: no more cache disk
        assert preflight.needs(scene, full, tmp_path / "c", tmp_path / "run2")["cache_disk"] == 0


def test_disk_model_walks_the_run_in_order():
    """The peak is the store's assembly transient or the volumes, whichever is larger, not their sum."""
    c = {"projections_needed": {0.02: 1000, 0.1: 200}, "projection_bytes": 1000, "recon_bytes_per_pitch": 4000,
         "truth_bytes": 2000, "volume_bytes": 10000, "largest_dataset_bytes": 1000}
    r = PROJECTION_RATIO
    v = VOLUME_RATIO
    d = disk_model(c)
    s1, s2 = 1000 * 1000 / r, 200 * 1000 / r
    assert d["cache_disk"] == int(max(2 * s1, s1 + 2 * s2))
    assert d["out_disk"] == int(10000 / v)       # the volumes' units are the result: no assembly transient
    assert d["disk_peak"] == int(max(2 * s1, s1 + 4000 / v + 2 * s2, s1 + s2 + 10000 / v))
    done = disk_model(c, existing={0.02: None, 0.1: None}, present_out=3000)
    assert done["cache_disk"] == 0 and done["out_disk"] == int(10000 / v - 3000)
    # uncompressed volumes count raw
    raw = disk_model(dict(c, volume_compression="none"))
    assert raw["out_disk"] == 10000 and raw["cache_disk"] == d["cache_disk"]
    # paper-p002 whole: within the 40 GiB of issue 20 (it was 125 GiB with raw units and a whole copy)
    assert scene_costs(load_scene("paper-p002"))["disk_peak"] <= 40 * GiB
    assert scene_costs(load_scene("paper-p010"))["disk_peak"] <= 40 * GiB


def test_auto_volume_compression_compresses_only_large_runs():
    """recon.volume_compression = "auto": LZF for the paper scenes' volumes, none for demo and tiny."""
    from clrecon.outputs.volumes import AUTO_COMPRESS_BYTES, resolve_compression

    assert scene_costs(load_scene("paper-p010"))["volume_compression"] == "lzf"
    assert scene_costs(load_scene("demo"))["volume_compression"] == "none"
    assert resolve_compression("auto", AUTO_COMPRESS_BYTES) == "lzf"
    assert resolve_compression("auto", AUTO_COMPRESS_BYTES - 1) == "none"
    assert resolve_compression("lzf", 0) == "lzf" and resolve_compression("none", 10 * AUTO_COMPRESS_BYTES) == "none"
    with pytest.raises(ValueError, match="allowed auto, lzf, none"):
        resolve_compression("gzip", 0)


def test_slabs_are_sized_by_each_slices_candidates_not_the_first_slices():
    """paper-p002's end slices have a sixth of the interior's candidates: the slabs follow each
    slice's size, so no slab's working set exceeds the budget (the first-slice probe sized the
    interior slabs 6.6x over it: 8.49 GiB peak against the modelled 4.6)."""
    from clrecon.pipeline.slabs import candidates_per_slice, reconstruction_slabs
    from clrecon.reconstruction import reconstruct
    from clrecon.scan import table as geometry

    scene = load_scene("paper-p002")
    cfg = reconstruct.ReconstructionConfig.from_scene(scene)
    table = geometry.projection_table(scene, 0.02)
    z = reconstruct.slice_positions(scene, None)
    n = candidates_per_slice(table, z, cfg)
    assert n.shape == z.shape and n[0] * 4 < n[len(n) // 2] and n[-1] * 4 < n[len(n) // 2]
    # by hand: the projections within the SSRB window of the middle slice
    w = reconstruct.rebin.slice_window_mm(scene.scanner, cfg.object_radius_mm)
    mid = z[len(z) // 2]
    assert n[len(n) // 2] == int(np.sum(np.abs(table.source_z_mm - mid) <= w))
    per = 1e6 * n / n.max()  # bytes per slice, proportional to the candidates
    slabs = reconstruction_slabs(per, budget=5e6)
    assert slabs[0][0] == 0 and slabs[-1][1] == len(z)
    assert all(a1 == b0 for (_, a1), (b0, _) in zip(slabs[:-1], slabs[1:], strict=True))
    assert all(per[a:b].sum() <= 5e6 or b - a == 1 for a, b in slabs)
    sizes = [b - a for a, b in slabs]
    assert sizes[0] > max(sizes[len(sizes) // 2 - 1:len(sizes) // 2 + 2])  # the ends take more slices
    assert reconstruction_slabs(np.array([9e6, 1.0]), budget=5e6) == [(0, 1), (1, 2)]  # one slice over budget: alone
    assert reconstruction_slabs(np.zeros(0)) == []


def test_the_mc_method_adds_its_working_set_at_its_worst_pitch():
    """mc's working set (the largest of its parts: the fit, the rounds' backprojections, the final
    pass; the registration processes at their peak beside the fit's registrations, idle beside the
    fit and the rounds' backprojections) after the reconstruction, sized at the pitch whose slabs use
    the most projections; the knobs it depends on move it."""
    from clrecon.reconstruction.motion import memory
    from clrecon.reconstruction.rebin import slice_window_mm

    scene = load_scene("demo")
    paper = ("barycentric", "local_linear", "r4dct", "nearest", "bin", "helical")
    base = run_costs(scene, methods=paper)["peak_memory_bytes"]
    with_mc = run_costs(scene, methods=(*paper, "mc"))["peak_memory_bytes"]
    sc, rc = scene.scanner, scene.recon
    w = slice_window_mm(sc, min(sc.fov_radius_mm, rc.fov_radius_mm))
    ext = (rc.nz - 1) * rc.slice_mm
    args = {p: (sc, w, rc.mc_knobs, ext, scene.scan.feed_mm(sc, p), 2, 5, 10, rc.nz, rc.ny, rc.nx,
                scene.scan.projection_count(sc, p)) for p in scene.scan.pitches}
    per_pitch = {p: memory.working_bytes(*a, voxel_mm=rc.voxel_mm) for p, a in args.items()}
    assert per_pitch[0.02] > per_pitch[0.1] > 0   # the lower pitch: more projections per slab
    assert with_mc > base and with_mc >= per_pitch[0.02]
    parts = memory.working_parts(*args[0.02], voxel_mm=rc.voxel_mm)
    idle = parts["idle registration processes"]
    assert per_pitch[0.02] == max(parts["registering"] + parts["registration processes"], parts["fit"] + idle,
                                  parts["round backprojection"] + idle, parts["final pass"])
    one_round = api.load_scene("demo", recon={"mc": {"rounds": 1}})
    assert memory.working_parts(*args[0.02][:2], one_round.recon.mc_knobs, *args[0.02][3:],
                                voxel_mm=rc.voxel_mm)["round backprojection"] == 0
    coarse = api.load_scene("demo", recon={"mc": {"downsample": 2}})
    assert run_costs(coarse, methods=(*paper, "mc"))["peak_memory_bytes"] < with_mc


def test_the_mc_model_follows_the_registration_it_runs():
    """scikit-image's Lucas-Kanade (``lucas_kanade``) registers in a pool of processes
    (``registration.FLOW_BYTES_PER_VOXEL`` each, in the process below ``POOL_MIN_VOXELS``); TV-L1 runs in
    the process on the OpenCL device, no pool: its fit holds one registration's ``flow.BYTES_PER_VOXEL``
    (64 B a voxel of the registration grid); the default (OpenCL Lucas-Kanade, then TV-L1) likewise,
    the larger of the two steps' own."""
    from clrecon.reconstruction.motion import flow, memory, registration
    from clrecon.reconstruction.motion import lk as lkcl
    from clrecon.reconstruction.rebin import slice_window_mm

    scene = load_scene("demo")
    sc, rc = scene.scanner, scene.recon
    w = slice_window_mm(sc, min(sc.fov_radius_mm, rc.fov_radius_mm))
    ext = (rc.nz - 1) * rc.slice_mm
    n_reg = rc.nz * rc.ny * rc.nx

    def parts(reg, beat):
        knobs = api.load_scene("demo", recon={"mc": {"registration": reg, "beat_registration": beat}}).recon.mc_knobs
        return memory.working_parts(sc, w, knobs, ext, scene.scan.feed_mm(sc, 0.1), 2, 5, 10, rc.nz, rc.ny, rc.nx,
                                    scene.scan.projection_count(sc, 0.1), 1, voxel_mm=rc.voxel_mm)

    lk, tv = parts("lucas_kanade", "lucas_kanade"), parts("tvl1", "tvl1")
    assert tv["registration processes"] == tv["idle registration processes"] == 0
    workers = registration.registration_workers(n_reg, available_bytes=1 << 62)
    if workers > 1:  # each at its peak (its own set and its registration's), or idle (its own set)
        assert lk["registration processes"] == workers * (registration.FLOW_BYTES_PER_VOXEL * n_reg
                                                          + memory.WORKER_BYTES)
        assert lk["idle registration processes"] == workers * memory.WORKER_BYTES
    else:
        assert lk["registration processes"] == lk["idle registration processes"] == 0
    in_process = 0 if workers > 1 else registration.FLOW_BYTES_PER_VOXEL * n_reg
    for part in ("fit", "registering"):
        assert tv[part] - lk[part] == flow.BYTES_PER_VOXEL * n_reg - in_process
    pool = {"fit", "registering", "registration processes", "idle registration processes"}
    assert {k: v for k, v in tv.items() if k not in pool} == {k: v for k, v in lk.items() if k not in pool}
    # scikit-image's pool for the breathing, then TV-L1 in the process for the beat (one after the other:
    # the process holds the larger of the two steps' own, counted beside the pool's peak)
    both = parts("lucas_kanade", "tvl1")
    assert both["registration processes"] == lk["registration processes"]
    for part in ("fit", "registering"):
        assert both[part] - lk[part] == max(flow.BYTES_PER_VOXEL * n_reg, in_process) - in_process
    # the default: the OpenCL Lucas-Kanade runs in the process like TV-L1: its own lk.BYTES_PER_VOXEL, no pool
    cl = parts("lucas_kanade_cl", "tvl1")
    assert cl["registration processes"] == cl["idle registration processes"] == 0
    for part in ("fit", "registering"):
        assert cl[part] - tv[part] == (max(lkcl.BYTES_PER_VOXEL, flow.BYTES_PER_VOXEL) - flow.BYTES_PER_VOXEL) * n_reg
    default = memory.working_parts(sc, w, rc.mc_knobs, ext, scene.scan.feed_mm(sc, 0.1), 2, 5, 10, rc.nz, rc.ny, rc.nx,
                                   scene.scan.projection_count(sc, 0.1), 1, voxel_mm=rc.voxel_mm)
    assert default == cl


def test_the_mc_model_counts_the_registration_processes_beside_the_registrations_only():
    """The fit's new model (its basis's fields on the registration grid) and its float64 block are made
    after a step's registrations, and so is the shrinking of its fields (``knobs.shrink``): the
    registration processes at their peak sit beside the fit less those; the process pool is idle
    (each worker's own set) beside the whole fit. With scikit-image's Lucas-Kanade (``lucas_kanade``),
    the registration that runs in a pool."""
    from clrecon.reconstruction.motion import confidence, memory
    from clrecon.reconstruction.motion import method as mcm
    from clrecon.reconstruction.motion.model import FIT_BLOCK
    from clrecon.reconstruction.rebin import slice_window_mm

    def parts(shrink):
        scene = api.load_scene("demo", recon={"mc": {"shrink": shrink, "registration": "lucas_kanade"}})
        sc, rc = scene.scanner, scene.recon
        w = slice_window_mm(sc, min(sc.fov_radius_mm, rc.fov_radius_mm))
        return rc, memory.working_parts(sc, w, rc.mc_knobs, (rc.nz - 1) * rc.slice_mm, scene.scan.feed_mm(sc, 0.1),
                                        2, 5, 10, rc.nz, rc.ny, rc.nx, scene.scan.projection_count(sc, 0.1), 1,
                                        voxel_mm=rc.voxel_mm)

    rc, p = parts(False)
    nb = len(mcm.basis_of(rc.mc, 5, 10).names)
    f = mcm.factor_of(rc.nx, rc.ny, rc.voxel_mm, rc.mc)
    n_reg = rc.nz * (rc.ny // f) * (rc.nx // f)
    fld = 3 * n_reg * 4
    assert p["fit"] - p["registering"] == nb * fld + (4 * 50 + nb) * FIT_BLOCK * 8
    assert p["registration processes"] > p["idle registration processes"] > 0  # demo's grid registers in a pool
    _, q = parts(True)  # the shrinking: the 10 respiratory fields' copy and one field's shrink_field
    shrink = (10 * fld + confidence.SHRINK_BYTES_PER_VOXEL * n_reg
              + confidence.SHRINK_CHUNK_BYTES_PER_VOXEL * min(n_reg, confidence.CHUNK_VOXELS))
    assert q["fit"] == max(p["fit"], p["registering"] + shrink)
    assert {k: v for k, v in q.items() if k != "fit"} == {k: v for k, v in p.items() if k != "fit"}


def test_the_mc_model_holds_the_first_pass_on_the_registration_grid_only():
    """With ``downsample`` f the fit holds the first pass f**2 times smaller (read a unit at a time and
    block-averaged, never whole at full resolution); the read of one unit (its bytes and its array) is
    what grows with the unit's slices."""
    from clrecon.reconstruction.motion import memory
    from clrecon.reconstruction.rebin import slice_window_mm

    scene = load_scene("paper-p010")
    sc, rc = scene.scanner, scene.recon
    w = slice_window_mm(sc, min(sc.fov_radius_mm, rc.fov_radius_mm))
    ext = (rc.nz - 1) * rc.slice_mm

    def fit(ds, unit_slices, rounds=2):
        # without the fields' shrinking (its own part of the fit, counted in the test above)
        knobs = api.load_scene("paper-p010", recon={"mc": {"downsample": ds, "rounds": rounds,
                                                           "shrink": False}}).recon.mc_knobs
        return memory.working_parts(sc, w, knobs, ext, scene.scan.feed_mm(sc, 0.1), 2, 5, 10, rc.nz, rc.ny, rc.nx,
                                    scene.scan.projection_count(sc, 0.1), unit_slices, voxel_mm=rc.voxel_mm)["fit"]

    full = 50 * rc.nz * rc.ny * rc.nx * 4  # the first pass at full resolution: 5.77 GB
    coarse = 50 * rc.nz * (rc.ny // 2) * (rc.nx // 2) * 4
    assert fit(2, 1) < full + coarse  # the whole fit holds less than the full stack beside its copy did
    assert fit(2, rc.nz) == coarse + 2 * full  # the whole pass as one unit: its read is the fit's peak
    assert fit(1, 1) > full


def test_the_mc_final_pass_counts_only_the_model_planes_a_slab_reaches(monkeypatch):
    """The final pass refines the model on a slab's planes (its slices and ``margin_mm`` both sides,
    ``method.reach_planes``), not on every plane of the scan: on a whole paper-p010 (110 slices) each
    slab's refined model is that many planes' bytes, not 110's (page-aligned: a CPU device reads it
    in place, no device copy)."""
    from clrecon.reconstruction.motion import memory
    from clrecon.reconstruction.motion import method as mcm
    from clrecon.reconstruction.motion.model import FieldGrid
    from clrecon.reconstruction.rebin import slice_window_mm

    scene = load_scene("paper-p010")
    sc, rc = scene.scanner, scene.recon
    w = slice_window_mm(sc, min(sc.fov_radius_mm, rc.fov_radius_mm))
    ext = (rc.nz - 1) * rc.slice_mm
    seen = []
    real = memory.slab_model_planes

    def spy(*a):
        seen.append(real(*a))
        return seen[-1]

    def final(ds, planes):
        knobs = api.load_scene("paper-p010", recon={"mc": {"downsample": ds}}).recon.mc_knobs
        monkeypatch.setattr(memory, "slab_model_planes", planes)
        return memory.working_parts(sc, w, knobs, ext, scene.scan.feed_mm(sc, 0.1), 2, 5, 10, rc.nz, rc.ny,
                                    rc.nx, scene.scan.projection_count(sc, 0.1), 1, voxel_mm=rc.voxel_mm)["final pass"]

    nb = len(mcm.basis_of(rc.mc, 5, 10).names)  # the model's basis fields (1 + resp_degree + 2 harmonics: 6)
    plane_bytes = nb * 3 * rc.ny * rc.nx * 4  # one plane of the basis fields on the reconstruction grid
    for ds in (1, 2):  # the host's refined planes (or, at ds 1, its copy of the model's own), read in place
        seen.clear()
        now = final(ds, spy)
        every = final(ds, lambda s, dz, m, nz: nz)
        assert len(seen) == 1 and 0 < seen[0] < rc.nz
        assert every - now == (rc.nz - seen[0]) * plane_bytes
    # the count bounds what refine holds for any slab position when the model moves points <= margin_mm
    g = FieldGrid(nx=2, ny=2, nz=110, voxel_mm=1.0, z0_mm=-81.75, dz_mm=1.5)
    for s in (1, 8, 30):
        for z0 in np.linspace(-100.0, 80.0, 37):
            k0, k1 = mcm.reach_planes(g, z0 + 1.5 * np.arange(s), 20.0)
            assert k1 - k0 <= real(s, 1.5, 20.0, 110)
    assert real(8, 1.5, 20.0, 110) == 8 + 2 * 14 + 4
    assert real(100, 1.5, 20.0, 110) == 110
    assert real(1, 0.0, 20.0, 1) == 1


@pytest.mark.parametrize("scene_name", ["tiny", "demo"])
def test_the_kept_plans_are_counted_from_a_planned_slice_not_above_a_quarter_more(scene_name):
    """``kept_plans_bytes`` (one planned slice per pitch, times the slices) against the bytes of the
    plan of every slice, as the planning pass keeps it: not below, at most 25 % above (a slice at the
    scan's end holds fewer rows than the widest one the probe plans)."""
    scene = load_scene(scene_name)
    methods = ("barycentric", "local_linear", "r4dct", "nearest", "bin", "helical", "mc")
    targets, z = resolve_targets(scene), reconstruct.slice_positions(scene)
    cfg = reconstruct.ReconstructionConfig.from_scene(scene)
    held = max(reconstruct.plan_bytes(reconstruct.plan(cfg, cached_projection_table(scene, p), z, targets,
                                                       slabs.planned_methods(methods)))
               for p in scene.scan.pitches)
    got = kept_plans_bytes(scene, methods, targets, z, scene.scan.pitches)
    assert held <= got <= 1.25 * held, (got, held)
    assert kept_plans_bytes(scene, ("mc",), targets, z, scene.scan.pitches) > 0  # mc's first pass is planned
    assert kept_plans_bytes(scene, ("cv_tuned",), targets, z, scene.scan.pitches) == 0  # planned apart, later


def test_truths_already_cached_are_not_counted_beside_the_reconstruction(tmp_path, monkeypatch):
    """The pre-flight counts the truth stage's working set beside the reconstruction only where the
    truth cache does not already hold every target's truths (then the stage computes nothing)."""
    from clrecon.pipeline import costs
    from clrecon.pipeline.stages import truth as truth_stage
    seen = []
    real = costs.run_costs
    monkeypatch.setattr(costs, "run_costs", lambda *a, **k: (seen.append(k["truths_computed"]), real(*a, **k))[1])
    sc = load_scene("tiny")
    z = reconstruct.slice_positions(sc)
    targets = resolve_targets(sc, None, None)
    assert not truth_stage.all_cached(tmp_path / "c", sc, z, targets)
    run(sc, tmp_path / "a", methods=["barycentric"], cache_dir=tmp_path / "c", progress=False, report=False,
        log=lambda *a: None)
    assert truth_stage.all_cached(tmp_path / "c", sc, z, targets)
    run(sc, tmp_path / "b", methods=["barycentric"], cache_dir=tmp_path / "c", progress=False, report=False,
        log=lambda *a: None)
    assert seen == [True, False]
    on, off = real(sc, ["barycentric"]), real(sc, ["barycentric"], truths_computed=False)
    assert on["peak_memory_bytes"] - off["peak_memory_bytes"] in (0, truth_stage.working_bytes(
        sc.recon.nz, sc.scanner.views_per_rotation, sc.scanner.n_cols, sc.recon.ny, sc.recon.nx))
