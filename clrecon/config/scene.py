"""Scenes: TOML files validated into immutable config objects (stage 0 of the pipeline).

A scene says what scanner, scan protocol, breathing and heart rhythm, phantom, noise and
reconstruction to run. Every section is a frozen dataclass; derived quantities (collimation
at the isocentre, table feed, number of projections) are properties, never stored twice.

Errors name the key, the bad value and what is allowed; unknown keys are errors that
suggest the nearest valid key. Built-in scenes live in ``clrecon/config/scenes/*.toml``.
"""

from __future__ import annotations

import dataclasses
import difflib
import hashlib
import json
import math
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any, ClassVar

try:  # Python >= 3.11
    import tomllib
except ModuleNotFoundError:  # pragma: no cover
    import tomli as tomllib

from clrecon.config import dicom_ct_pd
from clrecon.core.config import (
    BOOL,
    FRAC,
    NONNEG,
    NONNEGINT,
    NUM,
    POS,
    POSINT,
    F,
    Section,
    _num,
    _pos,
    _posint,
    field_of,
    one_of,
)
from clrecon.core.detector import DETECTORS, DetectorModel, detector_for
from clrecon.core.errors import SceneError
from clrecon.core.versions import PROJECTOR_VERSION
from clrecon.simulation.phantom_sources import PHANTOM_SOURCES, PhantomConfig

SCENE_DIR = Path(__file__).resolve().parent / "scenes"

#: The signal trace spans max(TRACE_MIN_S, the longest scan) + TRACE_MARGIN_S seconds.
TRACE_MIN_S = 60.0
TRACE_MARGIN_S = 5.0

# the registries' names (interpolation methods: clrecon.reconstruction.interpolation; ramp-filter windows:
# clrecon.reconstruction.filters); those packages import only clrecon.core
from clrecon.reconstruction.filters import FILTERS as _FILTER_REGISTRY  # noqa: E402
from clrecon.reconstruction.interpolation import METHODS as _METHOD_REGISTRY  # noqa: E402
from clrecon.reconstruction.interpolation.local_linear import LL_MAX_SLOTS, LL_POINT_RULES  # noqa: E402

METHODS = _METHOD_REGISTRY.names
FILTERS = _FILTER_REGISTRY.names
RHYTHMS = ("periodic", "hrv", "af", "pvc")
SCAN_SOURCES = ("simulated", "dicom-ct-pd")
STR = ("a string", lambda x: isinstance(x, str))


_f = field_of  # (default, allowed, check, doc)


# ---------------------------------------------------------------------------------------
@dataclass(frozen=True, kw_only=True)
class ScannerConfig(Section):
    """CT scanner hardware (Table 1 of the paper by default). Lengths in mm."""

    SECTION = "scanner"

    sid_mm: float = F(595.0, POS, "source to isocentre distance")
    sdd_mm: float = F(1085.6, POS, "source to detector distance")
    n_cols: int = F(900, POSINT, "detector columns")
    n_rows: int = F(64, POSINT, "detector rows")
    col_pitch_mm: float = F(0.8, POS, "detector column pitch at the detector")
    row_pitch_mm: float = F(0.8, POS, "detector row pitch at the detector")
    views_per_rotation: int = F(984, POSINT, "projections per rotation")
    rotation_time_s: float = F(0.3, POS, "seconds per rotation")
    detector: str = F("flat", one_of(DETECTORS.names), "detector model (clrecon.core.detector)")

    @property
    def detector_model(self) -> DetectorModel:
        """The detector model (:mod:`clrecon.core.detector`) every stage asks for geometry."""
        return detector_for(self)

    @property
    def collimation_iso_mm(self) -> float:
        """W = N_rows * row_pitch * SID / SDD (mm)."""
        return self.detector_model.collimation_iso_mm

    @property
    def fov_radius_mm(self) -> float:
        """Radius at the isocentre of the circle every column sees (mm)."""
        return self.detector_model.fov_radius_mm


