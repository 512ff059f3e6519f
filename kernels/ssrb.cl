// Single-slice rebinning (SSRB) of flat-detector helical cone-beam projections
// (Noo, Defrise, Clackdoyle & Kudo, Phys. Med. Biol. 44:561, 1999; docs/algorithms.md "SSRB").
//
// For slice z and projection k (source at z_k), the oblique ray of column u that crosses
// the slice plane where the fan ray passes closest to the rotation axis hits the detector
// at row coordinate  v(u) = (u^2 + SDD^2) / (SID SDD) * (z - z_k).  We sample v(u) by
// linear interpolation between detector rows and scale by
// sqrt(SDD^2 + u^2) / sqrt(SDD^2 + u^2 + v^2) (oblique path length -> in-plane path length).
//
// Outside the outer row centres the row coordinate is CLAMPED to the outer row (the scale
// then uses the v actually sampled). The caller picks candidates with
// clrecon.reconstruction.rebin.slice_window_mm so that this never happens for columns that see the object.
//
// One work-item per (pair, column), column fastest: neighbouring work-items read
// neighbouring detector cells (PoCL vectorises across work-items). Global size is padded
// to the fixed local size, hence the bounds check.

// CURVED = 1: a cylindrical detector (clrecon.core.detector.CylindricalDetector). Column c
// is at fan angle gamma = (c - central_col) * dgamma; the arc lies at in-plane distance SDD
// along every ray and the SSRB ray's midpoint at SID cos(gamma), so v = SDD / (SID cos gamma) * dz
// (rows at (r - central_row) * row_pitch) and the oblique -> in-plane factor is
// SDD / sqrt(SDD^2 + v^2).
// FFS = 1 (with CURVED): each pair has its focal spot's offset (a, b, c) from the focal centre
// (a along the central ray, b along e_u, c along z; clrecon.core.detector.spot_shift_in_frame)
// and dz = slice_z - z of the focal centre. The spot sits at height c: the ray from it through
// the midpoint reaches the arc (in-plane distance t) at v = c + (dz - c) t / (R' cos gamma).
// FFS_PHI = 1 (an in-plane shift, a or b != 0): the output column c is the ray at
// gamma_out = (c - central_col) dgamma from the *spot's* central ray (spot -> isocentre, R' =
// |spot|), the equiangular fan of the spot that FBP backprojects from the spot's angle; it
// meets the arc (centred on the focal centre) at the fractional column of angle gamma_phys,
// read by bilinear interpolation (columns and rows, both clamped to the detector).

#ifndef CURVED
#define CURVED 0
#endif
#ifndef FFS
#define FFS 0
#endif
#ifndef FFS_PHI
#define FFS_PHI 0
#endif

