"""Random analytic-phantom objects (ellipsoids and cylinders with planes and cuts) for the projector
tests, in the phantom record layout of clrecon.simulation.phantoms.analytic."""

import numpy as np

from clrecon.simulation.phantoms import analytic as ph


def random_rotation(rng):
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q *= np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] *= -1
    return q


def make_object(kind, mu, centre, axes, semi, planes=(), cuts=()):
    o = np.zeros(ph.STRIDE)
    o[ph.KIND], o[ph.MU] = kind, mu
    o[ph.CENTRE], o[ph.AXES], o[ph.SEMI] = centre, np.asarray(axes).reshape(9), semi
    o[20] = o[24] = 1.0
    for k, (n, d) in enumerate(planes):
        o[17 + 4 * k:20 + 4 * k], o[20 + 4 * k] = n, d
    for k in range(ph.N_CUTS):
        mi, cs, ca, cm = ph.cut_fields(k)
        if k < len(cuts):
            mode, cc, cax, csemi = cuts[k]
            o[mi], o[cs], o[ca], o[cm] = mode, cc, np.asarray(cax).reshape(9), csemi
        else:
            o[ca], o[cm] = np.eye(3).reshape(9), 1.0
    return o


def random_objects(rng, n):
    objs = []
    for _ in range(n):
        kind = rng.choice([ph.KIND_ELLIPSOID, ph.KIND_CYLINDER])
        centre = rng.uniform(-80, 80, 3)
        semi = rng.uniform(5, 60, 3)
        planes = []
        for _ in range(rng.integers(0, 3)):
            nrm = rng.normal(size=3)
            nrm /= np.linalg.norm(nrm)
            planes.append((nrm, nrm @ centre + rng.uniform(-0.3, 0.8) * semi.min()))
        cuts = []
        for _ in range(rng.integers(0, 3)):
            mode = rng.choice([ph.CUT_SUBTRACT, ph.CUT_INTERSECT])
            size = rng.uniform(20, 70, 3) if mode == ph.CUT_INTERSECT else rng.uniform(5, 40, 3)
            cuts.append((mode, centre + rng.uniform(-20, 20, 3), random_rotation(rng), size))
        objs.append(make_object(kind, rng.uniform(-0.02, 0.03), centre, random_rotation(rng), semi, planes, cuts))
    return np.array(objs)
