"""``clrecon scenes``: what each built-in scene will simulate and reconstruct, and what it costs."""

from __future__ import annotations

import functools

import numpy as np

from clrecon.config.scene import builtin_scene_names, load_scene
from clrecon.core.errors import SceneError
from clrecon.outputs.volumes import resolve_compression
from clrecon.pipeline import evaluate, slabs
from clrecon.pipeline.stages import truth as truth_stage
from clrecon.pipeline.variants import noise_variants
from clrecon.reconstruction import fbp as fbp_mod
from clrecon.reconstruction import reconstruct
from clrecon.reconstruction.interpolation import METHODS
from clrecon.reconstruction.iterative import method as mcir
from clrecon.reconstruction.motion import memory as mc_memory
from clrecon.reconstruction.motion import method as mc_method
from clrecon.reconstruction.rebin import slice_window_mm
from clrecon.reconstruction.reconstruct import KEEP_PLANS_BYTES, Targets, slab_bytes_per_slice, slices_per_slab
from clrecon.scan.table import cached_projection_table, recorded_content
from clrecon.simulation.measured import memory_bytes as measured_memory_bytes

GiB = 1024 ** 3
#: Modelled compression of the projection store and its units (LZF + shuffle on float32 line
#: integrals; measured 2.38x on paper-p002's 160 689 projections (34.5 GiB raw, 14.5 GiB
#: stored), 2.0-2.1x on thorax-like test data: the lower figure, so the model errs high).
PROJECTION_RATIO = 2.0
#: Modelled compression of the volumes and their units (LZF + shuffle on HU volumes, one chunk
#: per slice; measured on paper-p010 whole in float16, the zero outside the field of view
#: included: 3.34x, 30.1 GB of volumes and truths in 9.02 GB of units; float32 and tiny grids
#: compress less: 2.0 errs high on the paper scenes).
VOLUME_RATIO = 2.0


def scene_costs(scene) -> dict:
    """Sizes in bytes and counts: projections per pitch, store, volumes, peak memory estimate."""
    return run_costs(scene)


def kept_plans_bytes(scene, methods, targets: Targets, slices_z, pitches) -> int:
    """Bytes of the plans the planning pass keeps for one pitch's reconstruction (the larger pitch's),
    at most ``KEEP_PLANS_BYTES``: the plan of the slice with the most candidate rows
    (:func:`clrecon.pipeline.slabs.candidates_per_slice`, the probe of ``plan_slabs``), made for the
    methods the run plans (:func:`clrecon.pipeline.slabs.planned_methods`), times the slices (a plan's
    arrays are as wide as its widest slice's; measured against the plans of whole runs in
    docs/results/code-history.md "The plans the pre-flight counts"). The scan's whole table: on a
    measured scan a slice may plan fewer rows (those with usable traces), never more."""
    fixed = slabs.planned_methods(methods)
    z = tuple(float(v) for v in np.asarray(slices_z, np.float64).ravel())
    if not fixed or not z:
        return 0
    content = tuple(sorted(recorded_content(scene).items()))
    worst = max(_widest_plan_bytes(scene, float(p), fixed, targets, z, content) for p in pitches)
    return int(min(KEEP_PLANS_BYTES, worst * len(z)))


@functools.lru_cache(maxsize=8)
def _widest_plan_bytes(scene, pitch: float, fixed: tuple, targets: Targets, z: tuple, content: tuple) -> int:
    """:func:`kept_plans_bytes`' probe at one pitch: the plan bytes of the slice of ``z`` (mm) with the
    most candidate rows. Kept per process: a run's driver choice and its pre-flight ask for the same
    (``content``, the recorded inputs' digests, is only part of the key, as in
    :func:`clrecon.scan.table.cached_projection_table`)."""
    cfg = reconstruct.ReconstructionConfig.from_scene(scene)
    table = cached_projection_table(scene, pitch)
    zs = np.asarray(z, np.float64)
    d = int(np.argmax(slabs.candidates_per_slice(table, zs, cfg)))
    return reconstruct.plan_bytes(reconstruct.plan(cfg, table, zs[d:d + 1], targets, fixed))


