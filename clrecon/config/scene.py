"""Scenes: TOML files validated into immutable config objects (stage 0 of the pipeline).

A scene says what scanner, scan protocol, breathing and heart rhythm, phantom, noise and
reconstruction to run. Every section is a frozen dataclass; derived quantities (collimation
at the isocentre, table feed, number of projections) are properties, never stored twice.

Each section is defined by the stage it configures (``[scanner]``, ``[scan]``, ``[signals]``:
:mod:`clrecon.scan.config`; ``[noise]``: :mod:`clrecon.simulation.config`; ``[phantom]``:
:mod:`clrecon.simulation.phantom_sources`; ``[recon]``: :mod:`clrecon.reconstruction.config`);
this module composes them, so it stands above those stages and imports them, never the other
way (``docs/data-flow.md`` "Layering"). The section classes are re-exported here.

Errors name the key, the bad value and what is allowed; unknown keys are errors that
suggest the nearest valid key. Built-in scenes live in ``clrecon/config/scenes/*.toml``.
"""

from __future__ import annotations

import dataclasses
import difflib
import hashlib
import json
import math
from collections.abc import Mapping
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

try:  # Python >= 3.11
    import tomllib
except ModuleNotFoundError:  # pragma: no cover
    import tomli as tomllib

from clrecon.core.detector import DETECTORS
from clrecon.core.errors import SceneError
from clrecon.core.runtime import default_cache_tag
from clrecon.core.versions import PROJECTOR_VERSION
from clrecon.reconstruction.config import FILTERS, METHODS, ReconConfig
from clrecon.scan import dicom_ct_pd
from clrecon.scan.config import (
    MAX_SCAN_S,
    RHYTHMS,
    TRACE_MARGIN_S,
    TRACE_MIN_S,
    ScanConfig,
    ScannerConfig,
    SignalsConfig,
)
from clrecon.scan.table import recorded_content
from clrecon.simulation.config import NoiseConfig
from clrecon.simulation.phantom_sources import PHANTOM_SOURCES, PhantomConfig

__all__ = ["FILTERS", "METHODS", "RHYTHMS", "SECTIONS", "TRACE_MARGIN_S", "TRACE_MIN_S", "NoiseConfig",
           "PhantomConfig", "ReconConfig", "Scene", "ScanConfig", "ScannerConfig", "SignalsConfig",
           "builtin_scene_names", "load_scene", "scene_from_dict"]

SCENE_DIR = Path(__file__).resolve().parent / "scenes"


# ---------------------------------------------------------------------------------------
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
        later = {"detector": "flat", "central_col": -1.0, "central_row": -1.0, "flying_focal_spot": "none",
                 "ffs_angle_rad": 0.0, "ffs_radial_mm": 0.0, "ffs_z_mm": 0.0}
        scanner = {k: v for k, v in d["scanner"].items() if not (k in later and v == later[k])}
        phantom = {k: v for k, v in d["phantom"].items() if not (k == "kind" and v == "analytic")}
        if hasattr(self.phantom, "content_hash"):  # a phantom read from files: their content, not only their path
            phantom["content"] = self.phantom.content_hash()
        # recorded traces and a measured series: their content, not only their paths
        content = recorded_content(self)
        # The amplitude normalisation spans the whole signal trace, whose length depends on
        # the longest scan over *all* the scene's pitches: part of what a projection shows.
        # likewise the measured-scan and recorded-trace keys (issue 18) at their defaults
        scan_later = {"source": "simulated", "projections": "", "timestamp_unit": "ms", "flip_channels": False,
                      "flip_rows": False, "pixel_layout": "auto", "orientation": "tags", "rotation": "increasing",
                      "table_direction": "increasing"}
        sig_later = {"breathing_trace": "", "ecg_trace": "", "trace_align": "offset", "trace_offset_s": 0.0,
                     "ecg_offset_s": 0.0, "breathing_inhale": "up"}
        scan_d = {k: v for k, v in d["scan"].items() if not (k in scan_later and v == scan_later[k])
                  and k != "patient_position"}  # the patient position changes the labels, not the projections
        if self.measured:  # the series by its content (recorded_content), not by a path that may name the patient
            scan_d.pop("projections", None)
        signals_d = {k: v for k, v in d["signals"].items() if not (k in sig_later and v == sig_later[k])}
        payload = {"scanner": scanner, "scan": {**scan_d, "pitches": [pitch]},
                   "signals": signals_d, "phantom": phantom, "projector": PROJECTOR_VERSION,
                   "signal_trace_s": self.trace_duration_s}
        if content:
            payload["content"] = content
        if self.measured:  # the projections are the measured ones: no phantom, no projector
            payload.pop("phantom")
            payload.pop("projector")
        elif tag := default_cache_tag():  # simulated by another driver than PoCL: last bits differ
            payload["driver"] = tag
        return hashlib.sha256(json.dumps(payload, sort_keys=True).encode()).hexdigest()[:16]

    def replace(self, **sections: Any) -> Scene:
        """New scene with some sections' values replaced, e.g. ``replace(recon={"nz": 4})``.

        A ``phantom`` table with another ``kind`` replaces the whole section (the kinds have
        different keys). A table inside a section (``recon={"mc": {"rounds": 1}}``) is merged
        into the scene's own, so its other keys keep the scene's values.
        """
        d = self.to_dict()
        for sec, vals in sections.items():
            if sec == "phantom" and vals.get("kind", d[sec]["kind"]) != d[sec]["kind"]:
                d[sec] = dict(vals)
            elif sec in SECTIONS:
                for key, val in vals.items():
                    if isinstance(val, Mapping) and isinstance(d[sec].get(key), dict):
                        d[sec][key] = {**d[sec][key], **val}
                    else:
                        d[sec][key] = val
            else:
                d[sec] = vals
        return scene_from_dict(d, source=self.source)


