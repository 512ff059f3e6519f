// TV-L1 optical flow in 3D (Zach, Pock & Bischof, DAGM 2007; the scheme of Sanchez, Meinhardt-Llopis
// & Facciolo, IPOL 2013), for clrecon.reconstruction.motion.flow. Volumes (nz, ny, nx), x fastest;
// fields (3, nz, ny, nx) with components (dx, dy, dz) in mm; spacings hx, hy, hz mm. The float64
// NumPy references are the *_reference functions of clrecon.reconstruction.motion.flow.
//
// Work-item (ix, iy, iz): one voxel; one owner per output, no reductions (the same bits for any
// work-group size). Outside-grid work-items return.
//
// Differences: forward gradient (0 on the last index of an axis), its adjoint the backward
// divergence (p[0] at the first index, -p[n-2] at the last; 0 along an axis of one voxel), and the
// image gradient by central differences with the index clamped to the grid (one-sided at the ends,
// 0 along an axis of one voxel).

#define IDX(i, j, k) (((size_t)(k) * ny + (j)) * nx + (i))

#include "trilinear.h"

// Central difference of img along one axis at index i (stride s, n voxels, spacing h), clamped.
static float central(__global const float *restrict img, const size_t o, const int i, const int n,
                     const size_t s, const float h)
{
    if (n < 2)
        return 0.0f;
    const int lo = i > 0 ? 1 : 0, hi = i < n - 1 ? 1 : 0;
    return (img[o + hi * s] - img[o - lo * s]) / ((float)(lo + hi) * h);
}

// Backward divergence of one direction's dual component at index i along an axis (stride s).
static float backward(__global const float *restrict p, const size_t o, const int i, const int n,
                      const size_t s, const float h)
{
    if (n < 2)
        return 0.0f;
    if (i == 0)
        return p[o] / h;
    if (i == n - 1)
        return -p[o - s] / h;
    return (p[o] - p[o - s]) / h;
}

// out(x) = src at x + u(x) (trilinear, clamped): the moving image warped onto the fixed grid.
__kernel void flow_warp(__global const float *restrict src, __global const float *restrict u,
                        __global float *restrict out, const int nx, const int ny, const int nz,
                        const float hx, const float hy, const float hz)
{
    const int i = get_global_id(0), j = get_global_id(1), k = get_global_id(2);
    if (i >= nx || j >= ny || k >= nz)
        return;
    const size_t o = IDX(i, j, k), n = (size_t)nx * ny * nz;
    out[o] = trilinear(src, nx, ny, nz, (float)i + u[o] / hx, (float)j + u[n + o] / hy, (float)k + u[2 * n + o] / hz);
}

// rho0 = Iw - I0 - grad(Iw) . u0: the linearised data term's constant part at the warp's field u0.
__kernel void flow_residual(__global const float *restrict warped, __global const float *restrict fixed_img,
                            __global const float *restrict u, __global float *restrict rho0,
                            const int nx, const int ny, const int nz, const float hx, const float hy, const float hz)
{
    const int i = get_global_id(0), j = get_global_id(1), k = get_global_id(2);
    if (i >= nx || j >= ny || k >= nz)
        return;
    const size_t o = IDX(i, j, k), n = (size_t)nx * ny * nz;
    const float gx = central(warped, o, i, nx, 1, hx);
    const float gy = central(warped, o, j, ny, (size_t)nx, hy);
    const float gz = central(warped, o, k, nz, (size_t)nx * ny, hz);
    rho0[o] = warped[o] - fixed_img[o] - (gx * u[o] + gy * u[n + o] + gz * u[2 * n + o]);
}

