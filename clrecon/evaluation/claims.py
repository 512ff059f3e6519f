"""The paper's claims as measured results (after the metrics): ``results["claims"]``.

Each claim of Wang et al. (5DCT; abstract, results and discussion) that the run's metrics can
check becomes one entry per (pitch, variant, field of view, method) it applies to::

    {"claim": str,            # the statement, e.g. "local linear at or below barycentric"
     "holds": bool | None,    # None: skipped
     "numbers": {label: float},   # the MAEs (HU) or volumes (mL) compared
     "detail": str,           # the comparison in words, e.g. "20.3 <= 24.0 HU"
     "pitch": str | None, "variant": str | None, "fov": str | None, "method": str | None,
     "skipped": str}          # only when skipped: why (an input the run lacks)

The claims (pooled MAE of ``results["metrics"]``, lower is better):

- (a) interpolation below no interpolation: every 5DCT interpolation method (barycentric,
  local linear: the registry's ``five_d`` methods) below every phase-resolved or phase-blind
  method without interpolation (nearest, bin, helical: neither ``five_d`` nor on the
  respiratory grid), per pitch, variant and FOV (abstract: "eliminated the severe axial
  misalignment artifacts ... without phase-space interpolation");
- (b) the lowest pitch below the highest, per 5DCT method, variant and FOV (results: "For all
  reconstruction methods and FOVs, the MAE ... substantially lower at a pitch of 0.02");
  the paper's methods only, i.e. the ``five_d`` ones;
- (c) local linear at or below barycentric, per pitch, variant and FOV (abstract);
- (d) respiratory-only 5DCT below r4DCT in the heart: the small-FOV MAE of the
  respiratory-only comparison (``results["respiratory_only"]``), averaged over the cardiac
  phases, per pitch, variant and 5DCT method (abstract: "respiratory-only volumes with fewer
  residual cardiac-motion artifacts than conventional r4DCT ... including at ... pitch
  (0.1)");
- (e1) respiratory-only 5DCT's LV blood-pool volume varies less across amplitudes than
  r4DCT's (results, Figure 4: "the blood pool volume and myocardium shape were less
  varied"): per cardiac phase the spread (max - min, mL) over the amplitudes of the volume
  minus the ground truth's (the truth's measured volume itself varies a little with the voxel
  grid), averaged over the cardiac phases;
- (e2) local linear's advantage over barycentric is largest at the lowest pitch (abstract:
  "with the largest improvement at low pitch"): (bary - ll) at the lowest pitch above that at
  the highest, per variant and FOV;
- (e3) the lowest pitch with local linear is the best of the 5DCT (method, pitch)
  combinations (results: "the combination of pitch 0.02 and local linear interpolation
  providing the best quantitative performance"), per variant and FOV.

Beside the paper's claims, the goals a second-pass method (``mc``, docs/motion-model.md) was
built to (issue 34), per pitch, variant and FOV where it ran:

- (g1) at a clinical pitch (>= 0.1) its MAE at or below 0.75 x min(barycentric, local linear);
- (g2) at every pitch at or below min(barycentric, local linear);
- (g3) at every pitch below r4DCT.

A claim whose inputs the run lacks (one pitch only, a method not run, no respiratory-only
comparison) is one entry with ``holds = None`` and the reason. The paper's phase-dependence
remark (errors concentrated at rapid cardiac motion) is not checked: it needs the phantom's
motion speed per phase, which the metrics do not carry. The choices where the paper is vague
are in docs/choices.md "The paper's claims, measured".
"""

from __future__ import annotations

from clrecon.reconstruction import interpolation

FOVS = ("large", "small")


def _interp_methods() -> tuple[str, ...]:
    """The paper's 5DCT interpolation (and cv_tuned, which is one of them per scan); not a method
    made from their volumes by a later stage (``mc``): the claims are the paper's, about its methods."""
    second = set(interpolation.second_pass_methods())
    return tuple(m for m in interpolation.five_d_methods() if m not in second)


