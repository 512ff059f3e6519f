// Matched cone-beam backprojection: the exact transpose of kernels/voxel_project.cl
// (clrecon.reconstruction.iterative.cone_backprojector.backproject_volume).
//
// Each work-item takes one ray (column, row, view), walks it with the forward kernel's own ray
// set-up and samples (joseph_ray.h: clip to the box, dominant axis k, slab range, in-plane
// coordinates at each plane), and where the forward kernel reads four voxels with the bilinear weights
//     w_i (1 - fj)(1 - fl), w_i fj (1 - fl), w_i (1 - fj) fl, w_i fj fl   (times len / |b_k|)
// it adds y[ray] times the same weights to the same four voxels. Two voxels coincide when an
// in-plane axis is one voxel thick (dj or dl = 0): the forward kernel then reads the voxel
// twice, and the transpose adds both weights to it.
//
// The scatter is a 64-bit fixed-point sum (fixed_add.h): bit-identical whatever the order the
// work-items run in, the chunking of the views or the device's scheduling. `acc` holds two
// uints per voxel (lo, hi), [z][y][x] order; `scale` is the host's power of two.
//
// The dot-product test (tests/reconstruction/test_cone_backprojector.py) checks the transpose.
//
// PAIR = 1: two projections on the same rays in one walk (proj, scale, acc as above and proj2,
// scale2, acc2): A^T proj and A^T proj2 with each accumulator's values exactly those of two
// single calls with the same scales. OS-SART's first visit of a subset needs both its update
// A^T r and its column sums A^T m (the ray mask); the walk and the sample set-up are shared.

#include "fixed_add.h"
#include "joseph_ray.h"

#ifndef CURVED
#define CURVED 0
#endif
#ifndef PAIR
#define PAIR 0
#endif

// one sample's value yw to the four voxels the projector reads, with its bilinear weights
inline void scatter4(volatile __global uint *acc, const float yw, const size_t p, const int dj, const int dl,
                     const float fj, const float fl, const float scale)
{
    const float e0 = yw * (1.0f - fl), e1 = yw * fl;
    fixed_add(acc + 2 * p, e0 * (1.0f - fj), scale);
    fixed_add(acc + 2 * (p + dj), e0 * fj, scale);
    fixed_add(acc + 2 * (p + dl), e1 * (1.0f - fj), scale);
    fixed_add(acc + 2 * (p + dl + dj), e1 * fj, scale);
}

__kernel void voxel_backproject(__global const float *proj, const int nx, const int ny, const int nz,
                                const float hx, const float hy, const float hz,
                                __global const float *views, __global const float *u_mm,
                                __global const float *v_mm, const int n_cols, const int n_rows,
#if CURVED
                                __global const float *vscale,
#endif
                                const float scale, volatile __global uint *acc
#if PAIR
                                , __global const float *proj2, const float scale2, volatile __global uint *acc2
#endif
                                )
{
    const int col = get_global_id(0), row = get_global_id(1), view = get_global_id(2);
    if (col >= n_cols || row >= n_rows)
        return;
    const size_t o = ((size_t)view * n_rows + row) * n_cols + col;
    const float y = proj[o];
#if PAIR
    const float y2 = proj2[o];
    if (y == 0.0f && y2 == 0.0f)
        return;
#else
    if (y == 0.0f)
        return;
#endif
#if CURVED
    const float u = u_mm[col], v = v_mm[row] * vscale[col];
#else
    const float u = u_mm[col], v = v_mm[row];
#endif
    JosephRay r;
    if (!joseph_ray(views + VIEW_REC * view, u, v, nx, ny, nz, hx, hy, hz, &r))
        return;                                                 // misses (or d = 0): no weight
    const float ys = y * r.mm;                                  // the forward's final g_k -> mm factor
#if PAIR
    const float ys2 = y2 * r.mm;
#endif
    for (int i = r.i_lo; i <= r.i_hi; ++i) {
        size_t p;
        float fj, fl;
        const float w = joseph_sample(&r, i, &p, &fj, &fl);
        scatter4(acc, ys * w, p, r.dj, r.dl, fj, fl, scale);
#if PAIR
        scatter4(acc2, ys2 * w, p, r.dj, r.dl, fj, fl, scale2);
#endif
    }
}
