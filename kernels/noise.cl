// CT noise on line integrals (clrecon/simulation/noise.py, which holds the float64 NumPy reference of
// exactly this generator): N = Poisson(I0 exp(-p)) + Normal(0, sigma_e), p' = -log(max(N, floor) / I0).
//
// Random numbers: Philox4x64-10 (Salmon, Moraes, Dror & Shaw, "Parallel random numbers: as
// easy as 1, 2, 3", SC 2011), counter-based: block (cell, round, 0, 0) under the key
// (seed, projection index) gives four 64-bit words. Every cell of every projection therefore
// owns its stream, and the noise is the same whatever the chunking, order or device.
// Round 0: words 0, 1 -> the electronic noise (Box-Muller); words 2, 3 -> the first Poisson
// attempt. Rounds 1, 2, ...: two more Poisson attempts each (words 0, 1 and 2, 3).
//
// Poisson sampler: lam < 10 by inversion (one uniform); lam >= 10 by Hoermann's transformed
// rejection PTRS (Insurance: Mathematics and Economics 12, 1993), the algorithm NumPy uses,
// with NumPy's log-gamma series, so the float64 reference can follow it step for step.
// After MAX_ROUNDS rounds without acceptance (probability < 1e-100) the mean is returned.
//
// Two passes, so that PoCL can vectorise the common case (docs/kernels.md, "Making kernels fast on
// PoCL"): add_noise does round 0 straight-line -- no loops, no early returns, and clang's
// __builtin_ math (LLVM intrinsics, inlined; PoCL's OpenCL builtins such as sqrt, floor or
// mul_hi are calls that stop the vectoriser) -- and resolves every cell that the fast test
// of the first PTRS attempt accepts (~86 % for means >= 10); it flags the others (mean below
// 10, or not accepted by that test), which add_noise_rest redoes with the whole algorithm
// (loops, scalar). Measured on PoCL: the flagged fifth costs pass 2 as much as pass 1 costs for
// all cells; a vectorised pass over a list of them (the whole first attempt) did not pay off there.
// Intel's CPU runtime is the other way round (it vectorises pass 2 too, whole vectors wherever one
// lane is flagged): there the host takes add_noise_listed / add_noise_list, which list the flagged
// cells (docs/results/noise-interp-intel.md). All passes follow the same steps, so a cell's value
// does not depend on which pass finished it.
//
// Needs cl_khr_fp64 (the host falls back to the NumPy reference without it). Built without
// -cl-fast-relaxed-math: the reference must be reproducible.

#pragma OPENCL EXTENSION cl_khr_fp64 : enable
// no a*b+c -> fma contraction: the NumPy reference rounds every operation separately
#pragma OPENCL FP_CONTRACT OFF

#define PHILOX_M0 0xD2E7470EE14C6C93UL
#define PHILOX_M1 0xCA5A826395121157UL
#define PHILOX_W0 0x9E3779B97F4A7C15UL
#define PHILOX_W1 0xBB67AE8584CAA73BUL

#define PTRS_MIN_LAM 10.0
#define INVERSION_MAX_K 200.0
#define MAX_ROUNDS 64
#define TWO_PI 6.283185307179586

// helpers must be inlined for the work-item loop to vectorise (calls stop it)
#define INLINE inline __attribute__((always_inline))
// LLVM_MATH=1 (the host sets it on PoCL): clang's __builtin_ math, i.e. LLVM intrinsics that
// PoCL inlines; other implementations (Oclgrind: "undefined external function llvm.exp.f64")
// get the OpenCL builtins.
#if LLVM_MATH
#define SQRT __builtin_sqrt
#define EXP __builtin_exp
#define LOG __builtin_log
#define FABS __builtin_fabs
#define FLOOR __builtin_floor
#define FMAX __builtin_fmax
#else
#define SQRT sqrt
#define EXP exp
#define LOG log
#define FABS fabs
#define FLOOR floor
#define FMAX fmax
#endif

// [0, 1) and (0, 1] from the top 53 bits
INLINE double u01_co(const ulong x) { return (double)(x >> 11) * 0x1.0p-53; }
INLINE double u01_oc(const ulong x) { return (double)((x >> 11) + 1UL) * 0x1.0p-53; }

