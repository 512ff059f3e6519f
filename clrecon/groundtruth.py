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
    """Exact in-plane fan-beam sinograms of the frozen phantom, (nz, V, C) float32.

    All slices go to the projector in one call (nz * V one-row views) so the per-call set-up
    is paid once per target.
    """
    sc = scene.scanner
    V = sc.views_per_rotation
    S = len(slices_z)
    beta = np.deg2rad(scene.scan.start_angle_deg) + 2 * np.pi * np.arange(V) / V
    u = detector_coords(sc.n_cols, sc.col_pitch_mm)
    objs = phantom.objects(c, a)
    src, det, e_u, e_v = detector_frames(np.tile(beta, S), np.repeat(np.asarray(slices_z, float), V),
                                         sc.sid_mm, sc.sdd_mm)
    objs_v = np.broadcast_to(objs, (S * V,) + objs.shape)
    out = projector.project_views(objs_v, src, det, e_u, e_v, u, np.zeros(1), rt=rt)
    return out.reshape(S, V, sc.n_cols)


def groundtruth_volumes(scene, slices_z: np.ndarray, targets, rt=None, progress=None, skip=()):
    """Ground-truth CT of every target, yielded as ``(i, j, (nz, ny, nx) float32 HU)``.

    One target at a time, so a caller can write it out and keep memory bounded; targets whose
    flat index ``i * n_resp + j`` is in ``skip`` (already done) are left out.
    """
    from .reconstruct import fbp_batched

    rc = scene.recon
    geom = fbp_mod.FanBeamGeometry.from_scene(scene)
    phantom = Phantom(scene.phantom)
    for i, c in enumerate(targets.cardiac):
        for j, a in enumerate(targets.resp):
            if i * len(targets.resp) + j in skip:
                continue
            sino = groundtruth_sinograms(scene, phantom, c, a, slices_z, rt=rt)
            yield i, j, fbp_batched(sino, geom, rc.filter, scene.phantom.mu_water_per_mm)
            if progress is not None:
                progress.update(1)


def phantom_truth_volumes(scene, slices_z: np.ndarray, targets, supersample: int = 2, rt=None, skip=()):
    """The analytic phantom voxelised at every target, yielded as ``(i, j, (nz, ny, nx) float32 HU)``."""
    rc = scene.recon
    phantom = Phantom(scene.phantom)
    x = voxel_coords(rc.nx, rc.voxel_mm)
    y = voxel_coords(rc.ny, rc.voxel_mm)
    for i, c in enumerate(targets.cardiac):
        for j, a in enumerate(targets.resp):
            if i * len(targets.resp) + j in skip:
                continue
            mu = phantom.voxelise(c, a, x, y, np.asarray(slices_z), supersample=supersample, rt=rt)
            yield i, j, mu_to_hu(mu, scene.phantom.mu_water_per_mm).astype(np.float32)


def lv_region_mask(phantom: Phantom, c: float, a: float, x_mm, y_mm, z_mm, margin_mm: float = 6.0,
                   rt=None) -> np.ndarray:
    """The phantom's LV blood-pool object at (c, a) grown by ``margin_mm``, as a (nz, ny, nx) bool mask.

    The region in which :func:`clrecon.metrics.blood_pool_volume_ml` counts contrast-enhanced
    voxels: it follows the heart as it breathes and beats, and the margin leaves room for a
    reconstruction whose cavity is blurred or displaced by motion.
    """
    from . import phantom as ph

    objs = phantom.objects(c, a)
    row = objs[phantom.names.index("lv_blood")][None].copy()
    row[0, ph.MU] = 1.0
    row[0, ph.SEMI] += margin_mm
    planes = row[0, ph.PLANES].reshape(ph.N_PLANES, 4)
    active = np.linalg.norm(planes[:, :3], axis=1) > 0
    planes[active, 3] += margin_mm * np.linalg.norm(planes[active, :3], axis=1)
    row[0, ph.PLANES] = planes.ravel()
    mu = projector.voxelise_objects(row, np.asarray(x_mm), np.asarray(y_mm), np.asarray(z_mm), supersample=1, rt=rt)
    return mu > 0.5
