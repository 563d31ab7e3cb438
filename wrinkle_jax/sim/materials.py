"""The five fabrics of the data set as physical parameters, and how they map to the solver.

Index order follows `wrinkle_jax.MATERIALS`: 0 silk_charmeuse, 1 wool_melton, 2 knit_terry,
3 silk_chiffon, 4 denim_light.

All values are APPROXIMATE, typical-of-the-class numbers (not fits to one measured bolt):

  * Areal density: trade weights converted to SI. Silk is sold by momme (1 momme =
    4.34 g/m^2): chiffon 6-8 mm, charmeuse 16-22 mm. Wool melton is a heavy, felted coat
    cloth of 14-20 oz/yd^2 (1 oz/yd^2 = 33.9 g/m^2); French terry knits are 200-300 g/m^2;
    "lightweight" denim is 6-8 oz/yd^2. Public fabric presets of garment CAD tools (e.g.
    the Marvelous Designer fabric library) list weights in the same ranges.
  * Bending rigidity B (N m): Kawabata KES-FB2 bending rigidity, reported in gf cm^2/cm
    (1 gf cm^2/cm = 9.81e-5 N m). Typical ranges (Kawabata & Niwa, "Fabric performance in
    clothing and clothing manufacture", J. Text. Inst. 80, 1989; and the KES literature on
    silks, suitings and denims): sheer silks 0.005-0.02, silk satins 0.01-0.05, knits
    0.03-0.1, light denim 0.2-0.5, melton 0.3-0.8 gf cm^2/cm.
  * Stretch stiffness k_s (N/m): the weight of the edge membrane (see below). Its uniaxial
    stiffness is NOT k_s but 0.33-0.34 k_s on the data set's jittered meshes (Poisson ratio
    ~1/3; `textile.membrane_uniaxial_stiffness`, `textile.MEMBRANE_UNIAXIAL`). Cited
    comparison (`textile.STRETCH_REFERENCE`, experiments/results/sim/textile/SOURCES.md): the
    measured fabrics of Wang, O'Brien & Ramamoorthi, "Data-driven elastic models for cloth",
    ACM TOG 30(4) 71 (SIGGRAPH 2011), released ARCSim material files, give at zero strain 6.5-130
    N/m for four garment-weight weft knits (median 66) and 411-4070 N/m for two cotton twill
    bottom-weights (an 11 oz stretch denim and a cotton/polyester pants twill; median 3030).
    Ours: terry 0.335 x 400 = 134 N/m (2.0 x the knit median), denim 0.335 x 2e4 = 6.7e3 N/m
    (2.2 x the twill median); the terry/denim contrast is 50 x here, 46 x in the measurements.
    No comparable measured silk or wool was found (their k_s are unverified estimates). At the
    data set's solver settings elongation under own weight is set by the solver and the 0.5 %
    stretch limits, not by k_s (hanging strip, `textile.hanging_strip`).
  * Shear is not a separate parameter: the edge-based membrane of `xpbd` couples stretch and
    shear (an isotropic triangulation gives an isotropic membrane), so shear stiffness is
    ~k_s/3, stiffer than real wovens in shear; wrinkle scale is set by bending/density.
  * Friction (cloth on skin-like body): 0.2 smooth silk to 0.6 looped terry; thickness from
    fabric specifications (0.1 mm chiffon to ~2 mm melton).
  * Damping: a small global velocity damping (1/s) standing in for internal friction
    (felted wool and terry are hysteretic, silks are lively); air drag is separate (`aero`).

Resolution scaling (why a material behaves the same at PD 10 and 30 mm):
  * Masses are lumped from areal density x triangle area, so the mass per area is fixed.
  * Stretch: the XPBD constraint per edge is the strain C = (l - L)/L with compliance
    alpha_e = 1 / (k_s A_e), where A_e is a third of the rest area of the edge's faces: the
    energy sum_e k_s A_e C_e^2 / 2 approximates the integral of k_s eps^2 / 2 over the cloth,
    independent of edge length.
  * Bending: the quadratic isometric bending energy (Bergou, Wardetzky, Harmon, Zorin &
    Grinspun, "A quadratic bending model for inextensible surfaces", SGP 2006) per interior
    edge, E_e = B/2 * c/(A_1 + A_2) * |sum_i K_i x_i|^2 with cotangent weights K, is a
    consistent discretization of the integral of B/2 (2H)^2 (H the mean curvature): it
    converges under refinement, so B (N m) is used as is at every PD (compliance 1/B per
    hinge). We take c = 1 (Bergou et al. write 3), which makes a cylinder of radius R store
    B / (2 R^2) per unit area, the cylindrical bend that defines KES rigidity (measured on
    the pattern mesher's jittered meshes at PD 10 and 30 mm, axis at 0-90 degrees: 1.00-1.13
    x; `experiments/bend_calibration.py`). Hinges on the rim of a clamped (pinned 2-D) region
    are normalised by their free face only (`cloth_model._hinges`): with the interior weights
    a clamp was soft by half a cell (cantilever bending length 16 % short at PD 10 mm, O(PD)).
  * The XPBD solver with one iteration per substep settles an interior hinge at B / (1 + r),
    r = h^2 B sum_k w_k K_k^2 (median 0.05-0.31 for these fabrics at PD 10 mm, 20 substeps;
    it grows as 1 / PD^4 and shrinks as 1 / substeps^2): stiff fabrics on fine meshes need
    substeps (or iterations) to show their full rigidity.
  * Wrinkles still differ with resolution only through what a mesh can hold: a 30 mm mesh
    cannot carry folds shorter than ~2 PD. The natural fold length (B / (rho g))^(1/3) is
    ~13 mm for the silks and terry and ~21-23 mm for melton and denim (see `fold_length`);
    air drag (relative to weight) makes chiffon react to motion much more than the rest.

Validation against textile tests (`sim.textile`, `experiments/textile_tests.py`, results in
`experiments/results/sim/textile/`):
  * Cusick drape coefficient (Cusick, "The measurement of fabric drape", J. Text. Inst. 59,
    1968, 253-260; BS 5058): 30 cm specimen clamped on an 18 cm disc.
  * Cantilever bending length (Peirce, "The 'handle' of cloth as a measurable quantity",
    J. Text. Inst. 21, 1930, T377-T416; ASTM D1388 / BS 3356): the chord to the strip's tip
    at 41.5 degrees gives c = overhang / 2 and flexural rigidity G = W c^3, so a fabric with
    rigidity B and areal density rho should show c = (B / (rho g))^(1/3) = `fold_length`.
  Reference ranges (`textile.REFERENCE`): bending lengths are derived from the KES rigidity
  and weight ranges listed above (an estimate, not a quoted bending length; the KES sources
  named above were not re-read in the tex20 search: no retrieved text contains those ranges);
  drape-coefficient ranges are UNCITED ESTIMATES (38 searches, SOURCES.md: the DC definition
  and instrument, no retrievable per-class measured DC). After the clamp
  fix every fabric's PD 10 mm bending length is inside its range with these parameters,
  chiffon only after B 0.006 -> 0.008 gf cm^2/cm (inside the sheer-silk KES range; rule in
  `experiments/results/sim/textile/DECISION.md`). The data set must be regenerated with
  them (it was simulated with the old bending model and chiffon's old B).
"""

