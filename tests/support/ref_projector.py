"""Plain NumPy float64 reference of the projector's line integrals (for the tests only).

Written from the textbook formulas on the world-frame packed objects, independently of the
kernel's per-view records: the line s + t (p - s), the interval of t inside each quadric
(|M (x - c)|^2 <= 1, M = D^-1 R^T; a cylinder uses two axes plus a slab along the third),
narrowed by the clip half-spaces and the intersect cuts, minus the subtract cuts, times
|p - s| and the additive density.
"""

import numpy as np

from clrecon.simulation.phantoms import analytic as ph


def _quad_interval(q0, d, axes_mask):
    """t-interval where |q0 + t d|^2 <= 1 over the masked axes; returns (t1, t2, hit)."""
    q0m, dm = q0 * axes_mask, d * axes_mask
    A = (dm * dm).sum(-1)
    B = (q0m * dm).sum(-1)
    C = (q0m * q0m).sum(-1) - 1.0
    disc = B * B - A * C
    par = A <= 1e-300
    with np.errstate(divide="ignore", invalid="ignore"):
        sq = np.sqrt(np.maximum(disc, 0.0))
        t1 = np.where(par, -np.inf, (-B - sq) / A)
        t2 = np.where(par, np.inf, (-B + sq) / A)
    hit = np.where(par, C <= 0.0, disc > 0.0)
    return t1, t2, hit


def _local(obj, centre_sl, axes_sl, semi_sl, x0, d):
    M = obj[axes_sl].reshape(3, 3).T / obj[semi_sl][:, None]
    return (x0 - obj[centre_sl]) @ M.T, d @ M.T


def line_integrals(objects, src, points):
    """Integral of mu along the lines from ``src`` (R, 3) through ``points`` (R, 3), float64 (R,)."""
    s = np.asarray(src, np.float64)
    d = np.asarray(points, np.float64) - s
    total = np.zeros(len(s))
    for o in np.asarray(objects, np.float64):
        kind = int(o[ph.KIND])
        if kind == ph.KIND_NONE or o[ph.MU] == 0.0:
            continue
        q0, dl = _local(o, ph.CENTRE, ph.AXES, ph.SEMI, s, d)
        if kind == ph.KIND_ELLIPSOID:
            t1, t2, hit = _quad_interval(q0, dl, np.ones(3))
        else:
            t1, t2, hit = _quad_interval(q0, dl, np.array([1.0, 1.0, 0.0]))
            with np.errstate(divide="ignore", invalid="ignore"):
                ta, tb = (1.0 - q0[:, 2]) / dl[:, 2], (-1.0 - q0[:, 2]) / dl[:, 2]
            zpar = dl[:, 2] == 0.0
            inside = np.abs(q0[:, 2]) <= 1.0
            t1 = np.maximum(t1, np.where(zpar, np.where(inside, -np.inf, np.inf), np.minimum(ta, tb)))
            t2 = np.minimum(t2, np.where(zpar, np.where(inside, np.inf, -np.inf), np.maximum(ta, tb)))
        for k in range(ph.N_PLANES):
            n, dd = o[17 + 4 * k:20 + 4 * k], o[20 + 4 * k]
            g = d @ n
            h = dd - s @ n
            with np.errstate(divide="ignore", invalid="ignore"):
                t = h / g
            t2 = np.where(g > 0, np.minimum(t2, t), t2)
            t1 = np.where(g < 0, np.maximum(t1, t), t1)
            hit &= ~((g == 0) & (h < 0))
        subs = []
        for k in range(ph.N_CUTS):
            mi, cs, ca, cm = ph.cut_fields(k)
            mode = int(o[mi])
            if mode == ph.CUT_NONE:
                continue
            cq, cd = _local(o, cs, ca, cm, s, d)
            c1, c2, chit = _quad_interval(cq, cd, np.ones(3))
            c1, c2 = np.where(chit, c1, 0.0), np.where(chit, c2, 0.0)
            if mode == ph.CUT_INTERSECT:
                t1, t2, hit = np.maximum(t1, c1), np.minimum(t2, c2), hit & chit
            else:
                subs.append((c1, c2))
        length = np.maximum(t2 - t1, 0.0)
        lo, hi = t1, t2
        for c1, c2 in subs:
            length = length - np.maximum(np.minimum(hi, c2) - np.maximum(lo, c1), 0.0)
        if len(subs) == 2:
            (a1, a2), (b1, b2) = subs
            length = length + np.maximum(np.minimum(np.minimum(hi, a2), b2) - np.maximum(np.maximum(lo, a1), b1), 0.0)
        total += o[ph.MU] * np.where(hit, np.maximum(length, 0.0), 0.0) * np.linalg.norm(d, axis=-1)
    return total


def project_views_ref(objects, src, det_centre, e_u, e_v, u_mm, v_mm):
    """Float64 reference of :func:`clrecon.simulation.projector.project_views`, (m, n_rows, n_cols)."""
    objs = np.asarray(objects, np.float64)
    u, v = np.asarray(u_mm, np.float64), np.asarray(v_mm, np.float64)
    out = np.zeros((len(objs), len(v), len(u)))
    for i in range(len(objs)):
        V, U = np.meshgrid(v, u, indexing="ij")
        pts = det_centre[i] + U[..., None] * e_u[i] + V[..., None] * e_v[i]
        out[i] = line_integrals(objs[i], np.broadcast_to(src[i], pts.shape).reshape(-1, 3),
                                pts.reshape(-1, 3)).reshape(U.shape)
    return out
