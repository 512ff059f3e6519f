"""``recon.cardiac_distance_scale`` (s): the cardiac axis times s in the phase-space distance and in
barycentric's triangulation. s = 1 is today's behaviour bit for bit; s changes which points are
nearest and which triangle holds the target, never the kernel weights or the barycentric
coordinates' exactness (a triangle reproduces a linear function of (c, a) whatever it is)."""

from __future__ import annotations

import numpy as np
import pytest

from clrecon.config.scene import load_scene
from clrecon.core.errors import SceneError
from clrecon.reconstruction import reconstruct
from clrecon.reconstruction.interpolation import weights as ip

TARGETS = np.array([[c, a] for c in (0.0, 0.2, 0.4, 0.6, 0.8) for a in np.arange(0.05, 1.0, 0.1)])


def _groups(seed=3):
    rng = np.random.default_rng(seed)
    c, a = rng.random(300), rng.random(300)
    return c, a, np.array([0, 40, 41, 43, 120, 300])


@pytest.mark.parametrize("value", [0.0, -1.0])
def test_scene_rejects_non_positive_scale(value):
    with pytest.raises(SceneError, match="recon.cardiac_distance_scale"):
        load_scene("tiny").replace(recon={"cardiac_distance_scale": value})


def test_default_is_one_and_reaches_the_weight_options():
    s = load_scene("tiny")
    assert s.recon.cardiac_distance_scale == 1.0
    cfg = reconstruct.ReconstructionConfig.from_scene(s.replace(recon={"cardiac_distance_scale": 2.5}))
    targets = reconstruct.Targets(tuple(s.cardiac_targets), tuple(s.resp_targets))
    assert reconstruct.weight_options(cfg, targets)["cardiac_distance_scale"] == 2.5


@pytest.mark.parametrize("method", ["barycentric", "local_linear", "nearest"])
def test_scale_one_is_bitwise_the_default(method):
    c, a, off = _groups()
    W0 = ip.batch_weights(method, c, a, off, TARGETS)
    W1 = ip.batch_weights(method, c, a, off, TARGETS, cardiac_distance_scale=1.0)
    np.testing.assert_array_equal(W0.index, W1.index)
    np.testing.assert_array_equal(W0.weight, W1.weight)


def test_bad_scale_is_a_value_error():
    c, a, off = _groups()
    for s in (0.0, -2.0, np.inf):
        with pytest.raises(ValueError, match="cardiac_distance_scale"):
            ip.batch_weights("nearest", c, a, off, TARGETS, cardiac_distance_scale=s)


def test_scale_changes_which_point_is_nearest():
    # target (0.4, 0.5): A is 0.1 away in c, B 0.15 away in amplitude
    c, a = np.array([0.5, 0.4]), np.array([0.5, 0.65])
    t = np.array([[0.4, 0.5]])
    assert ip.method_weights("nearest", c, a, t).index[0, 0] == 0
    assert ip.method_weights("nearest", c, a, t, cardiac_distance_scale=2.0).index[0, 0] == 1
    assert ip.method_weights("nearest", c, a, t, cardiac_distance_scale=1.4).index[0, 0] == 0


@pytest.mark.parametrize("scale", [0.25, 1.0, 4.0])
def test_barycentric_reproduces_a_linear_field_for_any_scale(scale):
    # points on a periodic-beat lattice (5 cardiac lines 0.2 apart), amplitudes scattered;
    # a field linear in (c, a) away from the wrap is reproduced exactly by any triangle
    rng = np.random.default_rng(5)
    lines = (0.07 + 0.2 * np.arange(5)) % 1.0
    c = np.repeat(lines, 9)
    a = rng.random(c.size)
    targets = np.array([[cc, aa] for cc in (0.2, 0.4, 0.6) for aa in (0.3, 0.5, 0.7)])
    W = ip.batch_weights("barycentric", c, a, [0, c.size], targets, cardiac_distance_scale=scale)
    tri = W.branch[0] == 0
    # s < 1 squeezes c: triangles then reach lines > 0.3 away in c, which the |dc| limit
    # rejects (segment fallback); at s >= 1 every target here lies in an accepted triangle
    assert tri.all() if scale >= 1 else tri.any()
    f = 3.0 * c - 2.0 * a + 1.0
    got = (W.weight[0] * f[W.index[0]]).sum(axis=-1)
    np.testing.assert_allclose(got[tri], (3.0 * targets[:, 0] - 2.0 * targets[:, 1] + 1.0)[tri], atol=1e-9)
    np.testing.assert_allclose(W.weight[0].sum(axis=-1), 1.0, atol=1e-12)


def test_scale_changes_the_triangles_and_local_linear_neighbours():
    c, a, off = _groups(7)
    for method in ("barycentric", "local_linear"):
        W1 = ip.batch_weights(method, c, a, off, TARGETS)
        W4 = ip.batch_weights(method, c, a, off, TARGETS, cardiac_distance_scale=4.0)
        assert not np.array_equal(W1.index, W4.index), method

