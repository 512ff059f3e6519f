"""Import of a measured DICOM-CT-PD scan into the projection store (stage 5, measured path).

What :func:`clrecon.simulation.simulate.simulate` does with the projector, this does with the
files of a DICOM-CT-PD series: the projections the run needs and the store lacks are read with
pydicom one file at a time (never the whole scan in memory), converted to line integrals
(``stored * RescaleSlope + RescaleIntercept``), laid out as the store's ``[row, column]``
(the file's pixel array is ``[channel, row]``: DICOM Rows = detector columns), flipped where
``scan.flip_channels`` / ``scan.flip_rows`` say, and written in chunks through the store's
public API (``writing()`` / ``write()``): each chunk is a checksummed unit file, so an import
killed at any instant resumes with the chunks already written, exactly as a simulation does.
A file that cannot be read fails the chunk before anything of it is written. Conventions:
``docs/measured-data.md``.
"""

from __future__ import annotations

import time

import numpy as np

from clrecon.core.errors import InputError
from clrecon.core.progress import progress as progress_counter
from clrecon.scan import dicom_ct_pd
from clrecon.scan.table import projection_table
from clrecon.simulation.config import SimulatedScan
from clrecon.simulation.store import ProjectionStore

#: The attributes the pixel pass parses (the header pass has read the rest).
PIXEL_TAGS = ["Rows", "Columns", "BitsAllocated", "PixelRepresentation", "PixelData"]
#: Files read per unit file of the store (as the simulation's CHUNK).
CHUNK = 256


def read_projection(path: str, slope: float, intercept: float, n_rows: int, n_cols: int, pydicom,
                    flip_channels: bool = False, flip_rows: bool = False) -> np.ndarray:
    """One file's line integrals as ``[row, column]`` float32, shape (n_rows, n_cols)."""
    try:
        ds = pydicom.dcmread(path, specific_tags=PIXEL_TAGS)
        rows, cols = int(ds.Rows), int(ds.Columns)
        bits, signed = int(ds.BitsAllocated), int(getattr(ds, "PixelRepresentation", 0))
        raw = ds.PixelData
    except Exception as e:  # noqa: BLE001 - pydicom raises many types on a damaged file
        raise InputError(f"{path}: pixel data unreadable ({type(e).__name__}); truncated file?") from None
    if (rows, cols) != (n_cols, n_rows):
        raise InputError(f"{path}: Rows x Columns = {rows} x {cols}; expected {n_cols} x {n_rows} "
                         f"(channels x detector rows) as in the rest of the series")
    if bits != 16:
        raise InputError(f"{path}: (0028,0100) BitsAllocated = {bits}; expected 16")
    need = rows * cols * 2
    if len(raw) < need:
        raise InputError(f"{path}: PixelData holds {len(raw)} bytes, expected {need} ({rows} x {cols} x 16 bit); "
                         f"truncated file?")
    pix = np.frombuffer(raw[:need], "<i2" if signed else "<u2").reshape(rows, cols)
    p = pix.T.astype(np.float32) * np.float32(slope) + np.float32(intercept)  # [channel, row] -> [row, channel]
    if flip_channels:
        p = p[:, ::-1]
    if flip_rows:
        p = p[::-1, :]
    if not np.all(np.isfinite(p)):
        raise InputError(f"{path}: non-finite line integrals after RescaleSlope/Intercept")
    return np.ascontiguousarray(p)


def import_series(scene: SimulatedScan, pitch: float, needed=None, cache_dir=None, chunk: int = CHUNK,
                  progress: bool = True, table=None) -> ProjectionStore:
    """Make sure the projections ``needed`` ((n,) bool, None = all) of a measured scene are in its store.

    Returns the finished store with ``n_simulated`` (here: imported in this call), ``n_reused``
    and ``simulate_s`` (seconds importing) set, as :func:`~clrecon.simulation.simulate.simulate`.
    """
    import pydicom

    if table is None:
        table = projection_table(scene, pitch)
    ix = dicom_ct_pd.series_index(scene.scan.projections)
    n = len(table)
    if len(ix) != n:
        raise InputError(f"{scene.scan.projections}: {len(ix)} files but the scan table has {n} views")
    needed = np.ones(n, bool) if needed is None else np.asarray(needed, bool)
    store = ProjectionStore.open(scene, pitch, cache_dir=cache_dir, table=table)
    missing = store.missing(needed)
    if missing.size == 0 and store.state == "final":
        return store
    sc = scene.scanner
    t0 = time.perf_counter()
    with progress_counter(int(missing.size), f"import {scene.name}", progress, "proj") as bar:
        with store.writing():
            for lo in range(0, missing.size, chunk):
                idx = missing[lo:lo + chunk]
                data = np.stack([read_projection(ix.files[k], ix.slope[k], ix.intercept[k], sc.n_rows, sc.n_cols,
                                                 pydicom, scene.scan.flip_channels, scene.scan.flip_rows)
                                 for k in idx])
                store.write(idx, data)
                store.n_simulated += int(idx.size)
                bar.update(int(idx.size))
    store.simulate_s = time.perf_counter() - t0
    return store
