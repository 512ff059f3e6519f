"""The ``mc`` method's motion model against the phantom's own motion (simulated scans only).

:func:`registration_error`: RMS and 95th percentile of |u_model(x; c, a) - u_true(x; c, a)| (mm)
over the targets, in the heart (walls, cavities, atria, lesion, aortic root) and in the body
outside the lungs, on the model's grid, beside the true motion's own RMS there. The true motion
is :func:`clrecon.simulation.phantoms.motion_field.displacement_fields` (docs/motion-model.md
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


def registration_error(scene, model, pairs) -> dict:
    """``{region: {rms_mm, p95_mm, true_motion_rms_mm}}`` of ``model`` (MotionModel) at the targets
    ``pairs`` (T, 2); ``{"skipped": why}`` where the phantom has no analytic motion."""
    if getattr(scene.phantom, "kind", "analytic") != "analytic":
        return {"skipped": f"phantom.kind = {scene.phantom.kind!r}: no analytic motion to compare with"}
    phantom = phantom_from_config(scene.phantom)
    g = model.grid
    x, y, z = g.coords()
    ref = tuple(model.reference)
    true = motion_field.displacement_fields(phantom, x, y, z, ref, np.asarray(pairs))
    Z, Y, X = np.meshgrid(z, y, x, indexing="ij")
    own = motion_field.owner(phantom, np.stack([X, Y, Z], -1), *ref)
    names = phantom.names
    heart = np.isin(own, [names.index(n) for n in HEART if n in names])
    body = (own >= 0) & ~np.isin(own, [names.index(n) for n in LUNGS if n in names])
    err2 = np.zeros((len(pairs),) + g.shape)
    for t, (c, a) in enumerate(np.asarray(pairs)):
        err2[t] = ((model.displacement(float(c), float(a)) - true[t]) ** 2).sum(0)
    t2 = (true.astype(np.float64) ** 2).sum(1)
    out = {}
    for key, m in (("heart", heart), ("body_outside_lungs", body)):
        if not m.any():
            continue
        e = np.sqrt(err2[:, m])
        out[key] = {"rms_mm": round(float(np.sqrt((e ** 2).mean())), 2),
                    "p95_mm": round(float(np.percentile(e, 95)), 2),
                    "true_motion_rms_mm": round(float(np.sqrt(t2[:, m].mean())), 2)}
    return out
