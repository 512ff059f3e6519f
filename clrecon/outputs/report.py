"""``report.md`` of a run directory: the Table-2-style comparison and the findings, as numbers.

Figures (issue: viewer/figures/export) are added by :mod:`clrecon.outputs.figures` when available.
"""

from __future__ import annotations

from pathlib import Path

from clrecon.core import atomic, machine_speed
from clrecon.core.resources import folder_bytes, peak_rss_bytes
from clrecon.evaluation import claims as claims_mod
from clrecon.evaluation import consistency
from clrecon.outputs import figures, measured_record, report_html
from clrecon.reconstruction.diagnostics import pooled as _pooled_diagnostics
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


def phantom_mae_markdown(results: dict, variant: str) -> list[str]:
    """The pooled MAE against the phantom itself (``mae_phantom_hu``), per pitch and method: a
    table, or nothing where the run's metrics have none."""
    met = results["metrics"]
    methods = [m for m in METHOD_ORDER if m in results["request"]["methods"]]
    rows = []
    for pk in met:
        r = met[pk].get(variant, {})
        if not methods or any("mae_phantom_hu" not in r.get(m, {}).get("large", {}) for m in methods):
            continue
        rows.append(f"| {pk[1:]} | " + " | ".join(f"{r[m]['large']['mae_phantom_hu']:.1f} | "
                                                 f"{r[m]['small']['mae_phantom_hu']:.1f}" for m in methods) + " |")
    if not rows:
        return []
    return ([f"MAE against the phantom itself, voxelised at each target (no reconstruction's resolution in "
             f"it; {variant}, HU):", "",
             "| pitch | " + " | ".join(f"{m}, large FOV | {m}, small FOV" for m in methods) + " |",
             "|---|" + "---|---|" * len(methods)] + rows + [""])


def summary_lines(results: dict) -> list[str]:
    """A few lines for the terminal: pooled large/small-FOV MAE per pitch, variant and method."""
    out = []
    for pk, byv in results["metrics"].items():
        for v, bym in byv.items():
            parts = [f"{m} {bym[m]['large']['mae_hu']:.1f}/{bym[m]['small']['mae_hu']:.1f}"
                     for m in METHOD_ORDER if m in bym]
            out.append(f"  MAE HU large/small FOV  pitch {pk[1:]} {v:<10}: " + ", ".join(parts))
    return out


def _sampling_lines(sampling: dict) -> list[str]:
    """One line: distinct cardiac phases and candidates per (slice, view), median (min-max), per pitch."""
    if not sampling:
        return []

    def mm(d):
        return f"{d['median']:g} ({d['min']}–{d['max']})"

    return ["Phase-space sampling per (slice, view), median (min–max): " + "; ".join(
        f"pitch {pk[1:]}: {mm(d['distinct_cardiac_phases_per_view'])} distinct cardiac phases among "
        f"{mm(d['candidates_per_view'])} candidates" for pk, d in sampling.items()) + ".", ""]


def claims_markdown(results: dict) -> list[str]:
    """The "Claims" section: each of the paper's claims, whether it holds here, and the numbers."""
    cl = results.get("claims") or []
    if not cl:
        return []
    lines = ["## Claims of the paper, measured", "",
             "Each claim of the paper (abstract and results) that this run's metrics can check "
             "(`clrecon.evaluation.claims`); pooled MAE, lower is better.", "",
             "| claim | where | holds | numbers |", "|---|---|---|---|"]
    for c in cl:
        why = c.get("skipped", "") if c["holds"] is None else c["detail"]
        holds = "skipped" if c["holds"] is None else ("yes" if c["holds"] else "no")
        lines.append(f"| {c['claim']} | {claims_mod.context(c) or '-'} | {holds} | {why} |")
    return lines + [""]


