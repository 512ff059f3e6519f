"""The ``mc`` section's kernel row: the motion-compensated backprojection against the static
fan-beam backprojector of the same geometry, in the same run.

The case (:func:`synthetic_case`) has a scene's geometry (`demo`: 128^2 voxels of 3 mm, 360 views
x 240 columns, flat detector) and the motion model's basis (NB = 6: constant, amplitude, 2 cardiac
harmonics), with synthetic data of `demo`'s sizes at pitch 0.10: projections every view on turns
2.8 mm apart in z, each rebinned to the 2-mm planes within its SSRB window plus one plane, random
rows; per (slice, view) the 3 projections nearest the slice in z with random weights (as
barycentric's 3 slots); smooth random fields of up to 6 mm.

Both are timed end to end (host arrays in, images out: the static one interleaves and uploads its
sinograms, the motion-compensated one forms its target's field and uploads its slots), alternating,
``repeats`` times after a warm-up, medians. Updates are counted inside the FOV circle for both:
static, (voxel, view, image); motion-compensated, (voxel, non-empty slot), the row reads (3 per
view here). The static backprojector gets 32 random filtered sinograms per call, two groups of 16
as the reconstruction launches them.
"""

from __future__ import annotations

import numpy as np
import scipy.ndimage

from clrecon.bench.timing import load1, timed
from clrecon.config.scene import load_scene
from clrecon.core.runtime import get_runtime
from clrecon.reconstruction import fbp, rebin
from clrecon.reconstruction.fbp import FanBeamGeometry
from clrecon.reconstruction.motion.backproject import MCBackprojector, PlaneRows, plane_range
from clrecon.reconstruction.motion.model import FieldGrid, MotionBasis, MotionModel

#: Sinograms per static call (two groups of 16 lanes: one launch of the batched kernel).
STATIC_BATCH = 32
#: Fewest timed repeats of each backprojector.
MIN_REPEATS = 3
#: The issue's goal for the motion-compensated kernel against the static one (updates/s ratio).
GOAL_RATIO = 0.25


def synthetic_case(n_slices: int = 4, seed: int = 34, scene="demo"):
    """(geom, model, rows, proj_basis, slot_proj, slot_w, slices_z) of the module docstring's case
    (``scene``: a scene name or a loaded scene, whose geometry)."""
    rng = np.random.default_rng(seed)
    sc = load_scene(scene) if isinstance(scene, str) else scene
    geom = FanBeamGeometry.from_scene(sc)
    V = geom.n_views
    feed = 2.8                                               # mm per turn: demo at pitch 0.10
    window = rebin.slice_window_mm(sc.scanner, geom.fov_radius_mm)
    slices_z = 2.5 * np.arange(n_slices)
    lo, hi = slices_z[0] - window - 2.0, slices_z[-1] + window + 2.0
    n_turns = int(np.ceil((hi - lo) / feed))
    z = lo + feed * (np.arange(n_turns)[:, None] + np.arange(V)[None, :] / V)   # (turn, view)
    proj_z = z.ravel()
    first, count = plane_range(proj_z, window, 2.0, lo - 4.0, hi + 4.0)
    rows = PlaneRows(rows=rng.normal(size=(proj_z.size, int(count.max()), geom.n_cols)).astype(np.float32),
                     plane_first=first.astype(np.int32), plane_count=count.astype(np.int32),
                     projection=np.arange(proj_z.size), proj_z_mm=proj_z, plane_dz_mm=2.0, window_mm=window)
    K = 3
    sp = np.empty((n_slices, V, K), np.int32)
    for s, zs in enumerate(slices_z):
        near = np.argsort(np.abs(z - zs), axis=0)[:K]           # (K, V) nearest turns per view
        sp[s] = (near * V + np.arange(V)[None, :]).T
    sw = rng.uniform(0.1, 1.0, sp.shape).astype(np.float32)
    basis = MotionBasis(resp_degree=1, cardiac_harmonics=2)
    grid = FieldGrid(nx=geom.nx, ny=geom.ny, nz=8, voxel_mm=geom.voxel_mm, z0_mm=lo, dz_mm=(hi - lo) / 7)
    f = scipy.ndimage.gaussian_filter(rng.normal(size=(basis.size, 3) + grid.shape), (0, 0, 1, 8, 8))
    f *= 6.0 / np.abs(f).max()
    model = MotionModel(basis=basis, grid=grid, fields=f.astype(np.float32), reference=(0.5, 0.5))
    pb = basis.values(rng.uniform(0, 1, proj_z.size), rng.uniform(0, 1, proj_z.size))
    return geom, model, rows, pb, sp, sw, slices_z