def _no_interp_methods() -> tuple[str, ...]:
    return tuple(n for n, m in interpolation.METHODS.items() if not m.five_d and m.target_grid != "resp")


def _resp_grid_methods() -> tuple[str, ...]:
    return interpolation.resp_grid_methods()


def _label(m: str) -> str:
    return interpolation.METHODS[m].label if m in interpolation.METHODS else m


def _pitch(pk: str) -> str:
    return f"{float(pk[1:]):g}"


def _entry(claim, holds, numbers, detail, pitch=None, variant=None, fov=None, method=None) -> dict:
    return {"claim": claim, "holds": None if holds is None else bool(holds), "numbers": numbers, "detail": detail,
            "pitch": pitch, "variant": variant, "fov": fov, "method": method}


def _skipped(claim, why) -> dict:
    e = _entry(claim, None, {}, "")
    e["skipped"] = why
    return e


def _mae(met, pk, v, m, fov) -> float:
    return float(met[pk][v][m][fov]["mae_hu"])


def _variants(met) -> list[str]:
    out = []
    for byv in met.values():
        out += [v for v in byv if v not in out]
    return out


def _sorted_pitches(met) -> list[str]:
    return sorted(met, key=lambda pk: float(pk[1:]))


def _fmt(x: float) -> str:
    return f"{x:.1f}"


def _pair(a: float, b: float) -> tuple[str, str]:
    """a and b with one decimal, or as many more (up to 4) as it takes to tell them apart."""
    for d in range(1, 5):
        sa, sb = f"{a:.{d}f}", f"{b:.{d}f}"
        if sa != sb:
            return sa, sb
    return f"{a:.1f}", f"{b:.1f}"


def _cmp(a: float, b: float, strict: bool = True, unit: str = "HU") -> str:
    """``"20.3 < 41.6 HU"``: the comparison as it came out."""
    sa, sb = _pair(a, b)
    op = ("<" if a < b else ">=") if strict else ("<=" if a <= b else ">")
    return f"{sa} {op} {sb} {unit}"


def _spread(values) -> float:
    return max(values) - min(values) if values else 0.0


def claim_interpolation(met) -> list[dict]:
    """(a) every interpolation method below every method without interpolation."""
    interp, none = _interp_methods(), _no_interp_methods()
    text = f"interpolation ({', '.join(interp)}) below no interpolation ({', '.join(none)})"
    out = []
    for pk in _sorted_pitches(met):
        for v, bym in met[pk].items():
            i_m = [m for m in interp if m in bym]
            n_m = [m for m in none if m in bym]
            if not (i_m and n_m):
                continue
            for fov in FOVS:
                a = {m: _mae(met, pk, v, m, fov) for m in i_m}
                b = {m: _mae(met, pk, v, m, fov) for m in n_m}
                holds = max(a.values()) < min(b.values())
                detail = (", ".join(f"{m} {_fmt(x)}" for m, x in a.items()) + " vs "
                          + ", ".join(f"{m} {_fmt(x)}" for m, x in b.items()) + " HU")
                out.append(_entry(text, holds, {**a, **b}, detail, pk, v, fov))
    return out or [_skipped(text, f"needs one of {', '.join(interp)} and one of {', '.join(none)} in the run")]


def claim_pitch(met) -> list[dict]:
    """(b) lowest pitch below highest pitch, per 5DCT method."""
    pks = _sorted_pitches(met)
    if len(pks) < 2:
        text = "lower pitch below higher pitch"
        return [_skipped(text, f"the run has one pitch ({', '.join(_pitch(p) for p in pks) or 'none'})")]
    lo, hi = pks[0], pks[-1]
    text = f"pitch {_pitch(lo)} below {_pitch(hi)}"
    out = []
    for v in _variants(met):
        if v not in met[lo] or v not in met[hi]:
            continue
        for m in _interp_methods():
            if m not in met[lo][v] or m not in met[hi][v]:
                continue
            for fov in FOVS:
                a, b = _mae(met, lo, v, m, fov), _mae(met, hi, v, m, fov)
                out.append(_entry(text, a < b, {f"pitch {_pitch(lo)}": a, f"pitch {_pitch(hi)}": b}, _cmp(a, b),
                                  None, v, fov, m))
    return out or [_skipped(text, f"no 5DCT method ({', '.join(_interp_methods())}) ran at both pitches")]


