// Reference kernel: the motion-compensated backprojection one voxel per work-item (scalar), the
// pipeline's kernel until 2026-12-06, kept as the benchmark's same-run reference and as the tests'
// independent cross-check of kernels/mc_backproject.cl (8 voxels per work-item in float8 lanes:
// the same operations per voxel in the same order). Launched by
// clrecon.bench.reference_kernels.mc_backproject_scalar.
//
// Motion-compensated fan-beam backprojection of SSRB rows on z planes (Rit, Sarrut & Desbat,
// IEEE TMI 28:1513, 2009, on rebinned helical data): each voxel x of a target state t is
// followed, through a motion model, to where it was when each row was measured, and the row of
// that projection rebinned to the plane through the moved point is read there.
// docs/motion-model.md "The method" (step 4); the NumPy float64 reference is
// clrecon.reconstruction.motion.backproject.mc_backproject_reference.
//
// Model (clrecon.reconstruction.motion.model): u(x_r; s) = sum_b B_b(s) U_b(x_r), fields U_b
// on the reconstruction's in-plane grid and MZ uniform z planes (model_z0 + m dz), trilinear
// with the indices clamped to the grid. For voxel x of the target:
//   1. x_r: NINV fixed-point steps x_r <- x - u_t(x_r) from x_r = x (u_t = the target's field,
//      made on the host as sum_b B_b(t) U_b);
//   2. W_b = U_b(x_r), b = 1..NB-1 (b = 0 is the constant: its difference is 0);
//   3. per (view j, slot k): projection p, weight w0; the displacement to p's state is
//      d = sum_b (B_b(p) - B_b(t)) W_b; the moved point x + d gives the column (fan_column.h,
//      weight wd) and the plane coordinate (z + d_z) / plane_dz - plane_first[p] of p's rows
//      (clamped to its planes; linear in plane and column);
//   4. the slot's weight is w0 times a taper of |z + d_z - z_p| (the SSRB distance of the row):
//      1 up to window - taper, falling linearly to 0 at the SSRB window (no row is used beyond
//      its detector); per view, sum(w wd val) / sum(w); if every weight is 0, the slot nearest
//      in z alone (its clamped plane);
//   5. mu = dbeta sum_j (view value); 0 outside the FOV circle (of the target pixel).
// Every output has one owner; the loops run in a fixed order: the result does not depend on
// the launch size, the slab or the worker.
//
// Layouts: rows (P, NPMAX, C) float, plane p of projection q at rows[(q NPMAX + p) C];
// slot_proj, slot_w (S, V, K) (empty slots: proj -1, at the end of a list); proj_basis (P, NB);
// fields (NB, 3, MZ_HELD, ny, nx); target_field (3, MZ_HELD, ny, nx): planes mz_first .. of the
// model's mz, as mc_backproject.cl; out (S, ny, nx).
// Compile-time: LX, LY (local size), VCHUNK (views per barrier chunk), NB (basis size, >= 1),
// NINV (inversion steps), CURVED (+ ATAN_TERMS, ATAN_C*: fan_column.h).

#ifndef CURVED
#define CURVED 0
#endif
#include "fan_column.h"

#if CURVED
#define COL_CENTRE col_centre
#else
#define COL_CENTRE (0.5f * (float)(n_cols - 1))
#endif

#define GRID_Z_FIRST mz_first
#include "motion_grid.h"

