"""The ``mcir`` method in the run (issue 42, docs/iterative.md): its stage shares ``mc``'s motion model,
makes volumes that land in volumes.h5, the metrics and the report with the solver's residuals, a
kill -9 at its write resumes to the same bits, the overlapped executor gives the serial bits, and
its knobs are refused in one line."""

import signal

import h5py
import numpy as np
import pytest
from run_compare import assert_identical, run_cli

from clrecon.config.overrides import load_scene
from clrecon.core.errors import ClreconError, SceneError
from clrecon.pipeline import executors
from clrecon.pipeline.run import run
from clrecon.pipeline.stages import mcir_reconstruct as mcir_stage
from clrecon.reconstruction import reconstruct
from clrecon.reconstruction.interpolation import METHODS, default_methods, first_pass, second_pass_methods
from clrecon.reconstruction.iterative import method as mcir
from clrecon.scan.table import cached_projection_table

QUIET = dict(progress=False, log=lambda *a: None)
METHODS_RUN = "barycentric,mc,mcir"


def _cli(out, cache, fault=None, extra=()):
    return run_cli(out, cache, METHODS_RUN, fault, extra)


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    out = tmp_path_factory.mktemp("ref")
    res = run(load_scene("tiny"), out, methods=METHODS_RUN.split(","), cache_dir=tmp_path_factory.mktemp("cache"),
              executor="serial", **QUIET)
    return out, res


def test_mcir_is_an_opt_in_second_pass_from_barycentric():
    assert "mcir" not in default_methods()
    assert "mcir" in second_pass_methods()
    assert first_pass("mcir") == "barycentric"
    assert METHODS["mcir"].stage == "mcir_reconstruct"


def test_mcir_volumes_residuals_metrics_and_report(reference):
    out, res = reference
    with h5py.File(out / "volumes.h5", "r") as f:
        for v in ("noisy", "noise-free"):
            vol = f[f"recon/p0.100/{v}/mcir"][()]
            assert vol.shape == f[f"recon/p0.100/{v}/barycentric"].shape and np.isfinite(vol).all()
    for v in ("noisy", "noise-free"):
        assert set(res["metrics"]["p0.100"][v]) == {"barycentric", "mc", "mcir"}
        assert res["method_seconds"]["p0.100"][v]["mcir"] > 0
        slabs = res["stages"]["mcir"]["slabs"]["p0.100"][v]
        assert slabs
        for info in slabs.values():
            h = info["sart"]
            assert len(h["running"]) >= 1 and h["final"] < h["initial"]
            assert h["stop"]
    report = (out / "report.md").read_text()
    assert "mcir" in report and "OS-SART solver" in report


def test_the_overlapped_executor_gives_the_serial_bits(tmp_path, reference):
    run(load_scene("tiny"), tmp_path, methods=METHODS_RUN.split(","), cache_dir=tmp_path / "cache",
        executor=executors.LocalExecutor(helper=False), **QUIET)
    assert_identical(tmp_path, reference, ("metrics",))


def test_sigkill_at_the_mcir_write_then_resume_is_bit_identical(tmp_path, reference):
    """The serial run writes barycentric's 2 units, mc's 2, then mcir's: killed mid-write of the
    first mcir unit, the rerun loads both models (no registration) and writes mcir's 2 units."""
    out, cache = tmp_path / "run", tmp_path / "cache"
    killed = _cli(out, cache, "recon:5")
    assert killed.returncode == -signal.SIGKILL, killed.stderr
    again = _cli(out, cache)
    assert again.returncode == 0, again.stderr
    res = assert_identical(out, reference, ("metrics",))
    assert res["units_written"]["recon"] == 2
    assert "registering" not in again.stdout


@pytest.mark.parametrize("table, key", [("epochs = 0", "recon.mcir.epochs = 0"),
                                        ("warp = 'twist'", "recon.mcir.warp = 'twist'"),
                                        ("voxel_factor = 9", "recon.mcir.voxel_factor = 9"),
                                        ("epoch = 2", "recon.mcir.epoch: unknown key")])
def test_a_bad_knob_is_refused_in_one_line(tmp_path, table, key):
    scene = tmp_path / "s.toml"
    scene.write_text(f'[recon]\nmethods = ["barycentric", "mcir"]\n[recon.mcir]\n{table}\n')
    with pytest.raises(SceneError) as e:
        load_scene(str(scene))
    assert key in str(e.value) and "\n" not in str(e.value)


def test_mcir_on_two_dask_workers_is_bit_identical(tmp_path, reference):
    pytest.importorskip("distributed")
    from clrecon.pipeline import distributed

    with distributed.connect(workers=2) as client:
        res = run(load_scene("tiny"), tmp_path / "run", methods=METHODS_RUN.split(","), cache_dir=tmp_path / "cache",
                  client=client, **QUIET)
    assert_identical(tmp_path / "run", reference, ("metrics",))
    assert res["distributed"]["units"]["mcir_reconstruct"] == 2  # one slab x 2 variants, on the workers