def claim_ll_vs_bary(met) -> list[dict]:
    """(c) local linear at or below barycentric."""
    text = "local linear at or below barycentric"
    out = []
    for pk in _sorted_pitches(met):
        for v, bym in met[pk].items():
            if "local_linear" not in bym or "barycentric" not in bym:
                continue
            for fov in FOVS:
                ll, ba = _mae(met, pk, v, "local_linear", fov), _mae(met, pk, v, "barycentric", fov)
                out.append(_entry(text, ll <= ba, {"local_linear": ll, "barycentric": ba},
                                  _cmp(ll, ba, strict=False), pk, v, fov))
    return out or [_skipped(text, "needs local_linear and barycentric in the run")]


def _resp_only_rows(ro):
    """(pk, variant, rows) of the respiratory-only comparison that has an r4DCT-like method."""
    for pk in sorted(ro or {}, key=lambda p: float(p[1:])):
        for v, rows in (ro[pk] or {}).items():
            if rows:
                yield pk, v, rows


def _error_spread(row: dict, m: str) -> float:
    """Spread (max - min, mL) over the amplitudes of method m's LV volume minus the truth's.

    The true LV volume does not change with breathing at a fixed cardiac phase, but its
    measured (voxel-counted) value does a little; the difference from the truth removes that,
    so what is left is artefact. For ``"groundtruth"``: the truth's own spread.
    """
    v = row["lv_volume_ml"]
    if m == "groundtruth":
        return _spread(list(v["groundtruth"]))
    return _spread([x - t for x, t in zip(v[m], v["groundtruth"], strict=True)])


def claim_resp_only(ro, skipped_because: str | None = None) -> list[dict]:
    """(d) respiratory-only 5DCT below r4DCT (small FOV) and (e1) less LV-volume variation.

    ``skipped_because``: the run's own reason when it skipped the respiratory-only study
    (``results["stages"]["metrics"]["respiratory_only_skipped_because"]``, e.g. a voxel phantom
    without an LV model); it replaces the generic reason.
    """
    t_mae = "respiratory-only 5DCT below r4DCT in the heart"
    t_lv = "respiratory-only 5DCT LV blood-pool volume error varies less across amplitudes than r4DCT's"
    out_mae, out_lv = [], []
    for pk, v, rows in _resp_only_rows(ro):
        present = rows[0]["small_fov_mae_hu"]
        refs = [m for m in _resp_grid_methods() if m in present]
        for r in refs:
            for m in (x for x in _interp_methods() if x in present):
                a = sum(row["small_fov_mae_hu"][m] for row in rows) / len(rows)
                b = sum(row["small_fov_mae_hu"][r] for row in rows) / len(rows)
                out_mae.append(_entry(t_mae, a < b, {m: a, r: b}, _cmp(a, b) + " (mean over cardiac phases)",
                                      pk, v, "small", m))
                sa, sb, gt = (sum(_error_spread(row, x) for row in rows) / len(rows) for x in (m, r, "groundtruth"))
                out_lv.append(_entry(t_lv, sa < sb, {m: sa, r: sb, "groundtruth_spread": gt},
                                     "spread of V - V_truth " + _cmp(sa, sb, unit="mL")
                                     + f" (truth's own spread {_fmt(gt)} mL; mean over cardiac phases)",
                                     pk, v, "small", m))
    why = skipped_because or (f"needs the respiratory-only comparison: {' or '.join(_resp_grid_methods())} "
                              "with a 5DCT method, on a scene with cardiac and respiratory motion")
    return (out_mae or [_skipped(t_mae, why)]) + (out_lv or [_skipped(t_lv, why)])


