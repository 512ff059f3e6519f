// Motion-compensated fan-beam backprojection of SSRB rows on z planes (Rit, Sarrut & Desbat,
// IEEE TMI 28:1513, 2009, on rebinned helical data): each voxel x of a target state t is
// followed, through a motion model, to where it was when each row was measured, and the row of
// that projection rebinned to the plane through the moved point is read there.
// docs/motion-model.md "The method" (step 4); the NumPy float64 reference is
// clrecon.reconstruction.motion.backproject.mc_backproject_reference, the one-voxel-per-work-item
// kernel it replaced kernels/reference/mc_backproject_scalar.cl.
//
// Model (clrecon.reconstruction.motion.model): u(x_r; s) = sum_b B_b(s) U_b(x_r), fields U_b
// on the reconstruction's in-plane grid and MZ uniform z planes (model_z0 + m dz), trilinear
// with the indices clamped to the grid. For voxel x of the target:
//   1. x_r: NINV fixed-point steps x_r <- x - u_t(x_r) from x_r = x (u_t = the target's field,
//      made on the host as sum_b B_b(t) U_b);
//   2. W_b = U_b(x_r), b = 1..NB-1 (b = 0 is the constant: its difference is 0);
//   3. per (view j, slot k): projection p, weight w0; the displacement to p's state is
//      d = sum_b (B_b(p) - B_b(t)) W_b; the moved point x + d gives the column (fan_column.h's
//      formula, weight wd) and the plane coordinate (z + d_z) / plane_dz - plane_first[p] of p's
//      rows (clamped to its planes; linear in plane and column);
//   4. the slot's weight is w0 times a taper of |z + d_z - z_p| (the SSRB distance of the row):
//      1 up to window - taper, falling linearly to 0 at the SSRB window (no row is used beyond
//      its detector); per view, sum(w wd val) / sum(w); if every weight is 0, the slot nearest
//      in z alone (its clamped plane);
//   5. mu = dbeta sum_j (view value); 0 outside the FOV circle (of the target pixel).
// Every output has one owner; the loops run in a fixed order: the result does not depend on
// the launch size, the slab or the worker.
//
// Vectorisation (docs/kernels.md "Making kernels fast on PoCL"): neither PoCL nor Intel's CPU
// runtime vectorises the scalar kernel's work-item loop around its view and slot loops (data-
// dependent trip counts, a break), so a work-item here holds LANES (8 or 16) voxels along x in
// the lanes of vectors (kernels/mc_lanes.h). What depends on (view, slot) only -- the
// projection, its weight, basis differences, plane range and z -- is read and computed once for
// all lanes; each lane does its voxel's operations in the scalar kernel's order (its float32
// result equals the scalar kernel's up to contraction into FMAs), and gathers its 4 row taps.
// Lanes past nx or outside the FOV compute on the point (0, 0) (every index stays in range) and
// are not stored. The host builds 16 lanes where the device's native float vector holds 16
// (AVX-512), else 8 (backproject.lanes_for); measured 3.2-3.5x the scalar kernel on both CPU
// drivers (docs/results/mc-cost.md "Cost", benchmarks/mc_backproject.py).
//
// Layouts: rows (P, NPMAX, C) float, plane p of projection q at rows[(q NPMAX + p) C];
// slot_proj, slot_w (S, V, K) (empty slots: proj -1, at the end of a list); proj_dbasis (P, NB):
// B_b(p) - B_b(t), formed on the host per target in float32 (the scalar kernel's subtraction);
// fields (NB, 3, MZ_HELD, ny, nx); target_field (3, MZ_HELD, ny, nx): planes mz_first ..
// mz_first + mz_held - 1 of the model's mz (a slab's window, backproject.ModelWindow: the host holds
// every plane the slab's reference positions reach; coordinates and clamp are the whole model's);
// out (S, ny, nx). Offsets within
// one projection's rows (NPMAX C) and within one field component (MZ ny nx) are int: the host
// checks they are below 2^31.
// Work-item (bx, iy, s): voxels ix = LANES bx .. LANES bx + LANES - 1 of row iy of slice s.
// The host picks LX, LY and VCHUNK per driver (backproject.launch_shape: a 8x32 tile on Intel's
// runtime, whose work-items then share a chunk's rows from cache; 1x8 elsewhere); a work-item's
// result does not depend on them.
// Compile-time: LANES, LX, LY (local size), VCHUNK (views per barrier chunk), NB (basis size, >= 1),
// NINV (inversion steps), CURVED (+ ATAN_TERMS, ATAN_C*: atan_poly.h's coefficients).