@dataclass(frozen=True, kw_only=True)
class ScanConfig(Section):
    """Helical protocol. Either ``coverage_mm`` or ``n_projections`` fixes the scan length.

    Coverage = source travel + W (docs/conventions.md "Helical scan length"); projections = round(travel/h * N) + 1.
    """

    SECTION = "scan"

    pitches: tuple = _f((0.02,), "a non-empty list of numbers in (0, 2]",
                        lambda v: isinstance(v, tuple) and len(v) > 0 and all(_pos(p) and p <= 2 for p in v),
                        "table feed per rotation / collimation W; one scan per pitch")
    coverage_mm: float = F(119.7, POS, "longitudinal coverage = travel + W")
    n_projections: int = F(0, NONNEGINT, "if > 0: the scan length in projections (overrides coverage_mm)")
    z_centre_mm: float = F(0.0, NUM, "table position of the scan centre")
    start_angle_deg: float = F(0.0, NUM, "gantry angle of the first view")
    source: str = F("simulated", one_of(SCAN_SOURCES), "'simulated' (the phantom) or 'dicom-ct-pd' (a measured "
                    "scan: projections = a folder of DICOM-CT-PD files, one projection each; docs/measured-data.md)")
    projections: str = F("", STR, "dicom-ct-pd: the folder of projection files (relative: to the scene file)")
    timestamp_unit: str = F("ms", one_of(("ms", "s")), "dicom-ct-pd: unit of the Timestamp tag (7033,1067)")
    flip_channels: bool = F(False, BOOL, "dicom-ct-pd: reverse the channel order of every projection "
                            "(docs/measured-data.md 'Pixel layout')")
    flip_rows: bool = F(False, BOOL, "dicom-ct-pd: reverse the detector-row order of every projection")

    PATH_KEYS: ClassVar[tuple] = ("projections",)

    def check(self) -> None:
        if self.source == "dicom-ct-pd" and not self.projections:
            raise SceneError("scan.projections = '': scan.source = 'dicom-ct-pd' needs the folder of projection files")

    def feed_mm(self, scanner: ScannerConfig, pitch: float) -> float:
        """Table feed per rotation h = pitch * W (mm)."""
        return pitch * scanner.collimation_iso_mm

    def projection_count(self, scanner: ScannerConfig, pitch: float) -> int:
        if self.n_projections > 0:
            return self.n_projections
        travel = max(self.coverage_mm - scanner.collimation_iso_mm, 0.0)
        return int(round(travel / self.feed_mm(scanner, pitch) * scanner.views_per_rotation)) + 1

    def travel_mm(self, scanner: ScannerConfig, pitch: float) -> float:
        n = self.projection_count(scanner, pitch)
        return (n - 1) * self.feed_mm(scanner, pitch) / scanner.views_per_rotation

    def z_start_mm(self, scanner: ScannerConfig, pitch: float) -> float:
        return self.z_centre_mm - self.travel_mm(scanner, pitch) / 2.0

    def duration_s(self, scanner: ScannerConfig, pitch: float) -> float:
        return self.projection_count(scanner, pitch) * scanner.rotation_time_s / scanner.views_per_rotation


