"""Bench section ``measured``: DICOM-CT-PD import, views/s (goal >= 200 views/s on 2 cores).

Writes ``n`` projections of a scene's detector (paper-p002: 900 x 64, 115 KB per file as
uint16; ``--quick``: 300 views, else 2000) as a DICOM-CT-PD series with the exporter's own
dataset builder, then times on that folder, cold (a fresh process cache, the OS page cache
warm from the write):

- the header pass (:func:`clrecon.scan.dicom_ct_pd.series_index`: every file's header),
- the import into a fresh projection store (:func:`clrecon.simulation.measured.import_series`),
- the reference: reading the same files' bytes (``Path.read_bytes``), the floor any reader pays.

views/s = n / (header + import seconds); the ratio to the byte-read floor says where the time goes.
"""

from __future__ import annotations

import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

from clrecon.bench.timing import load1
from clrecon.config.scene import load_scene
from clrecon.outputs.writers.dicom_ct_pd import projection_dataset, quantise
from clrecon.scan import dicom_ct_pd
from clrecon.scan.table import projection_table
from clrecon.simulation.measured import import_series

GOAL_VIEWS_PER_S = 200.0


def write_series(scene, n: int, folder: Path) -> None:
    """``n`` smooth synthetic projections of ``scene``'s detector as DICOM-CT-PD files in ``folder``."""
    import pydicom

    folder.mkdir(parents=True, exist_ok=True)
    table = projection_table(scene.replace(scan={"n_projections": n}), scene.scan.pitches[0])
    sc = scene.scanner
    u = np.linspace(-1, 1, sc.n_cols)
    base = (3.0 * np.clip(1 - u * u, 0, None) ** 0.5)[None, :] * np.ones((sc.n_rows, 1))
    photons = np.full(sc.n_cols, 2e5, np.float32)
    uids = ("1.2.826.0.1.3680043.8.498.1", "1.2.826.0.1.3680043.8.498.2", "1.2.826.0.1.3680043.8.498.3")
    for k in range(n):
        p = base * (1.0 + 0.1 * np.sin(0.01 * k))
        stored, slope, intercept = quantise(p)
        ds = projection_dataset(scene, table, k, stored, slope, intercept, photons, uids,
                                f"1.2.826.0.1.3680043.8.498.4.{k + 1}", "bench series")
        pydicom.dcmwrite(folder / f"PROJ{k + 1:06d}.dcm", ds, enforce_file_format=True)


def bench_measured_section(quick: bool = False, repeats: int = 1, scene_name: str = "paper-p002") -> dict:
    n = 300 if quick else 2000
    src = load_scene(scene_name)
    tmp = Path(tempfile.mkdtemp(prefix="clrecon-bench-measured-"))
    try:
        series = tmp / "projections"
        t0 = time.perf_counter()
        write_series(src, n, series)
        write_s = time.perf_counter() - t0
        (tmp / "m.toml").write_text('[scan]\nsource = "dicom-ct-pd"\nprojections = "projections"\n'
                                    '[noise]\nenabled = false\n')
        load_before = load1()
        t0 = time.perf_counter()
        for p in sorted(series.iterdir()):
            p.read_bytes()
        bytes_s = time.perf_counter() - t0
        t0 = time.perf_counter()
        dicom_ct_pd.series_index(series)
        header_s = time.perf_counter() - t0
        scene = load_scene(tmp / "m.toml")  # the index is memoised: this maps it onto the scene
        t0 = time.perf_counter()
        store = import_series(scene, scene.scan.pitches[0], cache_dir=tmp / "cache", progress=False)
        import_s = time.perf_counter() - t0
        store.close()
        total = header_s + import_s
        return {"scene": scene_name, "views": n, "detector": [src.scanner.n_rows, src.scanner.n_cols],
                "write_s": write_s, "read_bytes_s": bytes_s, "header_s": header_s, "import_s": import_s,
                "views_per_s": n / total, "header_views_per_s": n / header_s, "import_views_per_s": n / import_s,
                "read_bytes_views_per_s": n / bytes_s, "ratio_to_byte_floor": total / bytes_s,
                "goal_views_per_s": GOAL_VIEWS_PER_S, "meets_goal": n / total >= GOAL_VIEWS_PER_S,
                "load_average_1min_before": load_before, "load_average_1min_after": load1()}
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def run(quick: bool = False, repeats: int = 3, log=print) -> dict:
    """The bench's ``measured``: :func:`bench_measured_section` on ``paper-p002``'s detector."""
    return bench_measured_section(quick, repeats)


def report_lines(r: dict | None) -> list[str]:
    if not r:
        return []
    return ["", f"7. DICOM-CT-PD import: {r['views']} views of {r['scene']} ({r['detector'][0]} x {r['detector'][1]}), "
            f"load {r['load_average_1min_before']}..{r['load_average_1min_after']}",
            f"   {r['views_per_s']:.0f} views/s (goal {r['goal_views_per_s']:.0f}: "
            f"{'met' if r['meets_goal'] else 'NOT met'}); header pass {r['header_views_per_s']:.0f} views/s, "
            f"pixel import {r['import_views_per_s']:.0f} views/s; byte-read floor {r['read_bytes_views_per_s']:.0f} "
            f"views/s ({r['ratio_to_byte_floor']:.1f}x slower than reading the bytes)"]
