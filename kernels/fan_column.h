// fan_column(x, y, cs, scale, centre, &w): the fractional detector column of the in-plane point
// (x, y) mm in the view whose table entry is cs = (cos b, sin b) / R, and its backprojection
// weight w -- (R/U)^2 on a flat detector, R^2/L^2 on a cylindrical one (CURVED = 1, with
// ATAN_TERMS and the coefficients of atan_poly.h defined). Shared by backproject.cl (the
// fan-beam FBP) and mc_backproject.cl (its motion-compensated form, which calls it at the
// point's moved position). Formulas and PoCL notes: fan_beam.h's header.
#ifndef CLRECON_FAN_COLUMN_H
#define CLRECON_FAN_COLUMN_H
#ifndef CURVED
#define CURVED 0
#endif
#if CURVED
// Pixel (x, y) in the view with table entry cs = (cos b, sin b) / R: returns the fractional
// column c = atan(V / U) / dgamma + centre and puts the weight R^2 / L^2 in *w.
#ifndef ATAN_TERMS
#define ATAN_TERMS 9
#endif
#include "atan_poly.h"
inline float fan_column(const float x, const float y, const float2 cs, const float inv_dgamma,
                        const float centre, float *w)
{
    const float ur = 1.0f - (x * cs.x + y * cs.y);                 // U / R
    const float vr = y * cs.x - x * cs.y;                          // V / R
    const float l2 = ur * ur + vr * vr;                            // L^2 / R^2
    const float d = 1.0f / (ur * l2);                              // one division for both:
    *w = d * ur;                                                   // R^2 / L^2
    const float t = vr * (d * l2);                                 // V / U = tan gamma
    return atan_poly(t) + centre;  // the coefficients carry 1 / dgamma
}
#else
// Pixel (x, y) in the view with table entry cs = (cos b, sin b) / R: returns the
// fractional column index c = u / col_pitch + centre and puts the distance weight
// (R/U)^2 in *w.
inline float fan_column(const float x, const float y, const float2 cs, const float sdd_over_pitch,
                        const float centre, float *w)
{
    const float r_over_u = 1.0f / (1.0f - (x * cs.x + y * cs.y));  // R / U
    *w = r_over_u * r_over_u;
    return sdd_over_pitch * (y * cs.x - x * cs.y) * r_over_u + centre;
}
#endif
#endif
