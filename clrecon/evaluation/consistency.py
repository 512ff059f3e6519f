"""Data consistency of a 5D method's volumes with the measured rows: a truth-free check of ``mc``.

For sampled (slice, view) groups (the truth-free sampling: :func:`clrecon.evaluation.truth_free.sample_slices`,
every ``view_step``-th view, every SSRB candidate row of :class:`clrecon.reconstruction.rebin.CandidateGroups`),
each rebinned row y_k, recorded at state (c_k, a_k), is compared with what a method's volumes
predict for it: the in-plane projection P_k of the method's image at (c_k, a_k),

    e_k = y_k - P_k I(c_k, a_k),

I(c, a) the method's target images interpolated to (c, a) over the target lattice (bilinear,
periodic in c, the amplitude clipped to the lattice's range; :func:`lattice_weights`). Projection
is linear, so each target image is projected and the projections are interpolated. P_k has the
geometry of the ground truth's in-plane rows (:func:`inplane_frames`: flat or cylindrical
cells, a flying focal spot's source), by the voxel projector
(:func:`clrecon.simulation.voxel_projector.project_volume`, Joseph's method). No ground truth
is used: it runs on measured scans.

Units: line integrals times 1000 / mu_water, "HU mm" (1000 HU mm = 1 mm of water path), as
:mod:`clrecon.evaluation.truth_free`. Regions: ``all``, the channels whose ray passes through
the reconstruction circle (``recon.object_radius_mm``); ``heart``, the channels whose ray crosses
the heart box ``recon.small_fov_mm`` (:func:`clrecon.evaluation.truth_free.heart_channels`).

What it can say and its biases (docs/consistency.md "Did it help? A truth-free check"): the
rows were used to make the volumes (for ``mc``'s variant A with the same barycentric weights as
barycentric itself, so the leakage is comparable between the two); SSRB rows differ from ideal
in-plane rows by 0.5-0.8 % of the row norm and the FBP's filter window smooths every image, the
same for every method; noise adds var(y_k) to every method's mean square alike. A method is
compared with another slice by slice: at each sampled slice by the difference of their mean squared
residuals, with a jackknife over blocks of consecutive sampled views (:func:`compare`), and over the
slices by a sign test on the slices where it is lower against those where it is higher
(:func:`verdict`): each slice counts once, so a few slices whose residual is large (an error that
adds up along the rays) do not carry the verdict. The pooled comparison over every block is reported
beside it. It says whether the difference is consistent over the sampled geometry, not what another
noise draw would give.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
from scipy.stats import binomtest

from clrecon.core.conventions import detector_frames
from clrecon.evaluation import truth_free
from clrecon.reconstruction import interpolation
from clrecon.reconstruction import reconstruct as rc_mod
from clrecon.reconstruction.fbp import FanBeamGeometry
from clrecon.reconstruction.interpolation import weights as interpolate
from clrecon.reconstruction.iterative import method as mcir_method
from clrecon.simulation import projector as analytic_projector
from clrecon.simulation.voxel_projector import project_volume

REGIONS = ("all", "heart")
#: The method whose help the verdict judges.
METHOD = "mc"
#: The method every other is compared with: ``mc``'s first pass (the registry's ``Method.first_pass``).
REFERENCE = interpolation.first_pass(METHOD)
#: The iterative method and what it is judged against: ``mc``, the image it starts from by default
#: (``recon.mcir.init`` "auto"), so its verdict says whether the iterations added anything.
ITERATIVE, ITERATIVE_AGAINST = mcir_method.NAME, METHOD
#: |z| of the jackknife's difference above which a comparison says "helped" / "worse".
Z_DECIDES = 2.0
#: The smallest effect a comparison reports: an RMS ratio within this of 1 (|ratio - 1| <= 0.005,
#: 0.5 %) says "no clear difference" whatever z says. The jackknife's z measures how consistent a
#: difference is over the blocks, not how large: two methods that err alike (a static scene, where
#: ``mc`` equals barycentric up to rounding) have a standard error as small as their difference, and
#: without this a ratio of 1.000 was called significant (issue 41). 0.5 % is the size of the check's
#: own model error (SSRB rows differ from ideal in-plane rows by 0.5-0.8 % of the row norm, the same
#: for every method; module docstring), and several times below the effect the check exists to see
#: (``mc`` against barycentric where it helped on ``demo``: docs/results/mc-consistency.md).
MIN_EFFECT = 0.005
#: Two-sided significance of the sign test over slices (:func:`verdict`): a region says "lower" or
#: "higher" when so many more slices are lower than higher (or the reverse) that a fair coin would
#: give it at most this often. The same level as |z| > Z_DECIDES (0.046).
SIGN_TEST_ALPHA = 0.05
#: The fewest slices that must differ for the sign test to decide: all of them agreeing then has a
#: two-sided p of 2 x 0.5^n <= SIGN_TEST_ALPHA (6: 0.031; 5 of 5 give 0.0625).
MIN_DECIDING_SLICES = next(n for n in range(1, 64) if 2 * 0.5 ** n <= SIGN_TEST_ALPHA)
#: What ``results.json`` keeps of each method's verdict against the reference, per region, beside its residual.
AGAINST_KEYS = ("ratio", "z", "pooled_says", "says", "slices_lower", "slices_higher", "sign_test_p")
#: z spacing (mm) of stacked in-plane images projected at once: any value > 0 keeps in-plane rays in their plane.
STACK_DZ_MM = 10.0


def inplane_frames(detector, geom: FanBeamGeometry, view, z_mm):
    """Frames of in-plane rows (source in the row's plane) of the given views and plane z's, as the ground truth."""
    beta = geom.view_angles_rad()[view]
    (src, centre, eu, ev), (u, _, vs) = analytic_projector.spot_frames(detector, beta, z_mm, (0, 0, 0))
    if geom.source_shifts:
        b_s, r_s = geom.source_angles_radii()
        src, centre, eu, ev = detector_frames(b_s[view], z_mm, r_s[view], detector.sdd_mm)
    return (src, centre, eu, ev), u, vs


@dataclass(frozen=True)
class ConsistencyConfig:
    """Sampling of the check: at most ``max_slices`` slices (evenly spread: 12, so the sign test over
    slices can decide with one or two slices against: 10 of 12 give p = 0.039), every
    ``view_step``-th view, ``block_views`` sampled views per jackknife block. For studies (the run
    uses the defaults): ``max_dz_mm`` keeps only the rows within that axial distance of their slice;
    ``unused_only`` only the rows barycentric gave no weight at any target (:func:`unused_rows`; none
    at pitch 0.10 on ``demo``)."""

    max_slices: int = 12
    view_step: int = 4
    block_views: int = 8
    max_dz_mm: float | None = None
    unused_only: bool = False

    def truth_free_config(self) -> truth_free.TruthFreeConfig:
        return truth_free.TruthFreeConfig(max_slices=self.max_slices, view_step=self.view_step)


def lattice_weights(c, a, cardiac, resp):
    """Bilinear weights of states (c, a) over a target lattice: ``(index (p, 4) int64, weight (p, 4) float64)``.

    ``index`` is the flat target ``i * len(resp) + j`` (cardiac-major, as the volumes' first two
    axes). Cardiac phase is periodic: between the largest target phase and the smallest + 1 the
    weights wrap around. The amplitude is clipped to [min(resp), max(resp)]. An axis of one
    target takes weight 1 on it. Targets need not be evenly spaced; they must be distinct.
    """
    c = np.mod(np.asarray(c, np.float64), 1.0)
    a = np.asarray(a, np.float64)
    if c.shape != a.shape or c.ndim != 1:
        raise ValueError(f"c {c.shape} and a {a.shape}: expected two (p,) arrays")
    ci, cw = _axis_weights(c, np.asarray(cardiac, np.float64), periodic=True)
    ri, rw = _axis_weights(a, np.asarray(resp, np.float64), periodic=False)
    nr = len(resp)
    index = (ci[:, :, None] * nr + ri[:, None, :]).reshape(-1, 4)
    weight = (cw[:, :, None] * rw[:, None, :]).reshape(-1, 4)
    return index.astype(np.int64), weight


def _axis_weights(x, lattice, periodic: bool):
    """Linear weights of x (p,) between its two neighbours on ``lattice`` (n,): ((p, 2) int, (p, 2))."""
    n = lattice.size
    if n == 0 or np.unique(lattice).size != n:
        raise ValueError(f"target lattice {lattice.tolist()}: must be non-empty and distinct")
    p = x.size
    if n == 1:
        return np.zeros((p, 2), np.int64), np.column_stack([np.ones(p), np.zeros(p)])
    order = np.argsort(lattice)
    s = lattice[order]
    if periodic:
        s = np.mod(s, 1.0)
        order = order[np.argsort(s)]
        s = np.sort(s)
        ext = np.concatenate([s, [s[0] + 1.0]])
        xx = np.where(x < s[0], x + 1.0, x)
        k = np.clip(np.searchsorted(ext, xx, side="right") - 1, 0, n - 1)
        lo, hi = ext[k], ext[k + 1]
        t = (xx - lo) / (hi - lo)
        return np.column_stack([order[k], order[(k + 1) % n]]), np.column_stack([1.0 - t, t])
    xx = np.clip(x, s[0], s[-1])
    k = np.clip(np.searchsorted(s, xx, side="right") - 1, 0, n - 2)
    t = (xx - s[k]) / (s[k + 1] - s[k])
    return np.column_stack([order[k], order[k + 1]]), np.column_stack([1.0 - t, t])


def inplane_projections(images_mu, voxel_mm: float, detector, geom, image, view, rt=None) -> np.ndarray:
    """In-plane rows of images: row m is image ``image[m]`` projected at view ``view[m]``, (m, C) float32.

    ``images_mu`` (Q, ny, nx) attenuation (1/mm) on the reconstruction grid (voxel centres
    :func:`clrecon.core.conventions.voxel_coords`, ``[iy, ix]`` as the FBP writes them); ``geom``
    the reconstruction's :class:`clrecon.reconstruction.fbp.FanBeamGeometry`; ``detector`` the
    scanner's detector model. The images are stacked ``STACK_DZ_MM`` apart along z and each row's
    rays lie in its image's plane (as the motion-model study's correction step does,
    ``benchmarks/studies/motion-model/correction.py``).
    """
    imgs = np.ascontiguousarray(images_mu, np.float32)
    image = np.asarray(image, np.int64)
    view = np.asarray(view, np.int64)
    if imgs.ndim != 3 or image.shape != view.shape or image.ndim != 1:
        raise ValueError(f"images {imgs.shape}, image {image.shape}, view {view.shape}: expected (Q, ny, nx), "
                         "(m,), (m,)")
    if image.size == 0:
        return np.zeros((0, geom.n_cols), np.float32)
    _, ny, nx = imgs.shape
    origin = (-0.5 * (nx - 1) * voxel_mm, -0.5 * (ny - 1) * voxel_mm, 0.0)
    (src, centre, eu, ev), u, vs = inplane_frames(detector, geom, view, image * STACK_DZ_MM)
    out = project_volume(imgs, origin, (voxel_mm, voxel_mm, STACK_DZ_MM), src, centre, eu, ev, u, np.zeros(1),
                         rt=rt, v_scale=vs)
    return out[:, 0, :]


def predicted_rows(volumes_hu, cardiac, resp, row_slice, row_view, row_c, row_a, *, geom, detector,
                   mu_water: float, rt=None) -> np.ndarray:
    """A method's prediction P_k I(c_k, a_k) of every row, (p, C) float32 line integrals.

    ``volumes_hu`` (n_c, n_r, S, ny, nx) the method's images (HU) at the target lattice
    ``cardiac`` (n_c,) x ``resp`` (n_r,) on S slices (an axis of length 1: one image for every
    target of it, as the writer stores a broadcast axis); ``row_slice`` (p,) index into S;
    ``row_view`` (p,) view index of the reconstruction's geometry; ``row_c``, ``row_a`` (p,) the
    row's recorded state. HU -> attenuation by mu = mu_water (1 + HU / 1000) (-1000 HU outside
    the FOV projects to 0). Each (target, slice) image is projected once per view it is needed
    at, then the projections are interpolated (:func:`lattice_weights`; linear, so the same as
    projecting the interpolated image).
    """
    vol = np.asarray(volumes_hu)
    nc, nr, S = vol.shape[:3]
    # an axis written at length 1 (a method blind to it, a scene without it) holds one image for every target
    cardiac = list(cardiac) if nc > 1 else [0.0]
    resp = list(resp) if nr > 1 else [0.0]
    if (nc, nr) != (len(cardiac), len(resp)):
        raise ValueError(f"volumes {vol.shape[:2]} and the lattice ({len(cardiac)}, {len(resp)}) disagree")
    sl = np.asarray(row_slice, np.int64)
    vw = np.asarray(row_view, np.int64)
    idx, w = lattice_weights(row_c, row_a, cardiac, resp)
    live = w != 0
    img = idx * S + sl[:, None]                                   # flat (target, slice) image of each corner
    view_c = np.broadcast_to(vw[:, None], idx.shape)
    key = img[live] * geom.n_views + view_c[live]
    uniq, inv = np.unique(key, return_inverse=True)
    used_img, img_pos = np.unique(uniq // geom.n_views, return_inverse=True)
    flat = vol.reshape((nc * nr * S,) + vol.shape[3:])
    mu = np.float32(mu_water) * (np.float32(1.0) + flat[used_img].astype(np.float32) / np.float32(1000.0))
    proj = inplane_projections(mu, geom.voxel_mm, detector, geom, img_pos, uniq % geom.n_views, rt=rt)
    del mu
    pos = np.full(idx.shape, -1, np.int64)
    pos[live] = inv
    out = np.zeros((sl.size, proj.shape[1]), np.float64)
    for k in range(idx.shape[1]):  # one corner at a time: no (p, 4, C) temporary
        r = np.flatnonzero(live[:, k])
        out[r] += w[r, k, None] * proj[pos[r, k]]
    return out.astype(np.float32)


def channels_through_circle(detector, geom, view, radius_mm: float) -> np.ndarray:
    """(m, C) bool: the in-plane rays at views ``view`` (m,) that pass within ``radius_mm`` of the
    rotation axis (the reconstruction circle), in :func:`inplane_projections`' geometry."""
    view = np.asarray(view, np.int64)
    (src, centre, eu, _), u, _ = inplane_frames(detector, geom, view, np.zeros(view.size))
    s = src[:, None, :2]
    d = centre[:, None, :2] + u[None, :, None] * eu[:, None, :2] - s
    cross = s[..., 0] * d[..., 1] - s[..., 1] * d[..., 0]
    return np.abs(cross) / np.linalg.norm(d, axis=-1) <= radius_mm


