"""``r4dct``: respiratory-only 4DCT baseline.

Amplitude only (cardiac ignored): linear between the candidates bracketing a*; outside the
sampled range, the nearest in amplitude. Solved on the respiratory-only target grid (one
target per amplitude; the volume is the same for every cardiac phase).
"""

from __future__ import annotations

import numpy as np

from clrecon.reconstruction.interpolation._common import bracket
from clrecon.reconstruction.interpolation.registry import register_method


@register_method(name="r4dct", label="r4DCT", neighbours=2, target_grid="resp", axes=("resp",),
                 five_d=False, marker="D", rank=2)
def weights(ch, targets, dc, da, d2, opts):
    da_r = ch.a[:, None, :] - targets[None, :, 1, None]
    return bracket(da_r if opts.use_resp else np.zeros_like(da_r), ch.valid)
