"""The reproduction tables: runs of the paper's scenes side by side with the paper's Table 2.

``python -m clrecon.outputs.reproduction RUN_DIR [RUN_DIR ...]`` prints Markdown for
``docs/results/paper-p010.md`` and ``docs/results/paper-p002.md`` from the runs' ``results.json``
(typically ``paper-p002`` and ``paper-p010``, one pitch each): Table 2 noise-free beside the paper's values, the noisy
table, the claims measured over both pitches together, the respiratory-only comparison, the
motion metrics, and per run the stage times, the peak memory and the disk it used. Nothing
in it is typed by hand: rerun it on new runs.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from clrecon.core import jsonio, machine_speed
from clrecon.core.resources import folder_bytes
from clrecon.evaluation import claims as claims_mod
from clrecon.outputs import report

#: The paper's Table 2 (noise-free MAE, HU) as given in its text and the issue that asked for
#: this report: method -> pitch key -> (large FOV, small FOV).
PAPER_TABLE2 = {
    "barycentric": {"p0.020": (28.2, 24.0), "p0.100": (37.9, 34.7)},
    "local_linear": {"p0.020": (21.8, 22.9), "p0.100": (33.5, 38.1)},
}
GiB = 1024 ** 3


def load(run_dirs) -> list[tuple[Path, dict]]:
    out = []
    for d in run_dirs:
        p = Path(d) / "results.json"
        try:
            out.append((Path(d), jsonio.loads(p.read_text())))
        except (OSError, ValueError) as e:
            raise SystemExit(f"{p}: not a finished run ({e})") from None
    return out


def merged(runs) -> dict:
    """One results-like dict over all runs' pitches (metrics, respiratory-only, motion, claims)."""
    m: dict = {"metrics": {}, "respiratory_only": {}, "motion": {}, "stages": {}}
    methods: list = []
    for _, r in runs:
        for key in ("metrics", "respiratory_only", "motion"):
            m[key].update(r.get(key) or {})
        methods += [x for x in r["request"]["methods"] if x not in methods]
        m["stages"] = r["stages"]
    first = runs[0][1]
    m["request"] = dict(first["request"], methods=methods)
    m["scene"] = first["scene"]
    m["claims"] = claims_mod.evaluate_claims(m)
    return m


def table2_vs_paper(res: dict) -> list[str]:
    met = res["metrics"]
    pks = sorted(met, key=lambda k: float(k[1:]))
    methods = [x for x in report.METHOD_ORDER if x in res["request"]["methods"]]
    head = "| method | " + " | ".join(f"pitch {pk[1:]} large FOV | pitch {pk[1:]} small FOV" for pk in pks) + " |"
    lines = [head, "|---|" + "---|---|" * len(pks)]
    for m in methods:
        cells = []
        for pk in pks:
            r = met[pk].get("noise-free", {}).get(m)
            paper = PAPER_TABLE2.get(m, {}).get(pk)
            for k, fov in enumerate(("large", "small")):
                ours = f"{r[fov]['mae_hu']:.1f} ± {r[fov]['std_hu']:.1f}" if r else "—"
                cells.append(f"{ours} (paper {paper[k]:.1f})" if paper else ours)
        lines.append(f"| {m} | " + " | ".join(cells) + " |")
    return lines


def stages_table(runs) -> list[str]:
    names = []
    for _, r in runs:
        names += [n for n in r["stages"] if n not in names]
    lines = ["| stage | " + " | ".join(r["scene"]["name"] for _, r in runs) + " |",
             "|---|" + "---|" * len(runs)]
    for n in names:
        cells = []
        for _, r in runs:
            st = r["stages"].get(n)
            cell = "—" if st is None else (f"{st['seconds']:.0f} s" if st["ran"] else "skipped")
            if st is not None and "beside_seconds" in st:  # a thread beside the reconstruction: its own time
                cell += f" (+{st['beside_seconds']:.0f} s beside)"
            cells.append(cell)
        lines.append(f"| {n} | " + " | ".join(cells) + " |")
    lines.append("| **total** | " + " | ".join(f"**{r['total_seconds'] / 60:.1f} min**" if "total_seconds" in r
                                             else "?" for _, r in runs) + " |")
    return lines


def _size(p: Path) -> int:
    if p.is_file():
        return p.stat().st_size
    return folder_bytes(p)


def resources_table(runs) -> list[str]:
    lines = ["| run | peak RSS | volumes (volumes.h5 + volumes.d/) | projection store | noise cells | read cells "
             "| load (1 min) start → end | machine probe start → end, other jobs |",
             "|---|---|---|---|---|---|---|---|"]
    for d, r in runs:
        stores = [Path(s["store"]) for s in r["stages"]["simulate"].get("per_pitch", {}).values() if s.get("store")]
        rss = r.get("peak_rss_bytes")
        load = r.get("load_average") or {}
        if not rss:
            lines.append(f"| {r['scene']['name']} | not recorded (run before this was) | | | | | | |")
            continue
        st = r["stages"]
        vols = _size(d / "volumes.h5") + _size(d / "volumes.d")
        lines.append(f"| {r['scene']['name']} | {rss / GiB:.2f} GiB | {vols / GiB:.2f} GiB | "
                     f"{sum(_size(s) for s in stores) / GiB:.2f} GiB | {st['noise'].get('cells', 0) / 1e9:.2f} G | "
                     f"{st['read'].get('cells', 0) / 1e9:.2f} G | {load.get('start', '?')} → {load.get('end', '?')} | "
                     f"{machine_speed.describe(r['machine_speed']) if r.get('machine_speed') else 'not recorded'} |")
    return lines


def markdown(runs) -> str:
    res = merged(runs)
    out = ["### Table 2, noise-free: MAE ± STD (HU) over all voxels of all 50 targets; the paper's MAE in brackets",
           ""] + table2_vs_paper(res) + [""]
    if any("noisy" in byv for byv in res["metrics"].values()):
        out += ["### The same with noise (the paper gives no noisy table)", ""]
        out += report.table2_markdown(res, "noisy") + [""]
    out += report.claims_markdown(res)
    for pk, byv in res["respiratory_only"].items():
        for v, rows in byv.items():
            if not rows:
                continue
            methods = [m for m in report.METHOD_ORDER if m in rows[0]["small_fov_mae_hu"]]
            out += [f"### Respiratory-only 5DCT vs r4DCT, pitch {pk[1:]}, {v}", "",
                    "| cardiac phase | " + " | ".join(f"{m} MAE" for m in methods) + " | GT LV spread | "
                    + " | ".join(f"{m} LV spread" for m in methods) + " |",
                    "|---|" + "---|" * (2 * len(methods) + 1)]
            out += [f"| {r['cardiac_phase']:.2f} | " + " | ".join(f"{r['small_fov_mae_hu'][m]:.1f}" for m in methods)
                    + f" | {r['lv_volume_spread_ml']['groundtruth']:.1f} | "
                    + " | ".join(f"{r['lv_volume_spread_ml'][m]:.1f}" for m in methods) + " |" for r in rows]
            out.append("")
    out += report.motion_markdown(res)
    out += ["### Stage times", ""] + stages_table(runs) + [""]
    out += ["### Memory and disk", ""] + resources_table(runs) + [""]
    return "\n".join(out) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m clrecon.outputs.reproduction", description=__doc__.splitlines()[0])
    ap.add_argument("run_dirs", nargs="+", help="finished run directories (results.json)")
    args = ap.parse_args(argv)
    sys.stdout.write(markdown(load(args.run_dirs)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