@dataclass(frozen=True, kw_only=True)
class SignalsConfig(Section):
    """Breathing and heart rhythm (docs/algorithms.md "Breathing and heart rhythm"; Lujan 1999 breathing model)."""

    SECTION = "signals"

    seed: int = F(1, NONNEGINT, "seed of the breathing and rhythm irregularities")
    resp_period_s: float = F(5.0, POS, "mean breathing period")
    resp_period_cv: float = _f(0.15, "a number in [0, 0.5]", lambda x: _num(x) and 0 <= x <= 0.5,
                               "cycle-to-cycle coefficient of variation of the period")
    resp_depth_cv: float = _f(0.15, "a number in [0, 0.5]", lambda x: _num(x) and 0 <= x <= 0.5,
                              "cycle-to-cycle coefficient of variation of the depth")
    resp_exponent: int = _f(2, "an integer in 1..4", lambda x: _posint(x) and x <= 4,
                            "n in cos^(2n): larger gives a longer end-exhale dwell")
    resp_drift: float = _f(0.05, "a number in [0, 0.5]", lambda x: _num(x) and 0 <= x <= 0.5,
                           "slow baseline drift, as a fraction of the mean depth, peak to peak")
    breath_hold: bool = F(False, BOOL, "no breathing: amplitude constant at breath_hold_amplitude")
    breath_hold_amplitude: float = F(0.5, FRAC, "normalised amplitude during a breath hold")
    rr_s: float = _f(0.75, "a number in [0.3, 2.0]", lambda x: _num(x) and 0.3 <= x <= 2.0, "mean R-R interval")
    rhythm: str = _f("periodic", "one of " + ", ".join(RHYTHMS), lambda x: x in RHYTHMS,
                     "periodic; hrv (3 % sinus variability); af (i.i.d. R-R); pvc (ectopic beats)")
    rr_cv: float = _f(0.0, "a number in [0, 0.4]", lambda x: _num(x) and 0 <= x <= 0.4,
                      "R-R coefficient of variation for hrv/af (0: the rhythm's default)")
    ectopic_rate: float = _f(0.0, "a number in [0, 0.5]", lambda x: _num(x) and 0 <= x <= 0.5,
                             "fraction of beats that are premature (pvc rhythm)")
    frame_time_s: float = F(0.0, NONNEG, "0: continuous motion; > 0: motion frozen in phantom frames of this length")
    breathing_trace: str = F("", STR, "recorded breathing trace (Varian RPM .vxp, or CSV time_s,amplitude) in place of "
                             "the breathing model (clrecon.scan.recorded)")
    ecg_trace: str = F("", STR, "recorded ECG (CSV of R-peak times r_peak_s, or a WFDB record .hea) in place of the "
                       "rhythm model")
    trace_align: str = F("offset", one_of(("offset", "beam-on")), "breathing trace time of scan time 0: "
                         "trace_offset_s, or the first beam-on (ttlin = 1) sample of the .vxp plus trace_offset_s")
    trace_offset_s: float = F(0.0, NUM, "breathing trace time (s) at scan time 0 (added to the beam-on time "
                              "with trace_align = 'beam-on')")
    ecg_offset_s: float = F(0.0, NUM, "ECG time (s) at scan time 0")
    breathing_inhale: str = F("up", one_of(("up", "down")), "the recorded amplitude rises ('up') or falls ('down') "
                              "on inhalation")

    PATH_KEYS: ClassVar[tuple] = ("breathing_trace", "ecg_trace")


@dataclass(frozen=True, kw_only=True)
class NoiseConfig(Section):
    """Poisson quanta + Gaussian electronic noise, seeded per projection."""

    SECTION = "noise"

    enabled: bool = F(True, BOOL, "add noise")
    i0_photons: float = _f(2.0e5, "a number in (0, 1e15]", lambda x: _pos(x) and x <= 1e15,
                           "unattenuated photons per detector cell (above 1e15 NumPy's Poisson sampler fails)")
    electronic_sigma: float = F(5.0, NONNEG, "std of the electronic noise, in photon-equivalent counts")
    seed: int = F(7, NONNEGINT, "noise seed")
    also_noise_free: bool = F(True, BOOL, "also reconstruct the noise-free projections (the paper's Table 2)")


