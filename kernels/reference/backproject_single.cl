#include "fan_beam.h"

// Reference kernel: one sinogram per work-item in the plain (B, n_views, n_cols) layout,
// with the edge clamp in the loop -- the straightforward way, kept as the benchmark's same-run
// reference and as the tests' independent cross-check of kernels/backproject.cl's batched
// kernel (its layout, padding and chunking).
// Work-item (ix, iy, b).   sino: (B, n_views, n_cols) float    out: (B, ny, nx) float
__kernel __attribute__((reqd_work_group_size(LX, LY, 1)))
void backproject_single(__global const float *restrict sino,
                        __global const float2 *restrict trig,
                        __global float *restrict out,
                        GEOMETRY_ARGS)
{
    const int ix = get_global_id(0), iy = get_global_id(1), b = get_global_id(2);
    if (ix >= nx || iy >= ny)
        return;
    const float x = ((float)ix - 0.5f * (float)(nx - 1)) * voxel_mm;
    const float y = ((float)iy - 0.5f * (float)(ny - 1)) * voxel_mm;
    const float last = (float)(n_cols - 1);
    float acc = 0.0f;
    if (x * x + y * y <= fov_r2) {
        __global const float *s = sino + (size_t)b * n_views * n_cols;
        for (int j = 0; j < n_views; ++j, s += n_cols) {
            float w;
            float c = fan_column(x, y, trig[j], sdd_over_pitch, COL_CENTRE, &w);
            c = c < 0.0f ? 0.0f : (c > last ? last : c);
            int i0 = (int)c;
            i0 = i0 > n_cols - 2 ? n_cols - 2 : i0;
            const float t = c - (float)i0;
            acc += w * ((1.0f - t) * s[i0] + t * s[i0 + 1]);
        }
        acc *= dbeta;
    }
    out[((size_t)b * ny + iy) * nx + ix] = acc;
}
