"""pyvista viewer of a run directory's 5D volumes: ``python -m clrecon view RUN_DIR``
(see :mod:`clrecon.viewer.app`)."""
