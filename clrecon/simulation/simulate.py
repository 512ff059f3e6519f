"""Simulation driver: project the helical scan of a scene into its projection store.

scene + pitch -> :func:`~clrecon.scan.table.projection_table` -> the store of that scan
(:mod:`clrecon.simulation.store`) -> project only the needed projections that are not yet stored, in
chunks, in index (= time) order. Noise is not added here: the store keeps noise-free line
integrals and :meth:`ProjectionStore.read` adds noise on the way out.
"""

from __future__ import annotations

import time

import numpy as np

from clrecon.core import write_behind
from clrecon.core.progress import progress as progress_counter
from clrecon.scan.table import cached_projection_table
from clrecon.simulation import measured
from clrecon.simulation.config import SimulatedScan
from clrecon.simulation.projector import project
from clrecon.simulation.store import ProjectionStore

#: Projections per unit file (the distributed path cuts the same chunks).
CHUNK = 256
#: Bytes of projections one projector call makes at most (a block of whole chunks, written as
#: its chunks' units once it is done): the analytic phantom is posed once per call at about
#: 28 ms fixed cost, which was 6 s of demo's 14.7 s simulation in calls of 256 projections of
#: 240 x 16; in blocks of 2 048 it is paid 8x less often. Paper scenes' 900 x 64 projections
#: (230 KB) make blocks of 2 chunks (their projector calls are cut at 2^24 cells anyway).
BLOCK_BYTES = 128 * 1024 ** 2  # two are held while a block's units are written behind the next
#: At most this many chunks per projector call.
BLOCK_CHUNKS = 8


def simulate(scene: SimulatedScan, pitch: float, needed=None, cache_dir=None, projector=None,
             chunk: int = CHUNK, progress: bool = True, write_behind_thread: bool = True) -> ProjectionStore:
    """Make sure the projections ``needed`` of ``(scene, pitch)`` are in the store.

    Parameters
    ----------
    scene : Scene
    pitch : float
        Helical pitch, normally one of ``scene.scan.pitches``.
    needed : ndarray of bool, shape (n,), optional
        Projections that must be present (n = projections of the scan); None = all.
    cache_dir : path-like, optional
        Store folder; default ``$CLRECON_CACHE`` or ``~/.cache/clrecon``.
    projector : callable, optional
        ``projector(scene, table) -> (len(table), n_rows, n_cols)`` line integrals for a
        sub-table of projections; default :func:`clrecon.simulation.projector.project`.
    chunk : int
        Projections per write (one unit file) and per call of a given ``projector``; the default
        projector is called on blocks of up to :data:`BLOCK_CHUNKS` chunks within
        :data:`BLOCK_BYTES` (the values do not depend on it: each projection is computed alone).
    progress : bool
        Progress with an ETA on stderr (:mod:`clrecon.core.progress`: a tqdm bar on a terminal,
        a log line a minute otherwise; none with ``CLRECON_NO_PROGRESS=1``).
    write_behind_thread : bool
        Write each block's units in a thread while the next block is projected (the same files
        either way).

    Returns
    -------
    ProjectionStore
        Finished (``.h5``) store, with ``n_simulated`` (projected in this call),
        ``n_reused`` (needed and already present) and ``simulate_s`` (seconds projecting
        and writing) set.

    Raises
    ------
    StoreError
        The existing store file is corrupt.
    """
    if not (isinstance(chunk, int) and chunk > 0):
        raise ValueError(f"chunk = {chunk!r}: must be an integer > 0")
    if scene.measured:  # a measured scan: its files are read into the store instead (same store, same units)
        return measured.import_series(scene, pitch, needed=needed, cache_dir=cache_dir, chunk=chunk, progress=progress)
    table = cached_projection_table(scene, pitch)
    n = len(table)
    if needed is None:
        needed = np.ones(n, dtype=bool)
    else:
        needed = np.asarray(needed)
        if needed.dtype != bool:
            raise TypeError(f"needed must be a boolean mask, got {needed.dtype}")
        if needed.shape != (n,):
            raise ValueError(f"needed has shape {needed.shape}, the scan has ({n},) projections")
    blocks = projector is None  # the default projector is called on blocks of chunks; a given one per chunk
    if projector is None:
        projector = project

    store = ProjectionStore.open(scene, pitch, cache_dir=cache_dir, table=table)
    missing = store.missing(needed)
    if missing.size == 0 and store.state == "final":
        return store

    t0 = time.perf_counter()
    with progress_counter(int(missing.size), f"simulate {scene.name} pitch {pitch:g}", progress, "proj") as bar:
        # A .partial with nothing missing still goes through writing() to be finished.
        with store.writing():
            per_block = block_size(scene, chunk) if blocks else chunk
            # each block's units are written by a thread while the next block is projected
            # (clrecon.core.write_behind; write_behind=False: in this thread)
            wb = write_behind.WriteBehind(background=write_behind_thread)
            try:
                for b0 in range(0, missing.size, per_block):
                    block = missing[b0:b0 + per_block]
                    data = projector(scene, table.take(block))
                    wb.submit(write_block, store, block, data, chunk, bar)
                wb.drain()
            finally:
                wb.close()
    store.simulate_s = time.perf_counter() - t0
    return store


def block_size(scene: SimulatedScan, chunk: int = CHUNK) -> int:
    """Projections per call of the default projector: whole chunks, at most :data:`BLOCK_CHUNKS`
    of them and within :data:`BLOCK_BYTES`."""
    proj_bytes = 4 * scene.scanner.n_rows * scene.scanner.n_cols
    return chunk * max(1, min(BLOCK_CHUNKS, BLOCK_BYTES // max(chunk * proj_bytes, 1)))


def write_block(store: ProjectionStore, block: np.ndarray, data: np.ndarray, chunk: int = CHUNK, bar=None) -> None:
    """Write one projected block into ``store``: one unit per ``chunk`` projections."""
    for lo in range(0, block.size, chunk):
        idx = block[lo:lo + chunk]
        store.write(idx, data[lo:lo + chunk])
        store.n_simulated += int(idx.size)
        if bar is not None:
            bar.update(int(idx.size))
