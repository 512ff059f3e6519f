"""``nearest``: the nearest candidate (distance with circular dc)."""

from __future__ import annotations

from clrecon.reconstruction.interpolation._common import nearest
from clrecon.reconstruction.interpolation.registry import register_method


@register_method(name="nearest", label="nearest", neighbours=1, target_grid="5d", axes=("cardiac", "resp"),
                 five_d=False, marker="v", rank=4)
def weights(ch, targets, dc, da, d2, opts):
    return nearest(d2)
