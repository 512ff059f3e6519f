"""The built-in analytic thorax A(c, a) (stage 3 of the pipeline, with :mod:`clrecon.simulation.projector`).

A breathing, beating thorax made of quadric primitives with *additive* densities (the
Shepp-Logan convention): every object adds ``mu(tissue) - mu(parent tissue)``, so a nested
organ carries the difference to the structure it sits in, and no two objects that are not
parent and child overlap (a test checks it at several states). ``c`` is the cardiac phase
in [0, 1) (0 = end-diastole, the R peak), ``a`` the respiratory amplitude in [0, 1]
(0 = end-exhale, 1 = end-inhale; the XCAT convention, as in :mod:`clrecon.scan.signals`).
World frame LPS (+x patient left, +y posterior, +z superior), mm, mu in 1/mm.

Primitives (one packed row of ``STRIDE`` float64 each, layout below):

- an ellipsoid ``|D^-1 R^T (x - c)| <= 1`` or a finite elliptic cylinder (the same in the
  first two local axes and ``|local z| <= 1`` along the third; semi-axis 3 = half length);
- intersected with up to two half-spaces ``n . x <= d`` (world frame);
- and with the inside (``CUT_INTERSECT``) or the outside (``CUT_SUBTRACT``) of up to two
  more ellipsoids ("cuts"). The lungs are the pleural cavity minus the diaphragm dome and
  minus the heart; the right ventricle is an ellipsoid minus the left ventricle. Along a
  ray every cut is one interval, so line integrals stay closed-form and exact.

Every number the anatomy is built from is a row of the one table ``PARAMETERS`` (value,
unit, source key into ``PARAMETER_SOURCES``, note). Motion:

- breathing (``a``): the diaphragm dome and the liver move ``diaphragm_si_mm * a``
  inferiorly; the chest wall expands ``chest_ap_mm * a`` anteriorly about the fixed back
  (skin, muscle, ribs, sternum, pleural cavity and the dome's AP size follow one affine
  map ``y -> y_back - (y_back - y) k(a)``); the lung darkens from -760 to -840 HU; the
  heart translates ``heart_si_fraction`` of the diaphragm motion inferiorly and a quarter of
  it anteriorly (XCAT: 20 mm SI, 5 mm AP);
- the beat (``c``): the LV cavity follows :func:`lv_blood_volume_ml` (truncated prolate
  ellipsoid, apex fixed, base descending ~11 mm), the LV wall thickens at constant
  myocardial volume, the RV follows the same curve (approximately), the atria fill while
  the ventricles empty, and the aortic root and the coronaries ride on the moving surfaces.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from types import MappingProxyType

import numpy as np

from clrecon.core.config import BOOL, FRAC, F, Section, number_in
from clrecon.core.conventions import MU_WATER_PER_MM, MU_WATER_RANGE_PER_MM, MU_WATER_WHY
from clrecon.core.runtime import aligned_empty
from clrecon.simulation.phantoms.layout import (  # noqa: F401
    AXES,
    CENTRE,
    CUT0,
    CUT_INTERSECT,
    CUT_LEN,
    CUT_NONE,
    CUT_SUBTRACT,
    KIND,
    KIND_CYLINDER,
    KIND_ELLIPSOID,
    KIND_NONE,
    MU,
    N_CUTS,
    N_PLANES,
    PLANES,
    SEMI,
    STRIDE,
    cut_fields,
)
from clrecon.simulation.voxelise import voxelise_objects


# ---------------------------------------------------------------------------------------
@dataclass(frozen=True, kw_only=True)
class PhantomConfig(Section):
    """The built-in analytic thorax (``[phantom] kind = "analytic"``). Motion amplitudes in mm."""

    SECTION = "phantom"

    kind: str = F("analytic", ("analytic", lambda x: x == "analytic"), "phantom source (registry PHANTOM_SOURCES)")
    cardiac_motion: bool = F(True, BOOL, "heart beats")
    respiratory_motion: bool = F(True, BOOL, "thorax breathes")
    diaphragm_si_mm: float = F(20.0, number_in(0, 40, "mm", "10-20 mm quiet, up to ~40 mm deep breathing"),
                               "diaphragm excursion end-exhale -> end-inhale")
    chest_ap_mm: float = F(12.0, number_in(0, 30, "mm", "5-15 mm quiet breathing"), "chest AP expansion")
    heart_si_fraction: float = F(0.6, FRAC, "heart SI motion / diaphragm motion")
    mu_water_per_mm: float = F(MU_WATER_PER_MM, number_in(*MU_WATER_RANGE_PER_MM, "/mm", MU_WATER_WHY),
                               "attenuation of water (1/mm)")
    metal_insert: bool = F(False, BOOL, "add a small metal-like (steel) insert near the spine")


# ---------------------------------------------------------------------------------------
#: Sources cited in the parameter table (docs/simulation.md "Analytic phantom" summarises them).
PARAMETER_SOURCES = MappingProxyType({
    "XCAT": "Segars et al., Med Phys 37:4902 (2010), XCAT sample-parameter defaults",
    "FORBILD": "FORBILD thorax phantom (Sourbelle, Erlangen): layout and proportions, scaled",
    "LV": "LV/RV volumes and kinematics: EDV ~130 / ESV ~55 mL, EF ~58 %, prolate LV, "
          "half-cosine systole, atrial kick ~7 % of SV (reference table, lit.)",
    "HU": "120 kVp attenuation table of the reference (lit.)",
    "NIST": "NIST XCOM: iron mu/rho ~0.83 cm^2/g at 70 keV x 7.87 g/cm^3 = 0.65 /mm",
    "lit": "commonly quoted anatomical range",
    "design": "our choice, made to satisfy the stated constraints (FOV, scan range, no overlap)",
})


@dataclass(frozen=True)
class Parameter:
    """One row of the phantom's parameter table."""

    name: str
    value: float
    unit: str
    source: str
    note: str = ""