def run_costs(scene, methods=None, n_cardiac=None, n_resp=None, slices_z=None, pitches=None,
              overlap: bool = True, targets: Targets | None = None, truths_computed: bool = True) -> dict:
    """:func:`scene_costs` of one run: the scene narrowed to ``methods``, targets, slices, ``pitches``.

    ``targets``: the run's (default: the scene's first ``n_cardiac`` phases and ``n_resp``
    amplitudes); the plans it keeps are probed with them (:func:`kept_plans_bytes`).
    ``truths_computed``: False where the truth cache holds them all (the truth stage's working set,
    beside the reconstruction, is then left out).

    ``projections_needed`` models the projections the slices use (those within the SSRB slice
    window of a slice, plus one rotation); ``volume_bytes`` is what ``volumes.h5`` holds: the
    5D methods on the full target grid, r4dct once per amplitude and helical once (they stand
    for every cardiac phase / every target), in ``recon.volume_dtype``. ``mcir_slab_bytes``: the
    largest ``mcir`` slab's modelled bytes (0 without ``mcir``).
    """
    sc, rc = scene.scanner, scene.recon
    methods = tuple(methods or rc.methods)
    pitches = tuple(pitches or scene.scan.pitches)
    n_c = len(scene.cardiac_targets) if n_cardiac is None else n_cardiac
    n_r = len(scene.resp_targets) if n_resp is None else n_resp
    nz = rc.nz if slices_z is None else len(slices_z)
    n_proj = {p: scene.scan.projection_count(sc, p) for p in pitches}
    proj_bytes = sc.n_rows * sc.n_cols * 4
    n_targets = n_c * n_r
    item = 2 if rc.volume_dtype == "float16" else 4
    vol_bytes = n_targets * nz * rc.ny * rc.nx * item
    n_var = len(noise_variants(scene))
    grid = {m: METHODS[m].target_grid for m in methods}
    # full-grid volume equivalents: a 5D method 1, r4dct 1 / n_c, helical 1 / n_targets
    per_pitch_variant = sum({"resp": 1.0 / n_c, "none": 1.0 / n_targets}.get(g, 1.0) for g in grid.values())
    n_vols = len(pitches) * n_var * per_pitch_variant + 2
    radius = min(sc.fov_radius_mm, rc.fov_radius_mm)
    window = slice_window_mm(sc, radius)
    z_extent = (max(slices_z) - min(slices_z)) if slices_z is not None and len(slices_z) else (nz - 1) * rc.slice_mm
    needed = {p: int(min(n_proj[p], ((z_extent + 2 * window) / scene.scan.feed_mm(sc, p) + 1)
                         * sc.views_per_rotation)) for p in pitches}
    # peak, as run.py walks it: one 512-projection read chunk (+ its noisy copy), one slab (its
    # rebinned rows of every variant, one method's images and the finished slab being written,
    # sized by reconstruct.slab_slices to at most SLAB_BYTES; the plan is part of that budget
    # there, not modelled here), the plans
    # kept between the planning pass and the reconstruction (kept_plans_bytes), one launch of
    # sinograms, and the truth
    def slab_of(feed_mm):  # the rebinned rows per slice and the reconstruction's slab (slices) at a feed
        rows = 2 * window / feed_mm * sc.views_per_rotation
        per = slab_bytes_per_slice(rows, sc.n_cols, n_var, n_targets, rc.ny, rc.nx, volume_itemsize=item)
        return rows, per, min(nz, slices_per_slab(per))

    rows_per_slice, per_slice, slab = slab_of(min(scene.scan.feed_mm(sc, p) for p in pitches))
    chunk = 512 * proj_bytes * (1 + n_var)
    if targets is None:
        targets = Targets(cardiac=tuple(scene.cardiac_targets)[:n_c], resp=tuple(scene.resp_targets)[:n_r])
    plans = kept_plans_bytes(scene, methods, targets,
                             reconstruct.slice_positions(scene) if slices_z is None else slices_z, pitches)
    slab_sinos = 2 * 32 * sc.views_per_rotation * sc.n_cols * 4
    buffers = device_buffers(scene, rows_per_slice)
    # one launch's images twice: the device buffer (host memory on a CPU device) and its host copy
    launch_images = 2 * buffers["the images of one backprojection launch"]
    # the read chunk lives while the slab's rows are made, the images, their launch buffers and the
    # finished slab being written while they are backprojected: the rows and plans are under both
    images = reconstruct.slab_images_bytes_per_slice(n_targets, rc.ny, rc.nx, item)
    peak = (slab * (per_slice - images) + max(chunk, slab * images + slab_sinos + launch_images) + plans
            + 2 * nz * rc.ny * rc.nx * 4)
    # ``overlap``: an executor that overlaps the stages (local, dask; not serial)
    if overlap and truths_computed:  # the truths beside the reconstruction: one target's working set on top
        peak += truth_stage.working_bytes(nz, sc.views_per_rotation, sc.n_cols, rc.ny, rc.nx)
    # the metrics stage, after the reconstruction: in each of its processes the LV region masks of
    # every target (bool, when r4dct's respiratory-only study runs), one target's truth and volume in
    # float32 and their difference; a second process's interpreter and imports about 0.4 GB
    n_keys = len(pitches) * n_var * len(methods)
    n_proc = evaluate.process_count(int(n_keys * vol_bytes))
    target_vox = nz * rc.ny * rc.nx
    regions = n_targets * target_vox if any(g == "resp" for g in grid.values()) else 0
    metrics_peak = n_proc * (regions + 3 * target_vox * 4) + (n_proc - 1) * 0.4e9
    if "mc" in methods or mcir.NAME in methods:  # mc's model (mcir's too), at its worst pitch, after the reconstruction
        # of its pitch: the pitch's plans (its input) stay; the truths are done (both stages come after
        # ``truth`` in the graph) (docs/results/code-history.md "The mc working set against the measured peak")
        held = plans
        knobs = rc.mc_knobs
        # the first pass's unit files hold the pitch's reconstruction slabs
        peak = max(peak, held + max(mc_memory.working_bytes(sc, window, knobs, z_extent, scene.scan.feed_mm(sc, p),
                                                            n_var, n_c, n_r, nz, rc.ny, rc.nx, n_proj[p],
                                                            slab_of(scene.scan.feed_mm(sc, p))[2],
                                                            voxel_mm=rc.voxel_mm)
                                    for p in pitches))
    mcir_slab = 0
    if mcir.NAME in methods:  # mcir's slabs after the model (the plans, every variant's model and what mc's stage left)
        z_run = reconstruct.slice_positions(scene) if slices_z is None else slices_z
        n_basis = mc_method.basis_of(rc.mc, n_c, n_r).size
        models = n_var * mc_memory.model_bytes(rc.mc, n_c, n_r, nz, rc.ny, rc.nx, voxel_mm=rc.voxel_mm)
        mcir_slab = max(mcir.run_memory_bytes(sc, rc, rc.mcir, radius, cached_projection_table(scene, p), z_run,
                                              n_basis) for p in pitches)
        peak = max(peak, held + models + mcir_slab + mc_memory.RESIDUE_BYTES)
    peak = max(peak, metrics_peak)
    if getattr(scene, "measured", False):  # the import's own needs and the process baseline (issue 35)
        peak += measured_memory_bytes(scene)
    out = {"projections": n_proj, "projections_needed": needed, "store_bytes": sum(n_proj.values()) * proj_bytes,
           "needed_store_bytes": sum(needed.values()) * proj_bytes, "projection_bytes": proj_bytes,
           "volume_bytes": int(vol_bytes * n_vols), "n_volumes": round(n_vols, 3), "n_targets": n_targets,
           "recon_bytes_per_pitch": int(vol_bytes * n_var * per_pitch_variant), "truth_bytes": int(2 * vol_bytes),
           "largest_dataset_bytes": int(vol_bytes), "peak_memory_bytes": int(peak), "slab_slices": slab,
           "volume_compression": resolve_compression(rc.volume_compression, int(vol_bytes * n_vols)),
           "device_buffers": buffers, "mcir_slab_bytes": int(mcir_slab)}
    out.update(disk_model(out))
    return out


