"""The analytic phantom's own deformation between two states: the true motion field.

The thorax of :mod:`clrecon.simulation.phantoms.analytic` is a set of posed quadrics, so it knows
where each of its points goes: a point belongs to the innermost object that holds it (the one
deepest in the ``parents`` tree), and moves with that object's pose. Used as the ground truth of
motion estimation (the registration error of :mod:`clrecon.reconstruction.motion`, and the
motion model fitted to the true fields; docs/results/mc-study.md "True motion of the phantom").

The rule, per point p at state s0 mapped to state s1 (float64):

- **affine** (every object): local coordinates ``q = ((p - C0) R0) / S0`` (centre C, rotation
  R whose columns are the local axes, semi-axes S) are kept, ``p' = C1 + (q S1) R1^T``. The
  chest wall's AP expansion, the liver and diaphragm's descent, the heart's breathing shift and
  the lesion's path are all exact under it.
- **shell** (an ellipsoid with a child ellipsoid of the same centre and axes, the point between
  them: the LV and RV walls): along the ray from the centre the point's fraction of the wall
  thickness is kept, and the ray turns as the cavity's affine map turns it; so the wall thickens
  as the cavity empties (constant myocardial volume) and the endocardium goes exactly where the
  cavity's own map takes it (the field is continuous there). From end-systole to end-diastole the
  outer ellipsoid's affine map carries 28 % of the wall's points into the cavity, this rule keeps
  99.9 % in the wall (the other way 95 %: the misses lie at the base, whose clip plane the rule
  does not follow; tests/reconstruction/test_motion_compensation.py).
- points in no object (air) do not move (:func:`displacement`; :func:`displacement_fields` fills them).

What the rule cannot say: a uniform region's interior has no texture (the lungs, whose density
also changes with breathing, -760 to -840 HU; air; the epicardial fat and the body muscle, which
are containers whose own pose does not follow the organs moving inside them), so where such a
point goes is not defined by the images at all; by the rule a lung point would follow its
cylinder (the chest's AP expansion, no SI motion) while the dome below it descends, and air would
stay while the skin moves -- a field no image shows and no smooth model can fit.
:func:`displacement_fields` therefore fills such *textureless* points (``TEXTURELESS`` and air)
with a smooth extension of the motion around them (normalised Gaussian averages of the other
points' displacements, widening until every point is filled), the motion a perfect registration
would report there. Sliding interfaces between
textured tissues (heart/lung is textured on one side only; liver/chest wall) stay
discontinuities. Registration errors are reported inside the heart and in the body outside the
lungs.
"""

from __future__ import annotations

import numpy as np
import scipy.ndimage

from clrecon.simulation.phantoms.analytic import Phantom, inside
from clrecon.simulation.phantoms.layout import AXES, CENTRE, KIND, KIND_ELLIPSOID, SEMI

#: Objects whose interior has no texture, so that their points' motion is not observable: filled by
#: the smooth extension of :func:`displacement_fields` (air too).
TEXTURELESS = ("lung_left", "lung_right", "trachea", "epicardial_fat", "body_muscle")
#: Widths (mm) of the normalised Gaussian averages that fill textureless points, narrow first.
FILL_SIGMAS_MM = (3.0, 6.0, 12.0, 24.0, 48.0, 96.0)


def _depths(phantom: Phantom) -> np.ndarray:
    """Depth of every object in the ``parents`` tree (1 = child of air), (n_obj,) int."""
    index = {n: i for i, n in enumerate(phantom.names)}
    depth = np.zeros(len(phantom.names), np.int64)
    for i, parent in enumerate(phantom.parents):
        d, p = 1, parent
        while p != "air" and p in index:
            d += 1
            p = phantom.parents[index[p]]
        depth[i] = d
    return depth


def _shell_child(phantom: Phantom, objs: np.ndarray) -> dict:
    """{object index: child index} for ellipsoids with a child ellipsoid of the same centre and axes."""
    out = {}
    for i, parent in enumerate(phantom.parents):
        if parent not in phantom.names:
            continue
        j = phantom.names.index(parent)
        if objs[i, KIND] == KIND_ELLIPSOID and objs[j, KIND] == KIND_ELLIPSOID and j not in out \
                and np.allclose(objs[i, CENTRE], objs[j, CENTRE]) and np.allclose(objs[i, AXES], objs[j, AXES]):
            out[j] = i
    return out


def owner(phantom: Phantom, points, c: float, a: float) -> np.ndarray:
    """Index of the innermost object holding each point at state (c, a), -1 for air; (...) int64."""
    pts = np.asarray(points, dtype=np.float64)
    objs = phantom.objects(c, a)
    depth = _depths(phantom)
    best = np.full(pts.shape[:-1], -1, np.int64)
    best_depth = np.zeros(pts.shape[:-1], np.int64)
    for i in np.argsort(depth, kind="stable"):
        ins = inside(objs[i], pts) & (depth[i] >= best_depth)
        best[ins] = i
        best_depth[ins] = depth[i]
    return best


def _frame(o):
    return o[CENTRE], o[AXES].reshape(3, 3), o[SEMI]


