"""``clrecon phantom export``: the analytic phantom written as 4D voxel frames (XCAT format or NIfTI).

The frames are what a user brings for ``[phantom] kind = "voxel"`` (docs/voxel-phantoms.md),
made from the built-in thorax so the voxel path can be checked against the exact analytic
path on the same scene (tests/simulation/test_voxel_phantom.py); no XCAT file can be shipped (XCAT is
licensed). What is written into ``OUT``:

- ``--format xcat``: ``<name>_atn_<k>.bin`` (k = 1..N; float32 little-endian, slice x row x
  column, mu in 1/pixel, slice 1 most inferior, rows anterior -> posterior, columns right ->
  left) and ``<name>_log`` with the lines :func:`clrecon.simulation.phantoms.frames.parse_xcat_log`
  reads (pixel and slice width in cm, array_size, slice range, Total Output Frames, Time Per
  Frame, the water coefficient in 1/cm and 1/pixel). No heart or breathing period is
  written (the frames follow the scene's irregular signals, which XCAT's periods cannot
  describe), so ``timing = "auto"`` reads them as ``"scene"``.
- ``--format nifti``: ``frame_<k>.nii`` (float32 HU, RAS+ affine) and ``frames.toml`` (file,
  cardiac_phase, resp_amplitude and, for a time trajectory, time_s of every frame).
- both: ``phantom.toml``, the ``[phantom]`` table to put into a scene (absolute path).

Frames (``n_frames``): along the scene's time trajectory, frame k at ``t_k = k D / (N - 1)``
(D the longest scan of the scene's pitches), posed at the scene's state at ``t_k``
(:func:`clrecon.scan.signals.physiology` ``state_cardiac``, ``state_resp``: what the analytic
projector poses at that time); or, with ``grid = (n_c, n_a)`` (NIfTI only), on the grid
``c = i / n_c``, ``a = j / (n_a - 1)``. Grid: cubic voxels of ``voxel_mm`` (default half the
scene's reconstruction voxel), in-plane a square of half-width max(scanner FOV radius, half
the reconstruction grid), along z the source range of every pitch widened by the cone:
``(n_rows / 2) row_pitch (SID + sqrt(2) r) / SDD`` with r that half-width, so that no ray
meets the body outside the frames. Each voxel is the mean of ``supersample^3`` point samples
(:func:`clrecon.simulation.voxelise.voxelise_objects`).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from clrecon.core import atomic
from clrecon.core.conventions import mu_to_hu
from clrecon.core.errors import ClreconError
from clrecon.scan import signals
from clrecon.simulation.config import SimulatedScan
from clrecon.simulation.phantoms.analytic import Phantom
from clrecon.simulation.voxelise import voxelise_objects

FORMATS = ("xcat", "nifti")


def export_grid(scene: SimulatedScan, voxel_mm: float | None = None):
    """Voxel-centre axes (x, y, z) mm, each increasing, of frames that cover the scanned volume."""
    sc, rc = scene.scanner, scene.recon
    h = float(voxel_mm or rc.voxel_mm / 2.0)
    if not (math.isfinite(h) and h > 0):
        raise ClreconError(f"--voxel-mm {voxel_mm!r}: must be a number > 0")
    half = max(sc.fov_radius_mm, 0.5 * max(rc.nx, rc.ny) * rc.voxel_mm)
    n = int(math.ceil(2 * half / h))
    xy = (np.arange(n) - (n - 1) / 2.0) * h
    z0 = min(scene.scan.z_start_mm(sc, p) for p in scene.scan.pitches)
    z1 = max(scene.scan.z_start_mm(sc, p) + scene.scan.travel_mm(sc, p) for p in scene.scan.pitches)
    margin = 0.5 * sc.n_rows * sc.row_pitch_mm * (sc.sid_mm + math.sqrt(2.0) * half) / sc.sdd_mm
    lo, hi = z0 - margin, z1 + margin
    nz = int(math.ceil((hi - lo) / h)) + 1
    z = 0.5 * (lo + hi) + (np.arange(nz) - (nz - 1) / 2.0) * h
    if n * n * nz > 2 ** 31 - 1:
        raise ClreconError(f"--voxel-mm {h:g}: {n} x {n} x {nz} voxels per frame is more than the projector's 2^31")
    return xy, xy.copy(), z


def export_states(scene: SimulatedScan, n_frames: int, grid=None):
    """Frame states: (c (N,), a (N,), t (N,) s or None) along the scene's time trajectory or on a grid."""
    if grid is not None:
        nc, na = (int(v) for v in grid)
        if nc < 1 or na < 1:
            raise ClreconError(f"--grid {nc}x{na}: both counts must be >= 1")
        cs = np.arange(nc) / nc
        as_ = np.linspace(0.0, 1.0, na) if na > 1 else np.array([0.5])
        c, a = (v.ravel() for v in np.meshgrid(cs, as_, indexing="ij"))
        return c, a, None
    if not (isinstance(n_frames, int) and n_frames >= 1):
        raise ClreconError(f"--frames {n_frames!r}: must be an integer >= 1")
    dur = max(scene.scan.duration_s(scene.scanner, p) for p in scene.scan.pitches)
    t = np.linspace(0.0, dur, n_frames) if n_frames > 1 else np.zeros(1)
    phys = signals.physiology(scene, t)
    return phys.state_cardiac, phys.state_resp, t


