"""Truth-free quality: cross-validation of the phase-space interpolation in sinogram space.

No ground truth is needed, so this works on measured scans. For a sample of (slice, view)
groups, each candidate turn k is held out in turn; its rebinned row y_k is predicted at its
own (cardiac phase c_k, respiratory amplitude a_k) from the remaining candidates with a
method's own weights (:func:`clrecon.reconstruction.interpolation.weights.batch_weights`, the
very weight functions the reconstruction uses: nothing is reimplemented here), and the
prediction error ``e_k = y_k - sum_j w_j y_j`` is pooled per method/kernel, variant and region
(whole row; the detector channels whose in-plane rays cross the heart box
``recon.small_fov_mm``).

Held-out folds (``scheme``):

- ``"loto"``: leave one turn out (only candidate k is removed);
- ``"nndm"``: nearest-neighbour-distance matching (Mila et al., Methods Ecol. Evol. 13:1304,
  2022, simplified): with k every candidate closer to (c_k, a_k) than a radius r_k is removed
  too, r_k taken from the distribution of the real task's target-to-nearest-candidate
  distances (deterministic quantiles), so the held-out prediction is about as far from its
  data as the reconstruction's targets are;
- ``"nndm_c"``: the same in cardiac phase alone: every candidate within |dc| < r_k of c_k is
  removed, r_k from the targets' distances to their nearest candidate in c. A periodic beat
  puts a view's candidates on a few cardiac-phase lines (docs/algorithms.md "Candidate
  selection": 5 lines 0.2 apart on ``demo``) while the targets lie between them; ``loto`` and
  ``nndm`` then predict a row from its own line, ``nndm_c`` from the neighbouring lines, as
  the reconstruction must;
- ``"interior"``: the ``loto`` folds whose held-out point lies inside the remaining points, i.e.
  in a Delaunay triangle of them (periodic in c) whose vertices are all within 0.3 in c
  (barycentric's own triangle test, ``Weights.branch``). Removing one of ~9 turns often leaves
  the point outside the others, which a target is less often (docs/results/truth-free.md "Where it
  fails"); these folds test interpolation, as the targets mostly need.

How the per-group targets are made: ``batch_weights`` solves the same targets for every
group, while every held-out row has its own (c_k, a_k). Each fold is therefore its own group
whose candidates are shifted by (0.5 - c_k) (mod 1, cardiac phase is periodic) and
(0.5 - a_k), with the one target (0.5, 0.5). The methods depend only on differences to the
target (the Delaunay triangulation is translation invariant), so this is the method's
prediction at (c_k, a_k) up to rounding.

Noise floor: in the noisy variant ``E[e_k^2] = bias^2 + var(y_k) + sum_j w_j^2 var(y_j)``.
The held-out row's own variance var(y_k) is the same for every method and is not an error of
the method: it is subtracted (``floor_subtracted``), from the noise model
(:func:`rebinned_noise_variance`: Poisson + electronic, delta method, evaluated at the
measured line integrals: no truth used). The methods' noise amplification (the last term)
stays, as it stays in their images.

Units: line integrals times 1000 / mu_water, i.e. "HU mm" (a row error of 1000 HU mm is one
mm of water path).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace

import numpy as np

from clrecon.core.conventions import circular_difference, source_positions
from clrecon.core.detector import spot_shift_in_frame
from clrecon.evaluation import metrics
from clrecon.reconstruction import fbp as fbp_mod
from clrecon.reconstruction import rebin
from clrecon.reconstruction import reconstruct as rc_mod
from clrecon.reconstruction.interpolation import weights as interpolate
from clrecon.simulation import noise as noise_mod

SCHEMES = ("loto", "nndm", "nndm_c", "interior")
REGIONS = ("row", "heart")
#: Golden-ratio sequence for the NNDM radii quantiles (deterministic, low discrepancy).
_GOLDEN = 0.6180339887498949


@dataclass(frozen=True)
class Kernel:
    """One fixed method with its kernel knobs (the choices of ``cv_tuned``)."""

    method: str
    kappa: float | None = None
    sigma: float | None = None
    local_linear_points: str | None = None
    local_linear_count: int | None = None

    @property
    def label(self) -> str:
        knobs = [f"{k}={v}" for k, v in (("kappa", self.kappa), ("sigma", self.sigma),
                                          ("points", self.local_linear_points),
                                          ("count", self.local_linear_count)) if v is not None]
        return self.method + (f"({','.join(knobs)})" if knobs else "")

    def options(self, base: dict) -> dict:
        """``base`` batch_weights options with this kernel's knobs put in."""
        o = dict(base)
        for k in ("kappa", "sigma", "local_linear_points", "local_linear_count"):
            if getattr(self, k) is not None:
                o[k] = getattr(self, k)
        return o

    def to_dict(self) -> dict:
        return {"method": self.method, **{k: getattr(self, k) for k in
                                          ("kappa", "sigma", "local_linear_points", "local_linear_count")
                                          if getattr(self, k) is not None}}

    @classmethod
    def from_dict(cls, d: dict) -> Kernel:
        return cls(**d)


