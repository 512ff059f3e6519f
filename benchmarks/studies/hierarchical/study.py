"""Accuracy of a hierarchical (tile-decimating) fan-beam backprojection against the direct one.

Issue 20, item 4 asks for a backprojection >= 3x faster than ``direct`` whose MAEs stay within
0.5 HU of the direct path's. This study measures, in float64 NumPy on the paper's geometry
(paper-p010: 984 views x 900 columns of 0.8 mm, SID 595 / SDD 1085.6 mm, 512^2 x 1 mm, Ram-Lak),
what any decimation-based backprojection (Basu & Bresler's hierarchical scheme and its one-level
form) costs and how far its images move:

* ``direct``: the reference, ``mu(x) = dbeta sum_j (R/U_j)^2 Q_j(c_j(x))``, linear in the column
  (the float32 kernel ``backproject_batched16x2`` agrees with it to 0.015 HU).
* ``hier``: the image cut into square tiles; each tile gets its own sinogram, views merged
  D at a time (the D views' samples summed at the tile centre's column plus the local offset t,
  linear in the parent's t), sampled at ``delta`` columns; levels nest (a tile's children take
  its sinogram as their parent). The leaf backprojects its tile from its own sinogram with the
  exact column and weight of the merged view's mean angle. ``delta`` < 1 oversamples t.
* ``lowpass``: the direct backprojection of the filtered sinogram low-passed at ``fc`` cycles
  per column: how much of the direct image comes from frequencies above the image grid's.

For each variant: the pixel difference from ``direct`` on a noise-free slice (HU: RMS, 99th
percentile, max over the FOV), its cost (interpolations per image over the direct one's:
decimation samples x D + leaf updates; a bound on the speed-up that ignores memory traffic), and
the change of two MAEs against the direct path's, each against its own reference image made
the same way (as the run's truth is reconstructed by the same backprojector):
``noise``: MAE of (noisy - noise-free) (Poisson at the scene's I0 plus electronic noise on the
same in-plane sinogram, the noise module's generator), and ``motion``: MAE of (another cardiac
phase - this one), over the FOV (large) and the scene's small-FOV box.

Run from the repository root (about 3 min on one core):
    python benchmarks/studies/hierarchical/study.py          -> benchmarks/studies/hierarchical/study.json
    python benchmarks/studies/hierarchical/study.py hann     -> study-hann.json (the same with the Hann window)
"""

import json
import math
import os
import sys
import time

import numpy as np
import scipy.fft

import clrecon
from clrecon.core.conventions import mu_to_hu
from clrecon.evaluation.groundtruth import GroundTruthConfig, groundtruth_sinograms
from clrecon.evaluation.metrics import MetricsConfig, fov_masks
from clrecon.reconstruction.fbp import filter_rows
from clrecon.simulation.noise import add_noise

HERE = os.path.dirname(os.path.abspath(__file__))


def column(x, y, beta, g):
    """Fractional column and weight (R/U)^2 of points (x, y) mm in view beta (flat detector)."""
    cb, sb = np.cos(beta) / g.sid_mm, np.sin(beta) / g.sid_mm
    r = 1.0 / (1.0 - (x * cb + y * sb))
    return g.sdd_mm / g.col_pitch_mm * (y * cb - x * sb) * r + 0.5 * (g.n_cols - 1), r * r


def lerp(row, pos):
    """Linear interpolation of samples row[0..n-1] at fractional positions (clamped to the ends)."""
    n = row.shape[-1]
    pos = np.clip(pos, 0.0, n - 1 - 1e-9)
    i0 = np.floor(pos).astype(np.int64)
    t = pos - i0
    return row[i0] * (1.0 - t) + row[np.minimum(i0 + 1, n - 1)] * t


def pixel_grid(g):
    xs = (np.arange(g.nx) - 0.5 * (g.nx - 1)) * g.voxel_mm
    ys = (np.arange(g.ny) - 0.5 * (g.ny - 1)) * g.voxel_mm
    return xs, ys


