// Matched cone-beam backprojection: the exact transpose of kernels/voxel_project.cl
// (clrecon.reconstruction.iterative.cone_backprojector.backproject_volume).
//
// Each work-item takes one ray (column, row, view), repeats the forward kernel's ray set-up
// line for line (clip to the box, dominant axis k, slab range, in-plane coordinates at each
// plane), and where the forward kernel reads four voxels with the bilinear weights
//     w_i (1 - fj)(1 - fl), w_i fj (1 - fl), w_i (1 - fj) fl, w_i fj fl   (times len / |b_k|)
// it adds y[ray] times the same weights to the same four voxels. Two voxels coincide when an
// in-plane axis is one voxel thick (dj or dl = 0): the forward kernel then reads the voxel
// twice, and the transpose adds both weights to it.
//
// The scatter is a 64-bit fixed-point sum (fixed_add.h): bit-identical whatever the order the
// work-items run in, the chunking of the views or the device's scheduling. `acc` holds two
// uints per voxel (lo, hi), [z][y][x] order; `scale` is the host's power of two.
//
// Keep the set-up below identical to voxel_project.cl: the dot-product test
// (tests/reconstruction/test_cone_backprojector.py) fails if the two drift apart.

#include "fixed_add.h"

#ifndef CURVED
#define CURVED 0
#endif

#define VIEW_REC 12

__kernel void voxel_backproject(__global const float *proj, const int nx, const int ny, const int nz,
                                const float hx, const float hy, const float hz,
                                __global const float *views, __global const float *u_mm,
                                __global const float *v_mm, const int n_cols, const int n_rows,
#if CURVED
                                __global const float *vscale,
#endif
                                const float scale, volatile __global uint *acc)
{
    const int col = get_global_id(0), row = get_global_id(1), view = get_global_id(2);
    if (col >= n_cols || row >= n_rows)
        return;
    const size_t o = ((size_t)view * n_rows + row) * n_cols + col;
    const float y = proj[o];
    if (y == 0.0f)
        return;
    __global const float *vr = views + VIEW_REC * view;
#if CURVED
    const float u = u_mm[col], v = v_mm[row] * vscale[col];
#else
    const float u = u_mm[col], v = v_mm[row];
#endif
    const float3 D = (float3)(vr[3], vr[4], vr[5]);
    const float3 eu = (float3)(vr[6], vr[7], vr[8]);
    const float3 ev = (float3)(vr[9], vr[10], vr[11]);
    const float3 d = D + u * eu + v * ev;                       // mm per unit t
    const float len = length(d);
    float a[3] = {vr[0], vr[1], vr[2]};
    float b[3] = {d.x / hx, d.y / hy, d.z / hz};                 // voxels per unit t
    const int n[3] = {nx, ny, nz};
    const int stride[3] = {1, nx, nx * ny};

    float t0 = 0.0f, t1 = INFINITY;
    for (int k = 0; k < 3; ++k) {
        const float lo = -0.5f - a[k], hi = (float)n[k] - 0.5f - a[k];
        if (b[k] != 0.0f) {
            const float ta = lo / b[k], tb = hi / b[k];
            t0 = fmax(t0, fmin(ta, tb));
            t1 = fmin(t1, fmax(ta, tb));
        } else if (lo > 0.0f || hi < 0.0f) {
            t1 = -1.0f;
        }
    }
    const float ab0 = fabs(b[0]), ab1 = fabs(b[1]), ab2 = fabs(b[2]);
    if (!(t1 > t0) || !(len > 0.0f))                            // misses (or d = 0): no weight
        return;
    const int k = (ab0 >= ab1 && ab0 >= ab2) ? 0 : (ab1 >= ab2 ? 1 : 2);
    const int j = k == 0 ? 1 : 0, l = k == 2 ? 1 : 2;
    const float ak = a[k], bk = b[k];
    const float ga = ak + bk * t0, gb = ak + bk * t1;
    const float glo = clamp(fmin(ga, gb), -0.5f, (float)n[k] - 0.5f);
    const float ghi = clamp(fmax(ga, gb), -0.5f, (float)n[k] - 0.5f);
    const int i_lo = clamp((int)floor(glo + 0.5f), 0, n[k] - 1);
    const int i_hi = clamp((int)floor(ghi + 0.5f), 0, n[k] - 1);
    const float rj = b[j] / bk, rl = b[l] / bk;
    const float cj = a[j] - rj * ak, cl = a[l] - rl * ak;
    const int nj = n[j], nl = n[l], sj = stride[j], sl = stride[l], sk = stride[k];
    const float gjmax = (float)(nj - 1), glmax = (float)(nl - 1);
    const int j0max = max(nj - 2, 0), l0max = max(nl - 2, 0);
    const int dj = nj > 1 ? sj : 0, dl = nl > 1 ? sl : 0;
    const float ys = y * (len / fabs(bk));                       // the forward's final g_k -> mm factor
    for (int i = i_lo; i <= i_hi; ++i) {
        const float w = fmin((float)i + 0.5f, ghi) - fmax((float)i - 0.5f, glo);
        const float gj = clamp(cj + rj * (float)i, 0.0f, gjmax);
        const float gl = clamp(cl + rl * (float)i, 0.0f, glmax);
        const int j0 = min((int)gj, j0max), l0 = min((int)gl, l0max);
        const float fj = gj - (float)j0, fl = gl - (float)l0;
        const size_t p = (size_t)i * sk + (size_t)j0 * sj + (size_t)l0 * sl;
        const float yw = ys * w;
        const float e0 = yw * (1.0f - fl), e1 = yw * fl;
        fixed_add(acc + 2 * p, e0 * (1.0f - fj), scale);
        fixed_add(acc + 2 * (p + dj), e0 * fj, scale);
        fixed_add(acc + 2 * (p + dl), e1 * (1.0f - fj), scale);
        fixed_add(acc + 2 * (p + dl + dj), e1 * fj, scale);
    }
}
