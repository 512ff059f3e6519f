"""Atomic outputs: every file a user opens by name appears whole or not at all, and a failed start
leaves nothing behind that a later run or reader would take for a run.

The faults are injected (``CLRECON_FAULT=write:<file name>:<n>:enospc``, :mod:`clrecon.core.faults`)
half-way through the bytes of a write: what a full disk does, without needing a small tmpfs (the
issue's disk-full test on a 20 MiB tmpfs left 0-byte PNGs under their final names).
"""

from __future__ import annotations

import errno
import os
import subprocess
import sys
from pathlib import Path

import pytest

from clrecon.cli import main
from clrecon.config.scene import load_scene
from clrecon.core import atomic, faults, jsonio
from clrecon.core.errors import ClreconError
from clrecon.core.runtime import Runtime
from clrecon.pipeline import slabs
from clrecon.pipeline.run import run

ARGV = ["run", "--scene", "tiny", "--methods", "nearest", "--no-progress"]
PNG_END = b"IEND\xaeB`\x82"


def _argv(out, cache):
    return ARGV + ["--out", str(out), "--cache", str(cache)]


def _partials(folder: Path) -> list[Path]:
    return [p for p in folder.rglob("*") if ".partial" in p.name]


def _whole_png(p: Path) -> bool:
    b = p.read_bytes()
    return b.startswith(b"\x89PNG\r\n\x1a\n") and b.endswith(PNG_END)


@pytest.fixture
def fresh_faults(monkeypatch):
    """A clean fault counter (the figures are drawn here, where the fault is set: no helper process
    under pytest, and write_figures without a pool draws in this process)."""
    faults._counts.clear()
    yield monkeypatch
    faults._counts.clear()


# ---------------------------------------------------------------------------------------
# the writer itself
def test_write_is_whole_or_absent_and_keeps_the_previous_version(tmp_path, fresh_faults):
    p = tmp_path / "a.json"
    fresh_faults.setenv("CLRECON_FAULT", "write:a.json:1:enospc")
    with pytest.raises(OSError) as e:
        atomic.write_json(p, {"x": 1})
    assert e.value.errno == errno.ENOSPC and not p.exists() and not _partials(tmp_path)
    fresh_faults.delenv("CLRECON_FAULT")
    atomic.write_json(p, {"x": 1})
    fresh_faults.setenv("CLRECON_FAULT", "write:a.json:2:enospc")  # the 2nd write from now on
    faults._counts.clear()
    atomic.write_json(p, {"x": 2})
    with pytest.raises(OSError):
        atomic.write_json(p, {"x": 3})
    assert jsonio.loads(p.read_text()) == {"x": 2} and not _partials(tmp_path)


def test_replacing_removes_the_temporary_file_when_the_writer_fails(tmp_path):
    p = tmp_path / "t.nii.gz"
    with pytest.raises(RuntimeError), atomic.replacing(p, keep_suffix=".nii.gz") as tmp:
        assert tmp.name == "t.partial.nii.gz"
        tmp.write_bytes(b"half")
        raise RuntimeError("the writer failed")
    assert not p.exists() and not _partials(tmp_path)


def test_fault_spec_parsing():
    assert faults.parse("recon:2") == ("recon", 2, "kill")
    assert faults.parse("write:*.png:1:enospc") == ("write:*.png", 1, "enospc")
    with pytest.raises(ValueError, match="expected <point>:<n>"):
        faults.parse("write:x")


