"""Phantom sources: one module per kind (``analytic``, ``voxel`` with its reader ``frames``),
registered in :mod:`clrecon.simulation.phantom_sources`."""
