"""What a measured run records about its input, and what it must not (``docs/measured-data.md``).

- ``results.json["measured_scan"]`` (:func:`measured_summary`): how the series was read (pixel
  layout, channel and row numbering), the orientation check's residuals for that reading and its
  mirror images and its verdict, where every geometry and calibration value came from (a tag of
  the file, the scene, or a default), and the patient position with the image frame it gives.
- The report's "Measured scan" section (:func:`report_lines`).
- No patient's path on disk: the copy of the results written to ``results.json``
  (:func:`for_disk`) holds the scene with its input paths replaced by their digests
  (:mod:`clrecon.scan.patient_data`) and without the simulation-only phantom keys.
- Exports that need the input again (:func:`run_input_scene`) take the scene file and check it
  against those digests.
"""

from __future__ import annotations

import copy
from pathlib import Path

from clrecon.config.scene import Scene, load_scene
from clrecon.core.errors import ClreconError
from clrecon.scan import dicom_ct_pd, patient_data
from clrecon.scan.patient_frame import lps_signs

#: default water attenuation (1/mm) when neither the series nor the scene gives one
_DEFAULT_MU = 0.0193


def _geometry(scene) -> dicom_ct_pd.SeriesGeometry:
    sc = scene.scan
    found = dicom_ct_pd.resolved_geometry(sc.projections, sc.pixel_layout, sc.orientation, sc.flip_channels,
                                          sc.flip_rows)
    if found is not None:  # the check as the scene load ran it (with what 'auto' saw)
        return found
    ix = dicom_ct_pd.series_index(sc.projections)
    has_ts = bool(ix.timestamp.size) and bool((ix.timestamp == ix.timestamp).all())
    return dicom_ct_pd.series_geometry(sc.projections, None if has_ts else scene.scanner.rotation_time_s,
                                       sc.timestamp_unit, sc.pixel_layout, sc.flip_channels, sc.flip_rows,
                                       sc.orientation, sc.patient_position)


def measured_summary(scene) -> dict:
    """``results.json["measured_scan"]`` of a measured scene (JSON-able; no path, no patient attribute)."""
    geom = _geometry(scene)
    ix = dicom_ct_pd.series_index(scene.scan.projections)
    has_ts = bool((ix.timestamp == ix.timestamp).all())
    from_file = {k: geom.tag_of[k] for k in (*geom.scanner, *geom.scan) if k in geom.tag_of}
    if not has_ts:
        from_file.pop("rotation_time_s", None)
    mu = float(scene.phantom.mu_water_per_mm)
    if "mu_water_per_mm" in geom.phantom:
        mu_src = "file " + geom.tag_of["mu_water_per_mm"]
    elif abs(mu - _DEFAULT_MU) > 1e-12:
        mu_src = "scene (phantom.mu_water_per_mm; the series has no (7041,1001) WaterAttenuationCoefficient)"
    else:
        mu_src = "default (the series has no (7041,1001) WaterAttenuationCoefficient)"
    calibration = {
        "mu_water_per_mm": {"value": mu, "from": mu_src},
        "rescale": {"from": "file (0028,1053) RescaleSlope, (0028,1052) RescaleIntercept, per file"
                    if ix.rescale_in_files else "default (slope 1, intercept 0: the files carry no rescale)"},
        "rotation_time_s": {"value": float(scene.scanner.rotation_time_s),
                            "from": "file (7033,1067) Timestamp" if has_ts else "scene (scanner.rotation_time_s)"},
    }
    position = scene.scan.patient_position or "HFS"
    pos_src = ("file (0018,5100) PatientPosition" if dicom_ct_pd.series_index(scene.scan.projections).const.get(
        "PatientPosition") else "scene (scan.patient_position)")
    sx, sy, sz = lps_signs(position)
    reading = geom.reading
    check = copy.deepcopy(geom.check)
    return {
        "series": patient_data.SERIES_PREFIX + dicom_ct_pd.series_signature(scene.scan.projections),
        "views": len(ix),
        "reading": {"pixel_layout": reading.layout, "flip_channels": bool(scene.scan.flip_channels),
                    "flip_rows": bool(scene.scan.flip_rows), "orientation": scene.scan.orientation,
                    "store_columns_reversed": reading.reverse_channels, "store_rows_reversed": reading.reverse_rows,
                    "central_col": reading.central_col, "central_row": reading.central_row,
                    "rotation": scene.scan.rotation, "table_direction": scene.scan.table_direction},
        "orientation_check": check,
        "from_file": from_file,
        "calibration": calibration,
        "noise": "measured: the projections carry their own noise; none is simulated",
        "patient_position": {"value": position, "from": pos_src, "lps_signs": [sx, sy, sz],
                             "image_frame": "the volumes are in the scanner frame (DICOM-CT-PD frame); LPS = "
                                            f"({sx:+d} x, {sy:+d} y, {sz:+d} z); the DICOM export's "
                                            "ImageOrientationPatient/ImagePositionPatient carry it"},
    }


