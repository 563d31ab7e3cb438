"""Sewing patterns: the garment catalogue. Each garment is a `Pattern` of 2D panels (polygons in
meters) with seams and a drape, meshed at a particle distance by `mesh_pattern` into a seamed
garment whose UVs ARE the pattern coordinates. The meshing machinery (`Panel`, `Seam`,
`Pattern`, `PatternMesh`, `mesh_pattern`, `mesh_quality`, ...) lives in `pattern_mesh` and is
re-exported here, so every old import path keeps working.

Garments (`GARMENTS`): `sheet` (1 m square, hanging), `flared_skirt` (4 gores, half-circle
flare), `circle_skirt` (6 gores, 288-degree flare, knee length), `pleated_skirt` (2 panels,
16 pleats pressed into the waist), and test-only `dress` (front/back with side and shoulder
seams) and `cape` (a 252-degree circular cape fastened at the neck); hanging panels pinned
along their top edge: `shawl` (down the back from the shoulders), `long_shawl` (1.0 x 1.1 m,
down to the calves) and `apron` (in front of the legs from the waist), and validation-only
`tabard` (in front, from the shoulders). Coordinates: z up, the mannequin faces +y. Each
pattern says where a scene's pins attach its landmarks (`Pattern.pin_targets`: skirt waists
onto the waistband, the cape's neck onto a ring; other landmarks stay in place).
"""

from __future__ import annotations

import math

import numpy as np

# The meshing machinery lives in pattern_mesh; every name stays importable from here (old
# import paths, pickles, the scenes and tests that build their own patterns).
from wrinkle_jax.sim.pattern_mesh import (  # noqa: F401
    Panel,
    Pattern,
    PatternError,
    PatternMesh,
    Seam,
    _arc,
    _inside_and_distance,
    _knn,
    _local_delaunay,
    _mesh_panel,
    _poly,
    _polyline_length,
    _resample,
    mesh_pattern,
    mesh_quality,
)

# --------------------------------------------------------------------------------------------
# Garments
# --------------------------------------------------------------------------------------------

WAIST_Z = 1.03          # meters: skirt waistband height on the mannequin
WAIST_RADII = (0.152, 0.132)  # ellipse half-axes (x, y) of the waistband, meters


def waist_ring_targets(initial: np.ndarray) -> np.ndarray:
    """Waistband targets of a skirt's waist vertices: each at its own azimuth on the waist
    ellipse (`WAIST_RADII`) at height `WAIST_Z`. initial (P, 3) -> (P, 3) meters."""
    rx, ry = WAIST_RADII
    ang = np.arctan2(initial[:, 1], initial[:, 0])
    return np.stack([rx * np.cos(ang), ry * np.sin(ang), np.full(len(initial), WAIST_Z)], 1)


def ellipse_perimeter(a: float, b: float) -> float:
    """Ramanujan's approximation of an ellipse's perimeter (meters)."""
    h = ((a - b) / (a + b)) ** 2
    return math.pi * (a + b) * (1 + 3 * h / (10 + math.sqrt(4 - 3 * h)))


def _rect(w: float, h: float) -> tuple:
    """Rectangle sides: 0 bottom, 1 right, 2 top, 3 left (counter-clockwise)."""
    c = np.array([[0, 0], [w, 0], [w, h], [0, h]], np.float64)
    return tuple(_poly([c[i], c[(i + 1) % 4]]) for i in range(4))


def sheet_pattern(width: float = 1.0, height: float = 1.0, top: float = 1.6) -> Pattern:
    """A hanging sheet in the x-z plane (front side facing -y), top edge at z = `top`."""

    def drape(_, p):
        return np.stack([p[:, 0] - width / 2, np.zeros(len(p)), top - height + p[:, 1]], 1)

    return Pattern("sheet", (Panel("sheet", _rect(width, height)),), (), drape,
                   {"top": (("sheet", 2),), "bottom": (("sheet", 0),)})


def panel_pattern(name: str, width: float, height: float, top: float, y: float,
                  facing: float) -> Pattern:
    """A rectangular panel hanging in an x-z plane at depth `y` (meters), its top edge (the
    "top" landmark, pinned by the scenes) at height `top`; `facing` = +1 puts the panel's
    front (outward) side towards +y, -1 towards -y."""

    def drape(_, p):
        x = facing * (width / 2 - p[:, 0])
        return np.stack([x, np.full(len(p), y), top - height + p[:, 1]], 1)

    return Pattern(name, (Panel(name, _rect(width, height)),), (), drape,
                   {"top": ((name, 2),), "bottom": ((name, 0),)})


