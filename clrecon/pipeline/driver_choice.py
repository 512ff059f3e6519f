"""Which CPU driver runs a run: the one predicted fastest for *this run's* mix of kernel work.

The two CPU drivers that come with clrecon are not ordered the same on every CPU or for every
run: Intel's runtime backprojects faster where PoCL interpolates and draws noise faster (both
measured, docs/drivers.md "Which is faster"), so which one finishes a run first depends on the
run's mix: a small demo is noise- and interpolation-heavy, a whole ``paper-p010`` mostly
backprojection. So, before a run with no ``CLRECON_DEVICE``:

1. every CPU driver that passes the probe is *timed* once per machine, driver version and
   Python, on the five kernel families of :mod:`clrecon.pipeline.driver_timing` (in the same
   child process that probes it; its cost: docs/performance.md);
   the seconds per unit of work are kept in ``<cache>/opencl-driver-timings.json`` beside the
   probe's verdicts, keyed like them (:func:`clrecon.core.drivers.verdict_key`);
2. :func:`run_work` counts the run's units of work per family from its scene, methods, targets,
   slices and pitches (the same quantities as the pre-flight's cost model,
   :func:`clrecon.pipeline.costs.run_costs`);
3. each driver's predicted kernel seconds are ``sum(units[f] * seconds_per_unit[f])``; the run takes
   the smallest, except that a driver later in :data:`clrecon.core.drivers.CPU_DRIVERS` order must
   beat the earlier ones by :data:`MARGIN` (timings on a shared machine move by a few percent);
4. :func:`apply` makes it this process's preferred CPU driver (and its children's: the choice is
   carried in ``CLRECON_DRIVER_PREFERENCE``), so every runtime the run makes -- its threads, its
   process pools, a local Dask cluster's workers -- uses the same driver, and the outputs stay
   bit-identical across executors.

Only the kernels are modelled: reading, writing, metrics and the mc method's own kernels are the
same on both drivers or not timed, so the prediction ranks the drivers but is not the run's wall
time. With one working CPU driver nothing is timed. ``CLRECON_DEVICE`` overrides all of it.
"""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path

from clrecon.config.scene import load_scene
from clrecon.core import drivers
from clrecon.core.cache import default_cache_dir
from clrecon.pipeline.costs import run_costs
from clrecon.pipeline.driver_timing import FAMILIES, TIMING_VERSION
from clrecon.pipeline.variants import noise_variants
from clrecon.reconstruction.fbp import FanBeamGeometry
from clrecon.reconstruction.interpolation import METHODS
from clrecon.reconstruction.rebin import slice_window_mm

#: A driver later in clrecon's order is taken only when predicted this much faster (fraction).
MARGIN = 0.03
#: Seconds the timing child may take (cold kernel builds on both drivers included).
TIMING_TIMEOUT_S = 300


@dataclasses.dataclass(frozen=True)
class DriverTiming:
    """One working CPU driver's timings."""

    key: str
    spec: str
    platform: str
    driver_version: str
    seconds_per_unit: dict
    cached: bool
    #: seconds the timing child took (probe, kernel builds, timings); 0 when cached
    child_seconds: float = 0.0


@dataclasses.dataclass(frozen=True)
class Decision:
    """The driver a run uses, and why (``results.json["driver"]["choice"]``)."""

    key: str | None
    reason: str
    #: driver key -> predicted kernel seconds of the run, per family and ``total``
    predicted: dict
    timings: tuple[DriverTiming, ...] = ()

    def as_dict(self) -> dict:
        return {"driver": self.key, "reason": self.reason, "predicted_kernel_seconds": self.predicted,
                "timings": {t.key: {"seconds_per_unit": t.seconds_per_unit, "cached": t.cached,
                                    "child_seconds": t.child_seconds} for t in self.timings}}


# -- the run's work ---------------------------------------------------------------------------

def run_work(scene, methods=None, n_cardiac=None, n_resp=None, slices_z=None, pitches=None,
             targets=None) -> dict[str, float]:
    """Units of work of each kernel family in a run (first run: the projections simulated too).

    Units are those of :mod:`clrecon.pipeline.driver_timing`: rays (projector), detector cells
    (noise, SSRB, interpolation) and voxel updates (backprojection). The mc method's second pass
    is counted as one more 5D method's first pass (its own kernels are not timed). ``targets``: the
    run's :class:`~clrecon.reconstruction.reconstruct.Targets` (``run_costs``' default: the scene's first
    ``n_cardiac`` / ``n_resp``), so that its plan probe is the pre-flight's, made once.
    """
    sc, rc = scene.scanner, scene.recon
    methods = tuple(methods or rc.methods)
    pitches = tuple(pitches or scene.scan.pitches)
    costs = run_costs(scene, methods, n_cardiac, n_resp, slices_z, pitches, targets=targets)
    n_targets = costs["n_targets"]
    n_c = len(scene.cardiac_targets) if n_cardiac is None else n_cardiac
    nz = rc.nz if slices_z is None else len(slices_z)
    variants = noise_variants(scene)
    n_var, n_noisy = len(variants), sum(v == "noisy" for v in variants)
    equiv = sum({"resp": 1.0 / n_c, "none": 1.0 / n_targets}.get(METHODS[m].target_grid, 1.0) for m in methods)
    V = FanBeamGeometry.from_scene(scene).n_views
    window = slice_window_mm(sc, min(sc.fov_radius_mm, rc.fov_radius_mm))
    cells = sc.n_rows * sc.n_cols
    work = dict.fromkeys(FAMILIES, 0.0)
    for p in pitches:
        needed = costs["projections_needed"][p]
        rows_per_slice = 2 * window / scene.scan.feed_mm(sc, p) * sc.views_per_rotation
        slices = n_var * equiv * n_targets * nz  # fan-beam images to make
        if not getattr(scene, "measured", False):
            work["projector"] += needed * cells
        work["noise"] += n_noisy * needed * cells
        work["ssrb"] += n_var * nz * rows_per_slice * sc.n_cols
        work["interpolation"] += slices * V * sc.n_cols
        work["backprojection"] += slices * V * rc.nx * rc.ny
    return work