@dataclass
class Residual:
    """Squared residuals of one method pooled per block and region: ``sq[region]`` and ``cells[region]``
    (B,) over the B blocks, ``floor[region]`` (B,) the sum of the rows' noise variance (0 without a
    noise model). The blocks are slice-major, B / ``n_slices`` per slice."""

    sq: dict
    cells: dict
    floor: dict
    n_slices: int = 1

    def rms(self, region: str) -> float:
        n = self.cells[region].sum()
        return float(np.sqrt(self.sq[region].sum() / n)) if n else float("nan")

    def per_slice_rms(self, region: str) -> np.ndarray:
        """(n_slices,) RMS per slice (NaN at a slice without cells in the region)."""
        sq = self.sq[region].reshape(self.n_slices, -1).sum(axis=1)
        n = self.cells[region].reshape(self.n_slices, -1).sum(axis=1)
        return np.where(n > 0, np.sqrt(sq / np.maximum(n, 1)), np.nan)

    def slice(self, s: int) -> Residual:
        """The blocks of slice ``s`` alone, as a one-slice Residual."""
        def part(d):
            return {r: x.reshape(self.n_slices, -1)[s] for r, x in d.items()}
        return Residual(part(self.sq), part(self.cells), part(self.floor), 1)

    def floor_rms(self, region: str) -> float:
        n = self.cells[region].sum()
        return float(np.sqrt(self.floor[region].sum() / n)) if n else float("nan")


