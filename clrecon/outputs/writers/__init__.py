"""Output writers of ``clrecon export``: one module per format, each registering itself here.

:data:`WRITERS` is the one list of export formats: ``export.FORMATS``, the ``--format``
choices of the CLI and the "must be one of" errors are read from it. A writer is a class
following :class:`clrecon.outputs.writers.base.Writer`, decorated with
``@WRITERS.register("<name>")``, in a module imported at the bottom of this file
(``docs/extending.md``, "A new output writer").
"""

from __future__ import annotations

from clrecon.core.registry import Registry

#: Export format name -> writer class (registration order = the order users see).
WRITERS: Registry = Registry("export format")

# Importing a writer module registers it; the order here is the order of FORMATS.
from clrecon.outputs.writers import dicom, dicom_ct_pd, nifti  # noqa: E402, F401 - after WRITERS: the modules register into it

__all__ = ["WRITERS"]
