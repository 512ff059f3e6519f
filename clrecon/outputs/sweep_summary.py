"""A sweep's summary (:mod:`clrecon.pipeline.sweep`): one table row per point x pitch x variant x method, and figures.

Columns: the point's folder, every swept key, ``pitch``, ``variant``, ``method``, then the
pooled metrics of ``results.json``: ``mae_small_hu`` / ``mae_large_hu`` (MAE in the small /
large field of view, HU), and the motion metrics (means over the targets, empty where the
phantom offers none): ``edge_width_mm`` (10-90 % edge width), ``lv_volume_error_ml``
(mean |error| of the LV blood-pool volume), ``target_error_mm`` (lesion position error),
``noise_std_hu``; and ``run_seconds`` (the point's wall time).

Figures ``sweep_<key>.png``: for each swept key, MAE (small and large FOV) and the motion
metrics against the key's values, one line per method x variant x pitch, the mean over the
other swept keys' values.
"""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

from clrecon.core import atomic

METRICS = ("mae_small_hu", "mae_large_hu", "edge_width_mm", "lv_volume_error_ml", "target_error_mm", "noise_std_hu")


def _mean(d, *keys):
    for k in keys:
        if not isinstance(d, dict) or d.get(k) is None:
            return None
        d = d[k]
    return float(d) if isinstance(d, (int, float)) else None


def rows_of(name: str, point: dict, results: dict) -> list[dict]:
    """The table rows of one point's ``results.json``."""
    out = []
    for pk, byv in results.get("metrics", {}).items():
        for v, bym in byv.items():
            for m, met in bym.items():
                mot = results.get("motion", {}).get(pk, {}).get(v, {}).get(m, {})
                out.append({"point": name, **{k: _cell(x) for k, x in point.items()}, "pitch": float(pk[1:]),
                            "variant": v, "method": m,
                            "mae_small_hu": _mean(met, "small", "mae_hu"),
                            "mae_large_hu": _mean(met, "large", "mae_hu"),
                            "edge_width_mm": _mean(mot, "edge_width_mm", "mean"),
                            "lv_volume_error_ml": _mean(mot, "lv_volume_error_ml", "mean_abs"),
                            "target_error_mm": _mean(mot, "target_error_mm", "mean"),
                            "noise_std_hu": _mean(mot, "noise_std_hu", "mean"),
                            "run_seconds": results.get("total_seconds")})
    return out


def _cell(x):
    return "+".join(str(v) for v in x) if isinstance(x, list) else x


def write(root: Path, grid: dict, points: list[tuple[str, dict, dict]]) -> dict:
    """Write ``summary.csv``, ``summary.md`` and the figures into ``root``; returns their paths and the rows."""
    rows = [r for name, point, res in points for r in rows_of(name, point, res)]
    cols = ["point", *grid, "pitch", "variant", "method", *METRICS, "run_seconds"]
    csv_path, md_path = root / "summary.csv", root / "summary.md"
    with atomic.replacing(csv_path) as tmp, open(tmp, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=cols)
        w.writeheader()
        for r in rows:
            w.writerow({c: "" if r.get(c) is None else r.get(c) for c in cols})
    lines = [f"# Sweep over {', '.join(grid)}", "", f"{len(points)} points; MAE in HU (small / large FOV), "
             "motion metrics as defined in each point's results.json (means over the targets).", "",
             "| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    for r in rows:
        lines.append("| " + " | ".join(_md(r.get(c)) for c in cols) + " |")
    atomic.write_text(md_path, "\n".join(lines) + "\n")
    figures = [_figure(root, key, grid[key], rows) for key in grid]
    return {"table_csv": str(csv_path), "table_md": str(md_path), "figures": [str(p) for p in figures if p],
            "rows": rows}


def _md(x) -> str:
    if x is None:
        return ""
    return f"{x:.3g}" if isinstance(x, float) else str(x)


def _figure(root: Path, key: str, values: list, rows: list[dict]) -> Path | None:
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    shown = [m for m in METRICS if any(r.get(m) is not None for r in rows)]
    if not shown:
        return None
    labels = [_cell(v) for v in values]
    numeric = all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in values)
    xs = [float(v) for v in values] if numeric else list(range(len(values)))
    series = sorted({(r["method"], r["variant"], r["pitch"]) for r in rows})
    fig, axes = plt.subplots(1, len(shown), figsize=(3.6 * len(shown), 3.2), squeeze=False)
    for ax, metric in zip(axes[0], shown, strict=True):
        for method, variant, pitch in series:
            ys = []
            for lab in labels:
                vals = [r[metric] for r in rows if r.get(key) == lab and r["method"] == method
                        and r["variant"] == variant and r["pitch"] == pitch and r.get(metric) is not None]
                ys.append(float(np.mean(vals)) if vals else np.nan)
            label = method if len({s[1:] for s in series}) == 1 else f"{method} {variant} p{pitch:g}"
            ax.plot(xs, ys, marker="o", label=label)
        ax.set_xlabel(key)
        ax.set_title(metric)
        if not numeric:
            ax.set_xticks(xs, [str(v) for v in labels])
    axes[0][0].legend(fontsize=7)
    fig.tight_layout()
    path = root / f"sweep_{key.replace('.', '_')}.png"
    atomic.save_figure(fig, path, dpi=90)
    plt.close(fig)
    return path
