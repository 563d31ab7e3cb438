"""Standard textile tests as simulator scenes: the Cusick drape test and the cantilever bending
length (issue 24, item 2).

  Cusick drape (BS 5058 / ISO 9073-9 style): a circular specimen (radius `radius`, 15 cm for
      the standard 30 cm specimen) is clamped concentrically between two discs (radius
      `support`, 9 cm) and hangs under its own weight. The drape coefficient is
          DC = (A_shadow - A_support) / (A_specimen - A_support)
      with A_shadow the area of the vertical projection of the settled specimen: 1 for a rigid
      (flat) specimen, ~0 for a perfectly limp one that hangs straight down.
      Mesh: a disc panel (the clamped part, every vertex pinned at rest) sewn to four annular
      sectors, so the clamp edge is exactly the support circle at every PD.
  Cantilever bending length (Peirce 1930; ASTM D1388 option A; BS 3356): a strip (25 mm wide)
      lies on a platform and overhangs its edge; it is pushed out until its tip touches a plane
      inclined at 41.5 degrees below the edge, i.e. until the chord from the edge to the tip
      makes 41.5 degrees with the horizontal. The bending length is c = overhang / 2 and the
      flexural rigidity G = W c^3 (W the weight per area; in SI, B = rho g c^3).
      Simulation: one mesh holds several strips with different overhangs (they do not touch);
      the platform part of each strip is clamped (a structured grid with a vertex column
      exactly on the edge, see `cantilever_strips`) and each strip's chord angle is measured
      after settling; the overhang at which the angle is 41.5 degrees is interpolated
      (log-linear) between the bracketing strips.
      Peirce's closed form c = l (cos(theta/2) / (8 tan theta))^(1/3) for a strip of overhang
      l and chord angle theta is reported per strip too (at 41.5 degrees it gives 0.509 l,
      the instrument's 1/2; a numerical heavy-elastica solve gives l = 2.000 c there).

Settling: gravity, no air; extra velocity damping (`settle_damping`, 1/s) is added to the
fabric's own so the specimen comes to rest quickly (damping moves no equilibrium). The run
stops when the largest free-vertex speed at the end of a block of frames is below `v_tol`
(m/s), or after `max_frames`; the result records which.

Projected area: the settled triangles are projected onto the horizontal plane and rasterised
(`projected_area`): a cell counts as covered when its centre lies inside any triangle
(their union, so overlapping folds count once). The error is at most the number of cells the
outline crosses times a cell area, ~ perimeter x cell (for a 30 cm disc on a 0.5 mm grid,
< 0.5 mm x 0.94 m = 4.7 cm^2 = 0.7 % of the disc, in practice far smaller since errors on
either side of the outline cancel).

Solver settings default to the data set's (`scenes.SceneConfig`: 30 fps, 20 substeps, 2
stretch sweeps, 1 iteration).
"""

from __future__ import annotations

import dataclasses
import math

import jax.numpy as jnp
import numpy as np

from wrinkle_jax.mesh import Garment, make_garment
from wrinkle_jax.sim import patterns, xpbd
from wrinkle_jax.sim.colliders import Colliders
from wrinkle_jax.sim.materials import Fabric

OVERHANGS = tuple(float(v) for v in np.geomspace(0.012, 0.16, 12))  # m, 1.27x apart
PEIRCE_ANGLE = math.radians(41.5)  # incline of the cantilever test (c = overhang / 2)
G = 9.81


@dataclasses.dataclass(frozen=True)
class SettleConfig:
    """How a specimen is brought to rest (static, hashable).

    Attributes: substeps, stretch_sweeps, iterations: solver settings (the data set's).
    settle_damping: extra velocity damping, 1/s. block: frames per jitted block (the speed
    is checked after each).
    v_tol: rest criterion, m/s (max free-vertex speed). max_frames: give up (recorded).
    """

    substeps: int = 20
    stretch_sweeps: int = 2
    iterations: int = 1
    settle_damping: float = 4.0
    block: int = 30
    v_tol: float = 2e-3
    max_frames: int = 900


