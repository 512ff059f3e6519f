"""What an output writer is (the protocol ``export`` drives) and the helpers writers share.

``export(run_dir, fmt, ...)`` resolves one source of a run, then for ``WRITERS[fmt]``:

1. ``ctx = writer.begin(ident, src, n_targets)`` once per export (``ident`` identifies the
   run, e.g. to derive stable UIDs; the default returns None);
2. ``writer.write_target(out, vol, axes, src, ci, ri, ctx)`` once per target (cardiac index
   ``ci``, respiratory index ``ri``), ``vol`` float32 HU ``[z, y, x]`` in the DICOM patient
   frame (LPS) with ``axes`` = ``{cardiac_phase, resp_amplitude, z_mm, y_mm, x_mm}``; it
   returns the files it wrote (under ``out``), listed in ``index.json``;
3. ``writer.finish(ctx)`` -> extra ``index.json`` entries (default none).

Writers import their optional package lazily through :meth:`Writer.require`, so a missing
package is a one-line :class:`ClreconError` with the install hint, raised only when that
format is asked for.
"""

from __future__ import annotations

import importlib
from pathlib import Path
from typing import TYPE_CHECKING, Any, ClassVar

import numpy as np

from clrecon.core.errors import ClreconError, StoreError

if TYPE_CHECKING:
    from clrecon.outputs.rundir import Source


class Writer:
    """Base of every output writer (subclass it and register the subclass in ``WRITERS``)."""

    #: Registry name = the ``--format`` value.
    name: ClassVar[str] = ""
    #: Human name in messages ("DICOM export needs ...").
    label: ClassVar[str] = ""
    #: Coordinate frame of the written files, recorded as ``index.json`` "frame".
    frame: ClassVar[str] = ""
    #: Optional package (import name) the writer needs, or "" for none.
    requires: ClassVar[str] = ""
    #: One-line install hint shown when ``requires`` is missing.
    install_hint: ClassVar[str] = "pip install 'clrecon[export]'"

    def require(self):
        """Import and return :attr:`requires`; a one-line ClreconError with the hint if missing."""
        try:
            return importlib.import_module(self.requires)
        except ImportError:
            raise ClreconError(f"{self.label} export needs {self.requires}: {self.install_hint}") from None

    def begin(self, ident: str, src: Source, n_targets: int) -> Any:
        """Per-export context handed to every :meth:`write_target` (default: None)."""
        return None

    def write_target(self, out: Path, vol: np.ndarray, axes: dict, src: Source, ci: int, ri: int,
                     ctx: Any) -> list[Path]:
        """Write target (ci, ri) under ``out``; return the paths written."""
        raise NotImplementedError

    def finish(self, ctx: Any) -> dict:
        """Extra ``index.json`` entries once every target is written (default: none)."""
        return {}


# ----------------------------------------------------------------------------------------
# Helpers shared by the writers (and the index)
def target_tag(c: float, a: float) -> str:
    """``C40% R05%`` for c = 0.4, a = 0.05 (percent, rounded)."""
    return f"C{round(c * 100):02d}% R{round(a * 100):02d}%"


def _file_tag(c: float, a: float) -> str:
    return f"C{round(c * 100):02d}_R{round(a * 100):02d}"


def _spacing(v: np.ndarray, name: str) -> float:
    if v.size < 2:
        return 1.0
    d = np.diff(v)
    if not np.allclose(d, d[0], rtol=1e-4, atol=1e-6) or d[0] <= 0:
        raise StoreError(f"axis {name} is not uniformly increasing; cannot write a regular grid")
    return float(d[0])


def source_stem(src: Source) -> str:
    """``method`` or ``method_<pitch>_<variant>``: default export folder and NIfTI file stem."""
    return src.method if src.pitch_key is None else f"{src.method}_{src.pitch_key}_{src.variant}"
