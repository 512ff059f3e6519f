"""``python -m benchmarks.dask_scaling``: Dask overhead, speedup 1 -> 2 workers, paper-p002 on 10 and 100 nodes.

Three parts, each printed with the machine's load average (a shared 2-core machine: medians):

1. **Overhead** (a 2-worker local cluster): the round trip of a task that does nothing
   (submit -> result, one at a time), the throughput of 200 such tasks in flight, and the
   round trip of an 8 MiB array (there and back: what a unit's arguments and result cost).
2. **Speedup**: one run of a small scene single-process, then on 1 and 2 local workers (each
   with a fresh projection store): the distributed phase's wall time, the units' compute
   seconds, the overhead per unit ((workers x wall - compute) / units) and the whole run's time.
3. **Model of paper-p002** on N nodes (N = 1, 10, 100) from unit costs measured here at small
   scale: one 256-projection chunk; the reconstruction of one slice x every target (``--quick``:
   a fifth of them, x 5) x every method of one variant from a store of zeros (the cost does
   not depend on the values; x 2 variants); the noise of a sample of projections (a slab
   reads and noises its projections once: x the slab's modelled projections, plus reading
   them at the disk speed measured here); one target's ground and phantom truth on one slice
   (x 110 slices); the client's planning of one slice (x 110); the evaluation at the metrics
   throughput (volume bytes per second) of part 2's single-process run (``--quick``: tiny's,
   which fixed costs dominate: an upper bound). Assumptions (printed too):
   a node = one worker as fast as this machine's 2 cores; units are list-scheduled, longest
   first, in two phases (projection chunks and truths, then the slabs, after the store is
   assembled); each unit pays the measured task overhead plus its bytes over a 10 Gb/s link
   to the client; the client writes every result as a unit file, assembles the store and
   ``volumes.h5`` and evaluates, at the disk throughput measured here, and cannot take
   results faster than it writes them; planning runs on the client, alone.
"""

from __future__ import annotations

import heapq
import os
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

from clrecon.config.scene import load_scene
from clrecon.core.runtime import get_runtime
from clrecon.core.stage_times import StageTimes
from clrecon.evaluation import groundtruth
from clrecon.pipeline import costs, distributed, work_units
from clrecon.pipeline.run import run
from clrecon.pipeline.variants import noise_variants
from clrecon.reconstruction import reconstruct
from clrecon.reconstruction.reconstruct import Targets
from clrecon.scan.table import projection_table
from clrecon.simulation import noise
from clrecon.simulation.simulate import CHUNK

#: Assumed link between a worker node and the client (bytes/s): 10 Gb/s Ethernet.
LINK_BYTES_S = 1.25e9
NODES = (1, 10, 100)


def _load() -> float:
    return round(os.getloadavg()[0], 2)


def bench_distributed_section(quick: bool = False, repeats: int = 3) -> dict:
    """Every number of the section (see the module docstring)."""
    out = {"load_before": _load()}
    out["overhead"] = overhead(repeats)
    out["tls"] = tls_overhead(repeats)
    out["speedup"] = speedup(quick)
    out["model"] = model_p002(quick, out["overhead"], out["speedup"])
    out["load_after"] = _load()
    return out


def overhead(repeats: int = 3) -> dict:
    """Task round trips on a 2-worker local cluster (seconds, medians)."""
    n = 10 * max(1, repeats)
    with distributed.connect(workers=2) as client:
        client.submit(work_units.round_trip, 0, pure=False).result()  # warm
        trips = []
        for i in range(n):
            t0 = time.perf_counter()
            client.submit(work_units.round_trip, i, pure=False).result()
            trips.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        client.gather(client.map(work_units.round_trip, range(200), pure=False))
        batch_s = time.perf_counter() - t0
        arr = np.ones(1 << 21, np.float32)  # 8 MiB
        pay = []
        for _ in range(max(3, repeats)):
            t0 = time.perf_counter()
            client.submit(work_units.round_trip, arr, pure=False).result()
            pay.append(time.perf_counter() - t0)
    return {"trivial_round_trip_s": float(np.median(trips)), "round_trips": n,
            "tasks_per_s_200_in_flight": 200 / batch_s, "payload_bytes": arr.nbytes,
            "payload_round_trip_s": float(np.median(pay)),
            "payload_bytes_per_s": 2 * arr.nbytes / max(float(np.median(pay)), 1e-9), "load": _load()}