#: The fixed kernels ``cv_tuned`` chooses among (and the trust study's kernel knobs): the two
#: 5DCT methods of the paper, local linear at a narrower and a wider kernel and with the
#: five nearest points (the paper's Figure 2B caption), and the nearest candidate.
DEFAULT_KERNELS = (
    Kernel("barycentric"),
    Kernel("local_linear"),
    Kernel("local_linear", kappa=4.0, sigma=0.08),
    Kernel("local_linear", kappa=0.25, sigma=0.3),
    Kernel("local_linear", local_linear_points="nearest", local_linear_count=5),
    Kernel("nearest"),
)


@dataclass
class Folds:
    """Held-out folds in CSR form: fold f holds out flat candidate ``held[f]`` and predicts it
    from ``member[offsets[f]:offsets[f+1]]`` (flat candidate indices), shifted to the target
    (0.5, 0.5): ``c``, ``a``, ``dz`` of those members."""

    held: np.ndarray
    offsets: np.ndarray
    member: np.ndarray
    c: np.ndarray
    a: np.ndarray
    dz: np.ndarray
    group: np.ndarray  # (F,) group of each fold
    radius: np.ndarray  # (F,) exclusion radius used (0 for loto)


def target_nearest_distances(c, a, offsets, targets, use_cardiac=True, use_resp=True) -> np.ndarray:
    """Distance from every (group, target) to its nearest candidate in (c, a), flat (G * T,).

    Circular in c. The distribution the NNDM folds match.
    """
    c = np.asarray(c, float)
    a = np.asarray(a, float)
    off = np.asarray(offsets, np.int64)
    t = np.asarray(targets, float).reshape(-1, 2)
    out = np.full((off.size - 1, t.shape[0]), np.inf)
    g = np.repeat(np.arange(off.size - 1), np.diff(off))
    for ti, (tc, ta) in enumerate(t):
        dc = circular_difference(c, tc) if use_cardiac else np.zeros_like(c)
        da = (a - ta) if use_resp else np.zeros_like(a)
        d = np.sqrt(dc * dc + da * da)
        np.minimum.at(out[:, ti], g, d)
    return out[np.isfinite(out)]


