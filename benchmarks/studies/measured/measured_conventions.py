"""The figures of docs/results/measured-conventions.md "Every convention, measured": rod and water per convention.

The engine's simulator scans the rod phantom of ``tests/support/rod_phantom.py`` (water cylinder, bone rod at
(40, 24) mm, bone sphere; cylindrical detector with a quarter-channel offset), the DICOM-CT-PD writer
writes it in each convention, and the measured reconstruction is measured: rod centre error (mm), water
mean (HU), rod core (HU), and the orientation check's residuals for the reading and its mirrors.

    .venv/bin/python benchmarks/studies/measured/measured_conventions.py OUT_DIR   # writes its measured-conventions.json
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import h5py
import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parents[2] / "tests" / "support"))
import rod_phantom as rp

from clrecon.config.scene import load_scene
from clrecon.core.errors import ClreconError
from clrecon.outputs.rundir import RunDirectory
from clrecon.outputs.volumes import read_volume
from clrecon.outputs.writers.dicom_ct_pd import Convention, export_scan
from clrecon.pipeline.run import run


def quiet(*a, **k):
    pass


def simulate(root: Path, name: str, symmetric=False, **scan) -> Path:
    frames = rp.write_phantom(root / f"ph-{int(symmetric)}", symmetric=symmetric)
    (root / f"{name}.toml").write_text(rp.scene_toml(frames, **scan))
    run(load_scene(root / f"{name}.toml"), root / name, cache_dir=root / "cache", progress=False, report=False,
        log=quiet)
    return root / name


def series(sim: Path, out: Path, **conv) -> Path:
    export_scan(RunDirectory(sim), out, convention=Convention(**conv))
    text = "".join(x for x in (out / "measured.toml").read_text().splitlines(True) if not x.startswith("flip_"))
    (out / "undeclared.toml").write_text(text)
    return out


def measure(root: Path, toml: Path, name: str, extra: dict | None = None) -> dict:
    t = toml
    if extra:
        t = toml.parent / f"{name}.toml"
        t.write_text(toml.read_text().replace('timestamp_unit = "ms"\n', 'timestamp_unit = "ms"\n' + "".join(
            f"{k} = {json.dumps(v)}\n" for k, v in extra.items())))
    try:
        scene = load_scene(t)
    except ClreconError as e:
        return {"refused": str(e).split(": ", 1)[1]}
    res = run(scene, root / f"run-{name}", cache_dir=root / "cache", progress=False, report=False, log=quiet)
    with h5py.File(root / f"run-{name}" / "volumes.h5") as f:
        x, y = f["axes/x_mm"][()], f["axes/y_mm"][()]
        vol = read_volume(f, f"recon/p{scene.scan.pitches[0]:.3f}/measured/nearest", (0, 0))
    m = [rp.rod_position_and_water(vol[k], x, y) for k in range(vol.shape[0])]
    ck = res["measured_scan"]["orientation_check"]
    return {"rod_error_mm": max(s["rod_error_mm"] for s in m), "water_hu": max((s["water_hu"] for s in m), key=abs),
            "rod_core_hu": float(np.mean([s["rod_core_hu"] for s in m])),
            "channels": {k: ck["channels"].get(k) for k in ("residuals", "verdict", "ratio")},
            "rows": {k: ck["rows"].get(k) for k in ("residuals", "verdict", "ratio")},
            "reading": res["measured_scan"]["reading"], "peak_rss_gib": res["peak_rss_bytes"] / 2**30,
            "modelled_gib": res["preflight"]["needs_bytes"]["memory"] / 2**30}


def main(root: Path) -> dict:
    import os

    t0 = time.time()
    load0 = os.getloadavg()
    root.mkdir(parents=True, exist_ok=True)
    out: dict = {}
    sim = simulate(root, "sim")
    tcia = series(sim, root / "tcia")
    out["TCIA layout, the format's numbering"] = measure(root, tcia / "measured.toml", "tcia")
    rr = series(sim, root / "rowsrows", layout="rows-are-detector-rows")
    out["DICOM Rows = detector rows, the format's numbering"] = measure(root, rr / "measured.toml", "rowsrows")
    ch = series(sim, root / "chanrev", flip_channels=True)
    out["channels numbered the other way, not declared"] = measure(root, ch / "undeclared.toml", "ch-undeclared")
    out["channels numbered the other way, scan.flip_channels"] = measure(root, ch / "measured.toml", "ch-declared")
    out["channels numbered the other way, orientation auto"] = measure(root, ch / "undeclared.toml", "ch-auto",
                                                                        {"orientation": "auto"})
    rw = series(sim, root / "rowrev", flip_rows=True)
    out["rows numbered the other way, not declared"] = measure(root, rw / "undeclared.toml", "rw-undeclared")
    out["rows numbered the other way, scan.flip_rows"] = measure(root, rw / "measured.toml", "rw-declared")
    out["rows numbered the other way, orientation auto"] = measure(root, rw / "undeclared.toml", "rw-auto",
                                                                    {"orientation": "auto"})
    cw = series(simulate(root, "sim-cw", rotation="decreasing"), root / "cw")
    out["gantry angle decreasing"] = measure(root, cw / "measured.toml", "cw")
    down = series(simulate(root, "sim-down", table="decreasing"), root / "down")
    out["table towards -z"] = measure(root, down / "measured.toml", "down")
    ffs = series(simulate(root, "sim-ffs", rotation="decreasing", ffs="phi+z"), root / "ffs")
    out["FFSXYZ, gantry angle decreasing"] = measure(root, ffs / "measured.toml", "ffs")
    sym = series(simulate(root, "sim-sym", symmetric=True), root / "sym", flip_channels=True)
    out["symmetric phantom, channels the other way, not declared"] = measure(root, sym / "undeclared.toml", "sym")
    import platform

    return {"date": time.strftime("%Y-%m-%d"), "cpu": platform.processor() or "see lscpu",
            "load_start": load0, "load_end": os.getloadavg(), "seconds": time.time() - t0,
            "phantom": {"rod_xy_mm": rp.ROD_XY, "rod_radius_mm": rp.ROD_RADIUS_MM, "rod_hu": rp.ROD_HU,
                        "water_radius_mm": rp.WATER_RADIUS_MM, "sphere_xyz_mm": rp.SPHERE_XYZ},
            "conventions": out}


if __name__ == "__main__":
    res = main(Path(sys.argv[1]))
    (HERE / "measured-conventions.json").write_text(json.dumps(res, indent=1, default=float) + "\n")
    for k, v in res["conventions"].items():
        print(k, json.dumps(v, default=float)[:300])
