"""Voxel phantoms (``[phantom] kind = "voxel"``): XCAT logs and NIfTI tables, errors, frame
blending, the export round trip, and the voxel path against the exact analytic path on ``tiny``.

Tolerances and bounds live in ``TOL`` below, each with its reason; nothing else in this file
is a tolerance.
"""

import math
import re

import numpy as np
import pytest

from clrecon.bench.suite import format_report, run_bench
from clrecon.cli import main
from clrecon.config.scene import load_scene, scene_from_dict
from clrecon.core.conventions import MU_WATER_PER_MM, detector_coords, detector_frames, mu_to_hu, voxel_coords
from clrecon.core.errors import SceneError
from clrecon.outputs.volumes import open_volumes, read_volume
from clrecon.pipeline.run import run
from clrecon.scan import signals
from clrecon.scan.table import projection_table
from clrecon.simulation import projector
from clrecon.simulation.phantom_export import export_phantom
from clrecon.simulation.phantom_sources import phantom_from_config
from clrecon.simulation.phantoms import frames as fr
from clrecon.simulation.phantoms.analytic import Phantom
from clrecon.simulation.phantoms.voxel import VoxelPhantomConfig, frame_weights, is_grid, resample_matrix
from clrecon.simulation.voxel_projector import project_volume
from clrecon.simulation.voxelise import voxelise_objects

nib = pytest.importorskip("nibabel")

EPS32 = float(np.finfo(np.float32).eps)

#: The one tolerance table: name -> (value, reason).
TOL = {
    # weights are float64 sums of products of numbers in [0, 1]
    "weights": (1e-12, "float64 rounding"),
    # a blend projected = the blend of the frames' projections; float32 sums of <= 4 terms of
    # line integrals <= 6: a few eps32 of the largest line integral
    "linear_rel": (1e-5, "float32 rounding of a sum of weighted projections"),
    # XCAT frames store mu * pixel width in float32 and divide again on reading; NIfTI frames
    # store HU in float32 and convert back: relative rounding ~ eps32 of mu, and of mu_w for HU
    "roundtrip_rel": (1e-5, "float32 storage of mu (XCAT) or HU (NIfTI)"),
    # first-order convergence: the voxel path's error is the L1 difference between sharp edges
    # and edges blurred by a kernel of width ~h (voxelisation box + Joseph's linear
    # interpolation), which halves with h; measured ratio 0.43 (h 4 -> 2 mm) on tiny
    "convergence": (0.6, "error ~ h (first order): halving h must take off at least 40 %"),
    # the voxel projections must not be shifted: the least-squares shift of the difference
    # along the analytic projection's column and row gradients, in mm at the isocentre, as a
    # fraction of h. A conventions error (voxel-centre vs corner origin, a flipped axis) shifts
    # by h/2 or more; measured <= 0.002 h (columns) and <= 0.04 h (rows, whose gradient is small:
    # the body is nearly uniform along z, so the row fit is the noisier) at h = 2 and 4 mm
    "shift_h": (0.1, "a half-voxel conventions error would give 0.5"),
    # the FBP's point response has negative side lobes, so the L1 difference of two
    # reconstructions can exceed the L1 difference of the phantoms by the ratio of the
    # response's L1 norm to its integral; allowance on the first-order estimate (measured
    # ratio measured / estimate: 0.87-1.10 for h = 1-8 mm on tiny, see docs/voxel-phantoms.md)
    "fbp_l1": (1.25, "allowance for the ramp filter's negative lobes on the L1 estimate"),
}


# ---------------------------------------------------------------------------------------
# helpers
LOG = """XCAT phantom program, version 2 (a free-form header line)
 Phantom array_size and slices:
  pixel width =  {pw_cm:.4f} (cm/pixel)
  slice width =  {sw_cm:.4f} (cm/pixel)
  voxel volume = pixel width x pixel width x slice width = 0.001 (cm^3)
  array_size = {n}
  starting slice number    = 7
  ending slice number      = {end}
  Total Output Frames = {frames}
  Time Per Frame = {dt} s ; total time = {tt} s
  hrt_period = {hrt} (s) ;  hrt_start_ph_index = 0.25
  resp_period = {resp} (s); resp_start_ph_index = 0.0

Linear Attenuation Coefficients (1/cm):
 Body (water) = {w_cm:.6f}
 Muscle = 0.2020
 Lung = 0.0500

Linear Attenuation Coefficients (1/pixel):
 Body (water) = {w_px:.8f}
 Muscle = {m_px:.8f}
 Lung = 0.0001

CREATING FRAME #1 ... (more free-form lines)
 pixel width = 99 (a later line does not count)
"""