_R = Parameter
#: THE parameter table: every number the phantom is built from. Lengths in mm (LPS, at
#: end-exhale), angles in degrees. "Heart frame" = (xi along the LV long axis, base -> apex;
#: eta perpendicular, towards the RV (right-anterior); zeta = xi x eta), origin at the
#: end-diastolic LV centre.
PARAMETERS: tuple = (
    # -- attenuation (HU at 120 kVp; mu = mu_water (1 + HU/1000)) --------------------------
    _R("hu_air", -1000, "HU", "HU", "outside the body, trachea"),
    _R("hu_fat", -100, "HU", "HU", "subcutaneous and epicardial fat"),
    _R("hu_muscle", 45, "HU", "HU", "chest wall, diaphragm, mediastinal soft tissue: 40-50"),
    _R("hu_lung_exhale", -760, "HU", "HU", "inflated lung -700..-900; denser at end-exhale"),
    _R("hu_lung_inhale", -840, "HU", "HU", "more air at end-inhale"),
    _R("hu_liver", 60, "HU", "HU", "liver ~60"),
    _R("hu_myocardium", 90, "HU", "HU", "enhanced myocardium 80-100"),
    _R("hu_blood_left", 400, "HU", "HU", "LV, LA, aorta, coronary lumen with CTA contrast: 300-450"),
    _R("hu_blood_right", 320, "HU", "HU", "RV, RA: contrast diluted by venous return, 300-450"),
    _R("hu_cortical_bone", 1200, "HU", "HU", "cortical bone 1000-1500"),
    _R("hu_trabecular_bone", 250, "HU", "HU", "trabecular bone / marrow 150-300"),
    _R("hu_neural_arch", 700, "HU", "HU", "laminae + spinous process: cortex and marrow averaged"),
    _R("hu_rib", 700, "HU", "HU", "thin cortex + marrow averaged over a 9 mm rib"),
    _R("hu_sternum", 450, "HU", "HU", "cancellous sternum with a thin cortex"),
    _R("hu_metal", 32000, "HU", "NIST", "steel, 0.65 /mm at ~70 keV (>= 3000 HU asked)"),
    # -- body and chest wall -------------------------------------------------------------
    _R("body_semi_lr", 160.0, "mm", "FORBILD", "thorax 20 x 10 cm, LR scaled to fit the 187 mm FOV"),
    _R("body_semi_ap", 110.0, "mm", "FORBILD", "the back (y = +110) stays on the table"),
    _R("body_half_length", 300.0, "mm", "design", "z in [-300, 300]: no scan sees the ends"),
    _R("fat_thickness", 12.0, "mm", "lit", "subcutaneous fat"),
    _R("heart_ap_per_si", 0.25, "1", "XCAT", "heart AP / diaphragm SI motion (XCAT 5 / 20 mm)"),
    # -- pleural cavity (lungs) ----------------------------------------------------------
    _R("cavity_semi_lr", 122.0, "mm", "FORBILD", "pleural cavity inside the ribs"),
    _R("cavity_semi_ap", 78.0, "mm", "FORBILD", "posterior edge in front of the neural arches"),
    _R("cavity_z_bottom", -140.0, "mm", "design", "above the dome centre: the dome cuts the lungs"),
    _R("cavity_z_top", 230.0, "mm", "design", "lung apices far above any scan"),
    _R("lung_medial_angle_left", 25.0, "deg", "design", "left medial plane normal: +x turned towards +y"),
    _R("lung_medial_angle_right", 15.0, "deg", "design", "right medial plane normal: -x turned towards +y"),
    _R("lung_margin", 3.0, "mm", "design", "pleura + tissue between lung and mediastinal organs"),
    # -- diaphragm dome and liver --------------------------------------------------------
    _R("dome_semi_lr", 127.0, "mm", "FORBILD", "large 'diaphragm' ellipsoid, inside the ribs"),
    _R("dome_semi_ap", 80.0, "mm", "FORBILD", "expands with the chest wall"),
    _R("dome_semi_si", 115.0, "mm", "FORBILD", ""),
    _R("dome_tilt", 8.0, "deg", "lit", "right hemidiaphragm higher than the left"),
    _R("dome_centre_z", -141.0, "mm", "design", "right liver dome top at z ~ -37 (exhale) .. -57 (inhale)"),
    _R("diaphragm_thickness", 4.0, "mm", "lit", "muscle sheet between lung and liver"),
    _R("liver_medial_x", 20.0, "mm", "design", "liver = dome right of x = 20 mm ..."),
    _R("liver_spine_angle", 48.0, "deg", "design", "... and in front of a plane clear of spine and aorta"),
    # -- spine ---------------------------------------------------------------------------
    _R("vertebra_semi_lr", 21.0, "mm", "FORBILD", "vertebral body r ~ 17.5 mm, elliptic"),
    _R("vertebra_semi_ap", 15.0, "mm", "FORBILD", ""),
    _R("vertebra_y", 46.0, "mm", "FORBILD", "FORBILD y = -5 cm, scaled"),
    _R("vertebra_height", 23.0, "mm", "lit", "thoracic vertebral body height"),
    _R("vertebra_pitch", 28.0, "mm", "lit", "body + intervertebral disc"),
    _R("vertebra_count", 13, "1", "design", "z in [-180, 180]: beyond any scan"),
    _R("cortex_thickness", 2.0, "mm", "lit", "vertebral cortical shell"),
    _R("arch_semi_lr", 25.0, "mm", "lit", "neural arch (laminae + spinous process), one cylinder"),
    _R("arch_semi_ap", 8.0, "mm", "lit", ""),
    _R("arch_y", 89.0, "mm", "lit", "behind a ~19 mm spinal canal"),
    _R("arch_height", 18.0, "mm", "lit", ""),
    # -- ribs and sternum ----------------------------------------------------------------
    _R("rib_ellipse_lr", 134.0, "mm", "FORBILD", "rib centre line: ellipse a ~ 18.5 cm, scaled"),
    _R("rib_ellipse_ap", 86.0, "mm", "FORBILD", "b ~ 9 cm, scaled"),
    _R("rib_radius", 4.5, "mm", "lit", "rib cross-section ~ 9 mm"),
    _R("rib_pairs", 9, "1", "design", "posterior ends z in [-90, 135], anterior ends 45 mm lower"),
    _R("rib_spacing", 28.0, "mm", "lit", "one rib per vertebra"),
    _R("rib_drop", 45.0, "mm", "lit", "anterior end lower than the posterior end"),
    _R("rib_start", 18.0, "deg", "design", "angle from the posterior midline (rib head)"),
    _R("rib_end", 140.0, "deg", "design", "costal cartilage beyond is not modelled"),
    _R("rib_segments", 4, "1", "design", "mitred cylinder segments per rib"),
    _R("sternum_semi_lr", 14.0, "mm", "FORBILD", "sternum at (0, 9 cm) in FORBILD"),
    _R("sternum_semi_ap", 6.0, "mm", "FORBILD", ""),
    _R("sternum_y", -90.0, "mm", "FORBILD", ""),
    _R("sternum_z_bottom", -110.0, "mm", "design", ""),
    _R("sternum_z_top", 130.0, "mm", "design", ""),
    # -- airway and great vessels --------------------------------------------------------
    _R("trachea_radius", 9.0, "mm", "lit", ""),
    _R("trachea_y", 5.0, "mm", "design", "in front of the oesophagus and spine"),
    _R("trachea_z_bottom", 90.0, "mm", "design", "carina above the atria"),
    _R("desc_aorta_radius", 11.0, "mm", "FORBILD", "r = 1 cm"),
    _R("desc_aorta_x", 36.0, "mm", "FORBILD", "left-anterior of the spine"),
    _R("desc_aorta_y", 34.0, "mm", "FORBILD", ""),
    _R("asc_aorta_radius", 14.0, "mm", "lit", "ascending aorta ~ 28 mm"),
    _R("asc_aorta_top_x", -24.0, "mm", "design", "top of the ascending aorta (moves with the heart)"),
    _R("asc_aorta_top_y", -34.0, "mm", "design", ""),
    _R("asc_aorta_top_z", 140.0, "mm", "design", "the arch is above any scan"),
    # -- heart position and orientation --------------------------------------------------
    _R("heart_x", 14.0, "mm", "design", "ED LV centre at end-exhale: left, anterior, z ~ 0"),
    _R("heart_y", -20.0, "mm", "design", ""),
    _R("heart_z", 6.0, "mm", "design", ""),
    _R("heart_azimuth", 55.0, "deg", "lit", "long axis 55 deg left of the sagittal plane"),
    _R("heart_elevation", 35.0, "deg", "lit", "apex 35 deg below the axial plane"),
    # -- LV: truncated prolate ellipsoid, base (mitral) plane at +0.4 a from the centre ----
    _R("lv_edv", 130.0, "mL", "LV", "end-diastolic volume"),
    _R("lv_esv", 54.0, "mL", "LV", "end-systolic volume: EF 58.5 %"),
    _R("lv_length_ed", 85.0, "mm", "lit", "apex to mitral plane at ED"),
    _R("lv_long_shortening", 13.0, "mm", "LV", "~13 mm long-axis shortening ED -> ES"),
    _R("lv_base_cut", 0.4, "1", "design", "mitral plane at 0.4 a beyond the cavity centre"),
    _R("lv_wall_ed", 10.0, "mm", "LV", "wall ~10 mm at ED, thickening in systole"),
    _R("lv_apex_wall_ed", 9.0, "mm", "lit", "apical wall at ED"),
    _R("lv_apex_wall_es", 11.0, "mm", "lit", "apical wall at ES; constant myocardial volume sets the rest"),
    # -- cardiac cycle, fractions of the R-R interval ------------------------------------
    _R("c_ejection_start", 0.03, "RR", "lit", "end of isovolumic contraction"),
    _R("c_end_systole", 0.38, "RR", "LV", "ES at 0.35-0.40; half-cosine ejection over 0.35 RR"),
    _R("c_filling_start", 0.44, "RR", "lit", "end of isovolumic relaxation"),
    _R("c_rapid_end", 0.62, "RR", "lit", "end of rapid filling"),
    _R("rapid_refill", 0.75, "1", "lit", "fraction of the stroke volume refilled rapidly"),
    _R("c_kick_start", 0.85, "RR", "LV", "atrial kick: 7 % of SV, peak inflow at ~0.92 RR"),
    _R("atrial_kick", 0.07, "1", "LV", ""),
    # -- RV: crescent = ellipsoid minus the LV epicardial ellipsoid -----------------------
    _R("rv_edv", 140.0, "mL", "LV", "RV 140 / 65 mL: the crescent follows them approximately"),
    _R("rv_esv", 65.0, "mL", "LV", ""),
    _R("rv_xi", -8.0, "mm", "design", "RV cavity centre along the long axis, heart frame, at ED"),
    _R("rv_semi_xi", 58.0, "mm", "design", "RV cavity ellipsoid semi-axis along the long axis, ED"),
    _R("rv_semi_zeta", 48.0, "mm", "design", "... across the septum (breadth of the crescent), ED"),
    _R("rv_septal_eta", -6.0, "mm", "design", "septal end of the cavity ellipsoid (hidden in the LV)"),
    _R("rv_depth_ed", 21.5, "mm", "design", "free wall beyond the LV epicardium: calibrated to 140 mL"),
    _R("rv_depth_es", 10.6, "mm", "design", "... calibrated to 65 mL (tests check both)"),
    _R("rv_wall", 4.0, "mm", "lit", "RV free wall 3-5 mm"),
    # -- atria (blood pools; walls not modelled) -----------------------------------------
    _R("atrium_min", 32.0, "mL", "lit", "atria 30-60 mL"),
    _R("atrium_max", 58.0, "mL", "lit", ""),
    _R("atrium_shape_xi", 0.85, "1", "design", "atrial semi-axes / r (product 1: volume 4/3 pi r^3)"),
    _R("atrium_shape_eta", 0.9, "1", "design", ""),
    _R("atrium_shape_zeta", 1.307, "1", "design", ""),
    _R("la_eta", -10.0, "mm", "design", "LA: posterior-left beyond the mitral plane"),
    _R("la_zeta", -3.0, "mm", "design", ""),
    _R("ra_eta", 40.0, "mm", "design", "RA: right beyond the tricuspid plane"),
    _R("ra_zeta", 6.0, "mm", "design", ""),
    _R("atrium_gap", 1.0, "mm", "design", "clearance between atrium and AV plane"),
    _R("root_eta", 14.0, "mm", "design", "aortic root on the AV plane, between the atria"),
    _R("root_zeta", -24.0, "mm", "design", ""),
    # -- epicardial fat envelope (heart frame; holds the beating heart) -------------------
    _R("env_xi", 1.0, "mm", "design", "centre"),
    _R("env_eta", 15.0, "mm", "design", ""),
    _R("env_zeta", 0.0, "mm", "design", ""),
    _R("env_semi_xi", 76.0, "mm", "design", "semi-axes"),
    _R("env_semi_eta", 62.5, "mm", "design", ""),
    _R("env_semi_zeta", 65.0, "mm", "design", ""),
    _R("env_clearance", 1.5, "mm", "design", "envelope trimmed this far from sternum, spine, aorta"),
    # -- coronary arteries: mitred cylinder chains on the epicardium ----------------------
    _R("coronary_radius", 1.75, "mm", "lit", "proximal lumen ~3.5 mm"),
    _R("coronary_clearance", 0.5, "mm", "design", "gap to the myocardium (+ chord sag)"),
    _R("lad_azimuth_base", -122.0, "deg", "design", "anterior interventricular groove on the LV:"
       " azimuth near the base ..."),
    _R("lad_azimuth_apex", -92.0, "deg", "design", "... and near the apex (0 = towards the RV)"),
    _R("lcx_azimuth", -145.0, "deg", "design", "left AV groove, lateral-posterior"),
    # -- target lesion in the LV wall (the localisation metric, clrecon.evaluation.motion) --
    _R("hu_lesion", 1000, "HU", "design", "hyperdense (calcified-scar-like) target, 600 HU above the contrast "
       "blood next to it: a threshold between the two isolates it (a +150 HU lesion, 240 HU, would sit "
       "below the 400 HU blood pool and could not be told from it)"),
    _R("lesion_radius", 4.5, "mm", "design", "9 mm sphere (~10 mm target): 0.5 mm inside the 10 mm "
       "end-diastolic wall, whose thinnest state it is"),
    _R("lesion_azimuth", -145.0, "deg", "design", "lateral (LCx-territory) wall at the LV equator, mid-wall: "
       "its centre 12-14 mm above the LV centre, inside the demo slab (|z| <= 30) at every state"),
    # -- metal insert --------------------------------------------------------------------
    _R("metal_radius", 3.0, "mm", "design", "pedicle-screw-like cylinder r ~3 mm"),
    _R("metal_half_length", 9.0, "mm", "design", "AP axis, inside the vertebral body at z = 0"),
    _R("metal_x", 8.0, "mm", "design", ""),
)
del _R
#: name -> value view of ``PARAMETERS``.
P = MappingProxyType({r.name: float(r.value) for r in PARAMETERS})

