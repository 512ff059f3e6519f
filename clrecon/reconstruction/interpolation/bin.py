"""``bin``: conventional phase binning.

Mean of the points inside the target's bin: cardiac [c* - wc/2, c* + wc/2) circular,
amplitude [a* - wa/2, a* + wa/2). An empty bin gives the nearest point (so a target always
gets a row; the bin baseline's artefacts come from motion inside the bin, not from missing
data). wc = ``cardiac_bin_width``, wa = ``resp_bin_width``.
"""

from __future__ import annotations

import numpy as np

from clrecon.reconstruction.interpolation._common import take
from clrecon.reconstruction.interpolation.registry import register_method


@register_method(name="bin", label="bin", neighbours=None, target_grid="5d", axes=("cardiac", "resp"),
                 five_d=False, marker="s", rank=3)
def weights(ch, targets, dc, da, d2, opts):
    return _bin(ch, dc, da, d2, opts.cardiac_bin_width, opts.resp_bin_width, opts.use_cardiac, opts.use_resp)


def _bin(ch, dc, da, d2, cardiac_bin_width, resp_bin_width, use_cardiac, use_resp):
    inside = np.isfinite(d2)
    if use_cardiac:
        inside &= (dc >= -0.5 * cardiac_bin_width) & (dc < 0.5 * cardiac_bin_width)
    if use_resp:
        inside &= (da >= -0.5 * resp_bin_width) & (da < 0.5 * resp_bin_width)
    count = inside.sum(axis=-1)
    K = max(int(count.max(initial=0)), 1)
    order = np.argsort(~inside, axis=-1, kind="stable")[..., :K]
    member = take(inside, order)
    w = np.where(member, 1.0 / np.maximum(count, 1)[..., None], 0.0)
    idx = np.where(member, order, 0)
    empty = count == 0  # empty bin -> nearest point
    if np.any(empty):
        near = np.argmin(d2, axis=-1)
        idx[..., 0] = np.where(empty, near, idx[..., 0])
        w[..., 0] = np.where(empty, 1.0, w[..., 0])
    return idx, w