def diagnostics_markdown(results: dict) -> list[str]:
    """Interpolation diagnostics pooled over targets: reach of the rows used, branch shares."""
    diag = results.get("diagnostics") or {}
    if not any(diag.values()):
        return []
    branches = []  # in the order the methods report them (barycentric: triangle, segment, nearest)
    for bym in diag.values():
        for d in bym.values():
            branches += [nm for nm in d.get("branch_share", {}) if nm not in branches]
    lines = ["## Interpolation diagnostics", "",
             "Largest circular |Δc| and |Δa| between a target and a row with non-zero weight (over all "
             "targets, slices and views), and the share of (slice, view) pairs per branch "
             "(methods that report one).", "",
             "| pitch | method | largest \\|Δc\\| | largest \\|Δa\\| | " + " | ".join(branches)
             + (" |" if branches else "|"),
             "|---|---|---|---|" + "---|" * len(branches)]
    for pk, bym in diag.items():
        for m in [m for m in METHOD_ORDER if m in bym] + [m for m in bym if m not in METHOD_ORDER]:
            p = _pooled_diagnostics(bym[m])
            cells = [f"{100 * p[nm]:.1f} %" if nm in p else "-" for nm in branches]
            lines.append(f"| {pk[1:]} | {m} | {p['max_abs_dc']:.3f} | {p['max_abs_da']:.3f} | "
                         + " | ".join(cells) + (" |" if cells else "|"))
    return lines + [""]


def _motion_cell(entry, metric: str) -> str:
    """One cell of the motion table: the mean over targets, '—' where not measured."""
    if entry is None:
        return "—"
    if metric == "lv_vs_analytic":
        d = (entry.get("lv_volume_error_ml") or {}).get("vs_analytic") or {}
        val, fmt = d.get("mean"), "{:+.1f}"
    else:
        d = entry.get(metric) or {}
        val, fmt = d.get("mean"), {"lv_volume_error_ml": "{:+.1f}", "noise_std_hu": "{:.1f}"}.get(metric, "{:.2f}")
    if val is None:
        return "—"
    out = fmt.format(val)
    if metric == "target_error_mm" and d.get("found", 0) < d.get("of", 0):
        out += f" ({d['found']}/{d['of']})"
    return out


def motion_markdown(results: dict) -> list[str]:
    """The "Motion metrics" section: one row per metric and method (ground truth first), pitch/variant columns."""
    mot = results.get("motion") or {}
    cols = [(pk, v) for pk in mot for v in mot[pk]]
    if not cols:
        return []
    present = {m for pk, v in cols for m in mot[pk][v]}
    rows = ["groundtruth"] + [m for m in METHOD_ORDER if m in present] \
        + sorted(present - set(METHOD_ORDER) - {"groundtruth"})
    covered = all(((mot[pk][v][m].get("lv_volume_error_ml") or {}).get("vs_analytic") or {}).get("slab_covers_lv")
                  for pk, v in cols for m in mot[pk][v])
    metrics_ = [("edge_width_mm", "edge width 10–90 % (mm)"), ("lv_volume_error_ml", "LV volume − ground truth (mL)")]
    if covered:
        metrics_.append(("lv_vs_analytic", "LV volume − analytic (mL)"))
    metrics_ += [("target_error_mm", "target localisation error (mm)"), ("noise_std_hu", "noise std (HU)")]
    d = results.get("motion_definitions") or {}
    nz = d.get("noise", {})
    lines = ["## Motion metrics", "",
             "Means over the targets (`clrecon.evaluation.motion`): the 10–90 % width of the LV blood → myocardium "
             "edge (median of radial profiles from the LV centre in the slice nearest it); the LV blood-pool "
             "volume (voxels > 220 HU in the true cavity + 6 mm) minus the ground truth's; the distance from the "
             "LV-wall lesion's threshold-weighted centroid to its true centre (found/targets where it was not "
             "found everywhere); the std of recon − ground truth in a uniform region"
             + (f" (cylinder r = {nz['radius_mm']:g} mm at (x, y) = ({nz['centre_mm'][0]:g}, "
                f"{nz['centre_mm'][1]:g}) mm, the descending aorta)" if nz else "")
             + ". The ground-truth row is the floor of the grid and FBP.", ""]
    if not covered:
        lines += ["The slab does not hold the whole LV cavity at every target: no comparison with the "
                  "phantom's analytic LV volume.", ""]
    lines.append("| metric | method | " + " | ".join(f"pitch {pk[1:]}, {v}" for pk, v in cols) + " |")
    lines.append("|---|---|" + "---|" * len(cols))
    for key, label in metrics_:
        for m in rows:
            cells = [_motion_cell(mot[pk][v].get(m), key) for pk, v in cols]
            if m == "groundtruth" and key in ("lv_volume_error_ml", "noise_std_hu"):
                continue  # zero by definition
            lines.append(f"| {label} | {m} | " + " | ".join(cells) + " |")
    return lines + [""]