def write_xcat(folder, vols_mu, pixel_mm=2.0, slice_mm=3.0, dt=0.1, hrt=1.0, resp=4.0, name="pat",
               n_frames=None, dtype="<f4", drop=()):
    """XCAT-format frames (mu in 1/mm, (nz, n, n) each) and their log; returns the log path."""
    folder.mkdir(parents=True, exist_ok=True)
    nz, n, _ = vols_mu[0].shape
    mw = MU_WATER_PER_MM
    text = LOG.format(pw_cm=pixel_mm / 10, sw_cm=slice_mm / 10, n=n, end=7 + nz - 1,
                      frames=len(vols_mu) if n_frames is None else n_frames, dt=dt, tt=dt * len(vols_mu), hrt=hrt,
                      resp=resp, w_cm=mw * 10, w_px=mw * pixel_mm, m_px=0.0202 * pixel_mm)
    log = folder / f"{name}_log"
    log.write_text(text)
    for k, v in enumerate(vols_mu, 1):
        if k not in drop:
            (np.asarray(v, np.float64) * pixel_mm).astype(dtype).tofile(folder / f"{name}_atn_{k}.bin")
    fr.clear_frame_cache()
    return log


def write_nifti(path, vol_zyx, affine):
    """A NIfTI file of a volume given as [z, y, x] LPS-increasing (stored as nibabel [i, j, k])."""
    nib.save(nib.Nifti1Image(np.asarray(vol_zyx, np.float32).transpose(2, 1, 0), affine), str(path))


def lps_affine(h, origin):
    """RAS+ affine of an axis-aligned LPS grid of spacing h (x, y, z) with voxel-0 centre origin."""
    a = np.eye(4)
    a[:3, :3] = np.diag(h)
    a[:3, 3] = origin
    return np.diag([-1.0, -1.0, 1.0, 1.0]) @ a


def voxel_cfg(frames, **kw):
    return VoxelPhantomConfig(frames=str(frames), **kw)


def static(scene):
    return scene.replace(noise={"enabled": False}, phantom={"cardiac_motion": False}, signals={"breath_hold": True})


def kernel_mad(h, n=400_000, seed=0):
    """E|X| (mm) of the blur the voxel path puts on an edge, (in-plane, along z), by Monte Carlo.

    The frames are box averages of width h (voxelisation) and Joseph's method interpolates
    linearly (a triangle of half-width h) across the ray in the non-dominant in-plane axis and
    in z. In-plane: X = n . (box_x + [interp], box_y + [interp]) for the normal n of an edge
    seen tangentially by a ray of uniform direction; along z: box + triangle.
    """
    rng = np.random.default_rng(seed)
    u = lambda: rng.uniform(-0.5, 0.5, n)  # noqa: E731
    tri = lambda: u() + u()  # noqa: E731
    phi = rng.uniform(0.0, np.pi, n)
    nx, ny = -np.sin(phi), np.cos(phi)
    dom_x = np.abs(np.cos(phi)) >= np.abs(np.sin(phi))
    xn = np.where(dom_x, nx * u() + ny * (u() + tri()), nx * (u() + tri()) + ny * u())
    return h * float(np.abs(xn).mean()), h * float(np.abs(u() + tri()).mean())


def phantom_variation(scene, states, z_mm, g=1.0):
    """Mean |grad_xy HU| and mean |d HU / dz| (HU/mm) of the analytic phantom over the scanner's
    FOV circle on the slices ``z_mm``, worst over ``states`` (finite differences, g mm grid)."""
    p = Phantom(scene.phantom)
    n = int(2 * scene.scanner.fov_radius_mm / g) + 2
    x = (np.arange(n) - (n - 1) / 2.0) * g
    circ = (x[None, :] ** 2 + x[:, None] ** 2) <= scene.scanner.fov_radius_mm ** 2
    tv2 = tvz = 0.0
    for c, a in states:
        for z in z_mm:
            hu = mu_to_hu(p.voxelise(c, a, x, x, np.array([z - g, z, z + g]), supersample=2),
                          scene.phantom.mu_water_per_mm)
            gy, gx = np.gradient(hu[1], g)
            tv2 = max(tv2, float(np.hypot(gx, gy)[circ].mean()))
            tvz = max(tvz, float((np.abs(hu[2] - hu[0]) / (2 * g))[circ].mean()))
    return tv2, tvz


def spatial_estimate(scene, h, states, z_mm):
    """First-order estimate (HU) of the voxel path's mean absolute error on the reconstruction:
    E|X_n| mean|grad_xy HU| + E|X_z| mean|dHU/dz| (docs/voxel-phantoms.md "Agreement")."""
    mn, mz = kernel_mad(h)
    tv2, tvz = phantom_variation(scene, states, z_mm)
    return mn * tv2 + mz * tvz