def test_mcir_on_a_measured_scan_reconstructs_what_it_does_on_the_simulation(tmp_path, reference):
    """The reference run's noisy projections written as DICOM-CT-PD and read back as a measured scan:
    mcir solves them to the simulated run's noisy mcir volumes within the import's quantisation
    carried through the solver (measured below), and it is mcir's image, not its first pass.

    Both runs register both steps with scikit-image's Lucas-Kanade (as when the tolerances below were
    measured; the default breathing is the same algorithm on OpenCL): the default TV-L1 beat carries
    the import's quantisation (0.25 HU) further into the motion model, and mcir's forward model and
    start then differ by up to 0.79 HU (measured; ``mc``'s own volumes stay within 0.25 HU,
    test_mc_method.py). What is tested here is mcir's reading of a measured scan, not the
    registration's sensitivity."""
    from clrecon.outputs.export import export

    out, _ = reference
    export(out, "dicom-ct-pd", out=tmp_path / "exp")
    lk = {"mc": {"registration": "lucas_kanade", "beat_registration": "lucas_kanade"}}
    sim_run = tmp_path / "sim"
    run(load_scene("tiny", recon=lk), sim_run, methods=METHODS_RUN.split(","), cache_dir=tmp_path / "cs",
        executor="serial", report=False, **QUIET)
    res = run(load_scene(tmp_path / "exp" / "measured.toml", recon=lk), tmp_path / "meas",
              methods=METHODS_RUN.split(","), cache_dir=tmp_path / "c", report=False,
              **QUIET)  # mcir starts from mc's volumes, as in the simulation
    assert res["stages"]["mcir"]["slabs"]["p0.100"]["measured"]
    with h5py.File(sim_run / "volumes.h5") as a, h5py.File(tmp_path / "meas" / "volumes.h5") as b:
        sim, meas = a["recon/p0.100/noisy/mcir"][()].astype(float), b["recon/p0.100/measured/mcir"][()].astype(float)
        bary = b["recon/p0.100/measured/barycentric"][()].astype(float)
    assert np.all(np.isfinite(meas))
    # the import quantises the projections (0.25 HU after FBP for the paper methods); SART is linear
    # in the data but for its clamp at zero attenuation (and, from mc's start, mc's own difference):
    # measured max 0.07 HU from mc's start (0.14 HU from zero with the density term on)
    assert np.abs(meas - sim).max() < 0.25, np.abs(meas - sim).max()
    assert np.abs(meas - bary).max() > 10.0


def test_mcir_on_a_cylindrical_detector_with_a_flying_focal_spot(tmp_path):
    """The rays are the scan's own (the arc's flat-equivalent cells, one view group per focal-spot
    state): on the curved, z-FFS tiny scan mcir explains its data as well as on the flat one (final
    residual measured 3.61 % against 3.72 %) and its error stays in the flat one's range (81.8
    against 85.9 HU large FOV); a geometry slip would leave the data unexplained."""
    out = {}
    for name, scanner in (("flat", {}), ("curved", {"detector": "cylindrical", "flying_focal_spot": "z",
                                                    "ffs_z_mm": 1.5})):
        scene = load_scene("tiny").replace(scanner=scanner, noise={"enabled": False})
        res = run(scene, tmp_path / name, methods=["barycentric", "mcir"], cache_dir=tmp_path / f"c{name}",
                  executor="serial", report=False, **QUIET)
        (info,) = res["stages"]["mcir"]["slabs"]["p0.100"]["noise-free"].values()
        out[name] = (info["sart"]["final"], res["metrics"]["p0.100"]["noise-free"]["mcir"]["large"]["mae_hu"])
    assert out["curved"][0] < 1.1 * out["flat"][0], out
    assert out["curved"][1] < 1.15 * out["flat"][1], out


