"""Can the truth-free cross-validated error be trusted? And what does choosing by it gain?

``python -m benchmarks.truth_free_trust --out DIR`` (about an hour). On simulated scenes, where
truth exists, every configuration (scene x pitch x noise variant x fixed kernel of
:data:`clrecon.evaluation.truth_free.DEFAULT_KERNELS`) gets its cross-validated row error
(``recon.truth_free``) and its true MAE against the ground truth; the study reports Spearman's rank
correlation between them (scipy.stats.spearmanr), pooled and within each (scene, pitch, variant)
case, per scheme (loto, nndm), region (heart channels <-> small FOV, whole row <-> large FOV) and
with / without the noise floor subtracted. It also reports, per case, the MAE of the kernel the CV
chooses (what ``cv_tuned`` reconstructs, bit for bit), of the better of barycentric and local
linear, and of the true-MAE oracle among the kernels (issue 19's goal: >= 15 % below the better of
the two), and the candidate-window option (``recon.candidate_window_mm``) at 0 (SSRB-exact) and 28
mm.

Small enough for a loaded 2-core machine: a few central slices; the paper slab uses a few
targets (the configuration is written with the numbers).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import time
from pathlib import Path

from clrecon.config.scene import load_scene
from clrecon.core import atomic, jsonio
from clrecon.evaluation.truth_free import DEFAULT_KERNELS, Kernel
from clrecon.pipeline.run import run

#: (scene, slices [i0, i1), cardiac targets or None = the scene's, resp targets or None)
CASES = {
    "demo": ("demo", (6, 10), None, None),
    "demo-hrv": ("demo-hrv", (6, 10), None, None),
    "paper-p010": ("paper-p010", (54, 56), (0.2, 0.6), (0.25, 0.55, 0.85)),
    "tiny": ("tiny", (0, 2), None, None),  # the tests' seconds-scale case
}
#: The study's cases (``tiny`` is for the tests).
STUDY = ("demo", "demo-hrv", "paper-p010")
#: Candidate windows of the window study (mm; 0 = the SSRB-exact window).
WINDOWS = (0.0, 28.0)


def _recon_overrides(k: Kernel) -> dict:
    d = {}
    if k.kappa is not None:
        d["kappa"] = k.kappa
    if k.sigma is not None:
        d["sigma"] = k.sigma
    if k.local_linear_points is not None:
        d["local_linear_points"] = k.local_linear_points
    if k.local_linear_count is not None:
        d["local_linear_count"] = k.local_linear_count
    return d


def _mae(res, pk, v, m):
    e = res["metrics"][pk][v][m]
    return {"large": e["large"]["mae_hu"], "small": e["small"]["mae_hu"]}


def run_case(name: str, out: Path, cache: Path, log=print) -> dict:
    """Every kernel's CV error and true MAE for one case (all the scene's pitches and variants)."""
    scene_name, sl, card, resp = CASES[name]
    base = load_scene(scene_name)
    kw = dict(slice_range=sl, cardiac=card, resp=resp, cache_dir=cache, progress=False, report=False,
              log=lambda *a, **k: None)
    t0 = time.perf_counter()
    plain = tuple(k for k in DEFAULT_KERNELS if not _recon_overrides(k))
    shutil.rmtree(out / f"{name}-cv", ignore_errors=True)  # a resumed run would not cross-validate again
    res0 = run(base.replace(recon={"truth_free": True}), out / f"{name}-cv", methods=[k.method for k in plain], **kw)
    seconds = {"cv_run": time.perf_counter() - t0, "truth_free_stage": res0["stages"]["truth_free"]["seconds"]}
    mae = {}
    for pk in res0["metrics"]:
        for v in res0["metrics"][pk]:
            for k in plain:
                mae[(pk, v, k.label)] = _mae(res0, pk, v, k.method)
    for k in DEFAULT_KERNELS:
        ov = _recon_overrides(k)
        if not ov:
            continue
        t1 = time.perf_counter()
        r = run(base.replace(recon=ov), out / f"{name}-{k.label}", methods=[k.method], **kw)
        seconds[k.label] = time.perf_counter() - t1
        for pk in r["metrics"]:
            for v in r["metrics"][pk]:
                mae[(pk, v, k.label)] = _mae(r, pk, v, k.method)
    windows = {}
    for wmm in WINDOWS[1:]:
        t1 = time.perf_counter()
        r = run(base.replace(recon={"candidate_window_mm": wmm}), out / f"{name}-w{wmm:g}",
                methods=["barycentric", "local_linear"], **kw)
        seconds[f"window {wmm:g}"] = time.perf_counter() - t1
        for pk in r["metrics"]:
            for v in r["metrics"][pk]:
                for m in ("barycentric", "local_linear"):
                    windows.setdefault(pk, {}).setdefault(v, {}).setdefault(m, {})[f"{wmm:g}"] = _mae(r, pk, v, m)
    for pk in windows:
        for v in windows[pk]:
            for m in windows[pk][v]:
                windows[pk][v][m]["0"] = mae[(pk, v, m)]
    rows = []
    tf = res0["truth_free"]
    for (pk, v, lab), e in mae.items():
        cv = tf[pk]["errors"][v]
        rows.append({"case": name, "pitch": pk, "variant": v, "kernel": lab, "mae_large": e["large"],
                     "mae_small": e["small"],
                     **{f"cv_{s}_{r}{suf}": cv[s][lab][r][key] for s in cv for r in ("row", "heart")
                        for suf, key in (("", "rms_hu_mm"), ("_raw", "rms_raw_hu_mm"))},
                     **{f"cv_{s}_img_{f}": cv[s][lab]["image"][f]["rms_hu"] for s in cv if "image" in cv[s][lab]
                        for f in ("small", "large")}})
    return {"case": name, "scene": scene_name, "slices": list(sl), "targets": {"cardiac": card, "resp": resp},
            "rows": rows, "windows": windows, "seconds": seconds,
            "truth_free_config": {pk: tf[pk]["config"] for pk in tf},
            "choices": {pk: tf[pk]["choice"] for pk in tf}, "folds": {pk: tf[pk]["folds"] for pk in tf},
            "commit": _commit(), "load_average": [round(x, 2) for x in os.getloadavg()],
            "date_utc": time.strftime("%Y-%m-%d %H:%M", time.gmtime())}


def _commit() -> str:
    import subprocess
    try:
        return subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                              cwd=Path(__file__).resolve().parent, check=False).stdout.strip()
    except OSError:
        return ""


def analyse(cases: list[dict]) -> dict:
    """Spearman rank correlations and the selection gains over the cases' rows."""
    from scipy.stats import spearmanr

    rows = [r for c in cases for r in c["rows"]]
    out = {"n_configurations": len(rows), "spearman": {}, "spearman_within_case": {}, "selection": []}
    schemes = sorted({k.split("_", 2)[1] if not k.startswith("cv_nndm_c") else "nndm_c"
                      for k in rows[0] if k.startswith("cv_")}) if rows else []
    measures = {"small": ["heart", "heart_raw", "img_small"], "large": ["row", "row_raw", "img_large"]}
    for fov, regions in measures.items():
        for s in schemes:
            for region in regions:
                key = f"cv_{s}_{region}"
                if key not in rows[0]:
                    continue
                x = [r[key] for r in rows]
                y = [r[f"mae_{fov}"] for r in rows]
                rho = spearmanr(x, y).statistic if len(rows) > 2 else float("nan")
                out["spearman"][f"{fov}:{s}:{region}"] = float(rho)
                within = {}
                for c in {(r["case"], r["pitch"], r["variant"]) for r in rows}:
                    sub = [r for r in rows if (r["case"], r["pitch"], r["variant"]) == c]
                    if len(sub) > 2:
                        within["/".join(c)] = float(spearmanr([r[key] for r in sub],
                                                              [r[f"mae_{fov}"] for r in sub]).statistic)
                out["spearman_within_case"][f"{fov}:{s}:{region}"] = within
    for c in sorted({(r["case"], r["pitch"], r["variant"]) for r in rows}):
        sub = {r["kernel"]: r for r in rows if (r["case"], r["pitch"], r["variant"]) == c}
        ent = {"case": c[0], "pitch": c[1], "variant": c[2]}
        for fov, regions in measures.items():
            best2 = min(sub["barycentric"][f"mae_{fov}"], sub["local_linear"][f"mae_{fov}"])
            for s in schemes:
                for region in (regions[0], regions[2]):
                    key = f"cv_{s}_{region}"
                    if key not in sub["barycentric"]:
                        continue
                    pick = min(sub, key=lambda k, key=key: sub[k][key])
                    ent[f"{fov}:{s}:{region}:choice"] = pick
                    ent[f"{fov}:{s}:{region}:mae"] = sub[pick][f"mae_{fov}"]
                    ent[f"{fov}:{s}:{region}:gain_pct"] = 100.0 * (1.0 - sub[pick][f"mae_{fov}"] / best2)
            orc = min(sub, key=lambda k: sub[k][f"mae_{fov}"])
            ent[f"{fov}:best_of_bary_ll"] = best2
            ent[f"{fov}:oracle"] = orc
            ent[f"{fov}:oracle_gain_pct"] = 100.0 * (1.0 - sub[orc][f"mae_{fov}"] / best2)
        out["selection"].append(ent)
    return out