# ---------------------------------------------------------------------------------------
# XCAT log
def test_xcat_log_fields_are_read_from_free_form_lines(tmp_path):
    log = write_xcat(tmp_path, [np.zeros((4, 6, 6))] * 3, pixel_mm=2.0, slice_mm=3.0, dt=0.05, hrt=0.8, resp=4.5)
    xl = fr.parse_xcat_log(log)
    assert (xl.pixel_width_mm, xl.slice_width_mm) == pytest.approx((2.0, 3.0))
    assert (xl.array_size, xl.start_slice, xl.end_slice, xl.n_slices) == (6, 7, 10, 4)
    assert (xl.n_frames, xl.time_per_frame_s, xl.hrt_period_s, xl.resp_period_s) == (3, 0.05, 0.8, 4.5)
    assert (xl.hrt_start_phase, xl.resp_start_phase) == (0.25, 0.0)
    assert xl.mu_water_per_mm == pytest.approx(MU_WATER_PER_MM, rel=1e-6)
    assert xl.atten_per_pixel["Muscle"] == pytest.approx(0.0404) and "Lung" in xl.atten_per_cm
    assert xl.stem == "pat" and xl.frame_path(2).name == "pat_atn_2.bin"


def test_xcat_log_in_mm_and_minimal(tmp_path):
    p = tmp_path / "a_log"
    p.write_text("pixel width = 1.5 mm\nslice width=2 mm\narray_size=4\nstartslice = 1\nendslice = 2\n"
                 "Linear Attenuation Coefficients (1/pixel):\nBody (water) = 0.03\n")
    xl = fr.parse_xcat_log(p)
    assert (xl.pixel_width_mm, xl.slice_width_mm, xl.n_slices) == (1.5, 2.0, 2)
    assert xl.n_frames is None and xl.time_per_frame_s is None and xl.mu_water_per_mm == pytest.approx(0.02)


@pytest.mark.parametrize("edit, message", [
    (lambda t: t.replace(" Body (water) = 0.03860000", " Bone = 0.1"), "Body (water)"),
    (lambda t: t.replace("  pixel width =  0.2000 (cm/pixel)", ""), "pixel width"),
    (lambda t: t.replace("  array_size = 6", ""), "array_size"),
    (lambda t: t.replace("ending slice number      = 10", "ending slice number = 3"), "ending slice"),
    (lambda t: t.replace("pixel width =  0.2000 (cm/pixel)", "pixel width = 0.2 mm"), "check the pixel width"),
    (lambda t: t.replace("Body (water) = 0.193000", "Body (water) = 0.0193"), "check the pixel width"),
])
def test_bad_xcat_logs_are_one_line_errors_naming_the_file(tmp_path, edit, message):
    log = write_xcat(tmp_path, [np.zeros((4, 6, 6))])
    log.write_text(edit(log.read_text()))
    with pytest.raises(SceneError, match=re.escape(message)) as e:
        fr.parse_xcat_log(log)
    assert str(log) in str(e.value) and "\n" not in str(e.value)


def test_xcat_frame_files_missing_or_of_the_wrong_size(tmp_path):
    log = write_xcat(tmp_path / "a", [np.zeros((4, 6, 6))] * 3, drop=(2,))
    with pytest.raises(SceneError, match="frame 2 of 3 .pat_atn_2.bin. is missing"):
        voxel_cfg(log)
    log = write_xcat(tmp_path / "b", [np.zeros((4, 6, 6))] * 2)
    (tmp_path / "b" / "pat_atn_2.bin").write_bytes(b"\0" * (4 * 6 * 6 * 4 - 4))
    with pytest.raises(SceneError, match="pat_atn_2.bin: 572 bytes, but the log's 4 slices x 6 x 6"):
        voxel_cfg(log)


def test_xcat_nan_voxel_and_byte_order_are_errors_naming_the_file(tmp_path):
    v = np.full((4, 6, 6), MU_WATER_PER_MM)
    bad = v.copy()
    bad[2, 3, 1] = np.nan
    log = write_xcat(tmp_path / "nan", [v, bad])
    ph = phantom_from_config(voxel_cfg(log, timing="scene")).with_states([0, 0.5], [0, 0])
    ph.frame(0)
    with pytest.raises(SceneError, match=r"pat_atn_2.bin: non-finite voxel nan at \[z, y, x\] = \[2, 3, 1\]"):
        ph.frame(1)
    log = write_xcat(tmp_path / "big", [v], dtype=">f4")
    ph = phantom_from_config(voxel_cfg(log, timing="scene")).with_states([0], [0])
    with pytest.raises(SceneError, match="byte_order = 'big'"):
        ph.frame(0)
    ph = phantom_from_config(voxel_cfg(log, timing="scene", byte_order="big")).with_states([0], [0])
    np.testing.assert_allclose(ph.frame(0), v, rtol=TOL["roundtrip_rel"][0])


