"""Conventions: the projection formulas in conventions.py agree with the detector frames."""

import numpy as np
import pytest

from clrecon.core.conventions import (
    circular_difference,
    collimation_iso_mm,
    detector_coords,
    detector_frames,
    hu_to_mu,
    mu_to_hu,
)


def test_hu_round_trip():
    hu = np.array([-1000.0, 0.0, 400.0, 1500.0])
    assert np.allclose(mu_to_hu(hu_to_mu(hu)), hu)
    assert hu_to_mu(-1000.0) == 0.0


def test_collimation_table1():
    assert collimation_iso_mm(64, 0.8, 595.0, 1085.6) == pytest.approx(28.0619, abs=1e-3)


def test_detector_coords_symmetric():
    u = detector_coords(4, 1.0)
    assert np.allclose(u, [-1.5, -0.5, 0.5, 1.5])


def test_point_projects_where_the_formula_says():
    rng = np.random.default_rng(0)
    sid, sdd = 595.0, 1085.6
    beta = rng.uniform(0, 2 * np.pi, 20)
    zk = rng.uniform(-10, 10, 20)
    src, det, e_u, e_v = detector_frames(beta, zk, sid, sdd)
    p = rng.uniform(-100, 100, (20, 3))
    # ray from source through p hits the detector plane at s + t (p - s)
    normal = (det - src) / sdd
    t = sdd / np.einsum("ij,ij->i", p - src, normal)
    hit = src + t[:, None] * (p - src)
    u = np.einsum("ij,ij->i", hit - det, e_u)
    v = np.einsum("ij,ij->i", hit - det, e_v)
    x, y, z = p.T
    U = sid - (x * np.cos(beta) + y * np.sin(beta))
    assert np.allclose(u, sdd * (-x * np.sin(beta) + y * np.cos(beta)) / U)
    assert np.allclose(v, sdd * (z - zk) / U)


def test_circular_difference():
    assert circular_difference(0.95, 0.05) == pytest.approx(-0.1)
    assert circular_difference(0.05, 0.95) == pytest.approx(0.1)
    assert -0.5 <= circular_difference(0.5, 0.0) < 0.5


def test_circular_difference_bit_for_bit_the_remainder_formula():
    """The floor form gives the float64 values of ``(c - c_ref + 0.5) % 1.0 - 0.5`` (what the
    planning used until 2026-12-04): random phases, whole and half-whole differences, signed
    zeros, subnormals, values next to 0.5 and large magnitudes; NaN stays NaN."""
    rng = np.random.default_rng(7)
    c = np.concatenate([rng.uniform(-5, 5, 200_000), rng.integers(-5, 6, 1000).astype(float),
                        rng.uniform(-1e6, 1e6, 20_000), rng.uniform(-1e-9, 1e-9, 20_000),
                        np.array([0.5, -0.5, 0.0, -0.0, 1.5, -1.5, 0.49999999999999994, -0.49999999999999994,
                                  np.nextafter(0.5, 1), np.nextafter(-0.5, -1), 5e-324, -5e-324, 2.0 ** 51 + 0.5])])
    for c_ref in (rng.uniform(0, 1, c.size), 0.0, -0.0, 0.37, 0.5):
        d = np.asarray(c, np.float64) - np.asarray(c_ref, np.float64)
        want = (d + 0.5) % 1.0 - 0.5
        got = circular_difference(c, c_ref)
        assert np.array_equal(got.view(np.int64), want.view(np.int64))
    assert np.isnan(circular_difference(np.array([np.nan, np.inf, -np.inf]), 0.0)).all()
