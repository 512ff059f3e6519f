"""``report.md`` of a run directory: the Table-2-style comparison and the findings, as numbers.

Figures (issue: viewer/figures/export) are added by :mod:`clrecon.outputs.figures` when available.
"""

from __future__ import annotations

from pathlib import Path

from clrecon.outputs import figures
from clrecon.reconstruction.interpolation import by_rank

#: Table order, best first: the interpolation methods by their registered ``rank``.
METHOD_ORDER = by_rank()


def _fmt(d) -> str:
    return f"{d['mae_hu']:.1f} ± {d['std_hu']:.1f}"


def table2_markdown(results: dict, variant: str) -> list[str]:
    met = results["metrics"]
    methods = [m for m in METHOD_ORDER if m in results["request"]["methods"]]
    head = "| pitch | " + " | ".join(f"{m}, large FOV | {m}, small FOV" for m in methods) + " |"
    sep = "|---|" + "---|---|" * len(methods)
    lines = [head, sep]
    for pk in met:
        if variant not in met[pk]:
            continue
        cells = []
        for m in methods:
            r = met[pk][variant][m]
            cells += [_fmt(r["large"]), _fmt(r["small"])]
        lines.append(f"| {pk[1:]} | " + " | ".join(cells) + " |")
    return lines


def summary_lines(results: dict) -> list[str]:
    """A few lines for the terminal: pooled large/small-FOV MAE per pitch, variant and method."""
    out = []
    for pk, byv in results["metrics"].items():
        for v, bym in byv.items():
            parts = [f"{m} {bym[m]['large']['mae_hu']:.1f}/{bym[m]['small']['mae_hu']:.1f}"
                     for m in METHOD_ORDER if m in bym]
            out.append(f"  MAE HU large/small FOV  pitch {pk[1:]} {v:<10}: " + ", ".join(parts))
    return out


def write_report(out_dir: Path, results: dict) -> Path:
    out_dir = Path(out_dir)
    s = results["scene"]
    lines = [f"# clrecon run: scene `{s['name']}`", "", s.get("description", ""), "",
             f"Device: {results['device']}. clrecon {results['versions']['clrecon']}.", ""]
    for v in results["request"]["variants"]:
        lines += [f"## Mean absolute error vs ground truth, {v} (HU, mean ± std over all voxels of all targets)", ""]
        lines += table2_markdown(results, v) + [""]
    ro = results.get("respiratory_only") or {}
    for pk, byv in ro.items():
        for v, rows in byv.items():
            lines += [f"## Respiratory-only 5DCT vs r4DCT, pitch {pk[1:]}, {v}", "",
                      "Per cardiac phase: small-FOV MAE (HU) over the respiratory targets, and the spread "
                      "(max − min, mL) of the LV blood-pool volume across respiratory targets (truth: "
                      "the ground-truth spread; breathing only moves the heart).", ""]
            methods = [m for m in METHOD_ORDER if rows and m in rows[0]["small_fov_mae_hu"]]
            lines.append("| cardiac phase | " + " | ".join(f"{m} MAE" for m in methods) + " | GT LV spread | "
                         + " | ".join(f"{m} LV spread" for m in methods) + " |")
            lines.append("|---|" + "---|" * (2 * len(methods) + 1))
            for r in rows:
                lines.append(f"| {r['cardiac_phase']:.2f} | " + " | ".join(f"{r['small_fov_mae_hu'][m]:.1f}" for m in methods)
                             + f" | {r['lv_volume_spread_ml']['groundtruth']:.1f} | "
                             + " | ".join(f"{r['lv_volume_spread_ml'][m]:.1f}" for m in methods) + " |")
            lines.append("")
    lines += ["## Stages", "", "| stage | ran | seconds |", "|---|---|---|"]
    for name, st in results["stages"].items():
        why = f" ({st['skipped_because']})" if st.get("skipped_because") else ""
        lines.append(f"| {name} | {'yes' if st['ran'] else 'no' + why} | {st['seconds']:.2f} |")
    lines.append("")
    lines += figures.write_figures(out_dir, results)
    path = out_dir / "report.md"
    tmp = path.with_name("report.md.partial")
    tmp.write_text("\n".join(lines) + "\n")
    tmp.replace(path)
    figures.write_html(out_dir, lines, title=f"clrecon run: {s['name']}")
    return path