def settle(mesh, pinned: np.ndarray, fab: Fabric, cfg: SettleConfig = SettleConfig(),
           limit_spans: bool = True) -> tuple[np.ndarray, dict]:
    """Let a mesh with static pins come to rest under gravity.

    Args:
      mesh: a `PatternMesh` or `StripMesh` (initial positions = its garment's vertices, m).
      pinned: (P,) vertex ids held at their initial positions.
      fab: fabric parameters.
      limit_spans: keep the material-independent multi-scale stretch limits of
        `cloth_model.stretch_limits` (slack 0.5 %), as the data set's scenes do.
    Returns:
      (positions (V, 3) float64 m, info {frames, max_speed_m_s, settled}).
    """
    g = mesh.garment
    model = xpbd.build_cloth(g, pinned, use_aero=False, attachments=False,
                             limit_spans=limit_spans)
    config = xpbd.SimConfig(fps=30.0, substeps=cfg.substeps, stretch_sweeps=cfg.stretch_sweeps,
                            iterations=cfg.iterations)
    params = xpbd.fabric_params(fab)
    init_fn, _ = xpbd.cloth_simulator(config)
    x0 = np.asarray(g.vertices, np.float32)
    state = init_fn(model, x0)
    n = cfg.block + 1
    pins = jnp.asarray(np.broadcast_to(x0[pinned], (n,) + x0[pinned].shape))
    drives = xpbd.Drive(time=jnp.arange(n, dtype=jnp.float32) / 30.0, pins=pins,
                        colliders=Colliders(),
                        extra_damping=jnp.full(n, cfg.settle_damping, jnp.float32))
    free = np.asarray(model.free) > 0
    frames, speed = 0, math.inf
    while frames < cfg.max_frames:
        state, _ = xpbd.run_frames(config, model, params, state, drives)
        frames += cfg.block
        speed = float(np.linalg.norm(np.asarray(state.v)[free], axis=1).max())
        if speed < cfg.v_tol:
            break
    info = {"frames": frames, "max_speed_m_s": speed, "settled": bool(speed < cfg.v_tol)}
    return np.asarray(state.x, np.float64), info


# --------------------------------------------------------------------------------------------
# Projected area
# --------------------------------------------------------------------------------------------


def projected_area(x: np.ndarray, faces: np.ndarray, cell: float = 5e-4) -> float:
    """Area (m^2) of the union of the triangles projected onto the x-y plane.

    Rasterised on a grid of `cell` m: a cell is covered when its centre lies inside (or on)
    a projected triangle. Error <= (cells crossed by the outline) x cell^2.

    Args:
      x: (V, 3) or (V, 2) positions, m. faces: (F, 3) int.
    """
    xy = np.asarray(x, np.float64)[:, :2]
    lo = xy.min(0) - cell
    n = np.ceil((xy.max(0) + cell - lo) / cell).astype(int)
    covered = np.zeros((n[1], n[0]), bool)
    tri = xy[np.asarray(faces)]
    for a, b, c in tri:
        i0, j0 = np.floor((np.minimum(np.minimum(a, b), c) - lo) / cell).astype(int)
        i1, j1 = np.ceil((np.maximum(np.maximum(a, b), c) - lo) / cell).astype(int)
        px = lo[0] + (np.arange(i0, i1) + 0.5) * cell
        py = lo[1] + (np.arange(j0, j1) + 0.5) * cell
        qx, qy = np.meshgrid(px, py)
        d1 = (b[0] - a[0]) * (qy - a[1]) - (b[1] - a[1]) * (qx - a[0])
        d2 = (c[0] - b[0]) * (qy - b[1]) - (c[1] - b[1]) * (qx - b[0])
        d3 = (a[0] - c[0]) * (qy - c[1]) - (a[1] - c[1]) * (qx - c[0])
        inside = ((d1 >= 0) & (d2 >= 0) & (d3 >= 0)) | ((d1 <= 0) & (d2 <= 0) & (d3 <= 0))
        covered[j0:j1, i0:i1] |= inside
    return float(covered.sum()) * cell * cell


# --------------------------------------------------------------------------------------------
# Cusick drape
# --------------------------------------------------------------------------------------------