def annotate_results(results: dict, scene, log=None) -> None:
    """Add ``results["measured_scan"]``; a warning of the orientation check goes to ``log`` too."""
    summary = measured_summary(scene)
    results["measured_scan"] = summary
    warn = summary["orientation_check"].get("warning")
    if warn and log is not None:
        log(f"WARNING orientation check: {warn} (docs/measured-conventions.md 'Orientation check')")


def for_disk(results: dict) -> dict:
    """The results as ``results.json`` holds them: a measured scene without its input paths (patient data)
    and without the simulation-only phantom keys; a simulated run's unchanged."""
    if not results.get("measured"):
        return results
    out = dict(results)
    scene = patient_data.redact_scene_dict(results["scene"])
    ph = scene.get("phantom") or {}
    scene["phantom"] = {k: ph[k] for k in ("kind", "mu_water_per_mm") if k in ph}
    out["scene"] = scene
    out["scene_source"] = patient_data.redact_source(results.get("scene_source", ""))
    return out


def run_input_scene(run, scene=None):
    """The scene a run was made from, for an export that reads its input again.

    A simulated run (or one recorded before paths were redacted): ``run.scene``. A measured run:
    ``scene`` (a scene file or a :class:`~clrecon.config.scene.Scene`), checked against the run's
    record; one-line :class:`ClreconError` without it or when it is another input.
    """
    rec = run.results.get("scene", {}) if run.has_results else {}
    proj = (rec.get("scan") or {}).get("projections", "")
    if scene is None:
        if not patient_data.is_redacted(proj):
            return run.scene
        raise ClreconError(f"{run.dir}: this measured run records its series only as {proj!r} (no path: patient "
                           f"data, docs/patient-data.md 'Patient data'); give the scene it was made from: "
                           f"export ... --scene FILE")
    given = scene if isinstance(scene, Scene) else load_scene(scene)
    if patient_data.is_redacted(proj):
        diff = patient_data.matches(rec, given.to_dict())
        if diff:
            where = getattr(given, "source", "") or "the scene"
            raise ClreconError(f"--scene {Path(where).name}: not the input of the run in {run.dir}: {diff}")
    return given


def _fmt(v) -> str:
    return "—" if v is None or v != v else f"{v:.4g}"


def report_lines(results: dict) -> list[str]:
    """The report's account of the reading, the orientation check, the calibration and the patient frame."""
    ms = results.get("measured_scan")
    if not ms:
        return []
    r, ck, pp = ms["reading"], ms["orientation_check"], ms["patient_position"]
    lines = [f"Series {ms['series']}: {ms['views']} views; pixel layout {r['pixel_layout']}; channels "
             f"{'numbered opposite to' if r['flip_channels'] else 'in'} the DICOM-CT-PD convention, rows "
             f"{'numbered opposite to' if r['flip_rows'] else 'in'} it (scan.orientation = '{r['orientation']}'); "
             f"gantry angle {r['rotation']}, table {r['table_direction']} in z.", ""]
    lines += ["### Orientation check (no ground truth: the data against their mirror images)", "",
              "Residual = RMS of the disagreement / RMS of the line integrals, lower is better "
              "(docs/measured-conventions.md 'Orientation check').", "",
              "| test | reading | residual | verdict |", "|---|---|---|---|"]
    for test, label in (("channels", "conjugate rays"), ("rows", "same-angle views across turns")):
        t = ck.get(test) or {}
        res = t.get("residuals") or {}
        if not res:
            lines.append(f"| {label} | — | — | cannot tell: {t.get('why', 'not run')} |")
            continue
        for i, (h, v) in enumerate(res.items()):
            verdict = ""
            if i == 0:
                verdict = f"{t.get('verdict', '')}" + (f" (best mirror / reading = {t['ratio']:.2f})"
                                                        if t.get("ratio") is not None else "")
            lines.append(f"| {label} | {h} | {_fmt(v)} | {verdict} |")
    lines.append("")
    if ck.get("warning"):
        lines += [f"**Warning: {ck['warning']}.** Check the image against the anatomy (the heart on the patient's "
                  "left) before using it.", ""]
    if str(ck.get("verdict", "")).startswith("mirror fits better"):
        lines += ["**The tags' numbering was mirrored by the data; the better fit was taken (scan.orientation = "
                  "'auto').**", ""]
    lines += ["### Where the values came from", "", "| value | from |", "|---|---|"]
    for k, v in ms["calibration"].items():
        val = f" = {v['value']:.6g}" if "value" in v else ""
        lines.append(f"| {k}{val} | {v['from']} |")
    lines.append(f"| geometry ({', '.join(sorted(ms['from_file']))}) | file: the DICOM-CT-PD tags |")
    lines.append(f"| patient position = {pp['value']} | {pp['from']} |")
    lines += ["", f"Image frame: {pp['image_frame']}. Noise: {ms['noise']}.", ""]
    return lines