def hu_mu(hu, mu_water):
    """HU -> mu (1/mm), float64."""
    return mu_water * (1.0 + np.asarray(hu, dtype=np.float64) / 1000.0)


# ---------------------------------------------------------------------------------------
# the cardiac volume curve
def lv_ejected_fraction(c) -> np.ndarray:
    """Fraction of the stroke volume out of the LV at cardiac phase ``c`` (0 at ED, 1 at ES).

    Isovolumic contraction to 0.03 RR, half-cosine ejection over 0.35 RR ending at ES
    (0.38 RR), isovolumic relaxation to 0.44, half-cosine rapid filling of 75 % of the stroke
    volume to 0.62, linear diastasis, half-cosine atrial kick of 7 % from 0.85 RR (peak
    inflow at 0.925 RR). ``c`` any shape, taken modulo 1; float64 of the same shape.
    """
    c = np.mod(np.asarray(c, dtype=np.float64), 1.0)
    c0, ces, cf, cr, ck = (P["c_ejection_start"], P["c_end_systole"], P["c_filling_start"],
                           P["c_rapid_end"], P["c_kick_start"])
    refill, kick = P["rapid_refill"], P["atrial_kick"]

    def hc(x):  # half-cosine ramp 0 -> 1 over x in [0, 1]
        return 0.5 * (1.0 - np.cos(np.pi * np.clip(x, 0.0, 1.0)))

    f = np.zeros_like(c)
    f = np.where((c >= c0) & (c < ces), hc((c - c0) / (ces - c0)), f)
    f = np.where((c >= ces) & (c < cf), 1.0, f)
    f = np.where((c >= cf) & (c < cr), 1.0 - refill * hc((c - cf) / (cr - cf)), f)
    f = np.where((c >= cr) & (c < ck), (1.0 - refill) + (kick - (1.0 - refill)) * (c - cr) / (ck - cr), f)
    f = np.where(c >= ck, kick * (1.0 - hc((c - ck) / (1.0 - ck))), f)
    return f


def lv_blood_volume_ml(c) -> np.ndarray:
    """LV blood-pool volume (mL) at cardiac phase ``c`` (any shape): EDV at 0, ESV at 0.38-0.44."""
    return P["lv_edv"] - (P["lv_edv"] - P["lv_esv"]) * lv_ejected_fraction(c)


def rv_blood_volume_ml(c) -> np.ndarray:
    """Nominal RV blood volume (mL): the LV curve scaled to 140 / 65 mL (the crescent follows it roughly)."""
    return P["rv_edv"] - (P["rv_edv"] - P["rv_esv"]) * lv_ejected_fraction(c)


