"""CT noise: Poisson quanta plus Gaussian electronic noise on line integrals (pipeline stage 4).

Design: the projection store holds **noise-free** line integrals; noise is added here when
projections are *read* (``ProjectionStore.read(..., noisy=True)``). One simulation therefore
serves both the noise-free and the noisy reconstruction (the paper's Table 2 reports both),
the expensive projector never reruns for a new noise level or seed, and the noise settings
are not part of the store's content hash.

Model, per detector cell of a projection with line integral p (dimensionless, mu * length):
    N = Poisson(I0 exp(-p)) + Normal(0, sigma_e)          (photon-equivalent counts)
    p_noisy = -log(max(N, N_FLOOR) / I0)
with I0 = ``NoiseConfig.i0_photons`` unattenuated photons per cell and sigma_e =
``NoiseConfig.electronic_sigma``. Zero or negative counts (photon starvation, or electronic
noise pushing a few counts below zero) have no logarithm; they are clamped to
``N_FLOOR`` = 1 photon, the smallest count a detector can meaningfully report. This caps the
noisy line integral at ln(I0) (~12.2 for 2e5 photons): a finite, documented ceiling instead of
inf or NaN, which is what scanners' positivity corrections do before the log as well.

Reproducibility: every projection draws from its own generator seeded by
``SeedSequence([seed, projection_index])``, so a projection's noise is the same whatever
the chunk size, order or worker that reads it.
"""

from __future__ import annotations

import numpy as np

from .scene import NoiseConfig

#: Counts below this (photons) are clamped before the log; see the module docstring.
N_FLOOR = 1.0


def projection_rng(seed: int, index: int) -> np.random.Generator:
    """The generator of one projection's noise: ``SeedSequence([seed, index])``."""
    return np.random.default_rng(np.random.SeedSequence([int(seed), int(index)]))


def add_noise(line_integrals, proj_index, cfg: NoiseConfig) -> np.ndarray:
    """Noisy line integrals from noise-free ones.

    ``cfg.enabled`` is not consulted: the caller decides whether noise is wanted.

    Parameters
    ----------
    line_integrals : array_like, shape (m, R, C)
        Noise-free line integrals (dimensionless), one projection per leading index.
    proj_index : array_like of int, shape (m,)
        Projection numbers k in the helical scan; they seed the noise.
    cfg : NoiseConfig
        ``i0_photons``, ``electronic_sigma`` and ``seed``.

    Returns
    -------
    numpy.ndarray, shape (m, R, C), float32
        Noisy line integrals, each at most ``ln(i0_photons / N_FLOOR)``.
    """
    p = np.asarray(line_integrals)
    idx = np.asarray(proj_index)
    if p.ndim != 3:
        raise ValueError(f"line_integrals must have shape (m, R, C), got {p.shape}")
    if idx.shape != (p.shape[0],):
        raise ValueError(f"proj_index must have shape ({p.shape[0]},), got {idx.shape}")
    if not np.issubdtype(idx.dtype, np.integer):
        raise TypeError(f"proj_index must be integers, got {idx.dtype}")
    i0 = float(cfg.i0_photons)
    sigma = float(cfg.electronic_sigma)
    out = np.empty(p.shape, dtype=np.float32)
    for j in range(p.shape[0]):
        rng = projection_rng(cfg.seed, idx[j])
        expected = i0 * np.exp(-p[j].astype(np.float64))
        counts = rng.poisson(expected).astype(np.float64)
        if sigma > 0:
            counts += rng.normal(0.0, sigma, counts.shape)
        np.maximum(counts, N_FLOOR, out=counts)
        out[j] = -np.log(counts / i0)
    return out
