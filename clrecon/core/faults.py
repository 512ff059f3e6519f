"""Test hook: make this process SIGKILL itself, or fail a write, at a chosen point (crash-safety tests).

Set ``CLRECON_FAULT=<point>:<n>``; the ``n``-th time the code passes :func:`point` with that
name (counting from 1), the process sends itself SIGKILL (no cleanup, no ``finally``, no
flush: exactly what ``kill -9`` or the OOM killer does). ``CLRECON_FAULT=<point>:<n>:enospc``
raises ``OSError(ENOSPC)`` there instead: the disk filled up (what a write on a full file
system raises). ``<point>`` may be a shell pattern (:mod:`fnmatch`), e.g. ``write:*.png``; the
count is per pattern, in this process. Unset, :func:`point` does nothing.

The points (the only calls of :func:`point` in clrecon):

``simulate``, ``recon``, ``truth``
    In the middle of writing the ``n``-th unit file of projections, of a reconstruction
    (slab x variant x method), of a truth target (ground truth or phantom): half of the
    temporary file is written (:func:`clrecon.core.units.write_unit`).
``mc-model``
    In the middle of writing the ``n``-th motion model of the ``mc`` method (one per pitch and
    noise variant, ``volumes.h5.units/mc/``).
``assemble-store``
    While the projection units are copied into the store under its ``.partial`` name, after
    the ``n``-th unit (a torn HDF5 file).
``assemble-volumes``
    While ``volumes.h5.partial`` is written, after the ``n``-th dataset's virtual mappings
    (a torn HDF5 file; the unit files it maps are untouched); also in the middle of rewriting
    an earlier version's ``.npz`` volume unit as an HDF5 unit.
``rename-store``, ``rename-volumes``
    Right before the assembled ``.partial`` is renamed to its final name (for the volumes:
    ``volumes.h5``, the axes and the virtual datasets over the unit files).
``worker-unit``
    At the start of the ``n``-th unit a Dask worker computes (:mod:`clrecon.pipeline.work_units`):
    a worker that dies mid-unit.
``write:<file name>``
    Half-way through writing a file that appears whole or not at all (:mod:`clrecon.core.atomic`:
    figures, reports, ``results.json``, export indexes), e.g. ``write:report.md:1:enospc`` or
    ``write:*.png:2``.
"""

from __future__ import annotations

import errno
import fnmatch
import os
import signal

_counts: dict[str, int] = {}
#: Actions a spec may end with (none: SIGKILL).
ACTIONS = ("enospc",)


def parse(spec: str) -> tuple[str, int, str]:
    """``(point pattern, n, action)`` of a ``CLRECON_FAULT`` value (action ``"kill"`` or one of :data:`ACTIONS`)."""
    parts = spec.split(":")
    action = parts.pop() if parts and parts[-1] in ACTIONS else "kill"
    n = parts.pop() if parts else ""
    try:
        return ":".join(parts), int(n), action
    except ValueError:
        raise ValueError(f"CLRECON_FAULT={spec!r}: expected <point>:<n>[:{'|'.join(ACTIONS)}]") from None


def point(name: str, path: str = "") -> None:
    """SIGKILL this process (or raise ENOSPC) if ``$CLRECON_FAULT`` names this point and this is its n-th pass.

    ``path`` names the file in the raised error."""
    spec = os.environ.get("CLRECON_FAULT")
    if not spec:
        return
    want, n, action = parse(spec)
    if not (want == name or fnmatch.fnmatchcase(name, want)):
        return
    _counts[want] = _counts.get(want, 0) + 1
    if _counts[want] != n:
        return
    if action == "enospc":
        raise OSError(errno.ENOSPC, "No space left on device (CLRECON_FAULT)", path or name)
    os.kill(os.getpid(), signal.SIGKILL)
