// Supersampled voxelisation of quadric primitives (clrecon.simulation.voxelise.voxelise_objects).
//
// One work-item = VW neighbouring voxels along x of one (y, z) line; each voxel is the mean
// of SS^3 point samples on a regular sub-grid. Objects come in per-slice lists (host culled
// by z); a work-item skips objects whose axis-aligned box misses its voxels. Per object the
// host sends (float32): the world-to-local map M = D^-1 R^T and centre, the clip planes and
// up to two cut ellipsoids (layout below, must match clrecon/simulation/voxelise.py).
//
// Defines: VW (1, 4, 8, 16), SS (samples per axis), LX, LY (work-group shape).

#ifndef VW
#define VW 8
#endif
#ifndef SS
#define SS 3
#endif
#ifndef LX
#define LX 8
#endif
#ifndef LY
#define LY 8
#endif

#if VW == 1
typedef float vec;
typedef int ivec;
#define VSTORE(x, i, p) ((p)[i] = (x))
#elif VW == 4
typedef float4 vec;
typedef int4 ivec;
#define VSTORE vstore4
#define VLOAD vload4
#elif VW == 8
typedef float8 vec;
typedef int8 ivec;
#define VSTORE vstore8
#define VLOAD vload8
#elif VW == 16
typedef float16 vec;
typedef int16 ivec;
#define VSTORE vstore16
#define VLOAD vload16
#else
#error "VW must be 1, 4, 8 or 16"
#endif

#define VREC 64
#define V_FLAGS 0
#define V_MU 1
#define V_BOX 2      /* xlo, xhi, ylo, yhi, zlo, zhi */
#define V_C 8        /* centre (3), then M row-major (9) */
#define V_M 11
#define V_PLANE 20   /* 2 x (nx, ny, nz, d): n . x <= d */
#define V_CUT 28     /* 2 x (centre (3), M (9)) */
#define KIND_ELLIPSOID 1
#define CUT_SUBTRACT 1

// local coordinate k of the sample points: M[k] . (p - c), p = (x (vector), y, z)
#define LOCAL(Mp, k, px, pyc, pzc) ((px) * (Mp)[3 * (k)] + ((pyc) * (Mp)[3 * (k) + 1] + (pzc) * (Mp)[3 * (k) + 2]))

__kernel __attribute__((reqd_work_group_size(LX, LY, 1)))
void voxelise(__global const float *obj,     // (n_obj, VREC)
              __global const int *lists,     // (nz, list_stride) object indices per slice
              __global const int *counts,    // (nz,)
              const int list_stride,
              __global const float *xs, __global const float *ys, __global const float *zs,
              const float dx, const float dy, const float dz,
              const int nx, const int ny, const int nz,
              __global float *out)           // (nz, ny, nx)
{
    const int seg = get_global_id(0), iy = get_global_id(1), iz = get_global_id(2);
    const int x0 = seg * VW;
    if (x0 >= nx || iy >= ny || iz >= nz)
        return;
    vec x;
#if VW == 1
    x = xs[x0];
#else
    {
        float tmp[VW];
        for (int l = 0; l < VW; ++l)
            tmp[l] = xs[min(x0 + l, nx - 1)];
        x = VLOAD(0, tmp);
    }
#endif
    const float y = ys[iy], z = zs[iz];
    const float xlo = xs[x0] - 0.5f * dx, xhi = xs[min(x0 + VW, nx) - 1] + 0.5f * dx;
    const float ylo = y - 0.5f * dy, yhi = y + 0.5f * dy;
    const float step_x = dx / SS, step_y = dy / SS, step_z = dz / SS;
    const float off0 = -0.5f + 0.5f / SS;  // first sub-sample offset in voxel units

    vec acc = (vec)(0.0f);
    const int n = counts[iz];
    __global const int *lst = lists + (size_t)iz * list_stride;
    for (int j = 0; j < n; ++j) {
        __global const float *o = obj + (size_t)lst[j] * VREC;
        if (o[V_BOX + 1] < xlo || o[V_BOX] > xhi || o[V_BOX + 3] < ylo || o[V_BOX + 2] > yhi)
            continue;
        const int flags = (int)o[V_FLAGS];
        const int kind = flags & 3, nplanes = (flags >> 2) & 3;
        const int cut0 = (flags >> 4) & 3, cut1 = (flags >> 6) & 3;
        __global const float *M = o + V_M;
        vec count = (vec)(0.0f);
        for (int sz = 0; sz < SS; ++sz) {
            const float pz = z + (off0 + sz / (float)SS) * dz;
            for (int sy = 0; sy < SS; ++sy) {
                const float py = y + (off0 + sy / (float)SS) * dy;
                const float pyc = py - o[V_C + 1], pzc = pz - o[V_C + 2];
                for (int sx = 0; sx < SS; ++sx) {
                    const vec px = x + (off0 * dx + sx * step_x);
                    const vec pxc = px - o[V_C];
                    const vec l0 = LOCAL(M, 0, pxc, pyc, pzc);
                    const vec l1 = LOCAL(M, 1, pxc, pyc, pzc);
                    const vec l2 = LOCAL(M, 2, pxc, pyc, pzc);
                    ivec in;
                    if (kind == KIND_ELLIPSOID)
                        in = l0 * l0 + l1 * l1 + l2 * l2 <= 1.0f;
                    else
                        in = (l0 * l0 + l1 * l1 <= 1.0f) & (fabs(l2) <= 1.0f);
                    for (int k = 0; k < nplanes; ++k) {
                        __global const float *pl = o + V_PLANE + 4 * k;
                        in &= px * pl[0] + (py * pl[1] + pz * pl[2]) <= pl[3];
                    }
                    for (int k = 0; k < 2; ++k) {
                        const int mode = k == 0 ? cut0 : cut1;
                        if (mode == 0)
                            continue;
                        __global const float *cc = o + V_CUT + 12 * k;
                        const vec qx = px - cc[0];
                        const float qy = py - cc[1], qz = pz - cc[2];
                        const vec m0 = LOCAL(cc + 3, 0, qx, qy, qz);
                        const vec m1 = LOCAL(cc + 3, 1, qx, qy, qz);
                        const vec m2 = LOCAL(cc + 3, 2, qx, qy, qz);
                        const ivec inc = m0 * m0 + m1 * m1 + m2 * m2 <= 1.0f;
                        in &= (mode == CUT_SUBTRACT) ? ~inc : inc;
                    }
                    count += select((vec)(0.0f), (vec)(1.0f), in);
                }
            }
        }
        acc += o[V_MU] * count;
    }
    acc *= 1.0f / (SS * SS * SS);
    __global float *dst = out + ((size_t)iz * ny + iy) * nx;
    if (x0 + VW <= nx) {
        VSTORE(acc, 0, dst + x0);
    } else {
#if VW == 1
        dst[x0] = acc;
#else
        float tmp[VW];
        VSTORE(acc, 0, tmp);
        for (int l = 0; x0 + l < nx; ++l)
            dst[x0 + l] = tmp[l];
#endif
    }
}
