"""Bench section ``truth_free`` (only when named): the cost of ``recon.truth_free``.

Against the reconstruction it accompanies: ``demo``, its 4 middle slices (``--quick``: 2), one run.
"""

from __future__ import annotations

import tempfile
from pathlib import Path

from clrecon.bench.timing import load1
from clrecon.config.scene import load_scene
from clrecon.pipeline.run import run as run_pipeline


def run(quick: bool = False, repeats: int = 3, log=print, *, scene="demo") -> dict:
    """Cost of ``recon.truth_free`` against the reconstruction it accompanies: :func:`clrecon.pipeline.run.run`
    on the scene's 4 middle slices (quick: 2) with it on, the truth_free stage's seconds next to the
    reconstruction's (read + noise + rebin + interpolate + fbp), same run, same cache (one run: ``repeats``
    and ``log`` unused)."""
    sc = load_scene(scene) if isinstance(scene, str) else scene
    nz = sc.recon.nz
    half = 1 if quick else 2
    slices = (max(0, nz // 2 - half), min(nz, nz // 2 + half))
    load = load1()
    with tempfile.TemporaryDirectory(prefix="clrecon-bench-tf-") as tmp:
        res = run_pipeline(sc.replace(recon={"truth_free": True}), Path(tmp) / "run", slice_range=slices,
                           cache_dir=Path(tmp) / "cache", progress=False, report=False, log=lambda *a, **k: None)
    st = res["stages"]
    recon_s = sum(st[k]["seconds"] for k in ("read", "noise", "rebin", "interpolate", "fbp") if k in st)
    tf_s = st["truth_free"]["seconds"]
    per_pitch = {pk: e["seconds"] for pk, e in res["truth_free"].items()}
    return {"scene": sc.name, "slices": list(slices), "methods": list(res["request"]["methods"]),
            "variants": list(res["request"]["variants"]), "load_average_1min_before": load,
            "truth_free_s": tf_s, "reconstruction_s": recon_s, "ratio": tf_s / recon_s if recon_s else None,
            "per_pitch": per_pitch, "folds": {pk: e["folds"] for pk, e in res["truth_free"].items()}}


def report_lines(tfc: dict) -> list[str]:
    """The section's lines of the bench report."""
    out = []
    out.append(f"truth-free CV ({tfc['scene']}, slices {tfc['slices'][0]}:{tfc['slices'][1]}, "
               f"{', '.join(tfc['methods'])}; {', '.join(tfc['variants'])}): {tfc['truth_free_s']:.1f} s "
               f"against {tfc['reconstruction_s']:.1f} s of reconstruction (x{tfc['ratio']:.2f}), "
               f"load {tfc['load_average_1min_before']}")
    return out
