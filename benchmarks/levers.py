"""``python -m benchmarks.levers``: the run's speed levers, each against what it replaced, in the same run.

Each row times the lever and what it replaced on the same data in the same process, the
repeats alternating (so that a change of the machine's load hits both), medians reported:

- ``volumes``: :class:`clrecon.outputs.volumes.VolumeWriter` writing CT-like HU volumes
  (float32, a disk of smooth structure and 3 HU noise inside the field of view, 0 outside, as
  the reconstruction writes them: one unit per slab of 8 slices), assembling them and reading
  every dataset back, with ``compression = "none"`` (what ``recon.volume_compression = "auto"``
  picks below :data:`clrecon.outputs.volumes.AUTO_COMPRESS_BYTES`) against ``"lzf"``;
- ``assembly``: the end of the run's volume writing on the same compressed (LZF) units of demo-sized
  CT-like datasets: ``volumes.h5`` mapping the units in place (format 3, :meth:`VolumeWriter.assemble`)
  against what format 2 did, each dataset's units checksum-checked and their compressed chunks
  copied into one file per dataset, fsync'd; then every dataset read back whole from each (the
  in-place layout's cost: a read opens the dataset's unit files);
- ``metrics``: the run's metrics stage (:func:`clrecon.pipeline.evaluate.evaluate`) on demo-sized
  CT-like volumes of 12 reconstructions (2 pitches x 2 variants x 3 methods) and their ground
  truth, in 2 processes against 1 (``evaluate(processes=...)``), the results compared for
  bit identity;
- ``write_behind``: the reconstruction's alternation of backprojection and unit writing, on
  paper-p010's sizes: per step a real backprojection of 64 thorax images (512^2 from 984 x 900,
  the direct kernel, from the device) and then one unit of 5 x 10 targets x 2 slices of CT-like
  HU in float16 + LZF (about a quarter of the step's backprojection time, as in paper-p010's
  run: 3 s of writing per 12.7 s of FBP); the unit written by the writer thread while the next
  step backprojects (:mod:`clrecon.core.write_behind`) against written in the foreground
  (``WriteBehind(background=False)``), the units' values compared;
- ``simulate_behind``: demo's whole simulation (both pitches, into fresh stores) with each
  block's projection units written by the writer thread while the next block is projected,
  against written in the foreground (``simulate(write_behind_thread=False)``), the stores' projections
  compared;
- ``posing``: the analytic phantom posed at demo's first pitch-0.02 projection states in calls
  of one block (:data:`clrecon.simulation.simulate.BLOCK_CHUNKS` chunks, the simulation's
  calls since 2026-12-02) against calls of one 256-projection chunk (before);
- ``interp_launch``: the reconstruction's launches at paper-p010's shape (32 sinograms of 984
  views x 900 columns interpolated from 40 candidate rows per view, 142 MB of rows, then
  backprojected to 512^2), for K = 3 (barycentric) and 8 (local linear) slots: the 8-columns
  interpolation kernel into kept scratch buffers (the reconstruction since 2026-12-05) against
  the loop kernel into fresh buffers (before), with the steps between them (the per-lane
  vectorised kernel into fresh buffers, then into kept ones: the reconstruction from 2026-12-03
  to 2026-12-05), which of the changes gives what; the interpolation launches alone, per-lane
  against 8 columns per work-item; the images compared for bit identity;
- ``rows_shared``: a paper-scale slab's rebinned rows (1 GiB, paper-p010's 900 columns) handed
  to the device and one K = 8 interpolation launch of 32 sinograms from rows all over them:
  read in place by the CPU device (``DeviceRows(share=True)``, a ``CL_MEM_USE_HOST_PTR`` buffer
  over the page-aligned array; the reconstruction since 2026-12-03) against copied into a new
  buffer (before), the sinograms compared for bit identity;
- ``objects_shared``: one simulation block of demo (2 048 projections posed in one call, 133 MB
  of float64 object records) projected with the records read in place by the CPU device
  (page-aligned by the phantom, the simulation since 2026-12-03) against a copy of them that the
  device must copy (before), the projections compared for bit identity;
- ``store_rows``: a slab's 16 of paper-p002's 64 detector rows (and all 64) read from a
  projection store chunked by blocks of 8 rows (the store since 2026-12-05) against one chunked
  by whole projections (before), real line integrals repeated to 4 096 projections, the arrays
  compared bit for bit;
- ``table2_kept``: the metrics' Table-2 sums of paper-p010-sized volume pairs (110 x 512 x 512
  float32 HU, CT-like) formed in kept arrays (``Table2.add(..., scratch)``, the metrics since
  2026-12-04) against the fresh-array formula it replaced, the float64 sums compared bit for bit.
"""

from __future__ import annotations

import hashlib
import json
import shutil
import tempfile
import time
from pathlib import Path

import h5py
import numpy as np

from clrecon.bench import reference_kernels
from clrecon.bench.paper import _scene, _thorax_sinograms, spread_indices
from clrecon.bench.timing import load1, timed
from clrecon.config.scene import load_scene
from clrecon.core import units, write_behind
from clrecon.core.conventions import detector_coords, detector_frames
from clrecon.core.resources import folder_bytes
from clrecon.core.runtime import aligned_empty, get_runtime
from clrecon.evaluation.metrics import MetricsConfig, Table2
from clrecon.outputs.volumes import VolumeWriter, open_volumes
from clrecon.pipeline import evaluate as evaluate_mod
from clrecon.pipeline.run import resolve_targets
from clrecon.reconstruction import fbp
from clrecon.reconstruction.interpolation import apply as apply_mod
from clrecon.reconstruction.reconstruct import slice_positions, voxel_coords
from clrecon.scan.table import projection_table
from clrecon.simulation import simulate as simulate_mod
from clrecon.simulation import store as store_mod
from clrecon.simulation.phantom_sources import phantom_from_config
from clrecon.simulation.projector import phantom_for_scene, project, project_views


def _ct_like(shape, k: int) -> np.ndarray:
    """(n_c, n_r, nz, ny, nx) float32 HU: smooth structure + 3 HU noise in the FOV disk, 0 outside."""
    return _ct_pattern(shape, k)


