"""The pyvista viewer: offscreen screenshots of a fake run, state/selection logic, one-line errors.

Everything that renders runs in one spawned child process: an OpenGL context on Mesa's
llvmpipe loads Mesa's LLVM, after which PoCL (another LLVM) aborts when it initialises in the
same process ("option registered more than once"). The pytest process itself must stay able
to run the OpenCL tests. Assertions fail inside the child and are re-raised here.
"""

from __future__ import annotations

import multiprocessing
from concurrent.futures import ProcessPoolExecutor

import h5py
import numpy as np
import pytest
from fake_run_dir import make_fake_run

from clrecon.cli import main
from clrecon.core.errors import ClreconError

pytest.importorskip("pyvista")
from clrecon.viewer.app import (
    WINDOWS,
    RunData,
    Viewer,
    initial_state,
    nearest_index,
    parse_fraction,
    screenshot,
    window_clim,
)


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    d = tmp_path_factory.mktemp("run")
    make_fake_run(d, methods=("nearest", "local_linear"), pitches=(0.1,))
    return d


@pytest.fixture(scope="module")
def render():
    """``render(fn, *args)``: run a module-level check in the rendering child process."""
    with ProcessPoolExecutor(max_workers=1, mp_context=multiprocessing.get_context("spawn")) as pool:
        yield lambda fn, *args: pool.submit(fn, *args).result(timeout=300)


def _png(path):
    import matplotlib.image as mpimg

    img = mpimg.imread(path)
    return img[..., :3].mean(axis=-1)  # grey, [0, 1]


def test_screenshot_shows_the_anatomy(run_dir, tmp_path, render):
    render(_screenshot_shows_the_anatomy, run_dir, tmp_path)


def _screenshot_shows_the_anatomy(run_dir, tmp_path):
    out = tmp_path / "shot.png"
    assert main(["view", str(run_dir), "--screenshot", str(out), "--size", "640x480", "--cardiac", "40%",
                 "--resp", "0.5", "--window", "mediastinum"]) == 0
    img = _png(out)
    assert img.shape == (480, 640)
    axial = img[20:220, 20:300]  # upper-left viewport: axial slice
    # body soft tissue (grey), lungs/air (black) and spine/contrast (white) are all there
    assert axial.std() > 0.15
    assert (axial < 0.05).mean() > 0.2 and (axial > 0.9).mean() > 0.005
    assert ((axial > 0.3) & (axial < 0.7)).mean() > 0.05
    volume = img[250:470, 330:630]  # lower-right viewport: volume rendering is not empty
    assert volume.std() > 0.02


def test_screenshot_lung_window_and_difference_differ(run_dir, tmp_path, render):
    render(_screenshot_lung_window_and_difference_differ, run_dir, tmp_path)


def _screenshot_lung_window_and_difference_differ(run_dir, tmp_path):
    a, _ = screenshot(run_dir, tmp_path / "lung.png", window="lung", size=(400, 300))
    b, title = screenshot(run_dir, tmp_path / "diff.png", method="nearest", difference=True, size=(400, 300))
    assert "nearest p0.100 noisy - groundtruth" in title and "W400/L0" in title
    ia, ib = _png(a), _png(b)
    assert ia.shape == ib.shape == (300, 400)
    assert np.abs(ia - ib).mean() > 0.02


def test_viewer_state_changes_update_the_grid(run_dir, render):
    render(_viewer_state_changes_update_the_grid, run_dir)


def _viewer_state_changes_update_the_grid(run_dir):
    data = RunData(run_dir)
    try:
        st = initial_state(data, method="local_linear", cardiac=0.0, resp=0.9)
        assert (st.cardiac, st.resp) == (0, 2)
        v = Viewer(data, st, off_screen=True, window_size=(300, 200))
        try:
            labels = [s.label for s in data.sources]
            gt = labels.index("groundtruth")
            v.set_state(source=gt, cardiac=1, resp=0)
            expect = data.volume(data.sources[gt], 1, 0)
            np.testing.assert_array_equal(np.asarray(v.grid.point_data["HU"]), expect.ravel())
            v.set_state(source=labels.index("nearest p0.100 noisy"), difference=True)
            assert abs(np.asarray(v.grid.point_data["HU"]).mean()) < 50  # a difference image, not HU
            # the cursor read-out: nearest voxel value at a world point (mm)
            ax = data.axes
            p = (ax["x_mm"][5], ax["y_mm"][7], ax["z_mm"][3])
            vol = v.current_volume()
            assert v.cursor_text(p).endswith(f"{vol[3, 7, 5]:.0f} HU")
            assert "outside" in v.cursor_text((1e4, 0, 0))
        finally:
            v.close()
    finally:
        data.close()