# ---------------------------------------------------------------------------------------
# a run's outputs
def test_a_figure_that_hits_a_full_disk_leaves_no_file_under_its_name(tmp_path, fresh_faults, capsys):
    """The first PNG write fails half-way: the figure is reported as failed, every PNG present is whole,
    no temporary file is left, and the run still finishes (a figure must not cost the run its report)."""
    fresh_faults.setenv("CLRECON_FAULT", "write:*.png:1:enospc")
    out = tmp_path / "run"
    assert main(_argv(out, tmp_path / "cache")) == 0
    pngs = sorted((out / "figures").glob("*.png"))
    assert pngs and all(_whole_png(p) for p in pngs)
    report = (out / "report.md").read_text()
    failed = [ln for ln in report.splitlines() if "failed (OSError" in ln and "No space left on device" in ln]
    assert len(failed) == 1, report
    assert not _partials(out)
    fresh_faults.delenv("CLRECON_FAULT")
    faults._counts.clear()
    assert main(_argv(out, tmp_path / "cache")) == 0  # the rerun draws every figure
    assert "failed (" not in (out / "report.md").read_text()
    assert len(list((out / "figures").glob("*.png"))) == len(pngs) + 1


@pytest.mark.parametrize("name", ["report.md", "report.html", "results.json"])
def test_a_report_file_that_hits_a_full_disk_is_absent_and_the_rerun_completes(tmp_path, fresh_faults, capsys, name):
    out, cache = tmp_path / "run", tmp_path / "cache"
    fresh_faults.setenv("CLRECON_FAULT", f"write:{name}:1:enospc")
    assert main(_argv(out, cache)) == 2
    err = capsys.readouterr().err
    assert err.startswith("clrecon: error: disk full") and err.count("\n") == 1, err
    assert not (out / name).exists() and not _partials(out)
    assert not (out / "results.json").exists()  # nothing says the run is finished
    assert not (out / "report.md").exists() and not (out / "report.html").exists()
    fresh_faults.delenv("CLRECON_FAULT")
    faults._counts.clear()
    assert main(_argv(out, cache)) == 0
    jsonio.loads_strictly((out / "results.json").read_text())
    assert (out / name).stat().st_size > 0 and not _partials(out)


def test_a_full_disk_at_results_json_leaves_no_report_that_reads_as_finished(tmp_path, monkeypatch, capsys):
    """results.json hits a full disk (as at 900-1700 KiB free): the run exits 2 and leaves no report.md or
    report.html (it left a complete report, full metric tables, beside volumes.h5 and no results.json);
    the rerun writes all three."""
    from clrecon.pipeline.stages import results as results_mod

    def full(path, obj):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(path))

    monkeypatch.setattr(results_mod, "_write_json_atomic", full)
    out, cache = tmp_path / "run", tmp_path / "cache"
    assert main(_argv(out, cache)) == 2
    err = capsys.readouterr().err
    assert err.startswith("clrecon: error: disk full") and err.count("\n") == 1, err
    assert (out / "volumes.h5").exists() and not (out / "results.json").exists()
    assert not (out / "report.md").exists() and not (out / "report.html").exists() and not _partials(out)
    monkeypatch.undo()
    assert main(_argv(out, cache)) == 0
    jsonio.loads_strictly((out / "results.json").read_text())
    assert "## Stages" in (out / "report.md").read_text() and (out / "report.html").exists() and not _partials(out)


def test_kill_mid_write_leaves_only_a_partial_file(tmp_path):
    """SIGKILL half-way through results.json: no torn results.json, only results.json.partial; the rerun
    finishes and replaces it."""
    out, cache = tmp_path / "run", tmp_path / "cache"
    env = dict(os.environ, CLRECON_FAULT="write:results.json:1", CLRECON_NO_PROGRESS="1",
               PYTHONPATH=str(Path(__file__).resolve().parents[2]))
    cmd = [sys.executable, "-m", "clrecon"] + _argv(out, cache)
    p = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=600)
    assert p.returncode == -9, p.stderr
    assert not (out / "results.json").exists() and (out / "results.json.partial").exists()
    assert not (out / "report.md").exists() and not (out / "report.html").exists()  # no report without results
    env.pop("CLRECON_FAULT")
    p = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=600)
    assert p.returncode == 0, p.stderr
    jsonio.loads_strictly((out / "results.json").read_text())
    assert not _partials(out)


