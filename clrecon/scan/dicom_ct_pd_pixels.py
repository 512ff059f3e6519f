"""The pixels of one DICOM-CT-PD file as clrecon's projection ``proj[row, column]`` (line integrals).

The header pass (:mod:`clrecon.scan.dicom_ct_pd`) decides how a series is read (a
:class:`~clrecon.scan.dicom_ct_pd.Reading`: which axis the DICOM Rows run along, and whether the
channel and row numbering run opposite to the store's); this applies it to one file. Used by the
import into the store (:mod:`clrecon.simulation.measured`) and by the orientation check
(:mod:`clrecon.scan.orientation_check`). Conventions: ``docs/measured-conventions.md``.
"""

from __future__ import annotations

import numpy as np

from clrecon.core.errors import InputError

#: The attributes the pixel pass parses (the header pass has read the rest).
PIXEL_TAGS = ["Rows", "Columns", "BitsAllocated", "PixelRepresentation", "PixelData"]


def read_projection(path: str, slope: float, intercept: float, n_rows: int, n_cols: int, pydicom,
                    reading=None) -> np.ndarray:
    """One file's line integrals ``stored * RescaleSlope + RescaleIntercept`` as ``[row, column]`` float32,
    shape (n_rows, n_cols), laid out and numbered as ``reading`` says (None: TCIA layout, no reversal)."""
    layout = getattr(reading, "layout", "rows-are-channels")
    try:
        ds = pydicom.dcmread(path, specific_tags=PIXEL_TAGS)
        rows, cols = int(ds.Rows), int(ds.Columns)
        bits, signed = int(ds.BitsAllocated), int(getattr(ds, "PixelRepresentation", 0))
        raw = ds.PixelData
    except Exception as e:  # noqa: BLE001 - pydicom raises many types on a damaged file
        raise InputError(f"{path}: pixel data unreadable ({type(e).__name__}); truncated file?") from None
    want = (n_cols, n_rows) if layout == "rows-are-channels" else (n_rows, n_cols)
    if (rows, cols) != want:
        raise InputError(f"{path}: Rows x Columns = {rows} x {cols}; expected {want[0]} x {want[1]} as in the rest "
                         f"of the series ({layout})")
    if bits != 16:
        raise InputError(f"{path}: (0028,0100) BitsAllocated = {bits}; expected 16")
    need = rows * cols * 2
    if len(raw) < need:
        raise InputError(f"{path}: PixelData holds {len(raw)} bytes, expected {need} ({rows} x {cols} x 16 bit); "
                         f"truncated file?")
    pix = np.frombuffer(raw[:need], "<i2" if signed else "<u2").reshape(rows, cols)
    if layout == "rows-are-channels":
        pix = pix.T  # [channel, row] -> [row, channel]
    p = pix.astype(np.float32) * np.float32(slope) + np.float32(intercept)
    if reading is not None and reading.reverse_channels:
        p = p[:, ::-1]
    if reading is not None and reading.reverse_rows:
        p = p[::-1, :]
    if not np.all(np.isfinite(p)):
        raise InputError(f"{path}: non-finite line integrals after RescaleSlope/Intercept")
    return np.ascontiguousarray(p)