def test_xcat_orientation_and_position(tmp_path):
    v = np.zeros((4, 6, 6))
    v[0, 1, 4] = 0.02                       # first slice, row 1, column 4
    log = write_xcat(tmp_path, [v], pixel_mm=2.0, slice_mm=3.0)
    for direction, z_index in (("superior", 0), ("inferior", 3)):
        cfg = voxel_cfg(log, timing="scene", slice_direction=direction, centre_mm=(10.0, -4.0, 100.0))
        ph = phantom_from_config(cfg).with_states([0], [0])
        g = ph.geometry
        assert g.shape == (4, 6, 6) and g.spacing_mm == (2.0, 2.0, 3.0)
        assert g.origin_mm == pytest.approx((10 - 5.0, -4 - 5.0, 100 - 4.5))
        mu = ph.frame(0)
        assert np.argwhere(mu).tolist() == [[z_index, 1, 4]]  # rows -> +y (posterior), columns -> +x (left)


def test_xcat_timing_from_the_log_periods(tmp_path):
    log = write_xcat(tmp_path, [np.zeros((2, 4, 4))] * 5, dt=0.1, hrt=0.8, resp=4.0)
    ph = phantom_from_config(voxel_cfg(log))
    assert ph.timing == "xcat" and not ph.needs_scene_states
    c, a = ph.frame_states
    t = 0.1 * np.arange(5)
    np.testing.assert_allclose(c, np.mod(0.25 + t / 0.8, 1.0), atol=1e-12)
    np.testing.assert_allclose(a, 0.5 * (1 - np.cos(2 * np.pi * t / 4.0)), atol=1e-12)
    text = log.read_text().replace("hrt_period = 0.8 (s) ;", "")
    log.write_text(text)
    fr.clear_frame_cache()
    assert phantom_from_config(voxel_cfg(log)).timing == "scene"          # auto without a period
    with pytest.raises(SceneError, match="no 'hrt_period = ...' line; use timing = 'scene'"):
        voxel_cfg(log, timing="xcat")


# ---------------------------------------------------------------------------------------
# NIfTI tables
def test_nifti_tables_toml_and_csv(tmp_path):
    (tmp_path / "d").mkdir()
    for k in range(2):
        write_nifti(tmp_path / "d" / f"f{k}.nii", np.zeros((3, 4, 5)), lps_affine((2, 2, 3), (0, 0, 0)))
    (tmp_path / "t.toml").write_text('[[frame]]\nfile = "d/f0.nii"\ncardiac_phase = 0.1\nresp_amplitude = 0.2\n'
                                     '[[frame]]\nfile = "d/f1.nii"\ntime_s = 0.5\ncardiac_phase = 0.3\n'
                                     'resp_amplitude = 0.9\n')
    rows = fr.parse_frame_table(tmp_path / "t.toml")
    assert [r.file for r in rows] == [tmp_path / "d" / "f0.nii", tmp_path / "d" / "f1.nii"]
    assert (rows[0].cardiac_phase, rows[0].resp_amplitude, rows[0].time_s) == (0.1, 0.2, None)
    (tmp_path / "t.csv").write_text("# a comment\nfile, time_s\nd/f0.nii, 0.0\nd/f1.nii, 0.25\n")
    ph = phantom_from_config(voxel_cfg(tmp_path / "t.csv"))
    assert ph.timing == "scene" and ph.frame_times_s.tolist() == [0.0, 0.25]
    ph = phantom_from_config(voxel_cfg(tmp_path / "t.toml", time_offset_s=1.0))
    assert ph.timing == "table" and ph.frame_states[0].tolist() == [0.1, 0.3]


@pytest.mark.parametrize("table, message", [
    ("file,cardiac_phase\nf0.nii,0.1\n", "give both cardiac_phase and resp_amplitude"),
    ("name,time_s\nf0.nii,0\n", "header naming the columns"),
    ("file,cardiac_phase,resp_amplitude\nf0.nii,1.2,0.5\n", "cardiac_phase = 1.2: must be in"),
    ("file,time_s\nf0.nii,soon\n", "time_s = 'soon': must be a number"),
    ("file,resp_amplitude,cardiac_phase\n", "no frames"),
    ("file,time_s\nmissing.nii,0\n", "missing.nii does not exist"),
])
def test_bad_nifti_tables(tmp_path, table, message):
    write_nifti(tmp_path / "f0.nii", np.zeros((3, 4, 5)), lps_affine((2, 2, 3), (0, 0, 0)))
    (tmp_path / "frames.csv").write_text(table)
    with pytest.raises(SceneError, match=message) as e:
        voxel_cfg(tmp_path)                                   # a folder holding frames.csv
    assert "frames.csv" in str(e.value) and "\n" not in str(e.value)


