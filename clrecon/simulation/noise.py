"""CT noise: Poisson quanta plus Gaussian electronic noise on line integrals (pipeline stage 4).

Design: the projection store holds **noise-free** line integrals; noise is added here when
projections are *read* (``ProjectionStore.read(..., noisy=True)``). One simulation therefore
serves both the noise-free and the noisy reconstruction (the paper's Table 2 reports both),
the expensive projector never reruns for a new noise level or seed, and the noise settings
are not part of the store's content hash.

Model, per detector cell of a projection with line integral p (dimensionless, mu * length):
    N = Poisson(I0 exp(-p)) + Normal(0, sigma_e)          (photon-equivalent counts)
    p_noisy = -log(max(N, N_FLOOR) / I0)
with I0 = ``NoiseConfig.i0_photons`` unattenuated photons per cell and sigma_e =
``NoiseConfig.electronic_sigma``. Zero or negative counts (photon starvation, or electronic
noise pushing a few counts below zero) have no logarithm; they are clamped to
``N_FLOOR`` = 1 photon, the smallest count a detector can meaningfully report. This caps the
noisy line integral at ln(I0) (~12.2 for 2e5 photons): a finite, documented ceiling instead of
inf or NaN, which is what scanners' positivity corrections do before the log as well.

Reproducibility: the random numbers come from the counter-based generator Philox4x64-10
(Salmon et al., SC 2011) keyed by ``(seed, projection index)`` with the detector cell in the
counter, so every cell of every projection owns its stream: a projection's noise is the same
whatever the chunk size, order, worker or device that reads it. The OpenCL kernel
(``kernels/noise.cl``, float64) does the work; :func:`add_noise_reference` is the same
generator and samplers in float64 NumPy, step for step (the tests compare them), and is
used on a device without float64. Poisson sampling: inversion below a mean of 10, else
Hoermann's PTRS (what NumPy uses); electronic noise: Box-Muller. Measured on demo-sized
projections (16 x 240, I0 = 2e5) on the 2-core PoCL machine: 24-28 M cells/s against
18.6 M cells/s for the NumPy ``Generator`` per projection it replaced (1.3-1.5x; PoCL's
double-precision log/exp stay scalar calls, see ``kernels/noise.cl``); on a GPU the same
kernel is the part that scales.
"""

from __future__ import annotations

import numpy as np

from clrecon.core import drivers
from clrecon.core.runtime import get_runtime
from clrecon.simulation.config import NoiseConfig

#: Counts below this (photons) are clamped before the log; see the module docstring.
N_FLOOR = 1.0


#: Philox4x64-10 constants (Random123): multipliers and Weyl key increments.
PHILOX_M = (0xD2E7470EE14C6C93, 0xCA5A826395121157)
PHILOX_W = (0x9E3779B97F4A7C15, 0xBB67AE8584CAA73B)
#: Means below this are sampled by inversion, above by PTRS (as in kernels/noise.cl).
PTRS_MIN_LAM = 10.0
INVERSION_MAX_K = 200.0
MAX_ROUNDS = 64

_U64 = np.uint64
_MASK32 = _U64(0xFFFFFFFF)