def predict(work: dict, timing: DriverTiming) -> dict:
    """Predicted kernel seconds per family and ``total`` of ``work`` on the driver timed by ``timing``."""
    out = {f: work.get(f, 0.0) * timing.seconds_per_unit[f] for f in FAMILIES}
    out["total"] = sum(out.values())
    return {k: round(v, 3) for k, v in out.items()}


# -- timings, cached per machine ------------------------------------------------------------------

def timings_path(cache_dir: Path | None = None) -> Path:
    return (cache_dir or default_cache_dir()) / "opencl-driver-timings.json"


def _timing_key(dev) -> str:
    return f"{drivers.verdict_key(dev)}:t{TIMING_VERSION}"


def run_timing_child(platform_name: str, device_index: int) -> dict:
    """Run :mod:`clrecon.pipeline.driver_timing` in a child process; its JSON line (or a failed verdict)."""
    return drivers.run_json_child("clrecon.pipeline.driver_timing", [platform_name, str(device_index)],
                                  TIMING_TIMEOUT_S, what="the probe and timing")


def time_driver(dev, index: int, cache_dir: Path | None = None, use_cache: bool = True) -> DriverTiming | None:
    """The timings of ``dev`` (the ``index``-th device of its platform), from the cache or a child.

    A child also records the probe's verdict (:func:`clrecon.core.drivers.remember_verdict`), so the
    runtime probes nothing after it; a child that gives no verdict (it died before its probe's line)
    leaves the verdict to the plain probe (:func:`clrecon.core.drivers.probe_device`). None where the
    device fails the probe, or passes it and its timing failed (its verdict then says it works)."""
    p = dev.platform
    drv = drivers.driver_of(p.name)
    spec = f"{p.name}:{index}"
    key = drv.key if drv else p.name
    path = timings_path(cache_dir)
    tkey = _timing_key(dev)
    if use_cache:
        hit = drivers.read_json_dict(path).get(tkey)
        if isinstance(hit, dict) and set(FAMILIES) <= set(hit.get("seconds_per_unit", {})):
            return DriverTiming(key, spec, p.name, dev.driver_version, hit["seconds_per_unit"], True)
        verdict = drivers.cached_verdict(dev, cache_dir)
        if verdict is not None and not verdict.ok:
            return None  # known to fail: not timed
    res = run_timing_child(p.name, index)
    if res.get("no_output") or "reason" not in res:
        # no verdict from the child (it died before its probe's line, or timed out): the plain probe decides
        verdict = drivers.probe_device(dev, index, cache_dir, use_cache=False)
        res = {"ok": verdict.ok, "reason": verdict.reason}
    else:
        drivers.remember_verdict(dev, bool(res.get("ok")), str(res.get("reason", "")), cache_dir)
    if not res.get("ok") or "seconds_per_unit" not in res:
        return None  # failed the probe; or passed it and the timing failed: working, untimed
    per_unit = {f: float(res["seconds_per_unit"][f]) for f in FAMILIES}
    drivers.remember(path, tkey, {"seconds_per_unit": per_unit, "platform": p.name,
                                  "driver_version": dev.driver_version, "cpu": drivers.cpu_line(),
                                  "build_seconds": res.get("build_seconds"), "child_seconds": res.get("seconds")})
    return DriverTiming(key, spec, p.name, dev.driver_version, per_unit, False, float(res.get("seconds") or 0.0))


# -- the choice -----------------------------------------------------------------------------------