# ---------------------------------------------------------------------------------------
def _measured_sections(parts: dict, raw: dict, prefix: str) -> dict:
    """``[scanner]`` and ``[scan]`` of a measured scene: the DICOM-CT-PD series' geometry.

    A key the scene gives must agree with the series (else a SceneError naming both); the
    series fills the rest (:func:`clrecon.scan.dicom_ct_pd.series_geometry`).
    """
    scan = parts["scanner"], parts["scan"]
    # the keys the scene gives, as validated (paths resolved against the scene file)
    sc_raw = {k: getattr(scan[0], k) for k in (raw.get("scanner", {}) or {})}
    scan_raw = {k: getattr(scan[1], k) for k in (raw.get("scan", {}) or {})}
    scan = scan[1]
    ph_raw = {k: getattr(parts["phantom"], k) for k in (raw.get("phantom", {}) or {}) if hasattr(parts["phantom"], k)}
    geom = dicom_ct_pd.series_geometry(scan.projections, sc_raw.get("rotation_time_s"), scan.timestamp_unit,
                                       scan.pixel_layout, scan.flip_channels, scan.flip_rows, scan.orientation,
                                       scan.patient_position)
    for sec, given, derived in (("scanner", sc_raw, geom.scanner), ("scan", scan_raw, geom.scan),
                                ("phantom", ph_raw, geom.phantom)):
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
    noise_raw = raw.get("noise", {}) or {}
    if noise_raw.get("enabled") is True:
        raise SceneError(f"{prefix}noise.enabled = true: a measured scan (scan.source = 'dicom-ct-pd') carries its own "
                         f"noise and clrecon adds none; remove the key")
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
    scan = ScanConfig(**{**scan_raw, **geom.scan, **geom.reading_keys})  # the reading the orientation check settled
    # simulation-only sections do not apply: no simulated noise; water from the series where it has it
    return {"scanner": scanner, "scan": scan, "noise": dataclasses.replace(parts["noise"], enabled=False),
            "phantom": dataclasses.replace(parts["phantom"], **geom.phantom)}


def _suggest(key: str, allowed) -> str:
    near = difflib.get_close_matches(key, list(allowed), n=1, cutoff=0.5)
    return f"; did you mean {near[0]!r}?" if near else f"; valid keys: {', '.join(allowed)}"


def _section_class(sec: str, raw: dict):
    """The config class of a TOML table: fixed, except ``[phantom]``, whose ``kind`` picks it."""
    if sec != "phantom":
        return SECTIONS[sec]
    kind = raw.get("kind", "analytic") if isinstance(raw, dict) else "analytic"
    if not isinstance(kind, str) or kind not in PHANTOM_SOURCES:
        raise SceneError(f"phantom.kind = {kind!r}: must be one of {', '.join(PHANTOM_SOURCES.names)}")
    return PHANTOM_SOURCES[kind].config


