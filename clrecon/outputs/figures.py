"""Figures of a run directory (after metrics, before/with the report): PNGs in ``RUN_DIR/figures/``.

:func:`write_figures` is called by :func:`clrecon.outputs.report.write_report` and returns the
markdown lines that link the figures (or say why one was skipped);
:func:`clrecon.outputs.report_html.write_html` turns the whole report into a self-contained
``report.html`` with the figures inline.

The figures reproduce the paper's (Wang et al., 5DCT; ``docs/README.md`` "The paper"):

- ``phase_space.png`` (Figure 2): for one (slice, view) the SSRB candidate projections as
  points (cardiac phase c, respiratory amplitude a), a target, the triangle barycentric
  interpolation chose and the <= 8 quadrant neighbours of local linear interpolation;
- ``coronal.png`` (Figure 3): coronal plane through the heart; phantom, ground truth and
  each method at each pitch, physical mm aspect;
- ``motion_rows.png`` (Figure 4): the respiratory-only (fixed c, every a) and cardiac-only
  (fixed a, every c) parts of the 5DCT against r4DCT, coronal through the heart;
- ``mae_per_target_{small,large}.png``: MAE per (cardiac, respiratory) target, per method;
- ``error_vs_time.png``: pooled MAE against reconstruction seconds per method, pitch, variant.
- ``motion_metrics.png``: edge width, LV volume error, target localisation error and noise std
  (:mod:`clrecon.evaluation.motion`) per method, pitch and variant.
- ``consistency_slices.png``: the truth-free check's residual per sampled slice and method, with
  the slices where ``mc`` is lower or higher than its first pass (runs with ``mc``).

Everything is matplotlib with the Agg backend (no display). Display conventions: coronal
images with patient right on the left (+x, patient left, to the right) and superior up;
grey scales in HU with the window (W/L) in the title.
"""

from __future__ import annotations

import textwrap
from pathlib import Path

import numpy as np

from clrecon.core import atomic
from clrecon.core.conventions import circular_difference
from clrecon.core.errors import ClreconError
from clrecon.evaluation.consistency import METHOD as METHOD_JUDGED
from clrecon.evaluation.groundtruth import offers_lv_region
from clrecon.outputs.rundir import RunDirectory
from clrecon.reconstruction import interpolation as _methods
from clrecon.reconstruction import reconstruct
from clrecon.reconstruction.interpolation import weights as interpolate
from clrecon.scan import table as geometry
from clrecon.simulation.phantom_sources import phantom_from_config

#: Display windows (width, level) in HU.
WINDOWS = {"lung": (1500.0, -600.0), "mediastinum": (400.0, 40.0), "cardiac": (800.0, 200.0)}
#: From the interpolation-method registry: figure columns simplest first (reverse ``rank``),
#: the 5DCT methods, the respiratory-grid (r4DCT-like) methods, and the markers.
COMPARE_ORDER = _methods.figure_order()
FIVE_D = _methods.five_d_methods()
RESP_GRID = _methods.resp_grid_methods()
MARKERS = _methods.markers()
FIGURE_DIR = "figures"


def _plt():
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    return plt


def _nearest(values, x: float, periodic: bool = False) -> int:
    v = np.asarray(values, float)
    d = np.abs(v - x)
    if periodic:
        d = np.minimum(d, 1.0 - d)
    return int(np.argmin(d))


def _pct(x: float) -> str:
    return f"{round(100 * x):02d}%"


# ---------------------------------------------------------------------------------------------
# Run directory access
class _Run(RunDirectory):
    """The bits of a run the figures need: results, axes, volumes (lazy, one plane at a time).

    A :class:`~clrecon.outputs.rundir.RunDirectory` with the run's ``results`` given, short axis
    names (``c``, ``a``, ``z``, ``y``, ``x``) and the methods in comparison order.
    """

    def __init__(self, out_dir: Path, results: dict):
        super().__init__(out_dir, results)

    @property
    def c(self) -> np.ndarray:
        return self.cardiac

    @property
    def a(self) -> np.ndarray:
        return self.resp

    def methods(self, pk: str, variant: str) -> list[str]:
        ms = super().methods(pk, variant)
        return [m for m in COMPARE_ORDER if m in ms] + [m for m in ms if m not in COMPARE_ORDER]

    def coronal(self, name: str, ci: int, ri: int, iy: int) -> np.ndarray:
        """(nz, nx) HU of the coronal plane y index ``iy`` of target (ci, ri)."""
        return np.asarray(self.read_part(name, cardiac=ci, resp=ri, y=iy), np.float32)

    def heart_centre_mm(self, ci: int, ri: int) -> tuple[float, float, float]:
        """(x, y, z) mm of the LV blood pool (phantom), else the centre of the small-FOV box."""
        try:
            phantom = phantom_from_config(self.scene.phantom)
            if not offers_lv_region(phantom):
                raise ValueError(f"phantom.kind = {self.scene.phantom.kind!r} has no LV model")
            p = phantom.lv_blood_pool_centre(float(self.c[ci]), float(self.a[ri]))
            return float(p[0]), float(p[1]), float(p[2])
        # no readable scene (StoreError, SceneError, KeyError) or no LV in it (ValueError): use the heart box
        except (ClreconError, KeyError, ValueError):
            x0, x1, y0, y1 = self.results["scene"]["recon"]["small_fov_mm"]
            return (x0 + x1) / 2.0, (y0 + y1) / 2.0, float(np.median(self.z))

    def heart_plane_index(self, ci: int, ri: int) -> int:
        """y index of the coronal plane through the heart (clamped to the grid)."""
        return _nearest(self.y, self.heart_centre_mm(ci, ri)[1])

    def extent(self, x0i=0, x1i=None):
        """imshow extent [left, right, bottom, top] mm of a coronal (z, x) plane (voxel edges)."""
        x = self.x[x0i:x1i]
        dx = float(self.x[1] - self.x[0]) if self.x.size > 1 else 1.0
        dz = float(self.z[1] - self.z[0]) if self.z.size > 1 else float(self.results["scene"]["recon"]["slice_mm"])
        return [x[0] - dx / 2, x[-1] + dx / 2, self.z[0] - dz / 2, self.z[-1] + dz / 2]


