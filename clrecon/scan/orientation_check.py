"""The data's own check that a measured series is read the right way round (no ground truth used).

A series read with its channels or rows numbered the wrong way reconstructs a point-reflected,
distorted image, or the wrong slices, with nothing in the headers to say so. Two redundancies
of a helical scan tell the right reading from its mirror images (``docs/measured-conventions.md``
"Orientation check"):

- **Conjugate rays** (channels, central element, angle direction). A full rotation measures
  every in-plane line twice: the ray at gantry angle beta and fan angle gamma (> 0 towards
  increasing beta) is the ray at beta + pi - 2 gamma and fan angle -gamma. One rotation around a
  slice z_s, each view rebinned
  to z_s (single-slice rebinning, Noo et al. 1999), is compared with itself at the conjugate
  positions (bilinear in angle and channel). With a quarter-detector offset the two samplings
  interleave, and they agree only when the channel direction, the central element and the angle
  direction fit together; a mirrored numbering compares each line with a different one.
- **The helix** (row direction). Two views at the same angle m turns apart, rebinned to the slice
  half-way between their source positions, see the same in-plane line from above and below; they
  agree only when the row index runs the way the table moves it (a feature's track across the
  rows must follow the table).

Each reading (the one the tags and keys give, and its mirror images) gets a residual: the RMS of
the disagreement over the RMS of the line integrals (dimensionless, lower is better). The
verdict compares the best mirror with the reading: ``confirmed`` when the mirror's residual is at
least :data:`CONFIRM_RATIO` times larger, ``mirror fits better`` when it is that much smaller,
else ``cannot tell`` (an object the mirror leaves unchanged: a centred cylinder for the channels,
anything uniform along z for the rows). Reversing the angle direction alone is the same test as
reversing the channels (the two together are the whole mirror image, which no data can tell from
the original: that is the frame's handedness, fixed by the format's definition, not checked here).
The flying focal spot's shifts are ignored (they add a small floor to every residual).
"""

from __future__ import annotations

import numpy as np

from clrecon.core.errors import InputError
from clrecon.scan.dicom_ct_pd_pixels import read_projection

#: a mirror is told from the reading when one residual is at least this many times the other
CONFIRM_RATIO = 1.5
#: rebinned rows use detector rows up to this fraction of the half height (away from the edge rows)
ROW_REACH = 0.85


def _gammas(n_cols: int, col_pitch: float, sdd: float, central_col: float, detector: str) -> np.ndarray:
    """Fan angle (rad) of every channel, (C,): positive towards +e_u (docs/conventions.md)."""
    c = np.arange(n_cols, dtype=np.float64) - central_col
    return c * col_pitch / sdd if detector == "cylindrical" else np.arctan(c * col_pitch / sdd)


def _rebin(proj: np.ndarray, dz: float, gam: np.ndarray, central_row: float, geo: dict) -> np.ndarray:
    """One view's row for the slice dz = z_slice - z_source above its source (SSRB), (C,), NaN off the detector."""
    R = proj.shape[0]
    if geo["detector"] == "cylindrical":
        v = dz * geo["sdd"] / (geo["sid"] * np.cos(gam))
    else:
        v = dz * geo["sdd"] / (geo["sid"] * np.cos(gam) ** 2)
    r = central_row + v / geo["row_pitch"]
    ok = (r >= 0) & (r <= R - 1)
    r0 = np.clip(np.floor(r).astype(np.int64), 0, max(R - 2, 0))
    f = np.clip(r - r0, 0.0, 1.0)
    cols = np.arange(proj.shape[1])
    r1 = np.minimum(r0 + 1, R - 1)
    out = (1.0 - f) * proj[r0, cols] + f * proj[r1, cols]
    return np.where(ok, out, np.nan)


def conjugate_residual(sino: np.ndarray, beta: np.ndarray, sign: int, gam: np.ndarray, central_col: float,
                       geo: dict) -> float:
    """RMS(P - P at the conjugate rays) / RMS(P) of one rotation's rebinned sinogram ``sino`` (V, C).

    ``beta`` (V,) the views' gantry angles (regular, step sign * 2 pi / V), ``gam`` (C,) the fan angles.
    """
    V, C = sino.shape
    step = 2.0 * np.pi / V
    a = beta[:, None] + np.pi - 2.0 * gam[None, :]
    t = np.mod((a - beta[0]) / (sign * step), V)
    i0 = np.floor(t).astype(np.int64) % V
    fi = t - np.floor(t)
    i1 = (i0 + 1) % V
    g2 = np.broadcast_to(-gam[None, :], a.shape)
    if geo["detector"] == "cylindrical":
        cc = central_col + g2 * geo["sdd"] / geo["col_pitch"]
    else:
        cc = central_col + geo["sdd"] * np.tan(g2) / geo["col_pitch"]
    inside = (cc >= 0) & (cc <= C - 1)
    c0 = np.clip(np.floor(cc).astype(np.int64), 0, C - 2)
    fc = np.clip(cc - c0, 0.0, 1.0)
    c1 = c0 + 1

    def at(i):
        return (1.0 - fc) * sino[i, c0] + fc * sino[i, c1]

    conj = (1.0 - fi) * at(i0) + fi * at(i1)
    d = np.where(inside, sino - conj, np.nan)
    ok = np.isfinite(d)
    if ok.sum() < 16:
        return float("nan")
    return float(np.sqrt(np.mean(d[ok] ** 2)) / max(np.sqrt(np.mean(sino[ok] ** 2)), 1e-30))