from __future__ import annotations

import dataclasses
import math

from wrinkle_jax import MATERIALS

GF_CM2_PER_CM = 9.80665e-5  # N m per (gf cm^2 / cm), the KES bending-rigidity unit


@dataclasses.dataclass(frozen=True)
class Fabric:
    """Physical fabric parameters (SI units).

    Attributes:
      name: one of `wrinkle_jax.MATERIALS`.
      density: areal density, kg/m^2.
      stretch: membrane (stretch/shear) stiffness k_s, N/m.
      bending: bending rigidity B, N m.
      damping: global velocity damping rate, 1/s.
      friction: Coulomb friction coefficient against colliders.
      thickness: cloth thickness, m (the collision offset is max(thickness, MIN_CONTACT)).
      drag: aerodynamic pressure-drag coefficient (normal to the cloth).
      lift: aerodynamic lift coefficient.
    """

    name: str
    density: float
    stretch: float
    bending: float
    damping: float
    friction: float
    thickness: float
    drag: float = 1.2
    lift: float = 0.3

    @property
    def contact_offset(self) -> float:
        """Distance (m) kept between cloth vertices and collider surfaces."""
        return max(self.thickness, MIN_CONTACT)

    def replace(self, **changes) -> Fabric:
        return dataclasses.replace(self, **changes)


