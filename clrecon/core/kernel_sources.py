"""The kernel sources: the ``kernels/`` folder and its ``#include`` expansion.

``.cl`` sources live in the top-level ``kernels/`` folder (``clrecon/kernels`` inside an installed
wheel). ``#include "x.h"`` lines are expanded here, in Python, so the source string handed to the
driver changes whenever a header does, and every cache keyed on the source (PoCL's, the kernel
binaries of :mod:`clrecon.core.runtime`) rebuilds exactly when needed.
"""

from __future__ import annotations

import re
from pathlib import Path


def kernel_dir() -> Path:
    """Folder holding the ``.cl`` sources, from a checkout or an installed wheel."""
    package = Path(__file__).resolve().parent.parent  # clrecon/
    for cand in (package / "kernels", package.parent / "kernels"):
        if cand.is_dir() and any(cand.glob("*.cl")):
            return cand
    raise FileNotFoundError(f"OpenCL kernel sources not found next to {package}")


_INCLUDE = re.compile(r'^\s*#\s*include\s+"([^"]+)"\s*$', re.M)


def load_source(name: str, _seen: set | None = None, folder: Path | None = None) -> str:
    """Source of ``kernels/name`` with local ``#include "..."`` expanded (each header once).

    ``folder``: a folder of kernels kept outside the package (a study's, e.g.
    ``benchmarks/studies/motion-model/``): ``name`` and its headers are looked up there first,
    then in ``kernels/`` (so such a kernel can include the package's headers)."""
    seen = set() if _seen is None else _seen
    path = Path(folder) / name if folder is not None and (Path(folder) / name).is_file() else kernel_dir() / name
    text = path.read_text()

    def sub(m):
        inc = m.group(1)
        if inc in seen:
            return ""
        seen.add(inc)
        return f"// ---- begin {inc}\n{load_source(inc, seen, folder)}\n// ---- end {inc}\n"

    return _INCLUDE.sub(sub, text)
