"""Strict JSON for every file clrecon writes: no bare ``NaN``/``Infinity``, a null with its reason instead.

Python's :mod:`json` writes a non-finite float as the bare tokens ``NaN``, ``Infinity`` and
``-Infinity``, which are not JSON (RFC 8259): strict parsers (JavaScript's ``JSON.parse``, jq,
Go, Rust's serde_json, ``json.loads(..., parse_constant=...)``) reject the whole file. A value
that is not a number in clrecon (an error over zero images, a volume below an LV that is not
in the slices) is written as ``null``, and the top-level object gets ``null_values``: for each
such value its JSON Pointer (RFC 6901, e.g. ``/truth_free/p0.100/errors/.../rms_hu``) and the
reason -- the ``null_because`` string of the object holding it where the code that made it says
why, else what it was (``NaN``, ``Infinity``). :func:`loads` restores those values, so that
clrecon's own readers see the floats they always saw; any other reader sees valid JSON.
"""

from __future__ import annotations

import json
import math
from typing import Any

#: Top-level key listing the values written as null: JSON Pointer -> reason.
NULLS_KEY = "null_values"
#: Key of an object that says why its non-finite values are not numbers.
REASON_KEY = "null_because"


def _name(x: float) -> str:
    return "NaN" if math.isnan(x) else ("Infinity" if x > 0 else "-Infinity")


def _escape(key) -> str:
    return str(key).replace("~", "~0").replace("/", "~1")


def _plain(o):
    """NumPy scalars and arrays, tuples and sets -> plain JSON types (anything else: TypeError)."""
    try:
        import numpy as np
    except ImportError:  # pragma: no cover - numpy is a core dependency
        np = None
    if np is not None:
        if isinstance(o, np.generic):
            return o.item()
        if isinstance(o, np.ndarray):
            return o.tolist()
    if isinstance(o, (tuple, set, frozenset)):
        return list(o)
    if hasattr(o, "__fspath__"):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def strict(obj: Any) -> tuple[Any, dict[str, str]]:
    """A copy of ``obj`` with every non-finite float replaced by None, and ``{pointer: reason}`` of those."""
    nulls: dict[str, str] = {}

    def walk(o, ptr: str, reason: str | None):
        if isinstance(o, float):
            if math.isfinite(o):
                return o
            nulls[ptr] = _name(o) + (f": {reason}" if reason else "")
            return None
        if isinstance(o, dict):
            why = o.get(REASON_KEY) if isinstance(o.get(REASON_KEY), str) else reason
            return {str(k) if not isinstance(k, str) else k: walk(v, f"{ptr}/{_escape(k)}", why) for k, v in o.items()}
        if isinstance(o, list):
            return [walk(v, f"{ptr}/{i}", reason) for i, v in enumerate(o)]
        if o is None or isinstance(o, (str, bool, int)):
            return o
        return walk(_plain(o), ptr, reason)

    return walk(obj, "", None), nulls


def dumps(obj: Any, **kw) -> str:
    """Strict JSON text of ``obj`` (``json.dumps`` keywords such as ``indent`` pass through)."""
    clean, nulls = strict(obj)
    if nulls:
        if not isinstance(clean, dict):
            raise ValueError(f"non-finite values at {', '.join(sorted(nulls))} and no top-level object to list "
                             f"them in")
        clean = {**clean, NULLS_KEY: dict(sorted(nulls.items()))}
    return json.dumps(clean, allow_nan=False, **kw)


def _reject(token: str):
    raise ValueError(f"not strict JSON: bare {token}")


def loads(text: str, restore: bool = True) -> Any:
    """Parse strict JSON (bare ``NaN``/``Infinity`` of files from earlier versions are read as such);
    with ``restore``, the values listed in ``null_values`` become the floats they were."""
    obj = json.loads(text)
    if not (restore and isinstance(obj, dict) and isinstance(obj.get(NULLS_KEY), dict)):
        return obj
    for ptr, reason in obj[NULLS_KEY].items():
        parts = [p.replace("~1", "/").replace("~0", "~") for p in ptr.split("/")[1:]]
        node = obj
        try:
            for p in parts[:-1]:
                node = node[int(p)] if isinstance(node, list) else node[p]
            last = parts[-1]
            if isinstance(node, list):
                last = int(last)
            if node[last] is None:
                word = str(reason).split(":", 1)[0]
                node[last] = {"NaN": math.nan, "Infinity": math.inf, "-Infinity": -math.inf}.get(word, math.nan)
        except (KeyError, IndexError, ValueError, TypeError):
            continue  # a pointer that no longer matches (a hand-edited file): leave it
    return obj


def loads_strictly(text: str) -> Any:
    """``json.loads`` that refuses bare ``NaN``/``Infinity`` as a strict parser does (for tests and checks)."""
    return json.loads(text, parse_constant=_reject)