def test_interactive_controls_build_offscreen_and_cursor_reads_mm(run_dir, tmp_path, render):
    render(_interactive_controls_build_offscreen_and_cursor_reads_mm, run_dir, tmp_path)


def _interactive_controls_build_offscreen_and_cursor_reads_mm(run_dir, tmp_path):
    data = RunData(run_dir)
    try:
        v = Viewer(data, initial_state(data), off_screen=True, window_size=(800, 600))
        try:
            v._add_widgets()  # sliders, preset/difference buttons, mouse observer
            assert {"cardiac", "resp", "source", "axial", "coronal", "sagittal"} <= set(v._widgets)
            v.screenshot(tmp_path / "controls.png")
            ax = data.axes
            x, y, z = ax["x_mm"][30], ax["y_mm"][8], v.state.z_mm
            v.p.subplot(0, 0)  # axial viewport: display position of a world point, then a mouse move there
            ren = v.p.renderer
            ren.SetWorldPoint(x, y, z, 1.0)
            ren.WorldToDisplay()
            dx, dy, _ = ren.GetDisplayPoint()
            v.p.iren.interactor.SetEventPosition(int(round(dx)), int(round(dy)))
            v._on_mouse_move(None, None)
            text = v._cursor_text.GetText(0)
            got = [float(t) for t in text.split("mm")[0].replace("x", "").replace("y", "").replace("z", "").split()]
            np.testing.assert_allclose(got, [x, y, z], atol=4.0)  # within half a voxel (8 mm)
            assert text.endswith("HU")

            def display(slot, p):
                v.p.subplot(*slot)
                v.p.renderer.SetWorldPoint(*p, 1.0)
                v.p.renderer.WorldToDisplay()
                return np.array(v.p.renderer.GetDisplayPoint()[:2])

            # radiological display: patient left (+x) on screen right, anterior (-y) up in axial,
            # superior (+z) up in coronal and sagittal, anterior on the left in sagittal
            assert display((0, 0), (50, 0, 0))[0] > display((0, 0), (-50, 0, 0))[0]
            assert display((0, 0), (0, -50, 0))[1] > display((0, 0), (0, 50, 0))[1]
            assert display((0, 1), (0, 0, 20))[1] > display((0, 1), (0, 0, -20))[1]
            assert display((0, 1), (50, 0, 0))[0] > display((0, 1), (-50, 0, 0))[0]
            assert display((1, 0), (0, 50, 0))[0] > display((1, 0), (0, -50, 0))[0]
            assert display((1, 0), (0, 0, 20))[1] > display((1, 0), (0, 0, -20))[1]
        finally:
            v.close()
    finally:
        data.close()


def test_selection_helpers():
    assert parse_fraction("40%") == pytest.approx(0.4) and parse_fraction("0.55") == 0.55
    assert nearest_index([0.0, 0.4, 0.8], 0.95, "cardiac", periodic=True) == 0
    with pytest.raises(ClreconError, match="targets are 0.05, 0.15"):
        nearest_index([0.05, 0.15], 0.5, "resp")
    assert window_clim(*WINDOWS["lung"]) == (-1350.0, 150.0)


def test_one_line_errors(run_dir, tmp_path, capsys):
    png = str(tmp_path / "x.png")
    assert main(["view", str(tmp_path / "missing"), "--screenshot", png]) == 2
    err = capsys.readouterr().err.strip()
    assert "no such run directory" in err and "\n" not in err
    assert main(["view", str(run_dir), "--screenshot", png, "--method", "barycentric"]) == 2
    err = capsys.readouterr().err.strip()
    assert "it has groundtruth, phantom; p0.100/noise-free: local_linear, nearest; p0.100/noisy" in err
    assert "\n" not in err
    old = tmp_path / "old"
    old.mkdir()
    with h5py.File(old / "volumes.h5", "w") as f:
        f.attrs["format_version"] = 0
    assert main(["view", str(old), "--screenshot", png]) == 2
    assert "volume format 0" in capsys.readouterr().err
    assert main(["view", str(run_dir), "--screenshot", png, "--window", "bone"]) == 2
    assert "lung, mediastinum, cardiac" in capsys.readouterr().err


def test_this_process_never_loaded_a_gl_driver():
    """Rendering stays in the child: no Mesa driver here, so PoCL can still start in this process."""
    maps = "/proc/self/maps"
    try:
        text = open(maps).read()
    except OSError:
        pytest.skip("no /proc/self/maps")
    assert "libEGL_mesa" not in text and "libGLX_mesa" not in text and "libOSMesa" not in text
