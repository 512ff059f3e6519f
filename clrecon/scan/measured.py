"""The per-projection table of a measured DICOM-CT-PD scan (stage 2 of the pipeline, measured path).

The geometry of every view comes from its file's header (:func:`clrecon.scan.dicom_ct_pd.series_views`:
gantry angle, source z, time; conventions in ``docs/measured-conventions.md``); the cardiac phase and
respiratory amplitude from the recorded traces (:mod:`clrecon.scan.recorded` via
:func:`clrecon.scan.signals.physiology`). Row k of the table is the k-th file in InstanceNumber order,
which is also row k of the projection store.
"""

from __future__ import annotations

import numpy as np

from clrecon.scan import dicom_ct_pd
from clrecon.scan.config import Acquisition


def views(scene: Acquisition) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(index (n,) int64, time_s, angle_rad, source_z_mm (n,) float64) of the scene's measured series."""
    g = dicom_ct_pd.series_views(scene.scan.projections, scene.scanner.rotation_time_s, scene.scan.timestamp_unit)
    n = g.angle_rad.size
    return np.arange(n, dtype=np.int64), g.time_s, g.angle_rad, g.source_z_mm
