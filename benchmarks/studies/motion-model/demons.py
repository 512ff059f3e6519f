"""ITK's fast symmetric-forces demons as a registration of the motion model (study code, outside the wheel).

ITK's fast symmetric-forces demons (Vercauteren et al., NeuroImage 45:S61, 2009;
``SimpleITK.FastSymmetricForcesDemonsRegistrationFilter``) in a coarse-to-fine pyramid, with
Gaussian regularisation of the displacement field (elastic-like), on images clipped to a HU
window and pre-smoothed. The alternative the study measured against the shipped Lucas-Kanade
registration (docs/results/mc-study.md "Registration": it creeps on larger shifts). It plugs into
the package's registration as a config with a ``register`` method
(:func:`clrecon.reconstruction.motion.registration.register`,
``estimate.separable_fields(..., cfg=DemonsConfig(...))``), in the package's convention:
``moving(x + u(x)) ~ fixed(x)``, u (3, nz, ny, nx) float32 mm (dx, dy, dz).

Determinism: no random sampling; ITK's thread count is pinned (``threads``) so that a result does
not depend on the machine's core count; that it is independent of the thread count itself has
not been checked. Needs SimpleITK (in the test extra).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


def _sitk():
    """SimpleITK, imported when the demons run (one line naming it if missing)."""
    try:
        import SimpleITK
    except ImportError as e:
        raise ImportError(f"the study's demons need SimpleITK ({e}): pip install SimpleITK") from None
    return SimpleITK


@dataclass(frozen=True, kw_only=True)
class DemonsConfig:
    """Knobs of the demons (docs/motion-model.md "Knobs" for the values tried on ``demo``).

    iterations : demons iterations per pyramid level, coarse to fine (one entry per level).
    shrink : in-plane shrink factor per level (z is never shrunk: slices are few and thick).
    field_sigma_mm : Gaussian smoothing (std, mm) of the displacement field after each iteration.
    image_sigma_mm : Gaussian pre-smoothing (std, mm) of both images (0: none).
    hu_window : (lo, hi) HU the images are clipped to before registration.
    max_step_mm : largest update per iteration (mm; 0: ITK's default, unbounded).
    threads : ITK threads (0: ITK's default).
    """

    iterations: tuple = (60, 40)
    shrink: tuple = (2, 1)
    field_sigma_mm: float = 4.0
    image_sigma_mm: float = 2.0
    hu_window: tuple = (-900.0, 600.0)
    max_step_mm: float = 1.0
    threads: int = 2

    def __post_init__(self):
        if len(self.iterations) != len(self.shrink) or not self.iterations:
            raise ValueError(f"iterations {self.iterations!r} and shrink {self.shrink!r}: one entry per level each")
        if any(int(i) < 0 for i in self.iterations) or any(int(s) < 1 for s in self.shrink):
            raise ValueError("iterations must be >= 0 and shrink factors >= 1")
        for name in ("field_sigma_mm", "image_sigma_mm", "max_step_mm"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise ValueError(f"{name} = {v!r}: must be a finite number >= 0")
        lo, hi = self.hu_window
        if not lo < hi:
            raise ValueError(f"hu_window = {self.hu_window!r}: must be (lo, hi) with lo < hi")

    def register(self, f: np.ndarray, m: np.ndarray, spacing_mm: tuple, origin_mm: tuple, initial=None) -> np.ndarray:
        """u (3, nz, ny, nx) float32 mm with ``m(x + u(x)) ~ f(x)``; ``initial``: a starting field
        (e.g. a neighbouring state's). Called by the package's ``register`` after its checks."""
        sitk = _sitk()
        if self.threads > 0:
            sitk.ProcessObject.SetGlobalDefaultNumberOfThreads(int(self.threads))
        fi = _prepare(_image(f, spacing_mm, origin_mm), self)
        mi = _prepare(_image(m, spacing_mm, origin_mm), self)
        field = None
        if initial is not None:
            u0 = np.asarray(initial, np.float64)
            if u0.shape != (3,) + f.shape:
                raise ValueError(f"initial: expected shape {(3,) + f.shape}, got {u0.shape}")
            field = sitk.GetImageFromArray(np.moveaxis(u0, 0, -1), isVector=True)
            field.CopyInformation(fi)
        for iters, shrink in zip(self.iterations, self.shrink, strict=True):
            factors = [int(shrink), int(shrink), 1]
            fl = sitk.Shrink(fi, factors) if shrink > 1 else fi
            ml = sitk.Shrink(mi, factors) if shrink > 1 else mi
            if field is not None:  # carry the field to this level's grid
                field = sitk.Resample(field, fl, sitk.Transform(), sitk.sitkLinear, 0.0, sitk.sitkVectorFloat64)
            else:
                field = sitk.Image(fl.GetSize(), sitk.sitkVectorFloat64, 3)
                field.CopyInformation(fl)
            if iters == 0:
                continue
            demons = sitk.FastSymmetricForcesDemonsRegistrationFilter()
            demons.SetNumberOfIterations(int(iters))
            demons.SetSmoothDisplacementField(True)
            demons.SetStandardDeviations(float(self.field_sigma_mm))
            demons.SetUseImageSpacing(True)
            if self.max_step_mm > 0:
                demons.SetMaximumUpdateStepLength(float(self.max_step_mm))
            field = demons.Execute(fl, ml, field)
        if field.GetSize() != fi.GetSize():
            field = sitk.Resample(field, fi, sitk.Transform(), sitk.sitkLinear, 0.0, sitk.sitkVectorFloat64)
        u = sitk.GetArrayFromImage(field)  # (nz, ny, nx, 3)
        return np.ascontiguousarray(np.moveaxis(u, -1, 0), np.float32)


def _image(vol: np.ndarray, spacing: tuple, origin: tuple):
    sitk = _sitk()
    img = sitk.GetImageFromArray(np.ascontiguousarray(vol, np.float32))
    img.SetSpacing(tuple(float(s) for s in spacing))
    img.SetOrigin(tuple(float(o) for o in origin))
    return img


def _prepare(img, cfg: DemonsConfig):
    sitk = _sitk()
    lo, hi = cfg.hu_window
    out = sitk.Clamp(img, sitk.sitkFloat32, float(lo), float(hi))
    if cfg.image_sigma_mm > 0:
        out = sitk.SmoothingRecursiveGaussian(out, float(cfg.image_sigma_mm))
    return out