@dataclass(frozen=True, kw_only=True)
class ReconConfig(Section):
    """Reconstruction grid, targets, methods and filter."""

    SECTION = "recon"

    nx: int = F(512, POSINT, "voxels along x (patient left)")
    ny: int = F(512, POSINT, "voxels along y (posterior)")
    nz: int = F(100, POSINT, "slices")
    voxel_mm: float = F(1.0, POS, "in-plane voxel size")
    slice_mm: float = F(1.0, POS, "slice spacing")
    cardiac_phases: tuple = _f((0.0, 0.2, 0.4, 0.6, 0.8), "a non-empty list of numbers in [0, 1)",
                               lambda v: isinstance(v, tuple) and len(v) > 0 and all(_num(c) and 0 <= c < 1 for c in v),
                               "target cardiac phases")
    resp_bins: int = _f(10, "an integer in 1..50", lambda x: _posint(x) and x <= 50,
                        "respiratory amplitude bins of equal width; targets at the bin midpoints")
    methods: tuple = _f(METHODS, "a non-empty list from " + ", ".join(METHODS),
                        lambda v: isinstance(v, tuple) and len(v) > 0 and all(m in METHODS for m in v)
                        and len(set(v)) == len(v), "reconstruction methods")
    kappa: float = F(1.0, POS, "von Mises concentration of the local-linear cardiac kernel")
    sigma: float = F(0.15, POS, "Gaussian width of the local-linear amplitude kernel")
    local_linear_extrapolate: bool = F(False, BOOL, "true: the paper's plain local-linear fit, which extrapolates "
                                       "along an axis the points do not bracket; false: locally constant there")
    local_linear_points: str = F("quadrants", one_of(LL_POINT_RULES), "local-linear neighbour selection: "
                                 "'quadrants' (local_linear_count nearest per quadrant, the paper's text) or "
                                 "'nearest' (the local_linear_count nearest overall, the paper's Figure 2B caption)")
    local_linear_count: int = _f(2, f"an integer in 1..{LL_MAX_SLOTS}", lambda x: _posint(x) and x <= LL_MAX_SLOTS,
                                 "local-linear points per quadrant ('quadrants': 4 x count slots) or in all "
                                 "('nearest')")
    max_turns: int = F(0, NONNEGINT, "0: every candidate turn within the SSRB window; N > 0: only the N candidates "
                       "nearest in z per (slice, view), for every method")
    filter: str = _f("ram-lak", "one of " + ", ".join(FILTERS), lambda x: x in FILTERS, "ramp filter window")
    volume_dtype: str = F("float32", one_of(("float32", "float16")), "on-disk dtype of the run's volumes: "
                          "'float16' halves volumes.h5 (values within 2^-11 relative, <= 0.5 HU below 2048 HU; "
                          "the metrics are computed from what is stored)")
    small_fov_mm: tuple = _f((-70.0, 85.0, -100.0, 40.0), "[x_min, x_max, y_min, y_max] with min < max",
                             lambda v: isinstance(v, tuple) and len(v) == 4 and all(_num(x) for x in v)
                             and v[0] < v[1] and v[2] < v[3],
                             "box around the heart (mm, LPS): the phantom's epicardial fat at every state + 10 mm")

    def check(self) -> None:
        if self.local_linear_points == "quadrants" and 4 * self.local_linear_count > LL_MAX_SLOTS:
            raise SceneError(f"recon.local_linear_count = {self.local_linear_count}: with local_linear_points = "
                             f"'quadrants' must be at most {LL_MAX_SLOTS // 4} (4 x count <= {LL_MAX_SLOTS} slots)")

    @property
    def resp_targets(self) -> tuple[float, ...]:
        """Target amplitudes: midpoints of ``resp_bins`` equal bins of [0, 1]."""
        return tuple((i + 0.5) / self.resp_bins for i in range(self.resp_bins))

    @property
    def fov_radius_mm(self) -> float:
        """Radius (mm) of the reconstruction circle inscribed in the image grid."""
        return 0.5 * min(self.nx, self.ny) * self.voxel_mm


SECTIONS = {
    "scanner": ScannerConfig,
    "scan": ScanConfig,
    "signals": SignalsConfig,
    "phantom": PhantomConfig,
    "noise": NoiseConfig,
    "recon": ReconConfig,
}
TOP_KEYS = ("name", "description") + tuple(SECTIONS)


