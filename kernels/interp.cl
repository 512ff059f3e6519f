// Phase-space interpolation kernels (docs/algorithms.md "Phase-space interpolation"; 5DCT paper 2.2).
//
// local_linear_weights: per row (one (slice, view, target)), the weights l of the local
//   weighted linear regression  y ~ b0 + b1 dc + b2 da,  value b0 = l^T y; a per-row guard
//   flag drops the dc and/or da slope column (extrapolation guard).
// apply_weights_interleaved16_cols8: rows of the output = weighted sums of rebinned rows, written
//   straight into the batched backprojector's layout (the reconstruction's kernel). Its earlier
//   versions (apply_weights, apply_weights_interleaved16, apply_weights_interleaved16_loop) are
//   kept as references in kernels/reference/interp_reference.cl (tests and benchmarks only).
//
// Build options: USE_DOUBLE (compute the 3x3 solve in double; needs cl_khr_fp64),
// K_SLOTS (points per row, 8 for the paper's two-per-quadrant selection).

#ifdef USE_DOUBLE
#pragma OPENCL EXTENSION cl_khr_fp64 : enable
typedef double real;
#else
typedef float real;
#endif

#ifndef K_SLOTS
#define K_SLOTS 8
#endif

#define PI_R ((real)3.141592653589793)

// Local weighted linear regression, solved in centred form.
//
// With w_j the similarity weights, S0 = sum w, m = sum w p / S0 (p_j = (dc_j, da_j)) and
// C = sum w (p - m)(p - m)^T / S0, the normal-equation solution of the paper,
// l^T = e1^T (X^T W X)^-1 X^T W, is identical to
//     l_j = w_j / S0 * (1 - m^T C^-1 (p_j - m)),
// which keeps the intercept out of the 2x2 solve (better conditioned in float32) and makes
// the degenerate cases explicit through the eigenvalues lam1 >= lam2 >= 0 of C, compared
// with thresh = max(rcond * D2, spread2), D2 = sum w |p|^2 / S0 the weighted mean squared
// distance of the points to the target (scale of the problem):
//   lam2 > thresh                  full fit b0 + b1 dc + b2 da (the paper's)
//   lam1 > thresh >= lam2          points (nearly) collinear, or a thin cloud far from the
//                                  target: fit b0 + b s along the principal direction s
//                                  (drops the degenerate direction; exact for the 1-D
//                                  no-cardiac / no-breathing cases where dc or da is 0)
//   lam1 <= thresh                 points coincide: weighted mean
// In every branch sum_j l_j = 1 exactly (in exact arithmetic) and nothing divides by zero.
// Relative to D2 the extrapolation is bounded (|g . (p - m)| <~ 1 / rcond), which bounds
// the float32 build's error by ~eps / rcond instead of letting it grow without limit.
//
// Weights are computed from log-weights minus their maximum, so the largest weight is 1:
// no underflow of all weights, whatever kappa, sigma and the distances. Relative weights
// below exp(log_floor) are set to zero in both precisions (the float64 reference does the
// same), so float32 underflow never changes which points take part. The cardiac term
// kappa (cos 2 pi x - 1) is evaluated as -2 kappa sin^2(pi x) (no cancellation near x = 0).
//
// Extrapolation guard: bit 1 of guard[i] drops the dc slope column, bit 2 the da slope column
// (the host sets them where every selected point lies on one side of the target along that
// axis). The weights w are computed from the true differences first; a guarded axis' coordinate
// is then set to 0 for every point, so the solve below fits y ~ b0 + b2 da, y ~ b0 + b1 dc or
// the weighted mean, with the same conditioning tests on the remaining column. guard = 0 runs
// the same operations as the plain fit.
//
// Layout (structure of arrays, row fastest): dc[k * n + i], da[k * n + i], l[k * n + i].
// Slots k >= count[i] are ignored and get l = 0.
__kernel void local_linear_weights(__global const real *dc,    // (K_SLOTS, n) signed circular dc
                                   __global const real *da,    // (K_SLOTS, n) a - a*
                                   __global const int *count,  // (n,) valid slots, first ones
                                   __global const int *guard,  // (n,) bit 1: drop dc slope, bit 2: da
                                   __global real *l_out,       // (K_SLOTS, n) weights
                                   const int n,
                                   const real kappa,
                                   const real inv_two_sigma2,  // 1 / (2 sigma^2)
                                   const real rcond,
                                   const real spread2,
                                   const real log_floor)       // log of the relative weight floor
{
    const int i = get_global_id(0);
    if (i >= n)
        return;
    const int cnt = clamp(count[i], 0, K_SLOTS);
    const int gd = guard[i];

    real x[K_SLOTS], y[K_SLOTS], w[K_SLOTS];
    real lmax = -INFINITY;
    for (int k = 0; k < K_SLOTS; ++k) {
        x[k] = (k < cnt) ? dc[k * n + i] : (real)0;
        y[k] = (k < cnt) ? da[k * n + i] : (real)0;
        const real sp = sin(PI_R * x[k]);
        w[k] = (real)-2 * kappa * sp * sp - y[k] * y[k] * inv_two_sigma2;
        if (k < cnt)
            lmax = fmax(lmax, w[k]);
        // guarded axis: out of the fit from here on (its kernel weight above stays)
        if (gd & 1)
            x[k] = (real)0;
        if (gd & 2)
            y[k] = (real)0;
    }
    real s0 = 0, sx = 0, sy = 0;
    for (int k = 0; k < K_SLOTS; ++k) {
        const real rel = w[k] - lmax;
        w[k] = (k < cnt && rel >= log_floor) ? exp(rel) : (real)0;
        s0 += w[k];
        sx += w[k] * x[k];
        sy += w[k] * y[k];
    }
    if (cnt == 0) {  // nothing to fit: all-zero weights (the host never sends such rows)
        for (int k = 0; k < K_SLOTS; ++k)
            l_out[k * n + i] = (real)0;
        return;
    }
    const real mx = sx / s0, my = sy / s0;
    real cxx = 0, cxy = 0, cyy = 0;
    for (int k = 0; k < K_SLOTS; ++k) {
        const real ex = x[k] - mx, ey = y[k] - my;
        cxx += w[k] * ex * ex;
        cxy += w[k] * ex * ey;
        cyy += w[k] * ey * ey;
    }
    cxx /= s0; cxy /= s0; cyy /= s0;

    const real tr = cxx + cyy;
    const real hd = (real)0.5 * (cxx - cyy);
    const real lam1 = (real)0.5 * tr + sqrt(hd * hd + cxy * cxy);
    const real det = cxx * cyy - cxy * cxy;
    const real lam2 = (lam1 > (real)0) ? det / lam1 : (real)0;

    // g = C^+ m (C^+ symmetric), so m^T C^+ (p - m) = g . (p - m).
    const real thresh = fmax(rcond * (tr + mx * mx + my * my), spread2);
    real gx = 0, gy = 0;
    if (lam2 > thresh) {
        gx = (cyy * mx - cxy * my) / det;
        gy = (-cxy * mx + cxx * my) / det;
    } else if (lam1 > thresh) {
        // principal eigenvector of C; take the better-conditioned of the two formulas
        real ex = cxy, ey = lam1 - cxx;
        const real fx = lam1 - cyy, fy = cxy;
        if (fx * fx + fy * fy > ex * ex + ey * ey) { ex = fx; ey = fy; }
        const real nrm = sqrt(ex * ex + ey * ey);
        ex /= nrm; ey /= nrm;
        const real proj = (ex * mx + ey * my) / lam1;
        gx = proj * ex;
        gy = proj * ey;
    }
    for (int k = 0; k < K_SLOTS; ++k) {
        const real lk = w[k] / s0 * ((real)1 - gx * (x[k] - mx) - gy * (y[k] - my));
        l_out[k * n + i] = (k < cnt) ? lk : (real)0;
    }
}

