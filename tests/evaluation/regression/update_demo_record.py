"""Rewrite ``demo_metrics.json`` from a fresh run of the demo scene (on purpose, in review).

    python tests/evaluation/regression/update_demo_record.py [RUN_DIR]

With RUN_DIR, the record is taken from that finished run of ``python -m clrecon run`` (the demo
scene) instead of running it again. The diff of the JSON file is the review: every changed
number shows.
"""

from __future__ import annotations

import json
import sys
import tempfile
from pathlib import Path

HERE = Path(__file__).resolve().parent
RECORD = HERE / "demo_metrics.json"


def record_from_results(res: dict) -> dict:
    """The regression record of a demo run: pooled Table-2 MAE/std per pitch, variant, method, FOV."""
    out = {}
    for pk, byv in res["metrics"].items():
        for v, bym in byv.items():
            for m, r in bym.items():
                for fov in ("large", "small"):
                    out[f"{pk}/{v}/{m}/{fov}"] = {"mae_hu": r[fov]["mae_hu"], "std_hu": r[fov]["std_hu"]}
    return {"scene": res["scene"]["name"], "methods": res["request"]["methods"],
            "pitches": res["request"]["pitches"], "variants": res["request"]["variants"], "metrics": out}


def main(argv: list[str]) -> int:
    if argv:
        res = json.loads((Path(argv[0]) / "results.json").read_text())
    else:
        from clrecon.config.scene import load_scene
        from clrecon.pipeline.run import run

        with tempfile.TemporaryDirectory() as tmp:
            res = run(load_scene("demo"), Path(tmp) / "run", progress=False, report=False)
    if res["scene"]["name"] != "demo":
        raise SystemExit(f"{argv[0]} is a run of scene {res['scene']['name']!r}, not demo")
    RECORD.write_text(json.dumps(record_from_results(res), indent=1, sort_keys=True) + "\n")
    print(f"wrote {RECORD}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