def _ct_pattern(shape, k: int) -> np.ndarray:
    """:func:`_ct_like`'s volumes (the metrics row's, at its scene's shape)."""
    rng = np.random.default_rng(k)
    nz, ny, nx = shape[-3:]
    y, x = np.meshgrid(np.arange(ny), np.arange(nx), indexing="ij")
    base = 40.0 * np.round(25 * np.cos(y / 9.0 + k) * np.sin(x / 7.0))
    v = base + rng.normal(0.0, 3.0, shape)
    v[..., (y - ny / 2) ** 2 + (x - nx / 2) ** 2 > (nx / 2) ** 2] = 0.0
    return v.astype(np.float32)


def _volumes_once(folder: Path, compression: str, data: dict, axes: dict) -> dict:
    shutil.rmtree(folder, ignore_errors=True)
    folder.mkdir(parents=True)
    w = VolumeWriter(folder / "volumes.h5", axes, True, True, run_key="bench", compression=compression)
    t0 = time.perf_counter()
    for name, v in data.items():
        w.create(name, v.shape, v.shape[2])
        for z0 in range(0, v.shape[2], 8):
            w.write(name, v[:, :, z0:z0 + 8], np.arange(z0, min(z0 + 8, v.shape[2])))
    t1 = time.perf_counter()
    w.close()
    t2 = time.perf_counter()
    with open_volumes(folder) as f:
        for name in data:
            f[name][()]
    t3 = time.perf_counter()
    disk = folder_bytes(folder)
    shutil.rmtree(folder, ignore_errors=True)
    return {"write_s": t1 - t0, "assemble_s": t2 - t1, "read_s": t3 - t2, "disk_bytes": disk}


def bench_volumes(quick: bool = False, repeats: int = 3) -> dict:
    """Write + assemble + read seconds of uncompressed against LZF volumes (module docstring)."""
    n_sets = 2 if quick else 8
    shape = (10, 5, 16, 128, 128)  # demo's 50 targets x 16 slices of 128^2
    data = {f"recon/p0.020/noise-free/m{k}": _ct_like(shape, k) for k in range(n_sets)}
    axes = {"cardiac_phase": np.linspace(0, 0.9, 10), "resp_amplitude": np.linspace(0.1, 0.9, 5),
            "z_mm": np.arange(16.0), "y_mm": np.arange(128.0), "x_mm": np.arange(128.0)}
    raw = sum(v.nbytes for v in data.values())
    runs = {"none": [], "lzf": []}
    load = [load1()]
    with tempfile.TemporaryDirectory(prefix="clrecon-bench-volumes-") as tmp:
        for _ in range(max(1, repeats)):
            for c in ("none", "lzf"):
                runs[c].append(_volumes_once(Path(tmp) / c, c, data, axes))
        load.append(load1())
    med = {c: {k: float(np.median([r[k] for r in rs])) for k in rs[0]} for c, rs in runs.items()}
    tot = {c: m["write_s"] + m["assemble_s"] + m["read_s"] for c, m in med.items()}
    return {"raw_bytes": raw, "datasets": n_sets, "median": med, "total_s": tot,
            "speedup": tot["lzf"] / tot["none"] if tot["none"] > 0 else float("nan"), "load": load,
            "repeats": max(1, repeats)}


def _copy_per_dataset(w: VolumeWriter, folder: Path) -> dict:
    """Format 2's assembly, as the reference of ``assembly``: each dataset's units (checksum
    checked) copied chunk by chunk into ``folder/<name>.h5``, fsync'd; returns name -> file."""
    folder.mkdir(parents=True, exist_ok=True)
    files = {}
    for name, (shape, _) in w._specs.items():
        p = folder / f"{name.replace('/', '~')}.h5"
        with h5py.File(p, "w") as f:
            ds = f.create_dataset("volume", shape=shape, dtype=w.dtype, chunks=w._chunks(shape), **w.filters)
            for up, m in w._units[name]:
                with units.open_unit(up) as (uf, _, _):
                    src = uf["data"]
                    z = np.asarray(m["z"], np.int64)
                    nt = ds.ndim - 3
                    for c in range(src.id.get_num_chunks()):
                        info = src.id.get_chunk_info(c)
                        mask, raw = src.id.read_direct_chunk(info.chunk_offset)
                        off = tuple(info.chunk_offset)
                        ds.id.write_direct_chunk(off[:nt] + (int(z[off[nt]]),) + off[nt + 1:], raw, mask)
        units.fsync_file(p)
        files[name] = p
    return files


def _assembly_once(folder: Path, data: dict, axes: dict, copy_first: bool) -> dict:
    shutil.rmtree(folder, ignore_errors=True)
    folder.mkdir(parents=True)
    w = VolumeWriter(folder / "volumes.h5", axes, True, True, run_key="bench", compression="lzf")
    for name, v in data.items():
        w.create(name, v.shape, v.shape[2])
        for z0 in range(0, v.shape[2], 8):
            w.write(name, v[:, :, z0:z0 + 8], np.arange(z0, min(z0 + 8, v.shape[2])))
    out: dict = {}
    digests: dict = {}

    def copy():
        t0 = time.perf_counter()
        files = _copy_per_dataset(w, folder / "copied")
        t1 = time.perf_counter()
        got = {}
        for name, p in files.items():
            with h5py.File(p, "r") as f:
                got[name] = f["volume"][()]
        out["copy"] = {"assemble_s": t1 - t0, "read_s": time.perf_counter() - t1}
        digests["copy"] = [hashlib.blake2b(got[n].tobytes()).hexdigest() for n in data]

    def in_place():
        t0 = time.perf_counter()
        f = w.assemble()
        t1 = time.perf_counter()
        got = {name: f[name][()] for name in data}
        out["in_place"] = {"assemble_s": t1 - t0, "read_s": time.perf_counter() - t1}
        digests["in_place"] = [hashlib.blake2b(got[n].tobytes()).hexdigest() for n in data]
        w.close()

    for step in ((copy, in_place) if copy_first else (in_place, copy)):
        step()
    shutil.rmtree(folder, ignore_errors=True)
    out["identical"] = digests["copy"] == digests["in_place"]
    return out


