// atan(t) / dgamma as the odd polynomial t (a0 + a1 t^2 + ... ): ATAN_TERMS (1..9) coefficients
// ATAN_C0.. passed as -D literals carrying 1 / dgamma, fitted on the host for the geometry's
// largest |tan gamma| (clrecon.core.detector.atan_defines). Shared by ssrb.cl (phi-FFS
// resampling) and backproject.cl (CURVED column lookup); included only where ATAN_TERMS is set.
#ifndef CLRECON_ATAN_POLY_H
#define CLRECON_ATAN_POLY_H
inline float atan_poly(const float t)
{
    const float t2 = t * t;
    float p = 0.0f;  // (0 t2 + the top coefficient folds away under -cl-fast-relaxed-math)
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
#endif