def drape_pattern(radius: float = 0.15, support: float = 0.09, z: float = 0.5) -> patterns.Pattern:
    """A flat circular specimen at height z: panel 0 the clamped disc (r <= support), panels
    1-4 annular quarter sectors sewn to it and to each other. Landmark "clamp" = the disc rim.
    """
    q = math.pi / 2
    disc = patterns.Panel("support", tuple(
        patterns._poly(patterns._arc(support, j * q - q / 2, (j + 1) * q - q / 2))
        for j in range(4)))
    sectors = tuple(patterns.Panel(f"ring{j}", patterns._sector(support, radius, q))
                    for j in range(4))
    seams = tuple(patterns.Seam((f"ring{j}", 1), (f"ring{(j + 1) % 4}", 3)) for j in range(4))
    seams += tuple(patterns.Seam((f"ring{j}", 2), ("support", j)) for j in range(4))

    def place(i, p):
        if i == 0:
            return np.stack([p[:, 0], p[:, 1], np.full(len(p), z)], 1)
        rho = np.hypot(p[:, 0], p[:, 1])
        ang = (i - 1) * q + np.arctan2(p[:, 0], -p[:, 1])
        return np.stack([rho * np.sin(ang), -rho * np.cos(ang), np.full(len(p), z)], 1)

    return patterns.Pattern("cusick", (disc,) + sectors, seams, place,
                            {"clamp": tuple(("support", j) for j in range(4))})


def clamped_vertices(mesh: patterns.PatternMesh, panel: int = 0) -> np.ndarray:
    """Vertex ids (sorted) of every face of UV panel `panel` (the clamped part)."""
    g = mesh.garment
    faces = np.asarray(g.faces)[np.asarray(g.panels) == panel]
    return np.unique(faces).astype(np.int32)


def drape_coefficient(x: np.ndarray, faces: np.ndarray, radius: float, support: float,
                      cell: float = 5e-4) -> float:
    """DC = (A_shadow - pi support^2) / (pi radius^2 - pi support^2) of positions x (V, 3)."""
    a_s = math.pi * support ** 2
    return (projected_area(x, faces, cell) - a_s) / (math.pi * radius ** 2 - a_s)


def cusick_drape(fab: Fabric, pd: float, radius: float = 0.15, support: float = 0.09,
                 seed: int = 0, cfg: SettleConfig = SettleConfig(), cell: float = 5e-4) -> dict:
    """Simulate the drape test; returns {dc, shadow_area_m2, vertices, frames, settled, ...}
    plus the settled positions under "x" (V, 3) and faces under "faces" (NumPy)."""
    mesh = patterns.mesh_pattern(drape_pattern(radius, support), pd, seed=seed)
    pinned = clamped_vertices(mesh)
    x, info = settle(mesh, pinned, fab, cfg)
    faces = np.asarray(mesh.garment.faces)
    rest_dc = drape_coefficient(mesh.garment.vertices, faces, radius, support, cell)
    dc = drape_coefficient(x, faces, radius, support, cell)
    z0 = float(np.asarray(mesh.garment.vertices)[0, 2])
    return {"dc": dc, "dc_flat_mesh": rest_dc, "vertices": int(len(x)),
            "hang_depth_m": float(z0 - x[:, 2].min()), **info, "x": x, "faces": faces}


# --------------------------------------------------------------------------------------------
# Cantilever bending length
# --------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True, eq=False)
class StripMesh:
    """Cantilever strips: garment (rest = UV layout, meters), clamped (P,) and tips[k] (n_k,)
    vertex ids, z of the platform edge (m)."""

    garment: Garment
    clamped: np.ndarray
    tips: tuple
    z_edge: float


def _grid_triangles(idx: np.ndarray) -> np.ndarray:
    """(2 I J, 3) int32 triangles of a structured grid of vertex indices `idx` (I + 1, J + 1),
    two per cell, cells in row-major order: with a = idx[i, j], b = idx[i + 1, j],
    c = idx[i + 1, j + 1], d = idx[i, j + 1], (a, b, c), (a, c, d) where i + j is even and
    (a, b, d), (b, c, d) where it is odd (alternating diagonals: no preferred shear)."""
    a, b, c, d = idx[:-1, :-1], idx[1:, :-1], idx[1:, 1:], idx[:-1, 1:]
    i, j = np.indices(a.shape)
    even = ((i + j) % 2 == 0)[..., None]
    first = np.where(even, np.stack([a, b, c], -1), np.stack([a, b, d], -1))
    second = np.where(even, np.stack([a, c, d], -1), np.stack([b, c, d], -1))
    return np.stack([first, second], 2).reshape(-1, 3).astype(np.int32)