def _colourbar(fig, im, label: str) -> None:
    """A colour bar in the right margin (the layout leaves x > 0.88 free)."""
    if im is not None:
        cax = fig.add_axes((0.9, 0.15, 0.015, 0.7))
        cb = fig.colorbar(im, cax=cax)
        cb.set_label(label, fontsize=8)
        cb.ax.tick_params(labelsize=7)


def _show_coronal(ax, img, extent, window, title=None):
    w, lv = WINDOWS[window]
    im = ax.imshow(img, cmap="gray", origin="lower", extent=extent, vmin=lv - w / 2, vmax=lv + w / 2,
                   aspect="equal", interpolation="nearest")
    if title:
        ax.set_title(title, fontsize=8)
    ax.tick_params(labelsize=6)
    return im


# ---------------------------------------------------------------------------------------------
# Figure 2: phase space
def phase_space_sample(scene, pitch: float, slice_z_mm: float, view: int, target) -> dict:
    """Candidates and the choices of barycentric and local linear for one (slice, view, target).

    Returns ``{"c", "a"}`` (n,) candidate phases/amplitudes, ``"index"`` (n,) their
    projection numbers, ``"target"`` (2,), and for each method ``"barycentric"`` /
    ``"local_linear"``: ``{"index": (k,) positions into the candidates, "weight": (k,)}``
    with non-zero weights only. Uses :func:`clrecon.reconstruction.reconstruct.candidate_groups_of`
    (the candidate window, then ``recon.max_turns``) and
    :func:`clrecon.reconstruction.interpolation.weights.method_weights` exactly as the reconstruction plan does.
    """
    table = geometry.cached_projection_table(scene, pitch)
    cfg = reconstruct.ReconstructionConfig.from_scene(scene)
    groups = reconstruct.candidate_groups_of(cfg, table, [float(slice_z_mm)])  # one slice: group = view
    rows = groups.row[groups.offsets[view]:groups.offsets[view + 1]]
    if rows.size == 0:
        raise ValueError(f"slice z = {slice_z_mm:.1f} mm, view {view}: no candidate projection")
    c = table.cardiac_phase[rows]
    a = table.resp_amplitude[rows]
    tg = np.asarray(target, float).reshape(1, 2)
    targets = reconstruct.Targets(tuple(scene.cardiac_targets), tuple(scene.resp_targets))
    opts = reconstruct.weight_options(cfg, targets)
    out = {"c": c, "a": a, "index": groups.projection[groups.offsets[view]:groups.offsets[view + 1]],
           "target": tg[0]}
    for m in FIVE_D:
        w = interpolate.method_weights(m, c, a, tg, **opts)
        live = np.asarray(w.weight[0]) != 0
        out[m] = {"index": np.asarray(w.index[0])[live], "weight": np.asarray(w.weight[0])[live]}
    return out


def plot_phase_space(path: Path, samples: list[tuple[str, dict]]) -> Path:
    """One panel per (title, :func:`phase_space_sample` result); writes ``path``."""
    plt = _plt()
    n = len(samples)
    fig, axes = plt.subplots(1, n, figsize=(5.2 * n, 4.6), squeeze=False)
    for ax, (title, s) in zip(axes[0], samples, strict=True):
        c0, a0 = s["target"]
        ax.scatter(s["c"], s["a"], s=14, c="tab:blue", alpha=0.6, label=f"candidates (n = {len(s['c'])})",
                   zorder=2)
        # chosen points drawn unwrapped next to the target (cardiac phase is periodic)
        b = s["barycentric"]
        bc = c0 + circular_difference(s["c"][b["index"]], c0)
        ba = s["a"][b["index"]]
        if len(b["index"]) >= 3:
            ax.fill(bc, ba, facecolor="tab:green", alpha=0.25, edgecolor="tab:green", lw=1.5, zorder=3,
                    label="barycentric triangle")
        elif len(b["index"]) == 2:
            ax.plot(bc, ba, color="tab:green", lw=1.5, zorder=3, label="barycentric segment")
        ax.scatter(bc, ba, s=60, facecolor="tab:green", edgecolor="k", zorder=4,
                   label=f"barycentric points ({len(b['index'])})")
        ll = s["local_linear"]
        lc = c0 + circular_difference(s["c"][ll["index"]], c0)
        ax.scatter(lc, s["a"][ll["index"]], s=150, facecolor="none", edgecolor="tab:orange", lw=2, zorder=5,
                   label=f"local linear neighbours ({len(ll['index'])})")
        ax.axvline(c0, color="0.6", lw=0.6, ls=":")
        ax.axhline(a0, color="0.6", lw=0.6, ls=":")
        ax.scatter([c0], [a0], marker="*", s=260, c="red", edgecolor="k", zorder=6,
                   label=f"target (c = {c0:.2f}, a = {a0:.2f})")
        lo = min(0.0, float(np.min(bc, initial=0.0)), float(np.min(lc, initial=0.0)))
        hi = max(1.0, float(np.max(bc, initial=1.0)), float(np.max(lc, initial=1.0)))
        ax.set_xlim(lo - 0.03, hi + 0.03)
        ax.set_ylim(-0.03, 1.03)
        ax.set_xlabel("cardiac phase c (fraction of the R-R interval)")
        ax.set_ylabel("respiratory amplitude a (normalised, 1 = end-inhale)")
        ax.set_title(title, fontsize=9)
        ax.legend(fontsize=6.5, loc="upper right", framealpha=0.85)
    fig.suptitle("Phase space of one (slice, view): candidate projections and the interpolation choices",
                 fontsize=10)
    fig.tight_layout()
    atomic.save_figure(fig, path, dpi=110)  # whole or not at all
    plt.close(fig)
    return path