def residual(rows, predicted, masks: dict, block, n_blocks: int, row_var=None, scale: float = 1.0,
             n_slices: int = 1) -> Residual:
    """Pooled squared residuals ``(y - P) * scale`` of rows (p, C) against ``predicted`` (p, C).

    ``masks`` ``{region: (p, C) bool}``; ``block`` (p,) the block of each row in [0, n_blocks),
    slice-major with n_blocks / ``n_slices`` blocks per slice; ``row_var`` (p, C) the rows' noise
    variance (line integral^2) or None.
    """
    if n_blocks % n_slices:
        raise ValueError(f"{n_blocks} blocks do not split into {n_slices} slices of equally many")
    e = (np.asarray(rows, np.float64) - np.asarray(predicted, np.float64)) * scale
    e2 = e * e
    blk = np.asarray(block, np.int64)
    sq, cells, floor = {}, {}, {}
    for r, m in masks.items():
        sq[r] = np.bincount(blk, (e2 * m).sum(axis=1), minlength=n_blocks)
        cells[r] = np.bincount(blk, m.sum(axis=1), minlength=n_blocks).astype(np.int64)
        floor[r] = (np.zeros(n_blocks) if row_var is None else
                    np.bincount(blk, (np.asarray(row_var, np.float64) * m).sum(axis=1) * scale * scale,
                                minlength=n_blocks))
    return Residual(sq, cells, floor, n_slices)