def run(quick: bool = False, repeats: int = 3, scene="demo", runtime=None) -> dict:
    """G updates/s of the motion-compensated and the static backprojector on ``scene``'s geometry
    (module docstring); ``quick``: 2 slices instead of 4. At least :data:`MIN_REPEATS` repeats
    (a launch takes well under a second), so the figures are medians also under ``--quick``."""
    rt = runtime or get_runtime()
    repeats = max(MIN_REPEATS, int(repeats))
    geom, model, rows, pb, sp, sw, zs = synthetic_case(2 if quick else 4, scene=scene)
    fov = int(geom.fov_mask().sum())
    mc_updates = fov * int(((sp >= 0) & (sw > 0)).sum())
    static_updates = fov * geom.n_views * STATIC_BATCH
    sino = np.random.default_rng(1).normal(size=(STATIC_BATCH, geom.n_views, geom.n_cols)).astype(np.float32)
    target = (0.3, 0.6)
    times = {"mc": [], "static": []}
    loads = []
    with MCBackprojector(rows, pb, model, zs, geom, runtime=rt) as bp:
        fns = {"mc": lambda: bp(sp, sw, target), "static": lambda: fbp.backproject(sino, geom, runtime=rt)}
        for fn in fns.values():  # warm-up: builds, PoCL's specialisation, first-touch buffers
            fn()
        for _ in range(repeats):
            loads.append(load1())
            for k, fn in fns.items():
                times[k].append(timed(fn))
        shape = {"lanes": bp.lanes, "local_size": list(bp.local_size), "view_chunk": bp.view_chunk}
    med = {k: float(np.median(v)) for k, v in times.items()}
    mc_g = mc_updates / med["mc"] / 1e9
    st_g = static_updates / med["static"] / 1e9
    return {"scene": scene if isinstance(scene, str) else scene.name, "device": rt.description,
            "image": [geom.ny, geom.nx], "views": geom.n_views, "cols": geom.n_cols, "slices": len(zs),
            "slots": int(sp.shape[2]), "basis": model.basis.size,
            "static_batch": STATIC_BATCH, "mc_updates": mc_updates, "static_updates": static_updates,
            "seconds": {k: [round(t, 4) for t in v] for k, v in times.items()}, "median_s": med,
            "mc_gups": mc_g, "static_gups": st_g, "ratio": mc_g / st_g, "goal_ratio": GOAL_RATIO,
            "repeats": repeats, "load_average_1min_repeats": loads, **shape}


def report_lines(r: dict | None) -> list[str]:
    """The row's lines of the bench report."""
    if not r:
        return []
    goal = "met" if r["ratio"] >= r["goal_ratio"] else "NOT met"
    return [f"   backprojection kernels ({r['scene']} geometry, {r['image'][1]}^2, {r['views']} views x {r['cols']} "
            f"columns; {r['device']}; median of {r['repeats']}, load {r['load_average_1min_repeats']}): "
            f"motion-compensated {r['mc_gups']:.3f} G updates/s ({r['slices']} slices, {r['slots']} slots, "
            f"NB = {r['basis']}, {r['lanes']} lanes, local {r['local_size'][0]}x{r['local_size'][1]}) against "
            f"static {r['static_gups']:.3f} ({r['static_batch']} images): x{r['ratio']:.3f} "
            f"(goal >= x{r['goal_ratio']:g}: {goal})",
            "   (updates inside the FOV: (voxel, row read) for motion-compensated, (voxel, view, image) for static; "
            "end to end, host to host)"]
