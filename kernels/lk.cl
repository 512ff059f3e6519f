// Iterative Lucas-Kanade optical flow in 3D: scikit-image's optical_flow_ilk (Le Besnerais &
// Champagnat, ICIP 2005) step for step, for clrecon.reconstruction.motion.lk. Volumes (nz, ny, nx),
// x fastest; flows (3, nz, ny, nx) in voxels, components in axis order (z, y, x) as scikit-image's.
// The float64 NumPy references are the *_reference functions of clrecon.reconstruction.motion.lk.
//
// Work-item (ix, iy, iz): one voxel (lk_box: one line along its axis); one owner per output, no
// reductions (the same bits for any work-group size). Outside-grid work-items return.
//
// No contraction of a * b + c into fma: NumPy rounds the product and the sum separately, and
// these kernels follow its order of operations where they can (the gradient, the error image,
// the products and the flow resize are then the same bits as NumPy's).
#pragma OPENCL FP_CONTRACT OFF

#define IDX(i, j, k) (((size_t)(k) * ny + (j)) * nx + (i))

#include "trilinear.h"

// np.gradient (unit spacing, edge_order 1) of img along one axis at index i (stride s, n >= 2 voxels):
// (f[i+1] - f[i-1]) / 2 inside, one-sided differences at the ends.
static float gradient(__global const float *restrict img, const size_t o, const int i, const int n, const size_t s)
{
    if (i == 0)
        return img[o + s] - img[o];
    if (i == n - 1)
        return img[o] - img[o - s];
    return (img[o + s] - img[o - s]) / 2.0f;
}

// out(x) = src at x + v(x) (trilinear, clamped): the moving image warped onto the reference grid.
// The coordinate is rounded to float32 first (scikit-image adds the float32 grid to the flow).
__kernel void lk_warp(__global const float *restrict src, __global const float *restrict v,
                      __global float *restrict out, const int nx, const int ny, const int nz)
{
    const int i = get_global_id(0), j = get_global_id(1), k = get_global_id(2);
    if (i >= nx || j >= ny || k >= nz)
        return;
    const size_t o = IDX(i, j, k), n = (size_t)nx * ny * nz;
    const float fz = v[o] + (float)k, fy = v[n + o] + (float)j, fx = v[2 * n + o] + (float)i;
    out[o] = trilinear(src, nx, ny, nz, fx, fy, fz);
}

// One of the nine local-system terms before the window sum, g = np.gradient(warped) (axes z, y, x):
// term q < 6: g_a g_b for (a, b) = (0,0) (0,1) (0,2) (1,1) (1,2) (2,2); q = 6 + a: g_a e with the error
// image e = ((g_0 v_0 + g_1 v_1) + g_2 v_2) + ref - warped (NumPy's order).
__kernel void lk_term(__global const float *restrict warped, __global const float *restrict ref,
                      __global const float *restrict v, __global float *restrict out,
                      const int nx, const int ny, const int nz, const int q)
{
    const int i = get_global_id(0), j = get_global_id(1), k = get_global_id(2);
    if (i >= nx || j >= ny || k >= nz)
        return;
    const size_t o = IDX(i, j, k), n = (size_t)nx * ny * nz;
    const float g[3] = {gradient(warped, o, k, nz, (size_t)nx * ny), gradient(warped, o, j, ny, (size_t)nx),
                        gradient(warped, o, i, nx, 1)};
    float r;
    if (q < 6) {
        const int a = q < 3 ? 0 : (q < 5 ? 1 : 2);
        const int b = q < 3 ? q : (q < 5 ? q - 2 : 2);
        r = g[a] * g[b];
    } else {
        const float p0 = g[0] * v[o], p1 = g[1] * v[n + o], p2 = g[2] * v[2 * n + o];
        const float s = (p0 + p1) + p2;
        const float e = (s + ref[o]) - warped[o];
        r = g[q - 6] * e;
    }
    out[o] = r;
}

// Index i of a line of n voxels extended by mirroring about its end voxels (scipy.ndimage's
// 'mirror': d c b | a b c d | c b a), repeatedly for lines shorter than the window.
static int mirror(int i, const int n)
{
    if (n == 1)
        return 0;
    const int p = 2 * n - 2;
    i %= p;
    if (i < 0)
        i += p;
    return i < n ? i : p - i;
}