def claim_ll_gain_at_low_pitch(met) -> list[dict]:
    """(e2) local linear's gain over barycentric larger at the lowest pitch than at the highest."""
    pks = _sorted_pitches(met)
    text = "local linear's gain over barycentric largest at the lowest pitch"
    if len(pks) < 2:
        return [_skipped(text, f"the run has one pitch ({', '.join(_pitch(p) for p in pks) or 'none'})")]
    lo, hi = pks[0], pks[-1]
    out = []
    for v in _variants(met):
        if not all(v in met[p] and {"local_linear", "barycentric"} <= set(met[p][v]) for p in (lo, hi)):
            continue
        for fov in FOVS:
            g_lo = _mae(met, lo, v, "barycentric", fov) - _mae(met, lo, v, "local_linear", fov)
            g_hi = _mae(met, hi, v, "barycentric", fov) - _mae(met, hi, v, "local_linear", fov)
            s_lo, s_hi = (x if x.startswith("-") else "+" + x for x in _pair(g_lo, g_hi))
            out.append(_entry(text, g_lo > g_hi, {f"gain at pitch {_pitch(lo)}": g_lo,
                                                  f"gain at pitch {_pitch(hi)}": g_hi},
                              f"barycentric - local linear: {s_lo} HU at pitch {_pitch(lo)} "
                              f"{'>' if g_lo > g_hi else '<='} {s_hi} HU at pitch {_pitch(hi)}", None, v, fov))
    return out or [_skipped(text, "needs local_linear and barycentric at both pitches")]


def claim_best_combination(met) -> list[dict]:
    """(e3) lowest pitch + local linear is the best 5DCT (method, pitch) combination."""
    pks = _sorted_pitches(met)
    interp = _interp_methods()
    text = "lowest pitch with local linear is the best 5DCT combination"
    if len(pks) < 2:
        return [_skipped(text, f"the run has one pitch ({', '.join(_pitch(p) for p in pks) or 'none'})")]
    out = []
    for v in _variants(met):
        combos = [(pk, m) for pk in pks if v in met[pk] for m in interp if m in met[pk][v]]
        if (pks[0], "local_linear") not in combos or len({m for _, m in combos}) < 2 \
                or len({pk for pk, _ in combos}) < 2:
            continue
        for fov in FOVS:
            nums = {f"{m}, pitch {_pitch(pk)}": _mae(met, pk, v, m, fov) for pk, m in combos}
            best = _mae(met, pks[0], v, "local_linear", fov)
            holds = all(best < _mae(met, pk, v, m, fov) for pk, m in combos if (pk, m) != (pks[0], "local_linear"))
            winner = min(nums, key=nums.get)
            out.append(_entry(text, holds, nums, f"local_linear at pitch {_pitch(pks[0])} {_fmt(best)} HU; "
                              f"best: {winner} {_fmt(nums[winner])} HU", None, v, fov))
    return out or [_skipped(text, f"needs {', '.join(interp)} at two pitches")]


#: The goal of a second-pass method at a clinical pitch (>= CLINICAL_PITCH): this share of the
#: better paper method's MAE (issue 34).
GOAL_RATIO, CLINICAL_PITCH = 0.75, 0.1


