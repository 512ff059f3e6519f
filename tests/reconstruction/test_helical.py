"""``helical``: the conventional free-breathing baseline (nearest turn in z, phase ignored).

Weights: one slot of weight 1 on the candidate nearest the slice in z, for every target; the
``dz`` input changes no other method. Plan: the nearest-in-z projection of every (slice,
view). End to end on ``tiny``: one volume for every target, equal to ``nearest`` without
motion, and with motion a larger small-FOV MAE than every phase-resolved method (law 6(b)
of issue 10: gating / phase-space interpolation beats the ungated reconstruction).
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from clrecon.config.scene import load_scene
from clrecon.outputs.volumes import open_volumes, read_volume
from clrecon.pipeline.run import resolve_targets, run
from clrecon.reconstruction import interpolation, rebin, reconstruct
from clrecon.reconstruction.interpolation import weights as ip
from clrecon.reconstruction.interpolation.base import Method
from clrecon.scan.table import projection_table

TARGETS = np.array([[c, a] for c in (0.0, 0.2, 0.4, 0.6, 0.8) for a in np.arange(0.05, 1.0, 0.1)])
#: phase-resolved methods of law 6(b) (every (c*, a*) target, phases used)
PHASE_RESOLVED = ("barycentric", "local_linear", "nearest", "bin")


# ---------------------------------------------------------------------------------------
# weights
@pytest.mark.parametrize("use_cardiac,use_resp", [(True, True), (True, False), (False, True)])
def test_helical_picks_the_candidate_nearest_in_z_for_every_target(use_cardiac, use_resp):
    rng = np.random.default_rng(4)
    counts = np.array([1, 2, 9, 44, 3, 17])
    off = np.concatenate([[0], np.cumsum(counts)])
    n = off[-1]
    c, a, dz = rng.random(n), rng.random(n), rng.uniform(-12.0, 12.0, n)   # signed: |dz| counts
    W = ip.batch_weights("helical", c, a, off, TARGETS, dz=dz, use_cardiac=use_cardiac, use_resp=use_resp,
                         chunk_groups=4)
    assert W.index.shape == (counts.size, TARGETS.shape[0], 1)
    assert np.all(W.weight == 1.0)
    for g in range(counts.size):
        k = off[g] + int(np.argmin(np.abs(dz[off[g]:off[g + 1]])))
        assert np.all(W.index[g, :, 0] == k)
    # the phases do not matter: other c, a give the same choice
    W2 = ip.batch_weights("helical", rng.random(n), rng.random(n), off, TARGETS[::7], dz=dz)
    assert np.array_equal(W2.index[:, :1], W.index[:, :1])


def test_helical_ties_go_to_the_earlier_candidate_and_dz_is_required():
    W = ip.method_weights("helical", [0.1, 0.5, 0.9], [0.2, 0.4, 0.6], TARGETS, dz=[3.0, -1.5, 1.5])
    assert np.all(W.index[:, 0] == 1) and np.all(W.weight[:, 0] == 1.0)
    with pytest.raises(ValueError, match="dz"):
        ip.method_weights("helical", [0.1, 0.5], [0.2, 0.4], TARGETS)
    with pytest.raises(ValueError, match="dz"):
        ip.method_weights("nearest", [0.1, 0.5], [0.2, 0.4], TARGETS, dz=[1.0])


@pytest.mark.parametrize("method", [m for m in ip.METHODS if m != "helical"])
def test_dz_changes_no_phase_method(method):
    rng = np.random.default_rng(5)
    counts = np.array([3, 17, 40, 1])
    off = np.concatenate([[0], np.cumsum(counts)])
    c, a = rng.random(off[-1]), rng.random(off[-1])
    a0 = ip.batch_weights(method, c, a, off, TARGETS)
    a1 = ip.batch_weights(method, c, a, off, TARGETS, dz=rng.uniform(-9, 9, off[-1]))
    assert np.array_equal(a0.index, a1.index) and np.array_equal(a0.weight, a1.weight)


def test_registry_record():
    m = interpolation.METHODS["helical"]
    assert m.target_grid == "none" and m.axes == () and not m.five_d and m.neighbours == 1
    # the last of the default methods, by rank and registration (opt-in methods such as cv_tuned
    # are registered after it and are in no default list)
    defaults = interpolation.default_methods()
    assert interpolation.by_rank(defaults)[-1] == "helical" and defaults[-1] == "helical"
    assert all(interpolation.METHODS[n].opt_in for n in interpolation.method_names() if n not in defaults)
    assert m.marker not in {x.marker for n, x in interpolation.METHODS.items() if n != "helical"}
    assert "helical" in load_scene("tiny").recon.methods       # the default method list is the registry's
    with pytest.raises(ValueError, match="axes"):
        Method(name="x", label="x", neighbours=1, target_grid="none", axes=("resp",), five_d=False, marker="o",
               rank=9, weights=lambda *a: None)
    with pytest.raises(ValueError, match="axes"):
        Method(name="x", label="x", neighbours=1, target_grid="5d", axes=(), five_d=False, marker="o", rank=9,
               weights=lambda *a: None)


# ---------------------------------------------------------------------------------------
# plan
def test_plan_takes_the_nearest_projection_in_z_of_every_slice_and_view():
    s = load_scene("tiny")
    cfg = reconstruct.ReconstructionConfig.from_scene(s)
    targets = resolve_targets(s)
    table = projection_table(s, s.scan.pitches[0])
    z = reconstruct.slice_positions(s)
    p = reconstruct.plan(cfg, table, z, targets, ["nearest", "helical"])
    mp = p.methods["helical"]
    nv = s.scanner.views_per_rotation
    assert mp.targets_shape == (1, 1) and mp.proj_index.shape == (len(z), nv, 1, 1)
    assert np.all(mp.weight == 1.0)
    w = rebin.slice_window_mm(s.scanner, cfg.object_radius_mm)
    for si, zs in enumerate(z):
        for j in range(nv):
            k = np.flatnonzero((table.view == j) & (np.abs(zs - table.source_z_mm) <= w))
            best = table.index[k[np.argmin(np.abs(zs - table.source_z_mm[k]))]]
            assert mp.proj_index[si, j, 0, 0] == best
    # adding helical to the plan leaves the other method's weights alone
    p0 = reconstruct.plan(cfg, table, z, targets, ["nearest"])
    assert np.array_equal(p0.methods["nearest"].proj_index, p.methods["nearest"].proj_index)
    assert np.array_equal(p0.methods["nearest"].weight, p.methods["nearest"].weight)


# ---------------------------------------------------------------------------------------
# end to end on tiny
@pytest.fixture(scope="module")
def moving_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("helical-run")
    s = load_scene("tiny").replace(noise={"enabled": False})
    res = run(s, out, methods=list(PHASE_RESOLVED) + ["helical"], cache_dir=tmp_path_factory.mktemp("cache"),
              progress=False, log=lambda *a: None)
    return out, res


def test_helical_is_worse_than_every_phase_resolved_method_in_the_heart(moving_run):
    _, res = moving_run
    met = res["metrics"]["p0.100"]["noise-free"]
    h = met["helical"]["small"]["mae_hu"]
    for m in PHASE_RESOLVED:
        assert h > met[m]["small"]["mae_hu"], (m, met[m]["small"]["mae_hu"], h)


def test_helical_volume_is_one_for_every_target_and_shows_in_the_outputs(moving_run):
    out, res = moving_run
    with open_volumes(out) as f:
        assert f["recon/p0.100/noise-free/helical"].shape[:2] == (1, 1)  # stored once
        vol = read_volume(f, "recon/p0.100/noise-free/helical")
    assert vol.shape[:2] == (2, 2) and np.isfinite(vol).all()  # and read as one for every target
    assert np.all(vol == vol[:1, :1])
    report = (out / "report.md").read_text()
    assert "helical, large FOV" in report and "## Claims" in report
    assert "failed" not in report
    on_disk = json.loads((out / "results.json").read_text())
    assert on_disk["claims"] and all({"claim", "holds", "numbers", "pitch", "variant", "fov"} <= set(c)
                                     for c in on_disk["claims"])
    assert "helical" in on_disk["method_seconds"]["p0.100"]["noise-free"]
