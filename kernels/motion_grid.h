// Trilinear sampling of motion-model fields on their grid: the reconstruction's in-plane voxel
// centres (nx, ny, voxel_mm; inv_voxel = 1 / voxel_mm) and mz uniform z planes (model_z0,
// inv_model_dz), indices clamped to the grid (the field extends by its edge values), as
// clrecon.reconstruction.motion.model.sample. Shared by mc_backproject.cl and mc_warp.cl; the
// macros read the kernel's variables of those names. A kernel that holds only planes
// GRID_Z_FIRST .. of the mz (a window of a larger model: the coordinates and the clamp stay the
// whole model's) defines GRID_Z_FIRST before including this header (default 0: every plane).
#ifndef CLRECON_MOTION_GRID_H
#define CLRECON_MOTION_GRID_H
#ifndef GRID_Z_FIRST
#define GRID_Z_FIRST 0
#endif
// Trilinear corner offsets and weights of point (px, py, pz) on the model grid (clamped).
#define GRID_CORNERS(px, py, pz)                                                              \
    float fx = (px) * inv_voxel + 0.5f * (float)(nx - 1);                                     \
    float fy = (py) * inv_voxel + 0.5f * (float)(ny - 1);                                     \
    float fz = ((pz) - model_z0) * inv_model_dz;                                              \
    fx = fx < 0.0f ? 0.0f : (fx > (float)(nx - 1) ? (float)(nx - 1) : fx);                    \
    fy = fy < 0.0f ? 0.0f : (fy > (float)(ny - 1) ? (float)(ny - 1) : fy);                    \
    fz = fz < 0.0f ? 0.0f : (fz > (float)(mz - 1) ? (float)(mz - 1) : fz);                    \
    int ix0 = (int)fx, iy0 = (int)fy, iz0 = (int)fz;                                          \
    ix0 = ix0 > nx - 2 ? nx - 2 : ix0;                                                        \
    iy0 = iy0 > ny - 2 ? ny - 2 : iy0;                                                        \
    iz0 = iz0 > mz - 2 ? mz - 2 : iz0;                                                        \
    const float tx = fx - (float)ix0, ty = fy - (float)iy0, tz = fz - (float)iz0;             \
    const size_t o000 = ((size_t)(iz0 - GRID_Z_FIRST) * ny + iy0) * nx + ix0;                   \
    const size_t sy = (size_t)nx, sz = (size_t)nx * ny;

#define TRILINEAR(f)                                                                          \
    ((1.0f - tz) * ((1.0f - ty) * ((1.0f - tx) * (f)[o000] + tx * (f)[o000 + 1])              \
                    + ty * ((1.0f - tx) * (f)[o000 + sy] + tx * (f)[o000 + sy + 1]))          \
     + tz * ((1.0f - ty) * ((1.0f - tx) * (f)[o000 + sz] + tx * (f)[o000 + sz + 1])           \
             + ty * ((1.0f - tx) * (f)[o000 + sz + sy] + tx * (f)[o000 + sz + sy + 1])))
#endif