def tls_overhead(repeats: int = 3) -> dict:
    """Round trips on a 1-worker local cluster over ``tcp://`` and over ``tls://``, alternated (seconds, medians).

    The TLS cluster uses ``distributed.Security.temporary()`` (an in-memory certificate; needs
    the ``cryptography`` package, else the figure is skipped). Both clusters run at once, so
    the two protocols see the same machine load.
    """
    import logging

    import distributed as d

    try:
        sec = d.Security.temporary()
    except ImportError as e:
        return {"skipped": f"needs the cryptography package ({e})"}
    n = 10 * max(1, repeats)
    arr = np.ones(1 << 21, np.float32)  # 8 MiB, as overhead()
    kw = dict(n_workers=1, threads_per_worker=1, processes=True, dashboard_address="127.0.0.1:0",
              silence_logs=logging.ERROR)
    times: dict = {"tcp": {"trivial": [], "payload": []}, "tls": {"trivial": [], "payload": []}}
    with d.LocalCluster(protocol="tcp", **kw) as c_tcp, d.LocalCluster(protocol="tls", security=sec, **kw) as c_tls, \
            d.Client(c_tcp) as tcp, d.Client(c_tls, security=sec) as tls:
        clients = {"tcp": tcp, "tls": tls}
        for c in clients.values():
            c.submit(work_units.round_trip, arr, pure=False).result()  # warm
        for i in range(n):
            for proto, c in clients.items():
                t0 = time.perf_counter()
                c.submit(work_units.round_trip, i, pure=False).result()
                times[proto]["trivial"].append(time.perf_counter() - t0)
        for _ in range(max(3, repeats)):
            for proto, c in clients.items():
                t0 = time.perf_counter()
                c.submit(work_units.round_trip, arr, pure=False).result()
                times[proto]["payload"].append(time.perf_counter() - t0)
    med = {p: {k: float(np.median(v)) for k, v in t.items()} for p, t in times.items()}
    return {"trivial_round_trip_s": {p: m["trivial"] for p, m in med.items()},
            "payload_round_trip_s": {p: m["payload"] for p, m in med.items()},
            "payload_bytes": arr.nbytes, "round_trips": n,
            "tls_over_tcp_trivial": med["tls"]["trivial"] / max(med["tcp"]["trivial"], 1e-9),
            "tls_over_tcp_payload": med["tls"]["payload"] / max(med["tcp"]["payload"], 1e-9),
            "tls_payload_bytes_per_s": 2 * arr.nbytes / max(med["tls"]["payload"], 1e-9), "load": _load()}


def _speedup_case(quick: bool):
    if quick:
        return "tiny", load_scene("tiny"), None
    return "demo (slices 0:4)", load_scene("demo"), (0, 4)


def speedup(quick: bool) -> dict:
    """A small run single-process, then on 1 and 2 local workers (fresh store each time)."""
    label, scene, slices = _speedup_case(quick)
    rows = []
    root = Path(tempfile.mkdtemp(prefix="clrecon-bench-dist-"))
    try:
        for workers in (None, 1, 2):
            tag = "serial" if workers is None else f"w{workers}"
            load = _load()
            kw = dict(slice_range=slices, cache_dir=root / f"cache-{tag}", progress=False, report=False,
                      log=lambda *a, **k: None)
            if workers is None:
                res = run(scene, root / tag, **kw)
                dist = None
            else:
                with distributed.connect(workers=workers) as client:
                    res = run(scene, root / tag, client=client, **kw)
                dist = res["distributed"]
            row = {"workers": workers or 0, "total_s": res["total_seconds"], "load": load,
                   "metrics_s": res["stages"]["metrics"]["seconds"],
                   "volume_bytes": costs.run_costs(scene, slices_z=res["request"]["slices_z_mm"])["volume_bytes"]}
            if dist:
                n_units = sum(dist["units"].values())
                compute = sum(v["sum"] for v in dist["unit_seconds"].values())
                row.update(phase_wall_s=dist["wall_seconds"], units=dist["units"], compute_s=compute,
                           overhead_per_unit_s=(workers * dist["wall_seconds"] - compute) / max(n_units, 1),
                           unit_seconds=dist["unit_seconds"])
            rows.append(row)
    finally:
        shutil.rmtree(root, ignore_errors=True)
    by = {r["workers"]: r for r in rows}
    return {"scene": label, "rows": rows, "phase_speedup_1_to_2": by[1]["phase_wall_s"] / by[2]["phase_wall_s"],
            "run_speedup_1_to_2": by[1]["total_s"] / by[2]["total_s"],
            "run_speedup_serial_to_2": by[0]["total_s"] / by[2]["total_s"]}