def fig_phase_space(run: _Run, path: Path) -> str:
    scene = run.scene
    pitches = run.results["request"]["pitches"]
    z = float(np.median(run.z))
    ci = _nearest(run.c, 0.4, periodic=True)
    ri = _nearest(run.a, 0.55)
    target = (float(run.c[ci]), float(run.a[ri]))
    view = 0
    samples = []
    for p in pitches:
        s = phase_space_sample(scene, float(p), z, view, target)
        samples.append((f"pitch {p:g}, slice z = {z:.1f} mm, view {view} (gantry angle "
                        f"{scene.scan.start_angle_deg:.0f} deg + k 360 deg)", s))
    plot_phase_space(path, samples)
    return (f"Phase space (paper Figure 2): candidate projections of the slice at z = {z:.1f} mm, view {view}, "
            f"target c = {target[0]:.2f}, a = {target[1]:.2f}; green: the points barycentric interpolation "
            f"weights, orange rings: the local-linear quadrant neighbours.")


# ---------------------------------------------------------------------------------------------
# Figure 3: coronal comparison
def fig_coronal(run: _Run, path: Path, window: str = "cardiac") -> str:
    plt = _plt()
    ci = _nearest(run.c, 0.4, periodic=True)
    ri = _nearest(run.a, 0.55)
    iy = run.heart_plane_index(ci, ri)
    pks = run.pitches()
    refs = [n for n in ("phantom", "groundtruth") if run.has(n)]
    per_pitch = [(pk, run.preferred_variant(pk)) for pk in pks]
    methods = []
    for pk, v in per_pitch:
        methods += [m for m in run.methods(pk, v) if m not in methods]
    methods = [m for m in COMPARE_ORDER if m in methods] + [m for m in methods if m not in COMPARE_ORDER]
    ext = run.extent()
    aspect = (ext[1] - ext[0]) / (ext[3] - ext[2])
    cols = refs + methods
    n_rows = max(1, len(per_pitch))
    transpose = aspect > 2.2  # flat panels (few slices): stack the methods vertically
    nr, nc = (len(cols), n_rows) if transpose else (n_rows, len(cols))
    pw = 3.4 if transpose else 2.3
    ph = pw / aspect + 0.45
    fig, axes = plt.subplots(nr, nc, figsize=(pw * nc + 1.2, ph * nr + 0.9), squeeze=False)
    im = None
    for r, (pk, v) in enumerate(per_pitch or [(None, None)]):
        for k, name in enumerate(cols):
            ax = axes[k, r] if transpose else axes[r, k]
            if name in refs:
                if r > 0:
                    ax.axis("off")
                    continue
                ds, title = name, {"phantom": "phantom", "groundtruth": "ground truth"}[name]
            else:
                if pk is None or name not in run.methods(pk, v):
                    ax.axis("off")
                    continue
                ds, title = run.recon_name(pk, v, name), f"{name}, pitch {float(pk[1:]):g} ({v})"
            im = _show_coronal(ax, run.coronal(ds, ci, ri, iy), ext, window, title)
            ax.set_xlabel("x (mm, patient left ->)", fontsize=6)
            ax.set_ylabel("z (mm, superior ^)", fontsize=6)
    w, lv = WINDOWS[window]
    title = (f"Coronal plane through the heart, y = {run.y[iy]:.1f} mm; target c = {run.c[ci]:.2f}, "
             f"a = {run.a[ri]:.2f}; window {window} W{w:.0f}/L{lv:.0f} HU")
    # wrapped to the figure's width (about 14 characters per inch at 9 pt): a one-column figure
    # (a volume of many slices) clipped it
    lines = textwrap.wrap(title, width=max(30, int(fig.get_size_inches()[0] * 14)))
    fig.suptitle("\n".join(lines), fontsize=9)
    fig.tight_layout(rect=(0, 0, 0.88, 1.0 - 0.25 * len(lines) / fig.get_size_inches()[1]))
    _colourbar(fig, im, "HU")
    atomic.save_figure(fig, path, dpi=110)  # whole or not at all
    plt.close(fig)
    return (f"Coronal panels (paper Figure 3) through the heart (y = {run.y[iy]:.1f} mm) for c = {run.c[ci]:.2f}, "
            f"a = {run.a[ri]:.2f}: phantom, ground truth and each method at each pitch; physical aspect "
            f"(z spacing {abs(ext[3] - ext[2]) / max(len(run.z), 1):.2f} mm, x spacing "
            f"{abs(ext[1] - ext[0]) / max(len(run.x), 1):.2f} mm); window W{w:.0f}/L{lv:.0f} HU.")


