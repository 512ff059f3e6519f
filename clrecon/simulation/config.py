"""The simulation stage's own configuration: the noise model, and what the stage needs of a scene.

``[noise]`` is a frozen, self-validating section (:class:`clrecon.core.config.Section`); the
phantom sections live with their sources (:mod:`clrecon.simulation.phantom_sources`). What the
projection store and the simulation driver need of a whole scene is the protocol
:class:`SimulatedScan` (``docs/data-flow.md`` "Layering").
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Protocol

from clrecon.core.config import BOOL, SEED, F, Section, number_in
from clrecon.core.errors import SceneError
from clrecon.scan.config import Acquisition


@dataclass(frozen=True, kw_only=True)
class NoiseConfig(Section):
    """Poisson quanta + Gaussian electronic noise, seeded per projection."""

    SECTION = "noise"

    enabled: bool = F(True, BOOL, "add noise")
    i0_photons: float = F(2.0e5, number_in(1.0, 1e15, "photons", "clinical CT 1e4-1e6 per cell and view; below "
                                           "1 nothing is measured; above 1e15 NumPy's Poisson sampler fails"),
                          "unattenuated photons per detector cell")
    electronic_sigma: float = F(5.0, number_in(0.0, 1e6, "counts", "detectors: a few photon-equivalent counts; "
                                               "at most i0_photons"),
                                "std of the electronic noise, in photon-equivalent counts")
    seed: int = F(7, SEED, "noise seed")
    also_noise_free: bool = F(True, BOOL, "also reconstruct the noise-free projections (the paper's Table 2)")

    def check(self) -> None:
        if self.electronic_sigma > self.i0_photons:
            raise SceneError(f"noise.electronic_sigma = {self.electronic_sigma!r}: must be at most noise.i0_photons = "
                             f"{self.i0_photons!r} (electronic noise above the unattenuated signal drowns every "
                             f"measurement)")


class SimulatedScan(Acquisition, Protocol):
    """An :class:`~clrecon.scan.config.Acquisition` with its phantom and noise, hashable per pitch.

    ``scan_hash(pitch)`` names the store of one pitch (content hash of what determines the
    noise-free projections); ``to_dict()`` is the plain-dict form recorded in the store.
    """

    @property
    def phantom(self) -> Any: ...
    @property
    def noise(self) -> NoiseConfig: ...
    def scan_hash(self, pitch: float) -> str: ...
    def to_dict(self) -> dict[str, Any]: ...
