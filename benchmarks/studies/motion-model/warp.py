"""A reference-frame volume warped by the motion model to other states (OpenCL, ``mc_warp.cl`` here).

Study code (the model-based correction variant, :mod:`correction`), outside the wheel: the
shipped ``mc`` method does not warp volumes. The kernel is built from this folder
(``Runtime.program``'s ``_folder``) and includes the package's ``kernels/motion_grid.h``.

``out(x) = vol(x_r)`` with ``x_r + u(x_r; s) = x``: the volume as it would look at state s, on the
reconstruction's in-plane grid at slices ``out_z``. The model-based correction step needs the
model image at every row's state (docs/motion-model.md "The method" (step 6)); states are
warped in batches so that a batch's fields fit :data:`BATCH_BYTES`.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from clrecon.core.runtime import get_runtime
from clrecon.reconstruction.motion.backproject import INVERSION_STEPS
from clrecon.reconstruction.motion.model import FieldGrid, MotionModel, sample

#: The folder of ``mc_warp.cl``.
HERE = Path(__file__).resolve().parent
#: Fixed local size (x, y) of the kernel.
LOCAL_SIZE = (8, 8)
#: Bytes of per-state fields uploaded per launch.
BATCH_BYTES = 256 << 20


def _check(volume, model: MotionModel, states, out_z, volume_grid):
    v = np.asarray(volume)
    vg = model.grid if volume_grid is None else volume_grid
    g = model.grid
    if (vg.nx, vg.ny) != (g.nx, g.ny) or vg.voxel_mm != g.voxel_mm:
        raise ValueError("volume_grid: must share the model grid's in-plane grid")
    if v.shape != vg.shape:
        raise ValueError(f"volume: expected its grid's shape {vg.shape} = (nz, ny, nx), got {v.shape}")
    if not np.all(np.isfinite(v)):
        raise ValueError("volume: must be finite")
    s = np.atleast_2d(np.asarray(states, np.float64))
    if s.ndim != 2 or s.shape[1] != 2:
        raise ValueError(f"states: expected (n, 2) = (c, a) rows, got {s.shape}")
    z = np.atleast_1d(np.asarray(out_z, np.float64))
    if z.ndim != 1 or not np.all(np.isfinite(z)):
        raise ValueError("out_z: expected finite slice positions (S,)")
    return v, s, z, vg


def warp_reference(volume, model: MotionModel, states, out_z, iterations: int = INVERSION_STEPS,
                   volume_grid: FieldGrid | None = None) -> np.ndarray:
    """Float64 NumPy reference of :func:`warp`: (n, S, ny, nx)."""
    v, s, z, vg = _check(volume, model, states, out_z, volume_grid)
    g = model.grid
    x, y, _ = g.coords()
    Z, Y, X = np.meshgrid(z, y, x, indexing="ij")
    pts = np.stack([X, Y, Z], -1)
    out = np.empty((len(s),) + Z.shape)
    for n, (c, a) in enumerate(s):
        xr = model.inverse_points(pts, c, a, iterations)
        out[n] = sample(v, vg, xr)
    return out


def warp(volume, model: MotionModel, states, out_z, iterations: int = INVERSION_STEPS, runtime=None,
         volume_grid: FieldGrid | None = None) -> np.ndarray:
    """``volume`` in the reference frame, seen at each state (n, 2): (n, S, ny, nx) float32.

    ``volume`` (nz, ny, nx) lies on ``volume_grid`` (default the model's grid): the model's in-plane
    grid with z planes of its own (a model image wants finer z than the motion field).
    """
    v, s, z, vg = _check(volume, model, states, out_z, volume_grid)
    rt = runtime or get_runtime()
    g = model.grid
    kern = rt.kernel("mc_warp.cl", "warp_volume", LX=LOCAL_SIZE[0], LY=LOCAL_SIZE[1], NINV=int(iterations),
                     _fast=True, _folder=HERE)
    S = len(z)
    out = np.empty((len(s), S, g.ny, g.nx), np.float32)
    per_state = 3 * int(np.prod(g.shape)) * 4
    batch = max(1, BATCH_BYTES // per_state)
    d_vol = rt.to_device(v, np.float32, "volume")
    d_z = rt.to_device(z, np.float32)
    basis = model.basis.values(s[:, 0], s[:, 1]).astype(np.float32)
    lx, ly = LOCAL_SIZE
    try:
        for b0 in range(0, len(s), batch):
            b1 = min(len(s), b0 + batch)
            fields = np.tensordot(basis[b0:b1], model.fields, axes=(1, 0))  # (b, 3, nz, ny, nx)
            d_f = rt.to_device(fields, np.float32, "state fields")
            d_out = rt.empty((b1 - b0, S, g.ny, g.nx))
            ev = kern(rt.queue, (-(-g.nx // lx) * lx, -(-g.ny // ly) * ly, (b1 - b0) * S), LOCAL_SIZE + (1,),
                      d_vol, d_f, d_z, d_out, np.int32(g.nx), np.int32(g.ny), np.int32(g.nz),
                      np.float32(g.voxel_mm), np.float32(g.z0_mm), np.float32(1.0 / g.dz_mm), np.int32(S),
                      np.int32(b1 - b0), np.int32(vg.nz), np.float32(vg.z0_mm), np.float32(1.0 / vg.dz_mm))
            out[b0:b1] = rt.from_device(d_out, (b1 - b0, S, g.ny, g.nx), wait_for=[ev])
            d_f.release()
            d_out.release()
    finally:
        d_vol.release()
        d_z.release()
    return out