def test_nifti_affine_ras_to_lps_permuted_and_flipped(tmp_path):
    """A volume stored as array [i, j, k] = [y, z, x reversed]: read back as mu[z, y, x] at its place."""
    vol = np.zeros((3, 4, 5))                                 # the truth, [z, y, x] LPS increasing
    vol[2, 1, 3] = 0.02
    h, origin = (2.0, 3.0, 4.0), (-10.0, 5.0, 20.0)           # spacing and voxel-0 centre (x, y, z) LPS
    # store as array [i, j, k] = [y, z, x] with x reversed (index 0 = largest x)
    data = vol.transpose(1, 0, 2)[:, :, ::-1]                 # [y, z, x reversed]
    lps = np.zeros((4, 4))
    lps[3, 3] = 1
    lps[1, 0], lps[2, 1], lps[0, 2] = h[1], h[2], -h[0]       # i -> +y, j -> +z, k -> -x
    lps[:3, 3] = (origin[0] + 4 * h[0], origin[1], origin[2])
    nib.save(nib.Nifti1Image(data.astype(np.float32), np.diag([-1.0, -1.0, 1, 1]) @ lps), str(tmp_path / "f.nii"))
    (tmp_path / "frames.csv").write_text("file,cardiac_phase,resp_amplitude\nf.nii,0,0\n")
    ph = phantom_from_config(voxel_cfg(tmp_path / "frames.csv", values="mu"))
    g = ph.geometry
    assert g.shape == (3, 4, 5) and g.spacing_mm == pytest.approx(h) and g.origin_mm == pytest.approx(origin)
    assert np.argwhere(ph.frame(0)).tolist() == [[2, 1, 3]]


def test_nifti_errors_spacing_oblique_nan_and_hu(tmp_path):
    write_nifti(tmp_path / "a.nii", np.zeros((3, 4, 5)), lps_affine((2, 2, 3), (0, 0, 0)))
    write_nifti(tmp_path / "b.nii", np.zeros((3, 4, 5)), lps_affine((2, 2, 2.5), (0, 0, 0)))
    (tmp_path / "frames.csv").write_text("file,time_s\na.nii,0\nb.nii,1\n")
    with pytest.raises(SceneError, match=r"b.nii: voxel spacing .* differs from the first frame's"):
        voxel_cfg(tmp_path)
    rot = lps_affine((2, 2, 3), (0, 0, 0))
    c, s = math.cos(0.1), math.sin(0.1)
    rot[:2, :2] = rot[:2, :2] @ np.array([[c, -s], [s, c]])
    write_nifti(tmp_path / "b.nii", np.zeros((3, 4, 5)), rot)
    with pytest.raises(SceneError, match="oblique"):
        voxel_cfg(tmp_path)
    v = np.zeros((3, 4, 5))
    v[0, 0, 0], v[1, 2, 3] = -1000.0, np.nan
    write_nifti(tmp_path / "b.nii", v, lps_affine((2, 2, 3), (0, 0, 0)))
    ph = phantom_from_config(voxel_cfg(tmp_path)).with_states([0, 0], [0, 1])
    a = ph.frame(0)
    assert np.all(a == np.float32(MU_WATER_PER_MM))           # HU 0 = water
    with pytest.raises(SceneError, match=r"b.nii: non-finite voxel nan at \[z, y, x\] = \[1, 2, 3\]"):
        ph.frame(1)


# ---------------------------------------------------------------------------------------
# between frames
def test_nearest_is_circular_in_cardiac_phase():
    fc, fa = np.array([0.0, 0.5, 0.8]), np.array([0.5, 0.5, 0.5])
    idx, w = frame_weights(fc, fa, [0.95, 0.6, 0.7], [0.5, 0.5, 0.5], "nearest")
    assert idx[:, 0].tolist() == [0, 1, 2] and np.all(w == 1.0)


def test_grid_blending_is_bilinear_and_circular():
    cs, as_ = np.array([0.0, 0.25, 0.5, 0.75]), np.array([0.0, 0.4, 1.0])
    fc, fa = (v.ravel() for v in np.meshgrid(cs, as_, indexing="ij"))
    assert is_grid(fc, fa) and not is_grid(fc[:-1], fa[:-1])
    rng = np.random.default_rng(3)
    c, a = rng.uniform(0, 1, 200), rng.uniform(-0.2, 1.2, 200)
    idx, w = frame_weights(fc, fa, c, a, "linear")
    tol = TOL["weights"][0]
    assert idx.shape == (200, 4) and np.all(w >= -tol) and np.allclose(w.sum(1), 1, atol=tol)
    # bilinear reproduces functions linear in a (clamped to the amplitude range), and in c
    # measured circularly from each state (the blend of the frames' c around it)
    np.testing.assert_allclose((w * fa[idx]).sum(1), np.clip(a, 0, 1), atol=tol)
    dc = (fc[idx] - c[:, None] + 0.5) % 1.0 - 0.5
    np.testing.assert_allclose((w * dc).sum(1), 0.0, atol=tol)
    # on a node: that frame alone
    idx, w = frame_weights(fc, fa, [0.25], [0.4], "linear")
    assert w[0][idx[0] == 4].sum() == pytest.approx(1.0)