def device_buffers(scene, rows_per_slice: float) -> dict[str, int]:
    """Bytes of the largest single device buffers the run cannot split further, by what they hold.

    Each must fit the device's largest allocation (``CL_DEVICE_MAX_MEM_ALLOC_SIZE``), which the
    pre-flight checks before any work (:func:`clrecon.pipeline.preflight.check`): one backprojection
    launch's images (``groups_per_launch`` x 16 images of ny x nx float32,
    :func:`clrecon.reconstruction.fbp.groups_per_launch`) and interleaved sinograms (V x (n_cols + 2)
    x 16 per group), one slice's rebinned candidate rows (``rows_per_slice`` x n_cols; a slab is
    halved until its rows fit, one slice cannot be) and one projection (n_rows x n_cols).
    """
    sc, rc = scene.scanner, scene.recon
    geom = fbp_mod.FanBeamGeometry.from_scene(scene)
    groups, lanes = fbp_mod.groups_per_launch(geom), fbp_mod.BATCH_LANES
    return {"the images of one backprojection launch": groups * lanes * rc.ny * rc.nx * 4,
            "the interleaved sinograms of one backprojection launch": groups * geom.n_views * (geom.n_cols + 2)
            * lanes * 4,
            "one slice's rebinned rows": int(rows_per_slice + 1) * sc.n_cols * 4,
            "one projection": sc.n_rows * sc.n_cols * 4}


