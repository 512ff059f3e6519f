"""5DCT reconstruction: plan weights, stream the store slab by slab, rebin, interpolate, FBP.

Stages 5-8 of the pipeline, for one scan (one pitch):

1. **Plan** (no projection data needed): for each slice, the SSRB candidates (every turn
   whose rows cover the slice, :func:`clrecon.reconstruction.rebin.candidates`), grouped by view; for each
   method the phase-space weights per (slice, view, target)
   (:func:`clrecon.reconstruction.interpolation.weights.method_weights`). The union of the (projection, slice) pairs
   with a non-zero weight is all the data the reconstruction will ever touch, so the
   simulator only needs to project those projections.
2. **Stream**: projections are read from the store in index (= time = z) order, in chunks;
   each chunk is rebinned only for the pairs it owns (:func:`clrecon.reconstruction.rebin.ssrb_rows`).
   Noise, if asked for, is applied to the chunk once per read (seeded per projection).
3. **Interpolate**: :func:`clrecon.reconstruction.interpolation.apply.apply_padded_interleaved` turns
   rebinned rows into one fan-beam sinogram per (slice, target).
4. **FBP**: :func:`clrecon.reconstruction.fbp.fbp_hu`, batched over slices and targets.

Slices are processed in slabs in z order so that only one slab's rebinned rows are held.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from clrecon.core.conventions import voxel_coords
from clrecon.core.detector import spot_shift_in_frame
from clrecon.core.errors import ClreconError
from clrecon.core.resources import rss_mark
from clrecon.core.runtime import aligned_empty, get_runtime
from clrecon.core.stage_times import StageTimes
from clrecon.reconstruction import fbp as fbp_mod
from clrecon.reconstruction import interpolation, parallel_fbp, rebin
from clrecon.reconstruction.interpolation import weights as interpolate
from clrecon.scan.table import ProjectionTable
from clrecon.simulation import noise


@dataclass(frozen=True)
class Targets:
    """Target grid: ``cardiac`` (n_c,) phases in [0,1) x ``resp`` (n_r,) amplitudes in [0,1]."""

    cardiac: tuple
    resp: tuple

    @property
    def pairs(self) -> np.ndarray:
        """(n_c * n_r, 2) array of (c*, a*), cardiac-major: row i*n_r + j = (cardiac[i], resp[j])."""
        cc, rr = np.meshgrid(np.asarray(self.cardiac, float), np.asarray(self.resp, float), indexing="ij")
        return np.stack([cc.ravel(), rr.ravel()], axis=1)

    @property
    def shape(self) -> tuple:
        return (len(self.cardiac), len(self.resp))


@dataclass(frozen=True, kw_only=True)
class ReconstructionConfig:
    """What the reconstruction of one scan needs, and nothing else.

    ``scanner`` (detector and views, :class:`clrecon.config.scene.ScannerConfig`),
    ``object_radius_mm`` (the reconstruction circle SSRB must serve, mm), ``fbp`` (the
    fan-beam geometry), ``filter`` (ramp window), ``mu_water_per_mm`` (HU conversion),
    ``noise`` (:class:`clrecon.config.scene.NoiseConfig`, for the noisy variant), and the
    interpolation options: ``kappa``, ``sigma`` (local-linear kernel widths), ``use_cardiac`` /
    ``use_resp`` (which phase axes exist), ``resp_bin_width`` (the bin method's amplitude bin),
    ``extrapolate`` (local linear's plain fit), ``local_linear_points`` / ``local_linear_count``
    (local linear's neighbours: ``count`` per quadrant or ``count`` nearest), and ``max_turns``
    (0: every candidate turn in the SSRB window; N > 0: the N nearest in z per (slice, view),
    :func:`limit_turns`, for every method), and ``backprojector``
    (:mod:`clrecon.reconstruction.backprojectors`: ``"direct"`` fan-beam FBP, or
    ``"parallel-rebin"``, :mod:`clrecon.reconstruction.parallel_fbp`).
    """

    scanner: object
    object_radius_mm: float
    fbp: fbp_mod.FanBeamGeometry
    filter: str
    mu_water_per_mm: float
    noise: object
    kappa: float
    sigma: float
    use_cardiac: bool
    use_resp: bool
    resp_bin_width: float
    extrapolate: bool
    local_linear_points: str = "quadrants"
    local_linear_count: int = 2
    #: cardiac axis factor s in the phase-space distance and the Delaunay triangulation
    #: (dimensionless; ``recon.cardiac_distance_scale``), 1: unscaled
    cardiac_distance_scale: float = 1.0
    max_turns: int = 0
    backprojector: str = "direct"
    #: candidate window half-width (mm), 0: the SSRB-exact window (``recon.candidate_window_mm``)
    candidate_window_mm: float = 0.0
    #: ``cv_tuned``'s chosen kernel ``(method, ((knob, value), ...))`` (set by the run from the
    #: truth-free cross-validation, :mod:`clrecon.evaluation.truth_free`); None: not chosen
    tuned: tuple | None = None

    @classmethod
    def from_scene(cls, scene) -> ReconstructionConfig:
        rc = scene.recon
        return cls(scanner=scene.scanner, object_radius_mm=object_radius_mm(scene),
                   fbp=fbp_mod.FanBeamGeometry.from_scene(scene), filter=rc.filter,
                   mu_water_per_mm=scene.phantom.mu_water_per_mm, noise=scene.noise, kappa=rc.kappa,
                   sigma=rc.sigma, use_cardiac=scene.has_cardiac, use_resp=scene.has_respiratory,
                   resp_bin_width=1.0 / rc.resp_bins, extrapolate=rc.local_linear_extrapolate,
                   local_linear_points=rc.local_linear_points, local_linear_count=rc.local_linear_count,
                   max_turns=rc.max_turns, backprojector=rc.backprojector,
                   candidate_window_mm=rc.candidate_window_mm, cardiac_distance_scale=rc.cardiac_distance_scale)


def slice_positions(scene, slice_range: tuple | None = None) -> np.ndarray:
    """z (mm) of the reconstructed slices, (nz,), centred on the scan centre; optional [i0, i1) range."""
    rc = scene.recon
    z = voxel_coords(rc.nz, rc.slice_mm, scene.scan.z_centre_mm)
    if slice_range is not None:
        i0, i1 = slice_range
        z = z[i0:i1]
    return z


def object_radius_mm(scene) -> float:
    """Radius of the region whose rays SSRB must serve: the reconstruction circle."""
    return min(scene.scanner.fov_radius_mm, scene.recon.fov_radius_mm)


@dataclass
class MethodWeights:
    """One method's interpolation weights over a set of slices (what :func:`plan` makes per method):
    arrays (S, V, T, K) of (slice, view, target, candidate)."""

    proj_index: np.ndarray  # int64 global projection index
    weight: np.ndarray      # float64, 0 in unused slots
    targets_shape: tuple    # (n_c, n_r) of the targets actually solved (r4dct: (1, n_r), helical: (1, 1))
    branch: np.ndarray | None = None  # int8 (S, V, T) branch taken (barycentric: Weights.branch), else None


@dataclass
class SlabWeights:
    """Every planned method's weights over one set of slices (a slab; :func:`plan`'s result): the
    slices' z (S,) mm, ``methods`` name -> :class:`MethodWeights`, and the planning's seconds."""

    slices_z: np.ndarray
    methods: dict = field(default_factory=dict)  # name -> MethodWeights
    seconds: float = 0.0
    #: name -> seconds of planning that method: its weights, plus an equal share of the shared
    #: candidate search (the whole plan's ``seconds`` is their sum)
    method_seconds: dict = field(default_factory=dict)

    def needed_pairs(self):
        """Unique (projection, slice) pairs with a non-zero weight, sorted by projection."""
        keys = []
        for mp in self.methods.values():
            S = mp.proj_index.shape[0]
            sl = np.broadcast_to(np.arange(S)[:, None, None, None], mp.proj_index.shape)
            nz = mp.weight != 0
            keys.append(mp.proj_index[nz].astype(np.int64) * S + sl[nz])
        if not keys:
            return np.zeros(0, np.int64), np.zeros(0, np.int64)
        u = np.unique(np.concatenate(keys))
        S = len(self.slices_z)
        return u // S, u % S

    def needed_projections(self, n_total: int) -> np.ndarray:
        proj, _ = self.needed_pairs()
        mask = np.zeros(n_total, bool)
        mask[proj] = True
        return mask


def plan(cfg: ReconstructionConfig, table: ProjectionTable, slices_z: np.ndarray, targets: Targets,
         methods) -> SlabWeights:
    """Weights of every method for every (slice, view, target); see the module docstring.

    Raises :class:`clrecon.core.errors.ClreconError` naming the slice and view when a (slice, view)
    has no SSRB candidate (slice outside the scanned range, or pitch too high for the rows).
    """
    t0 = time.perf_counter()
    sc = cfg.scanner
    nv = sc.views_per_rotation
    p = SlabWeights(slices_z=np.asarray(slices_z, float))
    groups = rebin.candidate_groups(table, p.slices_z, sc, cfg.object_radius_mm, cfg.candidate_window_mm)
    if groups.empty.any():
        g = int(np.flatnonzero(groups.empty)[0])
        z = p.slices_z[g // nv]
        zk = table.source_z_mm
        raise ClreconError(
            f"slice z = {z:.2f} mm, view {g % nv}: no projection covers it (scan covers source z "
            f"{zk.min():.1f}..{zk.max():.1f} mm with an SSRB window of "
            f"+-{rebin.slice_window_mm(sc, cfg.object_radius_mm):.2f} mm); reduce recon.nz/slice_mm or the pitch")
    if cfg.max_turns > 0:
        groups = limit_turns(groups, cfg.max_turns)
    c = table.cardiac_phase[groups.row]
    a = table.resp_amplitude[groups.row]
    opts = weight_options(cfg, targets)
    S = len(p.slices_z)
    t_shared = time.perf_counter() - t0
    for m in methods:
        t1 = time.perf_counter()
        tg, shape = method_targets(m, targets)
        w = interpolate.batch_weights(m, c, a, groups.offsets, tg, dz=groups.dz_mm, **opts)
        G, T, K = w.index.shape
        proj = groups.projection[w.index].reshape(S, nv, T, K)
        weight = np.where(w.weight != 0, w.weight, 0.0).reshape(S, nv, T, K)
        branch = None if w.branch is None else w.branch.reshape(S, nv, T)
        p.methods[m] = MethodWeights(proj_index=proj, weight=weight, targets_shape=shape, branch=branch)
        p.method_seconds[m] = time.perf_counter() - t1
    for m in p.method_seconds:
        p.method_seconds[m] += t_shared / len(p.method_seconds)
    p.seconds = time.perf_counter() - t0
    return p


def candidate_groups_of(cfg: ReconstructionConfig, table: ProjectionTable, slices_z) -> rebin.CandidateGroups:
    """The candidates :func:`plan` uses for ``slices_z``: the candidate window, then ``max_turns``."""
    groups = rebin.candidate_groups(table, np.asarray(slices_z, float), cfg.scanner, cfg.object_radius_mm,
                                    cfg.candidate_window_mm)
    return limit_turns(groups, cfg.max_turns) if cfg.max_turns > 0 else groups


def limit_turns(groups: rebin.CandidateGroups, max_turns: int) -> rebin.CandidateGroups:
    """Only the ``max_turns`` candidates nearest in z (smallest |slice_z - z_k|) of each (slice, view).

    A view's candidates are one per turn, so this keeps the ``max_turns`` turns nearest the
    slice (ties: the earlier projection). The kept candidates stay in projection order; a
    group with fewer keeps them all. ``max_turns <= 0`` returns ``groups`` unchanged.
    """
    if max_turns <= 0:
        return groups
    counts = groups.counts
    n = groups.row.size
    g = np.repeat(np.arange(counts.size), counts)
    pos = np.arange(n)
    order = np.lexsort((pos, np.abs(groups.dz_mm), g))  # by group, then |dz|, then projection order
    rank = np.empty(n, np.int64)
    rank[order] = pos - groups.offsets[g[order]]
    keep = rank < max_turns
    offsets = np.zeros_like(groups.offsets)
    np.cumsum(np.bincount(g[keep], minlength=counts.size), out=offsets[1:])
    return rebin.CandidateGroups(offsets=offsets, row=groups.row[keep], projection=groups.projection[keep],
                                 dz_mm=groups.dz_mm[keep], slice_z_mm=groups.slice_z_mm,
                                 views_per_rotation=groups.views_per_rotation)


def method_targets(method: str, targets: Targets) -> tuple[np.ndarray, tuple]:
    """The targets ``method`` is solved for: ``(pairs (T, 2), (n_c, n_r))`` by its ``target_grid``.

    ``"5d"``: every (c*, a*); ``"resp"`` (cardiac-blind, e.g. r4dct): one per amplitude, shape
    (1, n_r), the volume then standing for every cardiac phase; ``"none"`` (phase-blind, e.g.
    helical): the first target only, shape (1, 1), the volume standing for every target.
    """
    m = interpolation.METHODS.get(method)  # an unknown name is batch_weights' error
    if m is not None and m.target_grid == "resp":
        return targets.pairs[:len(targets.resp)], (1, len(targets.resp))
    if m is not None and m.target_grid == "none":
        return targets.pairs[:1], (1, 1)
    return targets.pairs, targets.shape


def weight_options(cfg: ReconstructionConfig, targets: Targets) -> dict:
    """Keyword options of :func:`clrecon.reconstruction.interpolation.weights.batch_weights`."""
    return dict(kappa=cfg.kappa, sigma=cfg.sigma, use_cardiac=cfg.use_cardiac, use_resp=cfg.use_resp,
                cardiac_bin_width=_cardiac_bin_width(targets), resp_bin_width=cfg.resp_bin_width,
                extrapolate=cfg.extrapolate, local_linear_points=cfg.local_linear_points,
                local_linear_count=cfg.local_linear_count, cardiac_distance_scale=cfg.cardiac_distance_scale,
                tuned=cfg.tuned)


def _cardiac_bin_width(targets: Targets) -> float:
    c = np.sort(np.asarray(targets.cardiac, float))
    if len(c) < 2:
        return 0.2
    gaps = np.diff(np.concatenate([c, [c[0] + 1.0]]))
    return float(np.min(gaps))


def reconstruct(cfg: ReconstructionConfig, store, plan_: SlabWeights, variants=("noise-free",), rt=None,
                times: StageTimes | None = None, progress=None, chunk: int = 512, on_slab=None,
                slab_size: int | None = None, max_buffer_bytes: int | None = None) -> dict:
    """Reconstruct every planned method and noise variant.

    Parameters
    ----------
    store : object with ``read_indices(indices, noisy=False, rows=(lo, hi)) -> (m, hi - lo, C) float32``
        and ``table`` (:class:`clrecon.simulation.store.ProjectionStore`).
    variants : sequence of ``"noise-free"`` / ``"noisy"``.
    progress : optional counter (``update(n)``), advanced by a slab's slice count as each of its
        (variant, method) volumes is done: its total is slices x variants x methods.
    on_slab : optional callback ``(slice_slice, {(variant, method): (n_c, n_r, s, ny, nx)})`` that
        receives each slab's volume of each (variant, method) as soon as it is finished (to write
        it out and free memory: only one method's slab of images is held at a time). If None,
        whole volumes are returned.
    slab_size : slices per slab; default :func:`slab_slices` of the plan.
    max_buffer_bytes : the largest single device buffer (bytes); default the device's
        ``CL_DEVICE_MAX_MEM_ALLOC_SIZE`` (:attr:`Runtime.max_alloc_bytes`). A slab whose rebinned
        rows of one variant (``pairs x n_cols`` float32, uploaded as one buffer) would exceed it
        is halved until they fit (slab size never changes the numbers); a single slice that does
        not fit raises :class:`SlabTooLarge`.

    Returns
    -------
    dict ``{(variant, method): volume (n_c, n_r, nz, ny, nx) float32 HU}`` (empty if ``on_slab``).
    """
    times = times or StageTimes()
    geom = cfg.fbp
    S = len(plan_.slices_z)
    if slab_size is None:
        slab_size = slab_slices(cfg, plan_, len(tuple(variants)))
    results: dict = {}
    if rt is None:
        rt = get_runtime()
    cap = int(rt.max_alloc_bytes if max_buffer_bytes is None else max_buffer_bytes)
    row_bytes = 4 * cfg.scanner.n_cols
    pending = [(s0, min(S, s0 + slab_size)) for s0 in range(0, S, slab_size)]
    while pending:
        s0, s1 = pending.pop(0)
        t0 = time.perf_counter()
        sub, ukeys = _slab_pairs(plan_, s0, s1)
        times.add("plan", time.perf_counter() - t0)
        if len(ukeys) * row_bytes > cap:
            if s1 - s0 == 1:
                raise SlabTooLarge(
                    f"slice {s0}: its {len(ukeys)} rebinned rows x {cfg.scanner.n_cols} columns need one device "
                    f"buffer of {len(ukeys) * row_bytes / 2**30:.2f} GiB, above the device's largest allocation "
                    f"({cap / 2**30:.2f} GiB, CL_DEVICE_MAX_MEM_ALLOC_SIZE); use fewer targets or methods per run, "
                    f"or a device with a larger allocation limit")
            mid = (s0 + s1) // 2  # halve the slab: both halves again checked against the cap
            pending[:0] = [(s0, mid), (mid, s1)]
            times.count("slab_splits", 1)
            continue

        def emit(key, vol, s0=s0, s1=s1):
            rss_mark(f"reconstruct: slices {s0}..{s1 - 1} of {key} ({vol.nbytes / 1e9:.3f} GB)")
            if on_slab is not None:
                on_slab(slice(s0, s1), {key: vol})
                return
            if key not in results:
                results[key] = np.zeros(vol.shape[:2] + (S,) + vol.shape[3:], np.float32)
            results[key][:, :, s0:s1] = vol

        _reconstruct_slab(cfg, store, plan_, s0, s1, variants, geom, rt, times, chunk, progress, emit, sub, ukeys)
    return results


#: Memory for one slab of the reconstruction (bytes): its plan, its rebinned rows of every
#: variant, and one method's images (the slab-size rule of :func:`slab_slices`).
SLAB_BYTES = 2.5e9
#: Plans of a whole scan kept in memory between the planning pass (which finds the
#: projections to simulate) and the reconstruction (bytes); beyond it a slab's plan is made
#: again when its turn comes.
KEEP_PLANS_BYTES = 2.0e9


def plan_bytes(plan_: SlabWeights) -> int:
    """Bytes a plan holds (its weight, index and branch arrays)."""
    n = 0
    for mp in plan_.methods.values():
        n += mp.proj_index.nbytes + mp.weight.nbytes + (0 if mp.branch is None else mp.branch.nbytes)
    return int(n)


def slab_bytes_per_slice(rows_per_slice: float, n_cols: int, n_variants: int, n_targets: int, ny: int, nx: int,
                         plan_bytes_per_slice: float = 0.0, volume_itemsize: int = 4) -> float:
    """Bytes one slice adds to a slab's working set (the slab-size rule, :func:`slices_per_slab`).

    Its rebinned rows (``rows_per_slice`` x ``n_cols`` float32, one copy per noise variant),
    its plan (``plan_bytes_per_slice``, with the int32/float32 copies the slab makes of it:
    half as large again), the images of the one method being reconstructed (``n_targets`` x ny
    x nx float32), and the finished (variant, method) slab being written: its copy in the
    volume dtype (``volume_itemsize`` bytes, 4 for float32, 2 for float16) and its compressed
    unit image, which :func:`clrecon.core.units.h5_image` holds twice at its end (the in-memory
    file and the bytes it returns; each counted at the raw size, the upper bound: LZF + shuffle
    leaves HU images at about 0.8 of it). The writer holds only those: the
    executors convert a finished slab in the run's thread once the previous one is on disk
    (:class:`clrecon.pipeline.executors.base.Work` ``prepare``), so the float32 images of two
    methods are never held at once (docs/results/code-history.md "The write behind's slab").
    """
    return (rows_per_slice * n_cols * 4 * max(n_variants, 1) + 1.5 * plan_bytes_per_slice
            + slab_images_bytes_per_slice(n_targets, ny, nx, volume_itemsize))


def slab_images_bytes_per_slice(n_targets: int, ny: int, nx: int, volume_itemsize: int = 4) -> int:
    """The images' part of :func:`slab_bytes_per_slice` (bytes per slice): one method's float32
    images and the finished slab being written (its volume-dtype copy and its compressed image twice)."""
    return int(n_targets * ny * nx * (4 + 3 * int(volume_itemsize)))


def slices_per_slab(bytes_per_slice: float, budget: float = SLAB_BYTES) -> int:
    """Slices per slab so that one slab's working set stays under ``budget`` bytes (at least 1).

    The one slab-size rule: the run (:func:`slab_slices`), its cost model
    (:mod:`clrecon.pipeline.costs`) and the bench's memory model use it. The result never
    changes the numbers, only memory and the number of times a projection is read.
    """
    return int(max(1, budget // max(bytes_per_slice, 1.0)))


def probe_sizes(probe: SlabWeights) -> tuple[float, int, float]:
    """``(rebinned rows per slice, targets, plan bytes per slice)`` of a plan of a few slices,
    the inputs of :func:`slab_bytes_per_slice`."""
    S = max(len(probe.slices_z), 1)
    proj, _ = probe.needed_pairs()
    n_t = max((int(np.prod(mp.targets_shape)) for mp in probe.methods.values()), default=1)
    return len(proj) / S, n_t, plan_bytes(probe) / S


def slab_slices(cfg: ReconstructionConfig, probe: SlabWeights, n_variants: int, budget: float = SLAB_BYTES,
                volume_itemsize: int = 4) -> int:
    """:func:`slices_per_slab` from the plan ``probe`` of a few slices, their mean size per slice
    (the run sizes its slabs slice by slice instead: :func:`clrecon.pipeline.slabs.plan_slabs`)."""
    rows, n_t, plan_b = probe_sizes(probe)
    return slices_per_slab(slab_bytes_per_slice(rows, cfg.scanner.n_cols, n_variants, n_t, cfg.fbp.ny, cfg.fbp.nx,
                                                plan_b, volume_itemsize), budget)


class SlabTooLarge(ClreconError, MemoryError):
    """One slice's rebinned rows do not fit in one device buffer (``CL_DEVICE_MAX_MEM_ALLOC_SIZE``)."""


def _slab_pairs(plan_: SlabWeights, s0: int, s1: int):
    """Slices ``s0:s1`` of the plan: ``(sub, ukeys)``, each method's ``(proj_index, weight,
    targets_shape)`` for the slab and the sorted unique (projection, slice) pair keys
    ``projection * (s1 - s0) + slice`` that carry a non-zero weight (one rebinned row each)."""
    sub = {m: (mp.proj_index[s0:s1], mp.weight[s0:s1], mp.targets_shape) for m, mp in plan_.methods.items()}
    keys = []
    Ssl = s1 - s0
    for idx, w, _ in sub.values():
        sl = np.broadcast_to(np.arange(Ssl)[:, None, None, None], idx.shape)
        nzm = w != 0
        keys.append(idx[nzm].astype(np.int64) * Ssl + sl[nzm])
    return sub, np.unique(np.concatenate(keys)) if keys else np.zeros(0, np.int64)


def _reconstruct_slab(cfg: ReconstructionConfig, store, plan_: SlabWeights, s0, s1, variants, geom, rt, times, chunk,
                      progress, emit, sub, ukeys) -> None:
    sc = cfg.scanner
    t0 = time.perf_counter()
    # (projection, slice) pairs of this slab (:func:`_slab_pairs`), and each method's index into them
    Ssl = s1 - s0
    pair_proj = ukeys // Ssl
    pair_slice = ukeys % Ssl
    pair_dz = plan_.slices_z[s0:s1][pair_slice] - store.table.source_z_mm[pair_proj]
    # a flying focal spot: each pair's spot offset from the focal centre (SSRB from the spot)
    pair_shift = None
    if store.table.focal_shift is not None:
        pair_shift = spot_shift_in_frame(store.table.focal_shift[pair_proj], sc.sid_mm)
    times.add("plan", time.perf_counter() - t0)

    # stream the store in index order, rebinning only the pairs each chunk owns
    # page-aligned, so that a CPU device reads them in place (DeviceRows(share=True) below)
    rows = {v: aligned_empty((len(ukeys), sc.n_cols), np.float32) for v in variants}
    bounds = np.unique(np.concatenate([np.arange(pair_proj.min(), pair_proj.max() + 1, chunk),
                                       [pair_proj.max() + 1]])) if len(pair_proj) else np.zeros(1, int)
    for b0, b1 in zip(bounds[:-1], bounds[1:], strict=True):
        lo, hi = np.searchsorted(pair_proj, [b0, b1])
        if lo == hi:
            continue
        wanted, slot = np.unique(pair_proj[lo:hi], return_inverse=True)
        # only the detector rows these pairs read (a slab of a few slices: a few of the rows),
        # and noise only for them: a cell's noise is keyed by its place on the whole detector
        shift = None if pair_shift is None else pair_shift[lo:hi]
        r_lo, r_hi = rebin.ssrb_row_range(pair_dz[lo:hi], sc, shift)
        t1 = time.perf_counter()
        clean = store.read_indices(wanted, noisy=False, rows=(r_lo, r_hi))
        times.add("read", time.perf_counter() - t1)
        times.count("read_cells", clean.size)
        for v in variants:
            data = clean
            if v == "noisy":
                t1 = time.perf_counter()
                data = noise.add_noise(clean, wanted, cfg.noise, first_row=r_lo)
                times.add("noise", time.perf_counter() - t1)
                times.count("noise_cells", data.size)
            t1 = time.perf_counter()
            rows[v][lo:hi] = rebin.ssrb_rows(data, slot.astype(np.int32).ravel(),
                                            pair_dz[lo:hi].astype(np.float32), sc, rt=rt, first_row=r_lo,
                                            pair_shift=shift)
            times.add("rebin", time.perf_counter() - t1)
    clean = data = None  # the last read chunk is not held through the FBP (the cost model counts them apart)

    # Cosine weighting and ramp filtering act on each row alone and linearly, so they commute
    # with the interpolation (weighted sums of rows of the same view): each rebinned row is
    # filtered once per variant instead of once per method and target, the filtered rows go
    # to the device once per variant, and every method interpolates them straight into the
    # backprojector's interleaved layout (no sinogram round trip through the host).
    # recon.backprojector = "parallel-rebin" filters after the interpolation instead (the ramp
    # filter in s acts on rebinned parallel rows, which mix fan views): rows stay unfiltered here.
    per_method = {}
    for m, (idx, w, tshape) in sub.items():
        t1 = time.perf_counter()
        key = idx.astype(np.int64) * Ssl + np.arange(Ssl)[:, None, None, None]
        pos = np.searchsorted(ukeys, key)
        pos = np.where(w != 0, np.clip(pos, 0, len(ukeys) - 1), 0).astype(np.int32)
        Sn, V, T, K = idx.shape
        # sinogram b = s * T + t (slice-major, as the images are reshaped below), (B, V, K)
        # padded to whole 16-lane groups once (not once per launch); pos is in [0, len(ukeys))
        per_method[m] = interpolate.pad_interleaved(pos.transpose(0, 2, 1, 3).reshape(Sn * T, V, K),
                                                    w.transpose(0, 2, 1, 3).reshape(Sn * T, V, K).astype(np.float32)
                                                    ) + (tshape, Sn * T)
        times.add("plan", time.perf_counter() - t1)
        times.add(f"plan:{m}", time.perf_counter() - t1)  # the method's share of "plan"
    step = fbp_mod.groups_per_launch(geom) * fbp_mod.BATCH_LANES
    mu_water = cfg.mu_water_per_mm
    par = None
    if cfg.backprojector == "parallel-rebin":
        par = parallel_fbp.ParallelFBP(geom, cfg.filter, runtime=rt)
    elif cfg.backprojector != "direct":
        raise ValueError(f"backprojector = {cfg.backprojector!r}: must be 'direct' or 'parallel-rebin'")
    for v in variants:
        t1 = time.perf_counter()
        if par is None:
            fbp_mod.filter_rows(rows[v], geom, cfg.filter, out=rows[v])
        t_filter = time.perf_counter() - t1
        times.add("fbp", t_filter)
        t1 = time.perf_counter()
        # the rows go to the device in place on a CPU device (no copy of ~1 GB at paper scale)
        # and are not touched again here; elsewhere they are copied and the host array dropped
        d_rows = interpolate.DeviceRows(rows.pop(v), rt=rt, share=True)
        t_upload = time.perf_counter() - t1
        times.add("interpolate", t_upload)
        # one launch's interleaved sinograms and images, allocated once per variant and reused by
        # every launch: fresh buffers of these sizes (paper-p010: 114 MB of sinograms, 2 x 34 MB of
        # images per launch) are new pages each time, and their first touch cost as much as the
        # interpolation kernel itself (docs/kernels.md, "Scratch buffers")
        n_launch = -(-step // fbp_mod.BATCH_LANES)
        d_sino = rt.empty((n_launch, geom.n_views, geom.n_cols + 2, fbp_mod.BATCH_LANES))
        d_img = rt.empty((step, geom.ny, geom.nx)) if par is None else None
        mu_host = np.empty((step, geom.ny, geom.nx), np.float32) if par is None else None
        try:
            for m, (pos_b, w_b, tshape, B) in per_method.items():
                img = np.empty((B, geom.ny, geom.nx), np.float32)
                t_interp = t_fbp = 0.0
                for b0 in range(0, B, step):
                    t1 = time.perf_counter()
                    g0 = b0 // fbp_mod.BATCH_LANES  # the padded weights are (G, V, K, 16): whole groups
                    g1 = -(-(b0 + step) // fbp_mod.BATCH_LANES)
                    buf, G = interpolate.apply_padded_interleaved(d_rows, pos_b[g0:g1], w_b[g0:g1],
                                                                  min(step, B - b0), rt=rt, out=d_sino)
                    t2 = time.perf_counter()
                    if par is None:
                        mu = fbp_mod.backproject_interleaved(buf, G, geom, runtime=rt, out_buf=d_img, out=mu_host)
                    else:
                        mu = par.images(buf, G)
                    n = min(step, B - b0)
                    # HU = 1000 (mu - mu_w) / mu_w (conventions.mu_to_hu), in float32 in place
                    np.multiply(mu[:n], np.float32(1000.0 / mu_water), out=img[b0:b0 + n])
                    img[b0:b0 + n] -= np.float32(1000.0)
                    t_interp += t2 - t1
                    t_fbp += time.perf_counter() - t2
                times.add("interpolate", t_interp)
                times.add("fbp", t_fbp)
                # per-method cost (weights are planned separately; the shared filtering and
                # upload split evenly): the "error against run time" figure
                times.add(f"method:{m}:{v}", t_interp + t_fbp + (t_filter + t_upload) / len(per_method))
                img = img.reshape(Sn, tshape[0], tshape[1], geom.ny, geom.nx).transpose(1, 2, 0, 3, 4)
                emit((v, m), img)  # a transposed view: the writer makes its one (dtype-converting) copy
                del img
                if progress is not None:  # one step per slice of each (variant, method)
                    progress.update(s1 - s0)
        finally:
            d_rows.release()
            d_sino.release()
            if d_img is not None:
                d_img.release()
    if par is not None:
        par.release()

