"""What every stage of a run sees: the resolved request, the open volume writer, the records.

:func:`open_run` resolves and checks a request (methods, targets, slices, pitches; the
pre-flight of memory and disk, :mod:`clrecon.pipeline.preflight`), opens the run's
:class:`~clrecon.outputs.volumes.VolumeWriter` (resuming an interrupted run of the same
request) and returns the :class:`RunContext` the stages of :mod:`clrecon.pipeline.graph` share.
The stages put what ``results.json`` reports into ``records`` (its keys are results.json's)
and their notes on a timed part into ``notes``; the executor sets ``clock``, ``pool`` and
``fine_units``; :func:`clrecon.pipeline.run.run` the graph, the executor's name and summary and the
machine-speed probe. Every field is typed and named here: no stage passes data to another through
the context but its records, notes and the caches named below (``unfinished``, ``mc_truth``).
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from clrecon.config.scene import Scene
from clrecon.core import machine_speed as machine_speed_mod
from clrecon.core.errors import ClreconError
from clrecon.outputs.volumes import VolumeWriter
from clrecon.pipeline import costs as costs_mod
from clrecon.pipeline import preflight
from clrecon.pipeline.stages import truth as truth_stage
from clrecon.pipeline.variants import noise_variants
from clrecon.reconstruction import interpolation, reconstruct
from clrecon.reconstruction.iterative import method as mcir_method
from clrecon.reconstruction.motion import mc_fbp, registration
from clrecon.reconstruction.motion import method as mc_method
from clrecon.reconstruction.reconstruct import Targets
from clrecon.scan import dicom_ct_pd
from clrecon.simulation.store import default_cache_dir

RESULTS_FORMAT = 1
#: The self-tuning method: planned after the truth-free cross-validation chose its kernel.
TUNED = interpolation.cv_tuned.NAME
#: recon keys added after run directories existed: left out of the run key at these defaults.
_RECON_LATER = {"candidate_window_mm": 0.0, "truth_free": False, "volume_compression": "auto",
                "cardiac_distance_scale": 1.0}
#: recon tables of the registered methods: in the run key whole (defaults included) where a method
#: of the run reads them, left out where none does.
_METHOD_KNOBS = {"mc": (mc_fbp.NAME, mcir_method.NAME), "mcir": (mcir_method.NAME,)}


def hashed_recon(recon: dict, methods) -> dict:
    """The scene's ``recon`` table as the run key hashes it: :data:`_RECON_LATER`'s keys left out at
    their fixed defaults (run directories made before those keys existed keep their key), and each
    registered method's table (:data:`_METHOD_KNOBS`) whole where a method of the run reads it, left
    out where none does. Whole, not "away from its defaults": a default that changes between
    versions (e.g. ``mc``'s registration) must not let an interrupted run resume with volumes and a
    saved motion model made under the old one."""
    out = dict(recon)
    for k, v in _RECON_LATER.items():
        if out.get(k) == v:
            out.pop(k)
    for k, readers in _METHOD_KNOBS.items():
        if not set(readers) & set(methods):
            out.pop(k, None)
    return out


@dataclass
class RunContext:
    """The run as the stages see it (module docstring); arrays in mm, targets cardiac-major."""

    scene: Scene
    out: Path
    methods: tuple
    pitches: tuple
    targets: Targets
    slices_z: np.ndarray          # (S,) mm
    slice_range: tuple | None
    variants: tuple               # noise variants: "noise-free", "noisy"
    recon_cfg: Any                # reconstruct.ReconstructionConfig
    cache_path: Path              # the projection store folder (and the truth cache's)
    writer: VolumeWriter
    rt: Any                       # the run's OpenCL runtime
    need: dict                    # the pre-flight's modelled needs (bytes)
    force: bool = False
    report: bool = True
    progress: bool = True
    log: Callable[..., Any] = print
    records: dict = field(default_factory=dict)
    notes: dict = field(default_factory=dict)
    clock: Any = None             # the executor's StageClock
    pool: Any = None              # the executor's warm helper process, or None
    fine_units: bool = False      # units are cut for workers elsewhere (Dask)
    # set by clrecon.pipeline.run.run for the results stage
    graph: tuple = ()             # the run's stages (pipeline.graph.GRAPH): the stage table's order and skips
    executor_kind: str = "serial"  # the executor's name (results.json "executor")
    executor_summary: Callable[[], dict | None] = lambda: None  # its results.json "distributed" entry, or None
    machine_speed: machine_speed_mod.Sample | None = None  # the probe started before the run's clock
    # kept by the stages across nodes
    unfinished: dict = field(default_factory=dict)  # pitch key -> (methods with an unfinished unit, their slices)
    mc_truth: dict = field(default_factory=dict)  # the phantom's own motion, kept for the mc model's next error

    @property
    def want_truth_free(self) -> bool:
        """The truth-free cross-validation runs (``recon.truth_free``, or the cv_tuned method)."""
        return bool(self.scene.recon.truth_free) or TUNED in self.methods

    @property
    def full_shape(self) -> tuple:
        rc = self.scene.recon
        return self.targets.shape + (len(self.slices_z), rc.ny, rc.nx)

    @property
    def n_targets(self) -> int:
        return self.targets.shape[0] * self.targets.shape[1]

    def note(self, part: str, **entries) -> None:
        """Entries for ``results.json["stages"][part]`` beside its times."""
        self.notes.setdefault(part, {}).update(entries)


def resolve_targets(scene: Scene, cardiac: Sequence[float] | None = None,
                    resp: Sequence[float] | None = None) -> Targets:
    """Targets of the run: the scene's, narrowed by ``cardiac``/``resp`` lists if given."""
    c = tuple(scene.cardiac_targets)
    r = tuple(scene.resp_targets)
    if cardiac:
        if not scene.has_cardiac:
            raise ClreconError("--targets: the scene has no cardiac motion, so there is no cardiac axis to select")
        bad = [x for x in cardiac if not 0 <= x < 1]
        if bad:
            raise ClreconError(f"--targets: cardiac phase {bad[0]} outside [0, 1)")
        c = tuple(float(x) for x in cardiac)
    if resp:
        if not scene.has_respiratory:
            raise ClreconError("--targets: the scene has no breathing, so there is no respiratory axis to select")
        bad = [x for x in resp if not 0 <= x <= 1]
        if bad:
            raise ClreconError(f"--targets: respiratory amplitude {bad[0]} outside [0, 1]")
        r = tuple(float(x) for x in resp)
    return Targets(cardiac=c, resp=r)


def json_default(o):
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, tuple):
        return list(o)
    raise TypeError(type(o))