# Mannequin landmarks the panels hang from (mannequin.HIP_HEIGHT + chest offsets): the
# shoulder line and the depth just outside the chest and pelvis capsules.
SHOULDER_Z = 1.44


def shawl_pattern() -> Pattern:
    """A shawl hanging down the back from the shoulder line (0.8 x 0.85 m, training)."""
    return panel_pattern("shawl", 0.8, 0.85, SHOULDER_Z, -0.17, -1.0)


def apron_pattern() -> Pattern:
    """An apron hanging in front of the legs from the waist (0.55 x 0.6 m, training)."""
    return panel_pattern("apron", 0.55, 0.6, WAIST_Z, 0.16, 1.0)


def tabard_pattern() -> Pattern:
    """VALIDATION-ONLY: a narrow front panel hanging from the shoulder line to the knees
    (0.45 x 0.9 m); checkpoint choices read it, training never sees it."""
    return panel_pattern("tabard", 0.45, 0.9, SHOULDER_Z, 0.17, 1.0)


def circle_skirt_pattern() -> Pattern:
    """A knee-length near-circle skirt (training): 6 gores, a 288-degree flare, 0.62 m long;
    much fuller than `flared_skirt`, so its hem swings out and folds into deep cones."""
    return flared_skirt_pattern(0.62, 1.6 * math.pi, 6, name="circle_skirt")


def long_shawl_pattern() -> Pattern:
    """A long, wide shawl down the back from the shoulder line to the calves (1.0 x 1.1 m,
    training): unlike `shawl`, its lower half hits the legs and folds around them."""
    return panel_pattern("long_shawl", 1.0, 1.1, SHOULDER_Z, -0.17, -1.0)


def _sector(r_in: float, r_out: float, angle: float, n: int = 96) -> tuple:
    """Annular sector centred on -v: sides 0 outer arc, 1 right edge, 2 inner arc, 3 left."""
    h = angle / 2
    return (_poly(_arc(r_out, -h, h, n)), _poly(_arc(1, h, h, 2) * [[r_out], [r_in]]),
            _poly(_arc(r_in, h, -h, n)), _poly(_arc(1, -h, -h, 2) * [[r_in], [r_out]]))


def flared_skirt_pattern(length: float = 0.8, flare: float = math.pi, gores: int = 4,
                         name: str = "flared_skirt") -> Pattern:
    """A long flared skirt: `gores` annular-sector panels, total pattern angle `flare`.

    The waist arc equals the waistband perimeter. Initial shape: the exact cone the flat
    sectors roll into (isometric), waist at `WAIST_Z`.
    """
    waist = ellipse_perimeter(*WAIST_RADII)
    r_in = waist / flare
    r_out = r_in + length
    g = flare / gores
    sin_b = flare / (2 * math.pi)
    cos_b = math.sqrt(1 - sin_b ** 2)
    apex = WAIST_Z + r_in * cos_b
    panels = tuple(Panel(f"gore{i}", _sector(r_in, r_out, g)) for i in range(gores))
    seams = tuple(Seam((f"gore{i}", 1), (f"gore{(i + 1) % gores}", 3)) for i in range(gores))

    def drape(i, p):
        rho = np.hypot(p[:, 0], p[:, 1])
        psi = np.arctan2(p[:, 0], -p[:, 1])
        theta = (i * g + psi) * (2 * math.pi / flare) - math.pi / 2
        r = rho * sin_b
        return np.stack([r * np.cos(theta), r * np.sin(theta), apex - rho * cos_b], 1)

    return Pattern(name, panels, seams, drape,
                   {"waist": tuple((f"gore{i}", 2) for i in range(gores)),
                    "hem": tuple((f"gore{i}", 0) for i in range(gores))},
                   pin_targets={"waist": waist_ring_targets})


