"""Weighted sums of rebinned rows: the interpolation weights applied on the OpenCL device.

:class:`DeviceRows` and :func:`apply_weights_interleaved` (kernel ``apply_weights_interleaved16_cols8``,
``kernels/interp.cl``) write whole sinograms straight into the batched backprojector's layout
(:func:`clrecon.reconstruction.fbp.interleave_batch`); :func:`apply_weights_reference` is the float64
NumPy reference of the weighted sum. The kernel's earlier versions, kept as references for the tests
and the benchmarks, are in ``kernels/reference/`` with their launchers in
:mod:`clrecon.bench.reference_kernels`.
"""

from __future__ import annotations

import numpy as np

from clrecon.core.runtime import get_runtime


def _check_apply(rows, index, weight):
    rows = np.asarray(rows)
    if rows.dtype.kind not in "fiu":
        raise TypeError(f"rows: expected a real numeric array, got dtype {rows.dtype}")
    index = np.asarray(index)
    if index.dtype.kind not in "iu":
        raise TypeError(f"index: expected an integer array, got dtype {index.dtype}")
    weight = np.asarray(weight)
    if weight.dtype.kind != "f":
        raise TypeError(f"weight: expected a float array, got dtype {weight.dtype}")
    if rows.ndim != 2 or index.ndim != 2 or weight.shape != index.shape:
        raise ValueError(f"expected rows (P, C), index and weight (B, K) of equal shape, got "
                         f"{rows.shape}, {index.shape}, {weight.shape}")
    live = weight != 0
    if np.any(live) and (index[live].min() < 0 or index[live].max() >= rows.shape[0]):
        raise ValueError(f"index: entries with non-zero weight must lie in [0, {rows.shape[0]})")
    return rows, np.where(live, index, 0), weight


def apply_weights_reference(rows, index, weight) -> np.ndarray:
    """Float64 NumPy reference of the weighted sum ``out[b] = sum_k weight[b, k] * rows[index[b, k]]``, (B, C)."""
    rows, index, weight = _check_apply(rows, index, weight)
    r = rows.astype(np.float64)
    w = weight.astype(np.float64)
    if r.shape[0] == 0:
        return np.zeros((index.shape[0], r.shape[1]))
    # zero weights do not touch their row (a NaN there must not leak through 0 * NaN)
    return np.einsum("bk,bkc->bc", w, np.where((w != 0)[..., None], r[index], 0.0))


class DeviceRows:
    """Rebinned rows uploaded once, for several :func:`apply_weights_interleaved` calls.

    ``rows`` (P, C) is converted to float32; :meth:`release` frees the device copy (on a
    CPU device it is host memory too, so release it as soon as the slab is done).

    ``share=True`` hands the caller's array to the device instead of copying it where the
    device can read it in place (:meth:`Runtime.share_with_device`: a CPU device, float32,
    C-contiguous, allocated by :func:`clrecon.core.runtime.aligned_empty`); the caller then gives the array up
    (no writes) until :meth:`release`. Same values either way: the kernels read the same floats.
    """

    def __init__(self, rows, rt=None, share: bool = False):
        rows = np.asarray(rows)
        if rows.dtype.kind not in "fiu":
            raise TypeError(f"rows: expected a real numeric array, got dtype {rows.dtype}")
        if rows.ndim != 2:
            raise ValueError(f"rows: expected shape (P, C), got {rows.shape}")
        self.rt = rt or get_runtime()
        self.shape = rows.shape
        self.buf = self.rt.share_with_device(rows, "rows") if share else self.rt.to_device(rows, np.float32, "rows")
        self._host = rows if share else None  # a shared buffer reads this memory: keep it alive

    def release(self) -> None:
        if self.buf is not None:
            self.buf.release()
            self.buf = None
        self._host = None


def apply_weights_interleaved(rows: DeviceRows, index, weight, rt=None):
    """Weighted sums of rebinned rows for whole sinograms, written in the batched backprojector's layout.

    Parameters
    ----------
    rows : DeviceRows
        (P, C) rows on the device.
    index : array_like of int
        (B, V, K): row of ``rows`` for slot k of view v of sinogram b; only slots with
        non-zero weight are read.
    weight : array_like of float
        (B, V, K) weights (converted to float32).
    rt : Runtime, optional

    Returns
    -------
    (buffer, n_groups)
        Device buffer of (n_groups, V, C + 2, 16) float32, n_groups = ceil(B / 16): the
        layout of :func:`clrecon.reconstruction.fbp.interleave_batch` (sinogram ``16 g + lane`` in lane
        ``lane`` of group ``g``; lanes beyond B are zero), for
        :func:`clrecon.reconstruction.fbp.backproject_interleaved`.
    """
    index = np.asarray(index)
    weight = np.asarray(weight)
    if index.dtype.kind not in "iu":
        raise TypeError(f"index: expected an integer array, got dtype {index.dtype}")
    if weight.dtype.kind != "f":
        raise TypeError(f"weight: expected a float array, got dtype {weight.dtype}")
    if index.ndim != 3 or weight.shape != index.shape:
        raise ValueError(f"expected index and weight (B, V, K) of equal shape, got {index.shape}, {weight.shape}")
    P, C = rows.shape
    B, V, K = index.shape
    live = weight != 0
    if np.any(live) and (index[live].min() < 0 or index[live].max() >= P):
        raise ValueError(f"index: entries with non-zero weight must lie in [0, {P})")
    idx, wgt = pad_interleaved(index, weight)
    return apply_padded_interleaved(rows, idx, wgt, B, rt=rt)


