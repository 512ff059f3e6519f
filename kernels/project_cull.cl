// The projector's culling pass: per-(view, object) records for kernels/project.cl, in float64
// (clrecon.simulation.projector).
//
// One work-item per view loops over the view's objects (packed layout of clrecon.simulation.phantoms.layout),
// culls them (bounding sphere against the pyramid of rays, then the object's detector
// rectangle against the detector) and writes the records of the survivors, compacted and
// in object order, as float32. It is the same computation as the NumPy reference
// clrecon.simulation.projector.prepare_records, which the tests compare it with; see there for the
// formulas. Defines: CULL (0: keep every active object, the unculled reference).

#pragma OPENCL EXTENSION cl_khr_fp64 : enable

#ifndef CULL
#define CULL 1
#endif

// packed object layout (clrecon/simulation/phantoms/layout.py)
#define STRIDE 57
#define O_KIND 0
#define O_MU 1
#define O_CENTRE 2
#define O_AXES 5
#define O_SEMI 14
#define O_PLANES 17
#define O_CUT0 25
#define CUT_LEN 16
#define KIND_CYLINDER 2
#define CUT_NONE 0
#define CUT_INTERSECT 2

#include "record.h"
#define NO_SLAB 256

// 3-vectors as double4 with w = 0: no undefined padding lane (Oclgrind's uninitialised-value
// checker otherwise taints dot products through the padding of double3)
typedef double4 d3;
#define V3(x, y, z) ((d3)((x), (y), (z), 0.0))

static d3 ld3(__global const double *p) { return V3(p[0], p[1], p[2]); }

static void st3(__global float *p, d3 v) { p[0] = (float)v.x; p[1] = (float)v.y; p[2] = (float)v.z; }

// M = D^-1 R^T applied to v: component i = (column i of R) . v / semi_i
static d3 local_of(__global const double *axes, __global const double *semi, d3 v) {
    const d3 c0 = V3(axes[0], axes[3], axes[6]);
    const d3 c1 = V3(axes[1], axes[4], axes[7]);
    const d3 c2 = V3(axes[2], axes[5], axes[8]);
    return V3(dot(c0, v) / semi[0], dot(c1, v) / semi[1], dot(c2, v) / semi[2]);
}

static d3 col_of(__global const double *axes, int j) { return V3(axes[j], axes[3 + j], axes[6 + j]); }

// detector rectangle of a box (local [lo, hi] in the primitive's normalised frame): see _rect
static double4 box_rect(d3 centre, __global const double *axes, __global const double *semi, d3 lo, d3 hi,
                        d3 s, d3 D0, d3 n, double nn, d3 a_u, d3 a_v) {
    const d3 c0 = col_of(axes, 0) * semi[0], c1 = col_of(axes, 1) * semi[1], c2 = col_of(axes, 2) * semi[2];
    const d3 base = centre - s + c0 * lo.x + c1 * lo.y + c2 * lo.z;
    const d3 s0 = c0 * (hi.x - lo.x), s1 = c1 * (hi.y - lo.y), s2 = c2 * (hi.z - lo.z);
    const double size = length(base) + length(s0) + length(s1) + length(s2);
    const double D0n = dot(D0, n), u0 = dot(D0, a_u), v0 = dot(D0, a_v);
    double umin = INFINITY, umax = -INFINITY, vmin = INFINITY, vmax = -INFINITY, dmin = INFINITY;
    for (int c = 0; c < 8; ++c) {
        const d3 X = base + s0 * (double)((c >> 2) & 1) + s1 * (double)((c >> 1) & 1) + s2 * (double)(c & 1);
        const double den = dot(X, n);
        const double lam = D0n / den;
        const double u = lam * dot(X, a_u) - u0, v = lam * dot(X, a_v) - v0;
        dmin = fmin(dmin, den);
        umin = fmin(umin, u); umax = fmax(umax, u);
        vmin = fmin(vmin, v); vmax = fmax(vmax, v);
    }
    if (!(dmin > 1e-9 * size * sqrt(nn)))
        return (double4)(-INFINITY, INFINITY, -INFINITY, INFINITY);
    return (double4)(umin, umax, vmin, vmax);
}

static void store_rect(__global float *p, double4 r) {
    const double4 pad = 1e-4 + 1e-5 * fabs(r);
    const double4 q = clamp(r + (double4)(-1.0, 1.0, -1.0, 1.0) * pad, -3e38, 3e38);
    p[0] = (float)q.x; p[1] = (float)q.y; p[2] = (float)q.z; p[3] = (float)q.w;
}

