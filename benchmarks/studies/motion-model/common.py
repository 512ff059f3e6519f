"""Shared steps of the motion-model study (docs/results/mc-study.md): first pass, truth, model, MC-FBP.

Everything goes through the package (the run's own planning, SSRB, FBP, ground truth and
metrics); only the glue lives here. Intermediate arrays are cached under ``$MOTION_STUDY_CACHE``
(default ``/tmp/clrecon-motion-study``) keyed by scene, pitch, variant and slices, so that the
tuning and the report do not redo the first pass and the truths.
"""

import hashlib
import json
import os
import time

import numpy as np

import clrecon
from clrecon.evaluation.groundtruth import GroundTruthConfig, groundtruth_volumes
from clrecon.evaluation.metrics import MetricsConfig, table2
from clrecon.reconstruction import reconstruct as rc
from clrecon.reconstruction.motion import backproject as mcb
from clrecon.reconstruction.motion import model as mm
from clrecon.reconstruction.motion import registration as reg
from clrecon.reconstruction.motion import slots as msl
from clrecon.reconstruction.rebin import candidate_groups, slice_window_mm, ssrb_row_range
from clrecon.scan.table import projection_table
from clrecon.simulation.phantom_sources import phantom_from_config
from clrecon.simulation.phantoms import motion_field
from clrecon.simulation.simulate import simulate

CACHE = os.environ.get("MOTION_STUDY_CACHE", "/tmp/clrecon-motion-study")
FIRST_PASS = ("barycentric", "local_linear", "nearest", "r4dct")


def _key(*parts) -> str:
    return hashlib.sha1(json.dumps(parts, default=str).encode()).hexdigest()[:16]


def cached(name, parts, fn):
    os.makedirs(CACHE, exist_ok=True)
    path = os.path.join(CACHE, f"{name}-{_key(*parts)}.npz")
    if os.path.exists(path):
        with np.load(path) as f:
            return {k: f[k] for k in f.files}
    out = fn()
    np.savez(path, **out)
    return out


class Context:
    """One (scene, pitch): the scene, its reconstruction config, targets, table, store."""

    def __init__(self, scene_name: str, pitch: float):
        self.name, self.pitch = scene_name, float(pitch)
        self.scene = clrecon.load_scene(scene_name)
        self.cfg = rc.ReconstructionConfig.from_scene(self.scene)
        self.targets = rc.Targets(cardiac=self.scene.cardiac_targets, resp=self.scene.resp_targets)
        self.table = projection_table(self.scene, self.pitch)
        self.store = simulate(self.scene, self.pitch, progress=False)
        self.report_z = rc.slice_positions(self.scene)
        # tuning slices: midway between report slices, in the heart's z range (never reported)
        self.tune_z = np.array([-12.0, -4.0, 4.0, 12.0]) + self.scene.scan.z_centre_mm
        self.geom = self.cfg.fbp
        self.mcfg = MetricsConfig.from_scene(self.scene)
        self.phantom = phantom_from_config(self.scene.phantom)

    @property
    def pairs(self):
        return self.targets.pairs


def first_pass(ctx: Context, variant: str, slices_z, methods=FIRST_PASS) -> dict:
    """The paper methods' HU volumes (n_c, n_r, S, ny, nx) per method (r4dct broadcast over c)."""
    def run():
        plan = rc.plan(ctx.cfg, ctx.table, np.asarray(slices_z), ctx.targets, methods)
        t0 = time.perf_counter()
        vols = rc.reconstruct(ctx.cfg, ctx.store, plan, variants=(variant,))
        out = {}
        for m in methods:
            v = vols[(variant, m)]
            out[m] = np.broadcast_to(v, (len(ctx.targets.cardiac),) + v.shape[1:]).copy()
        out["seconds"] = np.array(time.perf_counter() - t0)
        return out
    return cached("first", (ctx.name, ctx.pitch, variant, list(map(float, slices_z)), list(methods)), run)


