"""How ``mc`` cuts a scan's slices into slabs, and the memory its work holds (the pre-flight's model).

:func:`plane_row_slabs` is the cut :func:`clrecon.reconstruction.motion.mc_fbp.MCScan` makes (one
work unit per slab and noise variant); :func:`working_bytes` what a run of ``mc`` at one pitch
adds to the process's memory (read by :func:`clrecon.pipeline.costs.run_costs`).
"""

from __future__ import annotations

import numpy as np

from clrecon.reconstruction import rebin, reconstruct
from clrecon.reconstruction.motion import method as mcm
from clrecon.reconstruction.motion.registration import FLOW_BYTES_PER_VOXEL, registration_workers

#: Plane rows of one slab stay within this many bytes (half the reconstruction's slab budget).
ROWS_BYTES = reconstruct.SLAB_BYTES / 2
#: A slab may grow past the rows budget while its plane rows stay within this factor of its first
#: slice's alone. The rows of one slice reach ``knobs.margin_mm`` beyond it on both sides, so where
#: one slice's rows already exceed the budget (paper-p010: 1.31 GB against 1.25) each further slice
#: adds little (8 slices: 1.11x one slice's); without it every slab held one slice and the same
#: projections were read, noised and rebinned once per slice (534 s of a paper-p010 slab's 2 803 s).
GROWTH = 1.5


def _bytes_per_projection(scanner, window_mm: float, knobs) -> int:
    """Bytes of one projection's plane rows ((planes, n_cols) float32) for an SSRB window of ``window_mm``."""
    return (int((2 * (window_mm + knobs.plane_dz_mm)) / knobs.plane_dz_mm) + 2) * scanner.n_cols * 4


def plane_row_slabs(table, scanner, cfg, slices_z, knobs, budget: float | None = None) -> list[tuple[int, int]]:
    """Consecutive slice ranges whose plane rows ((P, planes, C) float32) stay within ``budget``
    (default :data:`ROWS_BYTES`), or within :data:`GROWTH` times the rows of the range's first slice
    where that is more."""
    budget = ROWS_BYTES if budget is None else budget
    w = rebin.slice_window_mm(scanner, cfg.object_radius_mm)
    per_proj = _bytes_per_projection(scanner, w, knobs)
    z = np.sort(np.asarray(table.source_z_mm, np.float64))
    reach = w + knobs.margin_mm

    def rows_bytes(a, b):
        lo, hi = slices_z[a] - reach, slices_z[b - 1] + reach
        return (np.searchsorted(z, hi, side="right") - np.searchsorted(z, lo)) * per_proj

    out, a = [], 0
    for b in range(1, len(slices_z) + 1):
        if b - 1 > a and rows_bytes(a, b) > max(budget, GROWTH * rows_bytes(a, a + 1)):
            out.append((a, b - 1))
            a = b - 1
    out.append((a, len(slices_z)))
    return out


def working_bytes(scanner, window_mm: float, knobs, z_extent_mm: float, feed_mm: float, n_var: int,
                  n_targets: int, nz: int, ny: int, nx: int) -> int:
    """Modelled memory of ``mc`` at one pitch (bytes), beside the process's baseline.

    The plane rows of a slab ((planes, n_cols) float32 per projection it uses, the projections
    within the SSRB window plus ``knobs.margin_mm`` of its slices: at most ``ROWS_BYTES``, or
    ``GROWTH`` times one slice's where that is more), kept for
    the final pass for every noise variant (when they fit ``ROWS_BYTES``) plus one variant's copy on
    the device (host memory on a CPU driver); the first pass of one variant, the previous round's
    images and the slab's output, float32 (3 x targets x slices x ny x nx); the registration's
    fields (13 registrations and the model's basis, 3 components each, at the registration's
    grid); the raw rows read for the plane rows (``method.READ_CHUNK_BYTES`` at a time, with their
    covering range and SSRB rows: 3 chunks); the registration processes' working sets
    (``FLOW_BYTES_PER_VOXEL`` per voxel each, one per core up to ``MAX_WORKERS``: 2 x 79 MB on
    ``demo`` with 2 cores, in processes of their own). Returns bytes. The model against a measured
    peak: docs/results/code-history.md "The mc working set against the measured peak"."""
    w = window_mm  # the SSRB slice window (reconstruction.rebin.slice_window_mm)
    per_proj = _bytes_per_projection(scanner, w, knobs)
    n_proj = (z_extent_mm + 2 * (w + knobs.margin_mm)) / feed_mm * scanner.views_per_rotation
    one_slice = 2 * (w + knobs.margin_mm) / feed_mm * scanner.views_per_rotation * per_proj
    rows = min(max(ROWS_BYTES, GROWTH * one_slice), n_proj * per_proj)  # plane_row_slabs' limit
    kept = n_var * rows if n_var * rows <= ROWS_BYTES else 0.0
    f = max(1, knobs.downsample)
    volumes = 3 * n_targets * nz * ny * nx * 4
    n_reg = nz * (ny // f) * (nx // f)
    fields = (13 + 1 + 2 * knobs.resp_degree + 2 * knobs.cardiac_harmonics) * 3 * n_reg * 4
    # the registration processes (one per core, at most MAX_WORKERS: the most the run starts)
    flows = registration_workers(n_reg, available_bytes=1 << 62) * FLOW_BYTES_PER_VOXEL * n_reg
    # the raw detector rows a slab's plane rows are made from, one chunk at a time, with the chunk's
    # covering range of the store and its SSRB rows (measured on a paper-p010 slice: 2.9 chunks of 128 MiB)
    read = 3 * min(mcm.READ_CHUNK_BYTES, n_proj * scanner.n_rows * scanner.n_cols * 4)
    return int(kept + rows + volumes + fields + flows + read)