def compare(a: Residual, b: Residual, region: str) -> dict:
    """Method a against method b in ``region``: RMS ratio a / b, the difference of mean squares
    (a - b, HU mm^2), its jackknife standard error over blocks, z = difference / SE, and what that
    says: ``"lower"`` (z < -Z_DECIDES), ``"higher"`` (z > Z_DECIDES) or ``"no clear difference"``
    (also, whatever z, where the ratio is within :data:`MIN_EFFECT` of 1: ``below_min_effect``)."""
    d = a.sq[region] - b.sq[region]
    n = a.cells[region].astype(np.float64)
    keep = n > 0
    d, n = d[keep], n[keep]
    B = d.size
    ra, rb = a.rms(region), b.rms(region)
    out = {"ratio": ra / rb if rb > 0 else float("nan"), "difference_ms_hu_mm2": float(d.sum() / n.sum()) if B else
           float("nan"), "blocks": int(B)}
    if B < 2:
        return dict(out, se_hu_mm2=float("nan"), z=float("nan"), says="no clear difference",
                    null_because="fewer than 2 blocks with cells in this region")
    loo = (d.sum() - d) / (n.sum() - n)
    se = float(np.sqrt((B - 1) / B * ((loo - loo.mean()) ** 2).sum()))
    diff = out["difference_ms_hu_mm2"]
    z = diff / se if se > 0 else 0.0 if diff == 0 else float(np.copysign(np.inf, diff))  # se 0: every block agrees
    small = bool(abs(out["ratio"] - 1.0) <= MIN_EFFECT)
    says = ("no clear difference" if small else "lower" if z < -Z_DECIDES else "higher" if z > Z_DECIDES
            else "no clear difference")
    return dict(out, se_hu_mm2=se, z=float(z), says=says, **({"below_min_effect": True} if small else {}))