def make_folds(c, a, offsets, dz=None, groups=None, scheme: str = "loto", nn_distances=None,
               use_cardiac: bool = True, use_resp: bool = True, min_members: int = 1) -> Folds:
    """Every held-out fold of the groups ``groups`` (default all) of the CSR candidate set.

    ``scheme``: ``"loto"``, ``"nndm"`` or ``"nndm_c"`` (need ``nn_distances``, the real task's
    target-to-nearest-candidate distances, :func:`target_nearest_distances`; for ``"nndm_c"``
    in cardiac phase alone). The held-out
    candidate is never among its fold's members (tests/evaluation/test_truth_free.py checks it). Folds
    with fewer than ``min_members`` members left are dropped.
    """
    if scheme not in SCHEMES or scheme == "interior":  # interior: interior_folds of the loto folds
        raise ValueError(f"scheme = {scheme!r}: must be one of loto, nndm, nndm_c (interior: interior_folds)")
    c = np.asarray(c, float) % 1.0
    a = np.asarray(a, float)
    off = np.asarray(offsets, np.int64)
    dz = np.zeros_like(c) if dz is None else np.asarray(dz, float)
    G = off.size - 1
    gsel = np.arange(G) if groups is None else np.asarray(groups, np.int64)
    cnt = np.diff(off)[gsel]
    gsel = gsel[cnt >= 2]
    cnt = np.diff(off)[gsel]
    # fold per candidate of the selected groups
    held = np.repeat(off[gsel], cnt) + (np.arange(cnt.sum()) - np.repeat(np.cumsum(cnt) - cnt, cnt))
    fgroup = np.repeat(gsel, cnt)
    F = held.size
    if scheme in ("nndm", "nndm_c"):
        nd = np.sort(np.asarray(nn_distances, float))
        if nd.size == 0:
            raise ValueError("nndm: nn_distances is empty")
        q = (np.arange(F) * _GOLDEN) % 1.0
        radius = nd[np.minimum((q * nd.size).astype(np.int64), nd.size - 1)]
    else:
        radius = np.zeros(F)
    n_f = cnt.repeat(cnt)  # members before exclusion (the whole group)
    owner = np.repeat(np.arange(F), n_f)
    start = np.repeat(off[fgroup], n_f)
    member = start + (np.arange(n_f.sum()) - np.repeat(np.cumsum(n_f) - n_f, n_f))
    k = held[owner]
    dcs = circular_difference(c[member], c[k]) if use_cardiac else np.zeros(member.size)
    das = (a[member] - a[k]) if use_resp else np.zeros(member.size)
    keep = member != k
    if scheme == "nndm":
        keep &= np.sqrt(dcs * dcs + das * das) >= radius[owner]
    elif scheme == "nndm_c":
        keep &= np.abs(dcs) >= radius[owner]
    member, owner, dcs, das = member[keep], owner[keep], dcs[keep], das[keep]
    nm = np.bincount(owner, minlength=F)
    ok = nm >= min_members
    if not np.all(ok):
        sel = ok[owner]
        member, owner, dcs, das = member[sel], owner[sel], dcs[sel], das[sel]
        remap = np.cumsum(ok) - 1
        owner = remap[owner]
        held, fgroup, radius, nm = held[ok], fgroup[ok], radius[ok], nm[ok]
    fo = np.zeros(held.size + 1, np.int64)
    np.cumsum(nm, out=fo[1:])
    return Folds(held=held, offsets=fo, member=member, c=(0.5 + dcs) % 1.0, a=0.5 + das, dz=dz[member],
                 group=fgroup, radius=radius)


def interior_folds(folds: Folds, options: dict) -> Folds:
    """The folds whose held-out point lies in a triangle of its members (barycentric's triangle
    branch at the shifted target (0.5, 0.5)), as a new :class:`Folds`."""
    if folds.held.size == 0:
        return folds
    w = interpolate.batch_weights("barycentric", folds.c, folds.a, folds.offsets, np.array([[0.5, 0.5]]),
                                  dz=folds.dz, allow_empty=True, **options)
    keep = w.branch[:, 0] == 0 if w.branch is not None else np.zeros(folds.held.size, bool)
    n = np.diff(folds.offsets)
    sel = np.repeat(keep, n)
    off = np.zeros(int(keep.sum()) + 1, np.int64)
    np.cumsum(n[keep], out=off[1:])
    return Folds(held=folds.held[keep], offsets=off, member=folds.member[sel], c=folds.c[sel], a=folds.a[sel],
                 dz=folds.dz[sel], group=folds.group[keep], radius=folds.radius[keep])


def fold_weights(folds: Folds, kernel: Kernel, options: dict):
    """The kernel's weights of every fold at its held-out point: ``(index (F, K) flat candidates,
    weight (F, K) float64)``. ``options``: batch_weights keywords (kernel knobs put in)."""
    o = kernel.options(options)
    if folds.held.size == 0:
        return np.zeros((0, 1), np.int64), np.zeros((0, 1))
    w = interpolate.batch_weights(kernel.method, folds.c, folds.a, folds.offsets, np.array([[0.5, 0.5]]),
                                  dz=folds.dz, allow_empty=True, **o)
    idx = folds.member[np.minimum(w.index[:, 0, :], max(folds.member.size - 1, 0))]
    return np.where(w.weight[:, 0, :] != 0, idx, 0), w.weight[:, 0, :]


