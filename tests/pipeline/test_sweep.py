"""Study files of ``clrecon sweep`` (clrecon.pipeline.sweep): parsing, the grid, point names, errors.
A sweep that runs (on a 2-worker cluster, and resumes) is in tests/pipeline/test_distributed.py."""

import pytest

from clrecon.cli import main
from clrecon.core.errors import ClreconError
from clrecon.pipeline.sweep import load_study, point_name, point_scene


def _study(tmp_path, text):
    p = tmp_path / "study.toml"
    p.write_text(text)
    return p


def test_grid_points_names_and_scenes(tmp_path):
    study = load_study(_study(tmp_path, 'scene = "tiny"\n[set]\n"noise.enabled" = false\n'
                                        '[grid]\n"recon.kappa" = [0.05, 0.1]\n"signals.rhythm" = ["periodic", "af"]\n'))
    assert study.name == "study"
    points = study.points()
    assert len(points) == 4 and points[1] == {"recon.kappa": 0.05, "signals.rhythm": "af"}
    assert [point_name(p) for p in points[:2]] == ["kappa=0.05_rhythm=periodic", "kappa=0.05_rhythm=af"]
    sc = point_scene(study, points[3])
    assert sc.recon.kappa == 0.1 and sc.signals.rhythm == "af" and not sc.noise.enabled


@pytest.mark.parametrize("text, match", [
    ('scene = "tiny"\n', r"\[grid\]: expected a table of swept keys"),
    ('scene = "tiny"\n[grid]\n"recon.kappa" = 0.1\n', r"recon.kappa: expected a non-empty list"),
    ('scene = "tiny"\n[grid]\nkappa = [0.1]\n', r"kappa: expected SECTION.KEY"),
    ('scene = "tiny"\nmethod = ["x"]\n[grid]\n"recon.kappa" = [0.1]\n', r"method: unknown study key"),
    ('scene = "tiny"\n[grid]\n"recon.kapa" = [0.1]\n', r"point kapa=0.1: .*kapa"),
    ('scene = "tiny"\n[grid]\n"signals.rhythm" = ["sinus"]\n', r"point rhythm=sinus: .*rhythm"),
    ('[grid]\n"recon.kappa" = [0.1]\n', r"no scene"),
    ('scene = "nope"\n[grid]\n"recon.kappa" = [0.1]\n', r"neither a file nor a built-in scene"),
])
def test_bad_study_files_say_what_is_wrong(tmp_path, text, match):
    with pytest.raises(ClreconError, match=match):
        load_study(_study(tmp_path, text))


def test_cli_sweep_reports_a_bad_file_in_one_line(tmp_path, capsys):
    assert main(["sweep", str(tmp_path / "missing.toml")]) == 2
    assert "cannot read the study file" in capsys.readouterr().err
