"""The demo's metrics as a regression record -- not a claim of physics.

``tests/evaluation/regression/demo_metrics.json`` holds the pooled Table-2 MAE and std (HU) of every
pitch, noise variant, method and field of view of ``python -m clrecon run`` on the demo
scene. Any change of the code that moves one of them by more than ``ATOL_HU`` fails here and
must update the record on purpose (``python tests/evaluation/regression/update_demo_record.py``), so the
change of numbers is visible in review. What the numbers mean is in docs/results/demo.md "demo" and
in the run's ``claims``; this test only says they did not change by accident.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

from clrecon.config.scene import load_scene
from clrecon.pipeline.run import run

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE / "regression"))
from update_demo_record import RECORD, record_from_results  # noqa: E402

#: Tolerance of the record (HU): the runs are deterministic on one machine (seeded signals and
#: noise, fixed reduction orders); a different CPU's float32 vector code may move the last
#: digits, far below 0.01 HU.
ATOL_HU = 0.01


@pytest.fixture(scope="module")
def demo_record(tmp_path_factory):
    out = tmp_path_factory.mktemp("demo")
    res = run(load_scene("demo"), out / "run", cache_dir=out / "cache", progress=False, report=False,
              log=lambda *a: None)
    return record_from_results(res)


def test_demo_metrics_match_the_regression_record(demo_record):
    want = json.loads(RECORD.read_text())
    assert {k: want[k] for k in ("scene", "methods", "pitches", "variants")} == \
        {k: demo_record[k] for k in ("scene", "methods", "pitches", "variants")}
    assert sorted(want["metrics"]) == sorted(demo_record["metrics"])
    moved = {k: (want["metrics"][k][q], demo_record["metrics"][k][q])
             for k in want["metrics"] for q in ("mae_hu", "std_hu")
             if abs(want["metrics"][k][q] - demo_record["metrics"][k][q]) > ATOL_HU}
    assert not moved, f"demo metrics moved (record, now) in HU; update the record on purpose: {moved}"
