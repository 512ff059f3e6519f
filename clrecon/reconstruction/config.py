"""The reconstruction stage's own section of a scene: grid, targets, methods, kernels and filter.

``[recon]`` is a frozen, self-validating section (:class:`clrecon.core.config.Section`). It
lives with the stage because it validates against the stage's registries (interpolation
methods, ramp-filter windows); :mod:`clrecon.config.scene` composes it into the scene
(``docs/data-flow.md`` "Layering").
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from clrecon.core.config import (
    BOOL,
    F,
    Section,
    _num,
    field_of,
    integer_in,
    number_in,
    one_of,
    zero_or_in,
)
from clrecon.core.errors import SceneError
from clrecon.reconstruction.backprojectors import BACKPROJECTORS
from clrecon.reconstruction.filters import FILTERS as _FILTER_REGISTRY
from clrecon.reconstruction.interpolation import METHODS as _METHOD_REGISTRY
from clrecon.reconstruction.interpolation import default_methods as _default_methods
from clrecon.reconstruction.interpolation.local_linear import LL_MAX_SLOTS, LL_POINT_RULES

METHODS = _METHOD_REGISTRY.names
FILTERS = _FILTER_REGISTRY.names

_f = field_of  # (default, allowed, check, doc)

# Ranges (docs/hostile-inputs.md "Ranges of scene values"): every real grid and kernel fits, and so
# do the coarse test grids (tiny: 32 x 32 voxels of 12 mm); beyond them a value is a typo, a unit
# slip or not a number, refused in one line where it enters.
IMAGE_SIDE = integer_in(2, 4096, "clinical images are 512 x 512, high-resolution ones up to 2048; a voxel size needs 2")
VOXEL_MM = number_in(0.005, 100.0, "mm", "micro-CT 0.005-0.1 mm, clinical 0.3-1 mm, coarse test grids up to tens "
                     "of mm")
#: Largest extent of the reconstruction grid along any axis (mm): a body is under 2 m.
MAX_GRID_MM = 2000.0


#: ``mc``'s z-plane spacing (mm) by default, and at most with ``[recon.mc] plane_dz_mm = 0`` (auto; below it
#: half the slice spacing): about ``demo``'s detector row pitch at the isocentre (1.75 mm).
MC_PLANE_DZ_MM = 2.0

#: The ``mc`` method's registrations (``[recon.mc] registration``, ``beat_registration``).
REGISTRATIONS = ("lucas_kanade", "tvl1", "lucas_kanade_cl")


@dataclass(frozen=True, kw_only=True)
class MotionCompensationConfig(Section):
    """``[recon.mc]``: knobs of the ``mc`` method (motion-compensated FBP, docs/motion-model.md "Knobs").

    Chosen once on ``demo``'s tuning slices (docs/results/mc-study.md "Tuning"); the ranges keep
    every value the method can run with and refuse typos and unit slips.
    """

    SECTION = "recon.mc"

    rounds: int = F(2, integer_in(1, 4, "round 2 gained 5-7 % on demo, round 3 1-2 %; each costs a "
                                     "registration and a backprojection pass"),
                    "registration rounds: 1 registers the barycentric first pass; each further round registers "
                    "the previous round's motion-compensated images")
    downsample: int = F(0, integer_in(0, 4, "0 = auto; the registration window must still hold the heart's walls"),
                        "in-plane factor the registration (and the rounds before the last) works at: 0 (auto) = the "
                        "coarsest grid whose voxels are at most 3 mm, the grid the registrations' knobs were chosen "
                        "on (demo's: 1 there, 2 on the paper scenes' 1-mm grid); 1 = the reconstruction grid, 2 = "
                        "half its voxels along x and y, ...; the last pass is always on the full grid "
                        "(docs/motion-model.md \"Knobs\")")
    registration: str = F("lucas_kanade_cl", one_of(REGISTRATIONS),
                          "the breathing step's registration: 'lucas_kanade_cl' (iterative Lucas-Kanade, windows "
                          "of flow_radius, flow_warps warps, on the engine's OpenCL runtime in the run's process: "
                          "clrecon.reconstruction.motion.lk), 'lucas_kanade' (the same algorithm by scikit-image, "
                          "in a process pool; needs the motion extra) or 'tvl1' (multi-resolution Huber-TV-L1 "
                          "optical flow on the engine's OpenCL runtime, clrecon.reconstruction.motion.flow)")
    beat_registration: str = F("tvl1", one_of(REGISTRATIONS),
                               "the beat step's registration (the same choices): TV-L1 by default, whose "
                               "edge-preserving regulariser lets the heart slide against its surroundings "
                               "(docs/motion-model.md \"Knobs\")")
    flow_radius: int = F(7, integer_in(1, 30, "voxels of the registration grid; the window is 2 r + 1 wide"),
                         "Lucas-Kanade window radius in voxels of the registration grid")
    flow_warps: int = F(10, integer_in(1, 50, "warps per pyramid level; 10 converged on demo"),
                        "Lucas-Kanade warps per pyramid level")
    shrink: bool = F(True, BOOL, "shrink each registered field towards zero where the fixed image's structure "
                     "(its structure tensor over the registration window, less the noise measured from the "
                     "registration's residual) cannot show the motion: the posterior mean under a zero-motion prior "
                     "(clrecon.reconstruction.motion.confidence); no knob to tune")
    resp_degree: int = F(1, integer_in(0, 3, "powers of the amplitude; the paper's targets are 10 amplitudes"),
                         "powers a, .., a^P of the respiratory amplitude in the motion model")
    cardiac_harmonics: int = F(2, integer_in(0, 4, "1 + 2 H coefficients need at least as many cardiac targets"),
                               "harmonics of the cardiac phase in the motion model")
    reference_cardiac_phase: float = F(0.8, number_in(0.0, 0.999, "", "a cardiac phase in [0, 1)"),
                                       "the model's reference state: the cardiac target nearest this phase "
                                       "(0.8: diastasis, the heart moves least)")
    reference_amplitude: float = F(0.45, number_in(0.0, 1.0, "", "amplitude units"),
                                   "the model's reference state: the respiratory target nearest this amplitude "
                                   "(mid amplitude: the smallest largest displacement to any target)")
    plane_dz_mm: float = F(MC_PLANE_DZ_MM, zero_or_in(0.1, 50.0, "mm", "0: auto, min(2 mm, half the slice "
                                                     "spacing); at most about the detector row pitch at the isocentre"),
                           "spacing of the z planes the rows are rebinned onto (a row is read between two planes, "
                           "linearly: a z blur of up to this, which also averages noise along z; where the slices lie "
                           "on planes a motionless voxel reads as the first pass does). 0 (auto): min(2 mm, "
                           "recon.slice_mm / 2) (ReconConfig.mc_knobs). On paper-p010's 1-mm slices 0.5 mm lowered "
                           "mc's noise-free MAE and its dense-bone bias but raised its noisy large-FOV MAE on the "
                           "whole scan, so the default stays 2 mm (docs/motion-model.md, the table of knobs)")
    taper_mm: float = F(2.0, number_in(0.1, 50.0, "mm", "within the SSRB window"),
                        "width of the row weight's fall to 0 at the end of its SSRB window")
    margin_mm: float = F(20.0, number_in(0.0, 200.0, "mm", "beyond the largest displacement along z"),
                         "planes kept beyond the run's first and last slice (a voxel the model moves is read there)")


@dataclass(frozen=True, kw_only=True)
class IterativeConfig(Section):
    """``[recon.mcir]``: knobs of the ``mcir`` method (OS-SART through the motion model, docs/iterative.md).

    The motion model is ``mc``'s (``[recon.mc]``); these knobs set the forward model and the solver.
    """

    SECTION = "recon.mcir"

    epochs: int = F(1, integer_in(1, 100, "each epoch costs one projection and one backprojection of every view"),
                    "OS-SART epochs at most (each visits every motion-state bin once); fewer when an epoch lowers "
                    "the data residual by less than tol. From mc's image (init 'auto') one epoch had the lower MAE "
                    "than 4 in every cell measured (docs/iterative.md \"Solver and stopping rule\")")
    cardiac_bins: int = F(20, integer_in(1, 200, "a bin spans 1/cardiac_bins of the R-R interval"),
                          "cardiac-phase bins the views are grouped into (one warp of the volume per bin)")
    resp_bins: int = F(10, integer_in(1, 100, "a bin spans 1/resp_bins of the amplitude range"),
                       "respiratory-amplitude bins the views are grouped into")
    warp: str = F("pull", one_of(("pull", "push")),
                  "the volume at a state: 'pull' (intensity-preserving: each point keeps its value where the model "
                  "moves it) or 'push' (mass-preserving: W_u^T, density falls where tissue expands)")
    density: bool = F(False, BOOL, "solve a density term too: attenuation linear in the amplitude per voxel (the lungs "
                      "darken as air comes in), in the reference frame; off by default: on demo it measured worse "
                      "(docs/iterative.md)")
    backprojector: str = F("voxel", one_of(("matched", "voxel")),
                           "SART's backprojection: 'voxel' (voxel-driven, a gather: about A^T for smooth data, and "
                           "faster) or 'matched' (the projector's exact transpose, a ray-driven fixed-point scatter); "
                           "how the two compare: docs/iterative.md \"Backprojectors\"")
    plane_dz_mm: float = F(2.0, number_in(0.1, 50.0, "mm", "about the detector row pitch at the isocentre"),
                           "spacing of the iterative volume's z planes")
    voxel_factor: int = F(1, integer_in(1, 4, "each factor of 2 costs about 2x per epoch"),
                          "in-plane subdivision of the reconstruction voxel for the iterative volume (2: half the "
                          "voxel size); the targets are sampled at the reconstruction grid's voxel centres")
    relaxation: float = F(1.0, number_in(0.01, 1.99, "", "SART converges for 0 < relaxation < 2"),
                          "OS-SART relaxation of the first epoch")
    decay: float = F(0.3, number_in(0.0, 10.0, "", "0: a constant relaxation"),
                     "epoch k's relaxation is relaxation / (1 + decay k)")
    tol: float = F(0.01, number_in(0.0, 1.0, "", "relative"),
                   "stop when an epoch lowers the data residual by less than this fraction")
    init: str = F("auto", one_of(("auto", "zero", "first_pass", "mc")),
                  "OS-SART's start: the reference state's target of the first pass (barycentric) or of the mc "
                  "method (needs mc among the methods), resampled to the iterative volume; 'auto': mc's where the "
                  "run has mc, else the first pass's; 'zero': from nothing (docs/iterative.md)")


@dataclass(frozen=True, kw_only=True)
class ReconConfig(Section):
    """Reconstruction grid, targets, methods and filter."""

    SECTION = "recon"

    nx: int = F(512, IMAGE_SIDE, "voxels along x (patient left)")
    ny: int = F(512, IMAGE_SIDE, "voxels along y (posterior)")
    nz: int = F(100, integer_in(1, 20000, "2 m of 0.1 mm slices"), "slices")
    voxel_mm: float = F(1.0, VOXEL_MM, "in-plane voxel size")
    slice_mm: float = F(1.0, VOXEL_MM, "slice spacing")
    cardiac_phases: tuple = _f((0.0, 0.2, 0.4, 0.6, 0.8), "a non-empty list of numbers in [0, 1)",
                               lambda v: isinstance(v, tuple) and len(v) > 0 and all(_num(c) and 0 <= c < 1 for c in v),
                               "target cardiac phases")
    resp_bins: int = F(10, integer_in(1, 50, "the paper uses 10"),
                        "respiratory amplitude bins of equal width; targets at the bin midpoints")
    methods: tuple = _f(_default_methods(), "a non-empty list from " + ", ".join(METHODS),
                        lambda v: isinstance(v, tuple) and len(v) > 0 and all(m in METHODS for m in v)
                        and len(set(v)) == len(v), "reconstruction methods")
    kappa: float = F(1.0, number_in(0.01, 1000.0, "", "0.01 is flat over the cardiac cycle, 1000 narrower than 1 % "
                                    "of it"), "von Mises concentration of the local-linear cardiac kernel")
    sigma: float = F(0.15, number_in(0.001, 10.0, "", "amplitude units: the amplitude spans [0, 1]"),
                     "Gaussian width of the local-linear amplitude kernel")
    local_linear_extrapolate: bool = F(False, BOOL, "true: the paper's plain local-linear fit, which extrapolates "
                                       "along an axis the points do not bracket; false: locally constant there")
    local_linear_points: str = F("quadrants", one_of(LL_POINT_RULES), "local-linear neighbour selection: "
                                 "'quadrants' (local_linear_count nearest per quadrant, the paper's text) or "
                                 "'nearest' (the local_linear_count nearest overall, the paper's Figure 2B caption)")
    local_linear_count: int = F(2, integer_in(1, LL_MAX_SLOTS, "the kernel's slots per row"),
                                 "local-linear points per quadrant ('quadrants': 4 x count slots) or in all "
                                 "('nearest')")
    cardiac_distance_scale: float = F(1.0, number_in(0.001, 1000.0, "", "amplitude units per cardiac cycle"),
                                      "s, dimensionless (amplitude units per cardiac cycle): the phase-space "
                                      "distance is sqrt((s dc)^2 + da^2) for neighbour selection "
                                      "(local_linear, nearest, barycentric's two-nearest fallback) and barycentric's "
                                      "Delaunay triangulation runs in (s c, a); 1 = unscaled, as the paper")
    max_turns: int = F(0, integer_in(0, 10000, "0: every candidate; a scan within its length limit has fewer turns"),
                       "0: every candidate turn within the SSRB window; N > 0: only the N candidates nearest in z per "
                       "(slice, view), for every method")
    candidate_window_mm: float = F(0.0, zero_or_in(0.1, MAX_GRID_MM, "mm", "0: the SSRB-exact window; the "
                                                   "paper's is ~28 mm"),
                                   "candidate window |slice z - source z| (mm); 0: the SSRB-exact window (no SSRB "
                                   "row off the detector); the 5DCT paper: half the detector width "
                                   "projected to the isocentre, ~28 mm (rows off the detector clamp to its edge)")
    truth_free: bool = F(False, BOOL, "cross-validate every method in sinogram space (no truth needed): "
                         "results.json['truth_free'] and a report section (clrecon.evaluation.truth_free)")
    filter: str = _f("ram-lak", "one of " + ", ".join(FILTERS), lambda x: x in FILTERS, "ramp filter window")
    backprojector: str = F("direct", one_of(BACKPROJECTORS), "FBP path (clrecon.reconstruction.backprojectors): "
                           "'direct' fan-beam backprojection of every view (the paper runs), or 'parallel-rebin' "
                           "(each interpolated sinogram rebinned to V/2 parallel views over pi, then parallel FBP; "
                           "needs an even views_per_rotation)")
    volume_dtype: str = F("float32", one_of(("float32", "float16")), "on-disk dtype of the run's volumes: "
                          "'float16' halves volumes.h5 (values within 2^-11 relative, <= 0.5 HU below 2048 HU; "
                          "the metrics are computed from what is stored)")
    volume_compression: str = F("auto", one_of(("auto", "lzf", "none")),
                                "compression of volumes.h5's dataset files and their units: 'lzf' (LZF + byte "
                                "shuffle, 2-3.5x smaller, ~80 MB/s to write on one core), 'none', or 'auto' (lzf "
                                "when the run's volumes are >= 4 GiB raw, as the paper scenes; none below: demo, "
                                "tiny); the values stored are the same either way")
    mc: MotionCompensationConfig = _f(MotionCompensationConfig(), "a [recon.mc] table",
                                      lambda v: isinstance(v, MotionCompensationConfig),
                                      "knobs of the mc method (docs/motion-model.md \"Knobs\")")
    mcir: IterativeConfig = _f(IterativeConfig(), "a [recon.mcir] table", lambda v: isinstance(v, IterativeConfig),
                               "knobs of the mcir method (docs/iterative.md \"Knobs\")")
    small_fov_mm: tuple = _f((-70.0, 85.0, -100.0, 40.0), f"[x_min, x_max, y_min, y_max] with min < max, each in "
                             f"[{-MAX_GRID_MM:g}, {MAX_GRID_MM:g}] mm (a box in the patient)",
                             lambda v: isinstance(v, tuple) and len(v) == 4
                             and all(_num(x) and abs(x) <= MAX_GRID_MM for x in v) and v[0] < v[1] and v[2] < v[3],
                             "box around the heart (mm, LPS): the phantom's epicardial fat at every state + 10 mm")

    def check(self) -> None:
        for key, n, size in (("nx", self.nx, self.voxel_mm), ("ny", self.ny, self.voxel_mm),
                             ("nz", self.nz, self.slice_mm)):
            if n * size > MAX_GRID_MM:
                what = "voxel_mm" if key != "nz" else "slice_mm"
                raise SceneError(f"recon.{key} x recon.{what} = {n} x {size:g} mm = {n * size:g} mm: the grid must "
                                 f"span at most {MAX_GRID_MM:g} mm along each axis (a body is under 2 m)")
        if self.local_linear_points == "quadrants" and 4 * self.local_linear_count > LL_MAX_SLOTS:
            raise SceneError(f"recon.local_linear_count = {self.local_linear_count}: with local_linear_points = "
                             f"'quadrants' must be at most {LL_MAX_SLOTS // 4} (4 x count <= {LL_MAX_SLOTS} slots)")

    @property
    def mc_knobs(self) -> MotionCompensationConfig:
        """``[recon.mc]`` with what its 0 (auto) values derive from this grid resolved: ``plane_dz_mm`` =
        min(:data:`MC_PLANE_DZ_MM`, ``slice_mm`` / 2). What ``mc``'s code takes as its knobs."""
        if self.mc.plane_dz_mm:
            return self.mc
        return dataclasses.replace(self.mc, plane_dz_mm=min(MC_PLANE_DZ_MM, self.slice_mm / 2))

    @property
    def resp_targets(self) -> tuple[float, ...]:
        """Target amplitudes: midpoints of ``resp_bins`` equal bins of [0, 1]."""
        return tuple((i + 0.5) / self.resp_bins for i in range(self.resp_bins))

    @property
    def fov_radius_mm(self) -> float:
        """Radius (mm) of the reconstruction circle inscribed in the image grid."""
        return 0.5 * min(self.nx, self.ny) * self.voxel_mm