def bench_assembly(quick: bool = False, repeats: int = 3) -> dict:
    """Seconds to assemble and read back LZF volumes in place against copied per dataset (module docstring)."""
    n_sets = 2 if quick else 8
    shape = (10, 5, 16, 128, 128)
    data = {f"recon/p0.020/noise-free/m{k}": _ct_like(shape, k) for k in range(n_sets)}
    axes = {"cardiac_phase": np.linspace(0, 0.9, 10), "resp_amplitude": np.linspace(0.1, 0.9, 5),
            "z_mm": np.arange(16.0), "y_mm": np.arange(128.0), "x_mm": np.arange(128.0)}
    runs: dict = {"copy": [], "in_place": []}
    identical = True
    load = [load1()]
    with tempfile.TemporaryDirectory(prefix="clrecon-bench-assembly-") as tmp:
        for r in range(max(1, repeats)):
            got = _assembly_once(Path(tmp) / "a", data, axes, copy_first=r % 2 == 0)
            identical &= got["identical"]
            for k in runs:
                runs[k].append(got[k])
        load.append(load1())
    med = {k: {q: float(np.median([r[q] for r in rs])) for q in rs[0]} for k, rs in runs.items()}
    return {"raw_bytes": sum(v.nbytes for v in data.values()), "datasets": n_sets, "median": med,
            "speedup": (med["copy"]["assemble_s"] / med["in_place"]["assemble_s"]
                        if med["in_place"]["assemble_s"] > 0 else float("nan")),
            "read_ratio": (med["in_place"]["read_s"] / med["copy"]["read_s"]
                           if med["copy"]["read_s"] > 0 else float("nan")),
            "identical": bool(identical), "load": load, "repeats": max(1, repeats)}


def bench_write_behind(quick: bool = False, repeats: int = 3, scene_name: str = "paper-p010") -> dict:
    """Seconds of backprojection steps each followed by a unit write, the writes in a thread
    against in the foreground (module docstring)."""
    sc = _scene(scene_name)
    rt = get_runtime()
    geom = fbp.FanBeamGeometry.from_scene(sc)
    n_img, steps = 64, 3 if quick else 6
    sino = _thorax_sinograms(sc, n_img, rt)
    B, V, C = sino.shape
    rows = sino.reshape(-1, C).copy()
    fbp.filter_rows(rows, geom, sc.recon.filter, out=rows)
    launch = fbp.groups_per_launch(geom) * fbp.BATCH_LANES
    bufs = []
    for b0 in range(0, B, launch):
        g = fbp.interleave_batch(rows.reshape(B, V, C)[b0:b0 + launch])
        bufs.append((rt.to_device(g), g.shape[0]))
    vols = [_ct_like((5, 10, 2, sc.recon.ny, sc.recon.nx), k) for k in range(steps)]
    per_unit = vols[0].shape[2]  # slices per unit
    shape = vols[0].shape[:2] + (steps * per_unit,) + vols[0].shape[3:]
    axes = {name: np.arange(float(n)) for name, n in zip(("cardiac_phase", "resp_amplitude", "z_mm", "y_mm", "x_mm"),
                                                          shape, strict=True)}

    def backproject():
        for b, g in bufs:
            fbp.backproject_interleaved(b, g, geom, runtime=rt)

    def once(folder: Path, background: bool) -> tuple[float, dict, float]:
        shutil.rmtree(folder, ignore_errors=True)
        folder.mkdir(parents=True)
        w = VolumeWriter(folder / "volumes.h5", axes, True, True, run_key="bench", dtype="float16", compression="lzf")
        w.create("recon/p0.100/noisy/m", shape, shape[2])
        wb = write_behind.WriteBehind(background)
        t0 = time.perf_counter()
        for k in range(steps):
            backproject()
            wb.submit(w.write, "recon/p0.100/noisy/m", vols[k], np.arange(k * per_unit, (k + 1) * per_unit))
        wb.drain()
        wall = time.perf_counter() - t0
        wb.close()
        # the units' values (by stem): LZF output is not byte-reproducible (h5py's liblzf leaves its
        # hash table uninitialised), so neither are the unit files' BLAKE2b names; the values are
        values = {p.name.rsplit(".", 2)[0]: hashlib.blake2b(units.read_unit(p)[0]["data"].tobytes()).hexdigest()
                  for p in folder.glob("volumes.d/*/recon~*")}
        w.abort()
        shutil.rmtree(folder, ignore_errors=True)
        return wall, values, wb.beside_seconds

    backproject()  # warm-up: kernel build, PoCL specialisation
    t_bp = []
    times: dict = {"foreground": [], "behind": []}
    writes: list = []
    values: dict = {}
    load = [load1()]
    with tempfile.TemporaryDirectory(prefix="clrecon-bench-write-behind-") as tmp:
        for r in range(max(1, repeats)):
            for mode in (("foreground", "behind") if r % 2 == 0 else ("behind", "foreground")):
                wall, values[mode], own = once(Path(tmp) / mode, mode == "behind")
                times[mode].append(wall)
                if mode == "foreground":
                    writes.append(own)
            t_bp.append(timed(backproject))
        load.append(load1())
    for b, _ in bufs:
        b.release()
    med = {k: float(np.median(v)) for k, v in times.items()}
    return {"steps": steps, "images_per_step": n_img, "unit_shape": list(vols[0].shape),
            "median_s": med, "backproject_step_s": float(np.median(t_bp)),
            "write_step_s": float(np.median(writes)) / steps,
            "speedup": med["foreground"] / med["behind"] if med["behind"] > 0 else float("nan"),
            "identical": values["foreground"] == values["behind"] and len(values["behind"]) == steps,
            "load": load, "repeats": max(1, repeats)}


def bench_simulate_behind(quick: bool = False, repeats: int = 3, scene_name: str = "demo") -> dict:
    """Seconds of a scene's whole simulation into fresh stores, the projection units written
    behind against in the foreground (module docstring)."""
    sc = load_scene(scene_name)
    pitches = sc.scan.pitches[:1] if quick else sc.scan.pitches
    times: dict = {"foreground": [], "behind": []}
    digests: dict = {}
    load = [load1()]
    with tempfile.TemporaryDirectory(prefix="clrecon-bench-simulate-") as tmp:
        for r in range(max(1, repeats)):
            for mode in (("foreground", "behind") if r % 2 == 0 else ("behind", "foreground")):
                d = Path(tmp) / f"{mode}{r}"
                t0 = time.perf_counter()
                stores = [simulate_mod.simulate(sc, p, cache_dir=d, progress=False,
                                                write_behind_thread=mode == "behind") for p in pitches]
                times[mode].append(time.perf_counter() - t0)
                digests[mode] = [hashlib.blake2b(s_.read(0, len(s_)).tobytes()).hexdigest() for s_ in stores]
                for s_ in stores:
                    s_.close()
                shutil.rmtree(d, ignore_errors=True)
        load.append(load1())
    med = {k: float(np.median(v)) for k, v in times.items()}
    return {"scene": scene_name, "pitches": list(pitches), "median_s": med,
            "speedup": med["foreground"] / med["behind"] if med["behind"] > 0 else float("nan"),
            "identical": digests["foreground"] == digests["behind"], "load": load, "repeats": max(1, repeats)}


