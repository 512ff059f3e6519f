"""The simulation stage's own configuration: the noise model, and what the stage needs of a scene.

``[noise]`` is a frozen, self-validating section (:class:`clrecon.core.config.Section`); the
phantom sections live with their sources (:mod:`clrecon.simulation.phantom_sources`). What the
projection store and the simulation driver need of a whole scene is the protocol
:class:`SimulatedScan` (``docs/data-flow.md`` "Layering").
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Protocol

from clrecon.core.config import BOOL, NONNEG, NONNEGINT, F, Section, _pos, field_of
from clrecon.scan.config import Acquisition

_f = field_of  # (default, allowed, check, doc)


@dataclass(frozen=True, kw_only=True)
class NoiseConfig(Section):
    """Poisson quanta + Gaussian electronic noise, seeded per projection."""

    SECTION = "noise"

    enabled: bool = F(True, BOOL, "add noise")
    i0_photons: float = _f(2.0e5, "a number in (0, 1e15]", lambda x: _pos(x) and x <= 1e15,
                           "unattenuated photons per detector cell (above 1e15 NumPy's Poisson sampler fails)")
    electronic_sigma: float = F(5.0, NONNEG, "std of the electronic noise, in photon-equivalent counts")
    seed: int = F(7, NONNEGINT, "noise seed")
    also_noise_free: bool = F(True, BOOL, "also reconstruct the noise-free projections (the paper's Table 2)")


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