def test_two_nearest_frames_on_a_trajectory():
    fc, fa = np.array([0.95, 0.05, 0.3]), np.array([0.2, 0.4, 0.9])      # a 1-D path through the seam
    idx, w = frame_weights(fc, fa, [0.0, 0.975, 0.9], [0.3, 0.25, 0.1], "linear")
    tol = TOL["weights"][0]
    # halfway between frames 0 and 1 across c = 0; a quarter of the way; before the first: frame 0
    assert sorted(zip(idx[0].tolist(), np.round(w[0], 12).tolist(), strict=True)) == [(0, 0.5), (1, 0.5)]
    assert dict(zip(idx[1].tolist(), w[1].tolist(), strict=True))[1] == pytest.approx(0.25, abs=tol)
    assert dict(zip(idx[2].tolist(), w[2].tolist(), strict=True))[0] == pytest.approx(1.0, abs=tol)


def test_blended_projection_is_the_blend_of_projections(tmp_path):
    rng = np.random.default_rng(1)
    vols = [rng.uniform(0.001, 0.03, (6, 10, 10)) for _ in range(3)]
    log = write_xcat(tmp_path, vols, pixel_mm=4.0, slice_mm=4.0)
    ph = phantom_from_config(voxel_cfg(log, timing="scene")).with_states([0.0, 0.3, 0.6], [0.5, 0.5, 0.5])
    beta = np.linspace(0, 2 * np.pi, 5, endpoint=False)
    src, det, eu, ev = detector_frames(beta, np.zeros(5), 595.0, 1085.6)
    u, v = detector_coords(24, 4.0), detector_coords(4, 4.0)
    c = np.array([0.1, 0.3, 0.45, 0.0, 0.2])
    got = ph.project(c, np.full(5, 0.5), src, det, eu, ev, u, v)
    g = ph.geometry
    for m in range(5):
        want = project_volume(ph.volume(c[m], 0.5), g.origin_mm, g.spacing_mm, src[m:m + 1], det[m:m + 1],
                              eu[m:m + 1], ev[m:m + 1], u, v)[0]
        np.testing.assert_allclose(got[m], want, rtol=0, atol=TOL["linear_rel"][0] * np.abs(want).max())
    assert len(fr._FRAMES) <= fr.FRAME_CACHE_SIZE                       # frames streamed, at most two held


def test_resample_matrix_constant_and_linear():
    m = resample_matrix(np.arange(-20.0, 21.0, 5.0), 5.0, origin=-9.0, spacing=2.0, n_in=10, ss=3)
    x_in = -9.0 + 2.0 * np.arange(10)
    dense = m.toarray()
    inside = np.abs(np.arange(-20.0, 21.0, 5.0)) <= 5.0                  # whole output voxel in [-10, 10]
    np.testing.assert_allclose(dense.sum(1)[inside], 1.0, atol=1e-12)
    assert np.all(dense.sum(1)[np.abs(np.arange(-20.0, 21.0, 5.0)) >= 15.0] == 0.0)   # outside the box: air
    np.testing.assert_allclose((dense @ (3.0 * x_in + 1))[inside], 3.0 * np.arange(-20.0, 21.0, 5.0)[inside] + 1,
                               atol=1e-12)


# ---------------------------------------------------------------------------------------
# scenes
def test_scene_with_a_voxel_phantom_and_a_relative_path(tmp_path):
    log = write_xcat(tmp_path / "xcat", [np.zeros((4, 6, 6))] * 2)
    (tmp_path / "s.toml").write_text('[phantom]\nkind = "voxel"\nframes = "xcat/pat_log"\ntiming = "scene"\n')
    s = load_scene(tmp_path / "s.toml")
    assert s.phantom.kind == "voxel" and s.phantom.frames == str(log)
    assert s.phantom.mu_water_per_mm == pytest.approx(MU_WATER_PER_MM, rel=1e-6)      # from the log's water
    h = s.scan_hash(0.02)
    (log.parent / "pat_atn_2.bin").write_bytes((np.ones(4 * 36) * 0.01).astype("<f4").tobytes())
    fr.clear_frame_cache()
    assert load_scene(tmp_path / "s.toml").scan_hash(0.02) != h                        # content enters the hash
    with pytest.raises(SceneError, match=r"s.toml: phantom.frames = .*nowhere.*: no such file"):
        (tmp_path / "s.toml").write_text('[phantom]\nkind = "voxel"\nframes = "nowhere_log"\n')
        load_scene(tmp_path / "s.toml")
    with pytest.raises(SceneError, match=r"phantom.diaphragm_si_mm: unknown key"):
        scene_from_dict({"phantom": {"kind": "voxel", "frames": str(log), "diaphragm_si_mm": 20}})
    with pytest.raises(SceneError, match="phantom.interpolation = 'cubic': must be one of nearest, linear"):
        scene_from_dict({"phantom": {"kind": "voxel", "frames": str(log), "interpolation": "cubic"}})