def truth_free_markdown(results: dict) -> list[str]:
    """The "Truth-free cross-validation" section (``results["truth_free"]``, ``recon.truth_free``)."""
    tf = results.get("truth_free") or {}
    if not tf:
        return []
    lines = ["## Truth-free cross-validation (sinogram space)", "",
             "Each candidate turn of the sampled (slice, view) groups is held out and its rebinned row predicted "
             "at its own (cardiac phase, amplitude) from the other turns with each kernel's own weights; RMS of "
             "the prediction error in HU mm (line integral x 1000 / mu_water). loto: leave one turn out; nndm: "
             "neighbours nearer than the targets' typical nearest-candidate distance are held out too. Noisy "
             "variant: the held-out row's own noise variance (noise model) is subtracted. No ground truth is "
             "used (docs/truth-free.md). `cv_tuned` uses the kernel marked *.", ""]
    for pk, ent in tf.items():
        if "errors" not in ent:
            lines += [f"Pitch {pk[1:]}: not cross-validated ({ent.get('skipped_because', '')}).", ""]
            continue
        cfg = ent["config"]
        for v, byscheme in ent["errors"].items():
            pick = ent["choice"][v]["label"]
            lines += [f"Pitch {pk[1:]}, {v}: {len(cfg['slices_z_mm'])} slices, every {cfg['view_step']}th view, "
                      + ", ".join(f"{n} {s} folds" for s, n in ent["folds"].items())
                      + ". Row and heart: HU mm; image small / large: RMS (HU) of the FBP of each fold's error "
                      "sinogram in the small / large FOV.", "",
                      "| kernel | " + " | ".join(f"{s} row | {s} heart | {s} image small | {s} image large"
                                                for s in byscheme) + " |",
                      "|---|" + "---|---|---|---|" * len(byscheme)]
            for lab in cfg["kernels"]:
                cells = []
                for s in byscheme:
                    e = byscheme[s][lab]
                    im = e.get("image") or {}
                    cells.append(f"{e['row']['rms_hu_mm']:.1f} | {e['heart']['rms_hu_mm']:.1f} | "
                                 f"{im.get('small', {}).get('rms_hu', float('nan')):.1f} | "
                                 f"{im.get('large', {}).get('rms_hu', float('nan')):.1f}")
                lines.append(f"| {lab}{' *' if lab == pick else ''} | " + " | ".join(cells) + " |")
            lines.append("")
    return lines


def consistency_markdown(results: dict) -> list[str]:
    """The "Did mc help? Data consistency" section (``results["consistency"]``, runs with ``mc``)."""
    cons = results.get("consistency") or {}
    if not cons:
        return []
    lines = ["## Did mc help? Data consistency of the rows (truth-free)", "",
             "Every candidate row of the sampled (slice, view) groups against the in-plane projection of each "
             "method's image interpolated to the row's own (cardiac phase, amplitude): RMS residual in HU mm (line "
             "integral x 1000 / mu_water) over the channels through the reconstruction circle and through the "
             "heart box. Lower is more consistent with the data; no ground truth is used, so it also runs on "
             "measured scans. The rows made the volumes, so every residual is biased low, and it is mostly the "
             "data model every method shares; the comparison of mc with its first pass (barycentric: the same rows "
             "and weights) is the point. At each sampled slice a difference of mean squares that holds over the "
             f"slice's blocks of views (jackknife |z| > {consistency.Z_DECIDES:g}, and more than "
             f"{100 * consistency.MIN_EFFECT:g} %) counts the slice as lower or higher; "
             "a sign test over the slices decides, so each slice counts once (the ratio and z pooled over every "
             "block are given too). On demo it saw mc's gain at pitch 0.10, not at 0.02, and it does not order the "
             "paper methods as the error against truth does (docs/consistency.md \"Did it help? A truth-free "
             "check\").", ""]
    for pk, ent in cons.items():
        if "residual" not in ent:
            lines += [f"Pitch {pk[1:]}: not checked ({ent.get('skipped_because', '')}).", ""]
            continue
        cfg = ent["config"]
        lines += [f"Pitch {pk[1:]}: {ent['n_rows']} rows of {len(cfg['slices_z_mm'])} slices, every "
                  f"{cfg['view_step']}th view."
                  + ("" if not cfg.get("left_out") else " Left out: " + "; ".join(f"{m} ({why})" for m, why in
                                                                                   cfg["left_out"].items()) + "."),
                  ""]
        variants = list(ent["residual"])
        methods = [m for m in METHOD_ORDER if any(m in ent["residual"][v] for v in variants)]
        lines += ["| variant | " + " | ".join(f"{m} all | {m} heart" for m in methods) + " | verdict |",
                  "|---|" + "---|---|" * len(methods) + "---|"]
        for v in variants:
            r = ent["residual"][v]
            cells = [f"{r[m]['rms_hu_mm']:.1f} | {r[m]['heart_rms_hu_mm']:.1f}" if m in r else "-- | --"
                     for m in methods]
            ver = ent["verdict"][v]
            lines.append(f"| {v} | " + " | ".join(cells) + f" | {ver.get('text', ver.get('null_because', ''))} |")
        lines.append("")
        for v, ver in (ent.get("mcir_verdict") or {}).items():  # the iterations against the image they start from
            lines += [f"mcir against mc, {v}: {ver.get('text', ver.get('null_because', ''))}.", ""]
    return lines