def displacement(phantom: Phantom, points, state_from: tuple, state_to: tuple, owners=None) -> np.ndarray:
    """True displacement (mm) of ``points`` (..., 3) mm from ``state_from`` = (c, a) to ``state_to``.

    Returns (..., 3) float64: ``p(state_to) - p``. See the module docstring for the rule.
    ``owners``: :func:`owner` of the points at ``state_from`` where the caller already has it
    (the expensive part; many target states from one reference state share it).
    """
    pts = np.asarray(points, dtype=np.float64)
    if pts.shape[-1:] != (3,):
        raise ValueError(f"points: expected shape (..., 3), got {pts.shape}")
    flat = pts.reshape(-1, 3)
    o0 = phantom.objects(*state_from)
    o1 = phantom.objects(*state_to)
    who = owner(phantom, flat, *state_from) if owners is None else np.asarray(owners).reshape(-1)
    if who.shape != flat.shape[:1]:
        raise ValueError(f"owners: expected {flat.shape[0]} entries, one per point, got {who.shape}")
    shells = _shell_child(phantom, o0)
    out = np.zeros_like(flat)
    for i in np.unique(who[who >= 0]):
        sel = who == i
        p = flat[sel]
        c0, r0, s0 = _frame(o0[i])
        c1, r1, s1 = _frame(o1[i])
        if i in shells:
            ci, _, si0 = _frame(o0[shells[i]])
            si1 = o1[shells[i], SEMI]
            out[sel] = _shell_map(p, c0, r0, s0, si0, c1, r1, s1, si1) - p
        else:
            q = ((p - c0) @ r0) / s0
            out[sel] = c1 + (q * s1) @ r1.T - p
    return out.reshape(pts.shape)


def _shell_map(p, c0, r0, so0, si0, c1, r1, so1, si1):
    """Shell rule: keep the wall fraction; the ray turns with the cavity's map (see module docstring)."""
    loc = (p - c0) @ r0                                  # mm, local frame
    rad = np.linalg.norm(loc, axis=-1)
    rho_o = np.linalg.norm(loc / so0, axis=-1)           # <= 1 inside the outer surface
    rho_i = np.linalg.norm(loc / si0, axis=-1)           # >= 1 outside the inner surface
    t_i, t_o = rad / np.maximum(rho_i, 1e-300), rad / np.maximum(rho_o, 1e-300)
    frac = np.where(t_o > t_i, (rad - t_i) / np.maximum(t_o - t_i, 1e-300), 0.0)
    d = loc * (si1 / si0)                                # the cavity's affine map of the ray direction
    d /= np.maximum(np.linalg.norm(d, axis=-1, keepdims=True), 1e-300)
    ti1 = 1.0 / np.linalg.norm(d / si1, axis=-1)
    to1 = 1.0 / np.linalg.norm(d / so1, axis=-1)
    return c1 + ((ti1 + frac * (to1 - ti1))[:, None] * d) @ r1.T


def displacement_fields(phantom: Phantom, x_mm, y_mm, z_mm, state_from: tuple, states_to,
                        fill_textureless: bool = True) -> np.ndarray:
    """:func:`displacement` on the grid of voxel centres ``x_mm`` (nx,), ``y_mm`` (ny,), ``z_mm`` (nz,),
    from one state to each of ``states_to`` (n, 2) = (c, a) rows.

    Returns (n, 3, nz, ny, nx) float32, components (dx, dy, dz) mm (the layout of
    :mod:`clrecon.reconstruction.motion` fields). The points' owners are found once. With
    ``fill_textureless`` (default) the points of :data:`TEXTURELESS` objects and of air get the
    smooth extension of the others' motion (module docstring); the axes must then be uniformly
    spaced.
    """
    axes = [np.asarray(v, float) for v in (z_mm, y_mm, x_mm)]
    z, y, x = np.meshgrid(*axes, indexing="ij")
    pts = np.stack([x, y, z], -1)
    who = owner(phantom, pts, *state_from)
    states = np.atleast_2d(np.asarray(states_to, np.float64))
    out = np.empty((len(states), 3) + pts.shape[:-1], np.float32)
    known = who >= 0
    for name in TEXTURELESS:
        if name in phantom.names:
            known &= who != phantom.names.index(name)
    spacing = [float(np.diff(v).mean()) if v.size > 1 else 1.0 for v in axes]
    if fill_textureless and any(v.size > 2 and not np.allclose(np.diff(v), spacing[k]) for k, v in enumerate(axes)):
        raise ValueError("fill_textureless needs uniformly spaced axes")
    for n, (c, a) in enumerate(states):
        d = np.moveaxis(displacement(phantom, pts, state_from, (float(c), float(a)), owners=who), -1, 0)
        out[n] = _fill(d, known, spacing) if fill_textureless else d
    return out


def _fill(field, known, spacing_mm) -> np.ndarray:
    """Replace the components of ``field`` (3, ...) outside ``known`` by normalised Gaussian averages
    of the known values, with the widths of :data:`FILL_SIGMAS_MM` in turn (a point is filled by the
    narrowest width whose average has weight >= 0.1); left-overs take the mean of the known."""
    out = np.array(field, np.float64)
    have = known.astype(np.float64)
    if not have.any():
        return out
    todo = ~known
    for sig in FILL_SIGMAS_MM:
        if not todo.any():
            break
        s = [sig / h for h in spacing_mm]
        den = scipy.ndimage.gaussian_filter(have, s, mode="nearest")
        ok = todo & (den >= 0.1)
        for k in range(3):
            num = scipy.ndimage.gaussian_filter(out[k] * have, s, mode="nearest")
            out[k][ok] = num[ok] / den[ok]
        todo &= ~ok
    for k in range(3):
        out[k][todo] = out[k][known].mean()
    return out