def claim_second_pass(met) -> list[dict]:
    """(g1-g3) the goals of the second-pass methods (``mc``) against the paper's methods and r4DCT."""
    out = []
    for m in interpolation.second_pass_methods():
        t1 = f"{m} at or below {GOAL_RATIO:g} x min(barycentric, local linear) at pitch >= {CLINICAL_PITCH:g}"
        t2, t3 = f"{m} at or below min(barycentric, local linear)", f"{m} below r4DCT"
        for pk in _sorted_pitches(met):
            for v, bym in met[pk].items():
                if m not in bym:
                    continue
                paper = [p for p in ("barycentric", "local_linear") if p in bym]
                for fov in FOVS:
                    x = _mae(met, pk, v, m, fov)
                    if paper:
                        best = min(_mae(met, pk, v, p, fov) for p in paper)
                        nums = {m: x, "min(" + ", ".join(paper) + ")": best}
                        if float(pk[1:]) >= CLINICAL_PITCH - 1e-9:
                            detail = f"{_fmt(x)} HU = {x / best:.3f} x {_fmt(best)} HU (goal <= {GOAL_RATIO:g})"
                            out.append(_entry(t1, x <= GOAL_RATIO * best, {**nums, "ratio": x / best}, detail,
                                              pk, v, fov, m))
                        out.append(_entry(t2, x <= best, nums, _cmp(x, best, strict=False), pk, v, fov, m))
                    if "r4dct" in bym:
                        r = _mae(met, pk, v, "r4dct", fov)
                        out.append(_entry(t3, x < r, {m: x, "r4dct": r}, _cmp(x, r), pk, v, fov, m))
    return out


def evaluate_claims(results: dict) -> list[dict]:
    """Every claim for ``results`` (needs ``metrics``; uses ``respiratory_only`` if present)."""
    if results.get("measured"):  # every claim is about error against truth, which a measured scan has not
        return []
    met = results.get("metrics") or {}
    met = {pk: byv for pk, byv in met.items() if byv}
    ro = results.get("respiratory_only") or {}
    ro_skip = ((results.get("stages") or {}).get("metrics") or {}).get("respiratory_only_skipped_because")
    return (claim_interpolation(met) + claim_pitch(met) + claim_ll_vs_bary(met) + claim_resp_only(ro, ro_skip)
            + claim_ll_gain_at_low_pitch(met) + claim_best_combination(met) + claim_second_pass(met))


def context(c: dict) -> str:
    """``"barycentric, pitch 0.1, noise-free, small FOV"``: the parts of a claim entry that are set."""
    parts = []
    if c.get("method"):
        parts.append(c["method"])
    if c.get("pitch"):
        parts.append(f"pitch {_pitch(c['pitch'])}")
    if c.get("variant"):
        parts.append(c["variant"])
    if c.get("fov"):
        parts.append(f"{c['fov']} FOV")
    return ", ".join(parts)


def verdict(c: dict) -> str:
    """``holds``, ``fails`` or ``skipped``."""
    return "skipped" if c["holds"] is None else ("holds" if c["holds"] else "fails")


def claim_lines(results: dict) -> list[str]:
    """One terminal line per claim, e.g. ``claim: pitch 0.02 below 0.1 (barycentric, noise-free, small FOV):
    holds (20.3 < 41.6 HU)``."""
    out = []
    for c in results.get("claims") or []:
        ctx = context(c)
        why = c.get("skipped") if c["holds"] is None else c["detail"]
        out.append(f"claim: {c['claim']}{f' ({ctx})' if ctx else ''}: {verdict(c)} ({why})")
    return out


def claim_summary_lines(results: dict, show_failures: int = 2) -> list[str]:
    """The claims in a few terminal lines: one per claim, how many of its cases hold.

    E.g. ``claim holds 4/8: local linear at or below barycentric; fails: pitch 0.02, noise-free,
    small FOV (23.3 > 20.3 HU), ... (+2 more)``. The full list is ``results["claims"]`` and the
    report's "Claims" section.
    """
    groups: dict[str, list[dict]] = {}
    for c in results.get("claims") or []:
        groups.setdefault(c["claim"], []).append(c)
    out = []
    for claim, cases in groups.items():
        tested = [c for c in cases if c["holds"] is not None]
        if not tested:
            out.append(f"claim skipped: {claim} ({cases[0].get('skipped', '')})")
            continue
        failed = [c for c in tested if not c["holds"]]
        line = f"claim holds {len(tested) - len(failed)}/{len(tested)}: {claim}"
        if failed:
            shown = "; ".join(f"{context(c)} ({c['detail']})" for c in failed[:show_failures])
            more = f" (+{len(failed) - show_failures} more)" if len(failed) > show_failures else ""
            line += f"; fails: {shown}{more}"
        out.append(line)
    return out
