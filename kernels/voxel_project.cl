// Cone-beam forward projection of a voxel volume (clrecon.simulation.voxel_projector.project_volume).
//
// Method: Joseph (1982). Along the ray's dominant axis k (the largest |component| of the
// direction in voxel-index units, ties to the lower axis x < y < z) the ray is cut into slabs
// [i - 1/2, i + 1/2] around the voxel-centre planes g_k = i. Slab i contributes
//     w_i * f_i,   w_i = length (mm) of the ray inside the slab and inside the volume's box,
//                  f_i = bilinear interpolation of mu in the plane g_k = i, at the ray's
//                        crossing, index coordinates clamped to [0, n - 1] (edge values
//                        extend over the half-voxel border of the box).
// Interior slabs all have w_i = h_k |d| / |d_k|; only the first and last can be partial, so a
// uniform volume gives mu x (exact chord through the box) up to float32 rounding.
//
// Ray: p(t) = s + t d, t >= 0 (the half-line from the source through the cell centre),
// d = (det - s) + u e_u + v e_v. In index units g = (p - o) / h, voxel centres at integers,
// the box is g in [-1/2, n - 1/2]. The host sends per view (float32, VIEW_REC floats):
// a = (s - o) / h, then D = det - s, e_u, e_v in mm.
//
// One work-item per (column, row, view); no local memory, no barriers.
//
// CURVED = 1 (a cylindrical detector): the cell of column c, row r is the flat-equivalent
// point (u[c], v[r] * vscale[c]) (clrecon.core.detector.CylindricalDetector.ray_cells); the
// half-line and its integral do not depend on where along the ray the point lies.

#ifndef CURVED
#define CURVED 0
#endif

#include "joseph_ray.h"

__kernel void voxel_project(__global const float *mu, const int nx, const int ny, const int nz,
                            const float hx, const float hy, const float hz,
                            __global const float *views, __global const float *u_mm,
                            __global const float *v_mm, const int n_cols, const int n_rows,
#if CURVED
                            __global const float *vscale,
#endif
                            __global float *out)
{
    const int col = get_global_id(0), row = get_global_id(1), view = get_global_id(2);
    if (col >= n_cols || row >= n_rows)
        return;
#if CURVED
    const float u = u_mm[col], v = v_mm[row] * vscale[col];
#else
    const float u = u_mm[col], v = v_mm[row];
#endif
    const size_t o = ((size_t)view * n_rows + row) * n_cols + col;
    JosephRay r;
    if (!joseph_ray(views + VIEW_REC * view, u, v, nx, ny, nz, hx, hy, hz, &r)) {
        out[o] = 0.0f;
        return;
    }
    float acc = 0.0f;
    for (int i = r.i_lo; i <= r.i_hi; ++i) {
        size_t q;
        float fj, fl;
        const float w = joseph_sample(&r, i, &q, &fj, &fl);
        __global const float *p = mu + q;
        const float m0 = p[0] + fj * (p[r.dj] - p[0]);
        const float m1 = p[r.dl] + fj * (p[r.dl + r.dj] - p[r.dl]);
        acc += w * (m0 + fl * (m1 - m0));
    }
    out[o] = acc * r.mm;
}