class _ZeroStore:
    """A projection store of zeros: the reconstruction's cost without simulating its input."""

    def __init__(self, table, shape):
        self.table, self.shape = table, shape

    def read_indices(self, indices, noisy=False, rows=None):
        n_rows = self.shape[0] if rows is None else rows[1] - rows[0]
        return np.zeros((len(indices), n_rows) + tuple(self.shape[1:]), np.float32)


def _disk_bytes_per_s(nbytes: int = 256 << 20) -> dict:
    """Write + fsync and read back ``nbytes`` in the temp folder (the run directory's disk)."""
    d = Path(tempfile.mkdtemp(prefix="clrecon-bench-disk-"))
    try:
        buf = np.random.default_rng(0).integers(0, 255, nbytes, np.uint8).tobytes()
        p = d / "x"
        t0 = time.perf_counter()
        with open(p, "wb") as f:
            f.write(buf)
            f.flush()
            os.fsync(f.fileno())
        w = time.perf_counter() - t0
        t0 = time.perf_counter()
        p.read_bytes()
        r = time.perf_counter() - t0
    finally:
        shutil.rmtree(d, ignore_errors=True)
    return {"write_bytes_per_s": nbytes / w, "read_bytes_per_s": nbytes / r}


def model_p002(quick: bool, over: dict, spd: dict) -> dict:
    """Measured unit costs of paper-p002 at small scale, and the modelled wall time on N nodes."""
    scene = load_scene("paper-p002")
    pitch = scene.scan.pitches[0]
    rc, sc = scene.recon, scene.scanner
    rt = get_runtime()
    cfg = reconstruct.ReconstructionConfig.from_scene(scene)
    table = projection_table(scene, pitch)
    variants = noise_variants(scene)
    methods = tuple(rc.methods)
    n_c, n_r = len(scene.cardiac_targets), len(scene.resp_targets)
    # measured on a share of the targets in --quick (scaled by the target count)
    c_used = scene.cardiac_targets[:1] if quick else scene.cardiac_targets
    targets = Targets(tuple(c_used), tuple(scene.resp_targets))
    target_scale = n_c / len(c_used)
    z_all = reconstruct.slice_positions(scene)
    z1 = z_all[len(z_all) // 2:len(z_all) // 2 + 1]
    m = {"load_before": _load(), "targets_measured": len(c_used) * n_r}
    t0 = time.perf_counter()
    plan = reconstruct.plan(cfg, table, z1, targets, methods)
    m["plan_one_slice_s"] = (time.perf_counter() - t0) * target_scale
    needed = plan.needed_projections(len(table))
    idx = np.flatnonzero(needed)[:CHUNK]
    m["chunk_s"] = float(np.median([work_units.simulate_chunk(scene, pitch, idx)[1] for _ in range(1 if quick else 2)]))
    # the per-slice part (rebin, interpolate, FBP) of one variant (the other costs the same) ...
    times = StageTimes()
    t0 = time.perf_counter()
    vols = reconstruct.reconstruct(cfg, _ZeroStore(table, (sc.n_rows, sc.n_cols)), plan, variants=("noise-free",),
                                   rt=rt, times=times, slab_size=1)
    per_variant = time.perf_counter() - t0 - times.seconds.get("read", 0.0)
    result_bytes_slice = sum(v.nbytes for v in vols.values()) * target_scale * len(variants)
    del vols
    slice_s = per_variant * target_scale * len(variants)
    # ... and the projection-bound part: each slab reads its projections once and noises them once
    sample = np.flatnonzero(needed)[:256 if quick else 1024]
    t0 = time.perf_counter()
    noise.add_noise(np.zeros((sample.size, sc.n_rows, sc.n_cols), np.float32), sample, scene.noise)
    noise_per_proj = (time.perf_counter() - t0) / sample.size if "noisy" in variants else 0.0
    m.update(recon_per_slice_s=slice_s, noise_per_projection_s=noise_per_proj,
             projections_needed_one_slice=int(needed.sum()))
    gt_cfg = groundtruth.GroundTruthConfig.from_scene(scene)
    one = Targets(tuple(scene.cardiac_targets[:1]), tuple(scene.resp_targets[:1]))
    t0 = time.perf_counter()
    list(groundtruth.groundtruth_volumes(gt_cfg, z1, one, rt=rt))
    list(groundtruth.phantom_truth_volumes(gt_cfg, z1, one, rt=rt))
    m["truth_one_target_one_slice_s"] = time.perf_counter() - t0
    m["disk"] = _disk_bytes_per_s(64 << 20 if quick else 256 << 20)
    m["load_after"] = _load()
    disk_w, disk_r = m["disk"]["write_bytes_per_s"], m["disk"]["read_bytes_per_s"]
    proj_s = noise_per_proj + sc.n_rows * sc.n_cols * 4 / disk_r  # noise + reading it (uncompressed, at disk speed)

    # units of the full run (the serial path's decomposition)
    full = costs.run_costs(scene)
    slab = full["slab_slices"]
    n_slabs = -(-rc.nz // slab)
    n_chunks = -(-full["projections_needed"][pitch] // CHUNK)
    slab_proj = costs.run_costs(scene, slices_z=z_all[:slab])["projections_needed"][pitch]
    t_slab = proj_s * slab_proj + slab * slice_s
    t_truth = m["truth_one_target_one_slice_s"] * rc.nz
    chunk_bytes = CHUNK * sc.n_rows * sc.n_cols * 4
    slab_bytes = result_bytes_slice * slab
    truth_bytes = 2 * rc.nz * rc.ny * rc.nx * 4
    per_task = over["trivial_round_trip_s"]
    sp = spd["rows"][0]
    metrics_bytes_per_s = sp["volume_bytes"] / max(sp["metrics_s"], 1e-9)
    client = {
        "plan_s": m["plan_one_slice_s"] * rc.nz,
        # store: chunks written as units, then read and written into <hash>.h5
        "store_assembly_s": full["needed_store_bytes"] * (1 / disk_r + 1 / disk_w),
        # volumes: slabs and truths written as units, read and written into volumes.h5, read to evaluate
        "volumes_assembly_s": full["volume_bytes"] * (1 / disk_r + 1 / disk_w),
        "evaluate_s": full["volume_bytes"] / metrics_bytes_per_s,
    }
    phase1 = [t_chunk + per_task + chunk_bytes / LINK_BYTES_S for t_chunk in [m["chunk_s"]] * n_chunks]
    phase1 += [t_truth + per_task + truth_bytes / LINK_BYTES_S] * (n_c * n_r)
    phase2 = [t_slab + per_task + slab_bytes / LINK_BYTES_S] * n_slabs
    bytes1 = n_chunks * chunk_bytes + n_c * n_r * truth_bytes
    bytes2 = n_slabs * slab_bytes
    take = min(LINK_BYTES_S, disk_w)  # the client takes results no faster than it writes them
    walls = {}
    for n in NODES:
        p1 = max(_list_schedule(phase1, n), bytes1 / take)
        p2 = max(_list_schedule(phase2, n), bytes2 / take)
        walls[n] = {"wall_s": client["plan_s"] + p1 + client["store_assembly_s"] + p2 + client["volumes_assembly_s"]
                    + client["evaluate_s"], "phase1_s": p1, "phase2_s": p2}
    return {"measured": m, "units": {"chunks": n_chunks, "slabs": n_slabs, "slab_slices": slab,
                                     "truths": n_c * n_r},
            "unit_s": {"chunk": m["chunk_s"], "slab": t_slab, "truth": t_truth},
            "unit_bytes": {"chunk": chunk_bytes, "slab": slab_bytes, "truth": truth_bytes},
            "compute_s": sum(phase1) + sum(phase2), "client_s": client, "nodes": walls,
            "assumptions": ("node = one worker as fast as this 2-core machine; LPT list scheduling in two phases "
                            "(chunks + truths, then slabs after the store is assembled); per unit: measured task "
                            f"round trip + bytes at {LINK_BYTES_S / 1e9:g} GB/s; client: planning alone, unit "
                            "writes + assembly + evaluation at this machine's measured disk and metrics throughput")}


def _list_schedule(durations: list[float], n: int) -> float:
    """Makespan of ``durations`` on ``n`` workers, longest first to the earliest free worker."""
    free = [0.0] * n
    for d in sorted(durations, reverse=True):
        heapq.heapreplace(free, free[0] + d)
    return max(free) if durations else 0.0


def report_lines(d: dict | None) -> list[str]:
    """The section's lines in ``bench``'s report."""
    if not d:
        return []
    o, s, m = d["overhead"], d["speedup"], d["model"]
    out = ["", f"7. distributed (Dask local cluster; load {d['load_before']} -> {d['load_after']})",
           f"   task round trip {1e3 * o['trivial_round_trip_s']:.1f} ms (median of {o['round_trips']}), "
           f"{o['tasks_per_s_200_in_flight']:.0f} tasks/s with 200 in flight, 8 MiB there and back "
           f"{1e3 * o['payload_round_trip_s']:.0f} ms ({o['payload_bytes_per_s'] / 1e6:.0f} MB/s)",
           *_tls_lines(d.get("tls")),
           f"   {s['scene']}: {'workers':>7s} {'run s':>7s} {'phase s':>8s} {'compute s':>9s} {'units':>6s} "
           f"{'overhead/unit s':>15s} {'load':>5s}"]
    for r in s["rows"]:
        if r["workers"]:
            out.append(f"   {'':{len(s['scene'])}s}  {r['workers']:>7d} {r['total_s']:>7.1f} {r['phase_wall_s']:>8.1f} "
                       f"{r['compute_s']:>9.1f} {sum(r['units'].values()):>6d} {r['overhead_per_unit_s']:>15.2f} "
                       f"{r['load']:>5.2f}")
        else:
            out.append(f"   {'':{len(s['scene'])}s}  {'serial':>7s} {r['total_s']:>7.1f} {'':>8s} {'':>9s} {'':>6s} "
                       f"{'':>15s} {r['load']:>5.2f}")
    out.append(f"   speedup 1 -> 2 workers: distributed phase {s['phase_speedup_1_to_2']:.2f}x, whole run "
               f"{s['run_speedup_1_to_2']:.2f}x (single-process -> 2 workers {s['run_speedup_serial_to_2']:.2f}x)")
    u, us = m["units"], m["unit_s"]
    out.append(f"   paper-p002 model: {u['chunks']} chunks x {us['chunk']:.2f} s, {u['slabs']} slabs "
               f"({u['slab_slices']} slices) x {us['slab']:.0f} s, {u['truths']} truths x {us['truth']:.0f} s; "
               f"client: plan {m['client_s']['plan_s']:.0f} s, store {m['client_s']['store_assembly_s']:.0f} s, "
               f"volumes {m['client_s']['volumes_assembly_s']:.0f} s, evaluate {m['client_s']['evaluate_s']:.0f} s")
    out.append("   modelled wall: " + ", ".join(f"{n} node{'s' if n > 1 else ''} {w['wall_s'] / 3600:.2f} h"
                                                 for n, w in m["nodes"].items()))
    out.append(f"   assumptions: {m['assumptions']}")
    return out


def _tls_lines(t: dict | None) -> list[str]:
    if not t:
        return []
    if "skipped" in t:
        return [f"   tls:// round trips: skipped ({t['skipped']})"]
    tr, pay = t["trivial_round_trip_s"], t["payload_round_trip_s"]
    return [f"   tls:// vs tcp:// (1 worker each, alternated; load {t['load']}): task round trip "
            f"{1e3 * tr['tls']:.1f} vs {1e3 * tr['tcp']:.1f} ms ({t['tls_over_tcp_trivial']:.2f}x), 8 MiB there and "
            f"back {1e3 * pay['tls']:.0f} vs {1e3 * pay['tcp']:.0f} ms ({t['tls_over_tcp_payload']:.2f}x, "
            f"{t['tls_payload_bytes_per_s'] / 1e6:.0f} MB/s over TLS)"]


if __name__ == "__main__":  # pragma: no cover - run by hand: python -m benchmarks.dask_scaling
    from benchmarks._cli import main

    raise SystemExit(main(bench_distributed_section, report_lines))
