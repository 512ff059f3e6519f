"""Phantom sources (registry): what the projector poses at each projection's (cardiac phase, amplitude).

A source is registered in :data:`PHANTOM_SOURCES` under the name a scene gives in
``[phantom] kind``, with its own config section (the ``[phantom]`` table's keys) and the class
that builds it from that config. The class gives the projector packed quadric objects per
state (``objects_batch(c, a)``) and the ground truth what it needs (``docs/extending.md``), or
carries its own projector (``carries_projector``: the voxel phantom, ``docs/voxel-phantoms.md``).
"""

from __future__ import annotations

from dataclasses import dataclass

from clrecon.core.registry import Registry
from clrecon.simulation.phantoms.analytic import Phantom, PhantomConfig
from clrecon.simulation.phantoms.voxel import VoxelPhantom, VoxelPhantomConfig


@dataclass(frozen=True)
class PhantomSource:
    """A registered phantom source: its config section class and the class built from it."""

    name: str
    config: type
    source: type
    description: str = ""


#: Phantom sources by ``[phantom] kind``.
PHANTOM_SOURCES: Registry[PhantomSource] = Registry("phantom source")
PHANTOM_SOURCES.register("analytic")(PhantomSource(
    "analytic", PhantomConfig, Phantom, "the built-in analytic thorax of quadrics (exact line integrals)"))
PHANTOM_SOURCES.register("voxel")(PhantomSource(
    "voxel", VoxelPhantomConfig, VoxelPhantom, "4D voxel frames (XCAT or NIfTI), projected by Joseph's method"))



def phantom_from_config(cfg):
    """The phantom a phantom config describes (its ``kind`` picks the source)."""
    return PHANTOM_SOURCES[cfg.kind].source(cfg)


__all__ = ["PHANTOM_SOURCES", "Phantom", "PhantomConfig", "PhantomSource", "phantom_from_config"]
