"""One paper-scale slab end to end (``-m slow``: minutes, not part of the default suite).

paper-p010 (Table 1, pitch 0.10: 900 x 64 detector, 984 views, 512 x 512 at 1 mm), two
slices at the centre of the volume, every method (with the phase-blind helical baseline),
noisy and noise-free, all 50 targets: the whole pipeline at the paper's sizes, in a child
process so that its peak memory is its own.
"""

import json
import subprocess
import sys

import numpy as np
import pytest

from clrecon.config.scene import load_scene
from clrecon.outputs.volumes import open_volumes, read_volume
from clrecon.reconstruction.interpolation import METHODS

pytestmark = pytest.mark.slow

CHILD = """
import json, resource, sys
from clrecon.api import load_scene, run
res = run(load_scene("paper-p010"), sys.argv[1], slices=(54, 56), cache=sys.argv[2], progress=False)
print(json.dumps({"peak_rss_kib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss,
                  "total_seconds": res.results["total_seconds"]}))
"""


def test_one_paper_scale_slab_end_to_end(tmp_path):
    out = tmp_path / "run"
    proc = subprocess.run([sys.executable, "-c", CHILD, str(out), str(tmp_path / "cache")],
                          capture_output=True, text=True, timeout=3600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    child = json.loads(proc.stdout.strip().splitlines()[-1])
    assert child["peak_rss_kib"] * 1024 < 8 * 1024 ** 3  # the bound on peak memory
    res = json.loads((out / "results.json").read_text())
    scene = load_scene("paper-p010")
    methods = scene.recon.methods
    assert "helical" in methods and set(res["request"]["variants"]) == {"noisy", "noise-free"}
    met = res["metrics"]["p0.100"]
    for v in ("noisy", "noise-free"):
        for m in methods:
            for fov in ("large", "small"):
                assert np.isfinite(met[v][m][fov]["mae_hu"]) and met[v][m][fov]["mae_hu"] > 0
    nf = met["noise-free"]
    # the phase-blind baseline is worse in the heart than every 5D method (the paper's premise)
    for m in ("barycentric", "local_linear", "nearest", "bin"):
        assert nf["helical"]["small"]["mae_hu"] > nf[m]["small"]["mae_hu"], m
    # noise only adds error
    for m in methods:
        assert met["noisy"][m]["large"]["mae_hu"] > nf[m]["large"]["mae_hu"], m
    # reading only the rows a slab uses: far fewer cells than whole projections
    sim = res["stages"]["simulate"]["per_pitch"]["p0.100"]
    whole = sim["projections_needed"] * scene.scanner.n_rows * scene.scanner.n_cols
    assert 0 < res["stages"]["noise"]["cells"] < 0.5 * whole
    with open_volumes(out) as f:
        for m in methods:
            ds = f[f"recon/p0.100/noisy/{m}"]
            assert ds.dtype == np.float16  # the paper scenes store half precision
            grid = METHODS[m].target_grid
            assert ds.shape == {"resp": (1, 10), "none": (1, 1)}.get(grid, (5, 10)) + (2, 512, 512)
        vol = read_volume(f, "recon/p0.100/noisy/local_linear", (2, 3))
        assert vol.shape == (2, 512, 512) and vol.dtype == np.float32 and np.isfinite(vol).all()
    assert (out / "report.md").exists()