def iterative_markdown(results: dict) -> list[str]:
    """The "mcir: the solver" section (``results["stages"]["mcir"]["slabs"]``, runs with ``mcir``): per
    pitch, variant and slab, the data residual before, after each epoch and at the end, and why it stopped."""
    slabs = ((results.get("stages") or {}).get("mcir") or {}).get("slabs") or {}
    if not slabs:
        return []
    start = ((results.get("stages") or {}).get("mcir") or {}).get("start", "zero")
    lines = ["## mcir: the OS-SART solver", "",
             f"Started from: {start if start == 'zero' else f'the {start} volume of the reference state'}. "
             "Relative data residual ||p - A x|| / ||p|| over the slab's cone-beam rows: of the start, after "
             "each epoch (running: summed as each motion-state bin was visited) and of the final volume; the "
             "solver stops after its epochs or when an epoch gains less than its tolerance, and returns its start "
             "if the final residual is higher (docs/iterative.md).", "",
             "| pitch | variant | slices | views | volume (z, y, x) | start | epochs (running) | final | stopped | "
             "seconds |", "|---|---|---|---|---|---|---|---|---|---|"]
    for pk, per in slabs.items():
        for v, ent in per.items():
            for sl, info in ent.items():
                h = info["sart"]
                run = ", ".join(f"{r:.4f}" for r in h["running"])
                secs = sum(info["seconds"].values())
                lines.append(f"| {pk[1:]} | {v} | {sl} | {info['views']} | {' x '.join(map(str, info['grid']))} | "
                             f"{h['initial']:.4f} | {run} | {h['final']:.4f} | {h['stop']} | {secs:.1f} |")
    return lines + [""]


def resources_markdown(results: dict, out_dir: Path) -> list[str]:
    """Measured peak memory and disk of the run beside the pre-flight's model (GiB), for planning the next one.

    Memory: this process's peak resident set so far (``ru_maxrss``); disk: the run folder's
    files now (volumes, report) against the modelled ``out_disk`` (the run folder's peak).
    """
    need = (results.get("preflight") or {}).get("needs_bytes") or {}
    if not need:
        return []
    rss = peak_rss_bytes()
    disk = folder_bytes(out_dir)
    gib = 1024 ** 3
    lines = ["## Memory and disk (measured against the pre-flight model)", "", "| | measured | modelled |",
             "|---|---|---|", f"| peak memory (resident, this process) | {rss / gib:.2f} GiB | "
             f"{need.get('memory', 0) / gib:.2f} GiB |",
             f"| run folder (volumes, report, figures) | {disk / gib:.2f} GiB | "
             f"{need.get('out_disk', 0) / gib:.2f} GiB (its modelled peak) |", ""]
    # (the model leaves out the interpreter and OpenCL's own ~0.5-1 GiB: only large runs are compared)
    if need.get("memory") and rss > 1.25 * need["memory"] and rss > 2 * gib:
        lines += [f"The peak memory is {rss / need['memory']:.1f}x the model: please report it with the scene "
                  "(the pre-flight uses the model to refuse runs that would not fit).", ""]
    return lines


def _driver_note(driver: dict | None) -> str:
    """How the OpenCL driver was chosen, and the drivers the probe passed over (docs/drivers.md)."""
    if not driver:
        return ""
    passed_over = [f"{p['platform']} {p['driver_version']} ({p['reason']})" for p in driver.get("probes", [])
                   if not p["ok"]]
    text = f", chosen as {driver['chosen_by']}"
    return text + (f"; passed over: {'; '.join(passed_over)}" if passed_over else "")


#: The files of a run's report that :func:`write_report` stages and :func:`commit_report` renames.
REPORT_FILES = ("report.md", "report.html")