__kernel void cull_records(__global const double *objs,   // views' objects: view i at objs + i * view_stride
                           const long view_stride,         // doubles between views (0: the same objects)
                           const int n_obj,
                           __global const double *views,  // (m, 12): src, det - src, e_u, e_v
                           const double ul, const double uh, const double vl, const double vh,
                           const int m,
                           __global float *rec,            // (m, n_obj, REC), compacted per view
                           __global int *count)            // (m,)
{
    const int iv = get_global_id(0);
    if (iv >= m)
        return;
    __global const double *vw = views + 12 * (size_t)iv;
    const d3 s = ld3(vw), D0 = ld3(vw + 3), eu = ld3(vw + 6), ev = ld3(vw + 9);
    const d3 n0 = cross(eu, ev);
    const double nn0 = dot(n0, n0);
    const d3 n = dot(D0, n0) >= 0.0 ? n0 : -n0;  // detector normal, away from the source
    const double nn = dot(n, n);
    const d3 nhat = n / sqrt(nn);
    const d3 a_u = cross(ev, n0) / nn0, a_v = cross(n0, eu) / nn0;
    // pyramid of rays through the outermost cell centres: inward unit normals of its sides
    d3 dirs[4] = {D0 + ul * eu + vl * ev, D0 + uh * eu + vl * ev, D0 + uh * eu + vh * ev, D0 + ul * eu + vh * ev};
    const d3 inner = D0 + 0.5 * (ul + uh) * eu + 0.5 * (vl + vh) * ev;
    d3 sides[4];
    for (int k = 0; k < 4; ++k) {
        const d3 N = cross(dirs[k], dirs[(k + 1) & 3]);
        const double norm = length(N);
        const int live = norm > 1e-12 * dot(dirs[k], dirs[k]);
        const double sgn = dot(N, inner) >= 0.0 ? 1.0 : -1.0;
        sides[k] = live ? N * (sgn / norm) : (d3)(0.0);
    }
    const d3 dd = normalize(inner);

    __global const double *obase = objs + (size_t)iv * view_stride;
    int kept = 0;
    for (int j = 0; j < n_obj; ++j) {
        __global const double *o = obase + (size_t)j * STRIDE;
        const int kind = (int)o[O_KIND];
        const double mu = o[O_MU];
        if (kind == 0 || mu == 0.0)
            continue;
        const d3 c = ld3(o + O_CENTRE);
        __global const double *ax = o + O_AXES;
        __global const double *semi = o + O_SEMI;
        const int cyl = kind == KIND_CYLINDER;
#if CULL
        {
            const double rho = cyl ? hypot(fmax(semi[0], semi[1]), semi[2]) : fmax(fmax(semi[0], semi[1]), semi[2]);
            const d3 rel = c - s;
            int in = 1;
            for (int k = 0; k < 4; ++k)
                in &= dot(rel, sides[k]) >= -rho;
            if (!in && !(dot(rel, nhat) <= rho))
                continue;
        }
#endif
        // the ray through the centre
        const d3 rc = c - s;
        const double den = dot(rc, n);
        const int front = den > 1e-12 * length(rc) * sqrt(nn);
        const double lam = front ? dot(D0, n) / den : 1.0;
        const d3 pc_rel = front ? rc * lam : D0;
        const double tc = front ? 1.0 / lam : dot(rc, D0) / dot(D0, D0);
        const d3 r = pc_rel - D0;
        const double uc = dot(cross(r, ev), n0) / nn0, vc = dot(cross(eu, r), n0) / nn0;
        const d3 Xc = s + tc * pc_rel;
        const d3 oo = local_of(ax, semi, Xc - c);
        const d3 dc = local_of(ax, semi, pc_rel), eul = local_of(ax, semi, eu), evl = local_of(ax, semi, ev);
        const d3 Wu = cross(oo, eul) + tc * cross(eul, dc);
        const d3 Wv = cross(oo, evl) + tc * cross(evl, dc);
        const d3 W0 = cross(oo, dc);
        const d3 mask = cyl ? V3(1.0, 1.0, 0.0) : V3(1.0, 1.0, 1.0);
        const double Bu = dot(oo * mask, eul) + tc * dot(eul * mask, dc);
        const double Bv = dot(oo * mask, evl) + tc * dot(evl * mask, dc);
        const double B0 = dot(oo * mask, dc);

        __global float *R = rec + ((size_t)iv * n_obj + kept) * REC;
        for (int i = 0; i < REC; ++i)
            R[i] = 0.0f;
        R[R_MU] = (float)mu;
        R[R_UC] = (float)uc; R[R_VC] = (float)vc; R[R_TC] = (float)tc;
        st3(R + R_DC, dc); st3(R + R_EU, eul); st3(R + R_EV, evl);
        st3(R + R_WU, Wu); st3(R + R_WV, Wv); st3(R + R_W0, W0);
        R[R_BU] = (float)Bu; R[R_BV] = (float)Bv; R[R_B0] = (float)B0;
        R[R_OX] = (float)oo.x; R[R_OY] = (float)oo.y; R[R_OZ] = (float)oo.z;

        // clip planes, and the local box they tighten when aligned with an axis
        int nplanes = 0;
        // local box as scalars: Oclgrind's uninitialised-value checker crashes on private
        // arrays and on vectors updated per component under a condition
        double lo_x = -1.0, lo_y = -1.0, lo_z = -1.0, hi_x = 1.0, hi_y = 1.0, hi_z = 1.0;
        for (int k = 0; k < 2; ++k) {
            const d3 pn = ld3(o + O_PLANES + 4 * k);
            const double pd = o[O_PLANES + 4 * k + 3];
            const int on = pn.x != 0.0 || pn.y != 0.0 || pn.z != 0.0;
            __global float *pl = R + R_PLANE + 4 * nplanes;
            if (on) {
                pl[0] = (float)dot(pn, pc_rel); pl[1] = (float)dot(pn, eu); pl[2] = (float)dot(pn, ev);
                pl[3] = (float)(pd - dot(pn, Xc));
                nplanes++;
                const d3 nl = V3(dot(col_of(ax, 0), pn) * semi[0], dot(col_of(ax, 1), pn) * semi[1],
                                   dot(col_of(ax, 2), pn) * semi[2]);
                const double rhs = pd - dot(pn, c);
                const d3 mag = V3(fabs(nl.x), fabs(nl.y), fabs(nl.z));
                const double tiny = 1e-9 * fmax(fmax(mag.x, mag.y), mag.z);
                // a plane along local axis a bounds the box on that axis
#define TIGHTEN(A, B, C)                                                          \
                if (mag.A > 0.0 && fmax(mag.B, mag.C) <= tiny) {                  \
                    if (nl.A > 0.0) hi_##A = fmin(hi_##A, rhs / nl.A);            \
                    else lo_##A = fmax(lo_##A, rhs / nl.A);                       \
                }
                TIGHTEN(x, y, z)
                TIGHTEN(y, z, x)
                TIGHTEN(z, x, y)
#undef TIGHTEN
            } else if (pd < 0.0) {  // n = 0, d < 0: excludes everything
                pl[3] = -1.0f;
                nplanes++;
            }
        }
        int flags = kind | (nplanes << 2);
        double4 rect = box_rect(c, ax, semi, V3(lo_x, lo_y, lo_z), V3(hi_x, hi_y, hi_z), s, D0, n, nn, a_u, a_v);
        for (int k = 0; k < 2; ++k) {
            __global const double *ct = o + O_CUT0 + CUT_LEN * k;
            const int mode = (int)ct[0];
            flags |= mode << (4 + 2 * k);
            if (mode == CUT_NONE)
                continue;
            const d3 cc = ld3(ct + 1);
            __global const double *cax = ct + 4;
            __global const double *csemi = ct + 13;
            __global float *cr = R + R_CUT + CUT_STRIDE * k;
            st3(cr, local_of(cax, csemi, Xc - cc));
            st3(cr + 3, local_of(cax, csemi, pc_rel));
            st3(cr + 6, local_of(cax, csemi, eu));
            st3(cr + 9, local_of(cax, csemi, ev));
            const double4 r2 = box_rect(cc, cax, csemi, V3(-1.0, -1.0, -1.0), V3(1.0, 1.0, 1.0),
                                        s, D0, n, nn, a_u, a_v);
            store_rect(R + R_CUT_RECT + 4 * k, r2);
            if (mode == CUT_INTERSECT)
                rect = (double4)(fmax(rect.x, r2.x), fmin(rect.y, r2.y), fmax(rect.z, r2.z), fmin(rect.w, r2.w));
        }
        if (cyl) {  // cylinder whose caps no ray meets (see prepare_records)
            const d3 axis = col_of(ax, 2);
            const double h_len = semi[2], rho_cap = fmax(semi[0], semi[1]);
            int no_slab = 1;
            for (int sg = -1; sg <= 1; sg += 2) {
                const d3 cap = c + (double)sg * h_len * axis - s;
                int below = 0, above = 0;
                for (int k = 0; k < 4; ++k) {
                    const double d = dot(cap, sides[k]);
                    below |= d < -rho_cap;
                    above |= d > rho_cap;
                }
                no_slab &= below & above;
            }
            const d3 r0 = s - c;
            const double b = dot(dd, axis), denom = 1.0 - b * b;
            const double t_ax = denom > 1e-12 ? (dot(r0, axis) - dot(r0, dd) * b) / denom : 0.0;
            const d3 on_axis = c + clamp(t_ax, -h_len, h_len) * axis - s;
            for (int k = 0; k < 4; ++k)
                no_slab &= dot(on_axis, sides[k]) >= 0.0;
            no_slab &= dot(on_axis, n) > 0.0;
            flags |= no_slab ? NO_SLAB : 0;
        }
        const double4 pad = 1e-4 + 1e-5 * fabs(rect);
        const double4 prect = rect + (double4)(-1.0, 1.0, -1.0, 1.0) * pad;
        store_rect(R + R_RECT, rect);
        R[R_FLAGS] = (float)flags;
#if CULL
        // rectangle off the detector: not kept, the next survivor overwrites this slot
        kept += (prect.y >= ul && prect.x <= uh && prect.w >= vl && prect.z <= vh) ? 1 : 0;
#else
        kept++;
#endif
    }
    count[iv] = kept;
}