// high 64 bits of a * b, in plain arithmetic (mul_hi is a call on PoCL)
INLINE ulong mulhi64(const ulong a, const ulong b)
{
    const ulong a_lo = a & 0xFFFFFFFFUL, a_hi = a >> 32, b_lo = b & 0xFFFFFFFFUL, b_hi = b >> 32;
    const ulong p0 = a_lo * b_lo, p1 = a_hi * b_lo, p2 = a_lo * b_hi, p3 = a_hi * b_hi;
    const ulong mid = (p0 >> 32) + (p1 & 0xFFFFFFFFUL) + (p2 & 0xFFFFFFFFUL);
    return p3 + (p1 >> 32) + (p2 >> 32) + (mid >> 32);
}

typedef struct {
    ulong w0, w1, w2, w3;
} words;

// Philox4x64-10 block of counter (c0, c1, 0, 0) under key (k0, k1)
INLINE words philox4x64_10(const ulong c0_in, const ulong c1_in, ulong k0, ulong k1)
{
    ulong c0 = c0_in, c1 = c1_in, c2 = 0UL, c3 = 0UL;
#pragma unroll
    for (int i = 0; i < 10; ++i) {
        if (i > 0) {
            k0 += PHILOX_W0;
            k1 += PHILOX_W1;
        }
        const ulong hi0 = mulhi64(PHILOX_M0, c0), lo0 = PHILOX_M0 * c0;
        const ulong hi1 = mulhi64(PHILOX_M1, c2), lo1 = PHILOX_M1 * c2;
        c0 = hi1 ^ c1 ^ k0;
        c1 = lo1;
        c2 = hi0 ^ c3 ^ k1;
        c3 = lo0;
    }
    const words r = {c0, c1, c2, c3};
    return r;
}

// log Gamma(x) for x >= 1, NumPy's random_loggam (numpy/random/src/distributions/distributions.c);
// the shift loop runs n <= 6 times (n = 0 for x >= 7, i.e. for nearly every PTRS candidate of a
// mean >= 10; no log is computed then: a loop, not six selects, which cost Intel's
// runtime six unused logs per slow test -- same operations on the same values, so the same bits)
INLINE double loggam(const double x)
{
    const double n = x < 7.0 ? FLOOR(7.0 - x) : 0.0;
    double x0 = x + n;
    const double x2 = (1.0 / x0) * (1.0 / x0);
    double gl0 = -1.39243221690590e+00;
    gl0 = gl0 * x2 + 1.796443723688307e-01;
    gl0 = gl0 * x2 - 2.955065359477124e-02;
    gl0 = gl0 * x2 + 6.410256410256410e-03;
    gl0 = gl0 * x2 - 1.917526917526918e-03;
    gl0 = gl0 * x2 + 8.417508417508418e-04;
    gl0 = gl0 * x2 - 5.952380952380952e-04;
    gl0 = gl0 * x2 + 7.936507936507937e-04;
    gl0 = gl0 * x2 - 2.777777777777778e-03;
    gl0 = gl0 * x2 + 8.333333333333333e-02;
    double gl = gl0 / x0 + 0.5 * 1.8378770664093453e+00 + (x0 - 0.5) * LOG(x0) - x0;
    for (double kk = 1.0; kk <= n; kk += 1.0) {
        gl = gl - LOG(x0 - 1.0);
        x0 = x0 - 1.0;
    }
    return (x == 1.0 || x == 2.0) ? 0.0 : gl;
}

// cos(2 pi u) for u in [0, 1), by symmetry onto [0, pi/2] and the Taylor series to y^20
// (error < 1e-15): PoCL's cos is a scalar call per lane, 5x this polynomial's cost.
INLINE double cos2pi(const double u)
{
    const double t = FABS(u - 0.5);              // cos(2 pi u) = -cos(2 pi t)
    const double y = TWO_PI * (t <= 0.25 ? t : 0.5 - t);
    const double y2 = y * y;
    double c = 4.110317623312165e-19;
    c = c * y2 - 1.5619206968586225e-16;
    c = c * y2 + 4.779477332387385e-14;
    c = c * y2 - 1.1470745597729725e-11;
    c = c * y2 + 2.08767569878681e-09;
    c = c * y2 - 2.755731922398589e-07;
    c = c * y2 + 2.48015873015873e-05;
    c = c * y2 - 0.001388888888888889;
    c = c * y2 + 0.041666666666666664;
    c = c * y2 - 0.5;
    c = c * y2 + 1.0;
    return t <= 0.25 ? -c : c;
}