def test_mcir_starts_from_mc_or_the_first_pass_unless_asked_for_zero(tmp_path, reference):
    """``init``: 'auto' (the reference run) starts OS-SART from mc's reference-state target, which
    explains the data far better than zero does (relative residual 1 from zero; measured 0.06 from
    either start on tiny); 'auto' without mc starts from the first pass; init = 'mc' without mc is
    refused in one line."""
    _, ref = reference

    def histories(res):
        slabs = res["stages"]["mcir"]["slabs"]["p0.100"]
        return [i["sart"] for v in ("noisy", "noise-free") for i in slabs[v].values()]

    assert ref["stages"]["mcir"]["start"] == "mc"
    zero = run(load_scene("tiny", recon__mcir__init="zero"), tmp_path / "zero", methods=METHODS_RUN.split(","),
               cache_dir=tmp_path / "cache", executor="serial", report=False, **QUIET)
    assert zero["stages"]["mcir"]["start"] == "zero"
    no_mc = run(load_scene("tiny"), tmp_path / "no-mc", methods=["barycentric", "mcir"], cache_dir=tmp_path / "cache",
                executor="serial", report=False, **QUIET)
    assert no_mc["stages"]["mcir"]["start"] == "barycentric"
    for h0, h, h1 in zip(histories(zero), histories(ref), histories(no_mc), strict=True):
        assert h0["initial"] == pytest.approx(1.0)
        assert h["initial"] < 0.2 and h1["initial"] < 0.2, (h0, h, h1)
        assert h["final"] <= h["initial"] and h1["final"] <= h1["initial"]
    with pytest.raises(ClreconError) as e:
        run(load_scene("tiny", recon__mcir__init="mc"), tmp_path / "refused", methods=["barycentric", "mcir"],
            cache_dir=tmp_path / "cache", **QUIET)
    assert "recon.mcir.init = 'mc'" in str(e.value) and "\n" not in str(e.value)


def _slab_inputs(name: str):
    """A scene's ``[recon]``, scanner, slice positions, pitch-0.1 table and object radius."""
    scene = load_scene(name)
    return (scene.recon, scene.scanner, reconstruct.slice_positions(scene), cached_projection_table(scene, 0.1),
            reconstruct.object_radius_mm(scene))


def test_the_preflight_models_the_slab_the_run_solves(reference):
    """The pre-flight's mcir part (``method.run_memory_bytes``) sizes the same views, volume and bins
    as the run's slab (its info in results.json), through the same cut."""
    _, res = reference
    rc, sc, z, table, radius = _slab_inputs("tiny")
    cuts, _ = mcir.slab_plan(sc, rc, rc.mcir, radius, table, z, 6)
    (info,) = res["stages"]["mcir"]["slabs"]["p0.100"]["noise-free"].values()
    assert cuts == [(0, len(z))]
    st = mcir.slab_setup(sc, rc, rc.mcir, radius, table.source_z_mm, z)
    assert [st.grid.nz, st.grid.ny, st.grid.nx] == info["grid"] and st.views.size == info["views"]
    assert mcir.n_bins(table.take(st.views), rc.mcir) == info["bins"]
    nv = st.grid.nz * st.grid.ny * st.grid.nx
    # one epoch (the default): the projections, one bin's SART weights and ray arrays at a time
    sub = table.take(st.views)
    largest = max(len(m) for m in mcir.state_bins(sub.cardiac_phase, sub.resp_amplitude, rc.mcir.cardiac_bins,
                                                   rc.mcir.resp_bins).members)
    ray = 4 * sc.n_rows * sc.n_cols
    assert rc.mcir.epochs == 1
    assert mcir.run_memory_bytes(sc, rc, rc.mcir, radius, table, z, 6) == \
        ray * (info["views"] + 6 * largest) + 4 * nv * (3 + 1 + 18 + 8) + 12 * nv * info["bins"]


def test_the_weights_are_counted_whole_only_where_a_later_epoch_reuses_them():
    """memory_bytes: with epochs > 1 every ray's row weight and every bin's column weights are held (the next
    epoch reuses them); with one epoch one bin's at a time (os_sart drops a subset's after its visit)."""
    grid = mcir.geo.VolumeGrid(nx=10, ny=12, nz=3, voxel_mm=4.0, z0_mm=0.0, dz_mm=2.0)
    nv, ray = 10 * 12 * 3, 4 * 5 * 7
    one = mcir.memory_bytes(grid, 100, 5, 7, 9, False, 4, epochs=1, largest_bin_views=20)
    many = mcir.memory_bytes(grid, 100, 5, 7, 9, False, 4, epochs=3, largest_bin_views=20)
    assert many - one == (ray * 100 + 4 * nv * 9) - (6 * ray * 20 + 4 * nv)