// Primal step, in place: v = u + the L1 data term's thresholding step (lambda theta = lt), then
// u = v + theta div(p_c) per component c. p (9, nz, ny, nx): component c's dual along axis d at 3 c + d.
__kernel void flow_primal(__global float *restrict u, __global const float *restrict p,
                          __global const float *restrict warped, __global const float *restrict rho0,
                          const int nx, const int ny, const int nz, const float hx, const float hy, const float hz,
                          const float lt, const float theta)
{
    const int i = get_global_id(0), j = get_global_id(1), k = get_global_id(2);
    if (i >= nx || j >= ny || k >= nz)
        return;
    const size_t o = IDX(i, j, k), n = (size_t)nx * ny * nz;
    const size_t sy = (size_t)nx, sz = (size_t)nx * ny;
    const float g[3] = {central(warped, o, i, nx, 1, hx), central(warped, o, j, ny, sy, hy),
                        central(warped, o, k, nz, sz, hz)};
    const float g2 = g[0] * g[0] + g[1] * g[1] + g[2] * g[2];
    float uc[3] = {u[o], u[n + o], u[2 * n + o]};
    const float rho = rho0[o] + g[0] * uc[0] + g[1] * uc[1] + g[2] * uc[2];
    float f = 0.0f;  // v = u + f g
    if (rho < -lt * g2)
        f = lt;
    else if (rho > lt * g2)
        f = -lt;
    else if (g2 > FLOW_EPS)
        f = -rho / g2;
    for (int c = 0; c < 3; ++c) {
        __global const float *pc = p + (size_t)(3 * c) * n;
        const float div = backward(pc, o, i, nx, 1, hx) + backward(pc + n, o, j, ny, sy, hy)
                          + backward(pc + 2 * n, o, k, nz, sz, hz);
        u[(size_t)c * n + o] = uc[c] + f * g[c] + theta * div;
    }
}

// Dual step, in place, for the Huber-TV of each component (Werlberger et al., BMVC 2009; Chambolle &
// Pock's projection form): q = (p_c + s grad u_c) / (1 + s eps), p_c = q / max(1, |q|); s = tau / theta,
// forward differences. eps = 0 is plain TV; below eps (a strain) the penalty is quadratic (no staircase).
__kernel void flow_dual(__global const float *restrict u, __global float *restrict p,
                        const int nx, const int ny, const int nz, const float hx, const float hy, const float hz,
                        const float s, const float eps)
{
    const int i = get_global_id(0), j = get_global_id(1), k = get_global_id(2);
    if (i >= nx || j >= ny || k >= nz)
        return;
    const size_t o = IDX(i, j, k), n = (size_t)nx * ny * nz;
    const size_t sy = (size_t)nx, sz = (size_t)nx * ny;
    const float shrink = 1.0f / (1.0f + s * eps);
    for (int c = 0; c < 3; ++c) {
        __global const float *uc = u + (size_t)c * n;
        __global float *pc = p + (size_t)(3 * c) * n;
        const float dx = i < nx - 1 ? (uc[o + 1] - uc[o]) / hx : 0.0f;
        const float dy = j < ny - 1 ? (uc[o + sy] - uc[o]) / hy : 0.0f;
        const float dz = k < nz - 1 ? (uc[o + sz] - uc[o]) / hz : 0.0f;
        const float qx = (pc[o] + s * dx) * shrink, qy = (pc[n + o] + s * dy) * shrink;
        const float qz = (pc[2 * n + o] + s * dz) * shrink;
        const float norm = fmax(1.0f, sqrt(qx * qx + qy * qy + qz * qz));
        pc[o] = qx / norm;
        pc[n + o] = qy / norm;
        pc[2 * n + o] = qz / norm;
    }
}

// Trilinear resampling of vol (mz, my, mx) onto (nz, ny, nx) voxels spanning the same extent:
// destination voxel i sits at source index (i + 0.5) mx / nx - 0.5 along x (likewise y, z), clamped.
// Batched over b = get_global_id(2) / nz volumes (b volumes of each shape, back to back).
__kernel void flow_resample(__global const float *restrict src, __global float *restrict dst,
                            const int mx, const int my, const int mz, const int nx, const int ny, const int nz)
{
    const int i = get_global_id(0), j = get_global_id(1), q = get_global_id(2);
    if (i >= nx || j >= ny || q >= nz * BATCH)
        return;
    const int b = q / nz, k = q - b * nz;
    const float fx = ((float)i + 0.5f) * ((float)mx / (float)nx) - 0.5f;
    const float fy = ((float)j + 0.5f) * ((float)my / (float)ny) - 0.5f;
    const float fz = ((float)k + 0.5f) * ((float)mz / (float)nz) - 0.5f;
    dst[(size_t)b * nx * ny * nz + IDX(i, j, k)] = trilinear(src + (size_t)b * mx * my * mz, mx, my, mz, fx, fy, fz);
}