def check_series(ix, scanner: dict, views, base, flip_channels: bool, flip_rows: bool,
                 reader=read_projection) -> dict:
    """Residuals of the reading ``base`` (a :class:`clrecon.scan.dicom_ct_pd.Reading`, from ``flip_*``) and
    its mirror images; the JSON-able dictionary recorded in
    ``results.json["measured_scan"]["orientation_check"]`` (no verdict yet: :func:`decide`)."""
    import pydicom

    n = len(ix)
    V = int(scanner["views_per_rotation"])
    R, C = int(scanner["n_rows"]), int(scanner["n_cols"])
    geo = {"sid": float(scanner["sid_mm"]), "sdd": float(scanner["sdd_mm"]),
           "col_pitch": float(scanner["col_pitch_mm"]), "row_pitch": float(scanner["row_pitch_mm"]),
           "detector": scanner["detector"]}
    layout = base.layout
    # channel hypotheses in the store numbering of the base reading: (reverse the columns, central column)
    chans = {"as read": (False, base.central_col), "channels mirrored": (True, C - 1.0 - base.central_col)}
    if abs((C - 1.0 - base.central_col) - base.central_col) > 1e-6:  # off-centre: the half-way mirror differs
        chans["channels mirrored, central element not reflected"] = (True, base.central_col)
    rows = {"as read": (False, base.central_row), "rows mirrored": (True, R - 1.0 - base.central_row)}
    out = {"method": "conjugate rays (channels) and same-angle views m turns apart (rows), docs/measured-data.md "
                     "'Orientation check'", "confirm_ratio": CONFIRM_RATIO,
           "reading": {"pixel_layout": layout, "flip_channels": bool(flip_channels), "flip_rows": bool(flip_rows)}}
    if n < V:
        out["channels"] = {"residuals": {}, "why": f"the series holds {n} views, less than one rotation ({V})"}
        out["rows"] = {"residuals": {}, "why": "no full rotation"}
        return out
    z = views.source_z_mm
    feed = abs(float(z[min(V, n - 1)] - z[0]))  # per rotation
    v_max = ROW_REACH * (R / 2.0 - 0.5) * geo["row_pitch"]  # |v| reachable on the detector (mm at the detector)
    dz_max = v_max * geo["sid"] / geo["sdd"]
    m = int(np.floor(2.0 * dz_max / feed)) if feed > 0 else 0  # turns apart: each view dz = m feed / 2 off its slice
    m = min(m, (n - V) // V)  # as far apart as the series allows
    span = V + (m * V if m >= 1 else 0)
    a0 = max(0, (n - span) // 2)
    block_a = np.arange(a0, a0 + V)
    block_b = block_a + m * V if m >= 1 and a0 + span <= n else None
    z_s = float(z[block_a[V // 2]])
    gam = {h: _gammas(C, geo["col_pitch"], geo["sdd"], c0, geo["detector"]) for h, (_, c0) in chans.items()}
    sino = {(hr, hc): np.empty((V, C)) for hr in rows for hc in chans}
    pair_a = {hr: np.empty((V, C)) for hr in rows}
    pair_b = {hr: np.empty((V, C)) for hr in rows}

    def load(k):
        return reader(ix.files[k], ix.slope[k], ix.intercept[k], R, C, pydicom, base).astype(np.float64)

    for i, k in enumerate(block_a):
        p = load(k)
        for hr, (rev_r, r0) in rows.items():
            pr = p[::-1, :] if rev_r else p
            for hc, (rev_c, _c0) in chans.items():
                pc = pr[:, ::-1] if rev_c else pr
                sino[(hr, hc)][i] = _rebin(pc, z_s - z[k], gam[hc], r0, geo)
            if block_b is not None:
                z_mid = 0.5 * (z[k] + z[block_b[i]])
                pair_a[hr][i] = _rebin(pr, z_mid - z[k], gam["as read"], r0, geo)
    if block_b is not None:
        for i, k in enumerate(block_b):
            p = load(k)
            for hr, (rev_r, r0) in rows.items():
                pr = p[::-1, :] if rev_r else p
                z_mid = 0.5 * (z[block_a[i]] + z[k])
                pair_b[hr][i] = _rebin(pr, z_mid - z[k], gam["as read"], r0, geo)
    row_res = {}
    if block_b is not None:
        for hr in rows:
            d = pair_a[hr] - pair_b[hr]
            ok = np.isfinite(d)
            row_res[hr] = (float(np.sqrt(np.mean(d[ok] ** 2)) / max(np.sqrt(np.mean(pair_a[hr][ok] ** 2)), 1e-30))
                           if ok.sum() >= 16 else float("nan"))
        out["rows"] = {"residuals": row_res, "turns_apart": m, "views": [int(block_a[0]), int(block_b[-1])]}
    else:
        out["rows"] = {"residuals": {}, "why": f"no two views at one angle see one slice (feed {feed:.1f} mm per "
                                               f"rotation, reach +-{dz_max:.1f} mm, {n} views of {V} per rotation)"}
    best_rows = "as read"
    if row_res and np.isfinite(row_res.get("rows mirrored", np.nan)) and \
            row_res["rows mirrored"] * CONFIRM_RATIO <= row_res["as read"]:
        best_rows = "rows mirrored"
    beta = views.angle_rad[block_a]
    res = {hc: conjugate_residual(sino[(best_rows, hc)], beta, views.rotation_sign, gam[hc], chans[hc][1], geo)
           for hc in chans}
    out["channels"] = {"residuals": res, "rows_reading": best_rows, "slice_z_mm": z_s,
                       "views": [int(block_a[0]), int(block_a[-1])]}
    return out


def _verdict(res: dict) -> tuple[str, str | None, float | None]:
    """(verdict, best mirror, ratio best-mirror / as-read) of one residual table."""
    if not res or not np.isfinite(res.get("as read", np.nan)):
        return "cannot tell", None, None
    alts = {k: v for k, v in res.items() if k != "as read" and np.isfinite(v)}
    if not alts:
        return "cannot tell", None, None
    best = min(alts, key=alts.get)
    ratio = alts[best] / max(res["as read"], 1e-30)
    if ratio >= CONFIRM_RATIO:
        return "confirmed", best, ratio
    if ratio * CONFIRM_RATIO <= 1.0:
        return "mirror fits better", best, ratio
    return "cannot tell", best, ratio


def decide(result: dict, folder: str, flip_channels: bool, flip_rows: bool, orientation: str) -> dict:
    """The verdicts of :func:`check_series`, and the keys of the reading to use: ``{flip_channels, flip_rows}``.

    ``orientation = "tags"``: a mirror that fits better is refused (one line with the remedy);
    ``"auto"``: the best fit is taken where the data tell, the tags' reading where they cannot.
    Adds ``verdict``, ``used`` and ``warning`` to ``result``.
    """
    vc, bc, rc = _verdict(result.get("channels", {}).get("residuals", {}))
    vr, br, rr = _verdict(result.get("rows", {}).get("residuals", {}))
    result["channels"].update(verdict=vc, best_mirror=bc, ratio=rc)
    result["rows"].update(verdict=vr, best_mirror=br, ratio=rr)
    fc, fr = flip_channels, flip_rows
    if vc == "mirror fits better" and bc and "not reflected" in bc:
        res = result["channels"]["residuals"]
        raise InputError(f"{folder}: (7031,1033) DetectorCentralElement does not fit the channel numbering: the "
                         f"conjugate rays fit channels mirrored with the central element left as it is (residual "
                         f"{res[bc]:.3g}) better than the reading from the tags ({res['as read']:.3g}); the series "
                         f"gives the central element for the other numbering: fix the tag (docs/measured-data.md "
                         f"'Orientation check')")
    wrong = []
    if vc == "mirror fits better":
        wrong.append(("channels", "flip_channels", not flip_channels, result["channels"]["residuals"], bc))
    if vr == "mirror fits better":
        wrong.append(("rows", "flip_rows", not flip_rows, result["rows"]["residuals"], br))
    if wrong and orientation != "auto":
        what = "; ".join(f"{w}: residual {res['as read']:.3g} as read, {res[b]:.3g} {b}" for w, _, _, res, b in wrong)
        keys = ", ".join(f"scan.{k} = {str(v).lower()}" for _, k, v, _, _ in wrong)
        raise InputError(f"{folder}: the data contradict the numbering read from the tags ({what}); the image would "
                         f"be mirrored: set {keys} (the series numbers its {' and '.join(w for w, *_ in wrong)} the "
                         f"other way) or scan.orientation = 'auto' (docs/measured-conventions.md 'Orientation check')")
    for _, key, val, _, _ in wrong:  # auto: take the fit
        if key == "flip_channels":
            fc = val
        else:
            fr = val
    warn = []
    for w, v in (("channels", vc), ("rows", vr)):
        if v == "cannot tell":
            why = result[w].get("why") or "the mirror fits as well (an object the mirror leaves unchanged?)"
            warn.append(f"the data cannot tell the {w}' numbering from its mirror ({why}): the tags' reading is "
                        f"used unverified")
    result["verdict"] = ("mirror fits better, taken (scan.orientation = 'auto')" if wrong
                         else ("confirmed" if vc == vr == "confirmed" else "not confirmed"))
    result["used"] = {"flip_channels": bool(fc), "flip_rows": bool(fr), "orientation": orientation}
    result["warning"] = "; ".join(warn)
    return {"flip_channels": bool(fc), "flip_rows": bool(fr)}
