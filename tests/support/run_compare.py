"""Bit-identity of two run directories (the crash, fault and distributed tests compare against
an uninterrupted single-process run), and the reference run of a setting's comparison."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import h5py
import pytest

from clrecon.config.scene import load_scene
from clrecon.pipeline.run import run

QUIET = dict(progress=False, log=lambda *a: None)

#: results.json entries that must be equal, besides every dataset of volumes.h5
KEYS = ("metrics", "respiratory_only", "motion", "diagnostics", "sampling")


def run_cli(out, cache, methods: str, fault=None, extra=()) -> subprocess.CompletedProcess:
    """``python -m clrecon run`` of ``tiny`` with ``methods`` (a comma list), serially, without
    progress, in a child process (``fault``: its ``CLRECON_FAULT``, e.g. ``recon:5`` for a kill -9)."""
    env = dict(os.environ, CLRECON_NO_PROGRESS="1")
    env.pop("CLRECON_FAULT", None)
    if fault:
        env["CLRECON_FAULT"] = fault
    cmd = [sys.executable, "-m", "clrecon", "run", "--scene", "tiny", "--methods", methods, "--out", str(out),
           "--cache", str(cache), "--no-progress", "--executor", "serial", *extra]
    return subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=600)


def volumes(path) -> dict:
    """Every dataset of ``path/volumes.h5`` as stored (dtype and shape on disk)."""
    with h5py.File(path / "volumes.h5", "r") as f:
        out = {}
        f.visititems(lambda n, o: out.__setitem__(n, o[()]) if isinstance(o, h5py.Dataset) else None)
    return out


def assert_identical(out, ref, keys=KEYS) -> dict:
    """``out`` equals the reference ``(ref_dir, ref_results)`` bit for bit; returns out's results."""
    ref_out, ref_res = ref
    va, vb = volumes(out), volumes(ref_out)
    assert va.keys() == vb.keys()
    for k in va:
        assert va[k].tobytes() == vb[k].tobytes(), k
    res = json.loads((out / "results.json").read_text())
    want = json.loads(json.dumps(ref_res, default=lambda o: o.tolist() if hasattr(o, "tolist") else list(o)))
    for key in keys:
        assert res[key] == want[key], key
    assert not [p for p in out.iterdir() if p.suffix in (".partial", ".units")]
    return res


def reference_run(tmp_path_factory, env: dict, scene: str = "tiny", executor=None):
    """``(out_dir, results, cache_dir)`` of ``scene`` run with the environment ``env`` set and
    ``executor`` (the module-scoped reference of a test comparing a setting against it); the
    environment is put back afterwards."""
    mp = pytest.MonkeyPatch()
    try:
        for k, v in env.items():
            mp.setenv(k, v)
        out, cache = tmp_path_factory.mktemp("ref"), tmp_path_factory.mktemp("cache")
        return out, run(load_scene(scene), out, cache_dir=cache, executor=executor, **QUIET), cache
    finally:
        mp.undo()
