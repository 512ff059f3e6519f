// Exact line integrals of quadric primitives on a flat detector (clrecon.simulation.projector).
//
// One work-item = VW neighbouring detector columns of one row of one view (explicit
// float vectors: PoCL vectorises across them directly, and the per-object branches stay
// scalar). One work-group = a tile of LX x VW columns by LY rows; its first work-item builds
// the tile's object list in local memory (culling by each object's detector rectangle),
// then every work-item loops over that list, skipping objects whose rectangle misses its
// own VW cells.
//
// Per (view, object) the host precomputes, in float64, a record of REC floats (layout in
// clrecon/simulation/projector.py, R_* below). Everything is expressed relative to the ray through the
// object's centre, parametrised x(tau) = s + (tc + tau)(p - s) with p the detector point, so
// no float32 quantity cancels: for a cell at (u, v), with du = u - uc, dv = v - vc,
//     e = du eu' + dv ev'             (local-frame offset per unit tau-shift)
//     q = o + tc e                    (local position at tau = 0)
//     d = dc' + e                     (local direction per unit tau)
// and the quadric |q + tau d|^2 = 1 has discriminant A - |q x d|^2 (Lagrange identity;
// q x d is linear in du, dv) and midpoint -B/A with B = q . d. Lengths are in units of
// tau, turned into mm by |p - s| at the end.
//
// Defines: VW (1, 4, 8, 16), LX, LY (work-group shape), CULL (0: every object for every
// ray, the reference for the culling test), LIST_MAX (local list capacity), CURVED (1: the
// cells are flat-equivalent points (u[c], v[r] * vscale[c]) of a cylindrical detector,
// clrecon.core.detector.CylindricalDetector.ray_cells; v then varies along the VW columns).

#ifndef VW
#define VW 8
#endif
#ifndef LX
#define LX 8
#endif
#ifndef LY
#define LY 8
#endif
#ifndef CULL
#define CULL 1
#endif
#ifndef LIST_MAX
#define LIST_MAX 256
#endif
#ifndef CURVED
#define CURVED 0
#endif

#if VW == 1
typedef float vec;
typedef int ivec;
#define VLOAD(i, p) ((p)[i])
#define VSTORE(x, i, p) ((p)[i] = (x))
#elif VW == 4
typedef float4 vec;
typedef int4 ivec;
#define VLOAD vload4
#define VSTORE vstore4
#elif VW == 8
typedef float8 vec;
typedef int8 ivec;
#define VLOAD vload8
#define VSTORE vstore8
#elif VW == 16
typedef float16 vec;
typedef int16 ivec;
#define VLOAD vload16
#define VSTORE vstore16
#else
#error "VW must be 1, 4, 8 or 16"
#endif

#include "record.h"

#define KIND_ELLIPSOID 1
#define KIND_CYLINDER 2
#define NO_SLAB 256  /* flag: no ray of this view meets the cylinder's end caps */
#define CUT_SUBTRACT 1
#define CUT_INTERSECT 2
#define BIG 1.0e30f

// the view record: D0 = det - src (3), e_u (3), e_v (3), pad
#define VIEW_REC 12

