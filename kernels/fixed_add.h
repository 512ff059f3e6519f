// Deterministic scatter: 64-bit fixed-point accumulation with OpenCL 1.1 32-bit atomics.
//
// A float contribution v is quantised to the integer rint(v * scale) (scale a power of two
// chosen by the host so that no voxel's sum can exceed 2^62 in magnitude), and added to a
// two's-complement 64-bit accumulator held as two uints (lo, hi): atomic_add on lo, then its
// carry and the high word on hi. Integer addition modulo 2^64 is associative and each carry is
// exact, so the final (hi, lo) is the exact sum of the quantised contributions whatever the
// order the work-items ran in: the scatter is bit-deterministic (unlike float atomics, whose
// sum depends on the order). The host converts (hi << 32 | lo) / scale to float.

inline void fixed_add(volatile __global uint *acc, const float v, const float scale)
{
    const long q = convert_long_rte(v * scale);   // v * scale: exact (scale is a power of two)
    if (q == 0)
        return;
    const ulong bits = as_ulong(q);
    const uint lo = (uint)bits;
    uint hi = (uint)(bits >> 32);
    if (lo != 0u) {
        const uint old = atomic_add(&acc[0], lo);
        if (old + lo < old)                        // the low word wrapped: carry into hi
            hi += 1u;
    }
    if (hi != 0u)
        atomic_add(&acc[1], hi);
}
