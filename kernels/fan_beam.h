// Distance-weighted fan-beam backprojection for a flat detector, full 2*pi scan.
// Kak & Slaney (1988), "Principles of Computerized Tomographic Imaging", sec. 3.4.2
// (equally spaced collinear detectors), in the conventions of clrecon/core/conventions.py:
//   source at (R cos b, R sin b), detector columns along e_u = (-sin b, cos b),
//   U = R - (x cos b + y sin b),  u = SDD (-x sin b + y cos b) / U,
//   column index  c = u / col_pitch + (n_cols - 1) / 2,
//   mu(x, y) = dbeta * sum_j (R / U_j)^2 * Q_j(c_j)        (Q: the filtered projection).
// Linear interpolation in c; c outside [0, n_cols - 1] (at most the half cell beyond the
// outer column centre, for pixels inside the FOV) takes the edge column's value. Pixels
// whose centre lies outside the scanner's FOV circle (fov_r2 = radius^2) are written as 0:
// not every view sees them, so their sum would be incomplete. The FOV circle is tangent to
// the outer column *edges*, so inside it |c - (n_cols-1)/2| <= n_cols/2 by construction.
//
// The per-view table `trig` holds (cos b / R, sin b / R): then R/U = 1 / (1 - x c' - y s')
// and c - c_centre = (SDD / col_pitch) (y c' - x s') (R/U), one reciprocal per view.
//
// Geometry comes in as kernel arguments, so one build serves every geometry; only the
// local size LX x LY and the view chunk VCHUNK are compile-time constants (-D): PoCL
// specialises its binaries per local size anyway (docs/kernels.md, "Making kernels fast on PoCL").
//
// PoCL notes (PoCL 3.0, LLVM target znver3 = AVX2 on this machine, so a float16 is two
// ymm registers):
// * builtins such as native_recip, clamp and min are *not inlined* here; a call in the
//   view loop spills the float16 accumulator to the stack on every view (measured 1.8x
//   slower). The loops below use plain arithmetic and ternaries only.
// * calling a builtin with a float16 argument (e.g. fma) makes clang warn about the
//   AVX-512 ABI, and a program built with that warning comes back from PoCL's on-disk
//   cache with no kernels in it (INVALID_KERNEL_NAME on the second run). Plain `a*b + c`
//   is contracted to FMAs under -cl-mad-enable instead.

// CURVED = 1: equiangular data of a cylindrical detector (Kak & Slaney sec. 3.4.1). The
// column of pixel (x, y) is c = gamma / dgamma + central_col with gamma = atan(V / U) (V =
// -x sin b + y cos b, the in-plane offset from the central ray), and the weight is R^2 / L^2,
// L^2 = U^2 + V^2 the squared distance from the source (the 1 / R^2 is in the filter's
// pre-weight, clrecon.reconstruction.fbp.cosine_weights). atan is an odd polynomial whose
// ATAN_TERMS coefficients the host fits for the geometry's largest |V / U| = tan(gamma_fov)
// (fewest terms with a float64 error <= 1e-7 rad; at most 9 = degree 17 on [0, 1]): plain
// arithmetic, as the PoCL notes below ask (FanBeamGeometry checks gamma_edge <= 45 degrees). `sdd_over_pitch` then carries
// 1 / dgamma, and `col_centre` the central column (0-based, without the pad column).
#ifndef CURVED
#define CURVED 0
#endif

#if CURVED
#define GEOMETRY_ARGS                                                                     \
    const int nx, const int ny,                                                            \
    const int n_views, const int n_cols,                                                   \
    const float voxel_mm,                                                                  \
    const float sdd_over_pitch,         /* 1 / dgamma, 1/rad */                            \
    const float fov_r2,                                                                    \
    const float dbeta,                                                                     \
    const float col_centre              /* central column, fractional, 0-based */
#define COL_CENTRE col_centre
#else
#define GEOMETRY_ARGS                                                                     \
    const int nx, const int ny,         /* image size, img[y, x] */                        \
    const int n_views, const int n_cols,                                                   \
    const float voxel_mm,               /* pixel size, mm */                               \
    const float sdd_over_pitch,         /* SDD / col_pitch */                              \
    const float fov_r2,                 /* squared FOV radius at the isocentre, mm^2 */    \
    const float dbeta                   /* 2 pi / n_views, rad */
#define COL_CENTRE (0.5f * (float)(n_cols - 1))
#endif

// fan_column(): the column and weight of a point in a view
#include "fan_column.h"
