"""Import of a measured DICOM-CT-PD scan into the projection store (stage 5, measured path).

What :func:`clrecon.simulation.simulate.simulate` does with the projector, this does with the
files of a DICOM-CT-PD series: the projections the run needs and the store lacks are read with
pydicom one file at a time (never the whole scan in memory), converted to line integrals
(``stored * RescaleSlope + RescaleIntercept``), laid out as the store's ``[row, column]`` and
numbered as the store numbers them (the reading the scene load settled from the tags, the
``scan.*`` keys and the orientation check: :func:`clrecon.scan.dicom_ct_pd_pixels.read_projection`),
and written in chunks through the store's
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
from clrecon.scan.dicom_ct_pd_pixels import PIXEL_TAGS, read_projection  # noqa: F401 (read_projection: patched in tests)
from clrecon.scan.table import cached_projection_table
from clrecon.simulation.config import SimulatedScan
from clrecon.simulation.store import ProjectionStore

#: Files read per unit file of the store (as the simulation's CHUNK).
CHUNK = 256
#: Header index per file: the decoded tag dictionary kept while the series is indexed, and the views' arrays.
HEADER_BYTES_PER_FILE = 2500
#: PoCL compiling the kernels into a cold kernel cache grows the process by about this much after
#: the pre-flight has measured it (PoCL only; docs/results/code-history.md "PoCL's kernel build").
KERNEL_BUILD_BYTES = 0.1 * 2**30


def memory_bytes(scene: SimulatedScan) -> int:
    """Modelled peak memory (bytes) of a measured scan beyond the reconstruction's own model
    (:func:`clrecon.pipeline.costs.run_costs`): the header index, one import chunk (the stacked float32
    line integrals and the files' decoded pixels), the orientation check's rebinned rows and a cold
    kernel build (``docs/measured-data.md`` "Import into the store"). The process itself (interpreter,
    libraries, the OpenCL driver: 0.2-0.4 GiB by driver) is measured by the pre-flight, not modelled."""
    sc = scene.scanner
    n = scene.scan.projection_count(sc, scene.scan.pitches[0])
    proj = sc.n_rows * sc.n_cols * 4
    chunk = CHUNK * proj * 2 + CHUNK * sc.n_rows * sc.n_cols * 2  # the stack, its rows list, the uint16 pixels
    check = sc.views_per_rotation * sc.n_cols * 8 * 10  # (rows x channels hypotheses + pairs) x V x C float64
    return int(n * HEADER_BYTES_PER_FILE + chunk + check + KERNEL_BUILD_BYTES)


def measured_reading(scene: SimulatedScan) -> dicom_ct_pd.Reading:
    """The reading (layout, numbering) of a measured scene's series, as its scan keys resolved it at load."""
    sc = scene.scan
    ix = dicom_ct_pd.series_index(sc.projections)
    return dicom_ct_pd.reading_for(ix, dicom_ct_pd.pixel_layout(ix, sc.pixel_layout), sc.flip_channels, sc.flip_rows)


def import_series(scene: SimulatedScan, pitch: float, needed=None, cache_dir=None, chunk: int = CHUNK,
                  progress: bool = True, table=None) -> ProjectionStore:
    """Make sure the projections ``needed`` ((n,) bool, None = all) of a measured scene are in its store.

    Returns the finished store with ``n_simulated`` (here: imported in this call), ``n_reused``
    and ``simulate_s`` (seconds importing) set, as :func:`~clrecon.simulation.simulate.simulate`.
    """
    import pydicom

    if table is None:
        table = cached_projection_table(scene, pitch)
    ix = dicom_ct_pd.series_index(scene.scan.projections)
    reading = measured_reading(scene)
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
                                                 pydicom, reading) for k in idx])
                store.write(idx, data)
                store.n_simulated += int(idx.size)
                bar.update(int(idx.size))
    store.simulate_s = time.perf_counter() - t0
    return store