def atrial_volume_ml(c) -> np.ndarray:
    """Blood volume of each atrium (mL): largest at ES (reservoir), smallest at ED (after the kick)."""
    return P["atrium_min"] + (P["atrium_max"] - P["atrium_min"]) * lv_ejected_fraction(c)


def _trunc_volume(a, b, h):
    """Volume (mm^3) of the prolate ellipsoid (semi-axis a along its axis, b across) kept for axial <= h."""
    h = np.minimum(h, a)
    return np.pi * b * b * (a * a * (h + a) - (h ** 3 + a ** 3) / 3.0) / (a * a)


def lv_shape(c):
    """LV cavity and epicardial semi-axes (mm) at phase ``c`` (arrays of c's shape).

    Returns ``(a, b, a_out, b_out)``. The cavity is a prolate ellipsoid cut at
    ``lv_base_cut * a`` beyond its centre (the mitral plane); its length ``(1 + cut) a``
    shortens linearly with the ejected fraction and ``b`` follows from the volume curve.
    The epicardium is concentric and cut by the same plane; its apical wall thickens
    linearly and ``b_out`` keeps the myocardial volume at its end-diastolic value.
    """
    f = lv_ejected_fraction(c)
    k = 1.0 + P["lv_base_cut"]
    frac = _trunc_volume(1.0, 1.0, P["lv_base_cut"]) / (4.0 / 3.0 * np.pi)
    a = (P["lv_length_ed"] - P["lv_long_shortening"] * f) / k
    vol = lv_blood_volume_ml(c) * 1000.0
    b = np.sqrt(vol / (frac * 4.0 / 3.0 * np.pi * a))
    a_ed = P["lv_length_ed"] / k
    b_ed = math.sqrt(P["lv_edv"] * 1000.0 / (frac * 4.0 / 3.0 * math.pi * a_ed))
    v_myo = _trunc_volume(a_ed + P["lv_apex_wall_ed"], b_ed + P["lv_wall_ed"], P["lv_base_cut"] * a_ed) \
        - P["lv_edv"] * 1000.0
    a_out = a + P["lv_apex_wall_ed"] + (P["lv_apex_wall_es"] - P["lv_apex_wall_ed"]) * f
    b_out = np.sqrt((vol + v_myo) / _trunc_volume(a_out, 1.0, P["lv_base_cut"] * a))
    return a, b, a_out, b_out


# ---------------------------------------------------------------------------------------
# small geometry helpers (all vectorised over leading axes)
def _unit(v):
    v = np.asarray(v, dtype=np.float64)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _dot(u, v):
    return np.einsum("...i,...i->...", u, v)


def heart_axes():
    """Heart frame unit vectors (xi: base -> apex, eta: towards the RV, zeta = xi x eta), each (3,)."""
    az, el = np.deg2rad(P["heart_azimuth"]), np.deg2rad(P["heart_elevation"])
    xi = np.array([np.sin(az) * np.cos(el), -np.cos(az) * np.cos(el), -np.sin(el)])
    eta = np.array([-np.cos(az), -np.sin(az), 0.0])  # right-anterior, perpendicular to xi
    return xi, eta, np.cross(xi, eta)


def _frame(*cols):
    """Rotation matrices (..., 3, 3) whose columns are the given (..., 3) axes."""
    return np.stack(np.broadcast_arrays(*cols), axis=-1)


def _axis_frame(axis):
    """Right-handed frames (..., 3, 3) whose third column is the unit vector along ``axis``."""
    w = _unit(axis)
    helper = np.where(np.abs(w[..., 2:3]) < 0.9, np.array([0.0, 0.0, 1.0]), np.array([1.0, 0.0, 0.0]))
    u = _unit(np.cross(helper, w))
    return _frame(u, np.cross(w, u), w)


def support(kind, centre, axes, semi, n):
    """Support function: max over the primitive (clips ignored) of ``n . x``, shape (...,).

    ``centre`` (..., 3), ``axes`` (..., 3, 3) with columns = local axes, ``semi`` (..., 3),
    ``n`` (..., 3) unit.
    """
    q = np.einsum("...ji,...j->...i", axes, n) * semi  # D R^T n
    if kind == KIND_ELLIPSOID:
        return _dot(centre, n) + np.linalg.norm(q, axis=-1)
    return _dot(centre, n) + np.linalg.norm(q[..., :2], axis=-1) + np.abs(q[..., 2])


@dataclass
class _Obj:
    """One posed primitive; arrays broadcast against the m states."""

    name: str
    parent: str
    kind: int
    hu: np.ndarray
    centre: np.ndarray
    axes: np.ndarray
    semi: np.ndarray
    planes: list          # [(n (..., 3), d (...)), ...] <= 2
    cuts: list            # [(mode, centre, axes, semi), ...] <= 2


_EYE = np.eye(3)