# ---------------------------------------------------------------------------------------------
# Figure 4: respiratory-only / cardiac-only rows vs r4DCT
def motion_rows_skip_reason(run: _Run) -> str | None:
    if len(run.c) < 2 or len(run.a) < 2:
        return "needs at least two cardiac and two respiratory targets"
    if not run.pitches():
        return "the run has no reconstructions"
    if not any(m in run.methods(pk, v) for pk in run.pitches() for v in run.variants(pk) for m in RESP_GRID):
        names = " or ".join(RESP_GRID)
        return f"the run has no {names} reconstruction (run with --methods including {names})"
    if not any(m in run.methods(pk, v) for pk in run.pitches() for v in run.variants(pk) for m in FIVE_D):
        return f"the run has no 5DCT ({' or '.join(FIVE_D)}) reconstruction"
    return None


def fig_motion_rows(run: _Run, path: Path, window: str = "cardiac") -> str:
    plt = _plt()
    ci0 = _nearest(run.c, 0.4, periodic=True)
    ri0 = _nearest(run.a, 0.55)
    iy = run.heart_plane_index(ci0, ri0)
    # crop x to the heart box (the figure is about cardiac and respiratory motion of the heart)
    x0, x1 = run.results["scene"]["recon"]["small_fov_mm"][:2]
    xi = np.nonzero((run.x >= x0) & (run.x <= x1))[0]
    xs = slice(int(xi[0]), int(xi[-1]) + 1) if xi.size >= 2 else slice(None)
    ext = run.extent(xs.start or 0, xs.stop)
    rows = []  # (label, [(dataset, ci, ri, column title)])
    if run.has("groundtruth"):
        rows.append((f"ground truth\nrespiratory-only\nc = {run.c[ci0]:.2f}",
                     [("groundtruth", ci0, j, f"a {_pct(a)}") for j, a in enumerate(run.a)]))
    for pk in run.pitches():
        v = "noise-free" if "noise-free" in run.variants(pk) else run.preferred_variant(pk)
        ms = run.methods(pk, v)
        m5 = next((m for m in FIVE_D if m in ms), None)
        p = f"pitch {float(pk[1:]):g}"
        if m5:
            rows.append((f"5DCT {m5}\n{p}\nrespiratory-only\nc = {run.c[ci0]:.2f}",
                         [(run.recon_name(pk, v, m5), ci0, j, f"a {_pct(a)}") for j, a in enumerate(run.a)]))
            rows.append((f"5DCT {m5}\n{p}\ncardiac-only\na = {run.a[ri0]:.2f}",
                         [(run.recon_name(pk, v, m5), i, ri0, f"c {_pct(c)}") for i, c in enumerate(run.c)]))
        for mr in (m for m in RESP_GRID if m in ms):
            rows.append((f"{_methods.METHODS[mr].label}\n{p}", [(run.recon_name(pk, v, mr), ci0, j, f"a {_pct(a)}")
                                                               for j, a in enumerate(run.a)]))
    ncol = max(len(r[1]) for r in rows)
    aspect = (ext[1] - ext[0]) / (ext[3] - ext[2])
    pw = 1.7
    width = pw * ncol + 2.6
    fig, axes = plt.subplots(len(rows), ncol, figsize=(width, (pw / aspect + 0.3) * len(rows) + 1.0), squeeze=False)
    im = None
    for r, (label, cells) in enumerate(rows):
        for k in range(ncol):
            ax = axes[r, k]
            if k >= len(cells):
                ax.axis("off")
                continue
            ds, ci, ri, title = cells[k]
            im = _show_coronal(ax, run.coronal(ds, ci, ri, iy)[:, xs], ext, window, title)
            ax.set_xticks([])
            ax.set_yticks([])
            if k == 0:
                ax.set_ylabel(label, fontsize=7, rotation=0, ha="right", va="center", labelpad=6)
    w, lv = WINDOWS[window]
    fig.suptitle(f"Motion-resolved parts of 5DCT vs r4DCT; coronal y = {run.y[iy]:.1f} mm, "
                 f"x {ext[0]:.0f} to {ext[1]:.0f} mm (patient left to the right),\nz {ext[2]:.0f} to {ext[3]:.0f} mm "
                 f"(superior up); window W{w:.0f}/L{lv:.0f} HU", fontsize=9)
    fig.tight_layout(rect=(0.0, 0, 0.88, 0.93))
    _colourbar(fig, im, "HU")
    atomic.save_figure(fig, path, dpi=110)  # whole or not at all
    plt.close(fig)
    return ("Respiratory-only (fixed cardiac phase, every amplitude) and cardiac-only (fixed amplitude, every "
            "phase) rows of the 5DCT against r4DCT (paper Figure 4), noise-free where available, coronal "
            f"through the heart; window W{w:.0f}/L{lv:.0f} HU.")