// apply_weights straight into the batched backprojector's layout (clrecon.reconstruction.fbp.interleave_batch):
// out16[g][v][cp][lane] = sum_k weight16[g, v, k, lane] * rows[index16[g, v, k, lane], clamp(cp - 1, 0, C - 1)]
// for sinogram b = 16 g + lane, cp = 0 .. n_cols + 1 (one replica of each edge column on either side).
// The sinograms never go back to the host: (filtered) rows in, backprojector input out.
//
// Work-item (cp, v, g) owns the 16 lanes of one column. The slot count is the build option
// APPLY_K (one build per K, the loop unrolled) and a zero weight is a select, not a branch: with
// no loop left inside the work-item, PoCL vectorises across work-items (neighbouring columns of the
// same rows); the index and weight are lane-inner (G, V, K, 16), one 16-lane load each per slot, and the
// 16 lanes go out in one 16-lane store. The host puts index 0 wherever the weight is 0, so the row read
// there is in range, and the select keeps whatever it holds (a NaN too) out of the sum. Per lane the
// slots are summed in k order exactly as the loop with a branch did (until 2026-12-03: a dynamic K,
// `if (w != 0)`, lane-major index/weight; bit-identical sums, 1.6-2.2x slower: docs/kernels.md).
#include "interp16.h"