def test_analytic_path_is_unchanged():
    s = load_scene("tiny")
    tb = projection_table(s, 0.1).take(np.arange(0, 300, 37))
    sc = s.scanner
    src, det, eu, ev = detector_frames(tb.angle_rad, tb.source_z_mm, sc.sid_mm, sc.sdd_mm)
    objs = Phantom(s.phantom).objects_batch(tb.state_cardiac, tb.state_resp)
    want = projector.project_views(objs, src, det, eu, ev, detector_coords(sc.n_cols, sc.col_pitch_mm),
                                   detector_coords(sc.n_rows, sc.row_pitch_mm))
    assert np.array_equal(projector.project(s, tb), want)


# ---------------------------------------------------------------------------------------
# export round trip
@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    """tiny's analytic phantom as 6 XCAT and 6 NIfTI frames of 8 mm along its time trajectory."""
    root = tmp_path_factory.mktemp("export")
    s = load_scene("tiny")
    return s, {f: export_phantom(s, root / f, f, 6, voxel_mm=8.0) for f in ("xcat", "nifti")}


def _voxel_scene(s, res, **kw):
    import tomllib

    ph = tomllib.loads(open(res["phantom_toml"]).read())["phantom"]
    return s.replace(phantom={**ph, **kw})


def test_export_round_trip(exported):
    s, res = exported
    c, a, t = np.array(res["xcat"]["states"][0]), np.array(res["xcat"]["states"][1]), np.array(res["xcat"]["times_s"])
    phys = signals.physiology(s, t)
    np.testing.assert_array_equal(c, phys.state_cardiac)
    np.testing.assert_array_equal(a, phys.state_resp)
    sx, sn = _voxel_scene(s, res["xcat"]), _voxel_scene(s, res["nifti"])
    px, pn = projector.phantom_for_scene(sx), projector.phantom_for_scene(sn)
    assert px.timing == "scene" and pn.timing == "table"
    np.testing.assert_allclose(px.frame_states[0], c, atol=1e-8)     # the log's Time Per Frame has 10 digits
    np.testing.assert_allclose(pn.frame_states[1], a, atol=1e-12)
    assert px.geometry.shape == pn.geometry.shape and px.geometry.origin_mm == pytest.approx(pn.geometry.origin_mm)
    x, y, z = (px.geometry.axis(k) for k in range(3))
    want = voxelise_objects(Phantom(s.phantom).objects(c[3], a[3]), x, y, z, supersample=2)
    rt = TOL["roundtrip_rel"][0]
    np.testing.assert_allclose(px.frame(3), want, rtol=rt, atol=rt * MU_WATER_PER_MM)
    np.testing.assert_allclose(pn.frame(3), want, rtol=rt, atol=rt * MU_WATER_PER_MM)
    tb = projection_table(s, 0.1).take(np.arange(0, 380, 19))
    p1, p2 = projector.project(sx, tb), projector.project(sn, tb)
    np.testing.assert_allclose(p1, p2, rtol=0, atol=rt * np.abs(p1).max())


def test_cli_phantom_export(tmp_path, capsys):
    assert main(["phantom", "export", "--format", "nifti", "--grid", "2x2", "--scene", "tiny", "--voxel-mm", "16",
                 str(tmp_path / "n")]) == 0
    assert "wrote 4 nifti frames" in capsys.readouterr().out
    assert len(fr.parse_frame_table(tmp_path / "n" / "frames.toml")) == 4
    assert main(["phantom", "export", "--format", "xcat", "--grid", "2x2", "--scene", "tiny", str(tmp_path / "x")]) == 2
    assert "needs --format nifti" in capsys.readouterr().err


def test_bench_voxel_projector_section():
    res = run_bench(quick=True, only=["voxel-projector"], repeats=1, log=lambda *a, **k: None)
    assert res["voxel-projector"]["rays_per_s"] > 0
    assert "voxel projector (Joseph)" in format_report(res)


# ---------------------------------------------------------------------------------------
# the voxel path against the analytic one
def test_voxel_projections_converge_without_shift(tmp_path):
    """Static tiny: the voxel projections' error halves with the voxel size and has no shift."""
    s = static(load_scene("tiny"))
    tb = projection_table(s, 0.1).take(np.arange(0, 384, 7))
    ref = projector.project(s, tb).astype(np.float64)
    err = {}
    for h in (4.0, 2.0):
        res = export_phantom(s, tmp_path / f"h{h:g}", "xcat", 1, voxel_mm=h)
        d = projector.project(_voxel_scene(s, res), tb).astype(np.float64) - ref
        gu, gv = np.gradient(ref, axis=2), np.gradient(ref, axis=1)
        X = np.stack([np.ones(d.size), gu.ravel(), gv.ravel()], 1)
        (_, su, sv), *_ = np.linalg.lstsq(X, d.ravel(), rcond=None)
        mag = s.scanner.sid_mm / s.scanner.sdd_mm                      # detector -> isocentre
        shift = (su * s.scanner.col_pitch_mm * mag / h, sv * s.scanner.row_pitch_mm * mag / h)
        assert max(abs(shift[0]), abs(shift[1])) < TOL["shift_h"][0], (h, shift)
        err[h] = np.abs(d).mean()
    assert err[2.0] < TOL["convergence"][0] * err[4.0], err