def cantilever_strips(overhangs, pd: float, width: float = 0.025, platform: float = 0.03,
                      spacing: float = 0.05, z: float = 0.5) -> StripMesh:
    """Strips k = 0.. along +x at y = k (width + spacing), flat at height z: a clamped part on
    x in [-platform, 0] and an overhang on [0, overhangs[k]]; a structured grid (columns
    ~`pd` apart with one exactly on the edge x = 0, max(1, round(width / pd)) cells across,
    cell diagonals alternating so the grid has no preferred shear direction).

    A structured grid because the pattern mesher cannot mesh 1-cell-wide rectangles (a
    25 mm strip at PD 30 mm); the data set's jittered meshes are not reproduced here.
    """
    verts, faces, panels, clamped, tips = [], [], [], [], []
    base = 0
    ny = max(1, round(width / pd))
    ys = np.linspace(0.0, width, ny + 1)
    for k, l in enumerate(overhangs):
        n_p = max(1, round(platform / pd))
        n_o = max(1, round(l / pd))
        xs = np.r_[np.linspace(-platform, 0.0, n_p + 1), np.linspace(0.0, l, n_o + 1)[1:]]
        gx, gy = np.meshgrid(xs, ys, indexing="ij")  # (nx, ny + 1)
        nx = len(xs)
        v = np.stack([gx.ravel(), gy.ravel() + k * (width + spacing), np.full(gx.size, z)], 1)
        idx = np.arange(gx.size).reshape(nx, ny + 1) + base
        faces.append(_grid_triangles(idx))
        panels.append(np.repeat(2 * k + (np.arange(nx - 1) >= n_p), 2 * ny))
        clamped.append(idx[: n_p + 1].ravel())
        tips.append(idx[-1].ravel())
        verts.append(v)
        base += gx.size
    x = np.concatenate(verts)
    f = np.concatenate(faces)
    g = make_garment(x, f, x[:, :2], f, np.concatenate(panels).astype(np.int32),
                     source=f"cantilever strips (pd={pd})")
    return StripMesh(g, np.concatenate(clamped).astype(np.int32), tuple(tips), float(z))


def chord_angle(x: np.ndarray, tip: np.ndarray, z_edge: float) -> float:
    """Angle (rad) below the horizontal of the chord from the platform edge (x = 0, z_edge)
    to the mean position of the tip vertices `tip` (the side view of the strip)."""
    p = np.asarray(x)[tip].mean(0)
    return float(math.atan2(z_edge - p[2], p[0]))


def peirce_c(overhang: float, theta: float) -> float:
    """Peirce's bending length c (m) of a cantilever of `overhang` m with chord angle theta."""
    return overhang * (math.cos(theta / 2) / (8 * math.tan(theta))) ** (1.0 / 3.0)


def bending_length(overhangs, angles) -> float:
    """Overhang / 2 at which the chord angle crosses 41.5 degrees (log-linear interpolation
    between the bracketing strips); NaN when the strips do not bracket it."""
    l = np.asarray(overhangs, np.float64)
    a = np.asarray(angles, np.float64)
    order = np.argsort(l)
    l, a = l[order], a[order]
    for i in range(len(l) - 1):
        if (a[i] - PEIRCE_ANGLE) * (a[i + 1] - PEIRCE_ANGLE) <= 0 and a[i] != a[i + 1]:
            t = (PEIRCE_ANGLE - a[i]) / (a[i + 1] - a[i])
            return 0.5 * float(np.exp(np.log(l[i]) + t * (np.log(l[i + 1]) - np.log(l[i]))))
    return float("nan")