// apply_weights_interleaved16's sums (kernels/reference/interp_reference.cl), 8 padded columns per work-item (the reconstruction's kernel
// since 2026-12-05). Work-item (cb, v, g) owns padded columns cp = 8 cb .. 8 cb + 7 of view v,
// group g. Each slot's 16 rows are read as 8 consecutive columns each (one unaligned 8-float load
// per lane and slot instead of 16 scalar gathers per column), accumulated per lane over those 8
// columns (acc[lane], 8 columns), and written out transposed, one 16-lane store per column. Per
// element the same operation as apply_weights_interleaved16 in the same slot order,
// `acc = w != 0 ? acc + w * r : acc` (one fused multiply-add where the compiler contracts one
// there, as it does there), so the output is the same bit for bit (tests/reconstruction/test_recon_fastpath.py).
// Blocks whose columns need the edge replicas (cp = 0, cp = n_cols + 1) or run past the row take
// the element-wise path of apply_weights_interleaved16 instead, one column at a time.
// Measured at paper-p010's shape: 2.5-2.6x the per-lane kernel at load 3, 1.6-1.8x (K = 8) and
// 1.2-1.3x (K = 3) idle (docs/algorithms.md, "Phase-space interpolation": the per-lane kernel's
// 16 scalar gathers per slot were its cost, not memory).
typedef float float8_unaligned __attribute__((ext_vector_type(8), aligned(4)));
#define COLS8_LANE(L)                                                                                         \
    {                                                                                                         \
        const float8 wl = (float8)(weight[sk + L]);                                                           \
        const float8 r = *(__global const float8_unaligned *)(rows + (size_t)index[sk + L] * (size_t)n_cols + col0); \
        acc[L] = wl != 0.0f ? acc[L] + wl * r : acc[L];                                                       \
    }
// column c of the block: lane l's value to out lane l (scalar stores: a 16-vector gathered from the 16
// accumulators crashes Oclgrind 21.10's uninitialised-value plugin)
#define COLS8_STORE(c, s)                                                                                     \
    o[(c) * 16 + 0] = acc[0].s; o[(c) * 16 + 1] = acc[1].s; o[(c) * 16 + 2] = acc[2].s;                       \
    o[(c) * 16 + 3] = acc[3].s; o[(c) * 16 + 4] = acc[4].s; o[(c) * 16 + 5] = acc[5].s;                       \
    o[(c) * 16 + 6] = acc[6].s; o[(c) * 16 + 7] = acc[7].s; o[(c) * 16 + 8] = acc[8].s;                       \
    o[(c) * 16 + 9] = acc[9].s; o[(c) * 16 + 10] = acc[10].s; o[(c) * 16 + 11] = acc[11].s;                   \
    o[(c) * 16 + 12] = acc[12].s; o[(c) * 16 + 13] = acc[13].s; o[(c) * 16 + 14] = acc[14].s;                 \
    o[(c) * 16 + 15] = acc[15].s;
__kernel void apply_weights_interleaved16_cols8(__global const float *rows,    // (P, n_cols)
                                                __global const int *index,     // (G, n_views, APPLY_K, 16) into P
                                                __global const float *weight,  // (G, n_views, APPLY_K, 16)
                                                __global float *out,           // (G, n_views, n_cols + 2, 16)
                                                const int n_views,
                                                const int n_cols)
{
    const int cp0 = 8 * get_global_id(0);
    const int v = get_global_id(1);
    const int g = get_global_id(2);
    if (cp0 >= n_cols + 2 || v >= n_views)
        return;
    const size_t gv = (size_t)g * n_views + v;
    const size_t slot = gv * (size_t)APPLY_K * 16;
    __global float *o = out + (gv * (size_t)(n_cols + 2) + (size_t)cp0) * 16;
    if (cp0 >= 1 && cp0 + 7 <= n_cols) {  // columns col = cp - 1 = cp0 - 1 .. cp0 + 6, all in the row
        const int col0 = cp0 - 1;
        float8 acc[16];
#pragma unroll
        for (int l = 0; l < 16; ++l)
            acc[l] = (float8)(0.0f);
#pragma unroll
        for (int k = 0; k < APPLY_K; ++k) {
            const size_t sk = slot + k * 16;  // the slot's 16 lanes (weights and indices read as scalars:
                                              // splatting a lane of a 16-vector crashes Oclgrind 21.10's
                                              // uninitialised-value plugin)
            COLS8_LANE(0) COLS8_LANE(1) COLS8_LANE(2) COLS8_LANE(3) COLS8_LANE(4) COLS8_LANE(5) COLS8_LANE(6)
            COLS8_LANE(7) COLS8_LANE(8) COLS8_LANE(9) COLS8_LANE(10) COLS8_LANE(11) COLS8_LANE(12)
            COLS8_LANE(13) COLS8_LANE(14) COLS8_LANE(15)
        }
        COLS8_STORE(0, s0) COLS8_STORE(1, s1) COLS8_STORE(2, s2) COLS8_STORE(3, s3)
        COLS8_STORE(4, s4) COLS8_STORE(5, s5) COLS8_STORE(6, s6) COLS8_STORE(7, s7)
        return;
    }
    for (int c = 0; c < 8 && cp0 + c < n_cols + 2; ++c) {  // an edge block: apply_weights_interleaved16's path
        STORE16(lanes_of_column(rows, index, weight, slot, row_column(cp0 + c, n_cols), n_cols), o + c * 16);
    }
}
#undef COLS8_LANE
#undef COLS8_STORE