#include "mc_lanes.h"

#if CURVED
#define COL_CENTRE col_centre
#else
#define COL_CENTRE (0.5f * (float)(n_cols - 1))
#endif

// out[l] = v.sl for the lanes l whose voxel lies in the image
#define STORE_LANE(l, v)                                                                      \
    if (ix0 + l < nx)                                                                         \
        o[l] = (v);

__kernel __attribute__((reqd_work_group_size(LX, LY, 1)))
void mc_backproject(__global const float *restrict rows,
                    __global const int *restrict plane_first,
                    __global const int *restrict plane_count,
                    __global const float *restrict proj_z,
                    __global const float *restrict proj_dbasis,
                    __global const int *restrict slot_proj,
                    __global const float *restrict slot_w,
                    __global const float *restrict fields,
                    __global const float *restrict target_field,
                    __global const float2 *restrict trig,
                    __global const float *restrict slice_z,
                    __global float *restrict out,
                    const int nx, const int ny, const int n_views, const int n_cols,
                    const float voxel_mm, const float sdd_over_pitch, const float fov_r2, const float dbeta,
                    const float col_centre,
                    const int n_slices, const int n_slots, const int np_max, const float inv_plane_dz,
                    const int mz, const float model_z0, const float inv_model_dz,
                    const int mz_first, const int mz_held,
                    const float window_mm, const float inv_taper_mm)
{
    const int ix0 = LANES * get_global_id(0), iy = get_global_id(1), s = get_global_id(2);
    const intL ixv = ix0 + LANE_IOTA_I;
    // ((float)ix - 0.5 (nx - 1)) voxel_mm per lane, as the scalar kernel (the sums are exact)
    const floatL xv = (((float)ix0 - 0.5f * (float)(nx - 1)) + LANE_IOTA_F) * voxel_mm;
    const float y = ((float)iy - 0.5f * (float)(ny - 1)) * voxel_mm;
    // no early return: every work-item of the group must reach the barriers
    const bool row_in = iy < ny && s < n_slices;
    // lanes in the image and the FOV (rows past the image, !row_in, do no work and store nothing;
    // and-ing a broadcast of row_in here made Oclgrind 21.10 compute masks of 1 instead of -1)
    const intL fov = (ixv < nx) & (xv * xv + y * y <= fov_r2);
    // does any lane lie in the FOV? Its lane nearest the centre column, tested on a radius 1e-4
    // larger (only a gate for the work: the stores test each lane). Not an OR of fov's lanes:
    // Oclgrind 21.10's uninitialised-value plugin crashes on that reduction's shuffles.
    const int last = ix0 + LANES - 1 < nx ? ix0 + LANES - 1 : nx - 1;
    const int ic = (nx - 1) / 2 < ix0 ? ix0 : ((nx - 1) / 2 > last ? last : (nx - 1) / 2);
    const float xc = ((float)ic - 0.5f * (float)(nx - 1)) * voxel_mm;
    const bool any_fov = row_in && ix0 < nx && xc * xc + y * y <= fov_r2 * 1.0002f;
    const floatL x = fov ? xv : 0.0f;           // lanes outside: the point (0, 0)
    const floatL yv = fov ? (floatL)(y) : 0.0f;
    // a work-item past the image samples the model at its slice's z (s < n_slices: the global size),
    // within the planes a window holds (backproject.ModelWindow), and stores nothing
    const float z = slice_z[s < n_slices ? s : n_slices - 1];
    const float inv_voxel = 1.0f / voxel_mm;
    const size_t fstride = (size_t)mz_held * ny * nx;   // one component of one field (the planes held)

    // 1.-2. the voxels' reference positions and their basis displacements W_b (b >= 1)
    floatL W[NB][3];
    {
        floatL rx = x, ry = yv, rz = (floatL)(z);
        for (int it = 0; it < NINV; ++it) {
            GRID_CORNERS_L(rx, ry, rz)
            const floatL ux = TRILINEAR_L(target_field);
            const floatL uy = TRILINEAR_L(target_field + fstride);
            const floatL uz = TRILINEAR_L(target_field + 2 * fstride);
            rx = x - ux;
            ry = yv - uy;
            rz = z - uz;
        }
        GRID_CORNERS_L(rx, ry, rz)
        for (int b = 1; b < NB; ++b) {
            __global const float *f = fields + (size_t)b * 3 * fstride;
            W[b][0] = TRILINEAR_L(f);
            W[b][1] = TRILINEAR_L(f + fstride);
            W[b][2] = TRILINEAR_L(f + 2 * fstride);
        }
    }

    const float last_col = (float)(n_cols - 1);
    floatL acc = (floatL)(0.0f);
    for (int j0 = 0; j0 < n_views; j0 += VCHUNK) {
        if (any_fov) {
            const int j1 = j0 + VCHUNK < n_views ? j0 + VCHUNK : n_views;
            for (int j = j0; j < j1; ++j) {
                const float2 cs = trig[j];
                const size_t base = ((size_t)s * n_views + j) * n_slots;
                floatL num = (floatL)(0.0f), den = (floatL)(0.0f);
                floatL best_tz = (floatL)(3.0e38f), best_val = (floatL)(0.0f);
                for (int k = 0; k < n_slots; ++k) {
                    const int p = slot_proj[base + k];
                    if (p < 0)
                        break;
                    const float w0 = slot_w[base + k];
                    if (w0 == 0.0f)
                        continue;
                    floatL dx = (floatL)(0.0f), dy = (floatL)(0.0f), dz = (floatL)(0.0f);
                    __global const float *db = proj_dbasis + (size_t)p * NB;
#pragma unroll
                    for (int b = 1; b < NB; ++b) {
                        const float beta = db[b];
                        dx += beta * W[b][0];
                        dy += beta * W[b][1];
                        dz += beta * W[b][2];
                    }
                    const floatL zm = z + dz;
                    floatL c, wd;
                    FAN_COLUMN_L(c, wd, x + dx, yv + dy, cs, sdd_over_pitch, COL_CENTRE)
                    c = CLAMP0_L(c, last_col);
                    intL i0 = TO_INT_L(c);
                    i0 = i0 > n_cols - 2 ? n_cols - 2 : i0;
                    const floatL tc = c - TO_FLOAT_L(i0);
                    const int cnt = plane_count[p];
                    floatL g = zm * inv_plane_dz - (float)plane_first[p];
                    g = CLAMP0_L(g, (float)(cnt - 1));
                    intL g0 = TO_INT_L(g);
                    g0 = g0 > cnt - 2 ? cnt - 2 : g0;
                    g0 = g0 < 0 ? 0 : g0;
                    const floatL tg = g - TO_FLOAT_L(g0);
                    // plane g0 + 1, or g0 itself where the projection has one plane
                    __global const float *r0 = rows + (size_t)p * np_max * n_cols;
                    __global const float *r1 = r0 + (cnt > 1 ? n_cols : 0);
                    const intL off = g0 * n_cols + i0;
                    const floatL val = (1.0f - tg) * ((1.0f - tc) * GATHER_L(r0, off) + tc * GATHER_L(r0 + 1, off))
                                       + tg * ((1.0f - tc) * GATHER_L(r1, off) + tc * GATHER_L(r1 + 1, off));
                    floatL dzp = zm - proj_z[p];
                    dzp = dzp < 0.0f ? -dzp : dzp;
                    floatL taper = (window_mm - dzp) * inv_taper_mm;
                    taper = taper < 0.0f ? 0.0f : (taper > 1.0f ? 1.0f : taper);
                    const floatL w = w0 * taper;
                    num += w * wd * val;
                    den += w;
                    const intL closer = dzp < best_tz;
                    best_tz = closer ? dzp : best_tz;
                    best_val = closer ? wd * val : best_val;
                }
                acc += den > 0.0f ? num / den : best_val;
            }
        }
        barrier(CLK_GLOBAL_MEM_FENCE);
    }
    if (!row_in || ix0 >= nx)
        return;
    const floatL res = fov ? acc * dbeta : 0.0f;
    __global float *o = out + ((size_t)s * ny + iy) * nx + ix0;
    FOR_LANES(STORE_LANE, res)
}