def cantilever(fab: Fabric, pd: float, overhangs=None, width: float = 0.025,
               cfg: SettleConfig = SettleConfig()) -> dict:
    """Simulate the cantilever test on strips of several overhangs (m; default `OVERHANGS`,
    the same for every fabric so one compiled solver serves all). Returns {bending_length_m,
    flexural_rigidity_N_m (rho g c^3), overhangs_m,
    angles_deg, peirce_c_m (per strip), frames, settled, ...}."""
    if overhangs is None:
        overhangs = OVERHANGS
    overhangs = [float(v) for v in overhangs]
    strips = cantilever_strips(overhangs, pd, width)
    x, info = settle(strips, strips.clamped, fab, cfg)
    angles = [chord_angle(x, tip, strips.z_edge) for tip in strips.tips]
    c = bending_length(overhangs, angles)
    return {"bending_length_m": c,
            "flexural_rigidity_N_m": fab.density * G * c ** 3 if math.isfinite(c) else c,
            "overhangs_m": overhangs, "angles_deg": [math.degrees(a) for a in angles],
            "peirce_c_m": [peirce_c(l, a) if a > 1e-3 else float("inf")
                           for l, a in zip(overhangs, angles, strict=True)],
            "vertices": int(len(x)), **info}


# --------------------------------------------------------------------------------------------
# Hanging strip (elongation under its own weight)
# --------------------------------------------------------------------------------------------


def hanging_strip_mesh(pd: float, length: float = 0.5, width: float = 0.1,
                       z: float = 1.0) -> StripMesh:
    """A strip hanging in the x-z plane from its top row (x in [0, width], z from `z` down to
    z - length); UVs = the flat pattern (x, length - depth), meters; a structured grid with
    alternating diagonals. `clamped` = the top row, `tips` = (the bottom row,)."""
    nx = max(1, round(width / pd))
    nz = max(1, round(length / pd))
    xs = np.linspace(0.0, width, nx + 1)
    ds = np.linspace(0.0, length, nz + 1)  # depth below the top row
    gx, gd = np.meshgrid(xs, ds, indexing="ij")  # (nx + 1, nz + 1)
    idx = np.arange(gx.size).reshape(gx.shape)
    f = _grid_triangles(idx)
    x = np.stack([gx.ravel(), np.zeros(gx.size), z - gd.ravel()], 1)
    uv = np.stack([gx.ravel(), length - gd.ravel()], 1)
    g = make_garment(x, f, uv, f, np.zeros(len(f), np.int32),
                     source=f"hanging strip (pd={pd})")
    return StripMesh(g, idx[:, 0].astype(np.int32), (idx[:, -1].astype(np.int32),), float(z))


def hanging_strip(fab: Fabric, pd: float, length: float = 0.5, width: float = 0.1,
                  cfg: SettleConfig = SettleConfig(), limit_spans: bool = True) -> dict:
    """Elongation of a strip hung from its top edge under its own weight.

    Returns {mean_strain (length change / length), nominal_strain (rho g L / (2 k_s): a 1-D
    linear membrane of stiffness k_s, lateral contraction ignored), frames, settled, ...}.
    """
    m = hanging_strip_mesh(pd, length, width)
    x, info = settle(m, m.clamped, fab, cfg, limit_spans=limit_spans)
    drop = m.z_edge - float(np.asarray(x)[m.tips[0], 2].mean())
    return {"mean_strain": drop / length - 1.0,
            "nominal_strain": fab.density * G * length / (2.0 * fab.stretch),
            "length_m": length, "width_m": width, "limit_spans": limit_spans,
            "vertices": int(len(x)), **info}


# --------------------------------------------------------------------------------------------
# Reference ranges
# --------------------------------------------------------------------------------------------

# Per fabric class: the KES bending-rigidity range (gf cm^2/cm) and the trade-weight range
# (g/m^2) quoted in `materials`, and a drape-coefficient range. The bending-length range is
# DERIVED from the first two with Peirce's relation c = (B / (rho g))^(1/3) (Peirce 1930; ASTM
# D1388): an estimate from the quoted ranges, not a quoted bending length (the KES sources named
# in `materials` were not re-read in the tex20 search, see SOURCES.md). The DC ranges are
# UNCITED ESTIMATES ("dc_source": None): repeated searches (experiments/results/sim/textile/
# SOURCES.md) found the DC definition, the instrument and general statements (Cusick 1968: 0
# limp to 1 rigid), but no retrievable per-class measured DC for these five fabric classes. By
# DECISION.md an uncited range is reported, never used to choose a parameter.
REFERENCE = {
    "silk_charmeuse": {"bending_gf_cm2_cm": (0.01, 0.05), "density_g_m2": (69.0, 95.0),
                       "dc": (0.15, 0.45), "dc_source": None},
    "wool_melton": {"bending_gf_cm2_cm": (0.3, 0.8), "density_g_m2": (475.0, 678.0),
                    "dc": (0.55, 0.90), "dc_source": None},
    "knit_terry": {"bending_gf_cm2_cm": (0.03, 0.1), "density_g_m2": (200.0, 300.0),
                   "dc": (0.25, 0.60), "dc_source": None},
    "silk_chiffon": {"bending_gf_cm2_cm": (0.005, 0.02), "density_g_m2": (26.0, 35.0),
                     "dc": (0.10, 0.40), "dc_source": None},
    "denim_light": {"bending_gf_cm2_cm": (0.2, 0.5), "density_g_m2": (203.0, 271.0),
                    "dc": (0.45, 0.85), "dc_source": None},
}
DC_UNCITED = "uncited estimate"


