// Per-(view, object) record written by project_cull.cl (the culling pass) and read by project.cl (and mirrored by
// clrecon/simulation/projector.py): REC floats per record, field offsets below.
#ifndef CLRECON_RECORD_H
#define CLRECON_RECORD_H
#define REC 76
#define R_FLAGS 0
#define R_MU 1
#define R_RECT 2     /* (u_lo, u_hi, v_lo, v_hi) of the object's detector rectangle */
#define R_ULO 2
#define R_UHI 3
#define R_VLO 4
#define R_VHI 5
#define R_UC 6
#define R_VC 7
#define R_TC 8
#define R_DC 9
#define R_EU 12
#define R_EV 15
#define R_WU 18
#define R_WV 21
#define R_W0 24
#define R_BU 27
#define R_BV 28
#define R_B0 29
#define R_OX 30      /* o: local position of the central ray at tau = 0 (0 unless the  */
#define R_OY 31      /* object centre does not project onto the detector plane)          */
#define R_PLANE 32   /* 2 x (g0, gu, gv, hk) */
#define R_CUT 40     /* 2 x (o (3), dc (3), eu (3), ev (3)) */
#define CUT_STRIDE 12
#define R_OZ 64
#define R_CUT_RECT 68  /* 2 x (u_lo, u_hi, v_lo, v_hi) of the cut ellipsoids */
#endif