def test_a_budget_below_the_whole_cuts_slabs_under_it():
    """A slab keeps the warp fields its budget leaves (the field cache shrinks first); slabs are cut only
    where the rest of a slab alone (cache 0) is over the budget, and every slab cut fits it."""
    rc, sc, z, table, radius = _slab_inputs("demo")
    whole, cache = mcir.slab_memory(sc, rc, rc.mcir, radius, table, z, 6)
    assert 0 < cache <= mcir.FIELD_CACHE_BYTES and whole <= mcir.SLAB_BYTES
    whole_rest, none = mcir.slab_memory(sc, rc, rc.mcir, radius, table, z, 6, budget=0)
    assert none == 0 and whole_rest < whole  # the fields are demo's largest part after the projections
    squeezed, part = mcir.slab_memory(sc, rc, rc.mcir, radius, table, z, 6, budget=0.5 * (whole + whole_rest))
    assert part == int(0.5 * (whole + whole_rest)) - whole_rest and squeezed <= 0.5 * (whole + whole_rest)
    single = max(mcir.slab_memory(sc, rc, rc.mcir, radius, table, z[a:a + 1], 6, budget=0)[0] for a in range(len(z)))
    assert single < whole_rest
    budget = 0.5 * (single + whole_rest)  # some cut fits it; the whole does not, even with no fields kept
    cuts, _ = mcir.slab_plan(sc, rc, rc.mcir, radius, table, z, 6, budget=budget)
    assert len(cuts) > 1 and cuts[0][0] == 0 and cuts[-1][1] == len(z)
    assert all(a2 == b1 for (_, b1), (a2, _) in zip(cuts, cuts[1:], strict=False))
    sizes = [mcir.slab_memory_bytes(sc, rc, rc.mcir, radius, table, z[a:b], 6, budget) for a, b in cuts]
    assert max(sizes) <= budget < whole_rest


def test_the_bins_counted_are_the_bins_solved():
    """``n_bins`` (the pre-flight's count, from the bin keys alone) equals the bins ``state_bins`` makes."""
    scene = load_scene("demo")
    table = cached_projection_table(scene, 0.1)
    knobs = scene.recon.mcir
    rng = np.random.default_rng(3)
    for views in (None, np.sort(rng.choice(len(table.source_z_mm), 700, replace=False)), np.arange(40)):
        c, a = table.cardiac_phase, table.resp_amplitude
        if views is not None:
            c, a = c[views], a[views]
        bins = mcir.state_bins(c, a, knobs.cardiac_bins, knobs.resp_bins)
        assert mcir.n_bins(table, knobs, views) == len(bins)
        counts = mcir.bin_counts(table, knobs, views)        # the largest bin the one-epoch model counts
        assert sorted(counts) == sorted(len(m) for m in bins.members)


def test_the_consistency_check_judges_mcir_against_mc(reference):
    """The truth-free check of a run with mc and mcir: mc against barycentric (``verdict``) and mcir
    against mc, the image it starts from (``mcir_verdict``), per variant, in results.json, the log
    and the report."""
    out, res = reference
    ent = res["consistency"]["p0.100"]
    assert ent["config"]["methods"] == ["barycentric", "mc", "mcir"]
    for v in ("noise-free", "noisy"):
        r, ver = ent["residual"][v], ent["mcir_verdict"][v]
        assert ver["against"] == "mc" and ver["helped"] in (True, False, None)
        assert ver["regions"]["all"]["ratio"] == pytest.approx(r["mcir"]["rms_hu_mm"] / r["mc"]["rms_hu_mm"])
        assert ver["text"].startswith("mcir ") and "of mc's" in ver["text"]
        assert ent["verdict"][v]["against"] == "barycentric"  # mc's own verdict unchanged
    assert "mcir against mc, noisy: mcir " in (out / "report.md").read_text()


def test_the_slab_cut_is_said_and_a_slice_over_the_budget_warned(reference):
    _, res = reference
    cut = res["stages"]["mcir"]["slab_cut"]["p0.100"]
    assert cut["slabs"] == 1 and not cut["over_budget"] and 0 < cut["largest_bytes"] < mcir_stage.SLAB_BYTES
    assert mcir_stage.slab_line([(0, 2)], 10**9) == "1 slab of 2 slice(s), the largest modelled at 1.00 GB"
    line = mcir_stage.slab_line([(0, 1), (1, 2), (2, 3)], 12 * 10**9)
    assert line.startswith("3 slabs of 1 slice(s), the largest modelled at 12.00 GB: one slice alone is over the 6 GiB")
    assert "coarser grid" in line and "\n" not in line


def test_a_slice_over_the_budget_is_noted_before_the_work(tmp_path, monkeypatch):
    """The pre-flight's figure for the largest mcir slab reaches the run's log at its start, with the
    same words as the stage's line (here forced: the budget below tiny's slab)."""
    monkeypatch.setattr(mcir, "SLAB_BYTES", 1000)
    monkeypatch.setattr(mcir_stage, "SLAB_BYTES", 1000)
    lines = []
    with pytest.raises(ClreconError):  # stopped at once after the notes (the fault below)
        run(load_scene("tiny"), tmp_path / "o", methods=["barycentric", "mcir"], cache_dir=tmp_path / "c",
            executor="serial", progress=False, log=lambda line: (lines.append(line),
                                                                  _stop() if "mcir" in line else None))
    note = next(x for x in lines if x.startswith("note: mcir: one slice alone is over the"))
    assert "GB modelled" in note and "coarser grid" in note


def _stop():
    raise ClreconError("stop here")