def dc_cited(name: str) -> bool:
    """True when the class's DC range carries a citation (`REFERENCE[name]["dc_source"]`)."""
    return bool(REFERENCE[name].get("dc_source"))


GF_CM2_PER_CM = 9.80665e-5


# Low-load stretch stiffness (N/m) of measured fabrics, for comparison with `Fabric.stretch`.
# Source: H. Wang, J. F. O'Brien & R. Ramamoorthi, "Data-driven elastic models for cloth:
# modeling and measurement", ACM Trans. Graph. 30(4), 71 (SIGGRAPH 2011), doi 10.1145/2010324.
# 1964966: the released ARCSim material files of its ten measured fabrics (read in the copies at
# github.com/wxhaooo/lyra, materials/*.json, whose README credits that database). Per fabric:
# the (axis-0, axis-90) diagonal stiffnesses k0, k2 at zero strain as ARCSim evaluates the file
# (row 0, each component clamped >= 0 and doubled, dde.cpp; energy per area (k0 G00^2 + k2 G11^2
# + 2 k1 G00 G11 + k3 G01^2) / 2 in Green strain G, physics.cpp), i.e. the uniaxial tangent
# stiffness; with lateral contraction free (k0 - k1^2 / k2) they change by < 0.1 % (k1 is small
# or clamped to 0). Derivation and the values at 1/12 and 1/6 strain: SOURCES.md. Classes with
# no comparable measured fabric in that set (the silks, melton) have no entry.
STRETCH_REFERENCE = {
    "knit_terry": {  # weft knits of garment weight, 187-284 g/m^2
        "navy-sparkle-sweat (sweater, 96 % polyester 4 % spandex)": (25.0, 6.5),
        "gray-interlock (t-shirt, 60 % cotton 40 % polyester)": (33.2, 69.0),
        "ivory-rib-knit (underwear, 95 % cotton 5 % spandex)": (85.7, 130.3),
        "camel-ponte-roma (jacket, 60 % polyester 40 % rayon)": (62.3, 88.1),
    },
    "denim_light": {  # cotton-rich twill bottom-weights, 220-324 g/m^2
        "11oz-black-denim (jeans, 99 % cotton 1 % spandex)": (410.7, 2027.8),
        "royal-target (pants, 65 % cotton 35 % polyester)": (4033.1, 4070.0),
    },
}
STRETCH_SOURCE = ("Wang, O'Brien & Ramamoorthi, SIGGRAPH 2011 (ACM TOG 30(4) 71), released "
                  "ARCSim material files")
STRETCH_RATIO_RULE = 3.0  # DECISION.md (tex20) rule 4: propose when ours > 3 x the median
# The edge membrane's uniaxial stiffness is NOT k_s: an affine uniaxial strain eps (lateral
# strain free) of sum_e k_s A_e C_e^2 / 2 stores MEMBRANE_UNIAXIAL k_s eps^2 / 2 per area on the
# data set's jittered meshes (0.330-0.344 at PD 10 and 30 mm, axes 0/45/90 deg; Poisson ratio
# 0.32-0.35; `membrane_uniaxial_stiffness`, tests/test_sim_textile.py). Measured stiffnesses
# are compared with MEMBRANE_UNIAXIAL x k_s.
MEMBRANE_UNIAXIAL = 0.335