class Phantom:
    """The analytic thorax of a :class:`~clrecon.config.scene.PhantomConfig`.

    Parameters
    ----------
    cfg : PhantomConfig, optional
        Motion switches and amplitudes, mu of water, metal insert. Default ``PhantomConfig()``.

    Notes
    -----
    ``cardiac_motion = False`` freezes the heart at c = 0 (end-diastole) and
    ``respiratory_motion = False`` freezes breathing at a = 0 (end-exhale), whatever state is
    asked for. The object list (``names``, ``parents``: the object whose tissue each one
    replaces, or ``"air"``) is fixed per config.
    """

    def __init__(self, cfg: PhantomConfig | None = None):
        self.cfg = cfg if cfg is not None else PhantomConfig()
        objs = self._build(np.zeros(1), np.zeros(1))
        self.names = tuple(o.name for o in objs)
        self.parents = tuple(o.parent for o in objs)
        self.tissue_hu = {o.name: float(np.asarray(o.hu).reshape(-1)[0]) for o in objs}
        self._states: dict[tuple[float, float], np.ndarray] = {}  # objects() cache, see prefetch

    def __repr__(self) -> str:
        return f"Phantom({self.cfg!r})"

    # -- public API ------------------------------------------------------------------------
    @property
    def n_objects(self) -> int:
        return len(self.names)

    #: States kept by :meth:`objects` (about 45 kB each).
    STATE_CACHE = 1024

    def objects(self, c: float, a: float) -> np.ndarray:
        """Packed objects at one state, (n_obj, STRIDE) float64 (layout: module constants).

        States are kept (up to :data:`STATE_CACHE`), so the truths and metrics of a target,
        which each pose the phantom at it, pose it once; :meth:`prefetch` poses many states
        in one vectorised call (50 targets: 0.15 s instead of 4 s). Returns a copy.
        """
        key = (float(c), float(a))
        hit = self._states.get(key)
        if hit is None:
            hit = self.objects_batch(np.atleast_1d(c), np.atleast_1d(a))[0]
            self._keep(key, hit)
        return hit.copy()

    def prefetch(self, c, a) -> None:
        """Pose the phantom at the states ``c``, ``a`` (m,) in one call, for :meth:`objects`.

        The batch gives the same numbers as one state at a time (every step is elementwise
        over states; checked in the tests).
        """
        c = np.atleast_1d(np.asarray(c, dtype=np.float64))
        a = np.atleast_1d(np.asarray(a, dtype=np.float64))
        todo = [k for k in range(c.size) if (float(c[k]), float(a[k])) not in self._states]
        if todo:
            objs = self.objects_batch(c[todo], a[todo])
            for n, k in enumerate(todo):
                self._keep((float(c[k]), float(a[k])), objs[n])

    def _keep(self, key, objs) -> None:
        if len(self._states) >= self.STATE_CACHE:
            self._states.pop(next(iter(self._states)))
        self._states[key] = objs

    def objects_batch(self, c, a) -> np.ndarray:
        """Packed objects at m states, (m, n_obj, STRIDE) float64; ``c``, ``a`` of shape (m,)."""
        c = np.atleast_1d(np.asarray(c, dtype=np.float64))
        a = np.atleast_1d(np.asarray(a, dtype=np.float64))
        if c.ndim != 1 or a.shape != c.shape:
            raise ValueError(f"c and a must be 1-D of equal length, got shapes {c.shape} and {a.shape}")
        if not (np.all(np.isfinite(c)) and np.all(np.isfinite(a))):
            raise ValueError("cardiac phase c and respiratory amplitude a must be finite")
        return self._pack(self._build(c, a), len(c))

    def mu_at(self, points, c: float, a: float) -> np.ndarray:
        """Attenuation (1/mm) at ``points`` (..., 3) mm, float64 point samples (NumPy reference)."""
        return mu_at(self.objects(c, a), points)

    def voxelise(self, c: float, a: float, x_mm, y_mm, z_mm, supersample: int = 3, rt=None) -> np.ndarray:
        """The phantom on a grid of voxel centres, mu (nz, ny, nx) float32 (1/mm).

        Each voxel is the mean of ``supersample**3`` point samples on a regular sub-grid of
        the voxel; voxel sizes are the axis spacings (a single-sample axis counts as 1 mm).
        Runs the OpenCL kernel ``kernels/voxelise.cl``.
        """
        return voxelise_objects(self.objects(c, a), x_mm, y_mm, z_mm, supersample=supersample, rt=rt)

    def lv_blood_volume_ml(self, c) -> np.ndarray:
        """LV blood-pool volume (mL) of this phantom at phase ``c`` (honours ``cardiac_motion``)."""
        c = np.asarray(c, dtype=np.float64)
        return lv_blood_volume_ml(c if self.cfg.cardiac_motion else np.zeros_like(c))

    def lv_blood_pool_centre(self, c: float, a: float) -> np.ndarray:
        """Centre of the LV cavity (x, y, z) mm at state (c, a): a seed inside the LV blood pool."""
        return self.objects(c, a)[self.names.index("lv_blood"), CENTRE].copy()

    def lesion_centre(self, c: float, a: float) -> np.ndarray:
        """Centre (x, y, z) mm of the LV-wall target lesion at state (c, a); its radius is ``P["lesion_radius"]``.

        The lesion is a sphere at the LV equator, mid-wall, at azimuth ``lesion_azimuth`` about
        the long axis (0 = towards the RV): it moves with the LV wall through the beat and
        with the heart through breathing (honours ``cardiac_motion`` / ``respiratory_motion``).
        """
        return self.objects(c, a)[self.names.index("lesion"), CENTRE].copy()

    def heart_box_mm(self, margin: float = 10.0, grid_mm: float = 3.0) -> tuple:
        """Axial box (x_min, x_max, y_min, y_max) mm holding the epicardial fat at every state.

        Found on a ``grid_mm`` grid of the trimmed envelope at end-diastole/end-systole x
        end-exhale/end-inhale, widened by ``margin`` (the default small FOV of the scenes).
        """
        i = self.names.index("epicardial_fat")
        lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
        for c in (0.0, P["c_end_systole"]):
            for a in (0.0, 1.0):
                o = self.objects(c, a)[i]
                ext = np.sqrt((o[AXES].reshape(3, 3) ** 2) @ o[SEMI] ** 2)
                axes = [np.arange(o[2 + k] - ext[k], o[2 + k] + ext[k] + grid_mm, grid_mm) for k in range(3)]
                pts = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
                pts = pts[inside(o, pts)]
                lo, hi = np.minimum(lo, pts.min(0)), np.maximum(hi, pts.max(0))
        return (float(lo[0] - margin), float(hi[0] + margin), float(lo[1] - margin), float(hi[1] + margin))

    # -- construction ------------------------------------------------------------------------
    def _pack(self, objs, m) -> np.ndarray:
        """(m, n_obj, STRIDE) float64 records of the posed objects.

        Each object's fields are written into one (m, STRIDE) block that stays in cache, and
        the block goes to the output in one copy of whole rows: writing each field straight
        into the output (its rows n_obj * STRIDE * 8 bytes apart) touched a new cache line
        per field and state, a quarter of demo's simulation (1.0 of 3.9 s at pitch 0.10)."""
        out = aligned_empty((m, len(objs), STRIDE), np.float64)  # page-aligned: the projector reads it in place
        block = np.empty((m, STRIDE))
        mw = self.cfg.mu_water_per_mm
        hu = {o.name: o.hu for o in objs}
        hu["air"] = np.asarray(P["hu_air"])
        for j, o in enumerate(objs):
            row = block
            row[...] = 0.0
            row[:, KIND] = o.kind
            row[:, MU] = np.broadcast_to(hu_mu(o.hu, mw) - hu_mu(hu[o.parent], mw), (m,))
            row[:, CENTRE] = np.broadcast_to(o.centre, (m, 3))
            row[:, AXES] = np.broadcast_to(o.axes, (m, 3, 3)).reshape(m, 9)
            row[:, SEMI] = np.broadcast_to(o.semi, (m, 3))
            row[:, 20] = row[:, 24] = 1.0  # unused planes: 0 . x <= 1
            for k, (n, d) in enumerate(o.planes):
                row[:, 17 + 4 * k:20 + 4 * k] = np.broadcast_to(n, (m, 3))
                row[:, 20 + 4 * k] = np.broadcast_to(d, (m,))
            for k in range(N_CUTS):
                mode_i, cs, ca, cm = cut_fields(k)
                if k < len(o.cuts):
                    mode, cc, cax, csemi = o.cuts[k]
                    row[:, mode_i] = mode
                    row[:, cs] = np.broadcast_to(cc, (m, 3))
                    row[:, ca] = np.broadcast_to(cax, (m, 3, 3)).reshape(m, 9)
                    row[:, cm] = np.broadcast_to(csemi, (m, 3))
                else:
                    row[:, ca] = _EYE.reshape(9)
                    row[:, cm] = 1.0
            out[:, j] = block
        return out

    def _build(self, c, a):
        """All objects posed at the states (c, a), each of shape (m,); a list of _Obj."""
        return _Thorax(self.cfg, c, a).build()