#if LK_DOUBLE
#pragma OPENCL EXTENSION cl_khr_fp64 : enable
#else
// a + b = s + e exactly (Knuth's TwoSum; no fast math, no contraction): e is the rounding of s.
// volatile: Intel's CPU compiler otherwise lost e in a sum of one repeated value (a line of one
// voxel: the mean of 41 copies came out 4 ulp off; tests/reconstruction/test_lk.py).
static float two_sum(const float a, const float b, float *e)
{
    volatile float s = a + b;
    volatile float bb = s - a;
    *e = (a - (s - bb)) + (b - bb);
    return s;
}
#endif

// Mean of the 2 r + 1 voxels of src around each voxel along one axis (0: z, 1: y, 2: x), mirrored at
// the ends (scipy.ndimage.uniform_filter1d, mode 'mirror'): one pass of the separable box filter.
// Work-item (a, b): one line along the axis ((x, y) for z, (x, z) for y, (y, z) for x), walked from
// its start with SciPy's sliding window sum: the first window summed from its first voxel, then
// per step sum += (entering - leaving), mean = sum / (2 r + 1), rounded to float32 at the output.
// LK_DOUBLE 1 (the device has cl_khr_fp64): the sum in float64 as SciPy's, the same bits where the
// compiler keeps the order; LK_DOUBLE 0: the sum kept as s + c in float32 with every addition's
// rounding error in c (TwoSum), so it does not drift along the line either.
// Each output has one owner and a fixed order of operations: the same bits for any work-group size.
// src and dst: volume src_slot of src and dst_slot of dst (+ slot nz ny nx: one of lk_solve's nine
// terms, or 0), distinct volumes.
__kernel void lk_box(__global const float *restrict src, __global float *restrict dst,
                     const int nx, const int ny, const int nz, const int axis, const int r,
                     const int src_slot, const int dst_slot)
{
    const int a = get_global_id(0), b = get_global_id(1);
    int n, na, nb;
    size_t s, o;
    if (axis == 0) {
        n = nz, na = nx, nb = ny, s = (size_t)nx * ny, o = IDX(a, b, 0);
    } else if (axis == 1) {
        n = ny, na = nx, nb = nz, s = (size_t)nx, o = IDX(a, 0, b);
    } else {
        n = nx, na = ny, nb = nz, s = 1, o = IDX(0, a, b);
    }
    if (a >= na || b >= nb)
        return;
    __global const float *line = src + (size_t)src_slot * nx * ny * nz + o;
    __global float *out = dst + (size_t)dst_slot * nx * ny * nz + o;
#if LK_DOUBLE
    const double size = (double)(2 * r + 1);
    double sum = 0.0;
    for (int t = -r; t <= r; ++t)
        sum += (double)line[(size_t)mirror(t, n) * s];
    out[0] = (float)(sum / size);
    for (int t = 1; t < n; ++t) {
        const int in = t + r, gone = t - r - 1;
        const double x_in = (double)line[(size_t)(in < n ? in : mirror(in, n)) * s];
        const double x_out = (double)line[(size_t)(gone >= 0 ? gone : mirror(gone, n)) * s];
        sum += x_in - x_out;
        out[(size_t)t * s] = (float)(sum / size);
    }
#else
    const float size = (float)(2 * r + 1);
    float sum = 0.0f, c = 0.0f, e;
    for (int t = -r; t <= r; ++t) {
        sum = two_sum(sum, line[(size_t)mirror(t, n) * s], &e);
        c += e;
    }
    out[0] = (sum + c) / size;
    for (int t = 1; t < n; ++t) {
        const int in = t + r, gone = t - r - 1;
        const float x_in = line[(size_t)(in < n ? in : mirror(in, n)) * s];
        const float x_out = line[(size_t)(gone >= 0 ? gone : mirror(gone, n)) * s];
        sum = two_sum(sum, x_in, &e);
        c += e;
        sum = two_sum(sum, -x_out, &e);
        c += e;
        out[(size_t)t * s] = (sum + c) / size;
    }
#endif
}