@dataclass(frozen=True, kw_only=True)
class Scene:
    """A whole validated scene. ``source`` is the file it came from (not part of equality)."""

    name: str = "custom"
    description: str = ""
    scanner: ScannerConfig = field(default_factory=ScannerConfig)
    scan: ScanConfig = field(default_factory=ScanConfig)
    signals: SignalsConfig = field(default_factory=SignalsConfig)
    phantom: PhantomConfig = field(default_factory=PhantomConfig)
    noise: NoiseConfig = field(default_factory=NoiseConfig)
    recon: ReconConfig = field(default_factory=ReconConfig)
    source: str = field(default="", compare=False)

    # -- what the scene asks for (docs/data-flow.md "Compute only what is asked") -----------------
    @property
    def measured(self) -> bool:
        """A measured scan (``scan.source`` not 'simulated'): no phantom, no ground truth."""
        return self.scan.source != "simulated"

    @property
    def has_cardiac(self) -> bool:
        if self.measured:  # the cardiac axis exists only with a recorded ECG
            return bool(self.signals.ecg_trace)
        return self.phantom.cardiac_motion

    @property
    def has_respiratory(self) -> bool:
        if self.measured:
            return bool(self.signals.breathing_trace)
        return self.phantom.respiratory_motion and not self.signals.breath_hold

    @property
    def cardiac_targets(self) -> tuple[float, ...]:
        return self.recon.cardiac_phases if self.has_cardiac else (0.0,)

    @property
    def resp_targets(self) -> tuple[float, ...]:
        return self.recon.resp_targets if self.has_respiratory else (self.signals.breath_hold_amplitude
                                                                     if self.signals.breath_hold else 0.5,)

    def to_dict(self) -> dict[str, Any]:
        d = {"name": self.name, "description": self.description}
        for sec in SECTIONS:
            d[sec] = {k: (list(v) if isinstance(v, tuple) else v)
                      for k, v in dataclasses.asdict(getattr(self, sec)).items()}
        return d

    @property
    def trace_duration_s(self) -> float:
        """Length of the scene's signal trace (s): max(60 s, longest scan of its pitches) + 5 s.

        The breathing amplitude is normalised over the whole trace (``docs/conventions.md``), so
        this length is part of what a projection shows.
        """
        longest = max(self.scan.duration_s(self.scanner, p) for p in self.scan.pitches)
        return max(TRACE_MIN_S, longest) + TRACE_MARGIN_S

    def scan_hash(self, pitch: float) -> str:
        """Content hash of everything that determines the noise-free projections of one pitch."""
        d = self.to_dict()
        # Keys added after stores existed hash only when they differ from what those stores
        # were made with (flat detector, analytic phantom), so earlier stores stay valid.
        scanner = {k: v for k, v in d["scanner"].items() if not (k == "detector" and v == "flat")}
        phantom = {k: v for k, v in d["phantom"].items() if not (k == "kind" and v == "analytic")}
        if hasattr(self.phantom, "content_hash"):  # a phantom read from files: their content, not only their path
            phantom["content"] = self.phantom.content_hash()
        # recorded traces and a measured series: their content, not only their paths
        content = recorded_content(self)
        # The amplitude normalisation spans the whole signal trace, whose length depends on
        # the longest scan over *all* the scene's pitches: part of what a projection shows.
        payload = {"scanner": scanner, "scan": {**d["scan"], "pitches": [pitch]},
                   "signals": d["signals"], "phantom": phantom, "projector": PROJECTOR_VERSION,
                   "signal_trace_s": self.trace_duration_s}
        if content:
            payload["content"] = content
        if self.measured:  # the projections are the measured ones: no phantom, no projector
            payload.pop("phantom")
            payload.pop("projector")
        return hashlib.sha256(json.dumps(payload, sort_keys=True).encode()).hexdigest()[:16]

    def replace(self, **sections: Any) -> Scene:
        """New scene with some sections' values replaced, e.g. ``replace(recon={"nz": 4})``.

        A ``phantom`` table with another ``kind`` replaces the whole section (the kinds have
        different keys).
        """
        d = self.to_dict()
        for sec, vals in sections.items():
            if sec == "phantom" and vals.get("kind", d[sec]["kind"]) != d[sec]["kind"]:
                d[sec] = dict(vals)
            elif sec in SECTIONS:
                d[sec].update(vals)
            else:
                d[sec] = vals
        return scene_from_dict(d, source=self.source)


# ---------------------------------------------------------------------------------------
def file_digest(path) -> str:
    """BLAKE2b (16 hex) of a file's bytes; a WFDB record (``.hea`` or its base name): of all its files."""
    p = Path(path)
    if p.suffix.lower() in (".hea", ".dat") or (not p.suffix and p.with_suffix(".hea").exists()):
        base = p.with_suffix("")
        files = sorted(q for q in base.parent.glob(base.name + ".*") if q.is_file())
    else:
        files = [p] if p.is_file() else []
    if not files:
        raise SceneError(f"{p}: no such file")
    h = hashlib.blake2b(digest_size=8)
    for q in files:
        h.update(q.name.encode())
        h.update(q.read_bytes())
    return h.hexdigest()


def recorded_content(scene: Scene) -> dict:
    """Content digests of the scene's recorded inputs (traces, measured series), for the scan hash."""
    out = {}
    for key in ("breathing_trace", "ecg_trace"):
        path = getattr(scene.signals, key)
        if path:
            out[key] = file_digest(path)
    if scene.measured:
        out["projections"] = dicom_ct_pd.series_signature(scene.scan.projections)
    return out


