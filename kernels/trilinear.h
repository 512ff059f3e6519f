// Trilinear sample of a float volume (x fastest; IDX(i, j, k) must be defined by the including
// kernel as its (nz, ny, nx) index) at fractional voxel index (fx, fy, fz), the index clamped to
// the grid: the volume extends by its edge values (scipy.ndimage.map_coordinates, order 1, mode
// 'nearest'), and an axis of one voxel is constant. Used by kernels/flow.cl and kernels/lk.cl; it
// compiles under the including file's FP_CONTRACT setting.

static float trilinear(__global const float *restrict vol, const int nx, const int ny, const int nz,
                       float fx, float fy, float fz)
{
    fx = clamp(fx, 0.0f, (float)(nx - 1));
    fy = clamp(fy, 0.0f, (float)(ny - 1));
    fz = clamp(fz, 0.0f, (float)(nz - 1));
    int i0 = (int)fx, j0 = (int)fy, k0 = (int)fz;
    i0 = min(i0, max(nx - 2, 0));
    j0 = min(j0, max(ny - 2, 0));
    k0 = min(k0, max(nz - 2, 0));
    const float tx = fx - (float)i0, ty = fy - (float)j0, tz = fz - (float)k0;
    const int i1 = min(i0 + 1, nx - 1), j1 = min(j0 + 1, ny - 1), k1 = min(k0 + 1, nz - 1);
    const float c00 = (1.0f - tx) * vol[IDX(i0, j0, k0)] + tx * vol[IDX(i1, j0, k0)];
    const float c10 = (1.0f - tx) * vol[IDX(i0, j1, k0)] + tx * vol[IDX(i1, j1, k0)];
    const float c01 = (1.0f - tx) * vol[IDX(i0, j0, k1)] + tx * vol[IDX(i1, j0, k1)];
    const float c11 = (1.0f - tx) * vol[IDX(i0, j1, k1)] + tx * vol[IDX(i1, j1, k1)];
    return (1.0f - tz) * ((1.0f - ty) * c00 + ty * c10) + tz * ((1.0f - ty) * c01 + ty * c11);
}