def by_slices(a: Residual, b: Residual, region: str) -> dict:
    """Method a against method b in ``region``, slice by slice: :func:`compare` at each slice (over its
    own blocks), then a two-sided sign test over the slices that differ (``lower`` against ``higher``;
    a slice with no clear difference is a tie and drops out). ``says`` is ``"lower"`` / ``"higher"``
    where the majority's sign-test p is at most :data:`SIGN_TEST_ALPHA`, else ``"no clear difference"``.
    Each slice counts once whatever the size of its residual."""
    if a.n_slices != b.n_slices:
        raise ValueError(f"{a.n_slices} and {b.n_slices} slices: the residuals are not of the same sampling")
    per = [compare(a.slice(s), b.slice(s), region) for s in range(a.n_slices)]
    lower = sum(p["says"] == "lower" for p in per)
    higher = sum(p["says"] == "higher" for p in per)
    p = float(binomtest(lower, lower + higher, 0.5).pvalue) if lower + higher else 1.0
    says = ("lower" if lower > higher and p <= SIGN_TEST_ALPHA else
            "higher" if higher > lower and p <= SIGN_TEST_ALPHA else "no clear difference")
    return {"says": says, "slices": a.n_slices, "slices_lower": int(lower), "slices_higher": int(higher),
            "sign_test_p": p, "per_slice": [{k: x[k] for k in ("ratio", "z", "says")} for x in per]}