#if CURVED
#if FFS_PHI
// atan(t) / dgamma for the column of a phi-FFS spot's ray
#include "atan_poly.h"
#endif
__kernel void ssrb_rows(__global const float *proj,      // (m, block_rows, n_cols): rows first_row..
                        __global const int *pair_slot,   // (n_pairs,) index into m
                        __global const float *pair_dz,   // (n_pairs,) slice_z - z of the focal centre, mm
#if FFS
                        __global const float4 *pair_shift, // (n_pairs,) spot offset (a, b, c) mm, 1 / R'
#endif
                        __global float *out,             // (n_pairs, n_cols) in-plane rows
                        const int n_pairs,
                        const int n_rows,
                        const int first_row,
                        const int block_rows,
                        const int n_cols,
                        __global const float4 *colgeo,   // (n_cols,) cos g, sin g, SDD / (SID cos g), 1 / cos g
                        const float dgamma,              // col_pitch / SDD, rad
                        const float row_pitch_mm,
                        const float sid_mm,
                        const float sdd_mm,
                        const float central_col,
                        const float central_row)
{
    const int col = get_global_id(0);
    const int p = get_global_id(1);
    if (col >= n_cols || p >= n_pairs)
        return;
    const float4 cg4 = colgeo[col];  // per column, from float64 on the host (no builtins here)
    const float dz = pair_dz[p];
#if FFS
    const float4 sh = pair_shift[p];
#if FFS_PHI
    // the spot's own fan: central ray n' = (SID - a, -b) / R', e_u' = (b, SID - a) / R'
    const float na = (sid_mm - sh.x) * sh.w, nb = -sh.y * sh.w;       // sh.w = 1 / R' (host)
    const float cg = cg4.x, sg = cg4.y;
    const float dx = cg * na - sg * nb, dy = cg * nb + sg * na;        // ray direction
    const float ad = sh.x * dx + sh.y * dy;
    const float t = -ad + sqrt(ad * ad - (sh.x * sh.x + sh.y * sh.y) + sdd_mm * sdd_mm);
    const float px = sh.x + t * dx, py = sh.y + t * dy;                          // hit on the arc
    const float fc = clamp(atan_poly(py / px) + central_col, 0.0f, (float)(n_cols - 1));
    const float v = sh.z + (dz - sh.z) * t * sh.w * cg4.w;           // cg4.w = 1 / cos g
#else
    const float t = sdd_mm;
    const float v = sh.z + (dz - sh.z) * cg4.z;
#endif
#else
    const float t = sdd_mm;
    const float v = cg4.z * dz;
#endif
    const float fr = clamp(v / row_pitch_mm + central_row, 0.0f, (float)(n_rows - 1));
    const int r0 = min((int)fr, max(n_rows - 2, 0));
    const int r1 = min(r0 + 1, n_rows - 1);
    const float tr = fr - (float)r0;
    const size_t base = (size_t)pair_slot[p] * (size_t)block_rows * (size_t)n_cols;
    __global const float *q0 = proj + base + (size_t)(r0 - first_row) * (size_t)n_cols;
    __global const float *q1 = proj + base + (size_t)(r1 - first_row) * (size_t)n_cols;
#if FFS_PHI
    const int c0 = min((int)fc, max(n_cols - 2, 0));
    const int c1 = min(c0 + 1, n_cols - 1);
    const float tc = fc - (float)c0;
    const float a0 = (1.0f - tc) * q0[c0] + tc * q0[c1];
    const float a1 = (1.0f - tc) * q1[c0] + tc * q1[c1];
#else
    const float a0 = q0[col];
    const float a1 = q1[col];
#endif
#if FFS
    const float vs = (fr - central_row) * row_pitch_mm - sh.z;  // height above the spot, as sampled
#else
    const float vs = (fr - central_row) * row_pitch_mm;
#endif
    const float scale = t / sqrt(t * t + vs * vs);
    out[(size_t)p * (size_t)n_cols + (size_t)col] = scale * ((1.0f - tr) * a0 + tr * a1);
}
#else
__kernel void ssrb_rows(__global const float *proj,      // (m, block_rows, n_cols): rows first_row..
                        __global const int *pair_slot,   // (n_pairs,) index into m
                        __global const float *pair_dz,   // (n_pairs,) slice_z - z_k, mm
                        __global float *out,             // (n_pairs, n_cols) in-plane rows
                        const int n_pairs,
                        const int n_rows,                // rows of the whole detector
                        const int first_row,             // detector row of the block's row 0
                        const int block_rows,            // rows held per projection
                        const int n_cols,
                        const float col_pitch_mm,
                        const float row_pitch_mm,
                        const float sid_mm,
                        const float sdd_mm)
{
    const int col = get_global_id(0);
    const int p = get_global_id(1);
    if (col >= n_cols || p >= n_pairs)
        return;

    const float u = ((float)col - 0.5f * (float)(n_cols - 1)) * col_pitch_mm;
    const float q = u * u + sdd_mm * sdd_mm;                 // |source -> cell (u, 0)|^2
    const float v = q / (sid_mm * sdd_mm) * pair_dz[p];
    const float centre = 0.5f * (float)(n_rows - 1);
    const float fr = clamp(v / row_pitch_mm + centre, 0.0f, (float)(n_rows - 1));

    // r0 <= n_rows - 2 keeps r0 + 1 inside; for a single-row detector r0 = r1 = 0.
    const int r0 = min((int)fr, max(n_rows - 2, 0));
    const int r1 = min(r0 + 1, n_rows - 1);
    const float t = fr - (float)r0;

    // size_t: m * n_rows * n_cols exceeds 2^31 for a paper-scale slab. The host checks that
    // the block holds every row the pairs read (clrecon.reconstruction.rebin.ssrb_row_range).
    const size_t base = (size_t)pair_slot[p] * (size_t)block_rows * (size_t)n_cols + (size_t)col;
    const float a0 = proj[base + (size_t)(r0 - first_row) * (size_t)n_cols];
    const float a1 = proj[base + (size_t)(r1 - first_row) * (size_t)n_cols];

    const float vs = (fr - centre) * row_pitch_mm;           // v actually sampled
    const float scale = sqrt(q / (q + vs * vs));
    out[(size_t)p * (size_t)n_cols + (size_t)col] = scale * ((1.0f - t) * a0 + t * a1);
}
#endif