def truth(ctx: Context, slices_z) -> np.ndarray:
    def run():
        gcfg = GroundTruthConfig.from_scene(ctx.scene)
        nc, nr = ctx.targets.shape
        out = np.empty((nc, nr, len(slices_z), ctx.geom.ny, ctx.geom.nx), np.float32)
        for i, j, v in groundtruth_volumes(gcfg, np.asarray(slices_z), ctx.targets):
            out[i, j] = v
        return {"truth": out}
    return cached("truth", (ctx.name, list(map(float, slices_z))), run)["truth"]


def mae(ctx: Context, recon, truth_) -> tuple:
    r = table2(np.asarray(recon, np.float32), truth_, ctx.mcfg)
    return round(r["large"]["mae_hu"], 3), round(r["small"]["mae_hu"], 3)


def field_grid(ctx: Context) -> mm.FieldGrid:
    return mm.FieldGrid.of_slices(ctx.geom.nx, ctx.geom.ny, ctx.geom.voxel_mm, ctx.report_z)


def registered_fields(ctx: Context, variant: str, volumes, ref_index: int, dcfg, tag: str):
    """u(x_ref; target) of every target's volume (T, 3, nz, ny, nx), registered to the reference's."""
    def run():
        v = np.asarray(volumes).reshape((-1,) + volumes.shape[2:])
        t0 = time.perf_counter()
        f = reg.register_to_reference(v, ref_index, (ctx.geom.voxel_mm, ctx.geom.voxel_mm,
                                                     float(ctx.report_z[1] - ctx.report_z[0])), cfg=dcfg)
        return {"fields": f, "seconds": np.array(time.perf_counter() - t0)}
    return cached("reg", (ctx.name, ctx.pitch, variant, ref_index, repr(dcfg), tag), run)


def true_fields(ctx: Context, reference: tuple, states) -> np.ndarray:
    """The phantom's true displacement from ``reference`` to each state, on the model grid."""
    def run():
        x, y, z = field_grid(ctx).coords()
        return {"fields": motion_field.displacement_fields(ctx.phantom, x, y, z, reference, states)}
    return cached("truefield", (ctx.name, list(map(float, reference)), np.asarray(states).round(6).tolist()),
                  run)["fields"]


def plane_rows(ctx: Context, variant: str, proj_ids, z_lo, z_hi, plane_dz):
    """Filtered SSRB rows of the projections on planes (package: motion.backproject.plane_rows)."""
    sc = ctx.scene.scanner
    ids = np.unique(np.asarray(proj_ids, np.int64))
    ids = ids[ids >= 0]
    w = slice_window_mm(sc, ctx.cfg.object_radius_mm)
    lo, hi = ssrb_row_range(np.array([-w - plane_dz, w + plane_dz]), sc)
    proj = ctx.store.read_indices(ids, noisy=(variant == "noisy"), rows=(lo, hi))
    return mcb.plane_rows(proj, ctx.table, ids, sc, ctx.geom, ctx.cfg.filter, plane_dz_mm=plane_dz,
                          z_lo_mm=z_lo, z_hi_mm=z_hi, object_radius_mm=ctx.cfg.object_radius_mm, first_row=lo)


def groups_for(ctx: Context, slices_z, margin_mm: float):
    w = slice_window_mm(ctx.scene.scanner, ctx.cfg.object_radius_mm)
    return candidate_groups(ctx.table, np.asarray(slices_z), ctx.scene.scanner, ctx.cfg.object_radius_mm,
                            w + margin_mm)


def mc_volumes(ctx: Context, rows, model, slot_proj, slot_w, slices_z, cfg: mcb.MCConfig, targets=None):
    """MC-FBP HU volumes (n_c, n_r, S, ny, nx) from slots (T, S, V, K) (local indices)."""
    pairs = ctx.pairs if targets is None else targets
    c = ctx.table.cardiac_phase[rows.projection]
    a = ctx.table.resp_amplitude[rows.projection]
    pb = model.basis.values(c, a)
    nc, nr = ctx.targets.shape
    out = np.empty((len(pairs), len(slices_z), ctx.geom.ny, ctx.geom.nx), np.float32)
    mw = ctx.cfg.mu_water_per_mm
    with mcb.MCBackprojector(rows, pb, model, slices_z, ctx.geom, cfg) as bp:
        for t, tgt in enumerate(pairs):
            mu = bp(slot_proj[t], slot_w[t], tuple(tgt))
            out[t] = 1000.0 * (mu - mw) / mw
    return out.reshape(nc, nr, len(slices_z), ctx.geom.ny, ctx.geom.nx) if targets is None else out