def verdict(res: dict, method: str = METHOD, reference: str = REFERENCE) -> dict:
    """Did ``method`` help against ``reference`` (its first pass)? From ``{method: Residual}`` of one
    variant: per region the slice-by-slice decision (:func:`by_slices`: ``says``, the counts, the sign
    test's p, ``per_slice``) beside the comparison pooled over every block (:func:`compare`: ``ratio``,
    ``z``, ... and its own ``pooled_says``), and ``helped``: True when ``method`` is lower in both
    regions, False when it is higher in either, else None (no clear difference). Fewer than
    :data:`MIN_DECIDING_SLICES` slices that differ cannot decide."""
    if method not in res or reference not in res:
        return {"helped": None, "null_because": f"{method} or {reference} is not in this run"}
    by = {}
    for r in REGIONS:
        pooled = compare(res[method], res[reference], r)
        by[r] = dict(pooled, pooled_says=pooled["says"], **by_slices(res[method], res[reference], r))
    says = [by[r]["says"] for r in REGIONS]
    helped = False if "higher" in says else True if all(s == "lower" for s in says) else None
    word = {True: "helped", False: "did not help", None: "no clear difference"}[helped]

    def counts(e):
        return f"lower at {e['slices_lower']}, higher at {e['slices_higher']} of {e['slices']} slices " \
               f"(sign test p {e['sign_test_p']:.3g})"

    a, h = by["all"], by["heart"]
    text = (f"{method} {word}: {counts(a)}, heart {counts(h)}; pooled residual x {a['ratio']:.3f} of "
            f"{reference}'s (z {a['z']:+.1f}), heart x {h['ratio']:.3f} (z {h['z']:+.1f})")
    if a["slices"] < MIN_DECIDING_SLICES:
        text += (f"; {a['slices']} slices cannot decide (a sign test needs at least {MIN_DECIDING_SLICES} that "
                 "differ)")
    small = [r for r in REGIONS if by[r].get("below_min_effect")]
    if small:
        text += (f"; pooled {' and '.join(small)} within {100 * MIN_EFFECT:g} % of 1: below the smallest effect "
                 "it reports")
    return {"helped": helped, "against": reference, "regions": by, "text": text}


