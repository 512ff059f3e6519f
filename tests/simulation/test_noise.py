"""Noise: flat-field statistics against theory, per-projection determinism, photon starvation."""

import numpy as np
import pytest

from clrecon.config.scene import NoiseConfig
from clrecon.simulation.noise import N_FLOOR, add_noise

# Flat field: M samples of a line integral P with I0 photons -> lam = I0 exp(-P) expected counts.
I0, P, SIGMA_E = 1.0e4, 2.0, 20.0
SHAPE = (40, 50, 50)  # M = 100 000 samples
M = int(np.prod(SHAPE))
# Tolerance: 5 standard errors of the estimate (a deterministic seed, but no cherry-picking).
K_SE = 5.0


def _flat(cfg):
    p = np.full(SHAPE, P, dtype=np.float32)
    return add_noise(p, np.arange(SHAPE[0]), cfg)


@pytest.mark.parametrize("sigma_e", [0.0, SIGMA_E])
def test_flat_field_counts_match_poisson_plus_electronic(sigma_e):
    cfg = NoiseConfig(i0_photons=I0, electronic_sigma=sigma_e, seed=3)
    noisy = _flat(cfg)
    assert noisy.dtype == np.float32 and noisy.shape == SHAPE
    counts = I0 * np.exp(-noisy.astype(np.float64))  # the clamp never acts at lam ~ 1353
    lam = I0 * np.exp(-P)
    var = lam + sigma_e ** 2
    # Mean of N: standard error sqrt(var / M).
    assert abs(counts.mean() - lam) < K_SE * np.sqrt(var / M)
    # Variance of N: standard error ~ var sqrt(2 / (M - 1)) (near-Gaussian at lam >> 1).
    assert abs(counts.var(ddof=1) - var) < K_SE * var * np.sqrt(2.0 / (M - 1))
    # Line integrals: delta method, Var(p) = var / lam^2.
    assert noisy.astype(np.float64).var() == pytest.approx(var / lam ** 2, rel=K_SE * np.sqrt(2.0 / M))


def test_electronic_noise_is_distinguishable():
    """The variance test above can fail: sigma_e = 20 adds 400 to a Poisson variance of 1353."""
    a = I0 * np.exp(-_flat(NoiseConfig(i0_photons=I0, electronic_sigma=0.0, seed=3)).astype(np.float64))
    b = I0 * np.exp(-_flat(NoiseConfig(i0_photons=I0, electronic_sigma=SIGMA_E, seed=3)).astype(np.float64))
    assert b.var() - a.var() > 300


def test_per_projection_seeding_independent_of_chunking_and_order():
    rng = np.random.default_rng(0)
    p = rng.uniform(0.0, 5.0, (23, 4, 7)).astype(np.float32)
    idx = np.arange(100, 123)
    cfg = NoiseConfig(seed=11)
    whole = add_noise(p, idx, cfg)
    pieces = np.concatenate([add_noise(p[a:b], idx[a:b], cfg) for a, b in [(0, 5), (5, 6), (6, 23)]])
    np.testing.assert_array_equal(whole, pieces)
    rev = add_noise(p[::-1], idx[::-1], cfg)[::-1]
    np.testing.assert_array_equal(whole, rev)
    # The projection index, not the position in the batch, seeds the noise.
    assert not np.array_equal(whole, add_noise(p, idx + 1, cfg))
    assert not np.array_equal(whole, add_noise(p, idx, NoiseConfig(seed=12)))


def test_photon_starvation_is_finite():
    cfg = NoiseConfig(i0_photons=1.0e3, electronic_sigma=5.0, seed=1)
    p = np.full((3, 8, 8), 40.0, dtype=np.float32)  # exp(-40) I0 ~ 4e-15 photons
    noisy = add_noise(p, np.arange(3), cfg)
    assert np.all(np.isfinite(noisy))
    assert noisy.max() <= np.float32(np.log(1.0e3 / N_FLOOR)) + 1e-5
    assert noisy.max() == pytest.approx(np.log(1.0e3), rel=1e-6)  # clamped cells sit at the ceiling


