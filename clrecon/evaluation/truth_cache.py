"""The truth cache: ground truth and phantom truth computed once per target, shared by runs.

The two truths of a target (:mod:`clrecon.evaluation.groundtruth`) depend on the phantom, the
detector and views, the reconstruction grid and filter, the slices and the target, never on
the pitch, the methods or the noise: paper-p002 and paper-p010 have the same truths. So each
target's truth unit (the same checksummed file the run directory's volume writer makes,
:mod:`clrecon.core.units`) is also kept in ``<cache_dir>/truth/<key>/``, hard-linked (no second
copy on disk while the run holds it; a copy where the file system cannot link), and a later
run with the same key takes it from there instead of computing it. A damaged cached unit fails
its checksum and is computed again. ``key`` is :func:`truth_key`.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
from pathlib import Path

import numpy as np

from clrecon.core import units
from clrecon.core.runtime import default_cache_tag
from clrecon.core.versions import PROJECTOR_VERSION
from clrecon.reconstruction.parallel_fbp import S_OVERSAMPLE

#: Bumped when the truths' computation changes (the key then changes: old entries are unused).
TRUTH_VERSION = 1


def truth_key(scene, slices_z, targets) -> str:
    """Content hash of everything the truths of a run depend on (hex, 24 characters)."""
    d = scene.to_dict()
    rc = d["recon"]
    payload = {"scanner": d["scanner"], "phantom": d["phantom"], "signals": d["signals"],
               "start_angle_deg": d["scan"].get("start_angle_deg"),
               "grid": {k: rc[k] for k in ("nx", "ny", "voxel_mm", "filter", "volume_dtype")},
               "slices_z": np.asarray(slices_z, float).round(9).tolist(),
               "targets": [list(targets.cardiac), list(targets.resp)],
               "dims": [scene.has_cardiac, scene.has_respiratory],
               "projector": PROJECTOR_VERSION, "truth": TRUTH_VERSION}
    if rc.get("backprojector", "direct") != "direct":  # (absent for direct: the keys of older caches stay)
        payload["backprojector"] = {"name": rc["backprojector"], "s_oversample": S_OVERSAMPLE}
    if hasattr(scene.phantom, "content_hash"):  # a phantom read from files: their content
        payload["phantom_content"] = scene.phantom.content_hash()
    if tag := default_cache_tag():  # computed by another driver than PoCL: last bits differ
        payload["driver"] = tag
    return hashlib.sha256(json.dumps(payload, sort_keys=True).encode()).hexdigest()[:24]


def _link(src: Path, dst: Path) -> None:
    """``dst`` = ``src`` by hard link (copy if linking fails), atomically (temporary name, rename)."""
    tmp = dst.with_name(f".{dst.name}.{os.getpid()}.tmp")
    tmp.unlink(missing_ok=True)
    try:
        os.link(src, tmp)
    except OSError:
        shutil.copyfile(src, tmp)
        units.fsync_file(tmp)
    os.replace(tmp, dst)
    units.fsync_dir(dst.parent)


class TruthCache:
    """The cached truth units of one key: ``find`` a target's unit, ``put`` one, ``link`` one out."""

    def __init__(self, cache_dir: str | Path, key: str):
        self.dir = Path(cache_dir) / "truth" / key

    def find(self, stem: str) -> Path | None:
        """The cached unit file named ``<stem>.<digest>.unit``, or None."""
        if not self.dir.is_dir():
            return None
        hits = sorted(self.dir.glob(f"{stem}.*{units.SUFFIX}"))
        return hits[0] if hits else None

    def put(self, unit_path: Path) -> None:
        """Keep a finished unit file (hard link; nothing if already there)."""
        self.dir.mkdir(parents=True, exist_ok=True)
        dst = self.dir / Path(unit_path).name
        if not dst.exists():
            _link(Path(unit_path), dst)

    def link(self, unit_path: Path, folder: Path) -> Path:
        """Link a cached unit into ``folder`` (a run's units folder); returns the new path."""
        dst = Path(folder) / Path(unit_path).name
        _link(Path(unit_path), dst)
        return dst

    def drop(self, unit_path: Path) -> None:
        """Remove a cached unit (it failed its checksum)."""
        Path(unit_path).unlink(missing_ok=True)
