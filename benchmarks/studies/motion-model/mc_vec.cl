// Study kernel (issue 41, item 4; benchmarks/studies/motion-model/mc_reads.py): the motion-compensated
// backprojection of kernels/mc_backproject.cl written one voxel per work-item, with every branch
// uniform across the work-items along x (the slice, the view, the slot, and a gate on the group's
// x range meeting the row's FOV chord), so that Intel's CPU compiler vectorises it across work-items
// (16 per AVX-512 vector, real gather instructions for the row taps) where the production kernel
// holds 16 voxels in explicit vectors and assembles its taps from scalar loads. Same arguments and
// results as the production kernel (within float32 contraction). Build options beside the
// production kernel's: LX, LY (a multiple of 16 along x for the vectoriser), VCHUNK (views between
// barriers; >= 100000: no barrier), and the study's variants: PAIR (each plane's two column taps as
// one 8-byte load), NOREAD (no row reads: the time of everything else), HOTREAD (mask: every slot
// reads projection p & HOTREAD's rows, a cache-resident few). Not part of the package.
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
    const int ix = get_global_id(0), iy = get_global_id(1), s = get_global_id(2);
    const float xv = ((float)ix - 0.5f * (float)(nx - 1)) * voxel_mm;
    const float y = ((float)iy - 0.5f * (float)(ny - 1)) * voxel_mm;
    const bool row_in = iy < ny && s < n_slices;
    const bool fov = ix < nx && xv * xv + y * y <= fov_r2;
    // uniform gate: does the group's x range meet the FOV chord of this row?
    const int gx0 = get_group_id(0) * LX;
    const int glast = gx0 + LX - 1 < nx ? gx0 + LX - 1 : nx - 1;
    const int ic = (nx - 1) / 2 < gx0 ? gx0 : ((nx - 1) / 2 > glast ? glast : (nx - 1) / 2);
    const float xc = ((float)ic - 0.5f * (float)(nx - 1)) * voxel_mm;
    const bool any_fov = row_in && gx0 < nx && xc * xc + y * y <= fov_r2 * 1.0002f;
    const float x = fov ? xv : 0.0f;
    const float yy = fov ? y : 0.0f;
    const float z = slice_z[s < n_slices ? s : n_slices - 1];
    const float inv_voxel = 1.0f / voxel_mm;
    const int fstride = mz_held * ny * nx;

    float W[NB][3];
    {
        float rx = x, ry = yy, rz = z;
        for (int it = 0; it < NINV; ++it) {
            GRID_CORNERS(rx, ry, rz)
            const float ux = TRILINEAR(target_field);
            const float uy = TRILINEAR(target_field + fstride);
            const float uz = TRILINEAR(target_field + 2 * fstride);
            rx = x - ux;
            ry = yy - uy;
            rz = z - uz;
        }
        GRID_CORNERS(rx, ry, rz)
        for (int b = 1; b < NB; ++b) {
            __global const float *f = fields + b * 3 * fstride;
            W[b][0] = TRILINEAR(f);
            W[b][1] = TRILINEAR(f + fstride);
            W[b][2] = TRILINEAR(f + 2 * fstride);
        }
    }
    const float last_col = (float)(n_cols - 1);
    float acc = 0.0f;
    for (int j0 = 0; j0 < n_views; j0 += VCHUNK) {
    if (any_fov) {
        const int j1 = j0 + VCHUNK < n_views ? j0 + VCHUNK : n_views;
        for (int j = j0; j < j1; ++j) {
            const float2 cs = trig[j];
            const int base = (s * n_views + j) * n_slots;
            float num = 0.0f, den = 0.0f, best_tz = 3.0e38f, best_val = 0.0f;
            for (int k = 0; k < n_slots; ++k) {
                const int p = slot_proj[base + k];
                if (p < 0)
                    break;
                const float w0 = slot_w[base + k];
                if (w0 == 0.0f)
                    continue;
                float dx = 0.0f, dy = 0.0f, dz = 0.0f;
                __global const float *db = proj_dbasis + p * NB;
#pragma unroll
                for (int b = 1; b < NB; ++b) {
                    const float beta = db[b];
                    dx += beta * W[b][0];
                    dy += beta * W[b][1];
                    dz += beta * W[b][2];
                }
                const float zm = z + dz;
                float wd;
                float c = fan_column(x + dx, yy + dy, cs, sdd_over_pitch, COL_CENTRE, &wd);
                c = c > 0.0f ? (c < last_col ? c : last_col) : 0.0f;
                int i0 = (int)c;
                i0 = i0 > n_cols - 2 ? n_cols - 2 : i0;
                const float tc = c - (float)i0;
                const int cnt = plane_count[p];
                float g = zm * inv_plane_dz - (float)plane_first[p];
                g = g > 0.0f ? (g < (float)(cnt - 1) ? g : (float)(cnt - 1)) : 0.0f;
                int g0 = (int)g;
                g0 = g0 > cnt - 2 ? cnt - 2 : g0;
                g0 = g0 < 0 ? 0 : g0;
                const float tg = g - (float)g0;
#ifdef HOTREAD
                __global const float *r0 = rows + (p & HOTREAD) * np_max * n_cols;
#else
                __global const float *r0 = rows + p * np_max * n_cols;
#endif
                __global const float *r1 = r0 + (cnt > 1 ? n_cols : 0);
                const int off = g0 * n_cols + i0;
#ifdef NOREAD
                const float val = tc * tg;
#elif defined(PAIR)
                const float2 a0 = vload2(0, r0 + off), a1 = vload2(0, r1 + off);
                const float val = (1.0f - tg) * ((1.0f - tc) * a0.x + tc * a0.y) + tg * ((1.0f - tc) * a1.x + tc * a1.y);
#else
                const float val = (1.0f - tg) * ((1.0f - tc) * r0[off] + tc * r0[off + 1])
                                  + tg * ((1.0f - tc) * r1[off] + tc * r1[off + 1]);
#endif
                float dzp = zm - proj_z[p];
                dzp = dzp < 0.0f ? -dzp : dzp;
                float taper = (window_mm - dzp) * inv_taper_mm;
                taper = taper < 0.0f ? 0.0f : (taper > 1.0f ? 1.0f : taper);
                const float w = w0 * taper;
                num += w * wd * val;
                den += w;
                const bool closer = dzp < best_tz;
                best_tz = closer ? dzp : best_tz;
                best_val = closer ? wd * val : best_val;
            }
            acc += den > 0.0f ? num / den : best_val;
        }
    }
#if VCHUNK < 100000
    barrier(CLK_GLOBAL_MEM_FENCE);
#endif
    }
    if (!row_in || ix >= nx)
        return;
    out[(s * ny + iy) * nx + ix] = fov ? acc * dbeta : 0.0f;
}
