"""Deformable registration of reconstructed volumes, for the motion model (scikit-image).

A thin wrapper: NumPy volumes in, displacement fields out, in the package's conventions
(volumes ``(nz, ny, nx)`` in HU on the reconstruction grid, fields ``(3, nz, ny, nx)`` float32
mm with components (dx, dy, dz)). :class:`FlowConfig` (``[recon.mc] registration = "lucas_kanade"``;
the default, ``"lucas_kanade_cl"``, is the same algorithm on OpenCL, :mod:`~clrecon.reconstruction.motion.lk`)
is scikit-image's iterative Lucas-Kanade optical flow (``skimage.registration.optical_flow_ilk``;
Le Besnerais & Champagnat, ICIP 2005), a least-squares flow in a window around each voxel,
coarse to fine with warps, on images clipped to a HU window (and optionally pre-smoothed: the
streaks of a first-pass 5D image and the lung's density change then pull less). Its window
averages out what the demons' voxel-wise forces follow (streaks), and it converges on large
shifts in a few warps where the demons creep (measured: docs/results/mc-study.md "Registration").

Another registration plugs in as a config object with a ``register(fixed, moving, spacing_mm,
origin_mm, initial)`` method returning the field in this module's convention: the motion-model
study's ITK demons (``benchmarks/studies/motion-model/demons.py``, outside the wheel) does.

Convention: ``register(fixed, moving)`` returns u on the fixed grid with
``moving(x + u(x)) ~ fixed(x)``: u maps each fixed-image point to where it is in the moving
image. With the reference state's volume as ``fixed`` and a target's as ``moving``, u is the
motion-model field u(x_ref; target) of :mod:`clrecon.reconstruction.motion.model`.

Determinism: the registration does not sample at random; a repeated call gives the same bits
(tests/reconstruction/test_motion_compensation.py).
"""

from __future__ import annotations

import math
import os
from concurrent.futures import as_completed
from dataclasses import dataclass

import numpy as np
import scipy.ndimage

from clrecon.core.errors import ClreconError
from clrecon.reconstruction.motion.flow import TVL1Config, register_tvl1
from clrecon.reconstruction.motion.lk import LKConfig, register_lk

#: The extra that installs the registration libraries (pyproject.toml ``[project.optional-dependencies]``).
EXTRA = "pip install 'clrecon[motion]'"


def require(module: str = "skimage"):
    """The registration library ``module`` (``skimage`` for the optical flow), imported here so that
    the rest of clrecon runs without it; one line if missing."""
    import importlib

    try:
        return importlib.import_module(module)
    except ImportError as e:
        raise ClreconError(f"the mc method registers its first pass with {module}, which is not installed "
                           f"({e}): {EXTRA}") from None


@dataclass(frozen=True, kw_only=True)
class FlowConfig:
    """Knobs of the Lucas-Kanade registration (:func:`register` with this config).

    radius : window radius in voxels (the window is (2 radius + 1) voxels along every axis).
    num_warp : warps per pyramid level.
    gaussian : a Gaussian window instead of a flat one.
    image_sigma_mm : Gaussian pre-smoothing (std, mm) of both images (0: none).
    hu_window : (lo, hi) HU the images are clipped to.
    """

    radius: int = 7
    num_warp: int = 10
    gaussian: bool = False
    image_sigma_mm: float = 0.0
    hu_window: tuple = (-900.0, 600.0)

    def __post_init__(self):
        if not (isinstance(self.radius, int) and self.radius >= 1):
            raise ValueError(f"radius = {self.radius!r}: must be an integer >= 1")
        if not (isinstance(self.num_warp, int) and self.num_warp >= 1):
            raise ValueError(f"num_warp = {self.num_warp!r}: must be an integer >= 1")
        if not (math.isfinite(self.image_sigma_mm) and self.image_sigma_mm >= 0):
            raise ValueError(f"image_sigma_mm = {self.image_sigma_mm!r}: must be a finite number >= 0")
        lo, hi = self.hu_window
        if not lo < hi:
            raise ValueError(f"hu_window = {self.hu_window!r}: must be (lo, hi) with lo < hi")


