// The driver probe (clrecon/core/drivers.py): one small kernel that uses what the real kernels
// lean on -- 16-float vectors read and written through float16 pointers (as interp.cl does; not
// vload16/vstore16, which PoCL 3.0 aborts on when compiling for AVX-512: docs/kernels.md
// "Kernel builds"), and the math builtins at full precision. A CPU driver that cannot build or run
// this correctly is not offered (PoCL 3.0 on a CPU its LLVM 14 does not know fails here with
// "unknown target CPU 'generic'").
//
// out[i] = sqrt(x) + exp(-x) + log(1 + x) + atan2(x, 1 + x) for x = a[i] >= 0, 16 lanes at a time.
// Reference: clrecon.core.driver_probe.probe_reference (float64).

#ifdef CLRECON_PROBE_FORCE_FAIL
#error "forced failure (CLRECON_PROBE_FAIL names this platform)"
#endif

__kernel void probe(__global const float16 *a, __global float16 *out, const int n16)
{
    const int i = get_global_id(0);
    if (i >= n16)
        return;
    const float16 x = a[i];
    out[i] = sqrt(x) + exp(-x) + log(1.0f + x) + atan2(x, 1.0f + x);
}