def bench_posing(quick: bool = False, repeats: int = 3) -> dict:
    """Seconds to pose the phantom at demo's projection states in block-sized against chunk-sized calls."""
    scene = load_scene("demo")
    table = projection_table(scene, 0.02)
    n = min(len(table), 4096 if quick else 8192)
    c, a = table.state_cardiac[:n], table.state_resp[:n]
    phantom = phantom_for_scene(scene)
    chunk = simulate_mod.CHUNK
    block = chunk * simulate_mod.BLOCK_CHUNKS

    def pose(step):
        t0 = time.perf_counter()
        for s in range(0, n, step):
            phantom.objects_batch(c[s:s + step], a[s:s + step])
        return time.perf_counter() - t0

    pose(block)  # warm-up
    times = {"chunk": [], "block": []}
    load = [load1()]
    for _ in range(max(2, repeats)):  # at least 2: one call of a block is short and noisy
        times["chunk"].append(pose(chunk))
        times["block"].append(pose(block))
    load.append(load1())
    med = {k: float(np.median(v)) for k, v in times.items()}
    return {"states": n, "chunk": chunk, "block": block, "median_s": med,
            "speedup": med["chunk"] / med["block"] if med["block"] > 0 else float("nan"), "load": load,
            "repeats": max(2, repeats)}


def bench_metrics(quick: bool = False, repeats: int = 3, scene_name: str = "demo") -> dict:
    """Seconds of the metrics stage in 2 processes against 1 on the same volume file (module docstring)."""
    scene = load_scene(scene_name)
    targets = resolve_targets(scene)
    z = slice_positions(scene, None)
    rc = scene.recon
    pitches = (0.02,) if quick else (0.02, 0.1)
    variants = ("noise-free",) if quick else ("noise-free", "noisy")
    methods = ("barycentric", "local_linear") if quick else ("barycentric", "local_linear", "nearest")
    shape = targets.shape + (len(z), rc.ny, rc.nx)
    axes = {"cardiac_phase": targets.cardiac, "resp_amplitude": targets.resp, "z_mm": z,
            "y_mm": voxel_coords(rc.ny, rc.voxel_mm), "x_mm": voxel_coords(rc.nx, rc.voxel_mm)}
    names = ["groundtruth"] + [f"recon/p{p:.3f}/{v}/{m}" for p in pitches for v in variants for m in methods]
    phantom = phantom_from_config(scene.phantom)
    times: dict = {"1": [], "2": []}
    results: dict = {}
    load = [load1()]
    with tempfile.TemporaryDirectory(prefix="clrecon-bench-metrics-") as tmp:
        w = VolumeWriter(Path(tmp) / "volumes.h5", axes, True, True, run_key="bench", compression="none")
        for k, name in enumerate(names):
            w.create(name, shape, len(z))
            w.write(name, _ct_pattern(shape, k), np.arange(len(z)))
        f = w.assemble()
        try:
            for _ in range(max(1, repeats)):
                for n in ("1", "2"):
                    t0 = time.perf_counter()
                    out = evaluate_mod.evaluate(scene, f, targets, z, pitches, variants, methods, phantom,
                                                processes=int(n))
                    times[n].append(time.perf_counter() - t0)
                    results[n] = json.dumps(out, sort_keys=True)
        finally:
            w.close()
        load.append(load1())
    med = {k: float(np.median(v)) for k, v in times.items()}
    return {"volumes": len(names) - 1, "targets": int(np.prod(targets.shape)),
            "raw_bytes": int(len(names) * np.prod(shape) * 4), "median_s": med,
            "speedup": med["1"] / med["2"] if med["2"] > 0 else float("nan"),
            "identical": results["1"] == results["2"], "load": load, "repeats": max(1, repeats)}


