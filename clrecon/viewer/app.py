"""The 5D volume viewer: ``python -m clrecon view RUN_DIR [--screenshot FILE ...]`` (pyvista).

Four viewports on one 5D volume of a run directory: axial, coronal and sagittal slices
(radiological display: patient right on screen left, anterior up in axial, superior up in
coronal/sagittal, physical mm aspect) and a volume rendering. Interactive controls:

- sliders: cardiac phase and respiratory amplitude (the run's targets), the source
  (each reconstruction, the ground truth, the phantom) and the three slice positions (mm);
- buttons: difference (source - ground truth) on/off; window-level presets lung
  (W1500/L-600), mediastinum (W400/L40), cardiac (W800/L200);
- text: what is shown, and the (x, y, z) mm position and HU value under the cursor.

``--screenshot`` renders the same views offscreen (no display needed: VTK's EGL/OSMesa
offscreen window from the VTK wheel) and writes a PNG.

Data (:class:`RunData`) and view state (:class:`ViewState`) are plain Python, independent of
pyvista, so they are tested without rendering.

Caveat: on a machine without a GPU the OpenGL context comes from Mesa's llvmpipe, which loads
Mesa's LLVM; PoCL (the OpenCL CPU device, another LLVM) then aborts if it is initialised later
in the same process. ``clrecon view`` never needs OpenCL, and the tests render in a child
process; do not render and run OpenCL in one Python process.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from clrecon.core import atomic
from clrecon.core.errors import ClreconError
from clrecon.outputs.export import target_tag
from clrecon.outputs.rundir import RunDirectory, Source

#: Window presets: name -> (width, level) in HU.
WINDOWS = {"lung": (1500.0, -600.0), "mediastinum": (400.0, 40.0), "cardiac": (800.0, 200.0)}
#: Window for difference images (recon - GT): symmetric around 0 HU.
DIFFERENCE_WINDOW = (400.0, 0.0)
#: Largest volume-rendering grid per axis (strided down beyond that: keeps CPU rendering fast).
VOLUME_RENDER_MAX = 160


def window_clim(width: float, level: float) -> tuple[float, float]:
    """Display range (HU) of a window: (level - width/2, level + width/2)."""
    return (level - width / 2.0, level + width / 2.0)


def nearest_index(values: np.ndarray, value: float, what: str, periodic: bool = False) -> int:
    """Index of the target nearest ``value`` (cardiac phase is periodic); error if far off."""
    v = np.asarray(values, float)
    d = np.abs(v - value)
    if periodic:
        d = np.minimum(d, 1.0 - d)
    i = int(np.argmin(d))
    spacing = float(np.min(np.diff(np.sort(v)))) if v.size > 1 else 1.0
    if d[i] > max(0.5 * spacing, 1e-6) + 1e-9:
        listed = ", ".join(f"{x:.3g}" for x in v)
        raise ClreconError(f"--{what} {value:g}: no target near it; this run's {what} targets are {listed}")
    return i


def parse_fraction(text) -> float | None:
    """``0.4``, ``"0.4"`` or ``"40%"`` -> 0.4 (None stays None)."""
    if text is None:
        return None
    s = str(text).strip()
    try:
        return float(s[:-1]) / 100.0 if s.endswith("%") else float(s)
    except ValueError:
        raise ClreconError(f"{text!r}: expected a fraction such as 0.4 or a percentage such as 40%") from None


class RunData(RunDirectory):
    """The volumes of one run directory, read one target at a time (the viewer's :class:`RunDirectory`).

    ``axes``: ``cardiac_phase`` (n_c,), ``resp_amplitude`` (n_r,), ``z_mm`` (nz,),
    ``y_mm`` (ny,), ``x_mm`` (nx,) (LPS, mm). ``sources``: every volume present.
    Adds a small cache of target volumes and difference images.
    """

    def __init__(self, run_dir):
        super().__init__(run_dir)
        self.run_dir = Path(run_dir)
        if not self.sources:
            self.close()
            raise ClreconError(f"{self.run_dir}: the volume store holds no volumes")
        self._cache: dict = {}

    def volume(self, source: Source, ci: int, ri: int, difference: bool = False) -> np.ndarray:
        """(nz, ny, nx) float32 HU of one target; ``difference``: source - ground truth."""
        key = (source.dataset, ci, ri, difference)
        if key not in self._cache:
            vol = self.read_target(source, ci, ri)
            if difference:
                if not self.has_groundtruth:
                    raise ClreconError("this run has no ground truth, so there is no difference image")
                vol = vol - self.read_target("groundtruth", ci, ri)
            if len(self._cache) > 8:
                self._cache.pop(next(iter(self._cache)))
            self._cache[key] = vol
        return self._cache[key]

    def probe(self, vol: np.ndarray, xyz_mm) -> tuple[int, int, int, float] | None:
        """Nearest voxel (iz, iy, ix) and its value at the point (x, y, z) mm; None if outside."""
        idx = []
        for k, p in zip(("z_mm", "y_mm", "x_mm"), (xyz_mm[2], xyz_mm[1], xyz_mm[0]), strict=True):
            ax = self.axes[k]
            d = float(ax[1] - ax[0]) if ax.size > 1 else 1.0
            i = int(round((p - ax[0]) / d))
            if not 0 <= i < ax.size:
                return None
            idx.append(i)
        return idx[0], idx[1], idx[2], float(vol[idx[0], idx[1], idx[2]])


@dataclass(frozen=True)
class ViewState:
    """What the viewer shows: source index, target indices, difference flag, window, slice mm."""

    source: int
    cardiac: int
    resp: int
    difference: bool = False
    window: str = "mediastinum"
    x_mm: float = 0.0
    y_mm: float = 0.0
    z_mm: float = 0.0

    def clim(self) -> tuple[float, float]:
        return window_clim(*(DIFFERENCE_WINDOW if self.difference else WINDOWS[self.window]))


def initial_state(data: RunData, method=None, pitch=None, variant=None, cardiac=None, resp=None,
                  difference: bool = False, window: str = "mediastinum", slice_mm=None) -> ViewState:
    """The start state from command-line choices (defaults: best method, middle targets, centre)."""
    if window not in WINDOWS:
        raise ClreconError(f"--window {window!r}: must be one of {', '.join(WINDOWS)}")
    src = data.resolve(method, pitch, variant)
    si = [s.dataset for s in data.sources].index(src.dataset)
    if difference and src.dataset == "groundtruth":
        raise ClreconError("--difference: pick a reconstruction (--method) to compare with the ground truth")
    if difference and not data.has_groundtruth:
        raise ClreconError("--difference: this run has no ground truth")
    ax = data.axes
    c = parse_fraction(cardiac)
    a = parse_fraction(resp)
    ci = nearest_index(ax["cardiac_phase"], c, "cardiac", periodic=True) if c is not None \
        else len(ax["cardiac_phase"]) // 2
    ri = nearest_index(ax["resp_amplitude"], a, "resp") if a is not None else len(ax["resp_amplitude"]) // 2
    centre = [float(np.median(ax[k])) for k in ("x_mm", "y_mm", "z_mm")]
    if slice_mm is not None:
        centre = [float(v) if v is not None else c0 for v, c0 in zip(slice_mm, centre, strict=True)]
    return ViewState(source=si, cardiac=ci, resp=ri, difference=difference, window=window,
                     x_mm=centre[0], y_mm=centre[1], z_mm=centre[2])


def _prepare_offscreen() -> None:
    """No X display: ask VTK for its EGL offscreen window (falls back to OSMesa by itself)."""
    if not os.environ.get("DISPLAY") and not os.environ.get("WAYLAND_DISPLAY"):
        os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")


def _pyvista():
    try:
        import pyvista as pv
    except ImportError:
        raise ClreconError("the viewer needs pyvista: pip install 'clrecon[viewer]'") from None
    return pv


# camera per 2D view: (direction of projection, view-up); LPS world, radiological display
_CAMERAS = {
    "axial": ((0.0, 0.0, 1.0), (0.0, -1.0, 0.0)),      # from the feet: R left, A up
    "coronal": ((0.0, 1.0, 0.0), (0.0, 0.0, 1.0)),     # from the front: R left, S up
    "sagittal": ((-1.0, 0.0, 0.0), (0.0, 0.0, 1.0)),   # from the left: A left, S up
}
_LABELS = {"axial": ("R", "L", "A", "P"), "coronal": ("R", "L", "S", "I"), "sagittal": ("A", "P", "S", "I")}
_NORMAL = {"axial": "z", "coronal": "y", "sagittal": "x"}
_SLOT = {"axial": (0, 0), "coronal": (0, 1), "sagittal": (1, 0), "volume": (1, 1)}


class Viewer:
    """Four-viewport pyvista viewer of one run; ``off_screen`` for screenshots."""

    def __init__(self, data: RunData, state: ViewState, off_screen: bool = False, window_size=(1300, 1000)):
        if off_screen:
            _prepare_offscreen()
        pv = _pyvista()
        self.pv = pv
        self.data = data
        self.state = state
        self.off_screen = off_screen
        try:
            self.p = pv.Plotter(shape=(2, 2), off_screen=off_screen, window_size=list(window_size),
                                border=True)
        except Exception as e:  # noqa: BLE001 - no usable OpenGL context: VTK/pyvista raise various types
            raise ClreconError(f"cannot open a render window ({e}); offscreen rendering needs the VTK wheel's "
                               f"EGL or OSMesa support") from None
        self.p.set_background("black")
        self.grid = self._make_grid()
        self._slice_actors: dict = {}
        self._picker = None
        self._cursor_text = None
        self._widgets: dict = {}
        self._cameras_set = False
        self.refresh()

    # -- data -> pyvista -------------------------------------------------------------------
    def _make_grid(self):
        nz, ny, nx = (self.data.axes[k].size for k in ("z_mm", "y_mm", "x_mm"))
        g = self.pv.ImageData(dimensions=(nx, ny, nz), spacing=self.data.spacing(), origin=self.data.origin())
        g.point_data["HU"] = np.zeros(nx * ny * nz, np.float32)
        return g

    def current_volume(self) -> np.ndarray:
        s = self.state
        return self.data.volume(self.data.sources[s.source], s.cardiac, s.resp, s.difference)

    def title(self) -> str:
        s = self.state
        src = self.data.sources[s.source]
        c = self.data.axes["cardiac_phase"][s.cardiac]
        a = self.data.axes["resp_amplitude"][s.resp]
        what = f"{src.label} - groundtruth" if s.difference else src.label
        w, lv = DIFFERENCE_WINDOW if s.difference else WINDOWS[s.window]
        wname = "difference" if s.difference else s.window
        return f"{what}   {target_tag(c, a)}   window {wname} W{w:.0f}/L{lv:.0f} HU"

    def refresh(self) -> None:
        """Re-draw every viewport for the current state."""
        s = self.state
        vol = self.current_volume()
        self.grid.point_data["HU"] = np.ascontiguousarray(vol, np.float32).ravel()  # x fastest = [z,y,x]
        clim = s.clim()
        cmap = "coolwarm" if s.difference else "gray"
        pos = {"x": s.x_mm, "y": s.y_mm, "z": s.z_mm}
        for view in ("axial", "coronal", "sagittal"):
            self.p.subplot(*_SLOT[view])
            n = _NORMAL[view]
            origin = [s.x_mm, s.y_mm, s.z_mm]
            sl = self.grid.slice(normal=n, origin=origin)
            if sl.n_points == 0:  # flat axis: the grid itself is the slice
                sl = self.grid
            self._slice_actors[view] = self.p.add_mesh(sl, scalars="HU", cmap=cmap, clim=clim, name=f"{view}-slice",
                                                       show_scalar_bar=False, lighting=False, pickable=True)
            self.p.add_text(f"{view} {n} = {pos[n]:.1f} mm", position="upper_left", font_size=9, color="white",
                            name=f"{view}-title")
            left, right, up, down = _LABELS[view]
            for text, where in ((left, "left_edge"), (right, "right_edge"), (up, "upper_edge"), (down, "lower_edge")):
                self.p.add_text(text, position=where, font_size=9, color="yellow", name=f"{view}-{where}")
            if not self._cameras_set:
                self._set_camera(view, sl)
        self.p.subplot(*_SLOT["volume"])
        self.p.add_scalar_bar(title="slices, HU", n_labels=3, fmt="%.0f", vertical=True, position_x=0.86,
                              position_y=0.45, height=0.45, width=0.07, color="white", label_font_size=10,
                              title_font_size=10, mapper=self._slice_actors["axial"].mapper)
        self._add_volume(vol, clim, cmap)
        self.p.add_text(self.title(), position="upper_left", font_size=8, color="white", name="state-title")
        self._cameras_set = True
        self.p.render()

    def _set_camera(self, view: str, mesh) -> None:
        d, up = _CAMERAS[view]
        c = np.asarray(self.grid.center)
        cam = self.p.camera
        cam.focal_point = tuple(c)
        cam.position = tuple(c - 2000.0 * np.asarray(d))
        cam.up = up
        self.p.enable_parallel_projection()
        self.p.reset_camera()

    def _add_volume(self, vol: np.ndarray, clim, cmap) -> None:
        stride = [max(1, int(np.ceil(n / VOLUME_RENDER_MAX))) for n in vol.shape]
        sub = vol[::stride[0], ::stride[1], ::stride[2]]
        sp = self.data.spacing()
        g = self.pv.ImageData(dimensions=(sub.shape[2], sub.shape[1], sub.shape[0]),
                              spacing=(sp[0] * stride[2], sp[1] * stride[1], sp[2] * stride[0]),
                              origin=self.data.origin())
        g.point_data["HU"] = np.ascontiguousarray(sub, np.float32).ravel()
        if self.state.difference:
            opacity = [0.6, 0.3, 0.0, 0.3, 0.6]  # |difference| opaque, agreement transparent
        else:
            opacity = [0.0, 0.0, 0.05, 0.25, 0.6]  # low HU (air, lung) transparent
        self.p.add_volume(g, scalars="HU", cmap=cmap, clim=clim, opacity=opacity, name="volume",
                          show_scalar_bar=False, shade=False)
        if not self._cameras_set:  # from the front (anterior), turned 30 degrees towards the patient's right
            c = np.asarray(self.grid.center)
            cam = self.p.camera
            cam.focal_point = tuple(c)
            cam.position = tuple(c + 2000.0 * np.array([-np.sin(np.pi / 6), -np.cos(np.pi / 6), 0.3]))
            cam.up = (0.0, 0.0, 1.0)
            self.p.reset_camera()

    # -- offscreen ----------------------------------------------------------------------------
    def screenshot(self, path) -> Path:
        """Render offscreen and write a PNG; returns the path."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        with atomic.replacing(path, keep_suffix=True) as tmp:  # whole or not at all
            self.p.screenshot(str(tmp))
        return path

    def close(self) -> None:
        self.p.close()

    # -- interactive --------------------------------------------------------------------------
    def set_state(self, **changes) -> None:
        new = replace(self.state, **changes)
        if new != self.state:
            self.state = new
            self.refresh()

    def _add_widgets(self) -> None:
        ax = self.data.axes
        nc, nr, ns = len(ax["cardiac_phase"]), len(ax["resp_amplitude"]), len(self.data.sources)
        style = dict(style="modern", title_height=0.02, fmt="%.0f")

        def int_slider(name, n, value, title, a, b, setter):
            if n < 2:
                return

            def cb(v, w=None):
                i = int(round(v))
                if name in self._widgets:  # pyvista calls back once while creating the widget
                    self._widgets[name].GetRepresentation().SetValue(i)
                setter(i)

            self._widgets[name] = self.p.add_slider_widget(cb, [0, n - 1], value=value, title=title, pointa=a,
                                                           pointb=b, **style)

        self.p.subplot(*_SLOT["volume"])
        int_slider("cardiac", nc, self.state.cardiac, "cardiac phase (target index)", (0.05, 0.1), (0.45, 0.1),
                   lambda i: self.set_state(cardiac=i))
        int_slider("resp", nr, self.state.resp, "respiratory amplitude (target index)", (0.55, 0.1), (0.95, 0.1),
                   lambda i: self.set_state(resp=i))
        int_slider("source", ns, self.state.source, "source (named in the title)", (0.55, 0.27), (0.95, 0.27),
                   lambda i: self.set_state(source=i, difference=self.state.difference
                                            and self.data.sources[i].dataset != "groundtruth"))
        # buttons, top left of the volume viewport (display pixels within the viewport)
        vp_h = int(self.p.window_size[1]) // 2
        size, step = 22, 32
        top = vp_h - 50

        def preset(on, name):
            for other, w in self._buttons.items():
                w.GetRepresentation().SetState(int(other == name))
            self.set_state(window=name)

        self._buttons = {}
        for k, name in enumerate(WINDOWS):
            y = top - step * k
            self._buttons[name] = self.p.add_checkbox_button_widget(
                lambda on, name=name: preset(on, name), value=name == self.state.window, position=(10, y),
                size=size, color_on="white", color_off="grey")
            self.p.add_text(f"{name} W{WINDOWS[name][0]:.0f}/L{WINDOWS[name][1]:.0f}", position=(40, y + 3),
                            font_size=7, color="white", name=f"button-{name}")
        if self.data.has_groundtruth:
            y = top - step * len(WINDOWS)
            self.p.add_checkbox_button_widget(self._toggle_difference, value=self.state.difference,
                                              position=(10, y), size=size, color_on="red", color_off="grey")
            self.p.add_text("difference (source - GT)", position=(40, y + 3), font_size=7, color="white",
                            name="button-diff")
        for view, key, axis in (("axial", "z_mm", "z_mm"), ("coronal", "y_mm", "y_mm"), ("sagittal", "x_mm", "x_mm")):
            v = ax[axis]
            if v.size < 2:
                continue
            self.p.subplot(*_SLOT[view])
            self._widgets[view] = self.p.add_slider_widget(
                lambda val, key=key: self.set_state(**{key: float(val)}), [float(v[0]), float(v[-1])],
                value=getattr(self.state, key), title=f"{axis[0]} (mm)", pointa=(0.58, 0.07), pointb=(0.95, 0.07),
                style="modern", title_height=0.02, fmt="%.1f")
        self.p.subplot(0, 0)
        self._cursor_text = self.p.add_text("", position="lower_left", font_size=9, color="cyan", name="cursor")
        self.p.iren.add_observer("MouseMoveEvent", self._on_mouse_move)

    def _toggle_difference(self, on: bool) -> None:
        if on and self.data.sources[self.state.source].dataset == "groundtruth":
            return
        self.set_state(difference=bool(on))

    def cursor_text(self, xyz_mm) -> str:
        """``x, y, z mm  value HU`` for a world point (the text shown under the cursor)."""
        hit = self.data.probe(self.current_volume(), xyz_mm)
        if hit is None:
            return f"x {xyz_mm[0]:.1f}  y {xyz_mm[1]:.1f}  z {xyz_mm[2]:.1f} mm (outside the volume)"
        return f"x {xyz_mm[0]:.1f}  y {xyz_mm[1]:.1f}  z {xyz_mm[2]:.1f} mm   {hit[3]:.0f} HU"

    def _on_mouse_move(self, obj, event) -> None:
        import vtk

        iren = self.p.iren.interactor
        x, y = iren.GetEventPosition()
        ren = iren.FindPokedRenderer(x, y)
        if self._picker is None:
            self._picker = vtk.vtkCellPicker()
            self._picker.SetTolerance(0.0005)
        if ren is None or not self._picker.Pick(x, y, 0, ren):
            return
        pos = self._picker.GetPickPosition()
        if self._cursor_text is not None:
            self._cursor_text.SetText(0, self.cursor_text(pos))  # lower_left corner
            self.p.render()

    def show(self) -> None:
        self._add_widgets()
        self.p.show(title=f"clrecon view {self.data.run_dir}")


def screenshot(run_dir, path, method=None, pitch=None, variant=None, cardiac=None, resp=None,
               difference: bool = False, window: str = "mediastinum", size=(1300, 1000)) -> tuple[Path, str]:
    """Render one state of a run offscreen to a PNG; returns (path, title of what is shown)."""
    data = RunData(run_dir)
    try:
        state = initial_state(data, method, pitch, variant, cardiac, resp, difference, window)
        v = Viewer(data, state, off_screen=True, window_size=size)
        try:
            out = v.screenshot(path)
            return out, v.title()
        finally:
            v.close()
    finally:
        data.close()


def view(run_dir, **choices) -> None:
    """Open the interactive viewer (needs a display)."""
    if not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
        raise ClreconError("no display to open a window on; use --screenshot FILE to render offscreen")
    data = RunData(run_dir)
    try:
        state = initial_state(data, **choices)
        print(f"clrecon view: {data.describe()}")
        Viewer(data, state).show()
    finally:
        data.close()
