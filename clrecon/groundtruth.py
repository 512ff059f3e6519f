"""Ground truth for each target (stage 9 of the pipeline, beside metrics).

Two truths per target (c*, a*) (DESIGN.md section 4, "Ground truth and metrics"):

- **ground truth CT** (what the metrics compare against): the phantom frozen at (c*, a*),
  exact *in-plane* fan-beam line integrals of each slice (a one-row detector whose source
  sits in the slice plane, all ``views_per_rotation`` views), reconstructed with the same FBP,
  filter and grid as the 5DCT. This isolates motion and interpolation error from the
  resolution of FBP itself.
- **phantom truth**: the analytic phantom voxelised at (c*, a*) with sub-voxel supersampling,
  in HU — the "XCAT phantom" column of the paper's figures.

Arrays are ``(n_cardiac, n_resp, nz, ny, nx)`` float32 HU.
"""

from __future__ import annotations

import numpy as np

from . import fbp as fbp_mod
from . import projector
from .conventions import detector_coords, detector_frames, mu_to_hu, voxel_coords
from .phantom import Phantom


def groundtruth_sinograms(scene, phantom: Phantom, c: float, a: float, slices_z: np.ndarray, rt=None) -> np.ndarray:
    """Exact in-plane fan-beam sinograms of the frozen phantom, (nz, V, C) float32."""
    sc = scene.scanner
    V = sc.views_per_rotation
    beta = np.deg2rad(scene.scan.start_angle_deg) + 2 * np.pi * np.arange(V) / V
    u = detector_coords(sc.n_cols, sc.col_pitch_mm)
    objs = phantom.objects(c, a)
    out = np.empty((len(slices_z), V, sc.n_cols), np.float32)
    for i, z in enumerate(slices_z):
        src, det, e_u, e_v = detector_frames(beta, np.full(V, z), sc.sid_mm, sc.sdd_mm)
        objs_v = np.broadcast_to(objs, (V,) + objs.shape)
        out[i] = projector.project_views(objs_v, src, det, e_u, e_v, u, np.zeros(1), rt=rt)[:, 0, :]
    return out


def groundtruth_volumes(scene, slices_z: np.ndarray, targets, rt=None, progress=None) -> np.ndarray:
    """Ground-truth CT for every target, (n_c, n_r, nz, ny, nx) float32 HU."""
    from .reconstruct import fbp_batched

    rc = scene.recon
    geom = fbp_mod.FanBeamGeometry.from_scene(scene)
    phantom = Phantom(scene.phantom)
    n_c, n_r = targets.shape
    out = np.empty((n_c, n_r, len(slices_z), rc.ny, rc.nx), np.float32)
    for i, c in enumerate(targets.cardiac):
        for j, a in enumerate(targets.resp):
            sino = groundtruth_sinograms(scene, phantom, c, a, slices_z, rt=rt)
            out[i, j] = fbp_batched(sino, geom, rc.filter, scene.phantom.mu_water_per_mm)
            if progress is not None:
                progress.update(1)
    return out


def phantom_truth_volumes(scene, slices_z: np.ndarray, targets, supersample: int = 2) -> np.ndarray:
    """The analytic phantom voxelised at every target, (n_c, n_r, nz, ny, nx) float32 HU."""
    rc = scene.recon
    phantom = Phantom(scene.phantom)
    x = voxel_coords(rc.nx, rc.voxel_mm)
    y = voxel_coords(rc.ny, rc.voxel_mm)
    n_c, n_r = targets.shape
    out = np.empty((n_c, n_r, len(slices_z), rc.ny, rc.nx), np.float32)
    for i, c in enumerate(targets.cardiac):
        for j, a in enumerate(targets.resp):
            mu = phantom.voxelise(c, a, x, y, np.asarray(slices_z), supersample=supersample)
            out[i, j] = mu_to_hu(mu, scene.phantom.mu_water_per_mm)
    return out
