"""Command line: ``python -m clrecon {run,sweep,scenes,devices,view,export,phantom,bench}`` (a thin layer
over the modules).

User errors (:class:`clrecon.core.errors.ClreconError`) print one line and exit with status 2;
``--debug`` shows the traceback instead.
"""

from __future__ import annotations

import argparse
import contextlib
import errno
import os
import signal
import sys
import threading

from clrecon.core.errors import ClreconError


def _floats(text: str) -> list[float]:
    return [float(x) for x in text.split(",") if x.strip()]


def parse_targets(text: str):
    """``CARDIAC/RESP`` lists, e.g. ``0,0.4/0.05,0.95``; either side may be empty (= the scene's)."""
    c, sep, r = text.partition("/")
    try:
        return (_floats(c) or None), (_floats(r) or None)
    except ValueError:
        raise ClreconError(f"--targets {text!r}: expected CARDIAC/RESP comma lists, e.g. 0,0.4/0.05,0.95") from None


def parse_slices(text: str):
    a, sep, b = text.partition(":")
    try:
        return int(a), int(b)
    except ValueError:
        raise ClreconError(f"--slices {text!r}: expected START:STOP slice indices, e.g. 4:8") from None


def cmd_run(args) -> int:
    from clrecon.config.scene import load_scene
    from clrecon.pipeline.run import run

    scene = load_scene(args.scene)
    methods = [m.strip() for m in args.methods.split(",")] if args.methods else None
    cardiac, resp = parse_targets(args.targets) if args.targets else (None, None)
    slices = parse_slices(args.slices) if args.slices else None
    pitches = _floats(args.pitch) if args.pitch else None
    out = args.out or f"runs/{scene.name}"
    with _client(args) as client:
        res = run(scene, out, methods=methods, cardiac=cardiac, resp=resp, slice_range=slices, pitches=pitches,
                  cache_dir=args.cache, progress=not args.no_progress, force=args.force, client=client,
                  executor=args.executor)
    print(f"wrote {out}/results.json, {out}/report.md, {out}/volumes.h5 in {res['total_seconds']:.1f} s")
    from clrecon.evaluation.claims import claim_summary_lines
    from clrecon.outputs.report import summary_lines
    for line in summary_lines(res) + claim_summary_lines(res):
        print(line)
    return 0


def _client(args):
    """``--workers N`` / ``--cluster ADDRESS``: a Dask client for the run (docs/distributed.md), else none."""
    tls = (args.tls_ca_file, args.tls_cert, args.tls_key)
    has_tls = any(v is not None for v in tls)
    if has_tls and not (args.cluster or "").lower().startswith("tls://"):
        where = f"--cluster {args.cluster}" if args.cluster else "no --cluster"
        raise ClreconError(f"--tls-ca-file/--tls-cert/--tls-key with {where}: the certificates are for a tls:// "
                           f"scheduler, e.g. --cluster tls://head:8786 (docs/distributed.md)")
    executor = getattr(args, "executor", None)
    if executor in ("serial", "local") and (args.workers is not None or args.cluster is not None):
        raise ClreconError(f"--executor {executor} with --workers/--cluster: the workers are Dask's; give "
                           f"--executor dask or leave --executor out")
    if args.workers is None and args.cluster is None:
        if executor != "dask":
            return contextlib.nullcontext(None)
        args.workers = os.cpu_count() or 1  # --executor dask alone: a local cluster, one worker per core
    from clrecon.pipeline.distributed import connect, tls_security

    security = tls_security(*tls, address=args.cluster) if has_tls else None
    return connect(workers=args.workers, cluster=args.cluster, security=security)


def cmd_sweep(args) -> int:
    from clrecon.pipeline.sweep import load_study, run_study

    study = load_study(args.study)
    with _client(args) as client:
        summary = run_study(study, out=args.out, cache_dir=args.cache, client=client, progress=not args.no_progress)
    print(f"wrote {summary['table_csv']}, {summary['table_md']} and {len(summary['figures'])} figures "
          f"({summary['points_run']} points run, {summary['points_kept']} kept from an earlier sweep)")
    return 0