// The new flow v from the window sums: terms (9, nz, ny, nx) as lk_term's q (A's six, then b's three),
// v = A^-1 b by LU with partial pivoting (LAPACK's getrf / getrs order: the first largest pivot,
// multipliers by the pivot's reciprocal, or by division below FLT_MIN as sgetf2, column-oriented
// substitutions); v = 0 where |det A| < 1e-14 (scikit-image's guard against badly conditioned
// systems) or det A is not a number.
__kernel void lk_solve(__global const float *restrict terms, __global float *restrict v,
                       const int nx, const int ny, const int nz)
{
    const int i = get_global_id(0), j = get_global_id(1), k = get_global_id(2);
    if (i >= nx || j >= ny || k >= nz)
        return;
    const size_t o = IDX(i, j, k), n = (size_t)nx * ny * nz;
    const float a00 = terms[o], a01 = terms[n + o], a02 = terms[2 * n + o];
    const float a11 = terms[3 * n + o], a12 = terms[4 * n + o], a22 = terms[5 * n + o];
    // rows (m0 m1 m2 | x) of A | b, swapped by partial pivoting; sg: the permutation's sign
    float4 r0 = (float4)(a00, a01, a02, terms[6 * n + o]);
    float4 r1 = (float4)(a01, a11, a12, terms[7 * n + o]);
    float4 r2 = (float4)(a02, a12, a22, terms[8 * n + o]);
    float sg = 1.0f;
    float4 t;
    if (fabs(r1.x) > fabs(r0.x) && fabs(r1.x) >= fabs(r2.x)) {  // the first largest |column 0|
        t = r0, r0 = r1, r1 = t, sg = -sg;
    } else if (fabs(r2.x) > fabs(r0.x) && fabs(r2.x) > fabs(r1.x)) {
        t = r0, r0 = r2, r2 = t, sg = -sg;
    }
    float l10 = 0.0f, l20 = 0.0f, l21 = 0.0f;
    // multipliers by the pivot's reciprocal where it is representable (|pivot| >= FLT_MIN), else by
    // division (LAPACK's sgetf2 and its sfmin): a pivot that underflowed to a subnormal has an
    // infinite reciprocal, and 0 * inf would be NaN where the quotient is 0
    if (r0.x != 0.0f) {
        if (fabs(r0.x) >= FLT_MIN) {
            const float inv = 1.0f / r0.x;
            l10 = r1.x * inv;
            l20 = r2.x * inv;
        } else {
            l10 = r1.x / r0.x;
            l20 = r2.x / r0.x;
        }
        r1.y = r1.y - l10 * r0.y, r1.z = r1.z - l10 * r0.z;
        r2.y = r2.y - l20 * r0.y, r2.z = r2.z - l20 * r0.z;
    }
    if (fabs(r2.y) > fabs(r1.y)) {  // column 1 (rows 1, 2), the multipliers swapped with their rows
        t = r1, r1 = r2, r2 = t, sg = -sg;
        const float u = l10;
        l10 = l20, l20 = u;
    }
    if (r1.y != 0.0f) {
        l21 = fabs(r1.y) >= FLT_MIN ? r2.y * (1.0f / r1.y) : r2.y / r1.y;
        r2.z = r2.z - l21 * r1.z;
    }
    const float det = sg * (r0.x * r1.y * r2.z);
    if (!(fabs(det) >= 1e-14f)) {  // also where a product overflowed into NaN: no flow there
        v[o] = 0.0f;
        v[n + o] = 0.0f;
        v[2 * n + o] = 0.0f;
        return;
    }
    // L y = P b (unit lower, column by column), then U v = y (column-oriented back substitution)
    float x0 = r0.w, x1 = r1.w, x2 = r2.w;
    x1 = x1 - x0 * l10;
    x2 = x2 - x0 * l20;
    x2 = x2 - x1 * l21;
    x2 = x2 / r2.z;
    x0 = x0 - x2 * r0.z;
    x1 = x1 - x2 * r1.z;
    x1 = x1 / r1.y;
    x0 = x0 - x1 * r0.y;
    x0 = x0 / r0.x;
    v[o] = x0;
    v[n + o] = x1;
    v[2 * n + o] = x2;
}

// The flow of a coarser level (3, mz, my, mx) on this level's grid (3, nz, ny, nx): scikit-image's
// _resize_flow, nearest neighbour (scipy.ndimage.zoom, order 0: the source indices iz, iy, ix per
// axis, made on the host) times the size ratio of the component's axis (sz, sy, sx, float32).
__kernel void lk_resize(__global const float *restrict src, __global float *restrict dst,
                        __global const int *restrict iz, __global const int *restrict iy,
                        __global const int *restrict ix, const int mx, const int my, const int mz,
                        const int nx, const int ny, const int nz, const float sz, const float sy, const float sx)
{
    const int i = get_global_id(0), j = get_global_id(1), k = get_global_id(2);
    if (i >= nx || j >= ny || k >= nz)
        return;
    const size_t o = IDX(i, j, k), n = (size_t)nx * ny * nz, m = (size_t)mx * my * mz;
    const size_t so = ((size_t)iz[k] * my + iy[j]) * mx + ix[i];
    dst[o] = sz * src[so];
    dst[n + o] = sy * src[m + so];
    dst[2 * n + o] = sx * src[2 * m + so];
}
