"""The reference kernels (``kernels/reference/``): kept only as same-run references for the
benchmarks and as independent cross-checks for the tests; nothing in the pipeline runs them.

- :func:`backproject_single`: one sinogram per work-item, the straightforward fan-beam
  backprojection (``reference/backproject_single.cl``), against the batched kernel of
  :func:`clrecon.reconstruction.fbp.backproject`;
- :func:`apply_weights`: the interpolation's weighted sum, one work-item per output element
  (``reference/interp_reference.cl``), against its float64 NumPy reference
  (:func:`clrecon.reconstruction.interpolation.apply.apply_weights_reference`);
- :func:`apply_padded_interleaved_lanes` and :func:`apply_interleaved_loop`: earlier interpolation
  kernels of the reconstruction, the same sums bit for bit as
  :func:`clrecon.reconstruction.interpolation.apply.apply_padded_interleaved` (8 columns per work-item);
- :func:`mc_backproject_scalar`: the motion-compensated backprojection one voxel per work-item
  (``reference/mc_backproject_scalar.cl``, the pipeline's earlier kernel), against
  :class:`clrecon.reconstruction.motion.backproject.MCBackprojector`'s 8 voxels per work-item.
  Which kernel ran when: docs/results/code-history.md "Which kernel ran when".

The projector's unculled build (``CULL=0`` of ``kernels/project_cull.cl`` and ``project.cl``,
``project(..., cull=False)``) is a build option of the pipeline's own kernels, not a file here.
"""

from __future__ import annotations

import numpy as np

from clrecon.core.runtime import get_runtime
from clrecon.reconstruction import fbp
from clrecon.reconstruction.interpolation import apply as apply_mod
from clrecon.reconstruction.interpolation._common import LOCAL as _LOCAL

#: The reference sources, relative to ``kernels/``.
BACKPROJECT_SINGLE = "reference/backproject_single.cl"
INTERP_REFERENCE = "reference/interp_reference.cl"
MC_BACKPROJECT_SCALAR = "reference/mc_backproject_scalar.cl"
#: Local size (x, y) of the scalar motion-compensated kernel (one voxel per work-item).
MC_SCALAR_LOCAL = (8, 8)


def backproject_single(filtered, geom: fbp.FanBeamGeometry, *, runtime=None) -> np.ndarray:
    """Same as :func:`clrecon.reconstruction.fbp.backproject` with the straightforward
    one-sinogram-per-work-item kernel (about 20x slower on PoCL); shapes as there."""
    a = fbp._check_sinograms(filtered, geom, "filtered")
    rt = runtime or get_runtime()
    kern = rt.kernel(BACKPROJECT_SINGLE, "backproject_single", _fast=True, **fbp._defines(geom))
    trig = rt.to_device(fbp._trig_table(geom))
    sino_buf = rt.to_device(a)
    out_buf = rt.empty(a.shape[:1] + (geom.ny, geom.nx))
    ev = kern(rt.queue, fbp._global_size(geom, a.shape[0]), fbp.LOCAL_SIZE + (1,), sino_buf, trig, out_buf,
              *fbp._geometry_args(geom))
    return rt.from_device(out_buf, (a.shape[0], geom.ny, geom.nx), wait_for=[ev])


def apply_weights(rows, index, weight, rt=None) -> np.ndarray:
    """Weighted sums of rebinned rows on the OpenCL device, one work-item per output element.

    ``rows`` (P, C) (converted to float32); ``index`` (B, K) int, the row of each slot (only
    slots with non-zero weight are read); ``weight`` (B, K) float (converted to float32).
    Returns float32 (B, C): ``out[b] = sum_k weight[b, k] * rows[index[b, k]]``.
    """
    rows, index, weight = apply_mod._check_apply(rows, index, weight)
    B, K = index.shape
    C = rows.shape[1]
    if B == 0 or C == 0:
        return np.zeros((B, C), np.float32)
    rt = rt or get_runtime()
    knl = rt.kernel(INTERP_REFERENCE, "apply_weights")
    d_rows = rt.to_device(rows, np.float32, "rows")
    d_idx = rt.to_device(index, np.int32, "index")
    d_w = rt.to_device(weight, np.float32, "weight")
    d_out = rt.empty((B, C), np.float32)
    ev = knl(rt.queue, (-(-C // _LOCAL) * _LOCAL, B), (_LOCAL, 1), d_rows, d_idx, d_w, d_out,
             np.int32(B), np.int32(C), np.int32(K))
    return rt.from_device(d_out, (B, C), np.float32, wait_for=[ev])


def apply_padded_interleaved_lanes(rows: apply_mod.DeviceRows, idx: np.ndarray, wgt: np.ndarray, B: int, rt=None,
                                   out=None):
    """:func:`clrecon.reconstruction.interpolation.apply.apply_padded_interleaved` with the per-lane
    kernel ``apply_weights_interleaved16`` (one padded column per work-item, 16 scalar gathers per
    slot): an earlier kernel of the reconstruction. Same output, bit for bit."""
    return apply_mod._launch_padded(rows, idx, wgt, B, rt, out, "apply_weights_interleaved16", 1, _LOCAL,
                                    source=INTERP_REFERENCE)


def apply_interleaved_loop(rows: apply_mod.DeviceRows, index: np.ndarray, weight: np.ndarray, rt=None, out=None):
    """An earlier interpolation kernel of the reconstruction (``apply_weights_interleaved16_loop``):
    :func:`clrecon.reconstruction.interpolation.apply.apply_weights_interleaved`'s output, bit for bit,
    from lane-major (B, V, K) ``index`` / ``weight`` with a run-time slot count. No validation
    (indices with non-zero weight in [0, P)). Returns ``(buffer, n_groups)``."""
    P, C = rows.shape
    rt = rt or rows.rt
    _, V, K = index.shape
    idx, wgt = apply_mod._pad_lane_major(index, weight)
    G = idx.shape[0] // 16
    d_out = rt.empty((G, V, C + 2, 16), np.float32) if out is None else out
    knl = rt.kernel(INTERP_REFERENCE, "apply_weights_interleaved16_loop")
    d_idx = rt.to_device(idx, np.int32, "index")
    d_w = rt.to_device(wgt, np.float32, "weight")
    knl(rt.queue, (-(-(C + 2) // _LOCAL) * _LOCAL, V, G), (_LOCAL, 1, 1), rows.buf, d_idx, d_w, d_out,
        np.int32(V), np.int32(C), np.int32(K)).wait()
    d_idx.release()
    d_w.release()
    return d_out, G


def mc_backproject_scalar(bp, slot_proj, slot_w, target) -> np.ndarray:
    """What ``bp(slot_proj, slot_w, target)`` returns (``bp`` a
    :class:`clrecon.reconstruction.motion.backproject.MCBackprojector`), computed by the scalar
    reference kernel on the same device buffers: (S, ny, nx) float32."""
    lx, ly = MC_SCALAR_LOCAL
    kern = bp.rt.kernel(MC_BACKPROJECT_SCALAR, "mc_backproject", **{**bp._defines, "LX": lx, "LY": ly})
    gsize = (-(-bp.geom.nx // lx) * lx, -(-bp.geom.ny // ly) * ly, len(bp.slices_z))
    return bp._launch(kern, gsize, MC_SCALAR_LOCAL, slot_proj, slot_w, target, scalar=True)