def run_study(out_dir, cases=STUDY, cache=None, log=print) -> dict:
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    cache = Path(cache) if cache else out / "cache"
    done = []
    for name in cases:
        f = out / f"case-{name}.json"
        if f.exists():
            done.append(jsonio.loads(f.read_text()))
            continue
        log(f"truth_free_trust: {name} ...", file=sys.stderr)
        c = run_case(name, out / "runs", cache, log)
        atomic.write_json(f, c, indent=1)
        done.append(c)
    res = {"cases": [c["case"] for c in done], "analysis": analyse(done)}
    atomic.write_json(out / "trust.json", res, indent=1)
    return res


def bench_section(quick: bool = False, log=print) -> dict:
    """The bench's ``truth_free_trust`` section (``--quick``: demo only)."""
    import tempfile
    out = Path(tempfile.mkdtemp(prefix="clrecon-trust-"))
    res = run_study(out, ("demo",) if quick else STUDY, log=log)
    res["out_dir"] = str(out)
    return res


def main(argv=None) -> int:  # pragma: no cover - a study, run by hand
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", required=True)
    p.add_argument("--cases", default=",".join(STUDY))
    p.add_argument("--cache")
    a = p.parse_args(argv)
    res = run_study(a.out, tuple(a.cases.split(",")), a.cache, log=print)
    print(json.dumps(res["analysis"], indent=1))
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
