"""The run's stages, one module each, wired together in :data:`clrecon.pipeline.graph.GRAPH`.

Each module holds one stage function ``stage(run, pitch, **needs)`` (docs/extending.md "A new
pipeline stage"); the computing lives in the packages below (``scan``, ``simulation``,
``reconstruction``, ``evaluation``, ``outputs``), a stage only wires it to the run.
"""
