"""The reconstruction's fast path: filter rows once, interpolate on the device into the
backprojector's layout, backproject several groups per launch -- against the plain path
(interpolate on the host layout, then :func:`clrecon.reconstruction.fbp.fbp_hu`)."""

from __future__ import annotations

import numpy as np
import pytest

from clrecon.bench import reference_kernels
from clrecon.config.scene import load_scene
from clrecon.core.runtime import aligned_empty
from clrecon.reconstruction import fbp, reconstruct
from clrecon.reconstruction.interpolation import weights as ip
from clrecon.scan.table import projection_table
from clrecon.simulation import simulate

# float32 kernels against float64 / float32 references, relative to max |reference|
TOL = {"interleaved_apply": 1e-6, "filter_commutes": 1e-5, "launch_grouping": 1e-6}

GEOM = fbp.FanBeamGeometry(sid_mm=595.0, sdd_mm=1085.6, n_cols=60, col_pitch_mm=12.0, n_views=48, nx=24, ny=24,
                           voxel_mm=14.0)


def _rel(a, b) -> float:
    return float(np.abs(np.asarray(a, float) - b).max() / max(np.abs(b).max(), 1e-30))


def _read_interleaved(buf, G, V, C, rt):
    out = np.empty((G, V, C + 2, 16), np.float32)
    rt.cl.enqueue_copy(rt.queue, out, buf)
    return out