# ---------------------------------------------------------------------------------------------
# MAE per target
#: Centred glyph outlines of the cell labels, (text, fontsize) -> Path (a few hundred at most).
_LABEL_PATHS: dict = {}


def _cell_labels(fig, ax, g: np.ndarray, vmax: float, fontsize: float = 5.5) -> None:
    """Each cell's value ``f"{v:.0f}"`` centred on cell (row i, column j) of ``g`` (n_i, n_j), as
    one PathCollection of glyph outlines (white below 0.6 vmax, black above; NaN cells unlabelled).

    Drawn as paths because Agg draws each ``ax.text`` on its own: the demo's two MAE-grid figures
    hold 2 x 1200 labels, which took 3.4-3.7 s of each figure's 3.4-3.7 s. A label's outline
    (:class:`matplotlib.textpath.TextPath`, the figure's default font, in points) is centred on
    its glyphs' box (of the outline's control points) and placed at the cell centre in data
    coordinates.
    """
    from matplotlib.collections import PathCollection
    from matplotlib.textpath import TextPath
    from matplotlib.transforms import Affine2D

    paths, offsets, colours = [], [], []
    for (i, j), val in np.ndenumerate(g):
        if not np.isfinite(val):
            continue
        text = f"{val:.0f}"
        key = (text, fontsize)
        if key not in _LABEL_PATHS:
            tp = TextPath((0.0, 0.0), text, size=fontsize)
            lo, hi = tp.vertices.min(axis=0), tp.vertices.max(axis=0)  # control points: the glyphs' box
            _LABEL_PATHS[key] = tp.transformed(Affine2D().translate(*(-(lo + hi) / 2)))
        paths.append(_LABEL_PATHS[key])
        offsets.append((j, i))
        colours.append("white" if val < 0.6 * vmax else "black")
    if paths:
        ax.add_collection(PathCollection(paths, offsets=np.asarray(offsets, float), offset_transform=ax.transData,
                                         transform=Affine2D().scale(1.0 / 72.0) + fig.dpi_scale_trans,
                                         facecolors=colours, edgecolors="none", linewidths=0),
                          autolim=False)


def fig_mae_per_target(run_results: dict, path: Path, fov: str) -> str:
    plt = _plt()
    met = run_results["metrics"]
    req = run_results["request"]
    cardiac = np.asarray(req["targets"]["cardiac"], float)
    resp = np.asarray(req["targets"]["resp"], float)
    rows = [(pk, v) for pk in met for v in met[pk]]
    methods = [m for m in COMPARE_ORDER if any(m in met[pk][v] for pk, v in rows)]
    methods += sorted({m for pk, v in rows for m in met[pk][v]} - set(methods))
    grids = {}
    for pk, v in rows:
        for m in methods:
            if m in met[pk][v]:
                g = np.asarray(met[pk][v][m]["per_target"][fov], float)
                grids[(pk, v, m)] = g
    vmax = max(float(np.nanmax(g)) for g in grids.values())
    fig, axes = plt.subplots(len(rows), len(methods), figsize=(2.3 * len(methods) + 1.2, 2.0 * len(rows) + 0.8),
                             squeeze=False)
    im = None
    for r, (pk, v) in enumerate(rows):
        for k, m in enumerate(methods):
            ax = axes[r, k]
            g = grids.get((pk, v, m))
            if g is None:
                ax.axis("off")
                continue
            im = ax.imshow(g, origin="lower", aspect="auto", cmap="magma", vmin=0, vmax=vmax,
                           extent=[-0.5, g.shape[1] - 0.5, -0.5, g.shape[0] - 0.5], interpolation="nearest")
            if g.size <= 60:
                _cell_labels(fig, ax, g, vmax)
            ax.set_xticks(range(g.shape[1]))
            ax.set_xticklabels([_pct(a) for a in resp[:g.shape[1]]], fontsize=5, rotation=90)
            ax.set_yticks(range(g.shape[0]))
            ax.set_yticklabels([_pct(c) for c in cardiac[:g.shape[0]]], fontsize=6)
            ax.set_title(f"{m}\npitch {float(pk[1:]):g}, {v}", fontsize=7)
            if r == len(rows) - 1:
                ax.set_xlabel("respiratory amplitude target", fontsize=6)
            if k == 0:
                ax.set_ylabel("cardiac phase target", fontsize=6)
    fig.suptitle(f"MAE vs ground truth per target, {fov} FOV (HU)", fontsize=9)
    # fixed margins in inches: tight_layout over the panels' 1000+ value labels took half the
    # figure's time (5 of 10 s on the demo) for the same layout
    w_in, h_in = fig.get_size_inches()
    fig.subplots_adjust(left=0.75 / w_in, right=0.86, bottom=0.85 / h_in, top=1 - 0.75 / h_in, wspace=0.35,
                        hspace=0.6)
    _colourbar(fig, im, "MAE (HU)")
    atomic.save_figure(fig, path, dpi=110)  # whole or not at all
    plt.close(fig)
    return (f"MAE (HU) per cardiac x respiratory target, {fov} FOV, one panel per method, pitch and variant; "
            f"colour scale 0 to {vmax:.0f} HU.")