def _xcat_log(name, scene, h_mm, n, nz, n_frames, dt, mu_w) -> str:
    lines = [
        f"clrecon phantom export: the analytic thorax of scene {scene.name!r} as XCAT-format attenuation frames",
        "(written by clrecon, not by the XCAT program; float32 little-endian, slice x row x column,",
        " slice 1 most inferior, rows anterior to posterior, columns patient right to left;",
        " frames follow the scene's signals: use timing = \"scene\")",
        "",
        f" pixel width = {h_mm / 10.0:.8g} (cm/pixel)",
        f" slice width = {h_mm / 10.0:.8g} (cm/pixel)",
        f" array_size = {n}",
        " starting slice number    = 1",
        f" ending slice number      = {nz}",
        f" Total Output Frames = {n_frames}",
        f" Time Per Frame = {dt:.10g} s",
        "",
        "Linear Attenuation Coefficients (1/cm):",
        f" Body (water) = {mu_w * 10.0:.8g}",
        " Air = 0",
        "",
        "Linear Attenuation Coefficients (1/pixel):",
        f" Body (water) = {mu_w * h_mm:.8g}",
        " Air = 0",
        "",
    ]
    return "\n".join(lines)


def _toml_str(p) -> str:
    return '"' + str(p).replace("\\", "\\\\").replace('"', '\\"') + '"'


def export_phantom(scene: SimulatedScan, out, fmt: str, n_frames: int = 0, voxel_mm: float | None = None, *, grid=None,
                   name: str = "clrecon", supersample: int = 2, rt=None) -> dict:
    """Write the scene's analytic phantom as frames into ``out`` (module docstring); returns a summary.

    Returns a dict: ``format``, ``out``, ``files`` (frame paths), ``header`` (log or table),
    ``phantom_toml``, ``shape`` (nz, ny, nx), ``voxel_mm``, ``origin_mm`` (x, y, z of voxel
    [0, 0, 0]), ``states`` (c, a lists), ``times_s`` (or None).
    """
    if fmt not in FORMATS:
        raise ClreconError(f"--format {fmt!r}: must be one of {', '.join(FORMATS)}")
    if scene.phantom.kind != "analytic":
        raise ClreconError(f"phantom export writes the analytic phantom; scene {scene.name!r} has "
                           f"phantom.kind = {scene.phantom.kind!r}")
    if grid is not None and fmt == "xcat":
        raise ClreconError("--grid: XCAT frames are a time series; a (c, a) grid needs --format nifti")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    x, y, z = export_grid(scene, voxel_mm)
    h = float(x[1] - x[0])
    c, a, t = export_states(scene, n_frames, grid)
    phantom = Phantom(scene.phantom)
    mu_w = scene.phantom.mu_water_per_mm
    nib = None
    if fmt == "nifti":
        try:
            import nibabel as nib
        except ImportError:
            raise ClreconError("--format nifti needs nibabel: pip install 'clrecon[export]'") from None
    files = []
    for k in range(len(c)):
        mu = voxelise_objects(phantom.objects(float(c[k]), float(a[k])), x, y, z, supersample=supersample, rt=rt)
        if fmt == "xcat":
            f = out / f"{name}_atn_{k + 1}.bin"
            atomic.write_bytes(f, (mu.astype(np.float64) * h).astype("<f4").tobytes())
        else:
            f = out / f"frame_{k + 1:03d}.nii"
            affine = np.diag([-1.0, -1.0, 1.0, 1.0]) @ np.array(
                [[h, 0, 0, x[0]], [0, h, 0, y[0]], [0, 0, h, z[0]], [0, 0, 0, 1.0]])     # LPS -> RAS
            img = nib.Nifti1Image(mu_to_hu(mu, mu_w).astype(np.float32).transpose(2, 1, 0), affine)
            img.header.set_xyzt_units("mm", "sec")
            with atomic.replacing(f, keep_suffix=True) as tmp:  # whole or not at all
                nib.save(img, str(tmp))
        files.append(f)
    if fmt == "xcat":
        header = out / f"{name}_log"
        dt = float(t[1] - t[0]) if len(t) > 1 else 1.0
        atomic.write_text(header, _xcat_log(name, scene, h, len(x), len(z), len(c), dt, mu_w))
        snippet = ['[phantom]', 'kind = "voxel"', f"frames = {_toml_str(header.resolve())}", 'format = "xcat"',
                   'timing = "scene"', 'interpolation = "linear"',
                   "centre_mm = [" + ", ".join(f"{0.5 * (v[0] + v[-1]):.10g}" for v in (x, y, z)) + "]"]
    else:
        header = out / "frames.toml"
        rows = ["# clrecon phantom export: the analytic thorax of scene " + repr(scene.name) + ", values in HU", ""]
        for k, f in enumerate(files):
            rows += ["[[frame]]", f"file = {_toml_str(f.name)}", f"cardiac_phase = {float(c[k])!r}",
                     f"resp_amplitude = {float(a[k])!r}"]
            if t is not None:
                rows.append(f"time_s = {float(t[k])!r}")
            rows.append("")
        atomic.write_text(header, "\n".join(rows))
        snippet = ['[phantom]', 'kind = "voxel"', f"frames = {_toml_str(header.resolve())}", 'format = "nifti"',
                   'timing = "table"', 'interpolation = "linear"', 'values = "hu"', f"mu_water_per_mm = {mu_w!r}"]
    if not scene.phantom.cardiac_motion:
        snippet.append("cardiac_motion = false")
    if not scene.phantom.respiratory_motion:
        snippet.append("respiratory_motion = false")
    toml = out / "phantom.toml"
    atomic.write_text(toml, "# paste into a scene file (replacing its [phantom] table)\n" + "\n".join(snippet) + "\n")
    return {"format": fmt, "out": str(out), "files": [str(f) for f in files], "header": str(header),
            "phantom_toml": str(toml), "shape": (len(z), len(y), len(x)), "voxel_mm": h,
            "origin_mm": (float(x[0]), float(y[0]), float(z[0])), "states": (c.tolist(), a.tolist()),
            "times_s": None if t is None else t.tolist()}
