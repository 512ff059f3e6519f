"""Progress: a log line with an ETA when stderr is not a terminal (nohup, batch jobs)."""

import io

from clrecon.core import progress as progress_mod
from clrecon.core.progress import LogProgress


def test_log_lines_carry_counts_rate_and_eta():
    out = io.StringIO()
    with LogProgress(10, "simulate demo", unit="proj", interval=0.0, stream=out) as bar:
        for _ in range(10):
            bar.update(1)
    lines = out.getvalue().splitlines()
    assert len(lines) == 10  # one per update before the end (interval 0), and the final line
    assert lines[0].startswith("[clrecon] simulate demo: 1/10 proj (10 %)") and "ETA" in lines[0]
    assert lines[-1].startswith("[clrecon] simulate demo: 10/10 proj in 0:00:00")


def test_interval_limits_the_lines():
    out = io.StringIO()
    bar = LogProgress(1000, "noise", interval=3600.0, stream=out)
    for _ in range(1000):
        bar.update(1)
    bar.close()
    bar.close()  # idempotent
    assert len(out.getvalue().splitlines()) == 1


def test_silenced_by_the_environment(monkeypatch, capsys):
    monkeypatch.setenv("CLRECON_NO_PROGRESS", "1")
    bar = progress_mod.progress(5, "x")
    bar.update(5)
    bar.close()
    assert capsys.readouterr().err == ""
    monkeypatch.delenv("CLRECON_NO_PROGRESS")
    bar = progress_mod.progress(5, "x")  # stderr captured: not a terminal -> log lines
    assert isinstance(bar, LogProgress)
    bar.update(5)
    bar.close()
    assert "[clrecon] x: 5/5" in capsys.readouterr().err
