// Voxel-driven cone-beam backprojection B ~ A^T of the voxel projector (kernels/voxel_project.cl):
// a gather, one work-item per voxel, no atomics (clrecon.reconstruction.iterative.cone_gather).
//
// For each view the voxel centre p (index g, world o + h g) is projected from the source s onto
// the detector's flat plane (centre det, unit e_u, e_v, normal n = e_u x e_v):
//     w = p - s,  t = (D . n) / (w . n)  (D = det - s),  u = t (w . e_u) - D . e_u,  v' = t (w . e_v) - D . e_v,
// the column coordinate fc of u on the cells' (monotone) u_mm, the row coordinate of v' / vscale(fc)
// on v_mm (vscale: a cylindrical detector's flat-equivalent cells, 1 for a flat one), and the
// values are read bilinearly between cell centres (zero beyond the outermost centres, fading over
// one cell). Each read is weighted by the voxel's expected Joseph weight summed over the rays
// near it,
//     V |w| (D . n)^2 / (du dv |w . n|^3)      (mm),
// V = hx hy hz the voxel's volume and du, dv (x vscale) the local cell pitch on the flat plane:
// the voxel's volume times the rays' density through it (rays per mm^2 across the ray). For a
// smooth y, B y ~ A^T y; B is not A's exact transpose (Joseph's weights alias with the ray
// spacing by ~10 % per view), which is why RTK-style SART pairs a ray-driven projector with a
// voxel-driven backprojector for speed, not for exactness. The matched transpose is
// kernels/voxel_backproject.cl.
//
// View record (GATHER_REC floats, host float64 -> float32): a = (s - o) / h (index units), n,
// e_u, e_v, D . n, D . e_u, D . e_v, then the first and last z plane whose voxels can read a row
// of the detector (host, conservative): a voxel outside them skips the view (a helical cone
// covers a fraction of a slab's planes per view). The sum over the launch's views runs in view order in float32
// (deterministic: no atomics; the host adds launches in their order).
//
// PAIR = 1: a second array on the same rays (proj2 -> out2) from the same projections and weights.
// Launch: global (nx, ny, nz); out[z][y][x] is written (overwritten), not accumulated.

#ifndef CURVED
#define CURVED 0
#endif
#ifndef PAIR
#define PAIR 0
#endif
#define GATHER_REC 18

// fractional index of x on the monotone increasing centres c[0..n-1] (n >= 2), extrapolated with
// the end pitches beyond them; *pitch: the bracketing interval's length. tab[T]: for uniform bins of
// width 1 / inv_delta (<= the smallest pitch) from c[0], the bracket of each bin's start; a point
// lies in that bracket or the next.
inline float cell_coordinate(__global const float *c, __global const int *tab, const int T, const float inv_delta,
                             const int n, const float x, float *pitch)
{
    const int i = clamp((int)floor((x - c[0]) * inv_delta), 0, T - 1);
    const int k = tab[i];
    const int lo = k + ((k < n - 2) & (x >= c[min(k + 1, n - 1)]));
    *pitch = c[lo + 1] - c[lo];
    return (float)lo + (x - c[lo]) / *pitch;
}

__kernel void cone_gather(__global const float *proj, const int nx, const int ny, const int nz,
                          const float hx, const float hy, const float hz,
                          __global const float *views, const int n_views,
                          __global const float *u_mm, __global const float *v_mm, const int n_cols, const int n_rows,
                          __global const int *u_tab, const int u_T, const float u_inv,
                          __global const int *v_tab, const int v_T, const float v_inv,
#if CURVED
                          __global const float *vscale,
#endif
#if PAIR
                          __global const float *proj2, __global float *out2,
#endif
                          __global float *out)
{
    const int x = get_global_id(0), y = get_global_id(1), z = get_global_id(2);
    if (x >= nx || y >= ny || z >= nz)
        return;
    const float vol = hx * hy * hz;
    float acc = 0.0f;
#if PAIR
    float acc2 = 0.0f;
#endif
    const float gx = (float)x, gy = (float)y, gz = (float)z;
    for (int m = 0; m < n_views; ++m) {
        __global const float *r = views + GATHER_REC * m;
        if (gz < r[15] || gz > r[16])
            continue;                                       // no row of this view reaches the plane
        const float wx = (gx - r[0]) * hx, wy = (gy - r[1]) * hy, wz = (gz - r[2]) * hz;
        const float wn = wx * r[3] + wy * r[4] + wz * r[5];
        const float Dn = r[12];
        const float t = Dn / wn;
        const float u = t * (wx * r[6] + wy * r[7] + wz * r[8]) - r[13];
        const float vp = t * (wx * r[9] + wy * r[10] + wz * r[11]) - r[14];
        float du, dv;
        const float fc = cell_coordinate(u_mm, u_tab, u_T, u_inv, n_cols, u, &du);
#if CURVED
        const int k0 = clamp((int)floor(fc), 0, n_cols - 2);
        const float fk = clamp(fc - (float)k0, 0.0f, 1.0f);
        const float vs = vscale[k0] + fk * (vscale[k0 + 1] - vscale[k0]);
#else
        const float vs = 1.0f;
#endif
        const float fr = cell_coordinate(v_mm, v_tab, v_T, v_inv, n_rows, vp / vs, &dv);
        // in front of the source, on the detector's cells or within one cell of them
        const int ok = (wn * Dn > 0.0f) & (fc > -1.0f) & (fc < (float)n_cols) & (fr > -1.0f) & (fr < (float)n_rows);
        const float aw = fabs(wn);
        const float weight = ok ? vol * sqrt(wx * wx + wy * wy + wz * wz) * Dn * Dn / (du * dv * vs * aw * aw * aw) : 0.0f;
        // off the detector (or a voxel in the source's plane: t, fc, fr not finite) the reads below
        // stay in range and finite, and carry weight 0
        const float fcs = ok ? fc : 0.0f, frs = ok ? fr : 0.0f;
        const float fc0 = floor(fcs), fr0 = floor(frs);
        const float a = fcs - fc0, b = frs - fr0;
        const int c0 = (int)fc0, r0 = (int)fr0;
        // the four cells, clamped onto the detector; a cell off it gets weight 0
        const int ca = clamp(c0, 0, n_cols - 1), cb = clamp(c0 + 1, 0, n_cols - 1);
        const int ra = clamp(r0, 0, n_rows - 1), rb = clamp(r0 + 1, 0, n_rows - 1);
        const float wa = (c0 >= 0) ? 1.0f - a : 0.0f, wb = (c0 + 1 < n_cols) ? a : 0.0f;
        const float va = (r0 >= 0) ? 1.0f - b : 0.0f, vb = (r0 + 1 < n_rows) ? b : 0.0f;
        const int base = ok ? m * n_rows * n_cols : 0;
        __global const float *pa = proj + base + ra * n_cols, *pb = proj + base + rb * n_cols;
        acc += weight * (va * (wa * pa[ca] + wb * pa[cb]) + vb * (wa * pb[ca] + wb * pb[cb]));
#if PAIR
        __global const float *qa = proj2 + base + ra * n_cols, *qb = proj2 + base + rb * n_cols;
        acc2 += weight * (va * (wa * qa[ca] + wb * qa[cb]) + vb * (wa * qb[ca] + wb * qb[cb]));
#endif
    }
    const size_t o = ((size_t)z * ny + y) * nx + x;
    out[o] = acc;
#if PAIR
    out2[o] = acc2;
#endif
}