# ---------------------------------------------------------------------------------------------
# error vs run time
def fig_error_vs_time(results: dict, path: Path) -> str:
    """Pooled MAE against each method's seconds (``results["method_seconds"]``: plan +
    interpolation + FBP), large and small FOV side by side; colour = pitch, marker = method,
    filled = noise-free, open = noisy. Constrained layout, legend outside the axes, plain
    tick labels (no per-point text: it overlapped where methods take similar time)."""
    plt = _plt()
    from matplotlib.lines import Line2D
    from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter

    met = results["metrics"]
    secs = results["method_seconds"]
    markers = MARKERS
    colours = {}
    fig, axes = plt.subplots(1, 2, figsize=(11.0, 4.3), layout="constrained")
    used = []
    for pk, byv in secs.items():
        colours.setdefault(pk, f"C{len(colours)}")
        for v, bym in byv.items():
            for m, s in bym.items():
                if m not in met.get(pk, {}).get(v, {}):
                    continue
                for ax, fov in zip(axes, ("large", "small"), strict=True):
                    mae = met[pk][v][m][fov]["mae_hu"]
                    ax.scatter([s], [mae], marker=markers.get(m, "x"), s=60, edgecolor=colours[pk],
                               facecolor=colours[pk] if v == "noise-free" else "none", lw=1.5)
                if m not in used:
                    used.append(m)
    for ax, fov in zip(axes, ("large", "small"), strict=True):
        ax.set_xscale("log")
        ax.xaxis.set_major_locator(LogLocator(subs=(1.0, 2.0, 5.0)))
        ax.xaxis.set_major_formatter(FuncFormatter(lambda x, _: f"{x:g}"))
        ax.xaxis.set_minor_formatter(NullFormatter())
        ax.tick_params(labelsize=8)
        ax.set_xlabel("seconds of the method (plan + interpolation + FBP)", fontsize=8)
        ax.set_ylabel("MAE vs ground truth (HU)", fontsize=8)
        ax.set_title(f"{fov} FOV", fontsize=9)
        ax.grid(alpha=0.3, which="both")
    leg = [Line2D([], [], ls="", marker="o", color=col, label=f"pitch {float(pk[1:]):g}")
           for pk, col in colours.items()]
    leg += [Line2D([], [], ls="", marker="o", markeredgecolor="k", markerfacecolor="k", label="noise-free"),
            Line2D([], [], ls="", marker="o", markeredgecolor="k", markerfacecolor="none", label="noisy")]
    leg += [Line2D([], [], ls="", marker=markers.get(m, "x"), color="0.3", label=_label(m)) for m in used]
    fig.legend(handles=leg, fontsize=7, loc="outside right center")
    device = str(results.get("device", "?"))
    fig.suptitle(f"Error against run time (device: {device[:70] + ('...' if len(device) > 70 else '')})",
                 fontsize=9)
    atomic.save_figure(fig, path, dpi=110)  # whole or not at all
    plt.close(fig)
    return ("MAE (HU, pooled over all targets) against the seconds each method took (its plan, interpolation "
            "and FBP), per pitch and variant.")


def _label(method: str) -> str:
    """The registry's human label of ``method`` (the name itself when unregistered)."""
    m = _methods.METHODS.get(method)
    return m.label if m is not None else method


# ---------------------------------------------------------------------------------------------
# motion metrics
MOTION_PANELS = (("edge_width_mm", "edge width 10–90 % (mm)"), ("lv_volume_error_ml", "LV volume − ground truth (mL)"),
                 ("target_error_mm", "target localisation error (mm)"), ("noise_std_hu", "noise std (HU)"))


def fig_motion_metrics(results: dict, path: Path) -> str:
    """Dots per method for the four motion metrics (means over targets), one colour per pitch,
    filled = noise-free, open = noisy; the ground truth's own value (the floor) as a dashed line."""
    plt = _plt()
    mot = results["motion"]
    cols = [(pk, v) for pk in mot for v in mot[pk]]
    present = {m for pk, v in cols for m in mot[pk][v]} - {"groundtruth"}
    methods = [m for m in COMPARE_ORDER if m in present] + sorted(present - set(COMPARE_ORDER))
    colours = {pk: f"C{k}" for k, pk in enumerate(mot)}
    fig, axes = plt.subplots(1, 4, figsize=(4.0 * 4, 3.8))
    offs = np.linspace(-0.25, 0.25, len(cols)) if len(cols) > 1 else np.zeros(1)
    for ax, (key, label) in zip(axes, MOTION_PANELS, strict=True):
        ref = None
        for k, (pk, v) in enumerate(cols):
            g = (mot[pk][v].get("groundtruth") or {}).get(key) or {}
            ref = g.get("mean") if ref is None else ref
            for x, m in enumerate(methods):
                d = (mot[pk][v].get(m) or {}).get(key) or {}
                if d.get("mean") is None:
                    continue
                ax.scatter([x + offs[k]], [d["mean"]], s=40, marker=MARKERS.get(m, "o"), edgecolor=colours[pk],
                           facecolor=colours[pk] if v == "noise-free" else "none", lw=1.4)
        if key in ("lv_volume_error_ml",):
            ax.axhline(0.0, color="0.5", lw=0.8)
        if ref is not None and key in ("edge_width_mm", "target_error_mm"):
            ax.axhline(ref, color="k", ls="--", lw=0.9, label="ground truth")
            ax.legend(fontsize=7, loc="best")
        ax.set_xticks(range(len(methods)))
        ax.set_xticklabels(methods, rotation=30, fontsize=7, ha="right")
        ax.set_title(label, fontsize=9)
        ax.grid(alpha=0.3)
    from matplotlib.lines import Line2D

    leg = [Line2D([], [], ls="", marker="o", color=col, label=f"pitch {float(pk[1:]):g}")
           for pk, col in colours.items()]
    leg += [Line2D([], [], ls="", marker="o", markeredgecolor="k", markerfacecolor="k", label="noise-free"),
            Line2D([], [], ls="", marker="o", markeredgecolor="k", markerfacecolor="none", label="noisy")]
    axes[-1].legend(handles=leg, fontsize=7, loc="center left", bbox_to_anchor=(1.02, 0.5))
    fig.suptitle("Motion metrics, means over targets", fontsize=10)
    fig.tight_layout()
    atomic.save_figure(fig, path, dpi=110)  # whole or not at all
    plt.close(fig)
    return ("Means over targets of the LV edge width, the LV blood-pool volume error, the lesion localisation "
            "error and the noise std per method, pitch (colour) and variant (filled: noise-free, open: noisy); "
            "dashed: the ground truth's own value.")