@dataclass
class ErrorSums:
    """Pooled squared errors of one (kernel, region): sum of e^2, of the held-out floor, cells."""

    sq: float = 0.0
    floor: float = 0.0
    cells: int = 0
    per_slice: dict = field(default_factory=dict)

    def add(self, sq, floor, cells):
        self.sq += float(sq)
        self.floor += float(floor)
        self.cells += int(cells)

    def rms(self, subtract_floor: bool) -> float:
        if self.cells == 0:
            return float("nan")
        ms = (self.sq - (self.floor if subtract_floor else 0.0)) / self.cells
        return float(np.sqrt(max(ms, 0.0)))


def fold_errors(rows, folds: Folds, index, weight, masks=None, row_var=None, chunk: int = 4096, signed=None):
    """Sums of squared prediction errors of the folds: ``{region: (sum e^2, sum var(y_k), cells)}``.

    ``rows`` (n, C) rebinned rows of the flat candidates; ``index``/``weight`` (F, K) from
    :func:`fold_weights`; ``masks`` ``{region: (F, C) bool}`` or ``{region: callable(fold ids)
    -> (f, C) bool}`` (default: the whole row only); ``row_var`` (n, C) noise variance of each
    row, or None (no floor). The held-out row never enters its own prediction (its index is
    not a member of its fold). ``signed``: an (F, C) array that receives the signed errors
    e_k (0 for a fold without weights), for the image-fold error.
    """
    masks = masks or {"row": None}
    out = {r: [0.0, 0.0, 0] for r in masks}
    F = folds.held.size
    for f0 in range(0, F, chunk):
        f1 = min(F, f0 + chunk)
        y = rows[folds.held[f0:f1]].astype(np.float64)
        w = weight[f0:f1]
        pred = np.einsum("fk,fkc->fc", w, rows[index[f0:f1]].astype(np.float64))
        live = w.sum(axis=1) > 0
        e = np.where(live[:, None], y - pred, 0.0)
        if signed is not None:
            signed[f0:f1] = e
        e2 = e * e
        v = None if row_var is None else row_var[folds.held[f0:f1]].astype(np.float64)
        for r, m in masks.items():
            mm = np.ones_like(e2, bool) if m is None else (m(np.arange(f0, f1)) if callable(m) else m[f0:f1])
            mm = mm & live[:, None]
            out[r][0] += float(e2[mm].sum())
            out[r][1] += 0.0 if v is None else float(v[mm].sum())
            out[r][2] += int(mm.sum())
    return {r: tuple(x) for r, x in out.items()}


# ---------------------------------------------------------------------------------------
# scan side: rows, noise variance, heart channels
def rebinned_noise_variance(data, slot, dz, scanner, cfg, rt=None, first_row: int = 0, pair_shift=None) -> np.ndarray:
    """Noise variance (p, C) of SSRB rows of the projections ``data`` (m, R, C) under the noise model.

    Per detector cell (delta method of p = -ln(N / I0), N = Poisson(lambda) + Normal(0,
    sigma_e)): var(p) = (lambda + sigma_e^2) / lambda^2 with lambda = I0 exp(-p), evaluated at
    the data given (plug-in: the measured line integrals; no truth). SSRB is, per column, a
    2-tap interpolation between detector rows times a scale, so its variance is
    A A_v + B B_v with A = SSRB(even-row indicator), A_v = SSRB(indicator x var) and B, B_v
    the same for the odd rows (exact for 2 taps; the kernel itself is used). With a flying
    focal spot in phi the curved SSRB also interpolates between columns (4 taps): then an
    approximation (the column taps' squares are not separated).
    """
    p = np.asarray(data, np.float64)
    lam = float(cfg.i0_photons) * np.exp(-p)
    var = (lam + float(cfg.electronic_sigma) ** 2) / np.maximum(lam, 1e-30) ** 2
    rows_idx = first_row + np.arange(p.shape[1])
    even = (rows_idx % 2 == 0)[None, :, None]
    out = np.zeros((len(slot), p.shape[2]))
    for ind in (even, ~even):
        ones = np.broadcast_to(ind, p.shape).astype(np.float32)
        A = rebin.ssrb_rows(ones, slot, dz, scanner, rt=rt, first_row=first_row,
                            pair_shift=pair_shift).astype(np.float64)
        Av = rebin.ssrb_rows((ind * var).astype(np.float32), slot, dz, scanner, rt=rt, first_row=first_row,
                             pair_shift=pair_shift).astype(np.float64)
        out += A * Av
    return out


