// Reference kernels of the phase-space interpolation's weighted sum, kept only as the tests' and
// the benchmarks' same-run references (the reconstruction runs kernels/interp.cl's
// apply_weights_interleaved16_cols8): the plain one-work-item-per-element gather, the per-lane
// interleaved kernel (the reconstruction's from 2026-12-03 to 2026-12-05) and the loop kernel
// (until 2026-12-03). All give the cols8 kernel's sums bit for bit (tests/reconstruction/test_recon_fastpath.py).

// out[b, col] = sum_k weight[b, k] * rows[index[b, k], col].
// One work-item per output element (gather, one owner), column fastest so neighbouring
// work-items read neighbouring columns of the same rebinned row. Zero weights are skipped,
// so an unused slot never reads (or propagates a NaN from) the row it points to.
__kernel void apply_weights(__global const float *rows,    // (P, n_cols) rebinned rows
                            __global const int *index,     // (B, k_slots) into P
                            __global const float *weight,  // (B, k_slots)
                            __global float *out,           // (B, n_cols)
                            const int n_out,
                            const int n_cols,
                            const int k_slots)
{
    const int col = get_global_id(0);
    const int b = get_global_id(1);
    if (col >= n_cols || b >= n_out)
        return;
    float acc = 0.0f;
    for (int k = 0; k < k_slots; ++k) {
        const float wk = weight[b * k_slots + k];
        if (wk != 0.0f)
            acc += wk * rows[(size_t)index[b * k_slots + k] * (size_t)n_cols + (size_t)col];
    }
    out[(size_t)b * (size_t)n_cols + (size_t)col] = acc;
}

#include "interp16.h"

__kernel void apply_weights_interleaved16(__global const float *rows,    // (P, n_cols)
                                          __global const int *index,     // (G, n_views, APPLY_K, 16) into P
                                          __global const float *weight,  // (G, n_views, APPLY_K, 16)
                                          __global float *out,           // (G, n_views, n_cols + 2, 16)
                                          const int n_views,
                                          const int n_cols)
{
    APPLY16_COLUMN
    const size_t gv = (size_t)g * n_views + v;
    STORE16(lanes_of_column(rows, index, weight, gv * (size_t)APPLY_K * 16, col, n_cols),
            out + (gv * (size_t)(n_cols + 2) + (size_t)cp) * 16);
}

// The reconstruction's kernel until 2026-12-03, kept as the same-run reference of
// `bench --only levers` ("interpolation launch"): apply_weights_interleaved16's sums with a run-time
// slot count, a branch per zero weight and lane-major index/weight (16 G, n_views, k_slots); the
// loops inside the work-item keep PoCL from vectorising it (docs/kernels.md, "Making kernels
// fast on PoCL"). Same output, bit for bit.
__kernel void apply_weights_interleaved16_loop(__global const float *rows,    // (P, n_cols)
                                               __global const int *index,     // (16 G, n_views, k_slots) into P
                                               __global const float *weight,  // (16 G, n_views, k_slots)
                                               __global float *out,           // (G, n_views, n_cols + 2, 16)
                                               const int n_views,
                                               const int n_cols,
                                               const int k_slots)
{
    APPLY16_COLUMN
    __global float *o = out + (((size_t)g * n_views + v) * (size_t)(n_cols + 2) + (size_t)cp) * 16;
    for (int lane = 0; lane < 16; ++lane) {
        const size_t slot = ((size_t)(g * 16 + lane) * (size_t)n_views + (size_t)v) * (size_t)k_slots;
        float acc = 0.0f;
        for (int k = 0; k < k_slots; ++k) {
            const float wk = weight[slot + k];
            if (wk != 0.0f)  // fused as the cols8 kernel's sum is, on every driver
                acc = fma(wk, rows[(size_t)index[slot + k] * (size_t)n_cols + (size_t)col], acc);
        }
        o[lane] = acc;
    }
}