def _flow(f: np.ndarray, m: np.ndarray, spacing_mm: tuple, cfg: FlowConfig) -> np.ndarray:
    lo, hi = cfg.hu_window
    ims = []
    for v in (f, m):
        a = np.clip(np.asarray(v, np.float64), lo, hi) / (hi - lo)
        if cfg.image_sigma_mm > 0:
            a = scipy.ndimage.gaussian_filter(a, [cfg.image_sigma_mm / s for s in spacing_mm[::-1]], mode="nearest")
        ims.append(a.astype(np.float32))
    # optical_flow_ilk(reference, moving) returns v (per axis z, y, x, voxels) with
    # moving(x + v(x)) ~ reference(x): the convention of register()
    flow = require("skimage.registration").optical_flow_ilk
    v = flow(ims[0], ims[1], radius=cfg.radius, num_warp=cfg.num_warp, gaussian=cfg.gaussian, prefilter=False)
    return np.stack([v[2] * spacing_mm[0], v[1] * spacing_mm[1], v[0] * spacing_mm[2]]).astype(np.float32)


def register(fixed, moving, spacing_mm: tuple, origin_mm: tuple = (0.0, 0.0, 0.0),
             cfg: FlowConfig | None = None, initial=None) -> np.ndarray:
    """Displacement field u with ``moving(x + u(x)) ~ fixed(x)``, on the fixed grid.

    Parameters
    ----------
    fixed, moving : (nz, ny, nx) arrays
        Volumes on one grid (HU), finite.
    spacing_mm : (dx, dy, dz)
        Voxel spacing (mm) along x, y, z.
    origin_mm : (x0, y0, z0)
        Centre of voxel (0, 0, 0) (mm); handed to a plugged-in registration (fields are relative).
    cfg : FlowConfig (default), TVL1Config (:mod:`clrecon.reconstruction.motion.flow`), LKConfig
        (:mod:`clrecon.reconstruction.motion.lk`), or a config with a ``register`` method (module docstring)
    initial : (3, nz, ny, nx) array, optional
        Starting field (mm), e.g. a neighbouring state's (a plugged-in registration only).

    Returns
    -------
    (3, nz, ny, nx) float32: (dx, dy, dz) mm, finite: a registration that returns a non-finite value
    raises RuntimeError naming it (a defect of the registration; its inputs were checked finite).
    """
    cfg = cfg or FlowConfig()
    f = np.asarray(fixed)
    m = np.asarray(moving)
    if f.ndim != 3 or m.shape != f.shape:
        raise ValueError(f"fixed {f.shape} and moving {m.shape}: expected two (nz, ny, nx) volumes of one shape")
    if not (np.all(np.isfinite(f)) and np.all(np.isfinite(m))):
        raise ValueError("fixed and moving must be finite")
    if len(spacing_mm) != 3 or min(spacing_mm) <= 0:
        raise ValueError(f"spacing_mm = {spacing_mm!r}: three spacings > 0 (x, y, z)")
    spacing = tuple(float(s) for s in spacing_mm)
    kind = next((k for k in _BUILT_IN if isinstance(cfg, k)), None)
    if kind is not None:
        if initial is not None:
            raise ValueError(f"initial: the {_BUILT_IN[kind][0]} registration starts from zero")
        u = _BUILT_IN[kind][1](f, m, spacing, cfg)
    elif callable(getattr(cfg, "register", None)):
        u = cfg.register(f, m, spacing, tuple(float(o) for o in origin_mm), initial)
    else:
        raise TypeError(f"cfg: expected a FlowConfig, a TVL1Config, an LKConfig or a registration config with a "
                        f"register() method, got {type(cfg).__name__}")
    bad = ~np.isfinite(u)
    if bad.any():  # never hand a later step NaN: a field is finite or the run stops here, naming the registration
        raise RuntimeError(f"registration {_BUILT_IN[kind][0] if kind else type(cfg).__name__} returned non-finite "
                           f"displacements in {int(bad.any(axis=0).sum())} of {bad[0].size} voxels of a "
                           f"{'x'.join(map(str, f.shape[::-1]))} pair: a defect of that registration, not of the "
                           f"data (its inputs were finite); please report it with the scene")
    return u


#: The built-in registrations' config types (a subclass counts as its base): (name in messages, function).
_BUILT_IN = {TVL1Config: ("TV-L1", register_tvl1), LKConfig: ("Lucas-Kanade (OpenCL)", register_lk),
             FlowConfig: ("Lucas-Kanade (scikit-image)", _flow)}