def wavy_ring(length: float, radius: float, waves: int, rx_scale=1.0, ry_scale=1.0,
              n: int = 8192):
    """A closed wavy curve r(t) = radius + a (1 + sin(waves t)) of perimeter `length`.

    Returns:
      (f, a): f(s) -> (N, 2) points at arc length s (counter-clockwise from -y), and a.
    """
    t = np.linspace(0.0, 2 * np.pi, n + 1)

    def curve(a):
        r = radius + a * (1.0 + np.sin(waves * t))
        ang = t - np.pi / 2
        return np.stack([rx_scale * r * np.cos(ang), ry_scale * r * np.sin(ang)], 1)

    def perim(a):
        return np.linalg.norm(np.diff(curve(a), axis=0), axis=1).sum()

    lo, hi = 0.0, radius
    if perim(lo) > length:
        raise PatternError(f"a ring of radius {radius} m is longer than {length} m")
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if perim(mid) < length else (lo, mid)
    a = 0.5 * (lo + hi)
    c = curve(a)
    s = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(c, axis=0), axis=1))]
    s *= length / s[-1]

    def at(q):
        q = np.mod(q, length)
        return np.stack([np.interp(q, s, c[:, 0]), np.interp(q, s, c[:, 1])], 1)

    return at, a


def pleated_skirt_pattern(width: float = 1.8, length: float = 0.6, panels: int = 2,
                          pleats: int = 16) -> Pattern:
    """A pleated (gathered) skirt: `panels` rectangles sewn into a tube of girth `width`.

    The initial shape is the tube hung on a wavy ring of radius ~0.24 m (isometric: a
    generalized cylinder); the waistband pins then press the top into `pleats` pleats on the
    waist (see `pleated_waist_targets`).
    """
    pw = width / panels
    ring, _ = wavy_ring(width, 0.24, pleats)
    ps = tuple(Panel(f"panel{i}", _rect(pw, length)) for i in range(panels))
    seams = tuple(Seam((f"panel{i}", 1), (f"panel{(i + 1) % panels}", 3)) for i in range(panels))

    def drape(i, p):
        xy = ring(i * pw + p[:, 0])
        return np.concatenate([xy, (WAIST_Z - length + p[:, 1])[:, None]], 1)

    def waist_targets(initial):
        xy = pleated_waist_targets(initial[:, :2], width, pleats)
        return np.concatenate([xy, np.full((len(initial), 1), WAIST_Z)], 1)

    return Pattern("pleated_skirt", ps, seams, drape,
                   {"waist": tuple((f"panel{i}", 2) for i in range(panels)),
                    "hem": tuple((f"panel{i}", 0) for i in range(panels))},
                   pin_targets={"waist": waist_targets})


def pleated_waist_targets(initial_xy: np.ndarray, width: float = 1.8, pleats: int = 16):
    """Waistband targets of the pleated skirt: the same arc-length positions on a wavy ring
    around the waist ellipse. initial_xy (P, 2) -> (P, 2) meters."""
    big, _ = wavy_ring(width, 0.24, pleats)
    rx, ry = WAIST_RADII
    small, _ = wavy_ring(width, 1.0, pleats, rx_scale=rx, ry_scale=ry)
    # Arc length of each initial point on the big ring (nearest sample).
    q = np.linspace(0.0, width, 8193)
    ring = big(q)
    s = q[np.argmin(((initial_xy[:, None] - ring[None]) ** 2).sum(-1), axis=1)]
    return small(s)


def _dress_outline(neck_depth: float) -> tuple:
    """Front/back dress panel sides (local u across, v up from the hem)."""
    t = np.linspace(0.0, 1.0, 12)
    arm = np.stack([0.25 - 0.09 * t - 0.04 * np.sin(np.pi * t), 0.72 + 0.23 * t], 1)
    neck = np.stack([0.07 * np.cos(np.pi * t), 0.99 - neck_depth * np.sin(np.pi * t)], 1)
    return (
        _poly([[-0.32, 0.0], [0.32, 0.0]]),           # 0 hem
        _poly([[0.32, 0.0], [0.25, 0.72]]),           # 1 right side seam
        _poly(arm),                                    # 2 right armhole
        _poly([[0.16, 0.95], [0.07, 0.99]]),          # 3 right shoulder seam
        _poly(neck),                                   # 4 neckline
        _poly([[-0.07, 0.99], [-0.16, 0.95]]),        # 5 left shoulder seam
        _poly(arm[::-1] * [-1, 1]),                    # 6 left armhole
        _poly([[-0.25, 0.72], [-0.32, 0.0]]),         # 7 left side seam
    )


