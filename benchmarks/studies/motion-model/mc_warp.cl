// A volume given in the motion model's reference frame, seen at other states: out(x) = vol(x_r)
// with x_r + u(x_r; s) = x (the point of the reference that is at x at state s). x_r by NINV
// fixed-point steps x_r <- x - u(x_r) from x_r = x, as mc_backproject.cl; u trilinear on the
// model grid (motion_grid.h), vol trilinear on its own z planes (vz planes from vol_z0, spacing
// 1 / inv_vol_dz; the same in-plane grid): a model image needs finer z than the motion.
// docs/motion-model.md "The method" (step 6) (a study's kernel, outside the wheel: built from
// this folder by warp.py, with the package's kernels/motion_grid.h). The NumPy float64 reference
// is warp.py's warp_reference.
//
// Work-item (ix, iy, q), q = b S + s: pixel (ix, iy) of output slice s (z = out_z[s]) of state b.
//   vol (vz, ny, nx)   fields (B, 3, mz, ny, nx): u(.; s_b)   out_z (S,)   out (B, S, ny, nx)
// Compile-time: LX, LY (local size), NINV (inversion steps). One owner per output.
#include "motion_grid.h"

__kernel __attribute__((reqd_work_group_size(LX, LY, 1)))
void warp_volume(__global const float *restrict vol,
                 __global const float *restrict fields,
                 __global const float *restrict out_z,
                 __global float *restrict out,
                 const int nx, const int ny, const int mz, const float voxel_mm,
                 const float model_z0, const float inv_model_dz, const int n_out, const int n_states,
                 const int vz, const float vol_z0, const float inv_vol_dz)
{
    const int ix = get_global_id(0), iy = get_global_id(1), q = get_global_id(2);
    if (ix >= nx || iy >= ny || q >= n_out * n_states)
        return;
    const int b = q / n_out, s = q - b * n_out;
    const float inv_voxel = 1.0f / voxel_mm;
    const float x = ((float)ix - 0.5f * (float)(nx - 1)) * voxel_mm;
    const float y = ((float)iy - 0.5f * (float)(ny - 1)) * voxel_mm;
    const float z = out_z[s];
    const size_t fstride = (size_t)mz * ny * nx;
    __global const float *u = fields + (size_t)b * 3 * fstride;
    float rx = x, ry = y, rz = z;
    for (int it = 0; it < NINV; ++it) {
        GRID_CORNERS(rx, ry, rz)
        const float ux = TRILINEAR(u);
        const float uy = TRILINEAR(u + fstride);
        const float uz = TRILINEAR(u + 2 * fstride);
        rx = x - ux;
        ry = y - uy;
        rz = z - uz;
    }
    {   // the volume's own z planes: the grid macros read mz, model_z0, inv_model_dz
        const int mz = vz;
        const float model_z0 = vol_z0, inv_model_dz = inv_vol_dz;
        GRID_CORNERS(rx, ry, rz)
        out[((size_t)q * ny + iy) * nx + ix] = TRILINEAR(vol);
    }
}