def bary_slots(ctx: Context, slices_z, rows):
    plan = rc.plan(ctx.cfg, ctx.table, np.asarray(slices_z), ctx.targets, ("barycentric",))
    mp = plan.methods["barycentric"]
    return msl.plan_slots(mp.proj_index, mp.weight, rows)


def kernel_slots(ctx: Context, slices_z, rows, sigma_c, sigma_a, max_slots, margin_mm):
    g = groups_for(ctx, slices_z, margin_mm)
    c = ctx.table.cardiac_phase[g.row]
    a = ctx.table.resp_amplitude[g.row]
    return msl.kernel_slots(g, c, a, ctx.pairs, sigma_c=sigma_c, sigma_a=sigma_a, max_slots=max_slots, rows=rows)


def candidate_rows(ctx: Context, variant: str, slices_z, method: str = "barycentric"):
    """SSRB rows (unfiltered) of every (projection, slice) pair the method's plan uses, and the plan.

    Returns (rows (p, C), pair_proj (p,), pair_slice (p,), plan): pairs sorted as
    ``SlabWeights.needed_pairs``.
    """
    z = np.asarray(slices_z, np.float64)
    plan = rc.plan(ctx.cfg, ctx.table, z, ctx.targets, (method,))
    proj, sl = plan.needed_pairs()
    sc = ctx.scene.scanner
    dz = z[sl] - ctx.table.source_z_mm[proj]
    lo, hi = ssrb_row_range(dz, sc)
    ids, slot = np.unique(proj, return_inverse=True)
    data = ctx.store.read_indices(ids, noisy=(variant == "noisy"), rows=(lo, hi))
    shift = None
    if ctx.table.focal_shift is not None:
        from clrecon.core.detector import spot_shift_in_frame
        shift = spot_shift_in_frame(ctx.table.focal_shift[proj], sc.sid_mm)
    from clrecon.reconstruction.rebin import ssrb_rows
    rows = ssrb_rows(data, slot.astype(np.int32), dz.astype(np.float32), sc, first_row=lo, pair_shift=shift)
    return rows, proj, sl, plan


def registered_average(ctx: Context, volumes, fields) -> np.ndarray:
    """Mean of the volumes (T, nz, ny, nx) brought to the reference frame by their fields (T, 3, ...)."""
    g = field_grid(ctx)
    x, y, z = g.coords()
    Z, Y, X = np.meshgrid(z, y, x, indexing="ij")
    pts = np.stack([X, Y, Z], -1)
    acc = np.zeros(g.shape)
    for v, f in zip(volumes, fields, strict=True):
        acc += mm.sample(v, g, pts + np.moveaxis(f, 0, -1))
    return (acc / len(volumes)).astype(np.float32)