// PTRS constants of a mean lam >= 10
#define PTRS_CONSTANTS(lam)                                \
    const double slam = SQRT(lam), loglam = LOG(lam);      \
    const double b = 0.931 + 2.53 * slam;                  \
    const double a = -0.059 + 0.02483 * b;                 \
    const double invalpha = 1.1239 + 1.1328 / (b - 3.4);   \
    const double vr = 0.9277 - 3.6224 / (b - 2.0);

// One PTRS attempt with words (xu, xv): the sample, or -1 when rejected.
INLINE double ptrs_attempt(const ulong xu, const ulong xv, const double lam, const double slam, const double loglam,
                           const double b, const double a, const double invalpha, const double vr)
{
    const double U = u01_co(xu) - 0.5;
    const double V = u01_oc(xv);
    const double us = 0.5 - FABS(U);
    const double kk = FLOOR((2.0 * a / us + b) * U + lam + 0.43);  // inf/NaN when us == 0: never kept
    const bool fast = us >= 0.07 && V <= vr;
    const bool skip = us < 0.013 && V > us;
    const double ks = (!skip && kk >= 0.0) ? kk : 0.0;
    const bool slow = !fast && !skip && kk >= 0.0
                      && LOG(V) + LOG(invalpha) - LOG(a / (us * us) + b) <= -lam + ks * loglam - loggam(ks + 1.0);
    return (fast || slow) ? kk : -1.0;
}

// The whole sampler (any lam), round-0 words r0 given: as poisson_reference in clrecon/simulation/noise.py.
INLINE double poisson(const double lam, const words r0, const ulong k0, const ulong k1, const ulong cell)
{
    if (!(lam > 0.0))
        return 0.0;
    if (lam < PTRS_MIN_LAM) {
        const double u = u01_co(r0.w2);
        double k = 0.0, pk = EXP(-lam), cdf = pk;
        while (u > cdf && k < INVERSION_MAX_K) {
            k += 1.0;
            pk *= lam / k;
            cdf += pk;
        }
        return k;
    }
    PTRS_CONSTANTS(lam)
    double k = ptrs_attempt(r0.w2, r0.w3, lam, slam, loglam, b, a, invalpha, vr);
    if (k >= 0.0)
        return k;
    for (int round = 1; round < MAX_ROUNDS; ++round) {
        const words r = philox4x64_10(cell, (ulong)round, k0, k1);
        k = ptrs_attempt(r.w0, r.w1, lam, slam, loglam, b, a, invalpha, vr);
        if (k >= 0.0)
            return k;
        k = ptrs_attempt(r.w2, r.w3, lam, slam, loglam, b, a, invalpha, vr);
        if (k >= 0.0)
            return k;
    }
    return FLOOR(lam + 0.5);
}

INLINE float noisy_value(const double counts, const words r0, const double i0, const double sigma,
                         const double n_floor)
{
    const double e = SQRT(-2.0 * LOG(u01_oc(r0.w0))) * cos2pi(u01_co(r0.w1));
    const double c = sigma > 0.0 ? counts + sigma * e : counts;
    return (float)(-LOG(FMAX(c, n_floor) / i0));
}

// Round 0 of cell `cell` of projection j (at = its place in p and out): writes the cell's value, exact
// where the fast acceptance test of the first PTRS attempt accepts (ptrs_attempt's first branch, same
// expressions) or the mean is 0, and returns whether it did (false: the whole sampler must redo it).
INLINE bool first_round(__global const float *p, __global const long *proj_index, __global float *out,
                        const int cell, const int j, const size_t at, const long cell0, const ulong seed,
                        const double i0, const double sigma, const double n_floor)
{
    const words r0 = philox4x64_10((ulong)(cell0 + cell), 0UL, seed, (ulong)proj_index[j]);
    const double lam = i0 * EXP(-(double)p[at]);
    // lam_p keeps the unused lanes finite
    const double lam_p = lam >= PTRS_MIN_LAM ? lam : PTRS_MIN_LAM;
    const double slam = SQRT(lam_p);
    const double b = 0.931 + 2.53 * slam;
    const double a = -0.059 + 0.02483 * b;
    const double vr = 0.9277 - 3.6224 / (b - 2.0);
    const double U = u01_co(r0.w2) - 0.5;
    const double V = u01_oc(r0.w3);
    const double us = 0.5 - FABS(U);
    const double k = FLOOR((2.0 * a / us + b) * U + lam_p + 0.43);
    const bool zero = !(lam > 0.0);
    const bool done = zero || (lam >= PTRS_MIN_LAM && us >= 0.07 && V <= vr);
    out[at] = noisy_value(zero ? 0.0 : k, r0, i0, sigma, n_floor);  // overwritten by pass 2 if !done
    return done;
}

