// Warp of a volume by a displacement field, and its exact transpose
// (clrecon.reconstruction.iterative.warp).
//
//   warp_pull:  out[p] = sum_q T(p, q) x[q]   = x at p + u(p), trilinear,
//   warp_push:  out[q] = sum_p T(p, q) g[p]   (the transpose: each g[p] scattered with the
//                                              same eight weights),
// p, q voxel indices of one grid (nz, ny, nx), [z][y][x] order; u (3, nz, ny, nx) float32 mm,
// components (dx, dy, dz); the sample point in index units is p + u(p) / h, each coordinate
// clamped to [0, n - 1] (the volume extended by its edge values), then
//   i0 = min(floor(g), n - 2) (0 for a one-voxel axis), f = g - i0, weights (1 - f, f) on
//   (i0, i0 + 1); on a one-voxel axis both weights fall on voxel 0.
// warp_push accumulates in 64-bit fixed point (fixed_add.h): bit-identical whatever the order.

#include "fixed_add.h"

inline void warp_weights(const float g, const int n, int *i0, int *di, float *f)
{
    const float c = clamp(g, 0.0f, (float)(n - 1));
    *i0 = min((int)c, max(n - 2, 0));
    *f = c - (float)(*i0);
    *di = n > 1 ? 1 : 0;
}

#define WARP_SETUP                                                                                   \
    const int x = get_global_id(0), y = get_global_id(1), z = get_global_id(2);                      \
    if (x >= nx || y >= ny || z >= nz)                                                               \
        return;                                                                                      \
    const size_t nxy = (size_t)nx * ny, nv = nxy * nz;                                               \
    const size_t o = (size_t)z * nxy + (size_t)y * nx + x;                                           \
    int x0, y0, z0, dx, dy, dz;                                                                      \
    float fx, fy, fz;                                                                                \
    warp_weights((float)x + u[o] / hx, nx, &x0, &dx, &fx);                                           \
    warp_weights((float)y + u[nv + o] / hy, ny, &y0, &dy, &fy);                                      \
    warp_weights((float)z + u[2 * nv + o] / hz, nz, &z0, &dz, &fz);                                  \
    const size_t q = (size_t)z0 * nxy + (size_t)y0 * nx + x0;                                        \
    const size_t sy = dy * (size_t)nx, sz = dz * nxy;

__kernel void warp_pull(__global const float *src, __global const float *u, const int nx, const int ny,
                        const int nz, const float hx, const float hy, const float hz, __global float *out)
{
    WARP_SETUP
    const float c00 = src[q] + fx * (src[q + dx] - src[q]);
    const float c10 = src[q + sy] + fx * (src[q + sy + dx] - src[q + sy]);
    const float c01 = src[q + sz] + fx * (src[q + sz + dx] - src[q + sz]);
    const float c11 = src[q + sz + sy] + fx * (src[q + sz + sy + dx] - src[q + sz + sy]);
    const float c0 = c00 + fy * (c10 - c00), c1 = c01 + fy * (c11 - c01);
    out[o] = c0 + fz * (c1 - c0);
}

__kernel void warp_push(__global const float *g, __global const float *u, const int nx, const int ny,
                        const int nz, const float hx, const float hy, const float hz, const float scale,
                        volatile __global uint *acc)
{
    WARP_SETUP
    const float v = g[o];
    if (v == 0.0f)
        return;
    const float gx = 1.0f - fx, gy = 1.0f - fy, gz = 1.0f - fz;
    fixed_add(acc + 2 * q, v * gx * gy * gz, scale);
    fixed_add(acc + 2 * (q + dx), v * fx * gy * gz, scale);
    fixed_add(acc + 2 * (q + sy), v * gx * fy * gz, scale);
    fixed_add(acc + 2 * (q + sy + dx), v * fx * fy * gz, scale);
    fixed_add(acc + 2 * (q + sz), v * gx * gy * fz, scale);
    fixed_add(acc + 2 * (q + sz + dx), v * fx * gy * fz, scale);
    fixed_add(acc + 2 * (q + sz + sy), v * gx * fy * fz, scale);
    fixed_add(acc + 2 * (q + sz + sy + dx), v * fx * fy * fz, scale);
}

// The inverse of a displacement field: v with v(p) = -u(p + v(p)), so that the point p + v(p)
// moves to p (clrecon.reconstruction.iterative.warp.invert_field). Fixed-point iteration from
// v = -u(p), ``steps`` times v <- -u(p + v(p)) with u sampled trilinearly (the weights of
// warp_pull, clamped at the edges), all in registers: the same values as ``steps`` rounds of
// three warp_pull calls of u's components, in one launch.
inline float sample3(__global const float *f, const size_t q, const int dx, const size_t sy, const size_t sz,
                     const float fx, const float fy, const float fz)
{
    const float c00 = f[q] + fx * (f[q + dx] - f[q]);
    const float c10 = f[q + sy] + fx * (f[q + sy + dx] - f[q + sy]);
    const float c01 = f[q + sz] + fx * (f[q + sz + dx] - f[q + sz]);
    const float c11 = f[q + sz + sy] + fx * (f[q + sz + sy + dx] - f[q + sz + sy]);
    const float c0 = c00 + fy * (c10 - c00), c1 = c01 + fy * (c11 - c01);
    return c0 + fz * (c1 - c0);
}

__kernel void invert_field(__global const float *u, const int nx, const int ny, const int nz, const float hx,
                           const float hy, const float hz, const int steps, __global float *v)
{
    const int x = get_global_id(0), y = get_global_id(1), z = get_global_id(2);
    if (x >= nx || y >= ny || z >= nz)
        return;
    const size_t nxy = (size_t)nx * ny, nv = nxy * nz;
    const size_t o = (size_t)z * nxy + (size_t)y * nx + x;
    float vx = -u[o], vy = -u[nv + o], vz = -u[2 * nv + o];
    for (int k = 0; k < steps; k++) {
        int x0, y0, z0, dx, dy, dz;
        float fx, fy, fz;
        warp_weights((float)x + vx / hx, nx, &x0, &dx, &fx);
        warp_weights((float)y + vy / hy, ny, &y0, &dy, &fy);
        warp_weights((float)z + vz / hz, nz, &z0, &dz, &fz);
        const size_t q = (size_t)z0 * nxy + (size_t)y0 * nx + x0;
        const size_t sy = dy * (size_t)nx, sz = dz * nxy;
        vx = -sample3(u, q, dx, sy, sz, fx, fy, fz);
        vy = -sample3(u + nv, q, dx, sy, sz, fx, fy, fz);
        vz = -sample3(u + 2 * nv, q, dx, sy, sz, fx, fy, fz);
    }
    v[o] = vx;
    v[nv + o] = vy;
    v[2 * nv + o] = vz;
}