def read_rows(store, groups: rebin.CandidateGroups, flat, scanner, variants, noise_cfg, rt=None,
              chunk: int = 256, want_var: bool = True):
    """Rebinned rows of the flat candidates ``flat`` of ``groups``: ``{variant: (rows (n, C) float32,
    var (n, C) or None)}`` (the variance only for ``"noisy"``, :func:`rebinned_noise_variance`)."""
    flat = np.asarray(flat, np.int64)
    proj = groups.projection[flat]
    dz = groups.dz_mm[flat]
    order = np.argsort(proj, kind="stable")
    n, C = flat.size, scanner.n_cols
    out = {v: (np.empty((n, C), np.float32), np.zeros((n, C)) if (v == "noisy" and want_var) else None)
           for v in variants}
    for b0 in range(0, n, chunk):
        sel = order[b0:b0 + chunk]
        wanted, slot = np.unique(proj[sel], return_inverse=True)
        shift = None
        if getattr(store.table, "focal_shift", None) is not None:  # flying focal spot: SSRB from each spot
            shift = spot_shift_in_frame(store.table.focal_shift[proj[sel]], scanner.sid_mm)
        r_lo, r_hi = rebin.ssrb_row_range(dz[sel], scanner, shift)
        clean = store.read_indices(wanted, noisy=False, rows=(r_lo, r_hi))
        for v in variants:
            data = clean if v != "noisy" else noise_mod.add_noise(clean, wanted, noise_cfg, first_row=r_lo)
            rows, var = out[v]
            s32 = slot.astype(np.int32).ravel()
            rows[sel] = rebin.ssrb_rows(data, s32, dz[sel].astype(np.float32), scanner, rt=rt, first_row=r_lo,
                                        pair_shift=shift)
            if var is not None:
                var[sel] = rebinned_noise_variance(data, s32, dz[sel].astype(np.float32), scanner, noise_cfg,
                                                   rt=rt, first_row=r_lo, pair_shift=shift)
    return out


def heart_channels(angle_rad, scanner, box) -> np.ndarray:
    """(n, C) bool: channels whose in-plane ray from the source at gantry angle ``angle_rad``
    (n,) crosses the axial box ``box = (x0, x1, y0, y1)`` mm (LPS; ``recon.small_fov_mm``)."""
    det = scanner.detector_model
    b = np.asarray(angle_rad, float)
    src = source_positions(b, np.zeros_like(b), scanner.sid_mm)[:, :2]
    u_eq = det.ray_cells()[0]
    # flat-equivalent detector line at distance SDD from the source, along e_u = (-sin b, cos b)
    centre = src + (scanner.sdd_mm) * np.stack([-np.cos(b), -np.sin(b)], axis=-1)
    e_u = np.stack([-np.sin(b), np.cos(b)], axis=-1)
    end = centre[:, None, :] + u_eq[None, :, None] * e_u[:, None, :]
    d = end - src[:, None, :]
    x0, x1, y0, y1 = box
    with np.errstate(divide="ignore", invalid="ignore"):
        tx0, tx1 = (x0 - src[:, None, 0]) / d[..., 0], (x1 - src[:, None, 0]) / d[..., 0]
        ty0, ty1 = (y0 - src[:, None, 1]) / d[..., 1], (y1 - src[:, None, 1]) / d[..., 1]
    tmin = np.fmax(np.fmin(tx0, tx1), np.fmin(ty0, ty1))  # fmin/fmax ignore the NaN of 0/0
    tmax = np.fmin(np.fmax(tx0, tx1), np.fmax(ty0, ty1))
    return tmax >= np.maximum(tmin, 0.0)