def bench_interp_launch(quick: bool = False, repeats: int = 3, scene_name: str = "paper-p010") -> dict:
    """Seconds of the reconstruction's interpolation + backprojection launches, now against before
    (module docstring)."""
    sc = _scene(scene_name)
    rt = get_runtime()
    geom = fbp.FanBeamGeometry.from_scene(sc)
    V, C = geom.n_views, geom.n_cols
    n_cand, launches = (10, 1) if quick else (40, 3)
    step = fbp.groups_per_launch(geom) * fbp.BATCH_LANES
    G = step // fbp.BATCH_LANES
    rng = np.random.default_rng(7)
    d_rows = apply_mod.DeviceRows(rng.standard_normal((V * n_cand, C)).astype(np.float32), rt=rt)
    d_sino = rt.empty((G, V, C + 2, fbp.BATCH_LANES))
    d_img = rt.empty((step, geom.ny, geom.nx))
    host = np.empty((step, geom.ny, geom.nx), np.float32)
    out: dict = {}
    load = [load1()]
    try:
        for K in (3, 8):
            idx = (np.arange(V)[None, :, None] * n_cand + rng.integers(0, n_cand, (step, V, K))).astype(np.int32)
            w = rng.random((step, V, K)).astype(np.float32)
            w[rng.random(w.shape) < 0.1] = 0.0
            pi, pw = apply_mod.pad_interleaved(idx, w)
            images: dict = {}

            def before(idx=idx, w=w, images=images):
                for _ in range(launches):
                    buf, g = reference_kernels.apply_interleaved_loop(d_rows, idx, w, rt=rt)
                    images["before"] = fbp.backproject_interleaved(buf, g, geom, runtime=rt)
                    buf.release()

            def fresh(pi=pi, pw=pw, images=images):
                for _ in range(launches):
                    buf, g = apply_mod.apply_padded_interleaved(d_rows, pi, pw, step, rt=rt)
                    images["fresh"] = fbp.backproject_interleaved(buf, g, geom, runtime=rt)
                    buf.release()

            def lanes(pi=pi, pw=pw, images=images):
                for _ in range(launches):
                    buf, g = reference_kernels.apply_padded_interleaved_lanes(d_rows, pi, pw, step, rt=rt, out=d_sino)
                    images["lanes"] = fbp.backproject_interleaved(buf, g, geom, runtime=rt, out_buf=d_img,
                                                                  out=host).copy()

            def now(pi=pi, pw=pw, images=images):
                for _ in range(launches):
                    buf, g = apply_mod.apply_padded_interleaved(d_rows, pi, pw, step, rt=rt, out=d_sino)
                    images["now"] = fbp.backproject_interleaved(buf, g, geom, runtime=rt, out_buf=d_img,
                                                                out=host).copy()

            def interp_lanes(pi=pi, pw=pw):
                for _ in range(launches):
                    reference_kernels.apply_padded_interleaved_lanes(d_rows, pi, pw, step, rt=rt, out=d_sino)

            def interp_now(pi=pi, pw=pw):
                for _ in range(launches):
                    apply_mod.apply_padded_interleaved(d_rows, pi, pw, step, rt=rt, out=d_sino)

            modes = {"before": before, "fresh": fresh, "lanes": lanes, "now": now,
                     "interp_lanes": interp_lanes, "interp_now": interp_now}
            for fn in modes.values():
                fn()  # warm-up: the kernel builds (one per K)
            times: dict = {k: [] for k in modes}
            for r in range(max(1, repeats)):
                for name in (list(modes) if r % 2 == 0 else list(modes)[::-1]):
                    times[name].append(timed(modes[name]))
            med = {k: float(np.median(v)) for k, v in times.items()}
            same = all(np.array_equal(images["before"].view(np.uint32), images[k].view(np.uint32))
                       for k in ("fresh", "lanes", "now"))

            def ratio(a, b, med=med):
                return med[a] / med[b] if med[b] > 0 else float("nan")

            out[str(K)] = {"median_s": med, "speedup": ratio("before", "now"),
                           "kernel_speedup": ratio("before", "fresh"), "scratch_speedup": ratio("fresh", "lanes"),
                           "cols8_speedup": ratio("lanes", "now"),
                           "cols8_interp_speedup": ratio("interp_lanes", "interp_now"),
                           "identical": bool(same)}
    finally:
        d_rows.release()
        d_sino.release()
        d_img.release()
    load.append(load1())
    return {"scene": sc.name, "sinograms_per_launch": step, "launches": launches, "views": V, "columns": C,
            "candidates_per_view": n_cand, "rows_bytes": int(V * n_cand * C * 4), "image": [geom.ny, geom.nx],
            "by_k": out, "load": load, "repeats": max(1, repeats)}


def bench_objects_shared(quick: bool = False, repeats: int = 3, scene_name: str = "demo") -> dict:
    """Seconds to project one simulation block of a scene (its first projections, posed in one
    call) with the posed objects read in place by the CPU device (page-aligned, the simulation
    since 2026-12-03) against the same objects copied to the device (an unaligned copy of them,
    made outside the timing); the projections compared bit for bit."""
    scene = load_scene(scene_name)
    sc = scene.scanner
    table = projection_table(scene, scene.scan.pitches[0])
    n = min(len(table), simulate_mod.CHUNK * (2 if quick else simulate_mod.BLOCK_CHUNKS))
    sub = table.take(np.arange(n))
    objs = phantom_for_scene(scene).objects_batch(sub.state_cardiac, sub.state_resp)
    moved = np.empty(objs.size + 1)[1:].reshape(objs.shape)  # not on a page boundary: copied
    moved[...] = objs
    src, det, eu, ev = detector_frames(sub.angle_rad, sub.source_z_mm, sc.sid_mm, sc.sdd_mm)
    u, v = detector_coords(sc.n_cols, sc.col_pitch_mm), detector_coords(sc.n_rows, sc.row_pitch_mm)
    outs: dict = {}

    def proj(name, arr):
        outs[name] = project_views(arr, src, det, eu, ev, u, v)

    modes = {"shared": lambda: proj("shared", objs), "copied": lambda: proj("copied", moved)}
    for fn in modes.values():
        fn()  # warm-up
    times: dict = {k: [] for k in modes}
    load = [load1()]
    for r in range(max(2, repeats)):
        for name in (list(modes) if r % 2 == 0 else list(modes)[::-1]):
            times[name].append(timed(modes[name]))
    load.append(load1())
    med = {k: float(np.median(v)) for k, v in times.items()}
    return {"scene": scene_name, "projections": n, "objects_bytes": int(objs.nbytes), "median_s": med,
            "speedup": med["copied"] / med["shared"] if med["shared"] > 0 else float("nan"),
            "identical": bool(np.array_equal(outs["shared"].view(np.uint32), outs["copied"].view(np.uint32))),
            "load": load, "repeats": max(2, repeats)}