def membrane_uniaxial_stiffness(garment: Garment, angle: float = 0.0,
                                eps: float = 1e-3) -> tuple[float, float]:
    """(E_eff / k_s, lateral strain / eps) of the simulator's edge membrane (weights A_e as in
    `cloth_model.build_cloth`) under an affine uniaxial strain `eps` along `angle` (rad, in the
    UV plane), the lateral strain minimising the energy. NumPy; rest state = the UVs (m)."""
    model = xpbd.build_cloth(garment, None, use_aero=False, attachments=False,
                             limit_spans=False)
    cat = lambda f: np.concatenate([np.asarray(getattr(c, f)) for c in model.stretch])  # noqa: E731
    i, j = cat("i"), cat("j")
    rest, a = cat("rest").astype(np.float64), 1.0 / cat("inv_area").astype(np.float64)
    uv = np.zeros((garment.num_vertices, 2))
    uv[np.asarray(garment.faces).ravel()] = np.asarray(garment.uvs)[
        np.asarray(garment.uv_faces).ravel()]
    d = uv[j] - uv[i]
    t = np.array([math.cos(angle), math.sin(angle)])
    n = np.array([-t[1], t[0]])

    def energy(lat):
        f = (1 + eps) * np.outer(t, t) + (1 + lat) * np.outer(n, n)
        c = (np.linalg.norm(d @ f.T, axis=1) - rest) / rest
        return 0.5 * float(np.sum(a * c * c))

    # The energy is quadratic in the lateral strain to O(eps): the vertex of the parabola
    # through three samples is its minimiser.
    e_m, e_0, e_p = energy(-eps), energy(0.0), energy(eps)
    lat = 0.5 * eps * (e_m - e_p) / max(e_m - 2 * e_0 + e_p, 1e-300)
    return float(2.0 * energy(lat) / (a.sum() * eps * eps)), float(lat / eps)


def stretch_comparison(name: str, stretch: float) -> dict | None:
    """Our membrane's uniaxial stiffness (MEMBRANE_UNIAXIAL x k_s, N/m) against the median of
    the class's measured zero-strain stiffnesses (both axes of every comparable fabric in
    `STRETCH_REFERENCE`); None without measured analogues. "proposed_N_m" is the k_s whose
    uniaxial stiffness equals that median (2 significant digits) when ours exceeds it by more
    than `STRETCH_RATIO_RULE` (a proposal: DECISION.md decides whether it is applied);
    "ratio_raw_k_s" compares k_s itself, as rule 4 was first worded (see DECISION.md)."""
    ref = STRETCH_REFERENCE.get(name)
    if not ref:
        return None
    vals = np.asarray([v for pair in ref.values() for v in pair], np.float64)
    med = float(np.median(vals))
    eff = MEMBRANE_UNIAXIAL * stretch
    ratio = eff / med
    return {"ours_k_s_N_m": stretch, "ours_uniaxial_N_m": eff,
            "measured_min_N_m": float(vals.min()), "measured_max_N_m": float(vals.max()),
            "median_N_m": med, "ratio": ratio, "ratio_raw_k_s": stretch / med,
            "proposed_N_m": (float(f"{med / MEMBRANE_UNIAXIAL:.2g}")
                             if ratio > STRETCH_RATIO_RULE else None),
            "fabrics": {k: list(v) for k, v in ref.items()}, "source": STRETCH_SOURCE}


def reference_bending_length(name: str) -> tuple[float, float]:
    """(min, max) bending length (m) of a fabric class from its KES rigidity and weight ranges:
    stiffest-lightest and limpest-heaviest corners of c = (B / (rho g))^(1/3)."""
    r = REFERENCE[name]
    (b0, b1), (w0, w1) = r["bending_gf_cm2_cm"], r["density_g_m2"]
    c = lambda b, w: (b * GF_CM2_PER_CM / (w * 1e-3 * G)) ** (1.0 / 3.0)  # noqa: E731
    return c(b0, w1), c(b1, w0)


def proposed_bending(fab: Fabric, measured_c: float, target_c: float) -> float:
    """Bending rigidity B (N m) that moves a measured bending length to `target_c`, assuming
    c ∝ B^(1/3) (Peirce; checked on the simulator in tests/test_sim_textile.py)."""
    return fab.bending * (target_c / measured_c) ** 3


def inside(value: float, lo_hi) -> bool:
    return bool(lo_hi[0] <= value <= lo_hi[1])