# ---------------------------------------------------------------------------------------------
# truth-free consistency, per slice
#: Line colours of the methods: matplotlib's cycle without its green and red (the triangles').
LINE_COLOURS = ("C0", "C1", "C4", "C5", "C6", "C7", "C8", "C9")


def fig_consistency_slices(results: dict, path: Path) -> str:
    """The consistency check's RMS residual (HU mm, channels through the circle) per sampled slice
    z, one line per method, one panel per (pitch, variant) (``results["consistency"]``); the slices
    where the verdict's method is lower than its first pass marked on its line by a filled triangle
    pointing down, higher by one pointing up, in the whole circle (``verdict[variant].regions.all.per_slice``)."""
    plt = _plt()
    cons = {pk: e for pk, e in (results.get("consistency") or {}).items() if "residual" in e}
    cells = [(pk, v) for pk, e in cons.items() for v in e["residual"]]
    fig, axes = plt.subplots(1, len(cells), figsize=(4.6 * len(cells) + 1.6, 3.6), squeeze=False,
                             layout="constrained")
    for ax, (pk, v) in zip(axes[0], cells, strict=True):
        ent = cons[pk]
        z = np.asarray(ent["config"]["slices_z_mm"], float)
        ver = ent["verdict"].get(v) or {}
        who = None
        for k, (m, e) in enumerate(ent["residual"][v].items()):
            ax.plot(z, e["per_slice_rms_hu_mm"], marker=MARKERS.get(m, "o"), ms=4, lw=1.2, color=LINE_COLOURS[k % 8],
                    label=_label(m))
            if m == METHOD_JUDGED:
                who = np.asarray(e["per_slice_rms_hu_mm"], float)
        per = ((ver.get("regions") or {}).get("all") or {}).get("per_slice") or []
        if who is not None and len(per) == z.size:
            for says, mk, col in (("lower", "v", "tab:green"), ("higher", "^", "tab:red")):
                at = np.array([p["says"] == says for p in per])
                if at.any():
                    ax.scatter(z[at], who[at], marker=mk, s=44, color=col, zorder=5,
                               label=f"{_label(METHOD_JUDGED)} {says} than {_label(ver['against'])} here")
        ax.set_title(f"pitch {float(pk[1:]):g}, {v}: " + ("helped" if ver.get("helped") else
                                                          "did not help" if ver.get("helped") is False else
                                                          "no clear difference"), fontsize=9)
        ax.set_xlabel("slice z (mm)", fontsize=8)
        ax.set_ylabel("RMS residual (HU mm)", fontsize=8)
        ax.tick_params(labelsize=7)
        ax.grid(alpha=0.3)
    legend = {}  # every panel's entries once (a panel may lack a triangle another has)
    for ax in axes[0]:
        for h, lab in zip(*ax.get_legend_handles_labels(), strict=True):
            legend.setdefault(lab, h)
    fig.legend(list(legend.values()), list(legend), fontsize=7, loc="outside right center")
    fig.suptitle("Truth-free consistency per sampled slice (lower: the volumes explain the rows better)", fontsize=9)
    atomic.save_figure(fig, path, dpi=110)  # whole or not at all
    plt.close(fig)
    return (f"RMS residual of the rows against each method's volumes per sampled slice (channels through the "
            f"reconstruction circle, HU mm); triangles mark the slices where {METHOD_JUDGED} is consistently lower "
            f"(down) or higher (up) than its first pass. The verdict is a sign test over these slices "
            f"(docs/consistency.md).")


# ---------------------------------------------------------------------------------------------
#: The figures drawn from ``results`` alone (no volumes): name -> function(results, path, *args).
_RESULTS_FIGURES = {"mae_per_target": fig_mae_per_target, "error_vs_time": fig_error_vs_time,
                    "motion_metrics": fig_motion_metrics, "consistency_slices": fig_consistency_slices}