def direct(q, g):
    """Float64 direct fan-beam backprojection of filtered views q (V, C): (ny, nx) mu."""
    xs, ys = pixel_grid(g)
    X, Y = np.meshgrid(xs, ys)
    fov = X ** 2 + Y ** 2 <= g.fov_radius_mm ** 2
    x, y = X[fov], Y[fov]
    acc = np.zeros(x.shape)
    db = 2 * math.pi / g.n_views
    for j in range(g.n_views):
        c, w = column(x, y, g.beta0_rad + j * db, g)
        acc += w * lerp(q[j], c)
    img = np.zeros((g.ny, g.nx))
    img[fov] = acc * db
    return img


def hierarchical(q, g, levels, delta, margin=2):
    """Float64 tile-decimating backprojection (module docstring); levels: [(tile_px, D), ...].

    Returns (image, interpolations done / direct's)."""
    V = g.n_views
    db = 2 * math.pi / V
    xs, ys = pixel_grid(g)
    R2 = g.fov_radius_mm ** 2
    centre = 0.5 * (g.n_cols - 1)
    tiles = [dict(x0=0, y0=0, nx=g.nx, ny=g.ny, cx=0.0, cy=0.0, S=q, t0=-centre, step=1.0)]
    angles = g.beta0_rad + db * np.arange(V)
    work = 0
    for T, D in levels:
        new_angles = angles.reshape(-1, D).mean(axis=1)
        out = []
        for P in tiles:
            pc, _ = column(P["cx"], P["cy"], angles, g)  # parent centre's column, every parent view
            for ty in range(P["y0"], P["y0"] + P["ny"], T):
                for tx in range(P["x0"], P["x0"] + P["nx"], T):
                    nx_, ny_ = min(T, P["x0"] + P["nx"] - tx), min(T, P["y0"] + P["ny"] - ty)
                    px, py = xs[tx:tx + nx_], ys[ty:ty + ny_]
                    near_x, near_y = np.clip(0.0, px[0], px[-1]), np.clip(0.0, py[0], py[-1])
                    if near_x ** 2 + near_y ** 2 > R2:
                        continue  # the tile lies outside the FOV circle: zeros
                    cx, cy = 0.5 * (px[0] + px[-1]), 0.5 * (py[0] + py[-1])
                    kx = np.array([px[0], px[-1], px[0], px[-1]])
                    ky = np.array([py[0], py[0], py[-1], py[-1]])
                    oc, _ = column(cx, cy, new_angles, g)
                    corners = np.stack([column(kx[i], ky[i], new_angles, g)[0] for i in range(4)])
                    t0 = math.floor((corners - oc).min() / delta) * delta - margin * delta
                    K = int(math.ceil(((corners - oc).max() + margin * delta - t0) / delta)) + 1
                    tk = t0 + delta * np.arange(K)
                    cc, _ = column(cx, cy, angles, g)  # this tile's centre column, every parent view
                    S = np.zeros((len(new_angles), K))
                    for m in range(len(new_angles)):
                        for d in range(D):
                            j = m * D + d
                            S[m] += lerp(P["S"][j], (tk + cc[j] - pc[j] - P["t0"]) / P["step"])
                    work += S.size * D
                    out.append(dict(x0=tx, y0=ty, nx=nx_, ny=ny_, cx=cx, cy=cy, S=S, t0=t0, step=delta))
        tiles, angles = out, new_angles
    img = np.zeros((g.ny, g.nx))
    for L in tiles:
        X, Y = np.meshgrid(xs[L["x0"]:L["x0"] + L["nx"]], ys[L["y0"]:L["y0"] + L["ny"]])
        inside = X ** 2 + Y ** 2 <= R2
        acc = np.zeros(X.shape)
        oc, _ = column(L["cx"], L["cy"], angles, g)
        for m, b in enumerate(angles):
            c, w = column(X, Y, b, g)
            acc += w * lerp(L["S"][m], (c - oc[m] - L["t0"]) / L["step"])
        work += int(inside.sum()) * len(angles)
        img[L["y0"]:L["y0"] + L["ny"], L["x0"]:L["x0"] + L["nx"]] = np.where(inside, acc * db, 0.0)
    return img, work