# ---------------------------------------------------------------------------------------
@dataclass(frozen=True)
class TruthFreeConfig:
    """What to cross-validate: ``kernels``, ``schemes``, how many slices (evenly spread) and every
    how many views (``view_step``)."""

    kernels: tuple = DEFAULT_KERNELS
    schemes: tuple = SCHEMES
    max_slices: int = 4
    view_step: int = 4
    choose_by: tuple = ("nndm", "heart")  # the (scheme, region) cv_tuned minimises
    image_fold: bool = True  # also the image-fold error (FBP of each held-out fold's error sinogram)


def cross_validate(store, table, slices_z, recon_cfg, targets, variants, box, tf: TruthFreeConfig = TruthFreeConfig(),
                   rt=None, candidate_groups=None) -> dict:
    """Cross-validated row errors of every kernel, scheme, variant and region for one scan (pitch).

    ``store`` must hold every candidate projection of the sampled slices (the run asks the
    simulator for them, :func:`needed_projections`). ``recon_cfg``:
    :class:`clrecon.reconstruction.reconstruct.ReconstructionConfig`; ``targets``: its
    ``Targets`` (the NNDM radii come from their nearest-candidate distances). Returns the
    ``results.json["truth_free"][pitch]`` entry.
    """
    t0 = time.perf_counter()
    sc = recon_cfg.scanner
    zs = sample_slices(slices_z, tf.max_slices)
    groups = candidate_groups if candidate_groups is not None else rc_mod.candidate_groups_of(recon_cfg, table, zs)
    nv = groups.views_per_rotation
    gsel = np.flatnonzero((groups.group_view % max(tf.view_step, 1)) == 0)
    c = table.cardiac_phase[groups.row]
    a = table.resp_amplitude[groups.row]
    opts = rc_mod.weight_options(recon_cfg, targets)
    use_c, use_r = recon_cfg.use_cardiac, recon_cfg.use_resp
    nd = target_nearest_distances(c, a, groups.offsets, targets.pairs, use_c, use_r)
    nd_c = target_nearest_distances(c, a, groups.offsets, targets.pairs, use_c, False) if use_c else nd
    folds = {s: make_folds(c, a, groups.offsets, groups.dz_mm, gsel, s, nd_c if s == "nndm_c" else nd, use_c, use_r)
             for s in tf.schemes if (use_c or s != "nndm_c") and s != "interior"}
    if "interior" in tf.schemes:
        base = folds["loto"] if "loto" in folds else make_folds(c, a, groups.offsets, groups.dz_mm, gsel, "loto",
                                                                 None, use_c, use_r)
        folds["interior"] = interior_folds(base, opts)
    used = np.unique(np.concatenate([np.concatenate([f.held, f.member]) for f in folds.values()]))
    t_plan = time.perf_counter() - t0
    t1 = time.perf_counter()
    rows_by_v = read_rows(store, groups, used, sc, variants, recon_cfg.noise, rt=rt)
    t_read = time.perf_counter() - t1
    pos = np.full(groups.row.size, -1, np.int64)
    pos[used] = np.arange(used.size)
    # heart channels per view (one per group view)
    views = np.arange(nv)
    angle = table.angle_rad[groups.row]
    view_angle = np.zeros(nv)
    first = groups.offsets[:-1][groups.counts > 0]
    view_angle[groups.group_view[groups.counts > 0]] = angle[first]
    heart_v = heart_channels(view_angle[views], sc, box)
    img_masks = image_masks(recon_cfg, box)
    res = {"config": {"kernels": [k.label for k in tf.kernels], "schemes": list(tf.schemes),
                      "slices_z_mm": list(map(float, zs)), "view_step": tf.view_step,
                      "units": "HU mm (line integral x 1000 / mu_water)",
                      "nndm_median_radius": float(np.median(nd)) if nd.size else None,
                      "nndm_c_median_radius": float(np.median(nd_c)) if nd_c.size else None,
                      "floor_subtracted": "noisy variant: the held-out row's own noise variance (noise model, "
                                          "Poisson + electronic, delta method at the measured line integrals)"},
           "folds": {s: int(f.held.size) for s, f in folds.items()},
           "errors": {}}
    t1 = time.perf_counter()
    for v in variants:
        rows, var = rows_by_v[v]
        imf = None
        if tf.image_fold:
            def imf(f, e):
                return image_fold_errors(f, e, groups.offsets, nv, max(tf.view_step, 1), recon_cfg.fbp,
                                         recon_cfg.filter, img_masks, recon_cfg.mu_water_per_mm, rt=rt)
        res["errors"][v] = kernel_errors(folds, rows, var, tf.kernels, opts, pos=pos,
                                         masks_of=lambda f: {"row": None, "heart": heart_v[groups.group_view[f.group]]},
                                         scale=1000.0 / recon_cfg.mu_water_per_mm, image_fold=imf)
    t_e = time.perf_counter() - t1
    res["choice"] = {v: choose(res["errors"][v], tf) for v in variants}
    res["seconds"] = {"plan": round(t_plan, 3), "read_rebin": round(t_read, 3), "weights_errors": round(t_e, 3),
                      "total": round(time.perf_counter() - t0, 3)}
    return res