def check(store, table, slices_z, recon_cfg, targets, variants, box, volumes, methods,
          cfg: ConsistencyConfig = ConsistencyConfig(), rt=None) -> dict:
    """The data-consistency residual of every method's volumes for one scan (pitch).

    ``store`` holds every candidate projection of the sampled slices (:func:`needed_projections`);
    ``table`` the projection table the plan used; ``slices_z`` (S,) the run's slices (mm);
    ``recon_cfg`` :class:`clrecon.reconstruction.reconstruct.ReconstructionConfig`; ``targets``
    its ``Targets``; ``box`` the heart box (x0, x1, y0, y1) mm; ``volumes(variant, method, slice
    indices) -> (n_c, n_r, s, ny, nx)`` HU; ``methods`` the 5D methods to check. Returns the
    ``results.json["consistency"][pitch]`` entry (docs/consistency.md "Did it help?").
    """
    t0 = time.perf_counter()
    sc = recon_cfg.scanner
    geom = recon_cfg.fbp
    zs = truth_free.sample_slices(slices_z, cfg.max_slices)
    s_idx = np.array([int(np.argmin(np.abs(np.asarray(slices_z) - z))) for z in zs])
    groups = rc_mod.candidate_groups_of(recon_cfg, table, zs)
    nv = groups.views_per_rotation
    step = max(cfg.view_step, 1)
    gsel = np.flatnonzero((groups.group_view % step) == 0)
    flat = np.concatenate([np.arange(groups.offsets[g], groups.offsets[g + 1]) for g in gsel]) if gsel.size else \
        np.zeros(0, np.int64)
    if cfg.unused_only:  # before the |dz| cut: the weights are those of whole groups
        flat = flat[unused_rows(REFERENCE, groups, flat, table, recon_cfg, targets)]
    if cfg.max_dz_mm is not None:
        flat = flat[np.abs(groups.dz_mm[flat]) <= cfg.max_dz_mm]
    g_of = np.repeat(np.arange(groups.n_groups), np.diff(groups.offsets))[flat]
    row_slice = g_of // nv
    row_view = groups.group_view[g_of]
    row_c = table.cardiac_phase[groups.row[flat]]
    row_a = table.resp_amplitude[groups.row[flat]]
    nvs = -(-nv // step)  # sampled views per slice: 0, step, 2 step, ...
    per_slice_blocks = -(-nvs // max(cfg.block_views, 1))
    block = row_slice * per_slice_blocks + (row_view // step) // max(cfg.block_views, 1)
    n_blocks = len(zs) * per_slice_blocks
    # masks: the reconstruction circle, the heart box (the truth-free's heart channels)
    circle = channels_through_circle(sc.detector_model, geom, row_view, recon_cfg.object_radius_mm)
    angle = table.angle_rad[groups.row[flat]]
    masks = {"all": circle, "heart": truth_free.heart_channels(angle, sc, box) & circle}
    t_plan = time.perf_counter() - t0
    t1 = time.perf_counter()
    rows_by_v = truth_free.read_rows(store, groups, flat, sc, variants, recon_cfg.noise, rt=rt) if flat.size else {}
    t_read = time.perf_counter() - t1
    scale = 1000.0 / recon_cfg.mu_water_per_mm
    out = {"config": {"slices_z_mm": [float(z) for z in zs], "view_step": step, "block_views": cfg.block_views,
                      **({"max_dz_mm": cfg.max_dz_mm} if cfg.max_dz_mm is not None else {}),
                      **({"unused_only": True} if cfg.unused_only else {}),
                      "blocks": int(n_blocks), "methods": list(methods),
                      "units": "HU mm (line integral x 1000 / mu_water)",
                      "regions": {"all": "channels whose ray passes through the reconstruction circle",
                                  "heart": "... and crosses the heart box recon.small_fov_mm"},
                      "z_decides": Z_DECIDES, "min_effect": MIN_EFFECT, "sign_test_alpha": SIGN_TEST_ALPHA},
           "n_rows": int(flat.size), "residual": {}, "verdict": {},
           **({"mcir_verdict": {}} if ITERATIVE in methods and ITERATIVE_AGAINST in methods else {})}
    t_pred = 0.0
    for v in variants:
        if flat.size == 0:
            break
        rows, var = rows_by_v[v]
        res = {}
        for m in methods:
            t2 = time.perf_counter()
            vol = volumes(v, m, s_idx)
            pred = predicted_rows(vol, targets.cardiac, targets.resp, row_slice, row_view, row_c, row_a, geom=geom,
                                  detector=sc.detector_model, mu_water=recon_cfg.mu_water_per_mm, rt=rt)
            t_pred += time.perf_counter() - t2
            res[m] = residual(rows, pred, masks, block, n_blocks, row_var=var, scale=scale, n_slices=len(zs))
        against = {m: verdict(res, m) for m in res if m != REFERENCE and REFERENCE in res}
        ent = {}
        for m, r in res.items():
            e = {"rms_hu_mm": r.rms("all"), "heart_rms_hu_mm": r.rms("heart"), "n_rows": int(flat.size),
                 "cells": int(r.cells["all"].sum()), "heart_cells": int(r.cells["heart"].sum()),
                 "per_slice_rms_hu_mm": r.per_slice_rms("all").tolist()}
            if var is not None:
                e["noise_floor_hu_mm"] = r.floor_rms("all")
                e["heart_noise_floor_hu_mm"] = r.floor_rms("heart")
            if m in against:  # the summary of its verdict against the reference
                e[f"against_{REFERENCE}"] = {g: {k: against[m]["regions"][g][k] for k in AGAINST_KEYS}
                                             for g in REGIONS}
            ent[m] = e
        out["residual"][v] = ent
        out["verdict"][v] = against[METHOD] if METHOD in against else verdict(res)
        if "mcir_verdict" in out:
            out["mcir_verdict"][v] = verdict(res, ITERATIVE, ITERATIVE_AGAINST)
    out["seconds"] = {"plan": round(t_plan, 3), "read_rebin": round(t_read, 3), "predict": round(t_pred, 3),
                      "total": round(time.perf_counter() - t0, 3)}
    return out


def unused_rows(method: str, groups, flat, table, recon_cfg, targets) -> np.ndarray:
    """(n,) bool over the candidates ``flat`` (indices into ``groups``' flat arrays, whole groups):
    True where ``method``'s weights are 0 at every target of its (slice, view), i.e. the row did not
    enter that slice's images (the plan's own weights,
    :func:`clrecon.reconstruction.interpolation.weights.batch_weights`)."""
    flat = np.asarray(flat, np.int64)
    if flat.size == 0:
        return np.zeros(0, bool)
    g = np.repeat(np.arange(groups.n_groups), np.diff(groups.offsets))[flat]
    starts = np.flatnonzero(np.r_[True, g[1:] != g[:-1]])
    off = np.r_[starts, flat.size]
    c = table.cardiac_phase[groups.row[flat]]
    a = table.resp_amplitude[groups.row[flat]]
    w = interpolate.batch_weights(method, c, a, off, np.asarray(targets.pairs, float), dz=groups.dz_mm[flat],
                                  allow_empty=True, **rc_mod.weight_options(recon_cfg, targets))
    used = np.zeros(flat.size, bool)
    used[w.index[w.weight != 0]] = True
    return ~used


def needed_projections(recon_cfg, table, slices_z, cfg: ConsistencyConfig = ConsistencyConfig()) -> np.ndarray:
    """Projection numbers :func:`check` reads (every candidate of the sampled slices' sampled views)."""
    return truth_free.needed_projections(recon_cfg, table, slices_z, cfg.truth_free_config())