__kernel __attribute__((reqd_work_group_size(LX, LY, 1)))
void mc_backproject(__global const float *restrict rows,
                    __global const int *restrict plane_first,
                    __global const int *restrict plane_count,
                    __global const float *restrict proj_z,
                    __global const float *restrict proj_basis,
                    __global const int *restrict slot_proj,
                    __global const float *restrict slot_w,
                    __global const float *restrict fields,
                    __global const float *restrict target_field,
                    __global const float *restrict target_basis,
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
    const int ix = get_global_id(0), iy = get_global_id(1), s = get_global_id(2);
    const float x = ((float)ix - 0.5f * (float)(nx - 1)) * voxel_mm;
    const float y = ((float)iy - 0.5f * (float)(ny - 1)) * voxel_mm;
    // no early return: every work-item of the group must reach the barriers
    const bool in_image = ix < nx && iy < ny && s < n_slices;
    const bool in_fov = in_image && x * x + y * y <= fov_r2;
    const float z = slice_z[s < n_slices ? s : n_slices - 1];   // past the image: its slice's (stores nothing)
    const float inv_voxel = 1.0f / voxel_mm;
    const size_t fstride = (size_t)mz_held * ny * nx;   // one component of one field (the planes held)

    // 1.-2. the voxel's reference position and its basis displacements W_b (b >= 1)
    float W[NB][3];
    float tb[NB];
    for (int b = 0; b < NB; ++b)
        tb[b] = target_basis[b];
    {
        float rx = x, ry = y, rz = z;
        for (int it = 0; it < NINV; ++it) {
            GRID_CORNERS(rx, ry, rz)
            const float ux = TRILINEAR(target_field);
            const float uy = TRILINEAR(target_field + fstride);
            const float uz = TRILINEAR(target_field + 2 * fstride);
            rx = x - ux;
            ry = y - uy;
            rz = z - uz;
        }
        GRID_CORNERS(rx, ry, rz)
        for (int b = 0; b < NB; ++b) {
            __global const float *f = fields + (size_t)b * 3 * fstride;
            W[b][0] = TRILINEAR(f);
            W[b][1] = TRILINEAR(f + fstride);
            W[b][2] = TRILINEAR(f + 2 * fstride);
        }
    }

    const float last_col = (float)(n_cols - 1);
    float acc = 0.0f;
    for (int j0 = 0; j0 < n_views; j0 += VCHUNK) {
        if (in_fov) {
            const int j1 = j0 + VCHUNK < n_views ? j0 + VCHUNK : n_views;
            for (int j = j0; j < j1; ++j) {
                const float2 cs = trig[j];
                const size_t base = ((size_t)s * n_views + j) * n_slots;
                float num = 0.0f, den = 0.0f, best_tz = 3.0e38f, best_val = 0.0f;
                for (int k = 0; k < n_slots; ++k) {
                    const int p = slot_proj[base + k];
                    if (p < 0)
                        break;
                    const float w0 = slot_w[base + k];
                    if (w0 == 0.0f)
                        continue;
                    float dx = 0.0f, dy = 0.0f, dz = 0.0f;
                    __global const float *pb = proj_basis + (size_t)p * NB;
                    for (int b = 1; b < NB; ++b) {
                        const float beta = pb[b] - tb[b];
                        dx += beta * W[b][0];
                        dy += beta * W[b][1];
                        dz += beta * W[b][2];
                    }
                    const float zm = z + dz;
                    float wd;
                    float c = fan_column(x + dx, y + dy, cs, sdd_over_pitch, COL_CENTRE, &wd);
                    c = c < 0.0f ? 0.0f : (c > last_col ? last_col : c);
                    int i0 = (int)c;
                    i0 = i0 > n_cols - 2 ? n_cols - 2 : i0;
                    const float tc = c - (float)i0;
                    const int cnt = plane_count[p];
                    float g = zm * inv_plane_dz - (float)plane_first[p];
                    g = g < 0.0f ? 0.0f : (g > (float)(cnt - 1) ? (float)(cnt - 1) : g);
                    int g0 = (int)g;
                    g0 = g0 > cnt - 2 ? cnt - 2 : g0;
                    g0 = g0 < 0 ? 0 : g0;
                    const int g1 = g0 + 1 < cnt ? g0 + 1 : g0;
                    const float tg = g - (float)g0;
                    __global const float *r0 = rows + ((size_t)p * np_max + g0) * n_cols;
                    __global const float *r1 = rows + ((size_t)p * np_max + g1) * n_cols;
                    const float val = (1.0f - tg) * ((1.0f - tc) * r0[i0] + tc * r0[i0 + 1])
                                      + tg * ((1.0f - tc) * r1[i0] + tc * r1[i0 + 1]);
                    float dzp = zm - proj_z[p];
                    dzp = dzp < 0.0f ? -dzp : dzp;
                    float taper = (window_mm - dzp) * inv_taper_mm;
                    taper = taper < 0.0f ? 0.0f : (taper > 1.0f ? 1.0f : taper);
                    const float w = w0 * taper;
                    num += w * wd * val;
                    den += w;
                    if (dzp < best_tz) {
                        best_tz = dzp;
                        best_val = wd * val;
                    }
                }
                acc += den > 0.0f ? num / den : best_val;
            }
        }
        barrier(CLK_GLOBAL_MEM_FENCE);
    }
    if (!in_image)
        return;
    out[((size_t)s * ny + iy) * nx + ix] = in_fov ? acc * dbeta : 0.0f;
}