def _add_cluster_args(p) -> None:
    p.add_argument("--workers", type=int, metavar="N",
                   help="compute the units on a local Dask cluster of N worker processes (needs clrecon[dask])")
    p.add_argument("--cluster", metavar="ADDRESS",
                   help="compute the units on the Dask scheduler at ADDRESS, e.g. tcp://10.0.0.1:8786; the cache "
                        "and run folders must be on a file system every worker sees (docs/distributed.md); "
                        "tls://HOST:PORT for an encrypted cluster (with --tls-* or Dask's distributed.comm.tls config)")
    p.add_argument("--tls-ca-file", metavar="PEM",
                   help="with --cluster tls://: the CA certificate that signed the scheduler's and workers' "
                        "certificates")
    p.add_argument("--tls-cert", metavar="PEM", help="with --cluster tls://: this client's certificate")
    p.add_argument("--tls-key", metavar="PEM",
                   help="with --cluster tls://: this client's private key (omit if appended to --tls-cert)")


def cmd_scenes(args) -> int:
    from clrecon.pipeline.costs import describe_scenes

    print(describe_scenes())
    return 0


def cmd_devices(args) -> int:
    import json

    from clrecon.core.drivers import format_devices, list_devices
    from clrecon.pipeline.driver_choice import format_timing_report, timing_report

    listing = list_devices(probe_again=args.probe_again)
    if not listing["clrecon_device"]:
        listing["timing"] = timing_report(time_again=args.probe_again)
    if args.json:
        print(json.dumps(listing, indent=1))
    else:
        print(format_devices(listing))
        if "timing" in listing:
            print("\n" + format_timing_report(listing["timing"]))
    return 0


def cmd_view(args) -> int:
    try:
        from clrecon.viewer.app import screenshot, view
    except ImportError as e:
        raise ClreconError(f"the viewer is not installed with this package ({e})") from None
    choices = dict(method=args.method, pitch=args.pitch, variant=args.variant, cardiac=args.cardiac,
                   resp=args.resp, difference=args.difference, window=args.window)
    if args.screenshot:
        try:
            w, h = (int(v) for v in args.size.lower().split("x"))
        except ValueError:
            raise ClreconError(f"--size {args.size!r}: expected WIDTHxHEIGHT, e.g. 1300x1000") from None
        path, title = screenshot(args.run_dir, args.screenshot, size=(w, h), **choices)
        print(f"wrote {path}: {title}")
        return 0
    view(args.run_dir, **choices)
    return 0


def cmd_export(args) -> int:
    from clrecon.outputs.export import export

    index = export(args.run_dir, args.format, method=args.method, pitch=args.pitch, variant=args.variant,
                   out=args.out, keep_identifiers=args.keep_identifiers, scene=args.scene)
    if index.get("format") == "dicom-ct-pd":
        print(f"wrote {index['files']['n_projections']} projections ({index['variant']}, pitch {index['pitch']:g}) "
              f"as DICOM-CT-PD with {index['files']['scene']} to {index['out']}")
        return 0
    what = (index["method"] if index["pitch_key"] is None
            else f"{index['method']} {index['pitch_key']} {index['variant']}")
    n_files = sum(len(t["files"]) for t in index["targets"])
    print(f"wrote {len(index['targets'])} targets of {what} as {args.format} ({n_files} files) to {index['out']}")
    return 0


def cmd_bench(args) -> int:
    from clrecon.bench.suite import format_report, run_bench, write_json

    only = [x.strip() for x in args.only.split(",") if x.strip()] if args.only else None
    if args.drivers:
        only = (only or []) + ["drivers"]
    res = run_bench(quick=args.quick, only=only, repeats=args.repeats)
    print(format_report(res))
    if args.json:
        write_json(res, args.json)
        print(f"wrote {args.json}")
    return 0


def parse_grid(text: str):
    """``NCxNA`` (e.g. ``5x3``) -> (5, 3)."""
    try:
        nc, na = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise ClreconError(f"--grid {text!r}: expected NCxNA, counts of cardiac phases and amplitudes, "
                           f"e.g. 5x3") from None
    return nc, na