MIN_CONTACT = 0.003  # m: contact offset floor (vertex-only collisions need a little margin)

FABRICS = {
    # 19 momme charmeuse: 82 g/m^2; B ~ 0.02 gf cm^2/cm.
    "silk_charmeuse": Fabric("silk_charmeuse", density=0.082, stretch=3.0e3,
                             bending=0.02 * GF_CM2_PER_CM, damping=0.1, friction=0.2,
                             thickness=0.00015),
    # 16 oz/yd^2 melton: 540 g/m^2; B ~ 0.5 gf cm^2/cm; felted, well damped.
    "wool_melton": Fabric("wool_melton", density=0.54, stretch=6.0e3,
                          bending=0.5 * GF_CM2_PER_CM, damping=0.6, friction=0.5,
                          thickness=0.002),
    # French terry: 280 g/m^2; soft loop knit, very stretchy; B ~ 0.06 gf cm^2/cm.
    "knit_terry": Fabric("knit_terry", density=0.28, stretch=4.0e2,
                         bending=0.06 * GF_CM2_PER_CM, damping=0.5, friction=0.6,
                         thickness=0.0012),
    # 7 momme chiffon: 30 g/m^2; B ~ 0.008 gf cm^2/cm (sheer silks 0.005-0.02, Kawabata &
    # Niwa 1989); very light and airy. Was 0.006 until the cantilever validation (bend19):
    # with the clamp-consistent bending model its PD 10 mm bending length was 11.1 mm, just
    # under the 11.3-19.7 mm derived for the class; 0.008 is the smallest value of the rule in
    # experiments/results/sim/textile/DECISION.md that clears it by 5 %.
    "silk_chiffon": Fabric("silk_chiffon", density=0.030, stretch=1.5e3,
                           bending=0.008 * GF_CM2_PER_CM, damping=0.1, friction=0.25,
                           thickness=0.0001),
    # 7 oz/yd^2 light denim: 240 g/m^2; B ~ 0.3 gf cm^2/cm; stiff twill.
    "denim_light": Fabric("denim_light", density=0.24, stretch=2.0e4,
                          bending=0.3 * GF_CM2_PER_CM, damping=0.3, friction=0.4,
                          thickness=0.0005),
}
if set(FABRICS) != set(MATERIALS):  # every material index needs parameters
    raise RuntimeError("FABRICS and wrinkle_jax.MATERIALS disagree")


def fabric(name: str) -> Fabric:
    """The named fabric; raises ValueError naming the valid choices."""
    try:
        return FABRICS[name]
    except KeyError:
        raise ValueError(f"unknown material {name!r}; expected one of "
                         f"{', '.join(MATERIALS)}") from None


def fold_length(f: Fabric, g: float = 9.81) -> float:
    """Gravity-bending length (B / (rho g))^(1/3), meters: the natural scale of folds."""
    return (f.bending / (f.density * g)) ** (1.0 / 3.0)


def material_table() -> list[dict]:
    """Rows (in `MATERIALS` order) with SI values, KES units and the fold length."""
    rows = []
    for name in MATERIALS:
        f = FABRICS[name]
        rows.append({
            "material": name, "density_g_m2": round(f.density * 1e3, 1),
            "stretch_N_m": f.stretch, "bending_N_m": f.bending,
            "bending_gf_cm2_cm": round(f.bending / GF_CM2_PER_CM, 4),
            "damping_1_s": f.damping, "friction": f.friction,
            "thickness_mm": f.thickness * 1e3,
            "fold_length_mm": round(1e3 * fold_length(f), 2),
            "stretch_wave_speed_m_s": round(math.sqrt(f.stretch / f.density), 1),
        })
    return rows
