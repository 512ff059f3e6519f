"""Test hook: make this process SIGKILL itself at a chosen point (for the crash-safety tests).

Set ``CLRECON_FAULT=<point>:<n>``; the ``n``-th time the code passes :func:`point` with that
name (counting from 1), the process sends itself SIGKILL (no cleanup, no ``finally``, no
flush: exactly what ``kill -9`` or the OOM killer does). Unset, :func:`point` does nothing.

The points (the only calls of :func:`point` in clrecon):

``simulate``, ``recon``, ``truth``
    In the middle of writing the ``n``-th unit file of projections, of a reconstruction
    (slab x variant x method), of a truth target (ground truth or phantom): half of the
    temporary file is written (:func:`clrecon.core.units.write_unit`).
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
"""

from __future__ import annotations

import os
import signal

_counts: dict[str, int] = {}


def point(name: str) -> None:
    """SIGKILL this process if ``$CLRECON_FAULT`` names this point and this is its n-th pass."""
    spec = os.environ.get("CLRECON_FAULT")
    if not spec:
        return
    want, _, n = spec.rpartition(":")
    if want != name:
        return
    _counts[name] = _counts.get(name, 0) + 1
    if _counts[name] == int(n):
        os.kill(os.getpid(), signal.SIGKILL)