def _pad_lane_major(index: np.ndarray, weight: np.ndarray):
    """``(index, weight)`` (B, V, K) padded to (16 G, V, K) int32/float32, G = ceil(B / 16): the
    sinograms beyond B zero-weight, index 0 wherever the weight is 0."""
    B, V, K = index.shape
    G = max(1, -(-B // 16))
    idx = np.zeros((G * 16, V, K), np.int32)
    wgt = np.zeros((G * 16, V, K), np.float32)
    idx[:B] = np.where(weight != 0, index, 0)
    wgt[:B] = weight
    return idx, wgt


def pad_interleaved(index: np.ndarray, weight: np.ndarray):
    """``(index, weight)`` (B, V, K) as the lane-inner int32/float32 pair that
    :func:`apply_padded_interleaved` takes, each (G, V, K, 16) with G = ceil(B / 16): sinogram
    ``16 g + lane`` in lane ``lane`` of group ``g``, the lanes beyond B zero-weight sinograms,
    index 0 wherever the weight is 0. The caller guarantees that every index with non-zero weight
    lies in ``[0, P)`` (the reconstruction makes them so); done once per method instead of once
    per launch."""
    _, V, K = index.shape
    idx, wgt = _pad_lane_major(index, weight)
    G = idx.shape[0] // 16
    return (np.ascontiguousarray(idx.reshape(G, 16, V, K).transpose(0, 2, 3, 1)),
            np.ascontiguousarray(wgt.reshape(G, 16, V, K).transpose(0, 2, 3, 1)))


#: Padded columns per work-item of ``apply_weights_interleaved16_cols8`` and its work-group width
#: (work-items): 8 x 8 measured best at paper-p010's shape at load 3 (2.9x the per-lane kernel; 4 and
#: 16 work-items 2.6x and 2.9x; idle, the kernel is 1.6-1.8x at K = 8: docs/kernels.md).
COLS_PER_ITEM = 8
COLS8_LOCAL = 8


def apply_padded_interleaved(rows: DeviceRows, idx: np.ndarray, wgt: np.ndarray, B: int, rt=None, out=None):
    """:func:`apply_weights_interleaved` of already padded, checked arrays (:func:`pad_interleaved`):
    ``idx`` int32 and ``wgt`` float32 of shape (G, V, K, 16) (a slice of whole groups), of which
    the first ``B`` sinograms are real. No validation here (the public function does it).

    ``out``: a device buffer of at least G V (C + 2) 16 floats to write into (and return) instead
    of a new one; the caller keeps it from launch to launch (a new buffer of this size is fresh
    memory: on the 2-core machine its first touch costs about 0.7 ms per MB, as much as the kernel).

    Kernel ``apply_weights_interleaved16_cols8`` (8 columns per work-item); the same bits as the
    per-lane reference kernel (:func:`clrecon.bench.reference_kernels.apply_padded_interleaved_lanes`),
    an earlier kernel of the reconstruction."""
    return _launch_padded(rows, idx, wgt, B, rt, out, "apply_weights_interleaved16_cols8", COLS_PER_ITEM, COLS8_LOCAL)


def _launch_padded(rows, idx, wgt, B, rt, out, kernel_name, cols_per_item, local, source="interp.cl"):
    P, C = rows.shape
    rt = rt or rows.rt
    V, K = idx.shape[1:3]
    G = max(1, -(-B // 16))
    nbytes = G * V * (C + 2) * 16 * 4
    if out is not None and out.size < nbytes:
        raise ValueError(f"out: a buffer of {out.size} bytes, the launch writes {nbytes}")
    d_out = rt.empty((G, V, C + 2, 16), np.float32) if out is None else out
    if B == 0 or P == 0 or C == 0 or V == 0 or K == 0:
        rt.cl.enqueue_fill_buffer(rt.queue, d_out, np.float32(0), 0, G * V * (C + 2) * 16 * 4).wait()
        return d_out, G
    idx, wgt = idx[:G], wgt[:G]
    knl = rt.kernel(source, kernel_name, APPLY_K=int(K))  # one build per slot count
    d_idx = rt.to_device(idx, np.int32, "index")
    d_w = rt.to_device(wgt, np.float32, "weight")
    items = -(-(C + 2) // cols_per_item)
    ev = knl(rt.queue, (-(-items // local) * local, V, G), (local, 1, 1), rows.buf, d_idx, d_w, d_out,
             np.int32(V), np.int32(C))
    ev.wait()
    d_idx.release()
    d_w.release()
    return d_out, G