@pytest.fixture(scope="module")
def agreement(tmp_path_factory):
    """tiny, noise-free, local linear: the analytic run, the XCAT-frames run (16 frames of 4 mm
    along the time trajectory) and the NIfTI-grid run (5 x 5 frames of 4 mm, nodes on the targets)."""
    root = tmp_path_factory.mktemp("agree")
    s = load_scene("tiny").replace(noise={"enabled": False})
    kw = dict(methods=["local_linear"], cache_dir=root / "cache", progress=False, log=lambda *a: None)
    out = {"analytic": (run(s, root / "a", **kw), root / "a")}
    xres = export_phantom(s, root / "fx", "xcat", 16, voxel_mm=4.0)
    out["xcat"] = (run(_voxel_scene(s, xres), root / "x", **kw), root / "x")
    nres = export_phantom(s, root / "fn", "nifti", 0, voxel_mm=4.0, grid=(5, 5))
    out["grid"] = (run(_voxel_scene(s, nres), root / "n", **kw), root / "n")
    return s, out, np.diff(xres["times_s"]).max()


def _mae(a_dir, b_dir, name, scene):
    x = voxel_coords(scene.recon.nx, scene.recon.voxel_mm)
    circ = (x[None, :] ** 2 + x[:, None] ** 2) <= scene.scanner.fov_radius_mm ** 2
    with open_volumes(a_dir / "volumes.h5") as fa, open_volumes(b_dir / "volumes.h5") as fb:
        return float(np.abs(read_volume(fa, name) - read_volume(fb, name))[..., circ].mean())


def test_voxel_run_agrees_with_the_analytic_run(agreement):
    """MAE (HU, FOV circle, every target) of the voxel runs against the analytic run within the
    first-order bound: E|X| x the phantom's variation (+ half a frame interval of motion)."""
    s, out, dt = agreement
    res_a, dir_a = out["analytic"]
    z = res_a["request"]["slices_z_mm"]
    targets = [(c, a) for c in res_a["request"]["targets"]["cardiac"] for a in res_a["request"]["targets"]["resp"]]
    spatial = spatial_estimate(s, 4.0, targets, z)
    # motion between frames: half a frame interval times the phantom's mean |dHU/dt|
    p = Phantom(s.phantom)
    x = voxel_coords(400, 1.0)
    circ = (x[None, :] ** 2 + x[:, None] ** 2) <= s.scanner.fov_radius_mm ** 2
    tt = np.linspace(0.05, 1.2, 6)
    phys0, phys1 = signals.physiology(s, tt), signals.physiology(s, tt + 0.01)
    rate = max(float(np.abs(mu_to_hu(p.voxelise(c1, a1, x, x, np.array(z)), MU_WATER_PER_MM)
                            - mu_to_hu(p.voxelise(c0, a0, x, x, np.array(z)), MU_WATER_PER_MM))[:, circ].mean()) / 0.01
               for c0, a0, c1, a1 in zip(phys0.state_cardiac, phys0.state_resp, phys1.state_cardiac,
                                         phys1.state_resp, strict=True))
    bound_recon = TOL["fbp_l1"][0] * spatial + 0.5 * dt * rate
    bound_gt = TOL["fbp_l1"][0] * spatial                      # grid nodes on the targets: no state error
    recon = "recon/p0.100/noise-free/local_linear"
    m_x = _mae(dir_a, out["xcat"][1], recon, s)
    m_g = _mae(dir_a, out["grid"][1], recon, s)
    gt_g = _mae(dir_a, out["grid"][1], "groundtruth", s)
    print(f"estimate {spatial:.1f} HU (motion term {0.5 * dt * rate:.2f}); recon MAE xcat {m_x:.1f}, "
          f"grid {m_g:.1f}; ground truth (grid) {gt_g:.1f}")
    assert m_x <= bound_recon and m_g <= bound_recon and gt_g <= bound_gt, (m_x, m_g, gt_g, bound_recon, bound_gt)
    assert m_x > 0.5 * spatial                                 # a real difference: the frames are not the quadrics
    # the analytic-only parts are skipped, with the reason
    res_x = out["xcat"][0]
    assert "no LV blood-pool model" in res_x["stages"]["metrics"]["respiratory_only_skipped_because"]
    assert res_x["scene"]["phantom"]["kind"] == "voxel"