def cmd_phantom(args) -> int:
    from clrecon.config.scene import load_scene
    from clrecon.simulation.phantom_export import export_phantom

    scene = load_scene(args.scene)
    grid = parse_grid(args.grid) if args.grid else None
    if grid is None and args.frames is None:
        raise ClreconError("phantom export: give --frames N (a time series) or --grid NCxNA (NIfTI)")
    res = export_phantom(scene, args.out, args.format, args.frames or 0, voxel_mm=args.voxel_mm, grid=grid)
    nz, ny, nx = res["shape"]
    print(f"wrote {len(res['files'])} {args.format} frames of {nx} x {ny} x {nz} voxels of {res['voxel_mm']:g} mm "
          f"and {res['header']} to {res['out']}; scene table: {res['phantom_toml']}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="clrecon", description=__doc__.splitlines()[0])
    p.add_argument("--debug", action="store_true", help="show tracebacks")
    sub = p.add_subparsers(dest="cmd", required=True)

    r = sub.add_parser("run", help="simulate (or reuse) -> reconstruct 5DCT -> evaluate -> report")
    r.add_argument("--scene", default="demo", help="built-in scene name or TOML file (default: demo)")
    r.add_argument("--out", help="run directory (default: runs/<scene>)")
    from clrecon.reconstruction.interpolation import METHODS  # the method registry

    r.add_argument("--methods", help="comma list from " + ",".join(METHODS.names))
    r.add_argument("--targets", help="CARDIAC/RESP lists, e.g. 0,0.4/0.05,0.95 (empty side = the scene's)")
    r.add_argument("--slices", help="START:STOP slice index range (only the projections those need are simulated)")
    r.add_argument("--pitch", help="comma list of the scene's pitches to run")
    r.add_argument("--cache", help="projection store folder (default: $CLRECON_CACHE or ~/.cache/clrecon)")
    r.add_argument("--no-progress", action="store_true", help=NO_PROGRESS_HELP)
    r.add_argument("--force", action="store_true",
                   help="run even if the pre-flight check says the memory or disk will not suffice")
    r.add_argument("--executor", choices=("serial", "local", "dask"),
                   help="who runs the stages: serial (one after the other, in this process), local (default: "
                        "overlapped on this machine's cores), dask (the units on Dask workers; implied by "
                        "--workers/--cluster; alone: a local cluster, one worker per core); the results are the "
                        "same bit for bit (docs/data-flow.md \"Executors\")")
    _add_cluster_args(r)
    r.set_defaults(func=cmd_run)

    sw = sub.add_parser("sweep", help="a study: a grid of runs (scenes, pitches, methods, kappa/sigma, rhythms), "
                                      "a summary table and figures; resumable (docs/distributed.md)")
    sw.add_argument("study", help="study TOML file")
    sw.add_argument("--out", help="study folder (default: the file's `out`, else runs/<study name>)")
    sw.add_argument("--cache", help="projection store folder (default: $CLRECON_CACHE or ~/.cache/clrecon)")
    sw.add_argument("--no-progress", action="store_true", help=NO_PROGRESS_HELP)
    _add_cluster_args(sw)
    sw.set_defaults(func=cmd_sweep)

    s = sub.add_parser("scenes", help="list the built-in scenes with their size, disk and memory")
    s.set_defaults(func=cmd_scenes)

    dv = sub.add_parser("devices", help="every OpenCL platform and device, whether each builds and runs clrecon's "
                                        "probe kernel, and which one runs by default (docs/drivers.md)")
    dv.add_argument("--json", action="store_true", help="print the listing as JSON")
    dv.add_argument("--probe-again", action="store_true",
                    help="probe and time every device again (forget remembered verdicts and timings)")
    dv.set_defaults(func=cmd_devices)

    v = sub.add_parser("view", help="3D viewer of a run's 5D volumes (pyvista); --screenshot renders offscreen")
    v.add_argument("run_dir", help="run directory (with volumes.h5)")
    v.add_argument("--screenshot", metavar="FILE", help="render offscreen to this PNG and exit (no display needed)")
    v.add_argument("--method", help="reconstruction method, groundtruth or phantom (default: best method present)")
    v.add_argument("--pitch", help="pitch, e.g. 0.02 (default: the smallest present)")
    v.add_argument("--variant", help="noisy or noise-free (default: noisy if present)")
    v.add_argument("--cardiac", help="cardiac phase target, e.g. 0.4 or 40%% (default: the middle target)")
    v.add_argument("--resp", help="respiratory amplitude target, e.g. 0.55 or 55%% (default: the middle target)")
    v.add_argument("--difference", action="store_true", help="show the method minus the ground truth")
    v.add_argument("--window", default="mediastinum", help="lung, mediastinum or cardiac (default: mediastinum)")
    v.add_argument("--size", default="1300x1000", help="screenshot size WIDTHxHEIGHT in pixels")
    v.set_defaults(func=cmd_view)

    e = sub.add_parser("export", help="write a run's 5D volumes as DICOM CT series or NIfTI files, one per target")
    e.add_argument("run_dir", help="run directory (with volumes.h5)")
    from clrecon.outputs.writers import WRITERS  # the one list of export formats
    e.add_argument("--format", required=True, choices=WRITERS.names)
    e.add_argument("--method", help="reconstruction method, groundtruth or phantom (default: best method present)")
    e.add_argument("--pitch", help="pitch, e.g. 0.02 (default: the smallest present)")
    e.add_argument("--variant", help="noisy or noise-free (default: noisy if present)")
    e.add_argument("--out", help="output folder (default: RUN_DIR/export/FORMAT/SOURCE)")
    e.add_argument("--keep-identifiers", action="store_true",
                   help="measured scans: copy the input's patient attributes into the exported DICOM (default: none)")
    e.add_argument("--scene", help="measured scans: the scene file the run was made from, for an export that reads "
                                   "the input again (dicom-ct-pd, --keep-identifiers): results.json records the "
                                   "series only by its digest (docs/patient-data.md 'Patient data')")
    e.set_defaults(func=cmd_export)

    ph = sub.add_parser("phantom", help="voxel phantoms: export the analytic phantom as XCAT or NIfTI frames")
    phs = ph.add_subparsers(dest="phantom_cmd", required=True)
    pe = phs.add_parser("export", help="write the scene's analytic phantom as 4D frames "
                                       "(for [phantom] kind = \"voxel\")")
    pe.add_argument("out", help="output folder (frames, the XCAT log or frames.toml, and phantom.toml)")
    pe.add_argument("--format", required=True, choices=("xcat", "nifti"))
    pe.add_argument("--frames", type=int, help="frames along the scene's time trajectory (over its longest scan)")
    pe.add_argument("--grid", help="NIfTI only: frames on a cardiac x amplitude grid instead, e.g. 5x3")
    pe.add_argument("--scene", default="demo", help="built-in scene name or TOML file (default: demo)")
    pe.add_argument("--voxel-mm", type=float, help="cubic voxel size (default: half the scene's recon voxel)")
    pe.set_defaults(func=cmd_phantom)

    b = sub.add_parser("bench", help="throughput figures, each with a reference measured in the same run")
    b.add_argument("--quick", action="store_true", help="smaller sizes and one repeat (about a minute)")
    b.add_argument("--json", metavar="FILE", help="also write every number and the machine description here")
    b.add_argument("--only", help="comma list from backprojection,projector,voxel-projector,interpolation,"
                   "end-to-end,memory,scaling,measured and the paper-scale paper-projector,noise,paper-fbp,"
                   "groundtruth; also, only when named: tradeoff (error against run time, ~50 min), truth_free "
                   "(cost of recon.truth_free against the reconstruction, ~2 min), drivers, mc (the mc method's cost "
                   "against the paper methods' on demo at pitch 0.10, ~5 min), iterative (the "
                   "voxel projector beside its matched transpose, the warp beside its transpose, ~10 s). The A/B "
                   "benchmarks of the code's own levers are in a checkout's benchmarks/ folder (benchmarks/README.md)")
    b.add_argument("--drivers", action="store_true",
                   help="every CPU OpenCL driver that passes the probe side by side: projector, SSRB, interpolation, "
                        "backprojection, noise and the demo cold (docs/drivers.md); with --only, added to it")
    b.add_argument("--repeats", type=int, help="timed repeats per figure (default 3; --quick 1); the median is shown")
    b.set_defaults(func=cmd_bench)
    return p


def _terminate(signum, frame):
    raise KeyboardInterrupt(f"signal {signum}")


NO_PROGRESS_HELP = ("no progress at all: neither the bars on a terminal nor the lines with an ETA that a "
                    "non-terminal stderr (nohup, a batch job) gets every CLRECON_PROGRESS_INTERVAL s")


def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    # SIGTERM (a batch system's cancel) unwinds like Ctrl-C: partial outputs are closed cleanly
    # and keep their temporary names, so a later run resumes from them.
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGTERM, _terminate)
    try:
        return args.func(args)
    except ClreconError as e:
        if args.debug:
            raise
        print(f"clrecon: error: {e}", file=sys.stderr)
        return 2
    except OSError as e:
        if args.debug:
            raise
        what = "disk full" if e.errno == errno.ENOSPC else "could not read or write a file"
        print(f"clrecon: error: {what} ({e.strerror or e}{': ' + str(e.filename) if e.filename else ''}); "
              f"outputs of earlier runs are kept; run again to resume", file=sys.stderr)
        return 2
    except MemoryError:
        if args.debug:
            raise
        print("clrecon: error: out of memory; `clrecon scenes` shows each scene's modelled peak memory: "
              "narrow --slices/--targets/--methods; finished outputs are kept", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("clrecon: interrupted; finished outputs and finished units of work are kept, unfinished files keep "
              ".partial names: "
              "run the same command again to resume", file=sys.stderr)
        return 130
