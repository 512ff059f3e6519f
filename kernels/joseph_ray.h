// One ray of the Joseph cone-beam projector, shared by the projector (voxel_project.cl) and its
// matched adjoint (voxel_backproject.cl), so both walk exactly the same samples. The method, the
// ray and the view record are described in voxel_project.cl.
//
// joseph_ray: sets up the ray of cell (col, row) of view record vr (VIEW_REC floats: a = (s - o) / h,
// D = det - s, e_u, e_v) with detector coordinates (u, v) mm; returns 0 where the half-line misses
// the box [-1/2, n - 1/2] (or d = 0). joseph_sample: the sample at plane i of the dominant axis
// (i_lo <= i <= i_hi): its weight w (g_k units), the flat index p of its lower corner and the
// bilinear fractions fj, fl; the corner's neighbours are at p + dj, p + dl, p + dl + dj.
// r.mm converts a sum over samples from g_k units to mm.

#define VIEW_REC 12

typedef struct {
    int i_lo, i_hi, sj, sl, sk, dj, dl, j0max, l0max;
    float glo, ghi, rj, rl, cj, cl, gjmax, glmax, mm;
} JosephRay;

inline int joseph_ray(__global const float *vr, const float u, const float v, const int nx, const int ny,
                      const int nz, const float hx, const float hy, const float hz, JosephRay *r)
{
    const float3 D = (float3)(vr[3], vr[4], vr[5]);
    const float3 eu = (float3)(vr[6], vr[7], vr[8]);
    const float3 ev = (float3)(vr[9], vr[10], vr[11]);
    const float3 d = D + u * eu + v * ev;                       // mm per unit t
    const float len = length(d);
    float a[3] = {vr[0], vr[1], vr[2]};
    float b[3] = {d.x / hx, d.y / hy, d.z / hz};                 // voxels per unit t
    const int n[3] = {nx, ny, nz};
    const int stride[3] = {1, nx, nx * ny};

    // clip the half-line t >= 0 to the box
    float t0 = 0.0f, t1 = INFINITY;
    for (int k = 0; k < 3; ++k) {
        const float lo = -0.5f - a[k], hi = (float)n[k] - 0.5f - a[k];
        if (b[k] != 0.0f) {
            const float ta = lo / b[k], tb = hi / b[k];
            t0 = fmax(t0, fmin(ta, tb));
            t1 = fmin(t1, fmax(ta, tb));
        } else if (lo > 0.0f || hi < 0.0f) {                    // parallel to the slab, outside it
            t1 = -1.0f;
        }
    }
    const float ab0 = fabs(b[0]), ab1 = fabs(b[1]), ab2 = fabs(b[2]);
    if (!(t1 > t0) || !(len > 0.0f))                            // misses (or d = 0)
        return 0;
    const int k = (ab0 >= ab1 && ab0 >= ab2) ? 0 : (ab1 >= ab2 ? 1 : 2);
    const int j = k == 0 ? 1 : 0, l = k == 2 ? 1 : 2;            // the two in-plane axes
    const float ak = a[k], bk = b[k];
    // slab range along k (g from the clipped ends, kept inside the box against rounding)
    const float ga = ak + bk * t0, gb = ak + bk * t1;
    r->glo = clamp(fmin(ga, gb), -0.5f, (float)n[k] - 0.5f);
    r->ghi = clamp(fmax(ga, gb), -0.5f, (float)n[k] - 0.5f);
    r->i_lo = clamp((int)floor(r->glo + 0.5f), 0, n[k] - 1);
    r->i_hi = clamp((int)floor(r->ghi + 0.5f), 0, n[k] - 1);
    // in-plane coordinates at plane i: g_j = a_j + r_j (i - a_k), r_j = b_j / b_k (|r_j| <= 1)
    r->rj = b[j] / bk;
    r->rl = b[l] / bk;
    r->cj = a[j] - r->rj * ak;
    r->cl = a[l] - r->rl * ak;
    const int nj = n[j], nl = n[l];
    r->sj = stride[j];
    r->sl = stride[l];
    r->sk = stride[k];
    r->gjmax = (float)(nj - 1);
    r->glmax = (float)(nl - 1);
    r->j0max = max(nj - 2, 0);
    r->l0max = max(nl - 2, 0);
    r->dj = nj > 1 ? r->sj : 0;
    r->dl = nl > 1 ? r->sl : 0;
    r->mm = len / fabs(bk);                                     // g_k units -> mm
    return 1;
}

inline float joseph_sample(const JosephRay *r, const int i, size_t *p, float *fj, float *fl)
{
    const float w = fmin((float)i + 0.5f, r->ghi) - fmax((float)i - 0.5f, r->glo);   // in units of g_k
    const float gj = clamp(r->cj + r->rj * (float)i, 0.0f, r->gjmax);
    const float gl = clamp(r->cl + r->rl * (float)i, 0.0f, r->glmax);
    const int j0 = min((int)gj, r->j0max), l0 = min((int)gl, r->l0max);
    *fj = gj - (float)j0;
    *fl = gl - (float)l0;
    *p = (size_t)i * r->sk + (size_t)j0 * r->sj + (size_t)l0 * r->sl;
    return w;
}