class _Thorax:
    """The thorax posed at m states, built region by region (:meth:`Phantom._build`).

    ``c``, ``a`` (m,): cardiac phase and respiratory amplitude, frozen at 0 where the config
    switches that motion off. Each region method appends its objects to ``objs``; :meth:`build`
    calls them in the order of the object list (the parents of an object come before it).
    Breathing is an affine map of the chest wall, y -> y_back - (y_back - y) k(a), a
    diaphragm descent and a heart shift (a fraction of it, plus an AP shift).
    """

    def __init__(self, cfg: PhantomConfig, c, a):
        self.cfg = cfg
        self.m = m = len(c)
        self.c = np.mod(c, 1.0) if cfg.cardiac_motion else np.zeros(m)
        self.a = a = np.clip(a, 0.0, 1.0) if cfg.respiratory_motion else np.zeros(m)
        self.objs: list = []
        self.k_ap = 1.0 + cfg.chest_ap_mm * a / (2.0 * P["body_semi_ap"])
        self.dz_diaphragm = -cfg.diaphragm_si_mm * a
        self.heart_shift = self.vec(0.0, -P["heart_ap_per_si"] * cfg.diaphragm_si_mm * a,
                                    cfg.heart_si_fraction * self.dz_diaphragm)

    def build(self) -> list:
        """All objects, in the object list's order."""
        self.body()
        self.spine()
        self.chest_wall()
        self.airway_and_descending_aorta()
        self.heart()
        self.liver()
        self.lungs()
        return self.objs

    # -- helpers ---------------------------------------------------------------------------
    def add(self, name, parent, kind, hu, centre, axes, semi, planes=(), cuts=()):
        self.objs.append(_Obj(name, parent, kind, np.asarray(hu, dtype=np.float64), np.asarray(centre, float),
                              np.asarray(axes, float), np.asarray(semi, float), list(planes), list(cuts)))

    def col(self, v):
        """(m,) or scalar -> (m, 1)."""
        return np.broadcast_to(np.asarray(v, dtype=np.float64), (self.m,))[:, None]

    def vec(self, x, y, z):
        """Scalars or (m,) -> (m, 3)."""
        return np.stack([np.broadcast_to(np.asarray(v, dtype=np.float64), (self.m,)) for v in (x, y, z)], -1)

    def chest_y(self, y):
        """The chest wall's breathing map of y (mm): y_back - (y_back - y) k(a), (m,)."""
        y_back = P["body_semi_ap"]
        return y_back - (y_back - np.asarray(y, dtype=np.float64)) * self.k_ap

    def dome(self) -> tuple:
        """(centre (m, 3), axes, semi (m, 3)) of the diaphragm dome, tilted, descending with breathing."""
        tilt = np.deg2rad(P["dome_tilt"])
        axes = _frame(np.array([np.cos(tilt), 0.0, np.sin(tilt)]), np.array([0.0, 1.0, 0.0]),
                      np.array([-np.sin(tilt), 0.0, np.cos(tilt)]))
        centre = self.vec(0.0, self.chest_y(0.0), P["dome_centre_z"] + self.dz_diaphragm)
        semi = self.vec(P["dome_semi_lr"], P["dome_semi_ap"] * self.k_ap, P["dome_semi_si"])
        return centre, axes, semi

    # -- regions ---------------------------------------------------------------------------
    def body(self):
        """Body fat and the muscle inside it: elliptic cylinders that follow the AP expansion."""
        for name, parent, tissue, t in (("body_fat", "air", "hu_fat", 0.0),
                                        ("body_muscle", "body_fat", "hu_muscle", P["fat_thickness"])):
            self.add(name, parent, KIND_CYLINDER, P[tissue], self.vec(0.0, self.chest_y(0.0), 0.0), _EYE,
                     self.vec(P["body_semi_lr"] - t, (P["body_semi_ap"] - t) * self.k_ap, P["body_half_length"]))

    def spine(self):
        """Vertebrae (cortex, marrow, neural arch; static) and the optional metal insert."""
        nv, ct = int(P["vertebra_count"]), P["cortex_thickness"]
        for k in range(nv):
            zc = (k - (nv - 1) / 2) * P["vertebra_pitch"]
            cen = np.array([0.0, P["vertebra_y"], zc])
            self.add(f"vertebra_{k}", "body_muscle", KIND_CYLINDER, P["hu_cortical_bone"], cen, _EYE,
                     [P["vertebra_semi_lr"], P["vertebra_semi_ap"], P["vertebra_height"] / 2])
            self.add(f"vertebra_{k}_marrow", f"vertebra_{k}", KIND_CYLINDER, P["hu_trabecular_bone"], cen, _EYE,
                     [P["vertebra_semi_lr"] - ct, P["vertebra_semi_ap"] - ct, P["vertebra_height"] / 2 - ct])
            self.add(f"neural_arch_{k}", "body_muscle", KIND_CYLINDER, P["hu_neural_arch"], [0.0, P["arch_y"], zc],
                     _EYE, [P["arch_semi_lr"], P["arch_semi_ap"], P["arch_height"] / 2])
            if self.cfg.metal_insert and abs(zc) < 1e-9:
                self.add("metal_insert", f"vertebra_{k}_marrow", KIND_CYLINDER, P["hu_metal"],
                         [P["metal_x"], P["vertebra_y"], zc], _axis_frame(np.array([0.0, 1.0, 0.0])),
                         [P["metal_radius"], P["metal_radius"], P["metal_half_length"]])

    def chest_wall(self):
        """Sternum and ribs (mitred cylinder chains): they follow the AP expansion."""
        chest_y, vec = self.chest_y, self.vec
        self.add("sternum", "body_muscle", KIND_CYLINDER, P["hu_sternum"],
                 vec(0.0, chest_y(P["sternum_y"]), 0.5 * (P["sternum_z_top"] + P["sternum_z_bottom"])), _EYE,
                 [P["sternum_semi_lr"], P["sternum_semi_ap"], 0.5 * (P["sternum_z_top"] - P["sternum_z_bottom"])])
        npairs, nseg = int(P["rib_pairs"]), int(P["rib_segments"])
        theta = np.deg2rad(np.linspace(P["rib_start"], P["rib_end"], nseg + 1))
        for k in range(npairs):
            z_post = (k - (npairs - 1) / 2) * P["rib_spacing"] + 0.5 * P["rib_drop"]
            for side, sname in ((-1.0, "right"), (1.0, "left")):
                drop = P["rib_drop"] * 0.5 * (1.0 - np.cos(np.pi * (theta - theta[0]) / (theta[-1] - theta[0])))
                pts = [vec(side * P["rib_ellipse_lr"] * np.sin(t), chest_y(P["rib_ellipse_ap"] * np.cos(t)),
                           z_post - dz)
                       for t, dz in zip(theta, drop, strict=True)]
                for s, seg in enumerate(mitred_chain(pts, P["rib_radius"])):
                    self.add(f"rib_{sname}_{k}_{s}", "body_muscle", KIND_CYLINDER, P["hu_rib"], *seg)

    def airway_and_descending_aorta(self):
        """Trachea and descending aorta (static cylinders)."""
        z_top = P["body_half_length"] - 10.0
        self.add("trachea", "body_muscle", KIND_CYLINDER, P["hu_air"],
                 [0.0, P["trachea_y"], 0.5 * (P["trachea_z_bottom"] + z_top)], _EYE,
                 [P["trachea_radius"], P["trachea_radius"], 0.5 * (z_top - P["trachea_z_bottom"])])
        self.add("descending_aorta", "body_muscle", KIND_CYLINDER, P["hu_blood_left"],
                 [P["desc_aorta_x"], P["desc_aorta_y"], 0.5 * (P["asc_aorta_top_z"] - z_top)], _EYE,
                 [P["desc_aorta_radius"], P["desc_aorta_radius"], 0.5 * (P["asc_aorta_top_z"] + z_top)])

    def heart(self):
        """The heart in its own frame (moved by breathing): fat envelope, ventricles, lesion, atria,
        ascending aorta and coronary arteries."""
        self.xi, self.eta, self.zeta = heart_axes()
        self.H = np.array([P["heart_x"], P["heart_y"], P["heart_z"]]) + self.heart_shift  # (m, 3)
        self.h_axes = _frame(self.xi, self.eta, self.zeta)
        self.left_ventricle()
        self.right_ventricle()
        self.atria()
        self.ascending_aorta()
        self.coronaries()

    def hf(self, px, py, pz):
        """Heart-frame coordinates (scalars or (m,)) -> world (m, 3)."""
        col = self.col
        return self.H + col(px) * self.xi + col(py) * self.eta + col(pz) * self.zeta

    def left_ventricle(self):
        """The epicardial fat envelope, the LV wall and cavity cut at the AV plane, the target lesion."""
        xi, eta, zeta, h_axes, chest_y = self.xi, self.eta, self.zeta, self.h_axes, self.chest_y
        a_cav, b_cav, a_out, b_out = self.lv = lv_shape(self.c)
        a_cav_ed, _, a_out_ed, _ = (float(v) for v in lv_shape(0.0))
        self.lv_xi = a_out_ed - a_out                          # epicardial apex fixed: the centre moves
        self.base_xi = self.lv_xi - P["lv_base_cut"] * a_cav   # AV (mitral/tricuspid) plane
        self.base_xi_ed = -P["lv_base_cut"] * a_cav_ed
        lv_centre, base_point = self.hf(self.lv_xi, 0.0, 0.0), self.hf(self.base_xi, 0.0, 0.0)
        self.vent_plane = (-xi, -_dot(base_point, xi))         # ventricular side: xi . x >= xi . base
        self.atrial_plane = (xi, _dot(base_point, xi))
        lv_out_semi = np.stack([a_out, b_out, b_out], -1)
        self.lv_out_cut = (CUT_SUBTRACT, lv_centre, h_axes, lv_out_semi)

        self.env = env = (self.hf(P["env_xi"], P["env_eta"], P["env_zeta"]), h_axes,
                          np.array([P["env_semi_xi"], P["env_semi_eta"], P["env_semi_zeta"]]))
        # the envelope ellipsoid is trimmed behind the sternum, in front of the vertebral bodies
        # and around the descending aorta (a long ellipsoid = the aorta locally)
        gap = P["env_clearance"]
        env_planes = [(np.array([0.0, -1.0, 0.0]), -(chest_y(P["sternum_y"] + P["sternum_semi_ap"]) + gap)),
                      (np.array([0.0, 1.0, 0.0]), P["vertebra_y"] - P["vertebra_semi_ap"] - gap)]
        r_ao = P["desc_aorta_radius"] + gap
        aorta_cut = (CUT_SUBTRACT, np.array([P["desc_aorta_x"], P["desc_aorta_y"], 0.0]), _EYE,
                     np.array([r_ao, r_ao, 1000.0]))
        self.add("epicardial_fat", "body_muscle", KIND_ELLIPSOID, P["hu_fat"], *env, planes=env_planes,
                 cuts=[aorta_cut])
        self.add("lv_myocardium", "epicardial_fat", KIND_ELLIPSOID, P["hu_myocardium"], lv_centre, h_axes,
                 lv_out_semi, planes=[self.vent_plane])
        self.add("lv_blood", "lv_myocardium", KIND_ELLIPSOID, P["hu_blood_left"], lv_centre, h_axes,
                 np.stack([a_cav, b_cav, b_cav], -1), planes=[self.vent_plane])
        # target lesion: a sphere riding on the LV wall, at the LV equator (the cavity's centre
        # plane across the long axis), mid-wall: the wall's normal there is radial, so the sphere
        # keeps (b_out - b) / 2 - radius >= 0.5 mm from the cavity and the epicardium at every phase
        phi = np.deg2rad(P["lesion_azimuth"])
        r_les = P["lesion_radius"]
        self.add("lesion", "lv_myocardium", KIND_ELLIPSOID, P["hu_lesion"],
                 lv_centre + self.col(0.5 * (b_cav + b_out)) * (np.cos(phi) * eta + np.sin(phi) * zeta), _EYE,
                 self.vec(r_les, r_les, r_les))

    def right_ventricle(self):
        """The RV crescent; its centre sits mid-ventricle and follows half of the base descent
        (free wall depth beyond the LV epicardium interpolated by the RV volume curve)."""
        b_out = self.lv[3]
        f = lv_ejected_fraction(self.c)
        depth = P["rv_depth_es"] + (P["rv_depth_ed"] - P["rv_depth_es"]) * (1.0 - f)
        eta_lo, eta_hi = P["rv_septal_eta"], b_out + depth
        self.rv_centre = self.hf(P["rv_xi"] + 0.5 * (self.base_xi - self.base_xi_ed), 0.5 * (eta_lo + eta_hi), 0.0)
        rv_in = np.stack([P["rv_semi_xi"] * (1.0 - 0.1 * f), 0.5 * (eta_hi - eta_lo),
                          P["rv_semi_zeta"] * (1.0 - 0.08 * f)], -1)
        self.rv_out = rv_in + P["rv_wall"]
        self.add("rv_myocardium", "epicardial_fat", KIND_ELLIPSOID, P["hu_myocardium"], self.rv_centre,
                 self.h_axes, self.rv_out, planes=[self.vent_plane], cuts=[self.lv_out_cut])
        self.add("rv_blood", "rv_myocardium", KIND_ELLIPSOID, P["hu_blood_right"], self.rv_centre, self.h_axes,
                 rv_in, planes=[self.vent_plane], cuts=[self.lv_out_cut])

    def atria(self):
        """Atria beyond the AV plane, semi-axes shape * r with the volume of the atrial curve."""
        shape = np.array([P["atrium_shape_xi"], P["atrium_shape_eta"], P["atrium_shape_zeta"]])
        r_at = (atrial_volume_ml(self.c) * 1000.0 / (4.0 / 3.0 * np.pi * np.prod(shape))) ** (1.0 / 3.0)
        for name, tissue, pe, pz in (("left_atrium", "hu_blood_left", P["la_eta"], P["la_zeta"]),
                                     ("right_atrium", "hu_blood_right", P["ra_eta"], P["ra_zeta"])):
            self.add(name, "epicardial_fat", KIND_ELLIPSOID, P[tissue],
                     self.hf(self.base_xi - shape[0] * r_at - P["atrium_gap"], pe, pz), self.h_axes,
                     self.col(r_at) * shape, planes=[self.atrial_plane])

    def ascending_aorta(self):
        """Ascending aorta: root on the AV plane -> top (moves with the heart); split at the fat
        envelope so each piece carries the difference to its own parent."""
        ones = np.ones(self.m)
        root = self.hf(self.base_xi, P["root_eta"], P["root_zeta"])
        top = np.array([P["asc_aorta_top_x"], P["asc_aorta_top_y"], P["asc_aorta_top_z"]]) + self.heart_shift
        ao_axes = _axis_frame(top - root)
        half = 0.5 * np.linalg.norm(top - root, axis=-1)
        ao = (0.5 * (top + root), ao_axes, np.stack([P["asc_aorta_radius"] * ones, P["asc_aorta_radius"] * ones,
                                                     half], -1))
        self.add("ascending_aorta", "body_muscle", KIND_CYLINDER, P["hu_blood_left"], *ao,
                 planes=[self.atrial_plane], cuts=[(CUT_SUBTRACT,) + self.env])
        self.add("aortic_root", "epicardial_fat", KIND_CYLINDER, P["hu_blood_left"], *ao,
                 planes=[self.atrial_plane], cuts=[(CUT_INTERSECT,) + self.env])

    def coronaries(self):
        """Coronary arteries, mitred cylinder chains through points just outside the epicardium:
        LAD and LCx on the LV, RCA on the RV."""
        a_cav, _, a_out, _ = self.lv
        rc = P["coronary_radius"]
        s_base = -P["lv_base_cut"] * a_cav / a_out
        lad = [self.on_lv(s_base + (0.92 - s_base) * t,
                          np.deg2rad(P["lad_azimuth_base"] + (P["lad_azimuth_apex"] - P["lad_azimuth_base"]) * t), 1.2)
               for t in np.linspace(0.08, 1.0, 6)]
        self.vessel("lad", lad, rc)
        lcx = [self.on_lv(s_base + 0.15, np.deg2rad(p), 1.5)
               for p in np.linspace(P["lcx_azimuth"] + 20.0, P["lcx_azimuth"] - 20.0, 4)]
        self.vessel("lcx", lcx, 0.85 * rc)
        rca = [self.on_rv(np.deg2rad(p), 6.0, 2.0) for p in np.linspace(75.0, -75.0, 6)]
        self.vessel("rca", rca, rc)

    def vessel(self, prefix: str, points: list, radius: float):
        """A coronary artery: blood-filled cylinders ``{prefix}_{k}`` mitred through ``points`` (m, 3)."""
        for s, seg in enumerate(mitred_chain(points, radius)):
            self.add(f"{prefix}_{s}", "epicardial_fat", KIND_CYLINDER, P["hu_blood_left"], *seg)

    def on_lv(self, s, phi, sag):
        """Point (m, 3) off the LV epicardium at axial fraction s (-1 base .. 1 apex), azimuth phi."""
        xi, eta, zeta, col = self.xi, self.eta, self.zeta, self.col
        _, _, a_out, b_out = self.lv
        rad = b_out * np.sqrt(np.maximum(1.0 - s * s, 0.0))
        pos = self.hf(self.lv_xi + a_out * s, rad * np.cos(phi), rad * np.sin(phi))
        nrm = _unit(col(s / a_out) * xi + col(np.sqrt(np.maximum(1 - s * s, 0.0)) / b_out)
                    * (np.cos(phi) * eta + np.sin(phi) * zeta))
        return pos + (P["coronary_radius"] + P["coronary_clearance"] + sag) * nrm

    def on_rv(self, psi, dxi, sag):
        """Point (m, 3) off the RV epicardium in the cross-section dxi mm apical of the AV plane."""
        xi, eta, zeta, col, rv_out = self.xi, self.eta, self.zeta, self.col, self.rv_out
        rel = self.rv_centre - self.H
        t = (self.base_xi + dxi - _dot(rel, xi)) / rv_out[:, 0]
        sc = np.sqrt(np.maximum(1.0 - t * t, 0.0))
        ey, ez = rv_out[:, 1] * sc, rv_out[:, 2] * sc
        pos = self.hf(self.base_xi + dxi, _dot(rel, eta) + ey * np.cos(psi), ez * np.sin(psi))
        nrm = _unit(col(np.cos(psi) / ey) * eta + col(np.sin(psi) / ez) * zeta)
        return pos + (P["coronary_radius"] + P["coronary_clearance"] + sag) * nrm

    def liver(self):
        """The liver: the diaphragm dome less the diaphragm muscle, less the heart resting on it,
        trimmed medially and clear of the spine and descending aorta."""
        dome_centre, dome_axes, dome_semi = self.dome()
        t = np.deg2rad(P["liver_spine_angle"])
        n_sp = np.array([np.cos(t), np.sin(t), 0.0])  # towards the spine (posterior-left)
        d_sp = min(-support(KIND_CYLINDER, np.array([0.0, P["vertebra_y"], 0.0]), _EYE,
                            np.array([P["vertebra_semi_lr"], P["vertebra_semi_ap"], 1.0]), -n_sp),
                   -support(KIND_CYLINDER, np.array([P["desc_aorta_x"], P["desc_aorta_y"], 0.0]), _EYE,
                            np.array([P["desc_aorta_radius"], P["desc_aorta_radius"], 1.0]), -n_sp))
        env = self.env
        self.add("liver", "body_muscle", KIND_ELLIPSOID, P["hu_liver"], dome_centre, dome_axes,
                 dome_semi - P["diaphragm_thickness"],
                 planes=[(np.array([1.0, 0.0, 0.0]), P["liver_medial_x"]), (n_sp, d_sp - P["lung_margin"])],
                 cuts=[(CUT_SUBTRACT, env[0], env[1], env[2] + P["diaphragm_thickness"])])

    def lungs(self):
        """Lungs: pleural cavity, beyond a medial plane clear of the posterior mediastinum, minus
        the diaphragm dome and minus the fat envelope grown by the margin; density with breathing."""
        m, a, env = self.m, self.a, self.env
        dome_centre, dome_axes, dome_semi = self.dome()
        lung_hu = P["hu_lung_exhale"] + (P["hu_lung_inhale"] - P["hu_lung_exhale"]) * a
        zb, zt = P["cavity_z_bottom"], P["cavity_z_top"]
        cav_centre = self.vec(0.0, self.chest_y(0.0), 0.5 * (zb + zt))
        cav_semi = self.vec(P["cavity_semi_lr"], P["cavity_semi_ap"] * self.k_ap, 0.5 * (zt - zb))
        by_name = {o.name: o for o in self.objs}
        obstacles = [by_name[n] for n in ("descending_aorta", "trachea", "ascending_aorta")]
        obstacles.append(_Obj("spine", "", KIND_CYLINDER, None, np.array([0.0, P["vertebra_y"], 0.0]), _EYE,
                              np.array([P["vertebra_semi_lr"], P["vertebra_semi_ap"], 1.0]), [], []))
        margin = P["lung_margin"]
        cuts = [(CUT_SUBTRACT, dome_centre, dome_axes, dome_semi),
                (CUT_SUBTRACT, env[0], env[1], env[2] + margin)]
        for name, ang, side in (("lung_right", P["lung_medial_angle_right"], -1.0),
                                ("lung_left", P["lung_medial_angle_left"], 1.0)):
            t = np.deg2rad(ang)
            n_out = np.array([side * np.cos(t), np.sin(t), 0.0])  # from the mediastinum into the lung
            d = np.max([support(o.kind, np.broadcast_to(o.centre, (m, 3)), np.broadcast_to(o.axes, (m, 3, 3)),
                                np.broadcast_to(o.semi, (m, 3)), n_out) for o in obstacles], axis=0)
            self.add(name, "body_muscle", KIND_CYLINDER, lung_hu, cav_centre, _EYE, cav_semi,
                     planes=[(-n_out, -(d + margin))], cuts=cuts)



