"""docs/reproduction.md's tables from run directories: Table 2 beside the paper's values,
claims over the pitches of several runs together."""

from fake_run_dir import make_fake_run

from clrecon.outputs import reproduction


def test_two_runs_one_pitch_each_make_one_table_with_the_papers_values(tmp_path, capsys):
    make_fake_run(tmp_path / "p002", pitches=(0.02,))
    make_fake_run(tmp_path / "p010", pitches=(0.1,), seed=1)
    assert reproduction.main([str(tmp_path / "p002"), str(tmp_path / "p010")]) == 0
    md = capsys.readouterr().out
    table = md.split("### Table 2")[1].split("###")[0]
    assert "pitch 0.020 large FOV" in table and "pitch 0.100 small FOV" in table
    row = next(line for line in table.splitlines() if line.startswith("| local_linear |"))
    assert "(paper 21.8)" in row and "(paper 22.9)" in row and "(paper 33.5)" in row and "(paper 38.1)" in row
    assert "(paper" not in next(line for line in table.splitlines() if line.startswith("| nearest |"))
    # a claim that needs both pitches is measured across the two runs
    assert "| pitch 0.02 below 0.1 |" in md
    assert "### Stage times" in md and "### Memory and disk" in md


def test_a_directory_without_results_is_one_line(tmp_path):
    import pytest

    with pytest.raises(SystemExit, match="not a finished run"):
        reproduction.main([str(tmp_path)])