def test_bad_inputs():
    cfg = NoiseConfig()
    with pytest.raises(ValueError, match="shape"):
        add_noise(np.zeros((4, 4), np.float32), np.arange(4), cfg)
    with pytest.raises(ValueError, match="proj_index"):
        add_noise(np.zeros((4, 2, 2), np.float32), np.arange(3), cfg)
    with pytest.raises(TypeError, match="integers"):
        add_noise(np.zeros((2, 2, 2), np.float32), np.array([0.0, 1.0]), cfg)


# --- the generator: Philox4x64-10 streams, OpenCL kernel vs its float64 NumPy reference ------
from clrecon.simulation import noise as noise_mod  # noqa: E402


@pytest.mark.parametrize("counter, key", [((0, 0, 0, 0), (0, 0)), ((5, 7, 0, 0), (7, 123456)),
                                          ((2 ** 64 - 2, 1, 2, 3), (2 ** 64 - 1, 99))])
def test_philox_matches_numpy_bit_generator(counter, key):
    """NumPy's Philox (4x64-10) increments its counter before each block."""
    bg = np.random.Philox(counter=np.array(counter, np.uint64), key=np.array(key, np.uint64))
    c = np.array(counter, np.uint64)
    with np.errstate(over="ignore"):
        c[0] += np.uint64(1)
    np.testing.assert_array_equal(noise_mod.philox4x64(c, np.array(key, np.uint64)), bg.random_raw(4))


@pytest.mark.parametrize("i0, sigma", [(2.0e5, 5.0), (2.0e5, 0.0), (50.0, 5.0), (3.0, 0.0)])
def test_kernel_matches_float64_reference(i0, sigma):
    """Same streams and samplers: identical values (inversion below a mean of 10, PTRS above,
    starvation, and every pass of the kernel)."""
    rng = np.random.default_rng(5)
    p = rng.uniform(0.0, 12.0, (5, 6, 70)).astype(np.float32)
    p[0, 0, :10] = 40.0  # starvation: mean ~0
    idx = np.array([0, 1, 17, 10 ** 6, 2 ** 40])
    cfg = NoiseConfig(i0_photons=i0, electronic_sigma=sigma, seed=9)
    np.testing.assert_array_equal(add_noise(p, idx, cfg), noise_mod.add_noise_reference(p, idx, cfg))


def test_kernel_matches_reference_at_huge_counts():
    p = np.random.default_rng(6).uniform(0.0, 3.0, (2, 4, 50)).astype(np.float32)
    cfg = NoiseConfig(i0_photons=1.0e15, seed=2)
    a, b = add_noise(p, np.arange(2), cfg), noise_mod.add_noise_reference(p, np.arange(2), cfg)
    assert np.mean(a == b) > 0.99
    np.testing.assert_allclose(a, b, rtol=1e-6, atol=1e-6)  # float32 rounding of -log(N / I0)


def test_reference_is_the_fallback_without_float64(monkeypatch):
    p = np.random.default_rng(7).uniform(0.0, 5.0, (3, 2, 9)).astype(np.float32)
    cfg = NoiseConfig(seed=4)
    want = add_noise(p, np.arange(3), cfg)
    monkeypatch.setattr(noise_mod, "_has_fp64", lambda rt: False)
    np.testing.assert_array_equal(add_noise(p, np.arange(3), cfg), want)


def test_cos2pi_polynomial():
    u = np.random.default_rng(8).random(100000)
    assert np.abs(noise_mod.cos2pi(u) - np.cos(2 * np.pi * u)).max() < 2e-15


@pytest.mark.parametrize("lam", [0.3, 4.0, 9.9, 10.0, 60.0, 3.0e4])
def test_poisson_counts_mean_and_variance(lam):
    """Both samplers: mean and variance of N within 5 standard errors (sigma_e = 0)."""
    shape = (20, 50, 50)
    i0 = 1.0e6
    p = np.full(shape, np.log(i0 / lam), np.float32)
    noisy = add_noise(p, np.arange(shape[0]), NoiseConfig(i0_photons=i0, electronic_sigma=0.0, seed=1))
    n = np.rint(i0 * np.exp(-noisy.astype(np.float64)))  # N >= 1 survives the log exactly enough
    lam_t = i0 * np.exp(-np.float64(p.flat[0]))
    m = n.size
    # the 1-photon floor turns N = 0 into 1: compare with the floored distribution's moments
    p0 = np.exp(-lam_t)
    mean = lam_t + p0
    var = lam_t + lam_t ** 2 + p0 - mean ** 2
    assert abs(n.mean() - mean) < K_SE * np.sqrt(var / m)
    assert abs(n.var(ddof=1) - var) < K_SE * var * np.sqrt(2.0 / (m - 1)) * 2