def lowpass(q, fc):
    n = scipy.fft.next_fast_len(2 * q.shape[1])
    f = scipy.fft.rfftfreq(n)
    return scipy.fft.irfft(scipy.fft.rfft(q, n=n, axis=1) * (f <= fc), n=n, axis=1)[:, :q.shape[1]]


VARIANTS = [("lowpass", 0.45), ("lowpass", 0.40), ("lowpass", 0.22),
            ("hier", [(32, 1)], 1.0), ("hier", [(32, 1)], 0.5), ("hier", [(32, 1)], 0.25),
            ("hier", [(32, 2)], 0.5), ("hier", [(32, 4)], 0.5), ("hier", [(16, 4)], 0.5),
            ("hier", [(32, 8)], 1.0), ("hier", [(16, 8)], 1.0), ("hier", [(16, 8)], 0.5),
            ("hier", [(64, 4), (16, 2)], 1.0), ("hier", [(64, 4), (16, 2)], 0.5)]


def name(v):
    if v[0] == "lowpass":
        return f"lowpass fc={v[1]}"
    return "hier " + " / ".join(f"{t}px D{d}" for t, d in v[1]) + f", delta={v[2]}"


def main(window=None):
    t_start = time.time()
    sc = clrecon.load_scene("paper-p010")
    cfg = GroundTruthConfig.from_scene(sc)
    g = cfg.fbp
    ph = cfg.source()
    z = np.array([0.0])
    clean = groundtruth_sinograms(cfg, ph, 0.3, 0.5, z)[0]
    moved = groundtruth_sinograms(cfg, ph, 0.6, 0.5, z)[0]
    noisy = add_noise(clean[:, None, :], np.arange(g.n_views), sc.noise)[:, 0, :]
    window = window or cfg.filter
    sinos = {k: filter_rows(s, g, window).astype(np.float64) for k, s in
             (("clean", clean), ("moved", moved), ("noisy", noisy))}
    mw = cfg.mu_water_per_mm
    masks = fov_masks(MetricsConfig.from_scene(sc))  # the metrics' own large and small FOVs
    fov = g.fov_mask()

    def maes(imgs):
        hu = {k: mu_to_hu(v, mw) for k, v in imgs.items()}
        out = {}
        for err, other in (("noise", "noisy"), ("motion", "moved")):
            d = np.abs(hu[other] - hu["clean"])
            out[err] = {k: float(d[masks[k]].mean()) for k in ("large", "small")}
        return out, hu["clean"]

    ref_imgs = {k: direct(q, g) for k, q in sinos.items()}
    ref_mae, ref_hu = maes(ref_imgs)
    rows = []
    for v in VARIANTS:
        t0 = time.time()
        if v[0] == "lowpass":
            imgs = {k: direct(lowpass(q, v[1]), g) for k, q in sinos.items()}
            cost = None
        else:
            imgs, works = {}, []
            for k, q in sinos.items():
                imgs[k], w = hierarchical(q, g, v[1], v[2])
                works.append(w)
            cost = works[0] / (int(fov.sum()) * g.n_views)
        m, hu = maes(imgs)
        e = (hu - ref_hu)[fov]
        rows.append({"variant": name(v), "cost": cost,
                     "pixel_rms_hu": float(np.sqrt((e ** 2).mean())), "pixel_p99_hu": float(np.percentile(np.abs(e), 99)),
                     "pixel_max_hu": float(np.abs(e).max()),
                     "mae_change_hu": {err: {fovn: m[err][fovn] - ref_mae[err][fovn] for fovn in ("large", "small")}
                                       for err in m}})
        print(json.dumps(rows[-1]), f"{time.time() - t0:.0f}s", flush=True)
    out_name = "study.json" if window == cfg.filter else f"study-{window}.json"
    json.dump({"date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()), "load": os.getloadavg(), "window": window,
               "seconds": round(time.time() - t_start), "reference_mae_hu": ref_mae, "rows": rows},
              open(os.path.join(HERE, out_name), "w"), indent=1)


if __name__ == "__main__":
    main(sys.argv[1] if len(sys.argv) > 1 else None)