def bench_rows_shared(quick: bool = False, repeats: int = 3, scene_name: str = "paper-p010") -> dict:
    """Seconds to hand a slab's rebinned rows to the device and run one interpolation launch from
    them, the rows read in place (``DeviceRows(share=True)``, the reconstruction since 2026-12-03)
    against copied into a new buffer (before); the launches' sinograms compared bit for bit."""
    sc = _scene(scene_name)
    rt = get_runtime()
    geom = fbp.FanBeamGeometry.from_scene(sc)
    V, C = geom.n_views, geom.n_cols
    # a paper-scale slab's rows: about 1 GB (a slab is <= 2.5 GB of rows, plan and images)
    rows_bytes = (64 << 20) if quick else (1 << 30)
    P = max(V, -(-rows_bytes // (4 * C)))
    rows = aligned_empty((P, C), np.float32)
    rng = np.random.default_rng(11)
    for r0 in range(0, P, 4096):
        rows[r0:r0 + 4096] = rng.standard_normal((min(4096, P - r0), C), dtype=np.float32)
    B, K = fbp.BATCH_LANES * 2, 8
    idx = rng.integers(0, P, (B, V, K)).astype(np.int32)  # rows from all over the slab
    w = rng.random((B, V, K)).astype(np.float32)
    pi, pw = apply_mod.pad_interleaved(idx, w)
    d_sino = rt.empty((B // fbp.BATCH_LANES, V, C + 2, fbp.BATCH_LANES))
    sinos: dict = {}

    def once(share: bool, name: str):
        d_rows = apply_mod.DeviceRows(rows, rt=rt, share=share)
        try:
            buf, G = apply_mod.apply_padded_interleaved(d_rows, pi, pw, B, rt=rt, out=d_sino)
            sinos[name] = rt.from_device(buf, (G, V, C + 2, fbp.BATCH_LANES))
        finally:
            d_rows.release()

    modes = {"shared": lambda: once(True, "shared"), "copied": lambda: once(False, "copied")}
    load = [load1()]
    try:
        for fn in modes.values():
            fn()  # warm-up: the kernel build
        times: dict = {k: [] for k in modes}
        for r in range(max(1, repeats)):
            for name in (list(modes) if r % 2 == 0 else list(modes)[::-1]):
                times[name].append(timed(modes[name]))
    finally:
        d_sino.release()
    load.append(load1())
    med = {k: float(np.median(v)) for k, v in times.items()}
    in_place = rt.is_cpu and rows.ctypes.data % max(1, int(rt.device.mem_base_addr_align) // 8) == 0
    return {"scene": sc.name, "rows_bytes": int(rows.nbytes), "sinograms": B, "slots": K, "in_place": bool(in_place),
            "median_s": med, "speedup": med["copied"] / med["shared"] if med["shared"] > 0 else float("nan"),
            "identical": bool(np.array_equal(sinos["shared"].view(np.uint32), sinos["copied"].view(np.uint32))),
            "load": load, "repeats": max(1, repeats)}


def bench_store_rows(quick: bool = False, repeats: int = 3, scene_name: str = "paper-p002") -> dict:
    """Seconds to read a slab's detector rows from a projection store chunked by blocks of
    :data:`clrecon.simulation.store.ROW_CHUNK` rows (the store since 2026-12-05,
    :func:`clrecon.simulation.store.chunk_shape`) against one chunked by whole projections (before),
    both with the store's filters (LZF, shuffle, Fletcher-32), on the same real line integrals: the
    scene's projections spread over its scan, repeated to the read's size. Rows: paper-p002's
    slabs of 5 slices read about 16 of the 64 (here rows 24-39), and all 64 for reference; the
    arrays read compared bit for bit."""
    sc = _scene(scene_name)
    table = projection_table(sc, sc.scan.pitches[0])
    n_real, n = (16, 512) if quick else (64, 4096)
    real = project(sc, table.take(spread_indices(len(table), n_real)))
    data = np.concatenate([real] * (n // n_real))
    _, R, C = data.shape
    layouts = {"rows": store_mod.chunk_shape(data.shape),
               "projections": (max(1, min(n, store_mod.CHUNK_BYTES // (R * C * 4))), R, C)}
    lo = max(0, R // 2 - 8)
    spans = {"slab": (lo, min(R, lo + 16)), "whole": (0, R)}
    folder = Path(tempfile.mkdtemp(prefix="clrecon-bench-store-"))
    load = [load1()]
    reads: dict = {}
    try:
        for name, chunks in layouts.items():
            with h5py.File(folder / f"{name}.h5", "w") as f:
                f.create_dataset("projections", data=data, chunks=chunks, compression="lzf", shuffle=True,
                                 fletcher32=True)

        def read(name, span):
            with h5py.File(folder / f"{name}.h5", "r", rdcc_nbytes=store_mod.CACHE_BYTES) as f:
                reads[(name, span)] = f["projections"][:, spans[span][0]:spans[span][1]]

        modes = {(name, span): (lambda name=name, span=span: read(name, span)) for name in layouts for span in spans}
        for fn in modes.values():
            fn()  # warm-up: the files in the page cache, as a run's store mostly is
        times: dict = {k: [] for k in modes}
        for r in range(max(1, repeats)):
            for k in (list(modes) if r % 2 == 0 else list(modes)[::-1]):
                times[k].append(timed(modes[k]))
        disk = {name: (folder / f"{name}.h5").stat().st_size for name in layouts}
    finally:
        shutil.rmtree(folder, ignore_errors=True)
    load.append(load1())
    med = {f"{name}/{span}": float(np.median(v)) for (name, span), v in times.items()}
    same = all(np.array_equal(reads[("rows", sp)].view(np.uint32), reads[("projections", sp)].view(np.uint32))
               for sp in spans)
    return {"scene": sc.name, "projections": n, "real_projections": n_real, "detector": [R, C],
            "chunks": {k: list(v) for k, v in layouts.items()}, "spans": {k: list(v) for k, v in spans.items()},
            "raw_bytes": int(data.nbytes), "disk_bytes": disk, "median_s": med,
            "speedup": {sp: med[f"projections/{sp}"] / med[f"rows/{sp}"] if med[f"rows/{sp}"] > 0 else float("nan")
                        for sp in spans},
            "identical": bool(same), "load": load, "repeats": max(1, repeats)}


def _table2_fresh(acc, i: int, j: int, recon: np.ndarray, truth: np.ndarray) -> None:
    """What ``Table2.add`` did until 2026-12-04: fresh arrays for every difference (the same-run reference)."""
    d = np.abs(recon - truth).reshape(recon.shape[0], -1)
    for fov, idx in acc.flat.items():
        x = d[:, idx].astype(np.float64)
        acc.sums[fov][i, j] = (x.sum(), (x * x).sum())
        acc.count[fov][i, j] = x.size


def bench_table2_kept(quick: bool = False, repeats: int = 3, scene_name: str = "paper-p010") -> dict:
    """Seconds per volume of the metrics' Table-2 sums, kept arrays (``Table2.add(..., scratch)``)
    against fresh ones (:func:`_table2_fresh`), on CT-like volume pairs of the scene's grid
    (paper-p010: 110 x 512 x 512; ``quick``: 8 slices); the sums compared bit for bit."""
    scene = load_scene(scene_name)
    rc = scene.recon
    nz = 8 if quick else rc.nz
    shape = (1, 1, nz, rc.ny, rc.nx)
    truth = _ct_pattern(shape, 0)[0, 0]
    vols = [_ct_pattern(shape, k)[0, 0] for k in (1, 2)]
    cfg = MetricsConfig.from_scene(scene)
    accs = {"kept": Table2(cfg, 1, len(vols)), "fresh": Table2(cfg, 1, len(vols))}
    scratch: dict = {}
    modes = {"kept": lambda j: accs["kept"].add(0, j, vols[j], truth, scratch),
             "fresh": lambda j: _table2_fresh(accs["fresh"], 0, j, vols[j], truth)}
    times: dict = {k: [] for k in modes}
    load = [load1()]
    for r in range(max(2, repeats)):
        for name in (list(modes) if r % 2 == 0 else list(modes)[::-1]):
            for j in range(len(vols)):
                times[name].append(timed(lambda name=name, j=j: modes[name](j)))
    load.append(load1())
    med = {k: float(np.median(v)) for k, v in times.items()}
    same = all(np.array_equal(accs["kept"].sums[f].view(np.int64), accs["fresh"].sums[f].view(np.int64))
               for f in accs["kept"].sums)
    return {"scene": scene_name, "shape": [nz, rc.ny, rc.nx], "median_s": med,
            "speedup": med["fresh"] / med["kept"] if med["kept"] > 0 else float("nan"), "identical": bool(same),
            "load": load, "repeats": max(2, repeats)}


#: The rows, in report order (``--only`` picks some).
ROWS = ("volumes", "assembly", "write_behind", "simulate_behind", "metrics", "posing", "interp_launch",
        "rows_shared", "objects_shared", "table2_kept", "store_rows")


def bench_levers(quick: bool = False, repeats: int = 3, metrics_scene: str = "demo",
                 write_scene: str = "paper-p010", simulate_scene: str = "demo",
                 store_scene: str = "paper-p002", only=None) -> dict:
    """The lever rows ``only`` (default: every one, :data:`ROWS`; module docstring); ``metrics_scene``:
    the metrics row's scene (its grid and targets); ``write_scene``: the write-behind row's (its
    scanner and grid); ``simulate_scene``: the simulation row's; ``store_scene``: the store row's."""
    rows = {"volumes": lambda: bench_volumes(quick, repeats), "assembly": lambda: bench_assembly(quick, repeats),
            "write_behind": lambda: bench_write_behind(quick, repeats, write_scene),
            "simulate_behind": lambda: bench_simulate_behind(quick, repeats, simulate_scene),
            "metrics": lambda: bench_metrics(quick, repeats, metrics_scene),
            "posing": lambda: bench_posing(quick, repeats),
            "interp_launch": lambda: bench_interp_launch(quick, repeats, write_scene),
            "rows_shared": lambda: bench_rows_shared(quick, repeats, write_scene),
            "objects_shared": lambda: bench_objects_shared(quick, repeats, simulate_scene),
            "table2_kept": lambda: bench_table2_kept(quick, repeats, write_scene),
            "store_rows": lambda: bench_store_rows(quick, repeats, store_scene)}
    bad = [r for r in (only or ()) if r not in rows]
    if bad:
        raise SystemExit(f"--only {bad[0]!r}: rows are {', '.join(ROWS)}")
    return {name: rows[name]() for name in (only or ROWS)}


def report_lines(res: dict | None) -> list[str]:
    """The report's lines of the rows in ``res``."""
    if not res:
        return []
    return [
        "levers (each against its same-run reference, alternating, medians):",
        *_volumes_lines(res.get("volumes")),
        *_assembly_lines(res.get("assembly")),
        *_write_behind_lines(res.get("write_behind")),
        *_simulate_behind_lines(res.get("simulate_behind")),
        *([f"   metrics stage, {res['metrics']['volumes']} reconstructions x {res['metrics']['targets']} targets "
           f"({res['metrics']['raw_bytes'] / 1e9:.2f} GB raw): 2 processes {res['metrics']['median_s']['2']:.2f} s, "
           f"1 process {res['metrics']['median_s']['1']:.2f} s: speedup {res['metrics']['speedup']:.2f}x, "
           f"results {'bit-identical' if res['metrics']['identical'] else 'DIFFERENT'} "
           f"(load {res['metrics']['load'][0]:.1f} -> {res['metrics']['load'][-1]:.1f})"] if "metrics" in res else []),
        *_posing_lines(res.get("posing")),
        *_interp_launch_lines(res.get("interp_launch")),
        *_rows_shared_lines(res.get("rows_shared")),
        *_objects_shared_lines(res.get("objects_shared")),
        *_table2_kept_lines(res.get("table2_kept")),
        *_store_rows_lines(res.get("store_rows")),
    ]


def _volumes_lines(v: dict | None) -> list[str]:
    if not v:
        return []
    mn, ml = v["median"]["none"], v["median"]["lzf"]
    return [f"   volumes, {v['datasets']} demo-sized datasets ({v['raw_bytes'] / 1e9:.2f} GB raw), write + assemble + "
            f"read: none {v['total_s']['none']:.2f} s ({mn['write_s']:.2f} + {mn['assemble_s']:.2f} + "
            f"{mn['read_s']:.2f}), lzf {v['total_s']['lzf']:.2f} s ({ml['write_s']:.2f} + {ml['assemble_s']:.2f} + "
            f"{ml['read_s']:.2f}): speedup {v['speedup']:.2f}x; disk {mn['disk_bytes'] / 1e9:.2f} vs "
            f"{ml['disk_bytes'] / 1e9:.2f} GB (load {v['load'][0]:.1f} -> {v['load'][-1]:.1f})"]


def _posing_lines(p: dict | None) -> list[str]:
    if not p:
        return []
    return [f"   phantom posing, {p['states']} demo states: blocks of {p['block']} {p['median_s']['block']:.2f} s, "
            f"chunks of {p['chunk']} {p['median_s']['chunk']:.2f} s: speedup {p['speedup']:.2f}x "
            f"(load {p['load'][0]:.1f} -> {p['load'][-1]:.1f})"]


def _store_rows_lines(a: dict | None) -> list[str]:
    if not a:
        return []
    m, (lo, hi) = a["median_s"], a["spans"]["slab"]
    return [f"   projection store read, {a['projections']} projections of {a['detector'][0]}x{a['detector'][1]} "
            f"({a['scene']}, {a['raw_bytes'] / 1e9:.2f} GB raw): rows {lo}-{hi - 1} from chunks of "
            f"{a['chunks']['rows'][1]} rows {m['rows/slab']:.2f} s, of whole projections "
            f"{m['projections/slab']:.2f} s: "
            f"speedup {a['speedup']['slab']:.2f}x; all rows {m['rows/whole']:.2f} vs {m['projections/whole']:.2f} s "
            f"({a['speedup']['whole']:.2f}x); disk {a['disk_bytes']['rows'] / 1e9:.2f} vs "
            f"{a['disk_bytes']['projections'] / 1e9:.2f} GB; {'bit-identical' if a['identical'] else 'DIFFERENT'} "
            f"(load {a['load'][0]:.1f} -> {a['load'][-1]:.1f})"]


def _table2_kept_lines(a: dict | None) -> list[str]:
    if not a:
        return []
    m = a["median_s"]
    return [f"   Table-2 sums per volume ({a['scene']}, {'x'.join(map(str, a['shape']))}): "
            f"kept arrays {m['kept']:.3f} s, fresh arrays {m['fresh']:.3f} s: speedup {a['speedup']:.2f}x, sums "
            f"{'bit-identical' if a['identical'] else 'DIFFERENT'} (load {a['load'][0]:.1f} -> {a['load'][-1]:.1f})"]


def _shared_vs_copied(a: dict, what: str, outputs: str) -> str:
    """One line of a read-in-place row: ``what`` (the data), both medians, the speedup, the outputs' identity."""
    m = a["median_s"]
    return (f"   {what}: read in place {m['shared']:.2f} s, copied {m['copied']:.2f} s: speedup {a['speedup']:.2f}x, "
            f"{outputs} {'bit-identical' if a['identical'] else 'DIFFERENT'} "
            f"(load {a['load'][0]:.1f} -> {a['load'][-1]:.1f})")


def _objects_shared_lines(a: dict | None) -> list[str]:
    if not a:
        return []
    return [_shared_vs_copied(a, f"posed objects to the projector ({a['scene']}, {a['projections']} projections, "
                                 f"{a['objects_bytes'] / 1e6:.0f} MB of objects)", "projections")]


def _rows_shared_lines(a: dict | None) -> list[str]:
    if not a:
        return []
    how = "" if a["in_place"] else "; not a CPU device, so copied either way"
    return [_shared_vs_copied(a, f"a slab's rows to the device + one launch ({a['scene']}, "
                                 f"{a['rows_bytes'] / 1e9:.2f} GB of rows, {a['sinograms']} sinograms, "
                                 f"K = {a['slots']}{how})", "sinograms")]


def _interp_launch_lines(a: dict | None) -> list[str]:
    if not a:
        return []
    head = (f"   interpolation + backprojection launches, {a['scene']}: {a['launches']} x {a['sinograms_per_launch']} "
            f"sinograms of {a['views']} x {a['columns']} from {a['candidates_per_view']} rows per view "
            f"({a['rows_bytes'] / 1e6:.0f} MB), {a['image'][0]}x{a['image'][1]}:")
    lines = [head]
    for k, r in a["by_k"].items():
        m = r["median_s"]
        lines.append(f"     K = {k}: now {m['now']:.2f} s, before {m['before']:.2f} s: speedup {r['speedup']:.2f}x "
                     f"(vectorised kernel {r['kernel_speedup']:.2f}x, scratch buffers {r['scratch_speedup']:.2f}x, "
                     f"8 columns per work-item {r['cols8_speedup']:.2f}x), "
                     f"images {'bit-identical' if r['identical'] else 'DIFFERENT'}")
        lines.append(f"       interpolation alone: {m['interp_now']:.3f} s with 8 columns per work-item, "
                     f"{m['interp_lanes']:.3f} s per lane: {r['cols8_interp_speedup']:.2f}x")
    lines[-1] += f" (load {a['load'][0]:.1f} -> {a['load'][-1]:.1f})"
    return lines


def _assembly_lines(a: dict | None) -> list[str]:
    if not a:
        return []
    m = a["median"]
    return [f"   volume assembly, {a['datasets']} LZF datasets ({a['raw_bytes'] / 1e9:.2f} GB raw): "
            f"in place (format 3) "
            f"{m['in_place']['assemble_s']:.3f} s, copied per dataset (format 2) {m['copy']['assemble_s']:.2f} s: "
            f"speedup {a['speedup']:.0f}x; read back {m['in_place']['read_s']:.2f} vs {m['copy']['read_s']:.2f} s "
            f"({a['read_ratio']:.2f}x), {'bit-identical' if a['identical'] else 'DIFFERENT'} "
            f"(load {a['load'][0]:.1f} -> {a['load'][-1]:.1f})"]


def _write_behind_lines(a: dict | None) -> list[str]:
    if not a:
        return []
    m = a["median_s"]
    return [f"   write behind, {a['steps']} steps of {a['images_per_step']} backprojections (512^2) + one float16 LZF "
            f"unit of {'x'.join(map(str, a['unit_shape']))} (backprojection {a['backproject_step_s']:.2f} s, write "
            f"{a['write_step_s']:.2f} s per step): written behind {m['behind']:.2f} s, in the foreground "
            f"{m['foreground']:.2f} s: speedup {a['speedup']:.2f}x, unit values "
            f"{'identical' if a['identical'] else 'DIFFERENT'} (load {a['load'][0]:.1f} -> {a['load'][-1]:.1f})"]


def _simulate_behind_lines(a: dict | None) -> list[str]:
    if not a:
        return []
    m, pitches = a["median_s"], ", ".join(f"{p:g}" for p in a["pitches"])
    return [f"   simulation written behind, {a['scene']} pitches {pitches} into fresh "
            f"stores: {m['behind']:.2f} s, in the foreground {m['foreground']:.2f} s: speedup {a['speedup']:.2f}x, "
            f"projections {'identical' if a['identical'] else 'DIFFERENT'} "
            f"(load {a['load'][0]:.1f} -> {a['load'][-1]:.1f})"]


if __name__ == "__main__":  # pragma: no cover - run by hand: python -m benchmarks.levers [--only ROW,...]
    from benchmarks._cli import main

    raise SystemExit(main(bench_levers, report_lines, rows=ROWS))