def disk_model(c: dict, existing: dict | None = None, present_out: int = 0, truth_copies: bool = False) -> dict:
    """Modelled disk growth of a run, walked as it happens (docs/data-flow.md, "Disk").

    Per pitch, in order: its projection units (compressed) and the store assembled from them
    coexist (``existing[pitch]`` = bytes of an unfinished store already there, copied to
    ``.partial``; a complete store: ``None`` = nothing to do), then the store keeps its new
    projections and that pitch's reconstruction units are written; at the end the truth units.
    The units are the result (``volumes.h5`` maps them in place: :class:`clrecon.outputs.volumes.VolumeWriter`),
    so the volumes have no assembly transient. ``present_out``: bytes of units and dataset files an interrupted run
    left (not written again). ``truth_copies``: the truth cache is on another file system
    (it copies the truths instead of linking them). Compressed sizes: the raw bytes over
    :data:`PROJECTION_RATIO` and (``c["volume_compression"] == "lzf"``, the default when absent)
    :data:`VOLUME_RATIO`; uncompressed volumes count raw.

    Returns bytes: ``cache_disk`` (the projection-store folder's peak growth), ``out_disk``
    (the run directory's: the volumes) and ``disk_peak`` (both on one file
    system: the largest growth at any instant, which is less than their sum since the store's
    assembly transient is over before the volumes are written).
    """
    existing = existing or {}
    vol_ratio = VOLUME_RATIO if c.get("volume_compression", "lzf") == "lzf" else 1.0
    grown = cache_peak = cache_grown = peak = 0.0
    for p, n_needed in c["projections_needed"].items():
        old = existing.get(p, 0)
        if old is None:  # complete store: nothing written
            grown += c["recon_bytes_per_pitch"] / vol_ratio
            continue
        new = n_needed * c["projection_bytes"] / PROJECTION_RATIO
        peak = max(peak, grown + old + 2 * new)
        cache_peak = max(cache_peak, cache_grown + old + 2 * new)
        grown += new + c["recon_bytes_per_pitch"] / vol_ratio
        cache_grown += new
    truths = c["truth_bytes"] / vol_ratio
    out = max(0.0, c["volume_bytes"] / vol_ratio - present_out)
    peak = max(peak, cache_grown + out)
    if truth_copies:
        cache_peak = max(cache_peak, cache_grown + truths)
        peak += truths
    return {"cache_disk": int(cache_peak), "out_disk": int(out), "disk_peak": int(peak)}


def detector_label(sc) -> str:
    """``900x64`` (flat), ``736x32 cyl`` (cylindrical), ``+phi+z`` with a flying focal spot."""
    label = f"{sc.n_cols}x{sc.n_rows}"
    if sc.detector != "flat":
        label += " cyl"
    if sc.flying_focal_spot != "none":
        label += f" {sc.flying_focal_spot}"
    return label


def describe_scenes() -> str:
    lines = [f"{'scene':<12} {'pitch':>6} {'projections':>12} {'scan s':>7} {'detector':>16} {'volume':>16} "
             f"{'targets':>7} {'store GiB':>9} {'volumes GiB':>11} {'peak mem GiB':>12} {'peak disk GiB':>13}"]
    for name in builtin_scene_names():
        try:
            s = load_scene(name)
        except SceneError as e:  # a stress scene that is invalid by design (stress-high-pitch)
            lines.append(f"{name:<12} invalid: {str(e).split(': ', 1)[-1]}")
            continue
        c = scene_costs(s)
        sc, rc = s.scanner, s.recon
        for i, p in enumerate(s.scan.pitches):
            lines.append(
                f"{name if i == 0 else '':<12} {p:>6.3f} {c['projections'][p]:>12,} "
                f"{s.scan.duration_s(sc, p):>7.1f} {detector_label(sc):>16} "
                f"{f'{rc.nx}x{rc.ny}x{rc.nz}':>16} {c['n_targets'] if i == 0 else '':>7} "
                f"{c['projections'][p] * sc.n_rows * sc.n_cols * 4 / GiB:>9.2f} "
                f"{c['volume_bytes'] / GiB if i == 0 else 0:>11.2f} "
                f"{c['peak_memory_bytes'] / GiB if i == 0 else 0:>12.2f} "
                f"{c['disk_peak'] / GiB if i == 0 else 0:>13.2f}")
        if s.description:
            lines.append(f"{'':<12} {s.description}")
    lines.append("detector: columns x rows, cyl = cylindrical (equiangular) arc, then the flying focal spot (phi, z)")
    lines.append("store: noise-free line integrals, float32 before compression, all projections (a run stores only"
                 " those its slices use); volumes: every method x pitch x noise variant + ground truth + phantom"
                 " (r4dct once per amplitude, helical once), in recon.volume_dtype (paper scenes: float16), before"
                 " compression; peak disk: the modelled most the store folder and the run directory hold at once"
                 " (one file system, every projection and slice, transients included, compressed: store / 2.0,"
                 " volumes / 2.0)")
    return "\n".join(lines)