def _mulhilo(a: int, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(high, low) 64-bit words of the 128-bit product of constant ``a`` and uint64 ``b``."""
    a_lo, a_hi = _U64(a & 0xFFFFFFFF), _U64(a >> 32)
    b_lo, b_hi = b & _MASK32, b >> _U64(32)
    p0, p1, p2, p3 = a_lo * b_lo, a_hi * b_lo, a_lo * b_hi, a_hi * b_hi
    mid = (p0 >> _U64(32)) + (p1 & _MASK32) + (p2 & _MASK32)
    hi = p3 + (p1 >> _U64(32)) + (p2 >> _U64(32)) + (mid >> _U64(32))
    return hi, _U64(a) * b


def philox4x64(counter, key) -> np.ndarray:
    """Philox4x64-10 blocks: ``counter`` (..., 4) and ``key`` (..., 2) uint64 -> (..., 4) uint64."""
    with np.errstate(over="ignore"):
        c = [np.array(x, dtype=np.uint64) for x in np.moveaxis(np.asarray(counter, dtype=np.uint64), -1, 0)]
        k = [np.array(x, dtype=np.uint64) for x in np.moveaxis(np.asarray(key, dtype=np.uint64), -1, 0)]
        for r in range(10):
            if r > 0:
                k = [k[0] + _U64(PHILOX_W[0]), k[1] + _U64(PHILOX_W[1])]
            hi0, lo0 = _mulhilo(PHILOX_M[0], c[0])
            hi1, lo1 = _mulhilo(PHILOX_M[1], c[2])
            c = [hi1 ^ c[1] ^ k[0], lo1, hi0 ^ c[3] ^ k[1], lo0]
        return np.stack(np.broadcast_arrays(*c), axis=-1)


def _u01_co(x):
    return (x >> _U64(11)).astype(np.float64) * 2.0 ** -53


def _u01_oc(x):
    return ((x >> _U64(11)) + _U64(1)).astype(np.float64) * 2.0 ** -53


def _loggam(x: np.ndarray) -> np.ndarray:
    """log Gamma(x) for x >= 1: NumPy's ``random_loggam`` series, vectorised (as in noise.cl)."""
    x = np.asarray(x, dtype=np.float64)
    n = np.where(x < 7.0, np.floor(7.0 - x), 0.0)
    x0 = x + n
    x2 = (1.0 / x0) * (1.0 / x0)
    coef = (8.333333333333333e-02, -2.777777777777778e-03, 7.936507936507937e-04, -5.952380952380952e-04,
            8.417508417508418e-04, -1.917526917526918e-03, 6.410256410256410e-03, -2.955065359477124e-02,
            1.796443723688307e-01, -1.39243221690590e+00)
    gl0 = np.full_like(x0, coef[9])
    for c in coef[8::-1]:
        gl0 = gl0 * x2 + c
    gl = gl0 / x0 + 0.5 * 1.8378770664093453e+00 + (x0 - 0.5) * np.log(x0) - x0
    for k in range(1, 7):
        live = k <= n
        gl = np.where(live, gl - np.log(np.where(live, x0 - 1.0, 1.0)), gl)
        x0 = np.where(live, x0 - 1.0, x0)
    return np.where((x == 1.0) | (x == 2.0), 0.0, gl)


_COS_TAYLOR = (1.0, -0.5, 0.041666666666666664, -0.001388888888888889, 2.48015873015873e-05,
               -2.755731922398589e-07, 2.08767569878681e-09, -1.1470745597729725e-11, 4.779477332387385e-14,
               -1.5619206968586225e-16, 4.110317623312165e-19)


def cos2pi(u) -> np.ndarray:
    """cos(2 pi u), u in [0, 1): the polynomial of noise.cl (error < 1e-15), same operations."""
    u = np.asarray(u, dtype=np.float64)
    t = np.abs(u - 0.5)
    y = 6.283185307179586 * np.where(t <= 0.25, t, 0.5 - t)
    y2 = y * y
    c = np.full_like(y, _COS_TAYLOR[10])
    for coef in _COS_TAYLOR[9::-1]:
        c = c * y2 + coef
    return np.where(t <= 0.25, -c, c)


def poisson_reference(lam, cell, key, r0) -> np.ndarray:
    """Poisson samples (float64 counts) of means ``lam`` (n,), as ``poisson()`` in noise.cl.

    ``cell`` (n,) uint64 counters, ``key`` (n, 2) uint64, ``r0`` (n, 4) the round-0 blocks.
    """
    lam = np.asarray(lam, dtype=np.float64)
    out = np.zeros(lam.shape)
    small = (lam > 0) & (lam < PTRS_MIN_LAM)
    if small.any():
        ls = lam[small]
        u = _u01_co(r0[small, 2])
        k = np.zeros_like(ls)
        pk = np.exp(-ls)
        cdf = pk.copy()
        live = (u > cdf) & (k < INVERSION_MAX_K)
        while live.any():
            k = np.where(live, k + 1.0, k)
            pk = np.where(live, pk * ls / np.where(live, k, 1.0), pk)
            cdf = np.where(live, cdf + pk, cdf)
            live = (u > cdf) & (k < INVERSION_MAX_K)
        out[small] = k
    big = np.flatnonzero(lam >= PTRS_MIN_LAM)
    if big.size == 0:
        return out
    lb = lam[big]
    slam, loglam = np.sqrt(lb), np.log(lb)
    b = 0.931 + 2.53 * slam
    a = -0.059 + 0.02483 * b
    invalpha = 1.1239 + 1.1328 / (b - 3.4)
    vr = 0.9277 - 3.6224 / (b - 2.0)
    done = np.zeros(big.size, bool)
    res = np.floor(lb + 0.5)  # after MAX_ROUNDS without acceptance
    r = r0[big]
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        for rnd in range(MAX_ROUNDS):
            if done.all():
                break
            if rnd > 0:
                ctr = np.zeros((big.size, 4), np.uint64)
                ctr[:, 0] = cell[big]
                ctr[:, 1] = rnd
                r = philox4x64(ctr, key[big])
            for h in ((1,) if rnd == 0 else (0, 1)):
                U = _u01_co(r[:, 2 * h]) - 0.5
                V = _u01_oc(r[:, 2 * h + 1])
                us = 0.5 - np.abs(U)
                k = np.floor((2.0 * a / us + b) * U + lb + 0.43)
                fast = (us >= 0.07) & (V <= vr)
                skip = (us < 0.013) & (V > us)
                ok_k = ~fast & ~skip & (k >= 0.0)
                kk = np.where(ok_k, k, 0.0)
                lhs = np.log(V) + np.log(invalpha) - np.log(a / (us * us) + b)
                rhs = -lb + kk * loglam - _loggam(kk + 1.0)
                accept = ~done & (fast | (ok_k & (lhs <= rhs)))
                res = np.where(accept, k, res)
                done |= accept
    out[big] = res
    return out


def add_noise_reference(line_integrals, proj_index, cfg: NoiseConfig, first_row: int = 0) -> np.ndarray:
    """Float64 NumPy reference of :func:`add_noise`: the same Philox streams and samplers."""
    p, idx = _check(line_integrals, proj_index)
    m = p.shape[0]
    cells = int(np.prod(p.shape[1:]))
    i0 = float(cfg.i0_photons)
    sigma = float(cfg.electronic_sigma)
    out = np.empty(p.shape, np.float32)
    cell = np.arange(cells, dtype=np.uint64) + np.uint64(_cell0(p, first_row))
    for j in range(m):
        key = np.broadcast_to(np.array([cfg.seed, int(idx[j]) & 0xFFFFFFFFFFFFFFFF], np.uint64), (cells, 2))
        ctr = np.zeros((cells, 4), np.uint64)
        ctr[:, 0] = cell
        r0 = philox4x64(ctr, key)
        lam = i0 * np.exp(-p[j].reshape(-1).astype(np.float64))
        counts = poisson_reference(lam, cell, key, r0)
        if sigma > 0:
            counts = counts + sigma * (np.sqrt(-2.0 * np.log(_u01_oc(r0[:, 0]))) * cos2pi(_u01_co(r0[:, 1])))
        counts = np.maximum(counts, N_FLOOR)
        out[j] = (-np.log(counts / i0)).astype(np.float32).reshape(p.shape[1:])
    return out


def _cell0(p, first_row) -> int:
    """Detector cell index of the first cell of a block of rows ``first_row ..`` of (m, R, C)."""
    if int(first_row) < 0:
        raise ValueError(f"first_row must be >= 0, got {first_row}")
    return int(first_row) * int(p.shape[2])


def _check(line_integrals, proj_index):
    p = np.asarray(line_integrals)
    idx = np.asarray(proj_index)
    if p.ndim != 3:
        raise ValueError(f"line_integrals must have shape (m, R, C), got {p.shape}")
    if idx.shape != (p.shape[0],):
        raise ValueError(f"proj_index must have shape ({p.shape[0]},), got {idx.shape}")
    if not np.issubdtype(idx.dtype, np.integer):
        raise TypeError(f"proj_index must be integers, got {idx.dtype}")
    return p, idx


def _has_fp64(rt) -> bool:
    return "cl_khr_fp64" in rt.device.extensions


def lists_flagged_cells(device) -> bool:
    """Whether :func:`add_noise` lists the cells that round 0 leaves open (kernels ``add_noise_listed``
    and ``add_noise_list``) instead of flagging them (``add_noise`` and ``add_noise_rest``, over every
    cell): on Intel's CPU runtime, whose vectoriser runs the flagged pass in whole vectors wherever one
    lane is flagged, not on PoCL (measured: docs/results/noise-interp-intel.md). Either way the output
    is the same bits: which kernel finishes a cell changes nothing in how it is computed."""
    try:
        name = str(device.platform.name)
    except Exception:  # noqa: BLE001 - a device that does not say: the flagged passes
        name = ""
    return drivers.INTEL.matches(name)


def add_noise(line_integrals, proj_index, cfg: NoiseConfig, rt=None, first_row: int = 0) -> np.ndarray:
    """Noisy line integrals from noise-free ones.

    ``cfg.enabled`` is not consulted: the caller decides whether noise is wanted.

    ``first_row`` says that ``line_integrals`` holds detector rows ``first_row ..
    first_row + R - 1`` of each projection (a reconstruction that reads only the rows its
    slices use): a cell's noise is keyed by its place on the whole detector, so the noise of
    a block of rows is exactly those rows of the whole projection's noise.

    Parameters
    ----------
    line_integrals : array_like, shape (m, R, C)
        Noise-free line integrals (dimensionless), one projection per leading index.
    proj_index : array_like of int, shape (m,)
        Projection numbers k in the helical scan; they key the noise.
    cfg : NoiseConfig
        ``i0_photons``, ``electronic_sigma`` and ``seed``.
    rt : Runtime, optional
        OpenCL runtime (default :func:`clrecon.core.runtime.get_runtime`); without float64
        support the NumPy reference computes the same numbers.
    first_row : int
        Detector row of the block's first row (default 0: whole projections).

    Returns
    -------
    numpy.ndarray, shape (m, R, C), float32
        Noisy line integrals, each at most ``ln(i0_photons / N_FLOOR)``.
    """
    p, idx = _check(line_integrals, proj_index)
    rt = rt or get_runtime()
    m = p.shape[0]
    cells = int(np.prod(p.shape[1:]))
    if m == 0 or cells == 0:
        return np.zeros(p.shape, np.float32)
    cell0 = _cell0(p, first_row)
    if not _has_fp64(rt):
        return add_noise_reference(p, idx, cfg, first_row=first_row)
    llvm_math = int("portable" in rt.device.platform.name.lower() or "pocl" in rt.device.platform.name.lower())
    listed = lists_flagged_cells(rt.device)
    names = ("add_noise_listed", "add_noise_list") if listed else ("add_noise", "add_noise_rest")
    knl, knl_rest = (rt.kernel("noise.cl", n, LLVM_MATH=llvm_math) for n in names)
    padded = -(-cells // _LOCAL) * _LOCAL  # pass 1 has no bounds check (it would stop vectorisation)
    flat_in = p.reshape(m, cells)
    out = np.empty((m, cells), np.float32)
    args = (np.int32(padded), np.int64(cell0), np.uint64(cfg.seed), np.float64(cfg.i0_photons),
            np.float64(cfg.electronic_sigma), np.float64(N_FLOOR))
    # blocks of projections keep the device buffers (host memory on a CPU device) small
    block = max(1, BLOCK_CELLS // padded)
    for j0 in range(0, m, block):
        j1 = min(m, j0 + block)
        part = flat_in[j0:j1]
        if padded != cells:
            part = np.pad(part, ((0, 0), (0, padded - cells)))
        d_p = rt.to_device(part, np.float32, "line_integrals")
        d_idx = rt.to_device(idx[j0:j1].astype(np.int64), np.int64, "proj_index")
        d_out = rt.empty((j1 - j0, padded), np.float32)
        if listed:
            # the list of flagged cells' places j * padded + cell: below 2^32, as a block holds at most
            # max(BLOCK_CELLS, padded) cells and padded is an int32
            d_rest = rt.empty(((j1 - j0) * padded,), np.uint32)
            d_count = rt.empty((1,), np.uint32)  # entries in the list
            rt.cl.enqueue_copy(rt.queue, d_count, np.zeros(1, np.uint32))
            ev = knl(rt.queue, (padded, j1 - j0), (_LOCAL, 1), d_p, d_idx, d_out, d_rest, d_count, *args)
            n_list = int(rt.from_device(d_count, (1,), np.uint32, wait_for=[ev])[0])
            if n_list:
                ev = knl_rest(rt.queue, (-(-n_list // _LOCAL) * _LOCAL,), (_LOCAL,), d_p, d_idx, d_out, d_rest,
                              np.int32(n_list), *args)
            d_count.release()
        else:
            d_rest = rt.empty((j1 - j0, padded), np.uint8)
            ev = knl(rt.queue, (padded, j1 - j0), (_LOCAL, 1), d_p, d_idx, d_out, d_rest, *args)
            ev = knl_rest(rt.queue, (padded, j1 - j0), (_LOCAL, 1), d_p, d_idx, d_out, d_rest, *args, wait_for=[ev])
        res = rt.from_device(d_out, (j1 - j0, padded), np.float32, wait_for=[ev])
        out[j0:j1] = res[:, :cells]
        for buf in (d_p, d_idx, d_out, d_rest):
            buf.release()
    return out.reshape(p.shape)


#: Cells per kernel launch (about 2^22: 16 MiB of line integrals, as many of output, and on Intel's
#: runtime as many of the list of open cells).
BLOCK_CELLS = 1 << 22
_LOCAL = 64  # fixed work-group size (PoCL specialises binaries per local size)
