"""Issue 42's pipeline rows: one `demo` run at pitch 0.10 with barycentric, local linear, `mc` and `mcir`,
`[recon.mcir]` knobs from the command line (docs/results/iterative-study.md "5. Starting from `mc`").

    PYTHONPATH=. python benchmarks/studies/iterative/pipeline_runs.py [SCENE] [KEY=VALUE ...]

e.g. ``init=zero``, ``init=first_pass epochs=1``. Prints, and appends to ``pipeline_runs.jsonl``
beside this script, the MAE per method (large / small FOV, HU) against the ground-truth CT and
against the phantom itself, `mcir`'s solver history and every method's seconds. The run folder
and the projection cache are under $ITER_RUNS_DIR (default /tmp/clrecon-iter-runs).
"""

import json
import os
import sys
import time

from clrecon.config.overrides import load_scene
from clrecon.pipeline.run import run

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.environ.get("ITER_RUNS_DIR", "/tmp/clrecon-iter-runs")


def main(argv):
    scene_name = argv[0] if argv and "=" not in argv[0] else "demo"
    knobs = dict(a.split("=", 1) for a in argv if "=" in a)
    over = {f"recon__mcir__{k}": (int(v) if v.isdigit() else v) for k, v in knobs.items()}
    tag = "-".join(f"{k}{v}" for k, v in knobs.items()) or "default"
    t = time.time()
    res = run(load_scene(scene_name, **over), f"{ROOT}/{scene_name}-{tag}",
              methods=["barycentric", "local_linear", "mc", "mcir"], pitches=[0.1], cache_dir=f"{ROOT}/cache",
              report=False, progress=False)
    out = {"scene": scene_name, "knobs": knobs, "wall_s": round(time.time() - t, 1), "load": os.getloadavg(),
           "start": res["stages"]["mcir"]["start"]}
    for v, m in res["metrics"]["p0.100"].items():
        out[v] = {k: [round(m[k][f]["mae_hu"], 2) for f in ("large", "small")] for k in m}
        out[v + " phantom"] = {k: [round(m[k][f]["mae_phantom_hu"], 2) for f in ("large", "small")] for k in m}
        out[v + " sart"] = [i["sart"] for i in res["stages"]["mcir"]["slabs"]["p0.100"][v].values()]
        out[v + " seconds"] = res["method_seconds"]["p0.100"][v]
    print(json.dumps(out))
    with open(os.path.join(HERE, "pipeline_runs.jsonl"), "a") as f:
        f.write(json.dumps(out) + "\n")


if __name__ == "__main__":
    main(sys.argv[1:])
