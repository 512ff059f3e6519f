// float8 forms, one lane per voxel, of what kernels/mc_backproject.cl computes per voxel: the
// fan-beam column (kernels/fan_column.h's formulas, operation for operation), the curved
// detector's atan polynomial (kernels/atan_poly.h's), and the motion model's trilinear samples
// (kernels/motion_grid.h's, with the clamps written so that a NaN coordinate clamps to 0 instead
// of reaching an index). Only mc_backproject.cl includes this header.
//
// PoCL notes (kernels/fan_beam.h): no OpenCL builtins here (PoCL calls some of them out of line
// and spills the accumulators); vector selects are the `?:` operator, conversions clang's
// __builtin_convertvector; gathers are element-wise loads.
#ifndef CLRECON_MC_LANES8_H
#define CLRECON_MC_LANES8_H
#ifndef CURVED
#define CURVED 0
#endif

#define TO_INT8(v) __builtin_convertvector((v), int8)
#define TO_FLOAT8(v) __builtin_convertvector((v), float8)
// p[o.s0], .., p[o.s7]: 8 loads at the int offsets o from pointer p
#define GATHER8(p, o)                                                                         \
    ((float8)((p)[(o).s0], (p)[(o).s1], (p)[(o).s2], (p)[(o).s3],                             \
              (p)[(o).s4], (p)[(o).s5], (p)[(o).s6], (p)[(o).s7]))
// v clamped to [0, hi] (hi scalar); NaN -> 0
#define CLAMP0_8(v, hi) ((v) > 0.0f ? ((v) < (hi) ? (v) : (hi)) : 0.0f)

#if CURVED
#ifndef ATAN_TERMS
#define ATAN_TERMS 9
#endif
// atan_poly.h's polynomial, lane by lane
inline float8 atan_poly8(const float8 t)
{
    const float8 t2 = t * t;
    float8 p = (float8)(0.0f);
#if ATAN_TERMS > 8
    p = p * t2 + ATAN_C8;
#endif
#if ATAN_TERMS > 7
    p = p * t2 + ATAN_C7;
#endif
#if ATAN_TERMS > 6
    p = p * t2 + ATAN_C6;
#endif
#if ATAN_TERMS > 5
    p = p * t2 + ATAN_C5;
#endif
#if ATAN_TERMS > 4
    p = p * t2 + ATAN_C4;
#endif
#if ATAN_TERMS > 3
    p = p * t2 + ATAN_C3;
#endif
#if ATAN_TERMS > 2
    p = p * t2 + ATAN_C2;
#endif
#if ATAN_TERMS > 1
    p = p * t2 + ATAN_C1;
#endif
    p = p * t2 + ATAN_C0;
    return p * t;
}

// fan_column.h (CURVED): column atan(V / U) / dgamma + centre and weight R^2 / L^2
inline float8 fan_column8(const float8 x, const float8 y, const float2 cs, const float inv_dgamma,
                          const float centre, float8 *w)
{
    const float8 ur = 1.0f - (x * cs.x + y * cs.y);
    const float8 vr = y * cs.x - x * cs.y;
    const float8 l2 = ur * ur + vr * vr;
    const float8 d = 1.0f / (ur * l2);
    *w = d * ur;
    const float8 t = vr * (d * l2);
    return atan_poly8(t) + centre;
}
#else
// fan_column.h (flat): column u / col_pitch + centre and weight (R/U)^2
inline float8 fan_column8(const float8 x, const float8 y, const float2 cs, const float sdd_over_pitch,
                          const float centre, float8 *w)
{
    const float8 r_over_u = 1.0f / (1.0f - (x * cs.x + y * cs.y));
    *w = r_over_u * r_over_u;
    return sdd_over_pitch * (y * cs.x - x * cs.y) * r_over_u + centre;
}
#endif

// motion_grid.h's GRID_CORNERS for 8 points: int8 offsets o000 within one field component, and
// the weights tx, ty, tz (float8). Reads the kernel's nx, ny, mz, inv_voxel, model_z0, inv_model_dz.
#define GRID_CORNERS8(px, py, pz)                                                             \
    float8 fx = (px) * inv_voxel + 0.5f * (float)(nx - 1);                                    \
    float8 fy = (py) * inv_voxel + 0.5f * (float)(ny - 1);                                    \
    float8 fz = ((pz) - model_z0) * inv_model_dz;                                             \
    fx = CLAMP0_8(fx, (float)(nx - 1));                                                       \
    fy = CLAMP0_8(fy, (float)(ny - 1));                                                       \
    fz = CLAMP0_8(fz, (float)(mz - 1));                                                       \
    int8 gx0 = TO_INT8(fx), gy0 = TO_INT8(fy), gz0 = TO_INT8(fz);                             \
    gx0 = gx0 > nx - 2 ? nx - 2 : gx0;                                                        \
    gy0 = gy0 > ny - 2 ? ny - 2 : gy0;                                                        \
    gz0 = gz0 > mz - 2 ? mz - 2 : gz0;                                                        \
    const float8 tx = fx - TO_FLOAT8(gx0), ty = fy - TO_FLOAT8(gy0), tz = fz - TO_FLOAT8(gz0); \
    const int8 o000 = (gz0 * ny + gy0) * nx + gx0;                                            \
    const int sy = nx, sz = nx * ny;

#define TRILINEAR8(f)                                                                         \
    ((1.0f - tz) * ((1.0f - ty) * ((1.0f - tx) * GATHER8(f, o000) + tx * GATHER8((f) + 1, o000))  \
                    + ty * ((1.0f - tx) * GATHER8((f) + sy, o000) + tx * GATHER8((f) + sy + 1, o000))) \
     + tz * ((1.0f - ty) * ((1.0f - tx) * GATHER8((f) + sz, o000) + tx * GATHER8((f) + sz + 1, o000)) \
             + ty * ((1.0f - tx) * GATHER8((f) + sz + sy, o000)                               \
                     + tx * GATHER8((f) + sz + sy + 1, o000))))
#endif
