"""Cylindrical (equiangular) detector and flying focal spot: projector, geometry, references.

The projector's line integrals to curved cells are checked against an independent float64
computation: the cell centres are built here from the definition (an arc of radius SDD centred
on the focal centre, gamma_c = (c - central_col) col_pitch / SDD, rows at
(r - central_row) row_pitch), and the chords through the quadrics by ``tests/ref_projector.py``
(textbook formulas), never through the flat-equivalent cells the projector uses.
"""

import numpy as np
import pytest
from ref_projector import line_integrals
from test_projector import random_objects, tol

from clrecon.core.detector import CylindricalDetector, spot_shift_in_frame
from clrecon.simulation import projector
from clrecon.simulation.phantoms import analytic as ph

SID, SDD = 595.0, 1085.6


def curved_det(n_cols=96, n_rows=12, col_pitch=7.5, row_pitch=16.0, central_col=None, central_row=None):
    cc = (n_cols - 1) / 2 + 0.25 if central_col is None else central_col
    cr = (n_rows - 1) / 2 if central_row is None else central_row
    return CylindricalDetector(sid_mm=SID, sdd_mm=SDD, n_cols=n_cols, n_rows=n_rows, col_pitch_mm=col_pitch,
                               row_pitch_mm=row_pitch, central_col=cc, central_row=cr)


def curved_cells(det, src, centre, e_u, e_v):
    """Cell centres (m, R, C, 3) of the arc, float64, from the definition."""
    n = (centre - src) / np.linalg.norm(centre - src, axis=-1, keepdims=True)
    g = (np.arange(det.n_cols) - det.central_col) * det.col_pitch_mm / det.sdd_mm
    v = (np.arange(det.n_rows) - det.central_row) * det.row_pitch_mm
    return (src[:, None, None, :] + det.sdd_mm * (np.cos(g)[None, None, :, None] * n[:, None, None, :]
                                                  + np.sin(g)[None, None, :, None] * e_u[:, None, None, :])
            + v[None, :, None, None] * e_v[:, None, None, :])


def reference(objs, spot, cells):
    m = len(cells)
    out = np.zeros(cells.shape[:3])
    for i in range(m):
        pts = cells[i].reshape(-1, 3)
        out[i] = line_integrals(objs[i], np.broadcast_to(spot[i], pts.shape), pts).reshape(cells.shape[1:3])
    return out


def project_curved(det, objs, beta, z, shift=(0.0, 0.0, 0.0), **kw):
    frames, (u, v, vs) = projector.spot_frames(det, beta, z, np.asarray(shift, float))
    return projector.project_views(objs, *frames, u, v, v_scale=vs, **kw)


def _spot(det, beta, z, shift):
    src, centre, eu, ev = det.frames(beta, z)
    n = (centre - src) / SDD
    return src + shift[0] * n + shift[1] * eu + shift[2] * ev, (src, centre, eu, ev)


@pytest.mark.parametrize("seed,shift", [(0, (0.0, 0.0, 0.0)), (1, (0.0, 0.0, 0.0)), (2, (0.4, -0.7, 0.6))])
def test_random_quadrics_on_curved_cells_match_float64_chords(seed, shift):
    """Random quadrics (both kinds, planes, cuts) on a quarter-offset arc, with and without a spot shift."""
    rng = np.random.default_rng(seed)
    m = 3
    det = curved_det()
    objs = np.broadcast_to(random_objects(rng, 10), (m, 10, ph.STRIDE))
    beta, z = rng.uniform(0, 2 * np.pi, m), rng.uniform(-40, 40, m)
    p = project_curved(det, objs, beta, z, shift)
    spot, fr = _spot(det, beta, z, np.asarray(shift))
    r = reference(objs, spot, curved_cells(det, *fr))
    assert np.count_nonzero(r) > 0.08 * r.size
    err = np.abs(p - r)
    assert np.all(err <= tol("kernel_atol") + tol("kernel_rtol") * np.abs(r)), err.max()
    q = project_curved(det, objs, beta, z, shift, cull=False)
    np.testing.assert_array_equal(p, q)


#: The phantom's line integrals on curved cells: relative error for rays that cross tissue
#: (r >= 0.5, i.e. >= 25 mm of water), absolute for the grazing rays at the body outline.
CURVED_RTOL = 1e-5


def test_phantom_on_curved_detector_within_1e_5_relative():
    pht = ph.Phantom()
    rng = np.random.default_rng(5)
    m = 3
    det = curved_det(n_cols=672, n_rows=16, col_pitch=1.1, row_pitch=1.0)
    beta, z = rng.uniform(0, 2 * np.pi, m), rng.uniform(-40, 40, m)
    objs = pht.objects_batch(rng.uniform(0, 1, m), rng.uniform(0, 1, m))
    p = project_curved(det, objs, beta, z)
    spot, fr = _spot(det, beta, z, np.zeros(3))
    cells = curved_cells(det, *fr)
    cols, rows = np.arange(2, 672, 7), np.array([0, 5, 8, 15])
    r = reference(objs, spot, cells[:, rows][:, :, cols])
    pc = p[:, rows][:, :, cols].astype(np.float64)
    thick = r >= 0.5
    assert thick.sum() > 0.4 * r.size and r.max() > 3.0
    rel = np.abs(pc - r)[thick] / r[thick]
    assert rel.max() <= CURVED_RTOL, rel.max()
    assert np.abs(pc - r).max() <= tol("phantom_atol")


def test_curved_differs_from_flat_where_it_should():
    """Guard: the same objects on flat cells at the same u give other integrals (the test can fail)."""
    rng = np.random.default_rng(0)
    det = curved_det()
    objs = np.broadcast_to(random_objects(rng, 10), (2, 10, ph.STRIDE))
    beta, z = np.array([0.3, 2.0]), np.array([0.0, 10.0])
    p = project_curved(det, objs, beta, z)
    src, centre, eu, ev = det.frames(beta, z)
    flat = projector.project_views(objs, src, centre, eu, ev, det.u_mm(), det.v_mm())
    assert np.abs(p - flat).max() > 1e-2


def test_spot_shift_frame():
    sh = spot_shift_in_frame(np.array([[0.001, 0.5, 0.3]]), SID)[0]
    rho = SID + 0.5
    assert sh[0] == pytest.approx(SID - rho * np.cos(0.001))
    assert sh[1] == pytest.approx(rho * np.sin(0.001)) and sh[2] == 0.3