__kernel __attribute__((reqd_work_group_size(LX, LY, 1)))
void project(__global const float *rec,      // (m, nmax, REC): each view's records, compacted
             __global const int *count,      // (m,) records per view
             const int first,                // this pass handles records [first, first + LIST_MAX)
             __global const float *view,     // (m, VIEW_REC)
             __global const float *u_pad,    // (n_seg * VW,) column centres, padded
             __global const float *seg_lo,   // (n_seg,) min u of each VW-segment
             __global const float *seg_hi,   // (n_seg,)
             __global const float *v_mm,     // (n_rows,)
             __global const float *tile_u,   // (n_tiles_u, 2) u range of each tile column
             __global const float *tile_v,   // (n_tiles_v, 2) v range of each tile row
#if CURVED
             __global const float *vs_pad,   // (n_seg * VW,) per-column scale of v, padded
             __global const float *vs_seg,   // (n_seg, 2) min, max of vs over each VW-segment
#endif
             const int n_cols, const int n_rows, const int n_seg, const int nmax,
             const int accumulate,
             __global float *out)            // (m, n_rows, n_cols)
{
    const int seg = get_global_id(0);
    const int row = get_global_id(1);
    const int iv = get_global_id(2);
    __global const float *vrec = rec + ((size_t)iv * nmax + first) * REC;
#if CULL
    const int n = clamp(count[iv] - first, 0, LIST_MAX);
#else
    const int n = count[iv];
#endif

#if CULL
    __local int list[LIST_MAX];
    __local int n_list;
    if (get_local_id(0) == 0 && get_local_id(1) == 0) {
        const int tx = get_group_id(0), ty = get_group_id(1);
        const float tulo = tile_u[2 * tx], tuhi = tile_u[2 * tx + 1];
        const float tvlo = tile_v[2 * ty], tvhi = tile_v[2 * ty + 1];
        int k = 0;
        for (int i = 0; i < n; ++i) {
            __global const float *r = vrec + (size_t)i * REC;
            if (r[R_UHI] >= tulo && r[R_ULO] <= tuhi && r[R_VHI] >= tvlo && r[R_VLO] <= tvhi)
                list[k++] = i;
        }
        n_list = k;
    }
    barrier(CLK_LOCAL_MEM_FENCE);
    const int n_loop = n_list;
#else
    const int n_loop = n;
#endif
    if (seg >= n_seg || row >= n_rows)
        return;

    const vec u = VLOAD(seg, u_pad);
#if CURVED
    const float v_row = v_mm[row];
    const vec v = v_row * VLOAD(seg, vs_pad);
    const float va = v_row * vs_seg[2 * seg], vb = v_row * vs_seg[2 * seg + 1];
    const float vlo = fmin(va, vb), vhi = fmax(va, vb);
    typedef vec vrow;
#else
    const float v = v_mm[row];
#define vlo v
#define vhi v
    typedef float vrow;
#endif
#if CULL
    const float slo = seg_lo[seg], shi = seg_hi[seg];
#endif
    __global const float *vw = view + (size_t)iv * VIEW_REC;
    const vec wx = vw[0] + v * vw[6] + u * vw[3];
    const vec wy = vw[1] + v * vw[7] + u * vw[4];
    const vec wz = vw[2] + v * vw[8] + u * vw[5];
    const vec ray_len = sqrt(wx * wx + wy * wy + wz * wz);  // |p - s| (mm per unit tau)

    vec acc = (vec)(0.0f);
    for (int j = 0; j < n_loop; ++j) {
#if CULL
        __global const float *r = vrec + (size_t)list[j] * REC;
        if (r[R_UHI] < slo || r[R_ULO] > shi || r[R_VHI] < vlo || r[R_VLO] > vhi)
            continue;
#else
        __global const float *r = vrec + (size_t)j * REC;
#endif
        const int flags = (int)r[R_FLAGS];
        const int kind = flags & 3;
        const int nplanes = (flags >> 2) & 3;
        const int simple = (flags & 255) < 4;  // no planes, no cuts
        const int cut0 = (flags >> 4) & 3;
        const int cut1 = (flags >> 6) & 3;
        const float tc = r[R_TC];
        const vec du = u - r[R_UC];
        const vrow dv = v - r[R_VC];
        // e = du eu' + dv ev'; d = dc' + e
        const vec ex = du * r[R_EU + 0] + dv * r[R_EV + 0];
        const vec ey = du * r[R_EU + 1] + dv * r[R_EV + 1];
        const vec ez = du * r[R_EU + 2] + dv * r[R_EV + 2];
        const vec dx = r[R_DC + 0] + ex;
        const vec dy = r[R_DC + 1] + ey;
        vec A, disc;
        if (kind == KIND_ELLIPSOID) {
            const vec dz = r[R_DC + 2] + ez;
            A = dx * dx + dy * dy + dz * dz;
            const vec w0 = du * r[R_WU + 0] + (dv * r[R_WV + 0] + r[R_W0 + 0]);
            const vec w1 = du * r[R_WU + 1] + (dv * r[R_WV + 1] + r[R_W0 + 1]);
            const vec w2 = du * r[R_WU + 2] + (dv * r[R_WV + 2] + r[R_W0 + 2]);
            disc = A - (w0 * w0 + w1 * w1 + w2 * w2);
        } else {
            A = dx * dx + dy * dy;
            const vec w2 = du * r[R_WU + 2] + (dv * r[R_WV + 2] + r[R_W0 + 2]);
            disc = A - w2 * w2;
        }
        if (simple && (kind == KIND_ELLIPSOID || (flags & NO_SLAB))) {
            // the common case: a plain ellipsoid, or a cylinder whose caps this view never sees
            acc += r[R_MU] * select((vec)(0.0f), 2.0f * sqrt(disc) / A, disc > 0.0f);
            continue;
        }
        // interval [t1, t2] in tau
        const float ee = (kind == KIND_ELLIPSOID) ? 1.0f : 0.0f;  // |e|^2 over the quadric's axes
        const vec B = du * r[R_BU] + (dv * r[R_BV] + r[R_B0]) + tc * (ex * ex + ey * ey + ee * ez * ez);
        const vec sq = sqrt(fmax(disc, 0.0f));
        const vec inv_a = 1.0f / A;
        vec t1 = (-B - sq) * inv_a;
        vec t2 = (-B + sq) * inv_a;
        ivec valid = disc > 0.0f;
        if (kind == KIND_CYLINDER && !(flags & NO_SLAB)) {
            // ray parallel to the axis: inside the infinite cylinder or not at all
            const vec dz = r[R_DC + 2] + ez;
            const vec qx = r[R_OX] + tc * ex, qy = r[R_OY] + tc * ey;
            const ivec par = A <= 1.0e-20f * (A + dz * dz);
            t1 = select(t1, (vec)(-BIG), par);
            t2 = select(t2, (vec)(BIG), par);
            valid = select(valid, qx * qx + qy * qy <= 1.0f, par);
            // slab |q_z + tau d_z| <= 1
            const vec qz = r[R_OZ] + tc * ez;
            const vec inv_dz = 1.0f / dz;
            const vec ta = (1.0f - qz) * inv_dz, tb = (-1.0f - qz) * inv_dz;
            const ivec zpar = fabs(dz) < 1.0e-30f;
            const ivec zin = fabs(qz) <= 1.0f;
            t1 = fmax(t1, select(fmin(ta, tb), select((vec)(BIG), (vec)(-BIG), zin), zpar));
            t2 = fmin(t2, select(fmax(ta, tb), select((vec)(-BIG), (vec)(BIG), zin), zpar));
        }
        for (int k = 0; k < nplanes; ++k) {
            __global const float *pl = r + R_PLANE + 4 * k;
            const vec ne = du * pl[1] + dv * pl[2];
            const vec g = pl[0] + ne;
            const vec kk = pl[3] - tc * ne;
            const vec t = kk / g;
            t2 = select(t2, fmin(t2, t), g > 0.0f);
            t1 = select(t1, fmax(t1, t), g < 0.0f);
            valid &= ~((g == 0.0f) & (kk < 0.0f));
        }
        // cut ellipsoids: intersect narrows [t1, t2]; subtract removes up to two intervals
        vec s1lo = (vec)(0.0f), s1hi = (vec)(0.0f), s2lo = (vec)(0.0f), s2hi = (vec)(0.0f);
        for (int k = 0; k < 2; ++k) {
            const int mode = k == 0 ? cut0 : cut1;
            if (mode == 0)
                continue;
#if CULL
            // a cut whose rectangle misses these cells meets none of their rays
            __global const float *rr = r + R_CUT_RECT + 4 * k;
            if (rr[1] < slo || rr[0] > shi || rr[3] < vlo || rr[2] > vhi) {
                if (mode == CUT_INTERSECT)
                    valid = (ivec)(0);
                continue;
            }
#endif
            __global const float *cr = r + R_CUT + CUT_STRIDE * k;
            const vec fx = du * cr[6] + dv * cr[9];
            const vec fy = du * cr[7] + dv * cr[10];
            const vec fz = du * cr[8] + dv * cr[11];
            const vec qx = cr[0] + tc * fx, qy = cr[1] + tc * fy, qz = cr[2] + tc * fz;
            const vec gx = cr[3] + fx, gy = cr[4] + fy, gz = cr[5] + fz;
            const vec A2 = gx * gx + gy * gy + gz * gz;
            const vec B2 = qx * gx + qy * gy + qz * gz;
            const vec C2 = qx * qx + qy * qy + qz * qz - 1.0f;
            const vec disc2 = B2 * B2 - A2 * C2;
            const vec sq2 = sqrt(fmax(disc2, 0.0f));
            const ivec hit = disc2 > 0.0f;
            const vec c1 = select((vec)(0.0f), (-B2 - sq2) / A2, hit);
            const vec c2 = select((vec)(0.0f), (-B2 + sq2) / A2, hit);
            if (mode == CUT_INTERSECT) {
                t1 = fmax(t1, c1);
                t2 = fmin(t2, c2);
                valid &= hit;
            } else if (k == 0 || (cut0 != CUT_SUBTRACT)) {
                s1lo = c1; s1hi = c2;
            } else {
                s2lo = c1; s2hi = c2;
            }
        }
        vec len = fmax(t2 - t1, 0.0f);
        // |I \ (S1 u S2)| = |I| - |I n S1| - |I n S2| + |I n S1 n S2|
        len -= fmax(fmin(t2, s1hi) - fmax(t1, s1lo), 0.0f);
        len -= fmax(fmin(t2, s2hi) - fmax(t1, s2lo), 0.0f);
        len += fmax(fmin(fmin(t2, s1hi), s2hi) - fmax(fmax(t1, s1lo), s2lo), 0.0f);
        acc += r[R_MU] * select((vec)(0.0f), fmax(len, 0.0f), valid);
    }
    acc *= ray_len;

    __global float *o = out + ((size_t)iv * n_rows + row) * n_cols;
    const int c0 = seg * VW;
    if (c0 + VW <= n_cols) {
        if (accumulate)
            acc += VLOAD(0, o + c0);
        VSTORE(acc, 0, o + c0);
    } else {
#if VW == 1
        if (c0 < n_cols) o[c0] = accumulate ? o[c0] + acc : acc;
#else
        float tmp[VW];
        VSTORE(acc, 0, tmp);
        for (int l = 0; c0 + l < n_cols; ++l)
            o[c0 + l] = accumulate ? o[c0 + l] + tmp[l] : tmp[l];
#endif
    }
}
