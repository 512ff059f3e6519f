"""Patient data: no identifier and no identifier-bearing path in any output or cache by default, and
``--keep-identifiers`` doing in every writer what docs/patient-data.md says (issue 37, item 3).

A measured series is planted with identifiers in every file and kept in a folder named after the
patient, with its traces and scene file beside it; the whole command line runs on it (``run`` in a
fresh process with its own HOME, so the default caches are in the test's folder too; then every
export), and every byte written anywhere is searched for the planted values. The fresh process also
measures the run's peak memory against the pre-flight's model (issue 35: within 1.5x on a measured scan).
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pydicom
import pytest

from clrecon.cli import main
from clrecon.config.scene import load_scene
from clrecon.outputs.export import export
from clrecon.pipeline.run import run

PATIENT_DIR = "Doe_Jane_MRN-778899"
#: attribute -> planted value (all distinctive enough that a hit in any binary file is the value itself)
PLANTED = {"PatientName": "DOE^JANE", "PatientID": "MRN-778899", "PatientBirthDate": "19610723", "PatientSex": "F",
           "PatientAge": "063Y", "AccessionNumber": "ACC5551234", "ReferringPhysicianName": "HOUSE^GREGORY",
           "InstitutionName": "St Elsewhere Clinic", "StudyID": "STUDY4242", "StudyDate": "20240117",
           "StudyTime": "101112"}
#: what must never appear by default (the identifiers and the folder's name)
MARKERS = ["DOE^JANE", "Doe_Jane", "MRN-778899", "778899", "19610723", "ACC5551234", "HOUSE^GREGORY", "Elsewhere",
           "STUDY4242", "20240117"]


def _quiet(*a, **k):
    pass


@pytest.fixture(scope="module")
def patient(tmp_path_factory):
    """A measured series of ``tiny`` in a folder named after the patient, identifiers in every file."""
    root = tmp_path_factory.mktemp("patient")
    run(load_scene("tiny"), root / "sim", methods=["nearest"], cache_dir=root / "simcache", progress=False,
        report=False, log=_quiet)
    pdir = root / "data" / PATIENT_DIR
    export(root / "sim", "dicom-ct-pd", out=pdir)
    for f in sorted((pdir / "projections").glob("*.dcm")):
        ds = pydicom.dcmread(f)
        for k, v in PLANTED.items():
            setattr(ds, k, v)
        ds.save_as(f)
    # traces named after the patient too, and the scene file in the patient's folder
    (pdir / "breathing.vxp").rename(pdir / "Doe_Jane_breathing.vxp")
    (pdir / "r_peaks.csv").rename(pdir / "Doe_Jane_ecg.csv")
    toml = (pdir / "measured.toml").read_text().replace('"breathing.vxp"', '"Doe_Jane_breathing.vxp"')
    toml = "\n".join(line for line in toml.splitlines() if not line.startswith("name = "))  # the default name
    (pdir / "Doe_Jane.toml").write_text(toml.replace('"r_peaks.csv"', '"Doe_Jane_ecg.csv"') + "\n")
    (pdir / "measured.toml").unlink()
    out = root / "out"
    home = root / "home"
    home.mkdir()
    env = {k: v for k, v in os.environ.items() if k not in ("CLRECON_CACHE",)}
    env.update(HOME=str(home), PYTHONPATH=str(Path(__file__).resolve().parents[2]))
    proc = subprocess.run([sys.executable, "-m", "clrecon", "run", "--scene", str(pdir / "Doe_Jane.toml"),
                           "--out", str(out / "run"), "--methods", "nearest", "--no-progress"],
                          env=env, capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, proc.stderr[-2000:]
    return {"root": root, "dir": pdir, "scene": pdir / "Doe_Jane.toml", "out": out, "home": home,
            "log": proc.stdout + proc.stderr}


def _hits(folder: Path, markers) -> list[str]:
    found = []
    for p in sorted(folder.rglob("*")):
        if p.is_file():
            raw = p.read_bytes()
            found += [f"{p.relative_to(folder)}: {m}" for m in markers if m.encode() in raw]
        found += [f"{p.relative_to(folder)}: {m} (name)" for m in markers if m in p.name]
    return found


def test_no_identifier_or_patient_path_in_any_output_or_cache(patient, capsys):
    out, home = patient["out"], patient["home"]
    run_dir = out / "run"
    # every export a user makes by default
    assert main(["export", str(run_dir), "--format", "dicom", "--method", "nearest",
                 "--out", str(out / "dicom")]) == 0
    assert main(["export", str(run_dir), "--format", "nifti", "--method", "nearest", "--out", str(out / "nifti")]) == 0
    assert main(["export", str(run_dir), "--format", "dicom-ct-pd", "--scene", str(patient["scene"]),
                 "--out", str(out / "dicom-ct-pd")]) == 0
    log = patient["log"] + capsys.readouterr().out
    # the cache (the default one, under this HOME), the run folder, the exports and the logs
    assert list((home / ".cache" / "clrecon").glob("*.h5")), "the run used the default cache"
    assert _hits(out, MARKERS) == []
    assert _hits(home, MARKERS) == []
    assert [m for m in MARKERS if m in log] == []
    res = json.loads((run_dir / "results.json").read_text())
    assert res["scene"]["scan"]["projections"].startswith("dicom-ct-pd series ")
    assert res["scene"]["signals"]["breathing_trace"].startswith("file ")
    assert res["scene_source"].startswith("file ")
    assert res["scene"]["name"] == "measured"  # not the scene file's name (Doe_Jane.toml)


def test_memory_model_within_one_and_a_half_of_the_measured_peak(patient):
    res = json.loads((patient["out"] / "run" / "results.json").read_text())
    modelled, peak = res["preflight"]["needs_bytes"]["memory"], res["peak_rss_bytes"]
    assert 1 / 1.5 <= peak / modelled <= 1.5, (peak / 2**30, modelled / 2**30)


def test_keep_identifiers_copies_what_the_docs_say_in_every_writer(patient, tmp_path):
    run_dir = patient["out"] / "run"
    with pytest.raises(Exception, match=r"--scene"):
        export(run_dir, "dicom", method="nearest", out=tmp_path / "x", keep_identifiers=True)
    export(run_dir, "dicom", method="nearest", out=tmp_path / "dicom", keep_identifiers=True, scene=patient["scene"])
    export(run_dir, "dicom-ct-pd", out=tmp_path / "pd", keep_identifiers=True, scene=patient["scene"])
    for f in (sorted((tmp_path / "dicom").rglob("*.dcm"))[0], sorted((tmp_path / "pd").rglob("*.dcm"))[0]):
        ds = pydicom.dcmread(f)
        for k, v in PLANTED.items():
            assert str(ds.get(k)) == v, (f.name, k, ds.get(k))
    shutil.rmtree(tmp_path / "dicom")
