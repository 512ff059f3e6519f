"""The scan stage's own configuration: scanner hardware, helical protocol, breathing and heart rhythm.

Three sections of a scene (``[scanner]``, ``[scan]``, ``[signals]``), each a frozen dataclass
that validates itself (:class:`clrecon.core.config.Section`); derived quantities (collimation
at the isocentre, table feed, number of projections) are properties, never stored twice.
Lengths in mm, times in s.

They live here, with the stage that uses them, so that the scan, simulation and
reconstruction stages need nothing from :mod:`clrecon.config` (which composes every stage's
sections into a :class:`~clrecon.config.scene.Scene` and sits above them; ``docs/data-flow.md``
"Layering"). What a stage needs of a whole scene it declares as a small protocol here
(:class:`Acquisition`): a :class:`~clrecon.config.scene.Scene` is one, and so is any object
with those attributes.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar, Protocol

import numpy as np

from clrecon.core.config import (
    BOOL,
    FRAC,
    NONNEG,
    NUM,
    SEED,
    F,
    Section,
    _num,
    field_of,
    integer_in,
    number_in,
    one_of,
    zero_or_in,
)
from clrecon.core.detector import DETECTORS, FFS_MODES, DetectorModel, detector_for, ffs_cycle, ffs_states
from clrecon.core.errors import SceneError
from clrecon.scan.recorded import trace_files

#: The signal trace spans max(TRACE_MIN_S, the longest scan) + TRACE_MARGIN_S seconds.
TRACE_MIN_S = 60.0
TRACE_MARGIN_S = 5.0
RHYTHMS = ("periodic", "hrv", "af", "pvc")
SCAN_SOURCES = ("simulated", "dicom-ct-pd")
#: scan.pixel_layout: TCIA's (DICOM Rows = detector channels) or the other (DICOM Rows = detector rows)
PIXEL_LAYOUTS = ("auto", "rows-are-channels", "rows-are-detector-rows")
#: scan.patient_position: DICOM (0018,5100) values clrecon maps onto LPS ('' = from the series / HFS)
PATIENT_POSITIONS = ("", "HFS", "HFP", "FFS", "FFP")
STR = ("a string", lambda x: isinstance(x, str))

_f = field_of  # (default, allowed, check, doc)

# Physical ranges (docs/hostile-inputs.md "Ranges of scene values"): wide enough for every clinical
# CT, C-arm and micro-CT geometry and for the coarse test scenes (tiny: 7.5 mm cells, 12 mm
# voxels), narrow enough that a non-number, a unit slip (metres, micrometres) or a typo is refused
# where it enters, in one line naming the key, the value and the range with its reason.
DETECTOR_CELL_MM = number_in(0.005, 100.0, "mm", "detector cells are 0.05-1.4 mm; coarse test detectors up to "
                             "tens of mm")
#: Longest scan (s) a scene may ask for: a free-breathing thorax scan lasts seconds to two
#: minutes (the paper's pitch-0.02 scan: 49 s); the signal model samples its trace every 5 ms.
MAX_SCAN_S = 600.0
#: Largest pitch list (one scan per pitch).
MAX_PITCHES = 64
PITCH_RANGE = (0.001, 2.0)
#: Offsets between a recorded trace's clock and the scan's (s).
OFFSET_S = number_in(-86400.0, 86400.0, "s", "within a day of the trace's start")


# ---------------------------------------------------------------------------------------
@dataclass(frozen=True, kw_only=True)
class ScannerConfig(Section):
    """CT scanner hardware (Table 1 of the paper by default). Lengths in mm."""

    SECTION = "scanner"

    sid_mm: float = F(595.0, number_in(10.0, 5000.0, "mm", "clinical CT 500-650 mm, C-arm ~800 mm, micro-CT "
                                       "from ~20 mm"), "source to isocentre distance")
    sdd_mm: float = F(1085.6, number_in(10.0, 10000.0, "mm", "clinical CT 950-1150 mm; more than sid_mm"),
                      "source to detector distance")
    n_cols: int = F(900, integer_in(2, 16384, "clinical CT 670-900 channels, flat panels a few thousand; the ramp "
                                    "filter needs 2"),
                    "detector columns")
    n_rows: int = F(64, integer_in(1, 4096, "clinical CT 16-320 rows, flat panels up to ~3000"), "detector rows")
    col_pitch_mm: float = F(0.8, DETECTOR_CELL_MM, "detector column pitch at the detector")
    row_pitch_mm: float = F(0.8, DETECTOR_CELL_MM, "detector row pitch at the detector")
    views_per_rotation: int = F(984, integer_in(2, 20000, "clinical CT 700-5000 views per rotation"),
                                "projections per rotation")
    rotation_time_s: float = F(0.3, number_in(0.05, 60.0, "s", "the fastest gantries turn in 0.25 s, C-arm "
                                              "sweeps take 4-20 s"), "seconds per rotation")
    detector: str = F("flat", one_of(DETECTORS.names), "detector model (clrecon.core.detector)")
    central_col: float = F(-1.0, NUM, "cylindrical: 0-based fractional column the central ray hits; "
                                      "-1 = the middle (n_cols - 1) / 2 (quarter offset: middle + 0.25)")
    central_row: float = F(-1.0, NUM, "cylindrical: 0-based fractional row the central ray hits; -1 = the middle")
    flying_focal_spot: str = F("none", one_of(FFS_MODES), "flying focal spot (cylindrical only): none, phi, z, phi+z")
    ffs_angle_rad: float = F(0.0, NONNEG, "phi-FFS: angular shift of the focal spot from the focal centre, +- per view")
    ffs_radial_mm: float = F(0.0, NUM, "phi-FFS: radial shift (mm, + away from the isocentre) with +ffs_angle_rad")
    ffs_z_mm: float = F(0.0, NONNEG, "z-FFS: axial shift of the focal spot from the focal centre, +- per view")

    def check(self) -> None:
        for key, n in (("central_col", self.n_cols), ("central_row", self.n_rows)):
            v = getattr(self, key)
            if v != -1.0 and not (0.0 <= v <= n - 1):
                raise SceneError(f"scanner.{key} = {v!r}: must be -1 (the middle) or a cell index in [0, {n - 1}]")
            if v != -1.0 and self.detector == "flat":
                raise SceneError(f"scanner.{key} = {v!r}: the flat detector is centred; an offset central "
                                 f"element needs scanner.detector = \"cylindrical\"")
        if self.flying_focal_spot != "none" and self.detector == "flat":
            raise SceneError(f"scanner.flying_focal_spot = {self.flying_focal_spot!r}: needs "
                             f"scanner.detector = \"cylindrical\" (the flat detector has no flying focal spot)")
        cycle = ffs_cycle(self.flying_focal_spot)
        if self.views_per_rotation % cycle:
            raise SceneError(f"scanner.views_per_rotation = {self.views_per_rotation}: must be a multiple of "
                             f"{cycle} with flying_focal_spot = {self.flying_focal_spot!r} (each view keeps its "
                             f"focal-spot state from turn to turn)")
        for key, modes in (("ffs_angle_rad", ("phi", "phi+z")), ("ffs_radial_mm", ("phi", "phi+z")),
                           ("ffs_z_mm", ("z", "phi+z"))):
            if getattr(self, key) != 0.0 and self.flying_focal_spot not in modes:
                raise SceneError(f"scanner.{key} = {getattr(self, key)!r}: only used with flying_focal_spot "
                                 f"in {', '.join(modes)} (it is {self.flying_focal_spot!r})")
        if self.ffs_angle_rad > 0.01 or abs(self.ffs_radial_mm) > 0.05 * self.sid_mm or self.ffs_z_mm > 0.25 * (
                self.n_rows * self.row_pitch_mm):
            raise SceneError(f"scanner focal-spot shifts (ffs_angle_rad = {self.ffs_angle_rad}, ffs_radial_mm = "
                             f"{self.ffs_radial_mm}, ffs_z_mm = {self.ffs_z_mm}): must stay within 0.01 rad, "
                             f"5 % of sid_mm and a quarter of the detector height (clinical shifts are ~1 mm)")

    @property
    def ffs_shifts(self) -> np.ndarray:
        """Focal-spot states of the FFS cycle, (cycle, 3): (angle rad, radial mm, axial mm); see :func:`ffs_cycle`."""
        return ffs_states(self.flying_focal_spot, self.ffs_angle_rad, self.ffs_radial_mm, self.ffs_z_mm)


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

    pitches: tuple = _f((0.02,), f"a list of 1 to {MAX_PITCHES} numbers in [{PITCH_RANGE[0]:g}, {PITCH_RANGE[1]:g}] "
                        "(5DCT scans at 0.02-0.1, clinical helical scans at 0.2-1.5; no scanner covers more than 2)",
                        lambda v: isinstance(v, tuple) and 0 < len(v) <= MAX_PITCHES
                        and all(_num(p) and PITCH_RANGE[0] <= p <= PITCH_RANGE[1] for p in v),
                        "table feed per rotation / collimation W; one scan per pitch")
    coverage_mm: float = F(119.7, number_in(1.0, 2000.0, "mm", "a body is under 2 m long"),
                           "longitudinal coverage = travel + W")
    n_projections: int = F(0, integer_in(0, 10 ** 7, "0: from coverage_mm; the paper's pitch-0.02 scan has "
                                         "160 689"), "if > 0: the scan length in projections (overrides coverage_mm)")
    z_centre_mm: float = F(0.0, number_in(-5000.0, 5000.0, "mm", "a table position; CT tables travel under 2 m"),
                           "table position of the scan centre")
    start_angle_deg: float = F(0.0, number_in(-3600.0, 3600.0, "deg", "within ten turns of 0; only the angle "
                                              "modulo 360 matters"), "gantry angle of the first view")
    source: str = F("simulated", one_of(SCAN_SOURCES), "'simulated' (the phantom) or 'dicom-ct-pd' (a measured "
                    "scan: projections = a folder of DICOM-CT-PD files, one projection each; docs/measured-data.md)")
    projections: str = F("", STR, "dicom-ct-pd: the folder of projection files (relative: to the scene file)")
    timestamp_unit: str = F("ms", one_of(("ms", "s")), "dicom-ct-pd: unit of the Timestamp tag (7033,1067)")
    flip_channels: bool = F(False, BOOL, "dicom-ct-pd: the series numbers its channels opposite to the "
                            "DICOM-CT-PD convention (docs/measured-conventions.md 'Channel and row numbering')")
    flip_rows: bool = F(False, BOOL, "dicom-ct-pd: the series numbers its detector rows opposite to the "
                        "DICOM-CT-PD convention")
    pixel_layout: str = F("auto", one_of(PIXEL_LAYOUTS), "dicom-ct-pd: which detector axis the DICOM Rows run "
                          "along; auto: decided from the tags (docs/measured-conventions.md 'Pixel layout')")
    orientation: str = F("tags", one_of(("tags", "auto")), "dicom-ct-pd: 'tags' reads the numbering the series "
                         "declares and refuses it when the data fit a mirror better; 'auto' takes the best fit "
                         "(docs/measured-conventions.md 'Orientation check')")
    patient_position: str = F("", one_of(PATIENT_POSITIONS), "patient position (DICOM (0018,5100)); '': from the "
                              "series (dicom-ct-pd), HFS for a simulated scan (docs/measured-conventions.md 'Patient "
                              "position and the image frame')")
    rotation: str = F("increasing", one_of(("increasing", "decreasing")), "gantry angle from view to view "
                      "(a measured series gives it)")
    table_direction: str = F("increasing", one_of(("increasing", "decreasing")), "source z from view to view "
                             "(a measured series gives it)")

    PATH_KEYS: ClassVar[tuple] = ("projections",)

    @property
    def measured_source(self) -> bool:
        """True for a measured scan (the projections are read from files, not simulated)."""
        return self.source != "simulated"

    def check(self) -> None:
        if self.source == "dicom-ct-pd" and not self.projections:
            raise SceneError("scan.projections = '': scan.source = 'dicom-ct-pd' needs the folder of projection files")
        if self.source == "simulated":  # the measured-scan keys do nothing here: say so rather than ignore them
            for key, off in (("projections", ""), ("timestamp_unit", "ms"), ("flip_channels", False),
                             ("flip_rows", False), ("pixel_layout", "auto"), ("orientation", "tags")):
                if getattr(self, key) != off:
                    raise SceneError(f"scan.{key} = {getattr(self, key)!r}: only used with scan.source = "
                                     f"'dicom-ct-pd' (a measured scan); this scene is simulated")


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
        """Source z of the first view (mm): the low end of the travel, the high end when the table runs -z."""
        return self.z_centre_mm - self.table_sign * self.travel_mm(scanner, pitch) / 2.0

    @property
    def rotation_sign(self) -> int:
        """+1 when the gantry angle increases from view to view, -1 when it decreases."""
        return 1 if self.rotation == "increasing" else -1

    @property
    def table_sign(self) -> int:
        """+1 when the source z increases from view to view, -1 when it decreases."""
        return 1 if self.table_direction == "increasing" else -1

    def duration_s(self, scanner: ScannerConfig, pitch: float) -> float:
        return self.projection_count(scanner, pitch) * scanner.rotation_time_s / scanner.views_per_rotation


@dataclass(frozen=True, kw_only=True)
class SignalsConfig(Section):
    """Breathing and heart rhythm (docs/simulation.md "Breathing and heart rhythm"; Lujan 1999 breathing model)."""

    SECTION = "signals"

    seed: int = F(1, SEED, "seed of the breathing and rhythm irregularities")
    resp_period_s: float = F(5.0, number_in(1.0, 30.0, "s", "human breathing: 2-8 s at rest, 1 s at 60 breaths "
                                            "a minute"), "mean breathing period")
    resp_period_cv: float = F(0.15, number_in(0.0, 0.5, "", "a CV above 50 % is no longer one breathing rhythm"),
                              "cycle-to-cycle coefficient of variation of the period")
    resp_depth_cv: float = F(0.15, number_in(0.0, 0.5, "", "a CV above 50 % is no longer one breathing depth"),
                             "cycle-to-cycle coefficient of variation of the depth")
    resp_exponent: int = F(2, integer_in(1, 4, "n of Lujan's cos^(2n) model; 1-3 in use"),
                           "n in cos^(2n): larger gives a longer end-exhale dwell")
    resp_drift: float = F(0.05, number_in(0.0, 0.5, "", "a fraction of the mean depth"),
                          "slow baseline drift, as a fraction of the mean depth, peak to peak")
    breath_hold: bool = F(False, BOOL, "no breathing: amplitude constant at breath_hold_amplitude")
    breath_hold_amplitude: float = F(0.5, FRAC, "normalised amplitude during a breath hold")
    rr_s: float = F(0.75, number_in(0.3, 2.0, "s", "heart rates of 30-200 beats a minute"), "mean R-R interval")
    rhythm: str = _f("periodic", "one of " + ", ".join(RHYTHMS), lambda x: x in RHYTHMS,
                     "periodic; hrv (3 % sinus variability); af (i.i.d. R-R); pvc (ectopic beats)")
    rr_cv: float = F(0.0, number_in(0.0, 0.4, "", "atrial fibrillation: ~20 %"),
                     "R-R coefficient of variation for hrv/af (0: the rhythm's default)")
    ectopic_rate: float = F(0.0, number_in(0.0, 0.5, "", "bigeminy: every other beat"),
                            "fraction of beats that are premature (pvc rhythm)")
    frame_time_s: float = F(0.0, zero_or_in(0.001, 60.0, "s", "4D phantom frames last 10-100 ms"),
                            "0: continuous motion; > 0: motion frozen in phantom frames of this length")
    breathing_trace: str = F("", STR, "recorded breathing trace (Varian RPM .vxp, or CSV time_s,amplitude) in place of "
                             "the breathing model (clrecon.scan.recorded)")
    ecg_trace: str = F("", STR, "recorded ECG (CSV of R-peak times r_peak_s, or a WFDB record .hea) in place of the "
                       "rhythm model")
    trace_align: str = F("offset", one_of(("offset", "beam-on")), "breathing trace time of scan time 0: "
                         "trace_offset_s, or the first beam-on (ttlin = 1) sample of the .vxp plus trace_offset_s")
    trace_offset_s: float = F(0.0, OFFSET_S, "breathing trace time (s) at scan time 0 (added to the beam-on time "
                              "with trace_align = 'beam-on')")
    ecg_offset_s: float = F(0.0, OFFSET_S, "ECG time (s) at scan time 0")
    breathing_inhale: str = F("up", one_of(("up", "down")), "the recorded amplitude rises ('up') or falls ('down') "
                              "on inhalation")

    PATH_KEYS: ClassVar[tuple] = ("breathing_trace", "ecg_trace")

    def check(self) -> None:
        for key, what in (("breathing_trace", "a Varian RPM .vxp or a time_s,amplitude CSV"),
                          ("ecg_trace", "a CSV of r_peak_s or a WFDB record's .hea")):
            path = getattr(self, key)
            if path and not trace_files(path):
                raise SceneError(f"signals.{key} = {path!r}: no such file (expected {what})")
        if not self.breathing_trace:  # the trace keys do nothing without a trace: say so rather than ignore them
            for key, off in (("trace_align", "offset"), ("breathing_inhale", "up")):
                if getattr(self, key) != off:
                    raise SceneError(f"signals.{key} = {getattr(self, key)!r}: only used with "
                                     f"signals.breathing_trace (a recorded breathing trace); none is given")


class MotionFlags(Protocol):
    """Which motions the phantom has (a phantom section has these two flags)."""

    @property
    def cardiac_motion(self) -> bool: ...
    @property
    def respiratory_motion(self) -> bool: ...


class Acquisition(Protocol):
    """What the scan stage needs of a scene: scanner, protocol, signals, motion flags, trace length, source.

    :class:`clrecon.config.scene.Scene` satisfies it; so does any object with these attributes.
    ``trace_duration_s`` (s) is the length of the signal trace the amplitude is normalised over
    (``docs/conventions.md`` "Respiratory amplitude"); ``measured`` is true for a measured scan
    (``scan.source`` not 'simulated', ``docs/measured-data.md``).
    """

    @property
    def name(self) -> str: ...
    @property
    def scanner(self) -> ScannerConfig: ...
    @property
    def scan(self) -> ScanConfig: ...
    @property
    def signals(self) -> SignalsConfig: ...
    @property
    def phantom(self) -> MotionFlags: ...
    @property
    def trace_duration_s(self) -> float: ...
    @property
    def measured(self) -> bool: ...