def timed_drivers(cache_dir: Path | None = None, use_cache: bool = True) -> tuple[list[DriverTiming], list[str]]:
    """The timings of every known CPU driver that passes the probe (clrecon's order), and the keys of those that
    pass it but could not be timed; ([], []) where no OpenCL platform answers (the runtime says so in its line)."""
    import pyopencl as cl

    drivers.register_wheel_drivers()
    try:
        platforms = cl.get_platforms()
    except cl.Error:
        return [], []
    timings, untimed = [], []
    for dev, idx in drivers.first_device_per_driver(platforms):
        t = time_driver(dev, idx, cache_dir, use_cache=use_cache)
        if t is not None:
            timings.append(t)
        elif (v := drivers.cached_verdict(dev, cache_dir)) is not None and v.ok:
            untimed.append(drivers.driver_of(dev.platform.name).key)
    return timings, untimed


def decide(work: dict, timings: list[DriverTiming]) -> Decision:
    """The driver with the smallest predicted kernel seconds for ``work`` (``timings`` in clrecon's order)."""
    if not timings:
        return Decision(None, "no CPU driver passes the probe", {})
    predicted = {t.key: predict(work, t) for t in timings}
    if len(timings) == 1:
        return Decision(timings[0].key, "the only CPU driver that passes the probe", predicted, tuple(timings))
    best = timings[0]
    for t in timings[1:]:
        if predicted[t.key]["total"] < (1.0 - MARGIN) * predicted[best.key]["total"]:
            best = t
    others = ", ".join(f"{t.key} {predicted[t.key]['total']:.3g} s" for t in timings if t is not best)
    reason = (f"predicted fastest for this run's kernels by timing: {best.key} {predicted[best.key]['total']:.3g} s "
              f"against {others}")
    return Decision(best.key, reason, predicted, tuple(timings))


def choose_for_run(scene, methods=None, n_cardiac=None, n_resp=None, slices_z=None, pitches=None,
                   cache_dir: Path | None = None, targets=None) -> Decision | None:
    """The run's driver :class:`Decision`; None where ``CLRECON_DEVICE`` names the device (nothing timed)."""
    if os.environ.get("CLRECON_DEVICE"):
        return None
    timings, untimed = timed_drivers(cache_dir)
    if untimed:  # a working driver whose timing failed: nothing to compare with, the default order decides
        return Decision(None, f"{', '.join(untimed)} passed the probe but could not be timed: clrecon's order",
                        {}, tuple(timings))
    if len(timings) < 2:
        return Decision(timings[0].key if timings else None,
                        "the only CPU driver that passes the probe" if timings else "no CPU driver passes the probe",
                        {}, tuple(timings))
    return decide(run_work(scene, methods, n_cardiac, n_resp, slices_z, pitches, targets=targets), timings)


def apply(decision: Decision | None) -> None:
    """Make ``decision``'s driver this process's (and its children's) preferred CPU driver, where it was
    chosen by comparing timings (with one working driver, or none timed, the default order stands)."""
    if decision is not None and decision.key and decision.predicted:
        drivers.prefer(decision.key, decision.reason)


# -- what ``clrecon devices`` shows -----------------------------------------------------------------

#: The scenes whose runs ``clrecon devices`` predicts on each working driver (the default and the paper's).
SHOWN_SCENES = ("demo", "paper-p010")


def timing_report(time_again: bool = False, cache_dir: Path | None = None) -> dict:
    """Each working CPU driver's timings and, for :data:`SHOWN_SCENES`, the predicted kernel seconds and choice.

    ``{"drivers": {key: {"seconds_per_unit", "cached", "child_seconds"}}, "scenes": {scene: Decision.as_dict()},
    "note": str}``; with one working driver (or none) only ``note`` says why nothing is compared."""
    timings, _untimed = timed_drivers(cache_dir, use_cache=not time_again)
    out = {"drivers": {t.key: {"seconds_per_unit": t.seconds_per_unit, "cached": t.cached,
                               "child_seconds": t.child_seconds} for t in timings}, "scenes": {}}
    if len(timings) < 2:
        out["note"] = ("one CPU driver passes the probe: every run uses it, nothing to compare" if timings
                       else "no CPU driver passes the probe")
        return out
    for name in SHOWN_SCENES:
        out["scenes"][name] = decide(run_work(load_scene(name)), timings).as_dict()
    out["note"] = (f"each run takes the driver predicted fastest for its own kernel work (a later driver in "
                   f"clrecon's order must win by {MARGIN:.0%}); CLRECON_DEVICE overrides")
    return out


def format_timing_report(rep: dict) -> str:
    """:func:`timing_report` as lines for a terminal."""
    lines = ["Driver timings (seconds per unit of work; the run's choice: docs/drivers.md \"The choice\"):"]
    for key, t in rep["drivers"].items():
        figs = ", ".join(f"{f} {t['seconds_per_unit'][f]:.3g}" for f in FAMILIES)
        how = "kept" if t["cached"] else f"timed now in {t['child_seconds']:.1f} s"
        lines.append(f"  {key}: {figs} ({how})")
    for name, d in rep["scenes"].items():
        pred = ", ".join(f"{k} {v['total']:.3g} s" for k, v in d["predicted_kernel_seconds"].items())
        lines.append(f"  {name}: predicted kernel seconds {pred} -> {d['driver']}")
    lines.append(f"  {rep['note']}")
    return "\n".join(lines)
