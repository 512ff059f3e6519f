// Vector forms, one lane per voxel, of what kernels/mc_backproject.cl computes per voxel: the
// fan-beam column (kernels/fan_column.h's formulas, operation for operation), the curved
// detector's atan polynomial (kernels/atan_poly.h's), and the motion model's trilinear samples
// (kernels/motion_grid.h's, with the clamps written so that a NaN coordinate clamps to 0 instead
// of reaching an index). LANES (8 or 16, a build option) voxels per vector: floatL, intL. Only
// mc_backproject.cl includes this header.
//
// PoCL notes (kernels/fan_beam.h): no OpenCL builtins here (PoCL calls some of them out of line
// and spills the accumulators) and no function with a vector argument (a 16-float argument
// changes the ABI on a CPU without AVX-512, and PoCL's cache then loses the program): macros;
// vector selects are the `?:` operator, conversions clang's __builtin_convertvector; gathers
// are element-wise loads.
#ifndef CLRECON_MC_LANES_H
#define CLRECON_MC_LANES_H
#ifndef CURVED
#define CURVED 0
#endif
#ifndef LANES
#define LANES 8
#endif

#if LANES == 16
#define floatL float16
#define intL int16
#define LANE_IOTA_I (int16)(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15)
#define LANE_IOTA_F                                                                           \
    (float16)(0.0f, 1.0f, 2.0f, 3.0f, 4.0f, 5.0f, 6.0f, 7.0f, 8.0f, 9.0f, 10.0f, 11.0f, 12.0f, 13.0f, 14.0f, 15.0f)
// p[o.s0], .., p[o.sf]: one load per lane at the int offsets o from pointer p
#define GATHER_L(p, o)                                                                        \
    ((float16)((p)[(o).s0], (p)[(o).s1], (p)[(o).s2], (p)[(o).s3],                            \
               (p)[(o).s4], (p)[(o).s5], (p)[(o).s6], (p)[(o).s7],                            \
               (p)[(o).s8], (p)[(o).s9], (p)[(o).sa], (p)[(o).sb],                            \
               (p)[(o).sc], (p)[(o).sd], (p)[(o).se], (p)[(o).sf]))
// f(lane number, component) for every lane
#define FOR_LANES(f, v)                                                                       \
    f(0, (v).s0) f(1, (v).s1) f(2, (v).s2) f(3, (v).s3) f(4, (v).s4) f(5, (v).s5) f(6, (v).s6) \
    f(7, (v).s7) f(8, (v).s8) f(9, (v).s9) f(10, (v).sa) f(11, (v).sb) f(12, (v).sc)          \
    f(13, (v).sd) f(14, (v).se) f(15, (v).sf)
#elif LANES == 8
#define floatL float8
#define intL int8
#define LANE_IOTA_I (int8)(0, 1, 2, 3, 4, 5, 6, 7)
#define LANE_IOTA_F (float8)(0.0f, 1.0f, 2.0f, 3.0f, 4.0f, 5.0f, 6.0f, 7.0f)
#define GATHER_L(p, o)                                                                        \
    ((float8)((p)[(o).s0], (p)[(o).s1], (p)[(o).s2], (p)[(o).s3],                             \
              (p)[(o).s4], (p)[(o).s5], (p)[(o).s6], (p)[(o).s7]))
#define FOR_LANES(f, v)                                                                       \
    f(0, (v).s0) f(1, (v).s1) f(2, (v).s2) f(3, (v).s3) f(4, (v).s4) f(5, (v).s5) f(6, (v).s6) \
    f(7, (v).s7)
#else
#error "LANES must be 8 or 16"
#endif

#define TO_INT_L(v) __builtin_convertvector((v), intL)
#define TO_FLOAT_L(v) __builtin_convertvector((v), floatL)
// v clamped to [0, hi] (hi scalar); NaN -> 0
#define CLAMP0_L(v, hi) ((v) > 0.0f ? ((v) < (hi) ? (v) : (hi)) : 0.0f)