// The whole sampler for cell `cell` of projection j.
INLINE void whole_sampler(__global const float *p, __global const long *proj_index, __global float *out,
                          const int cell, const int j, const size_t at, const long cell0, const ulong seed,
                          const double i0, const double sigma, const double n_floor)
{
    const ulong k1 = (ulong)proj_index[j];
    const ulong c = (ulong)(cell0 + cell);
    const words r0 = philox4x64_10(c, 0UL, seed, k1);
    const double lam = i0 * EXP(-(double)p[at]);
    out[at] = noisy_value(poisson(lam, r0, seed, k1, c), r0, i0, sigma, n_floor);
}

// Pass 1, work-item (cell, j): cell of projection j (cells = rows * columns, row-major).
// Straight-line: writes the cells resolved by round 0 and flags the rest in `rest`.
__kernel void add_noise(__global const float *p,          // (m, cells) noise-free line integrals
                        __global const long *proj_index,  // (m,) projection numbers k
                        __global float *out,              // (m, cells)
                        __global uchar *rest,             // (m, cells) 1 = left to add_noise_rest
                        const int cells,
                        const long cell0,                 // detector cell of column 0 of the block
                        const ulong seed,
                        const double i0,
                        const double sigma,
                        const double n_floor)
{
    const int cell = get_global_id(0);
    const int j = get_global_id(1);
    // no bounds check: the host pads cells to a multiple of the local size (an early return
    // keeps PoCL from vectorising the work-item loop)
    const size_t at = (size_t)j * (size_t)cells + (size_t)cell;
    const bool done = first_round(p, proj_index, out, cell, j, at, cell0, seed, i0, sigma, n_floor);
    rest[at] = done ? 0 : 1;
}

// Pass 2: the flagged cells, with the whole sampler (loops; scalar).
__kernel void add_noise_rest(__global const float *p,
                             __global const long *proj_index,
                             __global float *out,
                             __global const uchar *rest,
                             const int cells,
                             const long cell0,
                             const ulong seed,
                             const double i0,
                             const double sigma,
                             const double n_floor)
{
    const int cell = get_global_id(0);
    const int j = get_global_id(1);
    if (cell >= cells)
        return;
    const size_t at = (size_t)j * (size_t)cells + (size_t)cell;
    if (!rest[at])
        return;
    whole_sampler(p, proj_index, out, cell, j, at, cell0, seed, i0, sigma, n_floor);
}

// The same two passes with the flagged cells listed (the host's choice on Intel's CPU runtime, whose
// vectoriser runs add_noise_rest's vectors whole wherever one lane of eight is flagged: 4-5x the
// time of pass 1 for a fifth of the cells). Pass 1 appends each flagged cell's place
// j * cells + cell to `list` (count[0] entries, in no fixed order: each cell's value depends on the
// cell alone, so the output does not depend on the order); pass 2 runs the whole sampler on the
// list, every lane a flagged cell. Same functions as add_noise / add_noise_rest: the same bits.
__kernel void add_noise_listed(__global const float *p,           // (m, cells)
                               __global const long *proj_index,   // (m,)
                               __global float *out,               // (m, cells)
                               __global uint *list,               // (m * cells,) flagged places
                               volatile __global uint *count,     // (1,) entries in list, 0 on entry
                               const int cells,
                               const long cell0,
                               const ulong seed,
                               const double i0,
                               const double sigma,
                               const double n_floor)
{
    const int cell = get_global_id(0);
    const int j = get_global_id(1);
    const size_t at = (size_t)j * (size_t)cells + (size_t)cell;  // host pads cells (no bounds check)
    if (!first_round(p, proj_index, out, cell, j, at, cell0, seed, i0, sigma, n_floor))
        list[atomic_inc(count)] = (uint)at;
}

__kernel void add_noise_list(__global const float *p,
                             __global const long *proj_index,
                             __global float *out,
                             __global const uint *list,  // (n_list,) from add_noise_listed
                             const int n_list,
                             const int cells,
                             const long cell0,
                             const ulong seed,
                             const double i0,
                             const double sigma,
                             const double n_floor)
{
    const int i = get_global_id(0);
    if (i >= n_list)
        return;
    const uint at = list[i];
    const int j = (int)(at / (uint)cells);
    const int cell = (int)(at - (uint)j * (uint)cells);
    whole_sampler(p, proj_index, out, cell, j, (size_t)at, cell0, seed, i0, sigma, n_floor);
}
