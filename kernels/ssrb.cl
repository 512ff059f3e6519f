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