def dress_pattern(hem_z: float = 0.605) -> Pattern:
    """TEST-ONLY: a sleeveless A-line dress, front and back panels, side + shoulder seams.

    Girth ~1.0 m at the chest (the mannequin's is 0.88 m), 1.28 m at the hem. Initial shape:
    each horizontal line of a panel is rolled onto a half circle of radius 2 hw / pi (hw =
    the panel's half-width at that height), so front and back meet at the side seams; the top
    of each column curls over a quarter circle (radius = its distance from the y = 0 plane)
    so the shoulder seams meet on top of the shoulders. Nearly isometric; the pre-roll relaxes
    the rest.
    """

    def drape(i, p):
        u, v = p[:, 0], p[:, 1]
        hw = np.where(v <= 0.72, 0.32 - 0.07 * v / 0.72, 0.25)
        rho = 2 * hw / np.pi
        au = np.abs(u)
        v_sh = np.where(au >= 0.07, 0.99 - 0.04 * (np.clip(au, 0.07, 0.16) - 0.07) / 0.09, 0.99)
        radius = np.maximum(rho * np.cos(np.clip(u / rho, -np.pi / 2, np.pi / 2)), 1e-3)
        v_b = v_sh - np.pi * radius / 2
        phi = np.clip(v - v_b, 0, None) / radius
        x = rho * np.sin(u / rho)
        y = radius * np.cos(phi)
        z = hem_z + np.minimum(v, v_b) + radius * np.sin(phi)
        sign = 1.0 if i == 0 else -1.0  # front: x = -u (outward normals), back: x = u
        return np.stack([-sign * x, sign * y, z], 1)

    panels = (Panel("front", _dress_outline(0.09)), Panel("back", _dress_outline(0.03)))
    seams = (Seam(("front", 1), ("back", 7)), Seam(("front", 7), ("back", 1)),
             Seam(("front", 3), ("back", 5)), Seam(("front", 5), ("back", 3)))
    return Pattern("dress", panels, seams, drape,
                   {"shoulders": (("front", 3), ("front", 5)), "hem": (("front", 0), ("back", 0))})


CAPE_NECK_Z = 1.50
CAPE_NECK_RADIUS = 0.09


def cape_pattern(length: float = 0.55, angle: float = 1.4 * math.pi, z: float = 1.56) -> Pattern:
    """TEST-ONLY: a circular cape (annular sector of `angle`, open at the front).

    Initial shape: flat and horizontal at height `z` around the head (isometric); the neck
    pins then close the inner arc into a ring around the neck (see `cape_neck_targets`).
    """
    r_in = 2 * math.pi * CAPE_NECK_RADIUS / angle
    panels = (Panel("cape", _sector(r_in, r_in + length, angle, n=160)),)

    def drape(_, p):
        return np.stack([p[:, 0], p[:, 1], np.full(len(p), z)], 1)

    def neck_targets(initial):
        xy = cape_neck_targets(initial[:, :2], angle)
        return np.concatenate([xy, np.full((len(initial), 1), CAPE_NECK_Z)], 1)

    return Pattern("cape", panels, (), drape, {"neck": (("cape", 2),), "hem": (("cape", 0),)},
                   pin_targets={"neck": neck_targets})


def cape_neck_targets(initial_xy: np.ndarray, angle: float = 1.4 * math.pi) -> np.ndarray:
    """Ring positions (P, 2) around the neck for the cape's inner-arc vertices (P, 2)."""
    psi = np.arctan2(initial_xy[:, 0], -initial_xy[:, 1])
    theta = psi * (2 * math.pi / angle) - math.pi / 2
    return CAPE_NECK_RADIUS * np.stack([np.cos(theta), np.sin(theta)], 1)


GARMENTS = {
    "sheet": sheet_pattern,
    "flared_skirt": flared_skirt_pattern,
    "circle_skirt": circle_skirt_pattern,
    "pleated_skirt": pleated_skirt_pattern,
    "dress": dress_pattern,
    "cape": cape_pattern,
    "shawl": shawl_pattern,
    "long_shawl": long_shawl_pattern,
    "apron": apron_pattern,
    "tabard": tabard_pattern,
}
TEST_ONLY_GARMENTS = ("dress", "cape")
VAL_ONLY_GARMENTS = ("tabard",)


def make_pattern(name: str) -> Pattern:
    """The named garment's pattern; raises PatternError naming the valid choices."""
    try:
        return GARMENTS[name]()
    except KeyError:
        raise PatternError(f"unknown garment {name!r}; expected one of "
                           f"{', '.join(GARMENTS)}") from None