def test_nifti_export_that_hits_a_full_disk(tmp_path, fresh_faults, capsys):
    pytest.importorskip("nibabel")
    out, cache = tmp_path / "run", tmp_path / "cache"
    assert main(_argv(out, cache)) == 0
    exp = tmp_path / "nii"
    fresh_faults.setenv("CLRECON_FAULT", "write:*.nii.gz:2:enospc")
    assert main(["export", str(out), "--format", "nifti", "--out", str(exp)]) == 2
    assert capsys.readouterr().err.startswith("clrecon: error: disk full")
    files = sorted(exp.glob("*.nii.gz"))
    assert len(files) == 1 and not (exp / "index.json").exists() and not _partials(exp)
    import nibabel as nib

    assert nib.load(files[0]).get_fdata().size > 0  # the one written is whole


# ---------------------------------------------------------------------------------------
# failed starts
def _failing_build(*a, **k):
    raise RuntimeError("kernels/interp.cl: the OpenCL build failed (injected)")


def test_a_failed_start_leaves_no_stub_and_no_folder(tmp_path, monkeypatch):
    """A kernel that does not build (injected) before any unit is written: no run folder, no
    volumes.h5.units/run.json stub, no empty volumes.d/ (they were left behind before)."""
    monkeypatch.setattr(slabs, "plan_pitch", _failing_build)
    out = tmp_path / "run"
    with pytest.raises(RuntimeError, match="build failed"):
        run(load_scene("tiny"), out, methods=["nearest"], cache_dir=tmp_path / "cache", progress=False,
            report=False, log=lambda *a: None)
    assert not out.exists()


def test_a_failed_start_beside_an_earlier_result_keeps_it_and_leaves_no_empty_folder(tmp_path, monkeypatch):
    import hashlib

    out, cache = tmp_path / "run", tmp_path / "cache"
    run(load_scene("tiny"), out, methods=["nearest"], cache_dir=cache, progress=False, log=lambda *a: None)
    digest = {p.relative_to(out): hashlib.sha256(p.read_bytes()).hexdigest() for p in out.rglob("*") if p.is_file()}
    monkeypatch.setattr(slabs, "plan_pitch", _failing_build)
    with pytest.raises(RuntimeError, match="build failed"):  # another request: a new result would start
        run(load_scene("tiny"), out, methods=["bin"], cache_dir=cache, progress=False, log=lambda *a: None)
    for rel, h in digest.items():  # the earlier result untouched
        assert hashlib.sha256((out / rel).read_bytes()).hexdigest() == h, rel
    # what the failed start made is either resumable work (truths taken from the cache, units under a
    # run.json that names them) or gone: no empty folder, no run.json without units
    assert not [d for d in out.rglob("*") if d.is_dir() and not any(d.iterdir())]
    units = out / "volumes.h5.units"
    if units.exists():
        gen = jsonio.loads((units / "run.json").read_text())["datasets"]
        assert any((out / "volumes.d" / gen).iterdir())


def test_preflight_refuses_a_buffer_above_the_device_allocation_limit(tmp_path, monkeypatch):
    """recon.ny = 1 000 000 passed the pre-flight and failed in OpenCL (OUT_OF_HOST_MEMORY): the pre-flight
    now checks the buffers a run cannot split against CL_DEVICE_MAX_MEM_ALLOC_SIZE, before any work."""
    monkeypatch.setattr(Runtime, "max_alloc_bytes", property(lambda self: 512 * 1024))
    out = tmp_path / "run"
    with pytest.raises(ClreconError) as e:
        run(load_scene("tiny"), out, methods=["nearest"], cache_dir=tmp_path / "cache", progress=False,
            report=False, log=lambda *a: None)
    msg = str(e.value)
    assert msg.startswith("pre-flight: the interleaved sinograms of one backprojection launch need one device "
                          "buffer of") and "CL_DEVICE_MAX_MEM_ALLOC_SIZE" in msg and "\n" not in msg
    assert not out.exists()
