// Distance-weighted fan-beam backprojection (kernels/fan_beam.h: the geometry, its conventions
// and the PoCL notes), the batched kernel the reconstruction runs. Its one-sinogram-per-work-item
// reference is kernels/reference/backproject_single.cl (tests and benchmarks only).

#include "fan_beam.h"

// Batched kernel: 16 filtered sinograms interleaved as [view][column][batch] and read as
// one float16 per interpolation tap. The 16 lanes are the SIMD width; the geometry of a
// (pixel, view) pair is computed once for all 16 (docs/fbp.md "Fan-beam FBP": 3.9 vs 0.36 G
// updates/s for one sinogram per work-item). Each work-item does this for TWO groups of 16
// (g = 2 gp and 2 gp + 1, each in its own [view][column][16] plane, so the layout is that of
// clrecon.reconstruction.fbp.interleave_batch), sharing the geometry over 32 sinograms: measured 1.2x
// (10.2 -> 12.5 G updates/s at 128^2, 9.8 -> 11.5 at 512^2, on an idle 2-core machine).
// With an odd number of groups the last work-items read their group twice and store once.
//
// Columns are padded by one replica of the edge column on each side (n_cols + 2 stored),
// so the taps of any pixel inside the FOV are in range without a clamp in the loop.
//
// The work-group sweeps the views in chunks of VCHUNK separated by barriers: PoCL runs the
// work-items of a group one after another between barriers, so without the chunks each
// work-item would stream all views (~1.5 MB for an 8x8 tile) before its neighbour reuses
// them; with them the group's rows of a chunk stay in L1 (measured 1.35x faster).
//
// Work-item (ix, iy, gp): pixel (ix, iy) of the 32 (or 16) images of groups 2 gp, 2 gp + 1.
//   sino16: (n_groups, n_views, n_cols + 2) float16     out: (n_groups * 16, ny, nx) float

#include "store16.h"

__kernel __attribute__((reqd_work_group_size(LX, LY, 1)))
void backproject_batched16x2(__global const float16 *restrict sino16,
                             __global const float2 *restrict trig,
                             __global float *restrict out,
                             GEOMETRY_ARGS,
                             const int n_groups)
{
    const int ix = get_global_id(0), iy = get_global_id(1), g = 2 * get_global_id(2);
    const bool two = g + 1 < n_groups;  // the same for the whole work-group
    const float x = ((float)ix - 0.5f * (float)(nx - 1)) * voxel_mm;
    const float y = ((float)iy - 0.5f * (float)(ny - 1)) * voxel_mm;
    // no early return: every work-item of the group must reach the barriers
    const bool in_image = ix < nx && iy < ny;
    const bool in_fov = in_image && x * x + y * y <= fov_r2;
    const int stride = n_cols + 2;
    const float centre = COL_CENTRE + 1.0f;  // +1: the left pad column
    const size_t group_size = (size_t)n_views * stride;
    __global const float16 *sino = sino16 + (size_t)g * group_size;
    const size_t second = two ? group_size : 0;  // offset of the second group (none: itself)

    float16 acc0 = (float16)(0.0f), acc1 = (float16)(0.0f);
    for (int j0 = 0; j0 < n_views; j0 += VCHUNK) {
        if (in_fov) {
            const int j1 = j0 + VCHUNK < n_views ? j0 + VCHUNK : n_views;
            __global const float16 *s = sino + (size_t)j0 * stride;
            for (int j = j0; j < j1; ++j, s += stride) {
                float w;
                const float c = fan_column(x, y, trig[j], sdd_over_pitch, centre, &w);
                const int i0 = (int)c;  // c >= 0.5 inside the FOV: truncation is floor
                const float wb = w * (c - (float)i0);
                const float wa = w - wb;
                acc0 += wa * s[i0] + wb * s[i0 + 1];
                acc1 += wa * s[second + i0] + wb * s[second + i0 + 1];
            }
        }
        barrier(CLK_GLOBAL_MEM_FENCE);
    }
    if (!in_image)
        return;
    acc0 *= dbeta;
    acc1 *= dbeta;
    // One store per lane, straight into (B, ny, nx): written once per pixel, so cheap.
    const size_t plane = (size_t)nx * ny;
    __global float *o = out + (size_t)g * 16 * plane + (size_t)iy * nx + ix;
    STORE16(o, plane, acc0)
    if (two) {
        o += 16 * plane;
        STORE16(o, plane, acc1)
    }
}
