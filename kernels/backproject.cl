// Distance-weighted fan-beam backprojection for a flat detector, full 2*pi scan.
// Kak & Slaney (1988), "Principles of Computerized Tomographic Imaging", sec. 3.4.2
// (equally spaced collinear detectors), in the conventions of clrecon/core/conventions.py:
//   source at (R cos b, R sin b), detector columns along e_u = (-sin b, cos b),
//   U = R - (x cos b + y sin b),  u = SDD (-x sin b + y cos b) / U,
//   column index  c = u / col_pitch + (n_cols - 1) / 2,
//   mu(x, y) = dbeta * sum_j (R / U_j)^2 * Q_j(c_j)        (Q: the filtered projection).
// Linear interpolation in c; c outside [0, n_cols - 1] (at most the half cell beyond the
// outer column centre, for pixels inside the FOV) takes the edge column's value. Pixels
// whose centre lies outside the scanner's FOV circle (fov_r2 = radius^2) are written as 0:
// not every view sees them, so their sum would be incomplete. The FOV circle is tangent to
// the outer column *edges*, so inside it |c - (n_cols-1)/2| <= n_cols/2 by construction.
//
// The per-view table `trig` holds (cos b / R, sin b / R): then R/U = 1 / (1 - x c' - y s')
// and c - c_centre = (SDD / col_pitch) (y c' - x s') (R/U), one reciprocal per view.
//
// Geometry comes in as kernel arguments, so one build serves every geometry; only the
// local size LX x LY and the view chunk VCHUNK are compile-time constants (-D): PoCL
// specialises its binaries per local size anyway (docs/algorithms.md, "Making kernels fast on PoCL").
//
// PoCL notes (PoCL 3.0, LLVM target znver3 = AVX2 on this machine, so a float16 is two
// ymm registers):
// * builtins such as native_recip, clamp and min are *not inlined* here; a call in the
//   view loop spills the float16 accumulator to the stack on every view (measured 1.8x
//   slower). The loops below use plain arithmetic and ternaries only.
// * calling a builtin with a float16 argument (e.g. fma) makes clang warn about the
//   AVX-512 ABI, and a program built with that warning comes back from PoCL's on-disk
//   cache with no kernels in it (INVALID_KERNEL_NAME on the second run). Plain `a*b + c`
//   is contracted to FMAs under -cl-mad-enable instead.

// CURVED = 1: equiangular data of a cylindrical detector (Kak & Slaney sec. 3.4.1). The
// column of pixel (x, y) is c = gamma / dgamma + central_col with gamma = atan(V / U) (V =
// -x sin b + y cos b, the in-plane offset from the central ray), and the weight is R^2 / L^2,
// L^2 = U^2 + V^2 the squared distance from the source (the 1 / R^2 is in the filter's
// pre-weight, clrecon.reconstruction.fbp.cosine_weights). atan is an odd polynomial whose
// ATAN_TERMS coefficients the host fits for the geometry's largest |V / U| = tan(gamma_fov)
// (fewest terms with a float64 error <= 1e-7 rad; at most 9 = degree 17 on [0, 1]): plain
// arithmetic, as the PoCL notes below ask (FanBeamGeometry checks gamma_edge <= 45 degrees). `sdd_over_pitch` then carries
// 1 / dgamma, and `col_centre` the central column (0-based, without the pad column).
#ifndef CURVED
#define CURVED 0
#endif

#if CURVED
#define GEOMETRY_ARGS                                                                     \
    const int nx, const int ny,                                                            \
    const int n_views, const int n_cols,                                                   \
    const float voxel_mm,                                                                  \
    const float sdd_over_pitch,         /* 1 / dgamma, 1/rad */                            \
    const float fov_r2,                                                                    \
    const float dbeta,                                                                     \
    const float col_centre              /* central column, fractional, 0-based */
#define COL_CENTRE col_centre
#else
#define GEOMETRY_ARGS                                                                     \
    const int nx, const int ny,         /* image size, img[y, x] */                        \
    const int n_views, const int n_cols,                                                   \
    const float voxel_mm,               /* pixel size, mm */                               \
    const float sdd_over_pitch,         /* SDD / col_pitch */                              \
    const float fov_r2,                 /* squared FOV radius at the isocentre, mm^2 */    \
    const float dbeta                   /* 2 pi / n_views, rad */
#define COL_CENTRE (0.5f * (float)(n_cols - 1))
#endif

#include "fan_column.h"

// Batched kernel: 16 filtered sinograms interleaved as [view][column][batch] and read as
// one float16 per interpolation tap. The 16 lanes are the SIMD width; the geometry of a
// (pixel, view) pair is computed once for all 16 (docs/algorithms.md "Fan-beam FBP": 3.9 vs 0.36 G
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

// Reference kernel: one sinogram per work-item in the plain (B, n_views, n_cols) layout,
// with the edge clamp in the loop -- the straightforward way, kept for the benchmark and
// as an independent cross-check of the batched kernel's layout, padding and chunking.
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
