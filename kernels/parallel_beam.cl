// Fan-to-parallel rebinning and parallel-beam backprojection, batched 16 sinograms per float16
// (recon.backprojector = "parallel-rebin"; host side: clrecon/reconstruction/parallel_fbp.py).
//
// Conventions (clrecon/core/conventions.py and kernels/backproject.cl): fan view j at
// beta_j = beta0 + j dbeta (dbeta = 2 pi / V), the ray through fan angle gamma of view beta is the
// parallel ray (theta, s) with theta = beta - gamma + pi/2, s = SID sin gamma, where a parallel
// ray (theta, s) is the line {x cos theta + y sin theta = s}. Parallel view i is at
// theta_i = beta0 + pi/2 + i dbeta, i in [0, V/2): theta covers pi with the fan's step.
//
// Rebinning: parallel sample (i, k) (s_k = (k - (n_s - 1)/2) ds) is the mean of its two fan rays,
// the direct one (gamma_k = asin(s_k / SID), fan view i + gamma_k / dbeta) and the conjugate one
// (-gamma_k, fan view i + V/2 - gamma_k / dbeta), each bilinear in (view, column). The host table
// holds per s sample: (view offset direct, padded column direct, view offset conjugate, padded
// column conjugate); the view offsets are made >= 0 (+V where needed), the padded columns (the
// fan input has one edge replica on either side, clrecon.reconstruction.fbp.interleave_batch)
// are clamped to [0, n_cols + 1 - 2^-8] on the host, so no clamp is needed here.
//
//   fan16: (G, V, n_cols + 2) float16      table: (n_s,) float4      par16: (G, V/2, n_s) float16
__kernel void rebin_parallel16(__global const float16 *restrict fan16,
                               __global const float4 *restrict table,
                               __global float16 *restrict par16,
                               const int n_views, const int n_cols, const int n_s)
{
    const int k = get_global_id(0), i = get_global_id(1), g = get_global_id(2);
    const int n_par = n_views / 2;
    if (k >= n_s || i >= n_par)
        return;
    const int stride = n_cols + 2;
    __global const float16 *f = fan16 + (size_t)g * n_views * stride;
    const float4 t = table[k];
    float16 acc = (float16)(0.0f);
    for (int r = 0; r < 2; ++r) {
        const float vf = (float)i + (r == 0 ? t.x : t.z);
        const float cf = r == 0 ? t.y : t.w;
        const int v0 = (int)vf;  // vf >= 0: truncation is floor
        const float tv = vf - (float)v0;
        const int va = v0 % n_views, vb = (v0 + 1) % n_views;
        const int c0 = (int)cf;  // cf >= 0
        const float tc = cf - (float)c0;
        __global const float16 *ra = f + (size_t)va * stride + c0;
        __global const float16 *rb = f + (size_t)vb * stride + c0;
        const float16 a = ra[0] + tc * (ra[1] - ra[0]);
        const float16 b = rb[0] + tc * (rb[1] - rb[0]);
        acc += a + tv * (b - a);
    }
    par16[((size_t)g * n_par + i) * n_s + k] = 0.5f * acc;
}

// Parallel-beam backprojection, 2 x 16 filtered sinograms per work-item (as the fan kernel
// backproject_batched16x2 of backproject.cl: same tiling, view chunks and barriers, see there),
// with no distance weight and no per-view division:
//   mu(x, y) = dtheta * sum_i Q_i(c_i),  c_i = x cos theta_i / ds + y sin theta_i / ds + (n_s - 1) / 2,
// linear in c. The host table trig holds (cos theta_i / ds, sin theta_i / ds). Pixels outside
// the FOV circle (fov_r2 = radius^2, which the host keeps inside [s_1, s_{n_s - 2}]) are 0.
//   par16: (n_groups, n_par, n_s) float16      out: (16 n_groups, ny, nx) float
#include "store16.h"

__kernel __attribute__((reqd_work_group_size(LX, LY, 1)))
void backproject_parallel16x2(__global const float16 *restrict par16,
                              __global const float2 *restrict trig,
                              __global float *restrict out,
                              const int nx, const int ny, const int n_par, const int n_s,
                              const float voxel_mm, const float fov_r2, const float dtheta,
                              const int n_groups)
{
    const int ix = get_global_id(0), iy = get_global_id(1), g = 2 * get_global_id(2);
    const bool two = g + 1 < n_groups;
    const float x = ((float)ix - 0.5f * (float)(nx - 1)) * voxel_mm;
    const float y = ((float)iy - 0.5f * (float)(ny - 1)) * voxel_mm;
    const bool in_image = ix < nx && iy < ny;
    const bool in_fov = in_image && x * x + y * y <= fov_r2;
    const float centre = 0.5f * (float)(n_s - 1);
    const size_t group_size = (size_t)n_par * n_s;
    __global const float16 *sino = par16 + (size_t)g * group_size;
    const size_t second = two ? group_size : 0;

    float16 acc0 = (float16)(0.0f), acc1 = (float16)(0.0f);
    for (int j0 = 0; j0 < n_par; j0 += VCHUNK) {
        if (in_fov) {
            const int j1 = j0 + VCHUNK < n_par ? j0 + VCHUNK : n_par;
            __global const float16 *s = sino + (size_t)j0 * n_s;
            for (int j = j0; j < j1; ++j, s += n_s) {
                const float2 cs = trig[j];
                const float c = x * cs.x + y * cs.y + centre;
                const int i0 = (int)c;  // c >= 1 inside the FOV: truncation is floor
                const float wb = c - (float)i0;
                const float16 a0 = s[i0], a1 = s[second + i0];
                acc0 += a0 + wb * (s[i0 + 1] - a0);
                acc1 += a1 + wb * (s[second + i0 + 1] - a1);
            }
        }
        barrier(CLK_GLOBAL_MEM_FENCE);
    }
    if (!in_image)
        return;
    acc0 *= dtheta;
    acc1 *= dtheta;
    const size_t plane = (size_t)nx * ny;
    __global float *o = out + (size_t)g * 16 * plane + (size_t)iy * nx + ix;
    STORE16(o, plane, acc0)
    if (two) {
        o += 16 * plane;
        STORE16(o, plane, acc1)
    }
}