def _measured_sections(parts: dict, raw: dict, prefix: str) -> dict:
    """``[scanner]`` and ``[scan]`` of a measured scene: the DICOM-CT-PD series' geometry.

    A key the scene gives must agree with the series (else a SceneError naming both); the
    series fills the rest (:func:`clrecon.config.dicom_ct_pd.series_geometry`).
    """
    scan = parts["scanner"], parts["scan"]
    # the keys the scene gives, as validated (paths resolved against the scene file)
    sc_raw = {k: getattr(scan[0], k) for k in (raw.get("scanner", {}) or {})}
    scan_raw = {k: getattr(scan[1], k) for k in (raw.get("scan", {}) or {})}
    scan = scan[1]
    geom = dicom_ct_pd.series_geometry(scan.projections, sc_raw.get("rotation_time_s"), scan.timestamp_unit)
    for sec, given, derived in (("scanner", sc_raw, geom.scanner), ("scan", scan_raw, geom.scan)):
        for k, v in derived.items():
            if k not in given:
                continue
            g = tuple(given[k]) if isinstance(given[k], list) else given[k]
            same = (all(math.isclose(float(a), float(b), rel_tol=1e-5, abs_tol=1e-6) for a, b in zip(g, v, strict=True))
                    if isinstance(v, tuple) and isinstance(g, tuple) and len(g) == len(v)
                    else (math.isclose(float(g), float(v), rel_tol=1e-5, abs_tol=1e-6)
                          if isinstance(v, (int, float)) and isinstance(g, (int, float)) else g == v))
            if not same:
                src = geom.tag_of.get(k, "the views' angles and axial positions")
                raise SceneError(f"{prefix}{sec}.{k} = {given[k]!r} contradicts the DICOM-CT-PD series "
                                 f"{scan.projections}: {src} gives {v!r}; remove the key or fix it")
    if geom.scanner["detector"] not in DETECTORS:
        raise SceneError(f"{prefix}{scan.projections}: (7029,100B) DetectorShape gives detector model "
                         f"{geom.scanner['detector']!r}, which this build does not have (detector models: "
                         f"{', '.join(DETECTORS.names)})")
    lacking = [k for k in geom.scanner if k not in {f.name for f in fields(ScannerConfig)}]
    if lacking:
        raise SceneError(f"{prefix}{scan.projections}: {geom.tag_of.get(lacking[0], lacking[0])} needs "
                         f"scanner.{lacking[0]} = {geom.scanner[lacking[0]]!r}, which this build lacks (the "
                         f"cylindrical-detector / flying-focal-spot model is not on this branch)")
    scanner = ScannerConfig(**{**sc_raw, **geom.scanner})
    scan = ScanConfig(**{**scan_raw, **geom.scan})
    return {"scanner": scanner, "scan": scan}


def _suggest(key: str, allowed) -> str:
    near = difflib.get_close_matches(key, list(allowed), n=1, cutoff=0.5)
    return f"; did you mean {near[0]!r}?" if near else f"; valid keys: {', '.join(allowed)}"


def _section_class(sec: str, raw: dict):
    """The config class of a TOML table: fixed, except ``[phantom]``, whose ``kind`` picks it."""
    if sec != "phantom":
        return SECTIONS[sec]
    kind = raw.get("kind", "analytic") if isinstance(raw, dict) else "analytic"
    if kind not in PHANTOM_SOURCES:
        raise SceneError(f"phantom.kind = {kind!r}: must be one of {', '.join(PHANTOM_SOURCES.names)}")
    return PHANTOM_SOURCES[kind].config


def _resolve_paths(cls, raw: Any, source: str):
    """A section's path keys (``cls.PATH_KEYS``, e.g. a voxel phantom's ``frames``) that are
    relative, made relative to the scene file's folder (unchanged without a scene file)."""
    keys = getattr(cls, "PATH_KEYS", ())
    if not (keys and source and isinstance(raw, dict)):
        return raw
    base = Path(source).parent
    return {k: (str(base / v) if k in keys and isinstance(v, str) and v.strip() and not Path(v).is_absolute() else v)
            for k, v in raw.items()}


def _build_section(cls, raw: Any, where: str):
    """Map a TOML table's keys onto the section ``cls``, which validates itself."""
    if not isinstance(raw, dict):
        raise SceneError(f"{where}: expected a table [{where}], got {type(raw).__name__} {raw!r}")
    names = {f.name for f in fields(cls)}
    for key in raw:
        if key not in names:
            raise SceneError(f"{where}.{key}: unknown key{_suggest(key, names)}")
    return cls(**raw)