def correction_volumes(ctx: Context, variant: str, slices_z, model, ref_hu, ref_grid, bins=(20, 10), cand=None):
    """Model-based correction step (correction.py here) of every target: HU (n_c, n_r, S, ny, nx)."""
    import correction as corr
    import warp as mwarp

    from clrecon.reconstruction.fbp import fbp
    z = np.asarray(slices_z, np.float64)
    rows, proj, sl, plan = cand if cand is not None else candidate_rows(ctx, variant, z)
    mw = ctx.cfg.mu_water_per_mm
    ref_mu = (mw * (1.0 + np.asarray(ref_hu, np.float64) / 1000.0)).astype(np.float32)
    states = np.stack([ctx.table.cardiac_phase[proj], ctx.table.resp_amplitude[proj]], 1)
    view = ctx.table.view[proj]
    t0 = time.perf_counter()
    mrows = corr.model_rows(ref_mu, model, ctx.scene.scanner.detector_model, ctx.geom, view, z[sl], states,
                            bins=bins, volume_grid=ref_grid)
    t_model = time.perf_counter() - t0
    resid = rows - mrows
    mp = plan.methods["barycentric"]
    S = len(z)
    keys = proj.astype(np.int64) * S + sl
    nc, nr = ctx.targets.shape
    out = np.empty((nc, nr, S, ctx.geom.ny, ctx.geom.nx), np.float32)
    # the target term goes through the same projection and FBP as the rows' model (M(t) := W_t FBP P M_ref):
    # otherwise M(t) - FBP(P M(t)), the blur of a second projection and FBP, stays in the image
    g = ref_grid
    allv = np.tile(np.arange(ctx.geom.n_views), g.nz)
    zall = np.repeat(g.coords()[2], ctx.geom.n_views)
    ref_state = np.tile(np.asarray(model.reference, np.float64), (len(allv), 1))
    prow = corr.model_rows(ref_mu, model, ctx.scene.scanner.detector_model, ctx.geom, allv, zall, ref_state,
                           bins=bins, volume_grid=g)
    ref_rt = fbp(prow.reshape(g.nz, ctx.geom.n_views, -1), ctx.geom, ctx.cfg.filter)
    m_t = mwarp.warp(ref_rt, model, ctx.pairs, z, volume_grid=g)  # (T, S, ny, nx)
    fov = ctx.geom.fov_mask()
    for s in range(S):
        key = mp.proj_index[s].astype(np.int64) * S + s      # (V, T, K)
        pos = np.clip(np.searchsorted(keys, key), 0, len(keys) - 1)
        w = mp.weight[s]
        sino = corr.interpolate_rows(resid, np.moveaxis(pos, 1, 0), np.moveaxis(w, 1, 0))  # (T, V, C)
        mu = fbp(sino, ctx.geom, ctx.cfg.filter)
        out[:, :, s] = corr.corrected_images(mu, m_t[:, s], fov, mw).reshape(nc, nr, ctx.geom.ny, ctx.geom.nx)
    return out, {"model_rows_s": t_model, "pairs": int(len(proj))}


def separable_model(ctx: Context, variant: str, volumes, ref_ij, dcfg, basis):
    """Registration model (package: motion.estimate.separable_fields, then the basis fit), cached fields."""
    from clrecon.reconstruction.motion import estimate
    g = field_grid(ctx)

    def run():
        t0 = time.perf_counter()
        f, parts = estimate.separable_fields(volumes, ref_ij, g, dcfg)
        return {"fields": f, "seconds": np.array(time.perf_counter() - t0)}
    r = cached("sepreg", (ctx.name, ctx.pitch, variant, list(ref_ij), repr(dcfg)), run)
    ref = tuple(ctx.pairs[ref_ij[0] * ctx.targets.shape[1] + ref_ij[1]])
    model, rms = mm.fit_motion_model(r["fields"], ctx.pairs, basis, g, ref)
    return model, r["fields"], float(r["seconds"])


def true_model(ctx: Context, ref, basis):
    g = field_grid(ctx)
    tf = true_fields(ctx, ref, ctx.pairs)
    model, rms = mm.fit_motion_model(tf, ctx.pairs, basis, g, ref)
    return model, tf


def mc_reference_image(ctx: Context, variant: str, model, ref, fine_z, sigma_c, sigma_a, max_slots, margin, plane_dz,
                       taper):
    """MC-FBP image (HU) of the reference state on the fine slices ``fine_z``: the model image of the correction step."""
    g = groups_for(ctx, fine_z, margin)
    rows = plane_rows(ctx, variant, g.projection, fine_z.min() - margin - 2, fine_z.max() + margin + 2, plane_dz)
    c = ctx.table.cardiac_phase[g.row]
    a = ctx.table.resp_amplitude[g.row]
    sp, sw = msl.kernel_slots(g, c, a, np.array([ref]), sigma_c=sigma_c, sigma_a=sigma_a, max_slots=max_slots,
                              rows=rows)
    return mc_volumes(ctx, rows, model, sp, sw, fine_z, mcb.MCConfig(taper_mm=taper), targets=np.array([ref]))[0]