@pytest.mark.parametrize("B,K", [(1, 3), (16, 3), (21, 3), (40, 3), (21, 1), (17, 2), (33, 5), (21, 8)])
def test_apply_weights_interleaved_matches_reference(B, K):
    """Every slot count the methods use (one kernel build per K: nearest 1, r4dct 2, barycentric 3,
    bin 5, local linear 8), batches that fill no, one or several whole 16-lane groups."""
    rng = np.random.default_rng(B)
    P, V, C = 30, 7, 25
    rows = rng.standard_normal((P, C)).astype(np.float32)
    rows[5] = np.nan  # only ever pointed to by zero weights: must not leak
    idx = rng.integers(0, P, (B, V, K))
    w = rng.standard_normal((B, V, K)).astype(np.float32)
    w[idx == 5] = 0.0
    dr = ip.DeviceRows(rows)
    try:
        buf, G = ip.apply_weights_interleaved(dr, idx, w)
        got = _read_interleaved(buf, G, V, C, dr.rt)
    finally:
        dr.release()
    ref = ip.apply_weights_reference(np.nan_to_num(rows), idx.reshape(-1, K), w.reshape(-1, K)).reshape(B, V, C)
    assert G == -(-B // 16)
    assert _rel(got, fbp.interleave_batch(ref.astype(np.float32))) < TOL["interleaved_apply"]


@pytest.mark.parametrize("B,K", [(21, 3), (16, 1), (33, 8)])
def test_loop_kernel_reference_matches(B, K):
    """The bench's reference kernel (the reconstruction's until 2026-12-03) against the float64
    reference, and bit for bit against the vectorised kernel (same sums in the same order)."""
    from clrecon.bench.reference_kernels import apply_interleaved_loop

    rng = np.random.default_rng(100 + B)
    P, V, C = 30, 7, 25
    rows = rng.standard_normal((P, C)).astype(np.float32)
    rows[5] = np.nan
    idx = rng.integers(0, P, (B, V, K))
    w = rng.standard_normal((B, V, K)).astype(np.float32)
    w[idx == 5] = 0.0
    w[rng.random(w.shape) < 0.2] = 0.0
    dr = ip.DeviceRows(rows)
    try:
        old, G = apply_interleaved_loop(dr, idx, w)
        new, G2 = ip.apply_weights_interleaved(dr, idx, w)
        got_old, got_new = _read_interleaved(old, G, V, C, dr.rt), _read_interleaved(new, G2, V, C, dr.rt)
    finally:
        dr.release()
    ref = ip.apply_weights_reference(np.nan_to_num(rows), idx.reshape(-1, K), w.reshape(-1, K)).reshape(B, V, C)
    assert G == G2 == -(-B // 16)
    assert _rel(got_old, fbp.interleave_batch(ref.astype(np.float32))) < TOL["interleaved_apply"]
    assert np.array_equal(got_old.view(np.uint32), got_new.view(np.uint32))


@pytest.mark.parametrize("C", [1, 2, 5, 6, 7, 8, 13, 25, 94])
@pytest.mark.parametrize("K", [1, 3, 8])
def test_cols8_kernel_bit_identical_to_per_lane(C, K):
    """The 8-columns-per-work-item kernel (the reconstruction's since 2026-12-05) against the per-lane
    kernel it replaced, bit for bit, and against the float64 reference: row widths whose padded
    columns (C + 2) fall into interior blocks and edge blocks in every way (no interior block at
    all below C = 7; a block ending exactly at the last column; a partial last block), NaN rows
    reached only through zero weights, and the -0 / subnormal products of tiny weights."""
    rng = np.random.default_rng(1000 * C + K)
    P, V, B = 23, 5, 35
    rows = rng.standard_normal((P, C)).astype(np.float32)
    rows[4] = np.nan
    rows[7] *= np.float32(1e-38)  # subnormal products
    idx = rng.integers(0, P, (B, V, K))
    w = rng.standard_normal((B, V, K)).astype(np.float32)
    w[idx == 4] = 0.0
    w[rng.random(w.shape) < 0.2] = 0.0
    w[rng.random(w.shape) < 0.05] = -0.0
    pi, pw = ip.pad_interleaved(idx, w)
    dr = ip.DeviceRows(rows)
    try:
        now, G = ip.apply_padded_interleaved(dr, pi, pw, B)
        lanes, G2 = reference_kernels.apply_padded_interleaved_lanes(dr, pi, pw, B)
        got_now, got_lanes = _read_interleaved(now, G, V, C, dr.rt), _read_interleaved(lanes, G2, V, C, dr.rt)
    finally:
        dr.release()
    assert G == G2 == -(-B // 16)
    assert np.array_equal(got_now.view(np.uint32), got_lanes.view(np.uint32))
    ref = ip.apply_weights_reference(np.nan_to_num(rows), idx.reshape(-1, K), w.reshape(-1, K)).reshape(B, V, C)
    assert _rel(got_now, fbp.interleave_batch(ref.astype(np.float32))) < TOL["interleaved_apply"]


def test_launch_scratch_buffers_reused():
    """The reconstruction's scratch: the interleaved sinograms written into a kept buffer and the
    images into a kept device buffer and host array give what fresh buffers give, launch after
    launch (a smaller launch into the same buffers too), and a buffer too small is refused."""
    rng = np.random.default_rng(4)
    P, V, K, C = 40, GEOM.n_views, 3, GEOM.n_cols
    rows = rng.standard_normal((P, C)).astype(np.float32)
    dr = ip.DeviceRows(rows)
    rt = dr.rt
    d_sino = rt.empty((2, V, C + 2, 16))
    d_img = rt.empty((32, GEOM.ny, GEOM.nx))
    host = np.empty((32, GEOM.ny, GEOM.nx), np.float32)
    try:
        for B in (32, 7, 32):
            idx = rng.integers(0, P, (B, V, K))
            w = rng.standard_normal((B, V, K)).astype(np.float32)
            pi, pw = ip.pad_interleaved(idx, w)
            fresh, G = ip.apply_padded_interleaved(dr, pi, pw, B)
            kept, G2 = ip.apply_padded_interleaved(dr, pi, pw, B, out=d_sino)
            assert kept is d_sino and G2 == G
            np.testing.assert_array_equal(_read_interleaved(kept, G, V, C, rt), _read_interleaved(fresh, G, V, C, rt))
            a = fbp.backproject_interleaved(fresh, G, GEOM)
            b = fbp.backproject_interleaved(kept, G, GEOM, out_buf=d_img, out=host)
            assert b.base is host or b is host
            np.testing.assert_array_equal(a, b)
            fresh.release()
        with pytest.raises(ValueError, match="out: a buffer of"):
            ip.apply_padded_interleaved(dr, pi, pw, 48, out=d_sino)
        with pytest.raises(ValueError, match="out_buf: a buffer of"):
            fbp.backproject_interleaved(d_sino, 3, GEOM, out_buf=d_img)
        with pytest.raises(ValueError, match="out: expected"):
            fbp.backproject_interleaved(d_sino, 2, GEOM, out=np.empty((32, GEOM.ny, GEOM.nx + 1), np.float32))
    finally:
        dr.release()
        d_sino.release()
        d_img.release()


def test_shared_rows_read_in_place():
    """DeviceRows(share=True) over a page-aligned float32 array: on the CPU device the buffer is
    the array's own memory (CL_MEM_USE_HOST_PTR, same address), the interpolation reads the same
    floats as from a copy (bit for bit), and arrays the device cannot read in place (unaligned,
    strided, float64) are copied instead, with the same result."""
    rng = np.random.default_rng(5)
    P, V, K, C, B = 40, 9, 3, 33, 21
    idx = rng.integers(0, P, (B, V, K))
    w = rng.standard_normal((B, V, K)).astype(np.float32)
    src = rng.standard_normal((P, C)).astype(np.float32)
    copied = ip.DeviceRows(src)
    rt = copied.rt
    mf = rt.cl.mem_flags
    rows = aligned_empty((P, C), np.float32)
    assert rows.ctypes.data % 4096 == 0 and rows.flags.c_contiguous and rows.shape == (P, C)
    rows[...] = src
    unaligned = np.empty(P * C + 1, np.float32)[1:].reshape(P, C)
    unaligned[...] = src
    cases = {"aligned": rows, "unaligned": unaligned, "strided": np.repeat(src, 2, axis=1)[:, ::2],
             "float64": src.astype(np.float64)}
    try:
        ref, G = ip.apply_weights_interleaved(copied, idx, w)
        want = _read_interleaved(ref, G, V, C, rt)
        for name, arr in cases.items():
            dr = ip.DeviceRows(arr, share=True)
            try:
                in_place = bool(dr.buf.flags & mf.USE_HOST_PTR)
                assert in_place == (name == "aligned" and rt.is_cpu), name
                if in_place:
                    host = dr.buf.get_host_array((P, C), np.float32)
                    assert host.ctypes.data == arr.ctypes.data
                got, G2 = ip.apply_weights_interleaved(dr, idx, w)
                assert G2 == G
                np.testing.assert_array_equal(_read_interleaved(got, G, V, C, rt).view(np.uint32),
                                              want.view(np.uint32), err_msg=name)
            finally:
                dr.release()
                assert dr.buf is None and dr._host is None
    finally:
        copied.release()


def test_apply_weights_interleaved_checks():
    dr = ip.DeviceRows(np.zeros((4, 5), np.float32))
    with pytest.raises(ValueError):
        ip.apply_weights_interleaved(dr, np.full((1, 2, 1), 4), np.ones((1, 2, 1), np.float32))
    with pytest.raises(TypeError):
        ip.apply_weights_interleaved(dr, np.zeros((1, 2, 1)), np.ones((1, 2, 1), np.float32))
    with pytest.raises(ValueError):
        ip.apply_weights_interleaved(dr, np.zeros((2, 1), int), np.ones((2, 1), np.float32))
    buf, G = ip.apply_weights_interleaved(dr, np.zeros((0, 2, 1), int), np.zeros((0, 2, 1), np.float32))
    assert G == 1 and not _read_interleaved(buf, G, 2, 5, dr.rt).any()
    dr.release()
    dr.release()  # idempotent


def test_filter_commutes_with_interpolation():
    """filter(sum_k w_k row_k) == sum_k w_k filter(row_k): why rows are filtered once per variant."""
    rng = np.random.default_rng(3)
    P, B, K = 40, 5, 4
    rows = rng.standard_normal((P, GEOM.n_cols)).astype(np.float32)
    idx = rng.integers(0, P, (B * GEOM.n_views, K))
    w = rng.uniform(-0.5, 1.0, (B * GEOM.n_views, K)).astype(np.float32)
    after = fbp.filter_sinograms(ip.apply_weights_reference(rows, idx, w).reshape(B, GEOM.n_views, -1), GEOM)
    filtered = fbp.filter_rows(rows, GEOM)
    before = ip.apply_weights_reference(filtered, idx, w).reshape(B, GEOM.n_views, -1)
    assert _rel(before, after) < TOL["filter_commutes"]
    inplace = rows.copy()
    assert fbp.filter_rows(inplace, GEOM, out=inplace) is inplace
    np.testing.assert_array_equal(inplace, filtered)
    with pytest.raises(ValueError):
        fbp.filter_rows(rows[:, :-1], GEOM)


def test_several_groups_per_launch_match_one(monkeypatch):
    q = np.random.default_rng(4).standard_normal((37, GEOM.n_views, GEOM.n_cols)).astype(np.float32)
    many = fbp.backproject(q, GEOM)
    monkeypatch.setattr(fbp, "LAUNCH_GROUPS", 1)  # one group per launch: the kernel's odd case
    assert fbp.groups_per_launch(GEOM) == 1
    one = fbp.backproject(q, GEOM)
    assert _rel(many, one) < TOL["launch_grouping"]


def test_reconstruct_matches_plain_pipeline(tmp_path):
    """Fast path vs interpolate-then-FBP on the host, every method, both variants (tiny scene)."""
    sc = load_scene("tiny")
    pitch = sc.scan.pitches[0]
    table = projection_table(sc, pitch)
    z = reconstruct.slice_positions(sc)
    tg = reconstruct.Targets(tuple(sc.cardiac_targets), tuple(sc.resp_targets))
    p = reconstruct.plan(reconstruct.ReconstructionConfig.from_scene(sc), table, z, tg, sc.recon.methods)
    store = simulate.simulate(sc, pitch, needed=p.needed_projections(len(table)), cache_dir=tmp_path, progress=False)
    vols = reconstruct.reconstruct(reconstruct.ReconstructionConfig.from_scene(sc), store, p, variants=("noise-free",))
    geom = fbp.FanBeamGeometry.from_scene(sc)
    S = len(z)
    # plain path: rebin every needed (projection, slice) pair, weights on the host, FBP in HU
    from clrecon.reconstruction import rebin
    for m, mp in p.methods.items():
        Sn, V, T, K = mp.proj_index.shape
        sino = np.zeros((S, V, T, sc.scanner.n_cols))
        for s in range(S):
            for k in range(K):
                live = mp.weight[s, :, :, k] != 0
                proj = mp.proj_index[s, :, :, k][live]
                uniq, inv = np.unique(proj, return_inverse=True)
                data = store.read_indices(uniq)
                dz = (z[s] - store.table.source_z_mm[uniq]).astype(np.float32)
                r = rebin.ssrb_rows(data, np.arange(len(uniq), dtype=np.int32), dz, sc.scanner)
                sino[s][live] += mp.weight[s, :, :, k][live][:, None] * r[inv.ravel()]
        sino = sino.transpose(0, 2, 1, 3).reshape(S * T, V, -1)
        ref = fbp.fbp_batched(sino, geom, sc.recon.filter, sc.phantom.mu_water_per_mm)
        ref = ref.reshape(S, mp.targets_shape[0], mp.targets_shape[1], sc.recon.ny, sc.recon.nx)
        ref = ref.transpose(1, 2, 0, 3, 4)
        got = vols[("noise-free", m)]
        assert got.shape == ref.shape
        assert np.abs(got - ref).max() < 0.05, m  # HU; float32 rounding of a different summation order
    store.close()


def test_slab_halved_to_fit_the_device_buffer_limit_gives_identical_volumes(tmp_path):
    """A slab whose rebinned rows exceed one device buffer is halved until they fit
    (the paper-p002 whole run died on PoCL's CL_DEVICE_MAX_MEM_ALLOC_SIZE): same bits, and a
    limit below one slice's rows is a clear error, not the driver's INVALID_BUFFER_SIZE."""
    sc = load_scene("tiny")
    pitch = sc.scan.pitches[0]
    table = projection_table(sc, pitch)
    z = reconstruct.slice_positions(sc)
    tg = reconstruct.Targets(tuple(sc.cardiac_targets), tuple(sc.resp_targets))
    cfg = reconstruct.ReconstructionConfig.from_scene(sc)
    p = reconstruct.plan(cfg, table, z, tg, sc.recon.methods)
    store = simulate.simulate(sc, pitch, needed=p.needed_projections(len(table)), cache_dir=tmp_path, progress=False)
    variants = ("noise-free", "noisy")
    whole = reconstruct.reconstruct(cfg, store, p, variants=variants, slab_size=len(z))
    rows = [len(reconstruct._slab_pairs(p, s, s + 1)[1]) for s in range(len(z))]
    assert len(z) >= 2 and min(rows) > 0
    cap = 4 * sc.scanner.n_cols * (max(rows) + 1)  # one slice fits, the whole slab does not
    assert len(reconstruct._slab_pairs(p, 0, len(z))[1]) * 4 * sc.scanner.n_cols > cap
    times = reconstruct.StageTimes()
    split = reconstruct.reconstruct(cfg, store, p, variants=variants, slab_size=len(z), max_buffer_bytes=cap,
                                    times=times)
    assert times.counts.get("slab_splits", 0) >= 1
    assert split.keys() == whole.keys()
    for k in whole:
        np.testing.assert_array_equal(split[k], whole[k], err_msg=str(k))
    with pytest.raises(reconstruct.SlabTooLarge, match="CL_DEVICE_MAX_MEM_ALLOC_SIZE"):
        reconstruct.reconstruct(cfg, store, p, variants=variants, max_buffer_bytes=4 * sc.scanner.n_cols)
    store.close()


# --- the new kernels under Oclgrind (memcheck, data races, uninitialised values) -----------
def _grind(capfd):
    import os
    import re

    import pyopencl as cl

    from clrecon.core.runtime import Runtime

    if not any("oclgrind" in p.name.lower() for p in cl.get_platforms()):
        pytest.skip("Oclgrind is not installed: pip install 'pyopencl[oclgrind]'")
    saved = {k: os.environ.get(k) for k in ("OCLGRIND_DATA_RACES", "OCLGRIND_UNINITIALIZED")}
    os.environ.update(OCLGRIND_DATA_RACES="1", OCLGRIND_UNINITIALIZED="1")
    try:
        rt = Runtime("oclgrind")
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
    diag = re.compile(r"Invalid (read|write)|data race|[Uu]ninitiali[sz]ed|Oclgrind.*error|out of bounds", re.I)

    def clean():
        err = capfd.readouterr().err
        assert not diag.search(err), err[:4000]
    return rt, clean


def test_oclgrind_interleaved_apply_and_noise(capfd):
    from clrecon.config.scene import NoiseConfig
    from clrecon.simulation import noise

    rt, clean = _grind(capfd)
    rng = np.random.default_rng(1)
    # 20 columns: padded columns 0..21 in blocks of 8 -- an edge block, an interior one, a partial edge one
    rows = rng.standard_normal((9, 20)).astype(np.float32)
    idx = rng.integers(0, 9, (19, 3, 2))
    w = rng.standard_normal((19, 3, 2)).astype(np.float32)
    dr = ip.DeviceRows(rows, rt=rt)
    buf, G = ip.apply_weights_interleaved(dr, idx, w, rt=rt)  # the 8-columns kernel
    got = rt.from_device(buf, (G, 3, 22, 16))
    ref = fbp.interleave_batch(ip.apply_weights_reference(rows, idx.reshape(-1, 2), w.reshape(-1, 2))
                               .reshape(19, 3, 20).astype(np.float32))
    assert _rel(got, ref) < TOL["interleaved_apply"]
    # the per-lane reference kernel
    buf, G = reference_kernels.apply_padded_interleaved_lanes(dr, *ip.pad_interleaved(idx, w), 19, rt=rt)
    assert _rel(rt.from_device(buf, (G, 3, 22, 16)), ref) < TOL["interleaved_apply"]
    from clrecon.bench.reference_kernels import apply_interleaved_loop  # the bench's reference kernel
    buf, G = apply_interleaved_loop(dr, idx, w, rt=rt)
    assert _rel(rt.from_device(buf, (G, 3, 22, 16)), ref) < TOL["interleaved_apply"]
    p = rng.uniform(0, 12, (2, 3, 25)).astype(np.float32)  # 75 cells: padded to 128
    cfg = NoiseConfig(i0_photons=50.0, seed=2)              # both passes run
    np.testing.assert_array_equal(noise.add_noise(p, np.array([3, 9]), cfg, rt=rt),
                                  noise.add_noise_reference(p, np.array([3, 9]), cfg))
    # backprojection, two groups per work-item with an odd group count (the last one alone)
    small = fbp.FanBeamGeometry(sid_mm=595.0, sdd_mm=1085.6, n_cols=12, col_pitch_mm=60.0, n_views=10, nx=9, ny=7,
                                voxel_mm=40.0)
    q = rng.standard_normal((33, small.n_views, small.n_cols)).astype(np.float32)
    assert _rel(fbp.backproject(q, small, runtime=rt), reference_kernels.backproject_single(q, small)) < 1e-5
    clean()