def kernel_errors(folds: dict, rows, row_var, kernels, options: dict, pos=None, masks_of=None,
                  scale: float = 1.0, image_fold=None) -> dict:
    """``{scheme: {kernel label: {region: {rms_hu_mm, rms_raw_hu_mm, cells}}}}`` of the folds ``folds``
    (``{scheme: Folds}``) on ``rows`` (n, C) with noise variance ``row_var`` (n, C) or None.

    ``pos`` maps the folds' flat candidate ids to rows of ``rows`` (default identity);
    ``masks_of(folds) -> {region: (F, C) bool or None}`` (default: the whole row); ``scale``
    multiplies the RMS (line integral -> HU mm). ``rms_hu_mm`` has the held-out row's own noise
    variance subtracted when ``row_var`` is given, ``rms_raw_hu_mm`` never. ``image_fold(folds,
    signed errors (F, C)) -> {region: {...}}``: entries added per kernel under ``"image"``.
    """
    out = {}
    for s, f in folds.items():
        masks = masks_of(f) if masks_of is not None else {"row": None}
        lf = f if pos is None else replace(f, held=pos[f.held])
        for k in kernels:
            idx, w = fold_weights(f, k, options)
            if pos is not None:
                idx = np.maximum(pos[idx], 0)
            signed = None if image_fold is None else np.zeros((f.held.size, rows.shape[1]), np.float32)
            sums = fold_errors(rows, lf, idx, w, masks, row_var, signed=signed)
            ent = out.setdefault(s, {}).setdefault(k.label, {})
            if image_fold is not None:
                ent["image"] = image_fold(f, signed)
            for r, (sq, fl, n) in sums.items():
                es = ErrorSums(sq, fl, n)
                ent[r] = {"rms_hu_mm": es.rms(row_var is not None) * scale, "rms_raw_hu_mm": es.rms(False) * scale,
                          "cells": n}
                if n == 0:  # results.json writes the NaNs as null with this reason (clrecon.core.jsonio)
                    ent[r]["null_because"] = f"no held-out detector cell of this scheme falls in the {r} region"
    return out