def test_kernel_blocks_do_not_change_the_noise(monkeypatch):
    p = np.random.default_rng(9).uniform(0.0, 6.0, (7, 3, 30)).astype(np.float32)  # 90 cells: padded
    cfg = NoiseConfig(seed=5)
    whole = add_noise(p, np.arange(7), cfg)
    monkeypatch.setattr(noise_mod, "BLOCK_CELLS", 200)  # two projections per launch
    np.testing.assert_array_equal(add_noise(p, np.arange(7), cfg), whole)


@pytest.mark.parametrize("rows", [(0, 6), (2, 5), (5, 6)])
def test_a_block_of_rows_gets_exactly_those_rows_of_the_whole_projections_noise(rows):
    """``first_row``: the reconstruction draws noise only for the detector rows it reads; a
    cell's noise is keyed by its place on the whole detector, so it must not change."""
    rng = np.random.default_rng(11)
    p = rng.uniform(0.0, 12.0, (4, 6, 70)).astype(np.float32)
    idx = np.array([3, 4, 90, 2 ** 33])
    cfg = NoiseConfig(i0_photons=2e5, electronic_sigma=10.0, seed=5)
    whole = add_noise(p, idx, cfg)
    r0, r1 = rows
    block = add_noise(np.ascontiguousarray(p[:, r0:r1]), idx, cfg, first_row=r0)
    np.testing.assert_array_equal(block, whole[:, r0:r1])
    ref = noise_mod.add_noise_reference(np.ascontiguousarray(p[:, r0:r1]), idx, cfg, first_row=r0)
    np.testing.assert_array_equal(ref, whole[:, r0:r1])
    if r0 > 0:  # and the offset matters: the same values placed at row 0 differ
        assert not np.array_equal(add_noise(np.ascontiguousarray(p[:, r0:r1]), idx, cfg), block)
    with pytest.raises(ValueError, match="first_row"):
        add_noise(p, idx, cfg, first_row=-1)


@pytest.mark.parametrize("shape, i0", [((5, 6, 70), 2.0e5), ((5, 6, 70), 50.0), ((24, 64, 900), 2.0e5)])
def test_listed_and_flagged_passes_give_the_same_bits(monkeypatch, shape, i0):
    """add_noise_listed / add_noise_list (Intel's CPU runtime) against add_noise / add_noise_rest (the
    launch before them, PoCL's): the same bits on random cells (inversion, PTRS, starvation) and on a
    chunk of demo-sized projections (24 x 64 x 900), whichever the runtime chooses by default."""
    rng = np.random.default_rng(11)
    p = rng.uniform(0.0, 12.0, shape).astype(np.float32)
    p[0, 0, :10] = 40.0  # starvation
    idx = np.arange(shape[0]) * 3 + 5
    cfg = NoiseConfig(i0_photons=i0, electronic_sigma=5.0, seed=4)
    got = {}
    for listed in (False, True):
        monkeypatch.setattr(noise_mod, "lists_flagged_cells", lambda device, listed=listed: listed)
        got[listed] = add_noise(p, idx, cfg)
    np.testing.assert_array_equal(got[True].view(np.uint32), got[False].view(np.uint32))
    if shape[0] <= 5:
        np.testing.assert_array_equal(got[True], noise_mod.add_noise_reference(p, idx, cfg))
    monkeypatch.setattr(noise_mod, "BLOCK_CELLS", 2 * 64 * 960)  # several launches, several lists
    np.testing.assert_array_equal(add_noise(p, idx, cfg), got[False])
