"""``python -m benchmarks.backprojector``: images/s of each ``recon.backprojector`` at the paper's size.

Every option runs on the same in-plane fan-beam sinograms of the thorax phantom (paper-p010's
scanner: 984 views x 900 columns, 512^2 images of 1 mm), already on the device in the
interleaved layout the interpolation writes, as the reconstruction runs them; the repeats of
the options alternate so that a change of the machine's load hits both. ``speedup`` is an
option's images/s over ``direct``'s in the same run.

``direct`` is timed two ways: its backprojection alone (the reconstruction filters each
rebinned row once and shares it between every method and target, so per image the filter
is a small share) and with the filter of the image's own V rows (an upper bound of its
cost). ``parallel-rebin`` is the whole of its FBP stage: rebin kernel, read back, host ramp
filter of the V/2 parallel rows, upload, parallel backprojection (its parts are timed too).
The images of the options are compared pixel by pixel inside the FOV (HU).
"""

from __future__ import annotations

import time

import numpy as np

from clrecon.bench.paper import _scene, _thorax_sinograms
from clrecon.bench.timing import load1, timed
from clrecon.core.conventions import mu_to_hu
from clrecon.core.runtime import get_runtime
from clrecon.reconstruction import fbp, parallel_fbp


def bench_backprojector(scene="paper-p010", *, n_images: int = 32, repeats: int = 3, rt=None) -> dict:
    """Images/s and speedup over ``direct`` of every backprojector (module docstring); a dict."""
    sc = _scene(scene)
    rt = rt or get_runtime()
    geom = fbp.FanBeamGeometry.from_scene(sc)
    window = sc.recon.filter
    mu_w = sc.phantom.mu_water_per_mm
    sino = _thorax_sinograms(sc, n_images, rt)
    B, V, C = sino.shape
    load_before = load1()
    step = fbp.groups_per_launch(geom) * fbp.BATCH_LANES

    rows = sino.reshape(-1, C).copy()
    t_filter = timed(lambda: fbp.filter_rows(rows, geom, window, out=rows))
    filtered = rows.reshape(B, V, C)
    direct_bufs, raw_bufs = [], []
    for b0 in range(0, B, step):
        g = fbp.interleave_batch(filtered[b0:b0 + step])
        direct_bufs.append((rt.to_device(g), g.shape[0], min(step, B - b0)))
        g = fbp.interleave_batch(sino[b0:b0 + step])
        raw_bufs.append((rt.to_device(g), g.shape[0], min(step, B - b0)))
    par = parallel_fbp.ParallelFBP(geom, window, runtime=rt)
    out = {}

    def run_direct():
        out["direct"] = np.concatenate([fbp.backproject_interleaved(b, g, geom, runtime=rt)[:n]
                                        for b, g, n in direct_bufs])

    def run_parallel():
        out["parallel-rebin"] = np.concatenate([par.images(b, g)[:n] for b, g, n in raw_bufs])

    run_direct()  # warm-up: kernel builds, PoCL specialisation
    run_parallel()
    times = {"direct": [], "parallel-rebin": []}
    loads = []
    for _ in range(max(1, repeats)):
        loads.append(load1())
        times["direct"].append(timed(run_direct))
        times["parallel-rebin"].append(timed(run_parallel))
    # the parallel path's parts, once each on the first launch
    b, g, n = raw_bufs[0]
    parts = {}
    t0 = time.perf_counter()
    d_par, ev = par.rebin(b, g)
    host = rt.from_device(d_par, (g, par.par.n_angles, par.par.n_s, fbp.BATCH_LANES), wait_for=[ev])
    parts["rebin_s"] = time.perf_counter() - t0
    d_par.release()
    t0 = time.perf_counter()
    filt = par.filter_interleaved(host)
    parts["filter_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    d_f = rt.to_device(filt)
    par.backproject(d_f, g)
    parts["backproject_s"] = time.perf_counter() - t0
    d_f.release()
    for bufs in (direct_bufs, raw_bufs):
        for buf, _, _ in bufs:
            buf.release()
    par.release()
    parts = {k: v / (g * fbp.BATCH_LANES) for k, v in parts.items()}  # per image (16 g images per launch)

    med = {k: float(np.median(v)) for k, v in times.items()}
    m = geom.fov_mask()
    hu = {k: mu_to_hu(v, mu_w)[:, m] for k, v in out.items()}
    d = (hu["parallel-rebin"] - hu["direct"]).astype(np.float64)
    direct_own_rows_s = med["direct"] / B + t_filter / B
    options = {
        "direct": {"images_per_s": B / med["direct"], "seconds": times["direct"],
                   "images_per_s_with_own_rows_filter": 1.0 / direct_own_rows_s, "speedup": 1.0,
                   "what": "fan backprojection of V views from the device (rows filtered once, shared)"},
        "parallel-rebin": {"images_per_s": B / med["parallel-rebin"], "seconds": times["parallel-rebin"],
                           "speedup": med["direct"] / med["parallel-rebin"],
                           "speedup_vs_direct_with_own_rows_filter": direct_own_rows_s * B / med["parallel-rebin"],
                           "per_image_s": parts, "n_angles": par.par.n_angles, "n_s": par.par.n_s,
                           "ds_mm": par.par.ds_mm,
                           "what": "rebin + host ramp filter of V/2 rows + parallel backprojection"},
    }
    return {"device": rt.description, "scene": sc.name, "image": [geom.ny, geom.nx], "voxel_mm": geom.voxel_mm,
            "views": V, "cols": C, "images": B, "repeats": repeats, "load_average_1min_before": load_before,
            "load_average_1min_repeats": loads, "direct_filter_s_per_image": t_filter / B, "options": options,
            "pixel_diff_hu": {"vs": "direct", "in": "FOV circle", "max": float(np.abs(d).max()),
                              "rms": float(np.sqrt(np.mean(d ** 2))), "mean": float(d.mean())}}


def report_lines(res: dict | None) -> list:
    """Report lines of a :func:`bench_backprojector` result (none if absent)."""
    if not res:
        return []
    pd = res["pixel_diff_hu"]
    out = ["", f"B. backprojector: {res['images']} thorax images {res['image'][1]}^2 from {res['views']} views x "
               f"{res['cols']} columns ({res['scene']}); load {res['load_average_1min_before']} "
               f"(repeats {res['load_average_1min_repeats']})",
           f"   {'option':16s} {'images/s':>9s} {'speedup':>8s}  notes"]
    for name, o in res["options"].items():
        if name == "direct":
            note = (f"{o['images_per_s_with_own_rows_filter']:.1f} images/s with the filter of its own rows "
                    f"({1e3 * res['direct_filter_s_per_image']:.1f} ms/image)")
        else:
            p = o["per_image_s"]
            note = (f"{o['n_angles']} views x {o['n_s']} samples of {o['ds_mm']:.3f} mm; per image rebin "
                    f"{1e3 * p['rebin_s']:.1f} ms, filter {1e3 * p['filter_s']:.1f} ms, backprojection "
                    f"{1e3 * p['backproject_s']:.1f} ms; {o['speedup_vs_direct_with_own_rows_filter']:.2f}x "
                    "vs direct with its own rows' filter")
        out.append(f"   {name:16s} {o['images_per_s']:>9.1f} {o['speedup']:>7.2f}x  {note}")
    out.append(f"   pixel difference parallel-rebin - direct in the FOV: max {pd['max']:.1f} HU, "
               f"RMS {pd['rms']:.2f} HU, mean {pd['mean']:+.3f} HU")
    return out


def _bench(quick: bool = False, repeats: int = 3) -> dict:
    """Images/s of every recon.backprojector on paper-p010's thorax images, same run."""
    return bench_backprojector(n_images=16 if quick else 32, repeats=repeats)


if __name__ == "__main__":  # pragma: no cover - run by hand: python -m benchmarks.backprojector
    from benchmarks._cli import main

    raise SystemExit(main(_bench, report_lines))