def mitred_chain(points, radius):
    """Cylinders through consecutive points, mitred: a list of (centre, axes, semi, planes).

    ``points``: list of (m, 3) arrays. Neighbouring segments meet on the bisector plane of
    their axes, so a chain has neither overlaps nor gaps at its joints; the cylinders run a
    little past their end points so that the planes, not the caps, end them.
    """
    pts = [np.asarray(p, dtype=np.float64) for p in points]
    dirs = [_unit(pts[i + 1] - pts[i]) for i in range(len(pts) - 1)]
    out = []
    for i, w in enumerate(dirs):
        p0, p1 = pts[i], pts[i + 1]
        length = np.linalg.norm(p1 - p0, axis=-1)
        semi = np.stack([np.full_like(length, radius), np.full_like(length, radius), 0.5 * length + 2.0 * radius], -1)
        n0 = _unit(dirs[i - 1] + w) if i > 0 else w               # keep n0 . x >= n0 . p0
        n1 = _unit(w + dirs[i + 1]) if i < len(dirs) - 1 else w   # keep n1 . x <= n1 . p1
        planes = [(-n0, -_dot(n0, p0)), (n1, _dot(n1, p1))]
        out.append((0.5 * (p0 + p1), _axis_frame(w), semi, planes))
    return out


# ---------------------------------------------------------------------------------------
# NumPy float64 reference: point membership and density
def _local(points, centre, axes, semi):
    """World points (..., 3) -> normalised local coordinates of one primitive."""
    return ((points - centre) @ np.asarray(axes).reshape(3, 3)) / semi