def image_fold_errors(folds: Folds, signed, offsets, views_per_rotation: int, view_step: int, geom, window: str,
                      masks: dict, mu_water: float, rt=None) -> dict:
    """Image-fold error: FBP of the held-out folds' error sinograms, RMS (HU) in image regions.

    Fold rank r of slice s is, at every sampled view, the r-th candidate turn (in z order) of
    that (slice, view); its signed row errors form one sinogram over the sampled views, and
    FBP (linear) turns it into the image error that fold alone would make. Only ranks present
    at every sampled view are used. ``masks`` ``{region: (ny, nx) bool}``; ``geom`` the scan's
    fan-beam geometry (its ``n_views`` is divided by ``view_step``, which must divide it).
    Returns ``{region: {"rms_hu": ..., "images": n}}``. Not floor-subtracted: in the noisy
    variant it includes the held-out rows' own noise image.
    """
    nvs = views_per_rotation // view_step

    def none(why: str) -> dict:  # results.json writes the NaN as null with this reason (clrecon.core.jsonio)
        return {r: {"rms_hu": float("nan"), "images": 0, "null_because": why} for r in masks}

    if views_per_rotation % view_step:
        return none(f"the view step {view_step} does not divide the {views_per_rotation} views per rotation")
    if folds.held.size == 0:
        return none("the folds hold out no row")
    g = folds.group
    sl = g // views_per_rotation
    vi = (g % views_per_rotation) // view_step
    rank = folds.held - offsets[g]
    R = int(rank.max()) + 1
    key = sl * R + rank
    S = int(sl.max()) + 1
    count = np.bincount(key, minlength=S * R)
    keep = np.flatnonzero(count == nvs)
    out = {r: [0.0, 0] for r in masks}
    if keep.size == 0:
        return none(f"no fold rank (candidate turn) is present at all {nvs} sampled views of a slice, so no fold "
                    f"sinogram is complete enough to reconstruct (a short scan or a high pitch)")
    pos = np.full(S * R, -1)
    pos[keep] = np.arange(keep.size)
    sino = np.zeros((keep.size, nvs, signed.shape[1]), np.float32)
    ok = pos[key] >= 0
    sino[pos[key][ok], vi[ok]] = signed[ok]
    sh = tuple(getattr(geom, "source_shifts", ()) or ())
    # a flying focal spot's cycle, as the sampled views see it (view i is scan view i * view_step)
    geo = replace(geom, n_views=nvs, **({"source_shifts": tuple(sh[(i * view_step) % len(sh)] for i in range(len(sh)))}
                                         if sh else {}))
    for b0 in range(0, keep.size, 64):
        img = fbp_mod.fbp(sino[b0:b0 + 64], geo, window, runtime=rt).astype(np.float64) * (1000.0 / mu_water)
        for r, m in masks.items():
            out[r][0] += float((img[:, m] ** 2).sum())
            out[r][1] += int(m.sum()) * img.shape[0]
    return {r: ({"rms_hu": float(np.sqrt(sq / n)), "images": int(keep.size)} if n else
                {"rms_hu": float("nan"), "images": int(keep.size), "null_because": f"the {r} region is empty"})
            for r, (sq, n) in out.items()}


def choose(errors: dict, tf: TruthFreeConfig = None, kernels=None, by=None) -> dict:
    """The kernel with the smallest CV error of (scheme, region) ``by`` (default ``tf.choose_by``) in
    ``errors`` (one variant's :func:`kernel_errors`)."""
    tf = tf or TruthFreeConfig()
    kernels = kernels or tf.kernels
    s, r = by or tf.choose_by
    if s not in errors:  # the configured scheme was not run: the first one that was
        s = next(iter(errors))
    errs = {k.label: errors[s][k.label][r]["rms_hu_mm"] for k in kernels}
    best = min(kernels, key=lambda k: np.nan_to_num(errs[k.label], nan=np.inf))
    return {"kernel": best.to_dict(), "label": best.label, "by": {"scheme": s, "region": r}, "rms_hu_mm": errs}


def image_masks(recon_cfg, box) -> dict:
    """``{"large": the reconstruction circle, "small": the heart box inside it}`` (ny, nx) bool,
    the fields of view of :func:`clrecon.evaluation.metrics.fov_masks`."""
    g = recon_cfg.fbp
    return metrics.fov_masks(metrics.MetricsConfig(nx=g.nx, ny=g.ny, voxel_mm=g.voxel_mm,
                                                   large_radius_mm=recon_cfg.object_radius_mm,
                                                   small_fov_mm=tuple(box)))


def sample_slices(slices_z, n: int) -> np.ndarray:
    """At most ``n`` slices of ``slices_z``, evenly spread (ends included)."""
    z = np.asarray(slices_z, float)
    if z.size <= n:
        return z
    return z[np.unique(np.round(np.linspace(0, z.size - 1, n)).astype(int))]


def needed_projections(recon_cfg, table, slices_z, tf: TruthFreeConfig = TruthFreeConfig()) -> np.ndarray:
    """Projection numbers every fold of :func:`cross_validate` reads (all candidates of the sampled
    slices' sampled views)."""
    groups = rc_mod.candidate_groups_of(recon_cfg, table, sample_slices(slices_z, tf.max_slices))
    gsel = (groups.group_view % max(tf.view_step, 1)) == 0
    g = np.repeat(np.arange(groups.n_groups), groups.counts)
    return np.unique(groups.projection[gsel[g]])
