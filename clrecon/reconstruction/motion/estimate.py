"""Motion fields of every target from a first-pass 5D reconstruction, registered in two separable steps.

A first-pass 5D image at the clinical pitch carries streaks that differ from target to target
(each target takes other rows), while its anatomy at a given cardiac phase or amplitude is the
same; registering one streaked target to another follows the streaks as well as the anatomy
(docs/results/mc-study.md "Registration"). So the volumes are averaged before they are registered:

1. **breathing**: the targets of each amplitude a_j averaged over the cardiac phases (the beat is
   blurred, the streaks of 5 targets averaged), each registered to the reference amplitude's
   average: u_resp(x; a_j);
2. **beat**: every target brought to the reference amplitude by its amplitude's u_resp, averaged
   over the amplitudes at each cardiac phase c_i, each registered to the reference phase's
   average: u_card(x; c_i);
3. u(x; c_i, a_j) = u_resp(x; a_j) + u_card(x; c_i) -- the additive model of
   :mod:`clrecon.reconstruction.motion.model`, which is then fitted to these fields.

Each step may use its own registration (``cfg`` and ``beat_cfg``): the ``mc`` method registers the
breathing with Lucas-Kanade and the beat with TV-L1 by default (docs/motion-model.md "Knobs").

(n_resp - 1) + (n_cardiac - 1) registrations instead of n_cardiac n_resp - 1 (13 against 49 for the
50 targets). Shapes: volumes (n_c, n_r, nz, ny, nx) HU on the model grid; fields (n_c n_r, 3, nz,
ny, nx) float32 mm, target order cardiac-major as ``Targets.pairs``.
"""

from __future__ import annotations

import numpy as np

from clrecon.reconstruction.motion.confidence import shrink_field
from clrecon.reconstruction.motion.model import FieldGrid, sample
from clrecon.reconstruction.motion.registration import FlowConfig, register_to_reference


def to_reference(volume, field, grid: FieldGrid) -> np.ndarray:
    """``volume`` (nz, ny, nx) at a state, seen in the reference frame: ``volume(x + u(x))`` on the grid."""
    x, y, z = grid.coords()
    Y, X = np.meshgrid(y, x, indexing="ij")
    out = np.empty(grid.shape, np.float32)
    for k, zk in enumerate(z):  # slice by slice: the float64 points of a whole paper-scale grid would be GBs
        pts = np.stack([X, Y, np.full_like(X, zk)], -1) + np.moveaxis(np.asarray(field[:, k], np.float64), 0, -1)
        out[k] = sample(volume, grid, pts)
    return out


def shrunk(fields, images, reference: int, grid: FieldGrid, shrink, local: bool = False) -> tuple[np.ndarray, list]:
    """Each of ``fields`` (n, 3, nz, ny, nx), registered from ``images[reference]`` to ``images[i]``
    (n, nz, ny, nx) HU, shrunk towards zero where the fixed image cannot show it
    (:func:`clrecon.reconstruction.motion.confidence.shrink_field`); ``shrink``: (window radius,
    HU window); ``local``: under the local prior (the share of the images' difference the field
    explains, :func:`clrecon.reconstruction.motion.confidence.local_prior_scale`). Returns (fields,
    one info dict per non-reference field)."""
    radius, hu_window = shrink
    spacing = (grid.voxel_mm, grid.voxel_mm, grid.dz_mm)
    out = np.array(fields, np.float32)
    infos = []
    for i in range(len(out)):
        if i == reference:
            continue
        out[i], info = shrink_field(images[reference], to_reference(images[i], out[i], grid), out[i], spacing,
                                    radius, hu_window, moving=images[i] if local else None)
        infos.append(info)
    return out, infos


