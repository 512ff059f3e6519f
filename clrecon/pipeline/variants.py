"""Which noise variants a scene reconstructs (used by the run, its cost model and the bench)."""

from __future__ import annotations


def noise_variants(scene) -> tuple[str, ...]:
    """``("noisy", "noise-free")``, ``("noisy",)`` or ``("noise-free",)`` from ``scene.noise``.

    Noise-free is the paper's Table 2 condition; with noise enabled it is also reconstructed
    unless ``noise.also_noise_free = false`` (the store holds noise-free line integrals, so both
    come from one simulation).
    """
    if scene.measured:  # the projections are measured: read as they are (noise is in them)
        return ("measured",)
    if not scene.noise.enabled:
        return ("noise-free",)
    return ("noisy", "noise-free") if scene.noise.also_noise_free else ("noisy",)
