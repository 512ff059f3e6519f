"""Scene overrides: ``load_scene("tiny", recon={"nz": 4}, noise__enabled=False)``.

Used by the notebook API (:func:`clrecon.api.load_scene`) and by ``sweep`` (each grid point
is the study's scene with overrides). Values are validated exactly as in a scene file.
"""

from __future__ import annotations

import difflib
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from clrecon.config import scene as _scene
from clrecon.config.scene import Scene
from clrecon.core.errors import SceneError

PathLike = str | Path


def split_overrides(overrides: Mapping[str, Any]) -> dict:
    """``{"recon": {...}, "recon__nz": 4, "recon.nx": 8, "name": "x"}`` -> ``{"recon": {...}, "name": "x"}``."""
    sections = tuple(_scene.SECTIONS)
    out: dict = {}
    for key, value in overrides.items():
        sep = "__" if "__" in key else ("." if "." in key else None)
        if sep is not None:
            sec, _, sub = key.partition(sep)
            table, _, sub2 = sub.partition(sep) if sep in sub else ("", "", sub)
            if sec not in sections or not sub2 or "__" in sub2 or "." in sub2 or (sep in sub and not table):
                near = difflib.get_close_matches(sec, sections, n=1, cutoff=0.5)
                hint = f"; did you mean {near[0]}__{sub}?" if near and sub else f"; sections: {', '.join(sections)}"
                raise SceneError(f"override {key}: expected SECTION__KEY or SECTION__TABLE__KEY with SECTION one "
                                 f"of the scene's sections{hint}")
            if table:  # a table inside the section, e.g. recon__mc__rounds
                out.setdefault(sec, {}).setdefault(table, {})[sub2] = value
            else:
                out.setdefault(sec, {})[sub] = value
        elif key in sections:
            if not isinstance(value, Mapping):
                raise SceneError(f"override {key}={value!r}: expected a dict of [{key}] keys, e.g. "
                                 f"{key}={{...}} or {key}__KEY=VALUE")
            out.setdefault(key, {}).update(value)
        elif key in ("name", "description"):
            out[key] = value
        else:
            near = difflib.get_close_matches(key, sections + ("name", "description"), n=1, cutoff=0.5)
            hint = f"; did you mean {near[0]!r}?" if near else f"; valid: {', '.join(sections)}, name, description"
            raise SceneError(f"override {key}: not a scene section{hint}")
    return out


def load_scene(name_or_path: PathLike | Scene, **overrides: Any) -> Scene:
    """A scene by built-in name (``"tiny"``, ``"demo"``, ...) or TOML path, with overrides.

    Overrides, any mix of (later ones win within a section):

    - a section as a dict: ``recon={"nz": 4, "nx": 64}``, ``noise={"enabled": False}``;
    - one key as ``SECTION__KEY=VALUE``: ``recon__nz=4``, ``scan__pitches=[0.1]``; a key of a table
      inside a section as ``SECTION__TABLE__KEY``: ``recon__mc__rounds=1`` (the table's other keys
      keep the scene's values);
    - the same with a dot through ``**``: ``**{"recon.nz": 4}``;
    - ``name=...`` / ``description=...``.

    Values are validated exactly as in a scene file (:class:`~clrecon.core.errors.SceneError`
    naming the key, value and what is allowed). A :class:`Scene` is accepted too (overrides
    applied to it). Builds on :func:`clrecon.config.scene.load_scene` and :meth:`Scene.replace`.
    """
    scene = name_or_path if isinstance(name_or_path, Scene) else _scene.load_scene(name_or_path)
    if not overrides:
        return scene
    return scene.replace(**split_overrides(overrides))