def inside(obj_row, points) -> np.ndarray:
    """Boolean mask (...) of the points (..., 3) inside one packed object row (float64)."""
    o = np.asarray(obj_row, dtype=np.float64)
    pts = np.asarray(points, dtype=np.float64)
    kind = int(o[KIND])
    if kind == KIND_NONE:
        return np.zeros(pts.shape[:-1], bool)
    q = _local(pts, o[CENTRE], o[AXES], o[SEMI])
    if kind == KIND_ELLIPSOID:
        ins = _dot(q, q) <= 1.0
    else:
        ins = (q[..., 0] ** 2 + q[..., 1] ** 2 <= 1.0) & (np.abs(q[..., 2]) <= 1.0)
    for k in range(N_PLANES):
        ins &= pts @ o[17 + 4 * k:20 + 4 * k] <= o[20 + 4 * k]
    for k in range(N_CUTS):
        mode_i, cs, ca, cm = cut_fields(k)
        mode = int(o[mode_i])
        if mode != CUT_NONE:
            qc = _local(pts, o[cs], o[ca], o[cm])
            in_cut = _dot(qc, qc) <= 1.0
            ins &= ~in_cut if mode == CUT_SUBTRACT else in_cut
    return ins


def mu_at(objects, points) -> np.ndarray:
    """Sum of the densities of packed ``objects`` (n_obj, STRIDE) at ``points`` (..., 3), float64 1/mm."""
    pts = np.asarray(points, dtype=np.float64)
    out = np.zeros(pts.shape[:-1])
    for o in np.asarray(objects, dtype=np.float64):
        if o[KIND] != KIND_NONE and o[MU] != 0.0:
            out += np.where(inside(o, pts), o[MU], 0.0)
    return out