def _draw_results_figure(kind: str, results: dict, path: str, args: tuple) -> tuple[bool, str]:
    """(ok, caption or error) of one results-only figure; run in the figure process or here."""
    try:
        return True, _RESULTS_FIGURES[kind](results, Path(path), *args)
    except Exception as e:  # noqa: BLE001 - a figure must not cost the run its report
        return False, f"{type(e).__name__}: {e}"


def write_figures(out_dir, results: dict, pool=None) -> list[str]:
    """Write every figure the run has inputs for into ``out_dir/figures``; markdown lines back.

    A figure whose inputs the run lacks is skipped with a line saying why; one that fails is
    reported as a line too, so that the report (and ``results.json`` after it) is still written.
    ``pool``: a process pool (the run's warm helper process, :mod:`clrecon.pipeline.executors.local`)
    in which the figures drawn from ``results`` alone are drawn while this process draws those
    that read the volumes (matplotlib is single-threaded; on demo the report took 7.6 s of an
    80 s run, half of it the two MAE-grid figures); it is left running. None: all here. The lines
    keep the same order either way, and each figure is the same (the same code, the same inputs).
    """
    out_dir = Path(out_dir)
    fig_dir = out_dir / FIGURE_DIR
    fig_dir.mkdir(parents=True, exist_ok=True)
    lines = ["## Figures", ""]
    run = None
    try:
        run = _Run(out_dir, results)
    except (ClreconError, OSError) as e:  # StoreError: missing, unreadable or old volumes.h5
        return lines + [f"- Figures skipped: the run's volumes cannot be read ({e}).", ""]

    entries: list = []  # per figure, in report order: its markdown lines, or a pending (title, name, future)

    def done(title: str, name: str, ok: bool, text: str) -> list[str]:
        if not ok:
            return [f"- *{title}: failed ({text}).*", ""]
        return [f"### {title}", "", f"![{title}]({FIGURE_DIR}/{name})", "", text, ""]

    def add(name: str, title: str, fn, skip: str | None = None):
        if skip:
            entries.append([f"- *{title}: skipped, {skip}.*", ""])
            return
        try:
            caption = fn(fig_dir / name)
        except Exception as e:  # noqa: BLE001 - a figure must not cost the run its report
            entries.append(done(title, name, False, f"{type(e).__name__}: {e}"))
            return
        entries.append(done(title, name, True, caption))

    def add_results(name: str, title: str, kind: str, args: tuple = (), skip: str | None = None):
        if skip:
            entries.append([f"- *{title}: skipped, {skip}.*", ""])
            return
        path = str(fig_dir / name)
        if fig_pool is not None:
            try:
                fut = fig_pool.submit(_draw_results_figure, kind, results, path, args)
                entries.append((title, name, fut, (kind, results, path, args)))
                return
            except RuntimeError:  # the pool broke: draw here
                pass
        entries.append(done(title, name, *_draw_results_figure(kind, results, path, args)))

    has_metrics = any(results.get("metrics", {}).get(pk) for pk in results.get("metrics", {}))
    n_targets = len(run.c) * len(run.a)
    fig_pool = pool if has_metrics and n_targets >= 2 else None
    try:
        # queued first, so that the second process draws while this one draws the volume figures
        for fov in ("small", "large"):
            add_results(f"mae_per_target_{fov}.png", f"MAE per target, {fov} FOV", "mae_per_target", (fov,),
                        "the run has a single target" if n_targets < 2 else (None if has_metrics else
                                                                             "the run has no metrics"))
        has_secs = any(bym for byv in results.get("method_seconds", {}).values() for bym in byv.values())
        add_results("error_vs_time.png", "Error against run time", "error_vs_time", (),
                    ("a measured scan has no ground truth, so no error" if results.get("measured") else
                     None if has_secs and has_metrics else "results.json has no method_seconds or no metrics"))
        has_motion = any(byv for byv in (results.get("motion") or {}).values())
        add_results("motion_metrics.png", "Motion metrics", "motion_metrics", (),
                    None if has_motion else "results.json has no motion metrics")
        if any("residual" in e for e in (results.get("consistency") or {}).values()):  # runs with mc only
            add_results("consistency_slices.png", f"Did {METHOD_JUDGED} help? Per slice", "consistency_slices")
        tail, entries[:] = entries[:], []
        has_5d = results.get("dimensions", {}).get("cardiac", True) or results.get("dimensions", {}).get("resp", True)
        add("phase_space.png", "Phase space of one slice and view", lambda p: fig_phase_space(run, p),
            None if has_5d else "the scene has neither cardiac nor respiratory motion")
        add("coronal.png", "Coronal comparison through the heart", lambda p: fig_coronal(run, p),
            None if (run.pitches() or run.has("groundtruth")) else "the run has no volumes to show")
        add("motion_rows.png", "Respiratory-only and cardiac-only 5DCT vs r4DCT",
            lambda p: fig_motion_rows(run, p), motion_rows_skip_reason(run))
        entries.extend(tail)
        for e in entries:
            if isinstance(e, tuple):
                title, name, fut, call = e
                try:
                    ok, text = fut.result()
                except Exception:  # noqa: BLE001 - the process died (BrokenProcessPool) or could not start
                    ok, text = _draw_results_figure(*call)
                e = done(title, name, ok, text)
            lines.extend(e)
    finally:
        run.close()
    return lines