def open_run(scene: Scene, out: Path, methods, cardiac, resp, slice_range, pitches, cache_dir, *, rt,
             executor_kind: str, distributed: bool, force: bool, **opts) -> RunContext:
    """Resolve and check the request, run the pre-flight and open the volume writer (module docstring)."""
    methods = tuple(methods or scene.recon.methods)
    known = interpolation.method_names()
    unknown = [m for m in methods if m not in scene.recon.methods and m not in known]
    if unknown:
        raise ClreconError(f"--methods: unknown method {unknown[0]!r}; allowed: {', '.join(known)}")
    pitches = tuple(pitches or scene.scan.pitches)
    targets = resolve_targets(scene, cardiac, resp)
    rc = scene.recon
    if slice_range is not None and not (0 <= slice_range[0] < slice_range[1] <= rc.nz):
        raise ClreconError(f"--slices {slice_range[0]}:{slice_range[1]}: must satisfy 0 <= start < stop <= "
                           f"recon.nz = {rc.nz}")
    if distributed and (rc.truth_free or TUNED in methods):
        raise ClreconError("recon.truth_free and the cv_tuned method run in one process: drop --workers/--cluster")
    if distributed and scene.measured:
        raise ClreconError("a measured scan (scan.source = 'dicom-ct-pd') runs in one process: "
                           "drop --workers/--cluster")
    slices_z = reconstruct.slice_positions(scene, slice_range)
    for m in interpolation.second_pass_methods(methods):  # a method made from another method's first pass
        fp = interpolation.first_pass(m)
        if fp not in methods:
            raise ClreconError(f"method {m!r} is made from the {fp} first pass: add '{fp}' to "
                               f"recon.methods (or --methods)")
        if len(slices_z) < 2:
            raise ClreconError(f"method {m!r} registers the volumes along z: it needs at least 2 slices, the run "
                               f"has {len(slices_z)}")
        if m == mcir_method.NAME and rc.mcir.init == mc_fbp.NAME and mc_fbp.NAME not in methods:
            raise ClreconError("recon.mcir.init = 'mc' starts mcir from the mc method's volumes: add 'mc' to "
                               "recon.methods (or --methods), or set init to 'first_pass' or 'zero'")
        if mc_method.uses_library(scene.recon.mc):  # only 'lucas_kanade' (scikit-image); the others run on OpenCL
            registration.require("skimage.registration")  # before any work: one line naming the extra
    cache_path = Path(cache_dir).expanduser() if cache_dir is not None else default_cache_dir()
    run_costs = costs_mod.run_costs(scene, methods, len(targets.cardiac), len(targets.resp), slices_z, pitches,
                                    overlap=executor_kind != "serial", targets=targets,
                                    truths_computed=not truth_stage.all_cached(cache_path, scene, slices_z, targets))
    need = (preflight.needs(scene, run_costs, cache_path, out) if force
            else preflight.check(scene, run_costs, cache_path, out, rt=rt))
    variants = noise_variants(scene)
    axes = {"cardiac_phase": targets.cardiac, "resp_amplitude": targets.resp, "z_mm": slices_z,
            "y_mm": reconstruct.voxel_coords(rc.ny, rc.voxel_mm), "x_mm": reconstruct.voxel_coords(rc.nx, rc.voxel_mm)}
    scene_d = scene.to_dict()
    scene_d["recon"] = hashed_recon(scene_d["recon"], methods)
    run_key = hashlib.sha256(json.dumps(
        {"scene": scene_d, "methods": methods, "pitches": pitches, "variants": variants,
         "targets": [targets.cardiac, targets.resp], "slices": slices_z.tolist(), "format": RESULTS_FORMAT,
         **({"driver": rt.cache_tag} if rt.cache_tag else {})},  # no resumption across drivers
        sort_keys=True, default=json_default).encode()).hexdigest()
    writer = VolumeWriter(out / "volumes.h5", axes, keep_cardiac=scene.has_cardiac, keep_resp=scene.has_respiratory,
                          run_key=run_key, dtype=rc.volume_dtype, compression=run_costs["volume_compression"])
    run = RunContext(scene=scene, out=out, methods=methods, pitches=pitches, targets=targets, slices_z=slices_z,
                     slice_range=slice_range, variants=variants,
                     recon_cfg=reconstruct.ReconstructionConfig.from_scene(scene), cache_path=cache_path,
                     writer=writer, rt=rt, need=need, force=force, executor_kind=executor_kind, **opts)
    if writer.resumed:
        run.log("resuming an interrupted run: finished slices and targets are kept")
    if over := mcir_method.over_budget_note(run_costs.get("mcir_slab_bytes", 0)):  # before hours of work, not at it
        run.log(f"note: mcir: {over}")
    if scene.measured:  # a DICOMDIR beside the projections (normal on media): one note each
        for name, why in dicom_ct_pd.series_index(scene.scan.projections).skipped:
            run.log(f"note: scan.projections: {name} skipped: {why}")
    for key in ("sim_info", "diagnostics", "sampling", "recorded_signals", "method_seconds", "method_plan_seconds",
                "truth_free", "consistency", "metrics", "respiratory_only", "motion"):
        run.records[key] = {}
    run.records["units_written"] = {"projections": 0}
    run.records["counts"] = {}
    return run
