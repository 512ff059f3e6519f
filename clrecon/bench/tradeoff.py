"""Error against run time as a trade-off: per method, the knobs that trade seconds for error.

Every sweep point is one :func:`clrecon.pipeline.run.run` of ONE method (so no point shares
the candidate search, filtering or upload with another method) on the ``demo`` scene at pitch
0.02, with every target and both noise variants the scene gives, narrowed to a few central
slices (:data:`FULL_SLICES`: 4 of demo's 16, z = -6..6 mm, through the heart) to keep a point
under ~40 s on 2 cores. From its ``results.json``: the pooled MAE against the ground truth in
the small and large FOV (``metrics``) and the method's seconds (``method_seconds``: its plan,
interpolation and FBP for that variant).

A second-pass method (``mc``: motion-compensated FBP made from the registry's ``first_pass``,
barycentric) runs with its first pass (``methods = (barycentric, mc)``), and its point's seconds
are the method's whole cost: ``method_seconds`` of ``mc`` (its model's fit: every round's
registrations, model fit and, after the first round, motion-compensated backprojection on the
registration grid, the registration's process pool started; then the final pass: the
first-pass plan again, the plane rows and the motion-compensated backprojection) plus
``method_seconds`` of its first pass (barycentric's plan, interpolation and FBP of that
variant); ``seconds_parts`` keeps the two. Not counted: reading the first pass back from
``volumes.h5`` and the model's error against the phantom's motion (an evaluation; the row keeps
its figures as ``model_error``). The registration sees only the run's slices (its
``margin_mm`` widens the projection rows read around a slab, not the registered volume): on
:data:`FULL_SLICES` (16 mm of z) ``mc`` is below its ``THIN_Z_MM`` and warns that its model does
not recover the motion (the row keeps the warning); such a point measures ``mc``'s cost and
error on a run of these slices, not its motion model; the ``z`` point gives it the scene's
whole z.

``mcir`` (OS-SART through mc's motion model, made from the registry's ``first_pass``) runs with
its first pass and, where it starts from mc's image (``[recon.mcir] init`` 'auto' with mc in the
run), with mc too (:attr:`SweepPoint.also`): ``methods = (barycentric, mc, mcir)``. Its point's
seconds are the run's whole cost of the three (:func:`point_seconds`): their ``method_seconds``
summed with the motion model's fit counted once. The one model is fitted by the first of the
two second-pass stages (mc's) and loaded by the other, and each one's ``method_seconds`` holds
the fit's seconds, so one copy is taken off; what is left is the first pass + the model's fit +
mc's final pass + mcir's OS-SART (per slab: its setup, the epochs with their residuals, the
targets' sampling). ``seconds_parts`` keeps the three ``method_seconds`` as the run recorded
them, ``model_seconds`` the fit, ``solver`` each slab's epochs run, residuals and why it
stopped. Not counted, as for mc: reading the start image and the first pass back from
``volumes.h5``, the model's error against the phantom's motion. A point from ``zero`` needs no mc
image: its run is (barycentric, mcir), the mcir stage fitting the model.

Knobs (one changed at a time from the scene's setting, the *base*):

- local linear: points per quadrant ``q1``, ``q2`` (base), ``q3``; the nearest points overall
  ``n5`` (the paper's Figure 2B caption), ``n8``; ``kappa`` 0.5, 1 (base), 2; ``sigma`` 0.1,
  0.15 (base), 0.3 (``recon.local_linear_points``, ``local_linear_count``, ``kappa``, ``sigma``);
- barycentric, nearest, bin, helical, r4dct: the candidate turns used, ``recon.max_turns`` 0
  (all, base), 4, 2;
- mc: registration rounds ``r2`` (base), ``r1``; the registration's in-plane factor ``ds1``
  (base, in the base point), ``ds2``; TV-L1 for both registration steps ``tvl1`` and scikit-image's
  Lucas-Kanade for the breathing ``skimage`` (base: the scene's ``registration`` and
  ``beat_registration``, by default the OpenCL Lucas-Kanade and TV-L1) (``recon.mc.rounds``,
  ``downsample``, ``registration``, ``beat_registration``); every mc and mcir row keeps the
  registrations its run used (``registrations``, from ``results.json``); and, where the scene has at least
  ``THIN_Z_MM`` of slices, the base knobs on a run of every slice (``z64`` on demo: 64 mm of
  z for the registration), scored on the sweep's slices, its seconds the whole run's (the
  pipeline reconstructs every slice it registers); not in the quick sweep;
- mcir: OS-SART epochs at most ``e1`` (base), ``e2``, ``e4`` (``recon.mcir.epochs``; ``tol`` may
  stop it sooner: ``solver`` says), from mc's image (base) or from ``zero`` (``init``), on mc's
  base model; not in the quick sweep;
- every method except mc: views per rotation N (base) and N/2 (``v180`` on demo), the image grid nx = ny
  (base) and nx/2 with the voxel doubled (same FOV; ``64²`` on demo), and both halved. The
  ground truth is made on the same grid, so a coarser grid's MAE is against a coarser truth.

Outputs: ``tradeoff.json`` (every point, every method's Pareto front per variant, the load
average sampled during the sweep; a sweep of some methods merged into an earlier one:
:func:`merge_results`, the earlier sweep's figures kept and this one's under ``added``) and
``tradeoff.png`` (small-FOV MAE against seconds, log x, one panel per variant, one colour and
the registry's marker per method, each method's Pareto front as a step line, every point
labelled by its knob code). ``python -m clrecon bench --only
tradeoff`` runs it (not part of the default bench set: about 50 minutes on 2 cores, mc's five
points before ``skimage`` about 20 of them, and each mcir point tens of minutes more:
docs/performance.md); ``python -m
clrecon.bench.tradeoff --methods mc --merge docs/figures/tradeoff.json --out DIR`` sweeps some
methods and merges them into an earlier sweep.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import tempfile
import threading
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from clrecon.config.scene import load_scene
from clrecon.core import atomic
from clrecon.core.errors import ClreconError
from clrecon.evaluation import metrics
from clrecon.outputs.figures import _plt
from clrecon.outputs.volumes import open_volumes, pitch_key, read_part, recon_path
from clrecon.pipeline.run import run as run_pipeline
from clrecon.reconstruction import interpolation as _methods
from clrecon.reconstruction.iterative import method as mcir
from clrecon.reconstruction.motion import mc_fbp, registration
from clrecon.reconstruction.motion import method as mcm
from clrecon.reconstruction.reconstruct import slice_positions

#: Sweep pitch and the slices of a full sweep ([start, stop) of demo's 16: z = -6, -2, 2, 6 mm).
PITCH = 0.02
FULL_SLICES = (6, 10)
#: Methods whose knob is the number of candidate turns, and its values (0 = all).
TURN_METHODS = ("barycentric", "nearest", "bin", "helical", "r4dct")
MAX_TURNS = (0, 4, 2)
#: mc's points: (code, knob, ``recon.mc`` overrides); the first is the scene's setting (by default the
#: OpenCL Lucas-Kanade for the breathing, TV-L1 for the beat); ``skimage``: scikit-image's Lucas-Kanade
#: for the breathing (the same algorithm in a process pool; needs the motion extra).
MC_POINTS = (("r2", "base", {}), ("r1", "rounds", {"rounds": 1}), ("ds2", "downsample", {"downsample": 2}),
             ("tvl1", "registration", {"registration": "tvl1", "beat_registration": "tvl1"}),
             ("skimage", "registration", {"registration": "lucas_kanade"}))
#: mcir's points: (code, knob, ``recon.mcir`` overrides, whether the run makes mc's volumes too); the first
#: is the scene's setting with mc in the run (``init`` 'auto': OS-SART starts from mc's reference target).
#: 'zero' starts from nothing, so its run has no mc pass (the mcir stage fits the motion model itself).
MCIR_POINTS = (("e1", "base", {}, True), ("e2", "epochs", {"epochs": 2}, True), ("e4", "epochs", {"epochs": 4}, True),
               ("zero", "init", {"init": "zero", "epochs": 4}, False))


@dataclass(frozen=True)
class SweepPoint:
    """One run: ``method`` with ``recon`` / ``scanner`` overrides; ``code`` labels it in the figure.
    ``run_slices``: the run's slice range (start, stop) where it is wider than the slices the
    point is scored on (the sweep's): the MAE is of the sweep's slices, the seconds the run's.
    ``also``: methods the run makes besides ``method`` and its first pass, because ``method`` starts
    from their volumes (mcir from mc's); their seconds are part of the point's (:func:`run_methods`)."""

    method: str
    code: str
    knob: str
    recon: dict = field(default_factory=dict)
    scanner: dict = field(default_factory=dict)
    run_slices: tuple | None = None
    also: tuple = ()

    @property
    def name(self) -> str:
        safe = "".join(ch if ch.isalnum() else "_" for ch in self.code.replace("κ", "k").replace("σ", "s")
                       .replace("²", "2"))
        return f"{self.method}-{safe}"


def _keep(points: list, wanted, attr: str) -> list:
    """The points whose ``attr`` (``method`` or ``code``) is in ``wanted``; ClreconError naming the
    option ``--<attr>s`` for a value no point has."""
    have = [getattr(p, attr) for p in points]
    unknown = sorted(set(wanted) - set(have))
    if unknown:
        raise ClreconError(f"tradeoff --{attr}s: {unknown[0]!r} has no point in this sweep; allowed: "
                           f"{', '.join(dict.fromkeys(have))}")
    return [p for p in points if getattr(p, attr) in wanted]


def sweep_points(scene, quick: bool = False) -> list[SweepPoint]:
    """The sweep's points for ``scene`` (see the module docstring); ``quick``: five of them."""
    views = scene.scanner.views_per_rotation
    nx, ny, vox = scene.recon.nx, scene.recon.ny, scene.recon.voxel_mm
    half_v = {"views_per_rotation": max(1, views // 2)}
    half_g = {"nx": max(1, nx // 2), "ny": max(1, ny // 2), "voxel_mm": vox * nx / max(1, nx // 2)}
    cv, cg = f"v{half_v['views_per_rotation']}", f"{half_g['nx']}²"
    ll = "local_linear"
    if quick:
        return [SweepPoint(ll, "q2", "base"), SweepPoint(ll, "q1", "local_linear_count", {"local_linear_count": 1}),
                SweepPoint(ll, "n5", "local_linear_points",
                           {"local_linear_points": "nearest", "local_linear_count": 5}),
                SweepPoint("nearest", "all", "base"),
                SweepPoint("nearest", "t2", "max_turns", {"max_turns": 2})]
    pts = [SweepPoint(ll, "q2", "base"),
           *[SweepPoint(ll, f"q{n}", "local_linear_count", {"local_linear_count": n}) for n in (1, 3)],
           *[SweepPoint(ll, f"n{n}", "local_linear_points", {"local_linear_points": "nearest", "local_linear_count": n})
             for n in (5, 8)],
           *[SweepPoint(ll, f"κ{k:g}", "kappa", {"kappa": k}) for k in (0.5, 2.0)],
           *[SweepPoint(ll, f"σ{s:g}", "sigma", {"sigma": s}) for s in (0.1, 0.3)]]
    for m in TURN_METHODS:
        pts += [SweepPoint(m, "all" if t == 0 else f"t{t}", "base" if t == 0 else "max_turns",
                           {} if t == 0 else {"max_turns": t}) for t in MAX_TURNS]
    for m in [ll, *TURN_METHODS]:
        pts += [SweepPoint(m, cv, "views_per_rotation", scanner=half_v),
                SweepPoint(m, cg, "grid", recon=half_g),
                SweepPoint(m, f"{cv} {cg}", "views_per_rotation+grid", recon=half_g, scanner=half_v)]
    pts += [SweepPoint("mc", code, knob, {"mc": mc} if mc else {}) for code, knob, mc in MC_POINTS]
    pts += [SweepPoint(mcir.NAME, code, knob, {"mcir": kn} if kn else {}, also=(mc_fbp.NAME,) if with_mc else ())
            for code, knob, kn, with_mc in MCIR_POINTS]
    z_mm = scene.recon.nz * scene.recon.slice_mm
    if z_mm >= mc_fbp.THIN_Z_MM and scene.recon.nz > FULL_SLICES[1] - FULL_SLICES[0]:
        pts.append(SweepPoint("mc", f"z{z_mm:g}", "registration_z", run_slices=(0, scene.recon.nz)))
    return pts


def needs_motion_extra(scene, point: SweepPoint) -> bool:
    """Whether ``point``'s run registers with scikit-image (the motion extra): a second-pass method's
    point whose ``recon.mc`` (the scene's with the point's overrides) names ``lucas_kanade`` for a step."""
    if not _methods.second_pass_methods((point.method,)):
        return False
    knobs = (scene.replace(recon=point.recon) if point.recon else scene).recon.mc_knobs
    return mcm.uses_library(knobs)


def run_methods(method: str, also: tuple = ()) -> tuple[str, ...]:
    """The methods one point of ``method`` runs: a second-pass method with its first pass before it,
    then ``also`` (:attr:`SweepPoint.also`), then the method."""
    if method in _methods.second_pass_methods((method,)):
        return tuple(dict.fromkeys((_methods.first_pass(method), *also, method)))
    return (method,)


def point_seconds(parts: dict, model_seconds: float | None) -> float:
    """A point's seconds from its run's ``method_seconds`` per method (``parts``): their sum, with the
    motion model's fit counted once. Each second-pass method's ``method_seconds`` holds the model's
    seconds (``model_seconds``, the one model of the run, fitted by the first of them and loaded by
    the others: :func:`clrecon.pipeline.stages.mc_reconstruct.motion_model`), so where ``k`` of
    them ran, ``k - 1`` copies are taken off."""
    k = len(_methods.second_pass_methods(tuple(parts)))
    return round(sum(parts.values()) - max(0, k - 1) * float(model_seconds or 0.0), 3)


def pareto_front(seconds, mae) -> list[int]:
    """Indices of the Pareto-optimal points (no other point both faster and more accurate),
    fastest first: sorted by seconds (ties: lower MAE first), kept where the MAE is below every
    faster point's."""
    order = sorted(range(len(seconds)), key=lambda i: (seconds[i], mae[i]))
    front, best = [], np.inf
    for i in order:
        if mae[i] < best:
            front.append(i)
            best = mae[i]
    return front


class _LoadSampler:
    """The 1-minute load average every ``every_s`` seconds in a daemon thread."""

    def __init__(self, every_s: float = 5.0):
        self.samples: list = []
        self._stop = threading.Event()
        self._t = threading.Thread(target=self._loop, args=(every_s,), daemon=True)

    def _loop(self, every_s):
        t0 = time.perf_counter()
        while not self._stop.is_set():
            self.samples.append((round(time.perf_counter() - t0, 1), round(os.getloadavg()[0], 2)))
            self._stop.wait(every_s)

    def __enter__(self):
        self._t.start()
        return self

    def __exit__(self, *exc):
        self._stop.set()
        self._t.join(timeout=10)

    def summary(self) -> dict:
        v = np.array([s[1] for s in self.samples]) if self.samples else np.zeros(1)
        return {"min": float(v.min()), "median": float(np.median(v)), "max": float(v.max()),
                "samples": self.samples}


def run_tradeoff(quick: bool = False, out_dir=None, cache_dir=None, scene="demo", pitch: float = PITCH,
                 slices: tuple | None = None, warmup: bool = True, repeats: int | None = None, methods=None,
                 codes=None, merge=None, log=print) -> dict:
    """Run the sweep; write ``tradeoff.json`` and ``tradeoff.png`` into ``out_dir`` and return the JSON.

    Parameters
    ----------
    quick : bool
        Five points, one central slice, 2 x 2 targets (a smoke test, minutes).
    out_dir : path-like, optional
        Where the JSON and the figure go (default: a new temporary folder, kept). Each point's
        run directory is made under it and removed once its numbers are read.
    cache_dir : path-like, optional
        Projection store (default ``out_dir/cache``); the points of one scan reuse it.
    scene : str or Scene
        ``demo`` by default; tests pass ``tiny`` with its pitch.
    pitch : float
        The one pitch reconstructed (0.02).
    slices : (start, stop), optional
        Slice range (default :data:`FULL_SLICES` clipped to the scene, quick: the middle slice).
    warmup : bool
        Before each timed run, an untimed one of the same scene and method on one slice and
        one target without noise (a second-pass method: two slices and 2 x 2 targets, what its
        registration needs), so that the timed seconds hold no OpenCL kernel builds
        (the local-linear kernel is built per slot count, the backprojector per geometry:
        without it the first point of each build pays it).
    repeats : int, optional
        Timed runs per point (default 2, quick 1); a point's seconds are the fastest repeat's
        (``seconds_repeats`` keeps them all): on a shared machine the load inflates a single
        timing by tens of percent. The MAE is the same in every repeat (deterministic).
    methods : sequence of str, optional
        Only the points of these methods (default: every point of the sweep, less those that register
        with scikit-image (:func:`needs_motion_extra`) where the motion extra is not installed:
        ``skipped`` says so; asked for by name, such a point's run is refused in one line).
    codes : sequence of str, optional
        Only the points with these knob codes (of ``methods`` where given), e.g. ``("z64",)``.
    merge : path-like or dict, optional
        An earlier sweep's ``tradeoff.json`` (or its dict): the result is :func:`merge_results`
        of it and this sweep (its points that this sweep ran replaced, the others kept).
    """
    sc = load_scene(scene) if isinstance(scene, str) else scene
    out = Path(out_dir) if out_dir is not None else Path(tempfile.mkdtemp(prefix="clrecon-tradeoff-"))
    out.mkdir(parents=True, exist_ok=True)
    cache = Path(cache_dir) if cache_dir is not None else out / "cache"
    nz = sc.recon.nz
    if slices is None:
        slices = (nz // 2, nz // 2 + 1) if quick else (
            FULL_SLICES if FULL_SLICES[1] <= nz else (max(0, nz // 2 - 2), min(nz, nz // 2 + 2)))
    slices = (int(slices[0]), int(slices[1]))
    cardiac = resp = None
    if quick:
        cardiac = tuple(sc.cardiac_targets[::2][:2]) if sc.has_cardiac else None
        rt_ = sc.resp_targets
        resp = tuple(rt_[::max(1, len(rt_) // 2)][:2]) if sc.has_respiratory else None
    pk = pitch_key(pitch)
    repeats = max(1, int(repeats if repeats is not None else (1 if quick else 2)))
    points = sweep_points(sc, quick)
    if methods is not None:
        points = _keep(points, methods, "method")
    skipped = {}
    extra = [p for p in points if needs_motion_extra(sc, p)]
    if methods is None and extra:
        try:  # the full sweep runs without the motion extra, less the points registering with scikit-image
            registration.require("skimage.registration")
        except ClreconError as e:
            for m in dict.fromkeys(p.method for p in extra):
                skipped[m] = f"{', '.join(p.code for p in extra if p.method == m)}: {e}"
            log(f"tradeoff: {', '.join(p.name for p in extra)} skipped: {e}")
            points = [p for p in points if p not in extra]
    if codes is not None:
        points = _keep(points, codes, "code")
    base = json.loads(Path(merge).read_text()) if isinstance(merge, (str, Path)) else merge
    rows = []
    t_all = time.perf_counter()
    with _LoadSampler() as load:
        for k, p in enumerate(points):
            s_i = sc.replace(**{sec: vals for sec, vals in (("recon", p.recon), ("scanner", p.scanner)) if vals})
            run_dir = out / "runs" / p.name
            ms = run_methods(p.method, p.also)
            span = tuple(p.run_slices) if p.run_slices else slices
            scored = None  # {variant: {fov: mae}} of the sweep's slices, where the run is wider
            if warmup:
                two = len(ms) > 1  # a second-pass method registers along z: 2 slices, 2 x 2 targets
                n_w = 2 if two else 1
                run_pipeline(s_i.replace(noise={"enabled": False}), out / "runs" / "warmup", methods=ms,
                             pitches=(pitch,), slice_range=(slices[0], min(slices[1], slices[0] + n_w)),
                             cardiac=sc.cardiac_targets[:n_w] if sc.has_cardiac else None,
                             resp=sc.resp_targets[:n_w] if sc.has_respiratory else None,
                             cache_dir=cache, progress=False, report=False, log=lambda *a, **kw: None)
                shutil.rmtree(out / "runs" / "warmup", ignore_errors=True)
            load0 = os.getloadavg()[0]
            reps = []
            for _ in range(repeats):
                t0 = time.perf_counter()
                res = run_pipeline(s_i, run_dir, methods=ms, pitches=(pitch,), slice_range=span,
                                   cardiac=cardiac, resp=resp, cache_dir=cache, progress=False, report=False,
                                   log=lambda *a, **kw: None)
                reps.append((res, time.perf_counter() - t0))
                if span != slices and scored is None:
                    scored = {v: scored_mae(run_dir, s_i, pk, v, p.method, (slices[0] - span[0], slices[1] - span[0]))
                              for v in res["metrics"][pk]}
                shutil.rmtree(run_dir, ignore_errors=True)
            res, wall = reps[0]
            for v, bym in res["metrics"][pk].items():
                met = bym[p.method]
                parts = [{m: r_["method_seconds"][pk][v][m] for m in ms} for r_, _ in reps]
                secs = [point_seconds(pt, _model_notes(r_, pk, v)["model_seconds"]) for pt, (r_, _) in
                        zip(parts, reps, strict=True)]
                i_best = int(np.argmin(secs))
                best = reps[i_best][0]
                plan = best.get("method_plan_seconds", {}).get(pk, {})
                mae = scored[v] if scored else {fov: met[fov]["mae_hu"] for fov in ("small", "large")}
                row = {**asdict(p), "name": p.name, "variant": v,
                       "mae_small_hu": mae["small"], "mae_large_hu": mae["large"],
                       "seconds": min(secs), "seconds_repeats": secs,
                       "plan_seconds": plan.get(p.method) if len(ms) == 1 else sum(plan.get(m, 0.0) for m in ms),
                       "mae_same_in_repeats": all(r_["metrics"][pk][v][p.method]["small"]["mae_hu"]
                                                  == met["small"]["mae_hu"] for r_, _ in reps),
                       "run_seconds": round(wall, 2), "load_before": round(load0, 2),
                       "simulated": res["stages"]["simulate"]["per_pitch"][pk]["projections_simulated"]}
                if len(ms) > 1:
                    row["seconds_parts"] = parts[i_best]
                    row.update(_model_notes(best, pk, v))
                if p.method == mcir.NAME:
                    row["solver"] = _solver_notes(best, pk, v)
                if scored:  # the run's own pooled MAE, over all its slices
                    row["mae_run_slices_hu"] = {fov: met[fov]["mae_hu"] for fov in ("small", "large")}
                rows.append(row)
            log(f"tradeoff {k + 1}/{len(points)} {p.method} {p.code}: {wall:.1f} s, load {load0:.2f}; "
                + ", ".join(f"{r['variant']} MAE {r['mae_small_hu']:.1f}/{r['mae_large_hu']:.1f} HU "
                            f"{r['seconds']:.2f} s" for r in rows if r["name"] == p.name))
    sweep_s = round(time.perf_counter() - t_all, 1)
    result = {"scene": sc.name, "pitch": pitch, "slices": list(slices), "slices_z_mm": _slice_z(sc, slices),
              "targets": "all" if not quick else {"cardiac": cardiac, "resp": resp},
              "quick": quick, "repeats": repeats, "points": rows, "fronts": fronts(rows), "sweep_seconds": sweep_s,
              "load_average_1min": load.summary(), "logical_cores": os.cpu_count(),
              "methods": list(dict.fromkeys(p.method for p in points)), "run_points": [p.name for p in points],
              "seconds_definition": SECONDS_DEFINITION, **({"skipped": skipped} if skipped else {})}
    if base is not None:
        result = merge_results(base, result)
    atomic.write_json(out / "tradeoff.json", result, indent=1, ensure_ascii=False)
    plot_tradeoff(result, out / "tradeoff.png")
    result["out_dir"] = str(out)
    return result


#: What a point's ``seconds`` are (``tradeoff.json``; the module docstring says more).
SECONDS_DEFINITION = ("results.json method_seconds: the method's plan (weights + candidate search) + interpolation "
                      "+ FBP of that variant, this machine's OpenCL device; mc: its method_seconds (every round's "
                      "registration, model fit and motion-compensated backprojection, then the final pass) + its "
                      "first pass's (barycentric's), seconds_parts each; mcir: the method_seconds of its first pass, "
                      "of mc where it starts from mc's image, and its own (OS-SART's setup, epochs and target "
                      "sampling), the motion model's fit (in both mc's and mcir's) counted once, seconds_parts as "
                      "recorded and model_seconds; the fastest of `repeats` timed runs")


def _model_notes(res: dict, pk: str, variant: str) -> dict:
    """A second-pass point's model figures from its ``results.json`` (the run's one motion model,
    noted under mc's name whichever stage fitted it): ``model_error`` (heart and body, mm RMS
    against the phantom's motion), ``model_seconds``, the run's thin-z ``warning`` and the
    ``registrations`` it ran (each step's: ``breathing``, ``beat``)."""
    info = res.get("stages", {}).get("registration", {}).get(mc_fbp.NAME, {}).get(pk, {}).get(variant, {})
    err = info.get("error_against_phantom_motion", {})
    return {"model_error": {k: err[k] for k in ("heart", "body_outside_lungs") if k in err},
            "model_seconds": info.get("seconds"), "warning": info.get("warning"),
            "registrations": info.get("registrations")}


def _solver_notes(res: dict, pk: str, variant: str) -> dict:
    """An mcir point's OS-SART figures per slab from its ``results.json``: the start, the epochs run
    (residual after each), the relative residual at the start and the end, why it stopped."""
    info = res.get("stages", {}).get(mcir.NAME, {})
    out = {"start": info.get("start")}
    for slab, s in info.get("slabs", {}).get(pk, {}).get(variant, {}).items():
        h = s.get("sart", {})
        out[slab] = {"epochs": len(h.get("running", [])), "initial": h.get("initial"), "final": h.get("final"),
                     "stop": h.get("stop")}
    return out


#: Keys that must agree for two sweeps to share a figure.
_SAME_SWEEP = ("scene", "pitch", "slices", "targets", "quick")


def merge_results(base: dict, new: dict) -> dict:
    """``base`` (an earlier sweep's ``tradeoff.json``) with ``new``'s points in place of its points
    of the same name (``new["run_points"]``); its other points, and ``base``'s sweep figures
    (seconds, load, repeats), are kept as they were; ``new``'s go into ``added`` (one entry per
    merge; an older entry whose points are all run again is dropped). Fronts are recomputed.
    ClreconError where the two are not the same sweep (scene, pitch, slices, targets, quick)."""
    for key in _SAME_SWEEP:
        if base.get(key) != new.get(key):
            raise ClreconError(f"tradeoff merge: {key} = {new.get(key)!r} in this sweep but {base.get(key)!r} in "
                               f"the earlier one; merge only sweeps of the same scene, pitch, slices and targets")
    names = set(new["run_points"])
    rows = [r for r in base["points"] if r["name"] not in names] + list(new["points"])
    added = [a for a in base.get("added", []) if not set(a["run_points"]) <= names]
    added.append({k: new[k] for k in ("methods", "run_points", "repeats", "sweep_seconds", "load_average_1min",
                                      "logical_cores")})
    return {**base, "points": rows, "fronts": fronts(rows), "added": added,
            "seconds_definition": new["seconds_definition"]}


def scored_mae(run_dir, scene, pk: str, variant: str, method: str, sel: tuple) -> dict:
    """``{"small": mae, "large": mae}`` (HU) of ``method``'s volumes of ``variant`` in the run at
    ``run_dir`` against its ground truth, pooled over every target and the run's slices
    ``sel[0] .. sel[1]-1`` (indices into the run's slices), the FOVs of
    :func:`clrecon.evaluation.metrics.fov_masks` (the run's ``metrics`` over those slices)."""
    masks = metrics.fov_masks(metrics.MetricsConfig.from_scene(scene))
    z = {"z": slice(int(sel[0]), int(sel[1]))}
    with open_volumes(run_dir) as f:
        rec = read_part(f, recon_path(pk, variant, method), z)
        truth = read_part(f, "groundtruth", z)
    return {fov: metrics.abs_error_stats(rec, truth, masks[fov])["mae_hu"] for fov in ("small", "large")}


def _slice_z(sc, slices) -> list:
    return [float(z) for z in slice_positions(sc, tuple(slices))]


def fronts(rows) -> dict:
    """``{variant: {method: [code, ...]}}``: each method's Pareto front (small-FOV MAE vs seconds), fastest first."""
    out: dict = {}
    for v in dict.fromkeys(r["variant"] for r in rows):
        out[v] = {}
        for m in dict.fromkeys(r["method"] for r in rows):
            sel = [r for r in rows if r["variant"] == v and r["method"] == m]
            idx = pareto_front([r["seconds"] for r in sel], [r["mae_small_hu"] for r in sel])
            out[v][m] = [sel[i]["code"] for i in idx]
    return out


# ---------------------------------------------------------------------------------------
# figure
def _method_style() -> dict:
    """Method -> (colour, marker, label): colours by registry order, marker and label from the registry."""
    return {n: (f"C{i}", m.marker, m.label) for i, (n, m) in enumerate(_methods.METHODS.items())}


def _place_labels(fig, ax, items, marker_px: float = 5.0, others=()) -> None:
    """Annotate ``items`` (x, y, text, colour) next to their points without overlaps where possible:
    each label tries a ring of offsets and takes the first whose box meets no placed label, no
    marker (of ``items`` or of the unlabelled ``others``) and stays inside the axes (else the one
    meeting the fewest)."""
    from matplotlib.transforms import Bbox

    renderer = fig.canvas.get_renderer()
    pts = [(x, y) for x, y, _, _ in items] + [(x, y) for x, y, _, _ in others]
    xy = ax.transData.transform(np.array(pts)) if pts else np.zeros((0, 2))
    markers = [Bbox.from_extents(px - marker_px, py - marker_px, px + marker_px, py + marker_px) for px, py in xy]
    axbox = ax.get_window_extent(renderer)
    offsets = [(5, 3), (5, -9), (-5, 3), (-5, -9), (0, 7), (0, -13), (9, -3), (-9, -3),
               (12, 11), (-12, 11), (12, -17), (-12, -17), (0, 16), (0, -22)]
    placed = []
    for k, (x, y, text, col) in enumerate(items):
        best = None
        for dx, dy in offsets:
            ha = "left" if dx > 0 else ("right" if dx < 0 else "center")
            ann = ax.annotate(text, (x, y), xytext=(dx, dy), textcoords="offset points", fontsize=6, color=col,
                              ha=ha, va="bottom")
            bb = ann.get_window_extent(renderer)
            hits = sum(bb.overlaps(b) for b in placed) + sum(bb.overlaps(b) for j, b in enumerate(markers) if j != k)
            hits += 0 if (axbox.contains(bb.x0, bb.y0) and axbox.contains(bb.x1, bb.y1)) else 1
            if best is None or hits < best[2]:
                if best is not None:
                    best[0].remove()
                best = (ann, bb, hits)
            else:
                ann.remove()
            if hits == 0:
                break
        placed.append(best[1])


def _sec(row) -> float:
    """A point's seconds for the log axis (results.json rounds to 1 ms: at least 1 ms)."""
    return max(float(row["seconds"]), 1e-3)


#: The zoomed panels show the points with an MAE up to this multiple of the variant's lowest.
ZOOM_MAE_FACTOR = 1.5


def _draw_points(ax, rows, present, style, x_hi):
    """Every method's points (filled on its Pareto front, open when dominated) and its front as a step line."""
    for m in present:
        col, mk, _ = style[m]
        sel = [r for r in rows if r["method"] == m]
        if not sel:
            continue
        x = [_sec(r) for r in sel]
        y = [r["mae_small_hu"] for r in sel]
        front = pareto_front(x, y)
        on = set(front)
        ax.scatter([x[i] for i in front], [y[i] for i in front], marker=mk, s=42, color=col, edgecolor="k",
                   lw=0.5, zorder=4)
        off = [i for i in range(len(x)) if i not in on]
        ax.scatter([x[i] for i in off], [y[i] for i in off], marker=mk, s=42, facecolor="none", edgecolor=col,
                   lw=1.2, zorder=3)
        fx, fy = [x[i] for i in front], [y[i] for i in front]
        ax.step(fx + [x_hi], fy + [fy[-1]], where="post", color=col, lw=1.2, alpha=0.8, zorder=2)


def _log_seconds_axis(ax):
    from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter

    ax.set_xscale("log")
    ax.xaxis.set_major_locator(LogLocator(subs=(1.0, 2.0, 5.0)))
    ax.xaxis.set_major_formatter(FuncFormatter(lambda t, _: f"{t:g}"))
    ax.xaxis.set_minor_formatter(NullFormatter())
    ax.tick_params(labelsize=8)
    ax.grid(alpha=0.3, which="both")
    ax.set_xlabel("seconds (log): plan + interpolation + FBP; mc, mcir: + first pass, model fit, MC backprojection "
                  "(+ OS-SART)", fontsize=8)
    ax.set_ylabel("MAE vs ground truth, small FOV (HU)", fontsize=8)


def plot_tradeoff(result: dict, path) -> Path:
    """The trade-off figure of a :func:`run_tradeoff` result (see the module docstring); writes ``path``.

    One column per noise variant; top row every point, bottom row a zoom on the points within
    ``ZOOM_MAE_FACTOR`` of the variant's lowest MAE (the dashed box above), where the good
    settings crowd. Points are labelled by knob code in the zoom, and outside it in the top row.
    """
    plt = _plt()
    from matplotlib.lines import Line2D
    from matplotlib.patches import Rectangle

    rows = result["points"]
    variants = list(dict.fromkeys(r["variant"] for r in rows))
    variants.sort(key=lambda v: v != "noise-free")
    style = _method_style()
    present = [m for m in _methods.figure_order() if any(r["method"] == m for r in rows)]
    nv = len(variants)
    fig, axes = plt.subplots(2, nv, figsize=(6.6 * nv + 1.6, 10.0), squeeze=False, layout="constrained", dpi=110,
                             height_ratios=(1.0, 1.25))
    secs = [_sec(r) for r in rows]
    lo, hi = min(secs) / 1.25, max(secs) * 2.0  # room for the slowest point's label on its right
    boxes = {}
    for k, v in enumerate(variants):
        rv = [r for r in rows if r["variant"] == v]
        maes = [r["mae_small_hu"] for r in rv]
        span = max(maes) - min(maes)
        ax, az = axes[0, k], axes[1, k]
        _draw_points(ax, rv, present, style, hi)
        ax.set_xlim(lo, hi)
        ax.set_ylim(min(maes) - 0.06 * span - 0.5, max(maes) + 0.08 * span + 0.5)
        _log_seconds_axis(ax)
        ax.set_title(f"{v}: every point", fontsize=9)
        y_cut = ZOOM_MAE_FACTOR * min(maes)
        near = [r for r in rv if r["mae_small_hu"] <= y_cut]
        zs = [_sec(r) for r in near]
        zy = [r["mae_small_hu"] for r in near]
        zx0, zx1 = min(zs) / 1.3, max(zs) * 1.3
        zy0, zy1 = min(zy) - 0.04 * (max(zy) - min(zy)) - 0.3, max(zy) + 0.06 * (max(zy) - min(zy)) + 0.3
        boxes[v] = (zx0, zx1, zy0, zy1)
        ax.add_patch(Rectangle((zx0, zy0), zx1 - zx0, zy1 - zy0, fill=False, ls="--", lw=0.8, ec="0.4", zorder=1))
        _draw_points(az, rv, present, style, zx1 * 2)
        az.set_xlim(zx0, zx1)
        az.set_ylim(zy0, zy1)
        _log_seconds_axis(az)
        az.set_title(f"{v}: zoom on MAE <= {ZOOM_MAE_FACTOR:g} x the lowest (dashed box above)", fontsize=9)
    handles = [Line2D([], [], ls="-", lw=1.2, marker=style[m][1], color=style[m][0], markeredgecolor="k",
                      markeredgewidth=0.5, label=style[m][2]) for m in present]
    handles += [Line2D([], [], ls="", marker="o", color="0.4", markeredgecolor="k", markeredgewidth=0.5,
                       label="on the front"),
                Line2D([], [], ls="", marker="o", markerfacecolor="none", markeredgecolor="0.4", label="dominated")]
    fig.legend(handles=handles, fontsize=7, loc="outside right upper", title="method (step: Pareto front)",
               title_fontsize=7)
    z = result.get("slices_z_mm") or []
    fig.suptitle(f"Error against run time, {result['scene']} pitch {result['pitch']:g}, slices z = "
                 f"{', '.join(f'{t:g}' for t in z)} mm, all targets" if not result.get("quick") else
                 f"Error against run time, {result['scene']} pitch {result['pitch']:g} (quick)", fontsize=9)
    fig.supxlabel("labels: qN = N nearest per quadrant, nN = N nearest (local linear; base q2 κ1 σ0.15); κ, σ: kernel "
                  "widths; all / tN = every / the N nearest-in-z candidate turns; vN = N views per rotation; N² = "
                  "N x N image grid (same FOV);\nmc (base r2): rN = N registration rounds, ds2 = registration "
                  "at half the in-plane voxels, tvl1 = TV-L1 for both registration steps, zN = the base on a "
                  "run of N mm of slices scored on these; mcir (base e1): eN = N OS-SART epochs from mc's image, "
                  "zero = 4 epochs from zero", fontsize=6.5)
    fig.canvas.draw()  # lay out once, then place the labels in the final display coordinates
    fig.set_layout_engine("none")
    for k, v in enumerate(variants):
        zx0, zx1, zy0, zy1 = boxes[v]
        items = [(_sec(r), r["mae_small_hu"], r["code"], style[r["method"]][0])
                 for m in present for r in rows if r["variant"] == v and r["method"] == m]
        inside = [zx0 <= x <= zx1 and zy0 <= y <= zy1 for x, y, _, _ in items]
        _place_labels(fig, axes[0, k], [it for it, i in zip(items, inside, strict=True) if not i],
                      others=[it for it, i in zip(items, inside, strict=True) if i])
        _place_labels(fig, axes[1, k], [it for it, i in zip(items, inside, strict=True) if i])
    path = Path(path)
    atomic.save_figure(fig, path, dpi=110)
    plt.close(fig)
    return path


def format_table(result: dict) -> str:
    """Plain-text table of a :func:`run_tradeoff` result (bench report)."""
    lines = [f"{'method':13s} {'knob':12s} {'variant':10s} {'MAE small':>9s} {'MAE large':>9s} {'s':>7s} "
             f"{'plan s':>7s}  front"]
    fr = result.get("fronts", {})
    for r in result["points"]:
        on = r["code"] in fr.get(r["variant"], {}).get(r["method"], [])
        lines.append(f"{r['method']:13s} {r['code']:12s} {r['variant']:10s} {r['mae_small_hu']:>9.2f} "
                     f"{r['mae_large_hu']:>9.2f} {r['seconds']:>7.2f} "
                     f"{(r['plan_seconds'] if r['plan_seconds'] is not None else float('nan')):>7.2f}  "
                     f"{'*' if on else ''}")
    return "\n".join(lines)


def run(quick: bool = False, repeats: int = 3, log=print) -> dict:
    """The bench's ``tradeoff``: :func:`run_tradeoff` on ``demo``, its progress to stderr
    (one run per point)."""
    return run_tradeoff(quick, log=lambda *a, **k: log(*a, file=sys.stderr))


def report_lines(tr: dict) -> list[str]:
    """The section's lines of the bench report."""
    ld = tr["load_average_1min"]
    out = [""]
    out.append(f"6. error against run time: {tr['scene']} pitch {tr['pitch']:g}, slices "
               f"{tr['slices'][0]}:{tr['slices'][1]}, {len(tr['points'])} points in {tr['sweep_seconds']:.0f} s "
               f"(load {ld['min']:.2f}..{ld['max']:.2f}, median {ld['median']:.2f}); "
               f"{tr['out_dir']}/tradeoff.png; * = on the method's Pareto front")
    out.extend("   " + line for line in format_table(tr).splitlines())
    return out


def main(argv=None) -> dict:
    """``python -m clrecon.bench.tradeoff [--methods mc] [--merge tradeoff.json] [--out DIR]``: the
    sweep of some methods (default all), merged into an earlier sweep's JSON where given."""
    ap = argparse.ArgumentParser(prog="python -m clrecon.bench.tradeoff", description=main.__doc__)
    ap.add_argument("--methods", help="comma list: only these methods' points (default: every point)")
    ap.add_argument("--codes", help="comma list: only the points with these knob codes (e.g. z64)")
    ap.add_argument("--merge", metavar="JSON", help="an earlier sweep's tradeoff.json: its points of the other "
                    "methods are kept, of these methods replaced")
    ap.add_argument("--out", metavar="DIR", help="where tradeoff.json and tradeoff.png go (default: a new "
                    "temporary folder)")
    ap.add_argument("--cache", metavar="DIR", help="projection store (default: OUT/cache)")
    ap.add_argument("--repeats", type=int, help="timed runs per point (default 2)")
    a = ap.parse_args(argv)
    res = run_tradeoff(out_dir=a.out, cache_dir=a.cache, repeats=a.repeats, merge=a.merge,
                       methods=tuple(a.methods.split(",")) if a.methods else None,
                       codes=tuple(a.codes.split(",")) if a.codes else None,
                       log=lambda *x, **k: print(*x, file=sys.stderr, flush=True))
    print(format_table(res))
    print(f"{res['out_dir']}/tradeoff.json, tradeoff.png")
    return res


if __name__ == "__main__":
    main()