def _resolve_paths(cls, raw: Any, source: str):
    """A section's path keys (``cls.PATH_KEYS``, e.g. a voxel phantom's ``frames``) that are
    relative, made absolute from the scene file's folder (unchanged without a scene file), so
    that ``results.json`` records where the data was whatever the working folder."""
    keys = getattr(cls, "PATH_KEYS", ())
    if not (keys and source and isinstance(raw, dict)):
        return raw
    base = Path(source).resolve().parent
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
    # a measured scene's file is often named after the patient: its default name is not the file's
    default_name = "measured" if parts["scan"].measured_source else (Path(source).stem if source else "custom")
    scene = Scene(name=raw.get("name", default_name),
                  description=raw.get("description", ""), source=source, **parts)
    _check_consistency(scene, prefix)
    return scene


def _check_consistency(s: Scene, prefix: str) -> None:
    sc, rc = s.scanner, s.recon
    if sc.sdd_mm <= sc.sid_mm:
        raise SceneError(f"{prefix}scanner.sdd_mm = {sc.sdd_mm}: must be greater than scanner.sid_mm = {sc.sid_mm}")
    if rc.backprojector == "parallel-rebin" and sc.views_per_rotation % 2:
        raise SceneError(f"{prefix}recon.backprojector = 'parallel-rebin': needs an even scanner.views_per_rotation "
                         f"(conjugate rays half a rotation apart), got {sc.views_per_rotation}; use 'direct'")
    if rc.backprojector == "parallel-rebin" and sc.flying_focal_spot in ("phi", "phi+z"):
        raise SceneError(f"{prefix}recon.backprojector = 'parallel-rebin': not with scanner.flying_focal_spot = "
                         f"{sc.flying_focal_spot!r} (the rebinning assumes one source per view angle); use 'direct'")
    if s.scan.n_projections == 0 and s.scan.coverage_mm <= sc.collimation_iso_mm:
        raise SceneError(f"{prefix}scan.coverage_mm = {s.scan.coverage_mm}: must exceed the collimation "
                         f"W = {sc.collimation_iso_mm:.2f} mm (scanner.n_rows = {sc.n_rows} x row_pitch_mm = "
                         f"{sc.row_pitch_mm:g} at the detector, scaled to the isocentre)")
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
                         f"(slice, view) is {p_max:.4f} (scanner.n_rows = {sc.n_rows} x row_pitch_mm = "
                         f"{sc.row_pitch_mm:g}, field of view radius {min(sc.fov_radius_mm, rc.fov_radius_mm):.1f} mm)")
    for p in s.scan.pitches:
        n, t = s.scan.projection_count(sc, p), s.scan.duration_s(sc, p)
        if t > MAX_SCAN_S:
            how = (f"scan.n_projections = {n}" if s.scan.n_projections else
                   f"scan.coverage_mm = {s.scan.coverage_mm:g} at pitch {p:g} with collimation W = "
                   f"{sc.collimation_iso_mm:.3g} mm (scanner.n_rows = {sc.n_rows} x row_pitch_mm = "
                   f"{sc.row_pitch_mm:g}): {n} projections")
            raise SceneError(f"{prefix}{how} x scanner.rotation_time_s = {sc.rotation_time_s:g} / "
                             f"views_per_rotation = {sc.views_per_rotation}: a scan of {t:.4g} s; at most "
                             f"{MAX_SCAN_S:g} s (a free-breathing thorax scan lasts under two minutes; the "
                             f"paper's pitch-0.02 scan: 49 s)")


def load_scene(name_or_path: str | Path) -> Scene:
    """A built-in scene by name (``demo``, ``tiny``, ...) or a TOML file by path."""
    p = Path(name_or_path)
    if not p.suffix and not p.is_file():  # a bare name: a built-in scene (even beside a folder of that name)
        p = SCENE_DIR / f"{name_or_path}.toml"
        if not p.is_file():
            raise SceneError(f"scene {str(name_or_path)!r} is neither a file nor a built-in scene; "
                             f"built-in: {', '.join(builtin_scene_names())}")
    if p.is_dir():
        raise SceneError(f"scene file {str(p)!r} is a folder; expected a scene TOML file or a built-in scene name")
    if not p.is_file():
        raise SceneError(f"scene file {str(p)!r} does not exist")
    try:
        raw = tomllib.loads(p.read_text())
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as e:
        raise SceneError(f"{p}: malformed TOML: {e}") from None
    return scene_from_dict(raw, source=str(p))


def builtin_scene_names() -> list[str]:
    return sorted(f.stem for f in SCENE_DIR.glob("*.toml"))