#: Peak bytes of one Lucas-Kanade registration per voxel of its volumes, above its process's
#: resident set after the imports (:func:`register` in a spawned worker of ``mc``'s pool: the
#: clipped float64 copies, then ``optical_flow_ilk``'s pyramid, warped image, gradients and the
#: (3, 3) systems per voxel in float32, about 70 float32 volumes). The largest of the worker's
#: high-water marks measured above its baseline on 64 x 64 x 16 to 512 x 512 x 40 voxels
#: (``benchmarks/studies/motion-model/registration_memory.py``: 245-283 bytes per voxel, a second
#: registration in the same worker no more), rounded up; it errs high by up to 18 % on the largest
#: (docs/results/code-history.md "One Lucas-Kanade registration's memory").
FLOW_BYTES_PER_VOXEL = 290
#: At most this many registration processes (each needs FLOW_BYTES_PER_VOXEL per voxel).
MAX_WORKERS = 4
#: Volumes smaller than this (voxels) register in the run's process: starting a spawned worker
#: (importing NumPy, SciPy, scikit-image: 2-6 s of CPU on a shared 2-core machine) costs more than
#: it saves (``tiny``'s 32 x 32 x 2 registers in 0.3 s; ``demo``'s 128 x 128 x 16, 262 144 voxels, in 1.4 s).
POOL_MIN_VOXELS = 65536


def registration_workers(n_voxels: int, cores: int | None = None, available_bytes: int | None = None) -> int:
    """How many registrations to run at once: one per core, at most :data:`MAX_WORKERS`, and as
    many as half the memory available holds (:data:`FLOW_BYTES_PER_VOXEL` each); at least 1, and 1
    below :data:`POOL_MIN_VOXELS`."""
    if n_voxels < POOL_MIN_VOXELS:
        return 1
    if cores is None:
        cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    if available_bytes is None:
        try:
            available_bytes = os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
        except (ValueError, OSError, AttributeError):  # pragma: no cover - non-POSIX
            available_bytes = 0
    by_memory = int(0.5 * available_bytes // max(1, FLOW_BYTES_PER_VOXEL * n_voxels))
    return max(1, min(int(cores), MAX_WORKERS, by_memory))


def register_to_reference(volumes, reference: int, spacing_mm: tuple, cfg: FlowConfig | None = None,
                          order=None, progress=None, pool=None) -> np.ndarray:
    """u(x_ref; s_i) of every volume (n, nz, ny, nx) against ``volumes[reference]``: (n, 3, nz, ny, nx).

    ``order``: a sequence of (i, j) pairs, each volume i started from volume j's field (j done
    before, or -1 for a zero start; a plugged-in registration that takes a start only); default
    every i from zero. The reference's own field is 0.
    ``progress``: optional ``update(n)`` counter. ``pool``: optional ``concurrent.futures``
    executor (spawned processes: :func:`clrecon.core.resources.spawned_pool`) that runs the
    registrations of a default ``order`` at once; each is the same call on the same arrays, so
    the fields are the same bits as one after the other (tests/reconstruction/test_motion_compensation.py).
    """
    v = np.asarray(volumes)
    if v.ndim != 4:
        raise ValueError(f"volumes: expected (n, nz, ny, nx), got {v.shape}")
    n = v.shape[0]
    if not 0 <= reference < n:
        raise ValueError(f"reference = {reference}: must index one of the {n} volumes")
    out = np.zeros((n, 3) + v.shape[1:], np.float32)
    if pool is not None and order is None and not isinstance(cfg, (TVL1Config, LKConfig)):  # OpenCL uses every core
        futures = {pool.submit(register, v[reference], v[i], spacing_mm, cfg=cfg): i
                   for i in range(n) if i != reference}
        for fut in as_completed(futures):
            out[futures[fut]] = fut.result()
            if progress is not None:
                progress.update(1)
        return out
    pairs = [(i, -1) for i in range(n)] if order is None else list(order)
    done = {reference}
    for i, j in pairs:
        if i == reference:
            continue
        if j >= 0 and j not in done:
            raise ValueError(f"order: volume {i} starts from {j}, which is not registered before it")
        out[i] = register(v[reference], v[i], spacing_mm, cfg=cfg, initial=out[j] if j >= 0 else None)
        done.add(i)
        if progress is not None:
            progress.update(1)
    return out
