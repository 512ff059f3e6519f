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

#define VIEW_REC 12

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
    const size_t o = ((size_t)view * n_rows + row) * n_cols + col;

    // clip the half-line t >= 0 to the box
    float t0 = 0.0f, t1 = INFINITY;
    for (int k = 0; k < 3; ++k) {
        const float lo = -0.5f - a[k], hi = (float)n[k] - 0.5f - a[k];
        if (b[k] != 0.0f) {
            const float ta = lo / b[k], tb = hi / b[k];
            t0 = fmax(t0, fmin(ta, tb));
            t1 = fmin(t1, fmax(ta, tb));
        } else if (lo > 0.0f || hi < 0.0f) {                    // parallel to the slab, outside it
            t1 = -1.0f;
        }
    }
    const float ab0 = fabs(b[0]), ab1 = fabs(b[1]), ab2 = fabs(b[2]);
    if (!(t1 > t0) || !(len > 0.0f)) {                         // misses (or d = 0)
        out[o] = 0.0f;
        return;
    }
    const int k = (ab0 >= ab1 && ab0 >= ab2) ? 0 : (ab1 >= ab2 ? 1 : 2);
    const int j = k == 0 ? 1 : 0, l = k == 2 ? 1 : 2;            // the two in-plane axes
    const float ak = a[k], bk = b[k];
    // slab range along k (g from the clipped ends, kept inside the box against rounding)
    const float ga = ak + bk * t0, gb = ak + bk * t1;
    const float glo = clamp(fmin(ga, gb), -0.5f, (float)n[k] - 0.5f);
    const float ghi = clamp(fmax(ga, gb), -0.5f, (float)n[k] - 0.5f);
    const int i_lo = clamp((int)floor(glo + 0.5f), 0, n[k] - 1);
    const int i_hi = clamp((int)floor(ghi + 0.5f), 0, n[k] - 1);
    // in-plane coordinates at plane i: g_j = a_j + r_j (i - a_k), r_j = b_j / b_k (|r_j| <= 1)
    const float rj = b[j] / bk, rl = b[l] / bk;
    const float cj = a[j] - rj * ak, cl = a[l] - rl * ak;
    const int nj = n[j], nl = n[l], sj = stride[j], sl = stride[l], sk = stride[k];
    const float gjmax = (float)(nj - 1), glmax = (float)(nl - 1);
    const int j0max = max(nj - 2, 0), l0max = max(nl - 2, 0);
    const int dj = nj > 1 ? sj : 0, dl = nl > 1 ? sl : 0;
    float acc = 0.0f;
    for (int i = i_lo; i <= i_hi; ++i) {
        const float w = fmin((float)i + 0.5f, ghi) - fmax((float)i - 0.5f, glo);   // in units of g_k
        const float gj = clamp(cj + rj * (float)i, 0.0f, gjmax);
        const float gl = clamp(cl + rl * (float)i, 0.0f, glmax);
        const int j0 = min((int)gj, j0max), l0 = min((int)gl, l0max);
        const float fj = gj - (float)j0, fl = gl - (float)l0;
        __global const float *p = mu + i * sk + j0 * sj + l0 * sl;
        const float m0 = p[0] + fj * (p[dj] - p[0]);
        const float m1 = p[dl] + fj * (p[dl + dj] - p[dl]);
        acc += w * (m0 + fl * (m1 - m0));
    }
    out[o] = acc * (len / fabs(bk));                            // g_k units -> mm
}
