"""Phantom sources: one module per kind (``analytic``), registered in :mod:`clrecon.simulation.phantom_sources`."""