#if CURVED
#ifndef ATAN_TERMS
#define ATAN_TERMS 9
#endif
// atan_poly.h's Horner steps from its top coefficient; a coefficient past ATAN_TERMS is a step
// from p = 0 to p = 0 (0 * t2 + 0), so every lane's value is atan_poly's
#if ATAN_TERMS < 9
#define ATAN_C8 0.0f
#endif
#if ATAN_TERMS < 8
#define ATAN_C7 0.0f
#endif
#if ATAN_TERMS < 7
#define ATAN_C6 0.0f
#endif
#if ATAN_TERMS < 6
#define ATAN_C5 0.0f
#endif
#if ATAN_TERMS < 5
#define ATAN_C4 0.0f
#endif
#if ATAN_TERMS < 4
#define ATAN_C3 0.0f
#endif
#if ATAN_TERMS < 3
#define ATAN_C2 0.0f
#endif
#if ATAN_TERMS < 2
#define ATAN_C1 0.0f
#endif
// c = atan(V / U) / dgamma + centre and w = R^2 / L^2 of the points (x, y) in the view cs
#define FAN_COLUMN_L(c, w, px, py, cs, inv_dgamma, centre)                                      \
    {                                                                                         \
        const floatL ur_ = 1.0f - ((px) * (cs).x + (py) * (cs).y);                              \
        const floatL vr_ = (py) * (cs).x - (px) * (cs).y;                                       \
        const floatL l2_ = ur_ * ur_ + vr_ * vr_;                                             \
        const floatL d_ = 1.0f / (ur_ * l2_);                                                 \
        w = d_ * ur_;                                                                         \
        const floatL t_ = vr_ * (d_ * l2_);                                                   \
        const floatL t2_ = t_ * t_;                                                           \
        floatL p_ = ATAN_C8;                                                                  \
        p_ = p_ * t2_ + ATAN_C7;                                                              \
        p_ = p_ * t2_ + ATAN_C6;                                                              \
        p_ = p_ * t2_ + ATAN_C5;                                                              \
        p_ = p_ * t2_ + ATAN_C4;                                                              \
        p_ = p_ * t2_ + ATAN_C3;                                                              \
        p_ = p_ * t2_ + ATAN_C2;                                                              \
        p_ = p_ * t2_ + ATAN_C1;                                                              \
        p_ = p_ * t2_ + ATAN_C0;                                                              \
        c = p_ * t_ + (centre);                                                               \
    }
#else
// c = u / col_pitch + centre and w = (R/U)^2 of the points (x, y) in the view cs
#define FAN_COLUMN_L(c, w, px, py, cs, scale, centre)                                  \
    {                                                                                         \
        const floatL r_over_u_ = 1.0f / (1.0f - ((px) * (cs).x + (py) * (cs).y));               \
        w = r_over_u_ * r_over_u_;                                                            \
        c = (scale) * ((py) * (cs).x - (px) * (cs).y) * r_over_u_ + (centre);          \
    }
#endif

// motion_grid.h's GRID_CORNERS for LANES points: int offsets o000 within one field component,
// and the weights tx, ty, tz. Reads the kernel's nx, ny, mz, inv_voxel, model_z0, inv_model_dz
// and mz_first (the first plane the fields hold: offsets count from it).
#define GRID_CORNERS_L(px, py, pz)                                                            \
    floatL fx = (px) * inv_voxel + 0.5f * (float)(nx - 1);                                    \
    floatL fy = (py) * inv_voxel + 0.5f * (float)(ny - 1);                                    \
    floatL fz = ((pz) - model_z0) * inv_model_dz;                                             \
    fx = CLAMP0_L(fx, (float)(nx - 1));                                                       \
    fy = CLAMP0_L(fy, (float)(ny - 1));                                                       \
    fz = CLAMP0_L(fz, (float)(mz - 1));                                                       \
    intL gx0 = TO_INT_L(fx), gy0 = TO_INT_L(fy), gz0 = TO_INT_L(fz);                          \
    gx0 = gx0 > nx - 2 ? nx - 2 : gx0;                                                        \
    gy0 = gy0 > ny - 2 ? ny - 2 : gy0;                                                        \
    gz0 = gz0 > mz - 2 ? mz - 2 : gz0;                                                        \
    const floatL tx = fx - TO_FLOAT_L(gx0), ty = fy - TO_FLOAT_L(gy0), tz = fz - TO_FLOAT_L(gz0); \
    const intL o000 = ((gz0 - mz_first) * ny + gy0) * nx + gx0;                               \
    const int sy = nx, sz = nx * ny;

#define TRILINEAR_L(f)                                                                        \
    ((1.0f - tz) * ((1.0f - ty) * ((1.0f - tx) * GATHER_L(f, o000) + tx * GATHER_L((f) + 1, o000)) \
                    + ty * ((1.0f - tx) * GATHER_L((f) + sy, o000) + tx * GATHER_L((f) + sy + 1, o000))) \
     + tz * ((1.0f - ty) * ((1.0f - tx) * GATHER_L((f) + sz, o000) + tx * GATHER_L((f) + sz + 1, o000)) \
             + ty * ((1.0f - tx) * GATHER_L((f) + sz + sy, o000)                              \
                     + tx * GATHER_L((f) + sz + sy + 1, o000))))
#endif
