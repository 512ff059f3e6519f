// The interleaved interpolation kernels' shared parts: the slot count, the padded column a
// work-item owns, 16-lane loads and stores, and the 16 lanes of one column (kernels/interp.cl's
// apply_weights_interleaved16_cols8 and kernels/reference/interp_reference.cl's per-lane kernel).

#ifndef APPLY_K
#define APPLY_K 1
#endif
// the row column a padded column cp reads (edge replicas: cp 0 and n_cols + 1 read columns 0 and
// n_cols - 1)
inline int row_column(const int cp, const int n_cols)
{
    return cp < 1 ? 0 : (cp > n_cols ? n_cols - 1 : cp - 1);
}
// work-item (cp, v, g) of the interleaved kernels: its padded column cp, view v, group g and the
// row column it reads
#define APPLY16_COLUMN                                                    \
    const int cp = get_global_id(0);                                      \
    const int v = get_global_id(1);                                       \
    const int g = get_global_id(2);                                       \
    if (cp >= n_cols + 2 || v >= n_views)                                 \
        return;                                                           \
    const int col = row_column(cp, n_cols);
// 16 lanes read and written through a 16-vector pointer, not vload16/vstore16: PoCL 3.0 (LLVM 14)
// aborts compiling its own vload16/vstore16 on CPUs with AVX-512 ("LLVM ERROR: Do not know how to
// scalarize this operator's operand", seen 2026-12-04 on an AMD EPYC that PoCL names znver3 with
// 16-float native vectors), and two vload8 halves make Oclgrind report the joined vector as
// uninitialised. The pointer needs 64-byte alignment: every address here is a multiple of 16
// floats past the start of a buffer (OpenCL aligns buffers to CL_DEVICE_MEM_BASE_ADDR_ALIGN, at
// least 128 bytes in the full profile: the size of a long16).
#define LOAD16(T, p) (*(__global const T##16 *)(p))
#define STORE16(x, p) (*(__global float16 *)(p) = (x))
#define APPLY_ROW(s) r.s = rows[(size_t)ik.s * (size_t)n_cols + (size_t)col];
// The 16 lanes of one padded column: sum over the APPLY_K slots (index and weight lane-inner at
// `slot`) of weight * rows[index, col], zero weights selected out. Inlined (a call would stop
// PoCL's vectoriser), shared by the per-lane kernel and the 8-columns kernel's edge blocks.
inline __attribute__((always_inline)) float16 lanes_of_column(__global const float *rows,
                                                               __global const int *index,
                                                               __global const float *weight,
                                                               const size_t slot, const int col,
                                                               const int n_cols)
{
    float16 acc = (float16)(0.0f);
#pragma unroll
    for (int k = 0; k < APPLY_K; ++k) {
        const float16 wk = LOAD16(float, weight + slot + k * 16);
        const int16 ik = LOAD16(int, index + slot + k * 16);
        float16 r;
        APPLY_ROW(s0) APPLY_ROW(s1) APPLY_ROW(s2) APPLY_ROW(s3) APPLY_ROW(s4) APPLY_ROW(s5) APPLY_ROW(s6) APPLY_ROW(s7)
        APPLY_ROW(s8) APPLY_ROW(s9) APPLY_ROW(sa) APPLY_ROW(sb) APPLY_ROW(sc) APPLY_ROW(sd) APPLY_ROW(se) APPLY_ROW(sf)
        acc = wk != 0.0f ? acc + wk * r : acc;
    }
    return acc;
}
#undef APPLY_ROW