def write_report(out_dir: Path, results: dict, pool=None, staged: bool = False) -> Path:
    """``report.md`` and ``report.html`` of a run folder; ``pool``: a process pool for the
    results-only figures (:func:`clrecon.outputs.figures.write_figures`). Returns the path of
    ``report.md``. ``staged``: both are left whole under their temporary names
    (:func:`clrecon.core.atomic.stage_bytes`) until :func:`commit_report` (a run commits them once
    its ``results.json`` is whole, so a report never appears beside a failed run's volumes)."""
    out_dir = Path(out_dir)
    s = results["scene"]
    lines = [f"# clrecon run: scene `{s['name']}`", "", s.get("description", ""), "",
             f"Device: {results['device']}{_driver_note(results.get('driver'))}. "
             f"clrecon {results['versions']['clrecon']}.", ""]
    lines += _sampling_lines(results.get("sampling") or {})
    if results.get("measured"):
        lines += ["## Measured scan", "",
                  "This is a measured scan (DICOM-CT-PD projections): no ground truth exists, so **error against "
                  "truth is unavailable**; the reconstructions, figures and exports are made as for a simulated "
                  "scan. Patient identifiers of the input and the paths of its files are not copied into this "
                  "report, the logs, results.json, the projection cache or the exports (`export --keep-identifiers` "
                  "copies the identifiers into exported DICOM).", ""]
        lines += measured_record.report_lines(results)
        for pk, rs in (results.get("recorded_signals") or {}).items():
            why = ", ".join(f"{k} {n}" for k, n in rs["excluded_by_reason"].items() if n)
            lines += [f"Pitch {pk[1:]}: {rs['views_used']} of {rs['views_total']} views used; "
                      f"{rs['views_excluded']} left out ({why}) for lost or invalid recorded-trace stretches.", ""]
    for v in ([] if results.get("measured") else results["request"]["variants"]):
        lines += [f"## Mean absolute error vs ground truth, {v} (HU, mean ± std over all voxels of all targets)", ""]
        lines += table2_markdown(results, v) + [""] + phantom_mae_markdown(results, v)
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
                lines.append(f"| {r['cardiac_phase']:.2f} | "
                             + " | ".join(f"{r['small_fov_mae_hu'][m]:.1f}" for m in methods)
                             + f" | {r['lv_volume_spread_ml']['groundtruth']:.1f} | "
                             + " | ".join(f"{r['lv_volume_spread_ml'][m]:.1f}" for m in methods) + " |")
            lines.append("")
    lines += motion_markdown(results)
    lines += truth_free_markdown(results)
    lines += consistency_markdown(results)
    lines += iterative_markdown(results)
    lines += claims_markdown(results)
    lines += diagnostics_markdown(results)
    lines += ["## Stages", "", "| stage | ran | seconds |", "|---|---|---|"]
    for name, st in results["stages"].items():
        why = f" ({st['skipped_because']})" if st.get("skipped_because") else ""
        ran = ("yes" + (f" ({st['does']})" if st.get("does") else "")) if st["ran"] else "no" + why
        if "beside_seconds" in st:  # computed in a thread beside the reconstruction; seconds = the wait
            ran += f", beside the reconstruction ({st['beside_seconds']:.2f} s there; the run waited the seconds)"
        lines.append(f"| {name} | {ran} | {st['seconds']:.2f} |")
    lines.append("")
    if results.get("machine_speed"):
        lines += [f"Machine during the run: {machine_speed.describe(results['machine_speed'])} "
                  "(the probe: a fixed single-threaded workload before and after the run; a longer probe "
                  "means a slower machine, so compare stage seconds across runs only beside it).", ""]
    lines += resources_markdown(results, out_dir)
    lines += figures.write_figures(out_dir, results, pool=pool)
    path = out_dir / "report.md"
    atomic.write_text(path, "\n".join(lines) + "\n", staged=staged)
    report_html.write_html(out_dir, lines, title=f"clrecon run: {s['name']}", staged=staged)
    return path


def commit_report(out_dir: Path) -> None:
    """Put the report :func:`write_report` staged under its names (``report.md`` last)."""
    for name in reversed(REPORT_FILES):
        atomic.commit(Path(out_dir) / name)


def discard_report(out_dir: Path) -> None:
    """Remove a report :func:`write_report` staged and did not commit (a run that failed after it)."""
    for name in REPORT_FILES:
        atomic.discard(Path(out_dir) / name)