def separable_fields(volumes, reference: tuple, grid: FieldGrid, cfg: FlowConfig | None = None,
                     progress=None, pool=None, shrink: tuple | None = None,
                     beat_cfg: FlowConfig | None = None) -> tuple[np.ndarray, dict]:
    """Fields u(x_ref; c_i, a_j) of every target from the two registration steps (module docstring).

    Parameters
    ----------
    volumes : (n_c, n_r, nz, ny, nx) first-pass HU volumes on ``grid``
    reference : (i_ref, j_ref) indices of the reference target (cardiac, amplitude)
    grid : FieldGrid of the volumes (uniform slices)
    cfg : FlowConfig, or a plugged-in registration's config (:mod:`clrecon.reconstruction.motion.registration`):
        the breathing step's, and the beat's unless ``beat_cfg`` is given
    progress : optional ``update(n)`` counter, one step per registration
    pool : optional process pool running each step's registrations at once (same bits)
    shrink : optional (window radius, (lo, hi) HU): each step's fields shrunk towards zero where its
        fixed image cannot show the motion (:func:`shrunk`), before the next step uses them; the
        beat's under the local prior (module docstring)

    Returns
    -------
    (fields (n_c n_r, 3, nz, ny, nx) float32, parts) with ``parts["resp"]`` (n_r, 3, ...) and
    ``parts["cardiac"]`` (n_c, 3, ...), and with ``shrink`` ``parts["shrink"]``: the measured noise
    and mean gain of each shrunk field (:func:`clrecon.reconstruction.motion.confidence.shrink_voxels`).
    """
    parts = separable_parts(volumes, reference, grid, cfg, progress=progress, pool=pool, shrink=shrink)
    card, resp = parts["cardiac"], parts["resp"]
    fields = (card[:, None] + resp[None, :]).reshape((len(card) * len(resp), 3) + grid.shape)
    return fields, parts


def separable_parts(volumes, reference: tuple, grid: FieldGrid, cfg: FlowConfig | None = None,
                    progress=None, pool=None, shrink: tuple | None = None,
                    beat_cfg: FlowConfig | None = None) -> dict:
    """The two steps' fields of :func:`separable_fields`, not summed: ``{"resp": (n_r, 3, nz, ny, nx),
    "cardiac": (n_c, 3, nz, ny, nx)}`` float32 mm (the target (i, j)'s field is ``cardiac[i] + resp[j]``;
    :func:`clrecon.reconstruction.motion.model.fit_separable_model` fits them without that sum's
    n_c n_r fields), with ``"shrink"`` where ``shrink`` is given. Parameters as :func:`separable_fields`."""
    v = np.asarray(volumes, np.float32)
    if v.ndim != 5 or v.shape[2:] != grid.shape:
        raise ValueError(f"volumes: expected (n_c, n_r) + {grid.shape}, got {v.shape}")
    nc, nr = v.shape[:2]
    i_ref, j_ref = reference
    if not (0 <= i_ref < nc and 0 <= j_ref < nr):
        raise ValueError(f"reference = {reference!r}: must index the ({nc}, {nr}) targets")
    spacing = (grid.voxel_mm, grid.voxel_mm, grid.dz_mm)
    resp_avg = v.mean(axis=0)
    resp = register_to_reference(resp_avg, j_ref, spacing, cfg=cfg, progress=progress, pool=pool)
    infos: list = []
    if shrink is not None:
        resp, infos = shrunk(resp, resp_avg, j_ref, grid, shrink)
    card_avg = np.zeros((nc,) + grid.shape, np.float64)
    for j in range(nr):
        for i in range(nc):
            card_avg[i] += to_reference(v[i, j], resp[j], grid) if j != j_ref else v[i, j]
    card_avg /= nr
    card = register_to_reference(card_avg.astype(np.float32), i_ref, spacing,
                                 cfg=cfg if beat_cfg is None else beat_cfg, progress=progress, pool=pool)
    parts = {"resp": resp, "cardiac": card}
    if shrink is not None:
        card, more = shrunk(card, card_avg.astype(np.float32), i_ref, grid, shrink, local=True)
        parts.update(cardiac=card, shrink=infos + more)
    return parts
