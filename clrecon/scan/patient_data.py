"""Patient data: what of a measured scene may be written into outputs and caches.

A measured scan's folder, its traces and the scene file are often named after the patient
(``Doe_Jane_MRN-778899/``). Nothing clrecon writes by default (``results.json``, the report,
the projection store's ``scene_json`` in the shared cache, exports) holds such a path: each
input path of a measured scene is recorded by its content instead (``docs/patient-data.md``
"Patient data"):

- ``scan.projections`` -> ``"dicom-ct-pd series <signature>"``, the folder listing's digest
  (:func:`clrecon.scan.dicom_ct_pd.series_signature`, names, sizes and times of the files);
- ``signals.breathing_trace`` / ``signals.ecg_trace`` -> ``"file <digest>"``, the BLAKE2b of
  the file's bytes (:func:`clrecon.scan.recorded.file_digest`);
- the scene file's path -> ``"file <digest>"`` of its bytes.

The scene's ``name`` and ``description`` are recorded as given (a name chosen for the run); a
measured scene without a ``name`` is called ``measured``, not after its file.
A redacted scene cannot be loaded again by itself: an export that needs the input (the
DICOM-CT-PD re-export, ``--keep-identifiers``) takes the scene file again and checks it against
these digests (:func:`matches`).
"""

from __future__ import annotations

import copy

from clrecon.scan import dicom_ct_pd
from clrecon.scan.recorded import file_digest

#: prefix of a redacted series / trace path
SERIES_PREFIX = "dicom-ct-pd series "
FILE_PREFIX = "file "
TRACE_KEYS = ("breathing_trace", "ecg_trace")


def is_redacted(value) -> bool:
    return isinstance(value, str) and (value.startswith(SERIES_PREFIX) or value.startswith(FILE_PREFIX))


def redact_scene_dict(d: dict) -> dict:
    """A copy of a scene's ``to_dict()`` with every input path of a measured scene replaced by its digest.

    A simulated scene is returned unchanged (its paths are the user's phantom and trace files, not a
    patient's); so is a scene whose paths are already redacted.
    """
    scan = d.get("scan") or {}
    if scan.get("source") != "dicom-ct-pd":
        return d
    out = copy.deepcopy(d)
    proj = scan.get("projections", "")
    if proj and not is_redacted(proj):
        try:
            out["scan"]["projections"] = SERIES_PREFIX + dicom_ct_pd.series_signature(proj)
        except Exception:  # noqa: BLE001 - a folder gone since: still never write its name
            out["scan"]["projections"] = SERIES_PREFIX + "unavailable"
    sig = out.get("signals") or {}
    for key in TRACE_KEYS:
        v = sig.get(key, "")
        if v and not is_redacted(v):
            try:
                sig[key] = FILE_PREFIX + file_digest(v)
            except Exception:  # noqa: BLE001 - as above
                sig[key] = FILE_PREFIX + "unavailable"
    return out


def redact_source(source: str) -> str:
    """The scene file by the digest of its bytes (its name may be the patient's; '' stays '')."""
    if not source:
        return ""
    try:
        return FILE_PREFIX + file_digest(source)
    except Exception:  # noqa: BLE001 - a scene given as a dictionary, or a file gone since
        return FILE_PREFIX + "unavailable"


def matches(recorded: dict, scene_dict: dict) -> str:
    """'' when ``scene_dict`` (a loaded scene's ``to_dict()``) is the input ``recorded`` (a redacted
    scene) was made from; else what differs, for a one-line error."""
    mine = redact_scene_dict(scene_dict)
    for sec, key in (("scan", "projections"), *(("signals", k) for k in TRACE_KEYS)):
        a = (recorded.get(sec) or {}).get(key, "")
        b = (mine.get(sec) or {}).get(key, "")
        if a != b:
            return f"{sec}.{key}: the run recorded {a or 'none'!r}, the scene gives {b or 'none'!r}"
    return ""