def scene_from_dict(raw: dict[str, Any], source: str = "") -> Scene:
    """Validate a parsed TOML document into a :class:`Scene`."""
    prefix = f"{source}: " if source else ""
    if not isinstance(raw, dict):
        raise SceneError(f"{prefix}a scene must be a TOML table")
    for key in raw:
        if key not in TOP_KEYS:
            raise SceneError(f"{prefix}{key}: unknown key{_suggest(key, TOP_KEYS)}")
    try:
        parts = {}
        for sec in SECTIONS:
            cls = _section_class(sec, raw.get(sec, {}))
            parts[sec] = _build_section(cls, _resolve_paths(cls, raw.get(sec, {}), source), sec)
        if parts["scan"].source == "dicom-ct-pd":
            parts.update(_measured_sections(parts, raw, ""))
    except SceneError as e:
        raise SceneError(f"{prefix}{e}") from None
    for k in ("name", "description"):
        if k in raw and not isinstance(raw[k], str):
            raise SceneError(f"{prefix}{k} = {raw[k]!r}: must be a string")
    scene = Scene(name=raw.get("name", Path(source).stem if source else "custom"),
                  description=raw.get("description", ""), source=source, **parts)
    _check_consistency(scene, prefix)
    return scene


def _check_consistency(s: Scene, prefix: str) -> None:
    sc, rc = s.scanner, s.recon
    if sc.sdd_mm <= sc.sid_mm:
        raise SceneError(f"{prefix}scanner.sdd_mm = {sc.sdd_mm}: must be greater than scanner.sid_mm = {sc.sid_mm}")
    if s.scan.n_projections == 0 and s.scan.coverage_mm <= sc.collimation_iso_mm:
        raise SceneError(f"{prefix}scan.coverage_mm = {s.scan.coverage_mm}: must exceed the collimation "
                         f"W = {sc.collimation_iso_mm:.2f} mm")
    # Derived geometry must be finite (extreme values such as sid_mm = 1e-308 pass the
    # per-key checks but overflow or divide by zero here).
    # SSRB needs a candidate for every (slice, view): the feed per rotation must stay within
    # twice the slice window of the detector model
    try:
        p_max = sc.detector_model.max_covering_pitch(min(sc.fov_radius_mm, rc.fov_radius_mm))
        for p in s.scan.pitches:
            s.scan.projection_count(sc, p)
        finite = math.isfinite(p_max) and math.isfinite(sc.collimation_iso_mm)
    except (ArithmeticError, ValueError):
        finite = False
    if not finite:
        raise SceneError(f"{prefix}scanner (sid_mm = {sc.sid_mm}, sdd_mm = {sc.sdd_mm}, n_cols = {sc.n_cols}, "
                         f"col_pitch_mm = {sc.col_pitch_mm}, n_rows = {sc.n_rows}, row_pitch_mm = "
                         f"{sc.row_pitch_mm}), scan and recon sizes: the derived geometry (field of view, "
                         f"collimation, SSRB window, projection count) is not finite; "
                         f"use the mm sizes of a real scanner")
    too_high = [p for p in s.scan.pitches if p > p_max * (1.0 + 1e-9)]
    if too_high:
        raise SceneError(f"{prefix}scan.pitches = {list(s.scan.pitches)}: pitch {too_high[0]:g} leaves "
                         f"(slice, view) pairs without data; the largest pitch that covers every "
                         f"(slice, view) is {p_max:.4f}")


def load_scene(name_or_path: str | Path) -> Scene:
    """A built-in scene by name (``demo``, ``tiny``, ...) or a TOML file by path."""
    p = Path(name_or_path)
    if not p.suffix and not p.exists():
        p = SCENE_DIR / f"{name_or_path}.toml"
        if not p.exists():
            raise SceneError(f"scene {str(name_or_path)!r} is neither a file nor a built-in scene; "
                             f"built-in: {', '.join(builtin_scene_names())}")
    if not p.is_file():
        raise SceneError(f"scene file {str(p)!r} does not exist")
    try:
        raw = tomllib.loads(p.read_text())
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as e:
        raise SceneError(f"{p}: malformed TOML: {e}") from None
    return scene_from_dict(raw, source=str(p))


def builtin_scene_names() -> list[str]:
    return sorted(f.stem for f in SCENE_DIR.glob("*.toml"))
