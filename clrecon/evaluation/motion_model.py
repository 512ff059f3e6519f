"""The ``mc`` method's motion model against the phantom's own motion (simulated scans only).

:func:`registration_error`: RMS and 95th percentile of |u_model(x; c, a) - u_true(x; c, a)| (mm)
over the targets, in the heart (walls, cavities, atria, lesion, aortic root) and in the body
outside the lungs, on the model's grid, beside the true motion's own RMS there. The true motion
is :func:`clrecon.simulation.phantoms.motion_field.displacement_fields` (docs/results/mc-study.md
"True motion of the phantom"), defined for the analytic phantom only.
"""

from __future__ import annotations

import numpy as np

from clrecon.simulation.phantom_sources import phantom_from_config
from clrecon.simulation.phantoms import motion_field

#: The heart's objects of the analytic phantom (those present are used).
HEART = ("lv_myocardium", "lv_blood", "rv_myocardium", "rv_blood", "left_atrium", "right_atrium", "lesion",
         "aortic_root")
LUNGS = ("lung_left", "lung_right", "trachea")


#: In-plane grid the error is measured on: every s-th voxel of the model's grid, s = nx // this
#: (the phantom's true fields cost ~1 min for demo's 128 x 128 x 16 x 50 targets on one core).
ERROR_GRID = 64


def registration_error(scene, model, pairs, cache: dict | None = None) -> dict:
    """``{region: {rms_mm, p95_mm, true_motion_rms_mm}, stride}`` of ``model`` (MotionModel) at the
    targets ``pairs`` (T, 2), on every ``stride``-th voxel of its grid in-plane (:data:`ERROR_GRID`);
    ``{"skipped": why}`` where the phantom has no analytic motion. ``cache``: a dict that keeps the
    phantom's fields and regions for the next call on the same grid, reference and targets
    (another noise variant or pitch of the run)."""
    if getattr(scene.phantom, "kind", "analytic") != "analytic":
        return {"skipped": f"phantom.kind = {scene.phantom.kind!r}: no analytic motion to compare with"}
    phantom = phantom_from_config(scene.phantom)
    g = model.grid
    k = max(1, min(g.nx, g.ny) // ERROR_GRID)
    x, y, z = g.coords()
    x, y = x[::k], y[::k]
    ref = tuple(model.reference)
    key = (g, k, ref, np.asarray(pairs, np.float64).tobytes())
    if cache is None or key not in cache:
        true = motion_field.displacement_fields(phantom, x, y, z, ref, np.asarray(pairs))
        Z, Y, X = np.meshgrid(z, y, x, indexing="ij")
        own = motion_field.owner(phantom, np.stack([X, Y, Z], -1), *ref)
        names = phantom.names
        heart = np.isin(own, [names.index(n) for n in HEART if n in names])
        body = (own >= 0) & ~np.isin(own, [names.index(n) for n in LUNGS if n in names])
        if cache is not None:
            cache.clear()  # one grid at a time
            cache[key] = (true, heart, body)
    else:
        true, heart, body = cache[key]
    err2 = np.zeros((len(pairs),) + true.shape[2:])
    for t, (c, a) in enumerate(np.asarray(pairs)):
        err2[t] = ((model.displacement(float(c), float(a))[:, :, ::k, ::k] - true[t]) ** 2).sum(0)
    t2 = (true.astype(np.float64) ** 2).sum(1)
    out = {"stride": k}
    for key, m in (("heart", heart), ("body_outside_lungs", body)):
        if not m.any():
            continue
        e = np.sqrt(err2[:, m])
        out[key] = {"rms_mm": round(float(np.sqrt((e ** 2).mean())), 2),
                    "p95_mm": round(float(np.percentile(e, 95)), 2),
                    "true_motion_rms_mm": round(float(np.sqrt(t2[:, m].mean())), 2)}
    return out
