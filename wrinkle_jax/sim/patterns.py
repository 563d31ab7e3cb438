"""Sewing patterns: 2D panels (polygons in meters) meshed at a particle distance into seamed
garments whose UVs ARE the pattern coordinates.

Contract:
  * A `Pattern` is a set of `Panel`s (counter-clockwise outlines made of sides, each side a
    polyline in meters), `Seam`s that sew one side to another, and a `drape` function that
    places each panel's points in 3D (the initial, near-isometric shape).
  * `mesh_pattern(pattern, pd, seed)` (NumPy, once) returns a `PatternMesh`:

        garment.vertices (V, 3) float32 m   welded across seams (one vertex per seam point)
        garment.faces    (F, 3) int32       counter-clockwise in UV = outward in 3D
        garment.uvs      (T, 2) float32 m   pattern coordinates, panels laid side by side
        garment.uv_faces (F, 3) int32       split along seams (T >= V)
        garment.panels   (F,)   int32
        side_vertices    {(panel, side): (n+1,) int32 3D vertex ids from the side's start to
                          its end}

    Both sides of a seam are resampled with the same number of points, so welding is exact.
  * Meshing is isotropic and slightly irregular so wrinkles do not align with a grid: sides are
    resampled at spacing <= pd, the interior is a jittered equilateral lattice kept >= 0.55 pd
    from the outline, and the points are Delaunay-triangulated by a vectorized local method
    (every point's k nearest neighbours give candidate triangles, kept when their circumcircle
    is provably empty). The result is validated (area equals the polygon area, manifold edges)
    and its minimum angle is reported by `mesh_quality`.

Garments (`GARMENTS`): `sheet` (1 m square, hanging), `flared_skirt` (4 gores, half-circle
flare), `circle_skirt` (6 gores, 288-degree flare, knee length), `pleated_skirt` (2 panels,
16 pleats pressed into the waist), and test-only `dress` (front/back with side and shoulder
seams) and `cape` (a 252-degree circular cape fastened at the neck); hanging panels pinned
along their top edge: `shawl` (down the back from the shoulders), `long_shawl` (1.0 x 1.1 m,
down to the calves) and `apron` (in front of the legs from the waist), and validation-only
`tabard` (in front, from the shoulders). Coordinates: z up, the mannequin faces +y.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable

import numpy as np

from wrinkle_jax.mesh import Garment, make_garment, unique_edges


class PatternError(ValueError):
    """An invalid pattern or a meshing failure (the message names the panel)."""


@dataclasses.dataclass(frozen=True)
class Panel:
    """One pattern piece.

    Attributes:
      name: unique within the pattern.
      sides: tuple of polylines ((k_i, 2) as tuples, meters); side i ends where side i+1
        starts and the last side ends at the first side's start. The outline runs
        counter-clockwise.
    """

    name: str
    sides: tuple


@dataclasses.dataclass(frozen=True)
class Seam:
    """Sew side `a` = (panel name, side index) to side `b`; `a`'s start meets `b`'s end."""

    a: tuple
    b: tuple


@dataclasses.dataclass(frozen=True, eq=False)
class Pattern:
    """Panels, seams, the 3D placement and named landmarks.

    Attributes:
      name: garment name.
      panels: tuple of Panel.
      seams: tuple of Seam.
      drape: f(panel_index, local (N, 2) float64) -> (N, 3) float64 initial positions.
      landmarks: {name: tuple of (panel name, side index)} (e.g. "waist", "hem").
    """

    name: str
    panels: tuple
    seams: tuple
    drape: Callable
    landmarks: dict


@dataclasses.dataclass(frozen=True, eq=False)
class PatternMesh:
    """A meshed pattern (see the module docstring for shapes)."""

    garment: Garment
    pd: float
    side_vertices: dict
    uv_offsets: np.ndarray  # (num_panels, 2): uv = local + offset

    def landmark_vertices(self, pattern: Pattern, name: str) -> np.ndarray:
        """Unique 3D vertex ids along a landmark's sides (sorted)."""
        ids = [self.side_vertices[tuple(s)] for s in pattern.landmarks[name]]
        return np.unique(np.concatenate(ids)).astype(np.int32)


def _poly(points) -> tuple:
    return tuple(tuple(float(c) for c in p) for p in np.asarray(points, np.float64))


def _arc(radius: float, a0: float, a1: float, n: int = 64, center=(0.0, 0.0)) -> np.ndarray:
    """Polyline of a circular arc, angles in radians measured from -v towards +u."""
    t = np.linspace(a0, a1, n)
    return np.stack([center[0] + radius * np.sin(t), center[1] - radius * np.cos(t)], 1)


# --------------------------------------------------------------------------------------------
# Meshing
# --------------------------------------------------------------------------------------------


def _polyline_length(p: np.ndarray) -> float:
    return float(np.linalg.norm(np.diff(p, axis=0), axis=1).sum())


def _resample(p: np.ndarray, n: int) -> np.ndarray:
    """n + 1 points at uniform arc length along a polyline (endpoints kept exactly)."""
    seg = np.linalg.norm(np.diff(p, axis=0), axis=1)
    s = np.r_[0.0, np.cumsum(seg)]
    t = np.linspace(0.0, s[-1], n + 1)
    out = np.stack([np.interp(t, s, p[:, 0]), np.interp(t, s, p[:, 1])], 1)
    out[0], out[-1] = p[0], p[-1]
    return out


def _inside_and_distance(pts: np.ndarray, loop: np.ndarray, chunk: int = 2048):
    """Point-in-polygon (crossing number) and distance to the outline, vectorized in chunks."""
    a, b = loop, np.roll(loop, -1, axis=0)
    ab = b - a
    ab2 = np.maximum((ab * ab).sum(1), 1e-300)
    dy = np.where(np.abs(ab[:, 1]) > 0, ab[:, 1], 1.0)
    inside = np.zeros(len(pts), bool)
    dist = np.zeros(len(pts))
    for s in range(0, len(pts), chunk):
        p = pts[s:s + chunk, None, :]
        cross = (a[:, 1] > p[..., 1]) != (b[:, 1] > p[..., 1])
        x_at = a[:, 0] + (p[..., 1] - a[:, 1]) * ab[:, 0] / dy
        inside[s:s + chunk] = (cross & (p[..., 0] < x_at)).sum(1) % 2 == 1
        t = np.clip(((p - a) * ab).sum(-1) / ab2, 0.0, 1.0)
        d = p - (a + t[..., None] * ab)
        dist[s:s + chunk] = np.sqrt((d * d).sum(-1)).min(1)
    return inside, dist


def _knn(points: np.ndarray, k: int, cell: float, reach: int = 3):
    """k nearest neighbours (excluding self) via a uniform grid.

    Returns:
      (idx (N, k) int64, -1 padded; dist (N, k) float64, inf padded; coverage (N,) radius
      within which the returned neighbours are complete).
    """
    n = len(points)
    g = np.floor((points - points.min(0)) / cell).astype(np.int64)
    ny = int(g[:, 1].max()) + 1 + 2 * reach
    g += reach
    key = g[:, 0] * ny + g[:, 1]
    order = np.argsort(key, kind="stable")
    skey = key[order]
    per_cell = int(np.unique(skey, return_counts=True)[1].max())
    lanes = np.arange(per_cell)
    cands = []
    for dx in range(-reach, reach + 1):
        for dy in range(-reach, reach + 1):
            q = key + dx * ny + dy
            lo = np.searchsorted(skey, q, "left")
            hi = np.searchsorted(skey, q, "right")
            j = lo[:, None] + lanes
            ok = j < hi[:, None]
            cands.append(np.where(ok, order[np.minimum(j, n - 1)], -1))
    cand = np.concatenate(cands, 1)
    d = np.where(cand >= 0, np.linalg.norm(points[np.maximum(cand, 0)] - points[:, None], axis=-1),
                 np.inf)
    d[cand == np.arange(n)[:, None]] = np.inf
    kk = min(k, cand.shape[1])
    part = np.argpartition(d, kk - 1, axis=1)[:, :kk]
    dp = np.take_along_axis(d, part, 1)
    srt = np.argsort(dp, axis=1)
    idx = np.take_along_axis(np.take_along_axis(cand, part, 1), srt, 1)
    dist = np.take_along_axis(dp, srt, 1)
    idx = np.where(np.isfinite(dist), idx, -1)
    coverage = np.minimum(np.where(np.isfinite(dist[:, -1]), dist[:, -1], np.inf), reach * cell)
    return idx, dist, coverage


def _local_delaunay(points: np.ndarray, spacing: float, k_cand: int = 10, k_check: int = 24,
                    chunk: int = 65536) -> np.ndarray:
    """Delaunay triangles of well-spaced 2D points, (M, 3) counter-clockwise.

    A triangle (i, j, l) with j, l among i's `k_cand` nearest neighbours is kept when no point
    among i's `k_check` nearest lies inside its circumcircle and that circle lies within the
    radius where the neighbour list is complete (so the emptiness test is exact).
    """
    idx, _, coverage = _knn(points, k_check, spacing)
    kc = min(k_cand, idx.shape[1])
    ja, jb = np.triu_indices(kc, 1)
    i = np.repeat(np.arange(len(points)), len(ja))
    j = idx[:, :kc][:, ja].reshape(-1)
    l = idx[:, :kc][:, jb].reshape(-1)
    ok = (j >= 0) & (l >= 0)
    i, j, l = i[ok], j[ok], l[ok]
    keep = []
    for s in range(0, len(i), chunk):
        ii, jj, ll = i[s:s + chunk], j[s:s + chunk], l[s:s + chunk]
        b = points[jj] - points[ii]
        c = points[ll] - points[ii]
        cr = b[:, 0] * c[:, 1] - b[:, 1] * c[:, 0]
        good = np.abs(cr) > 2e-3 * spacing * spacing
        den = np.where(good, 2.0 * cr, 1.0)
        b2, c2 = (b * b).sum(1), (c * c).sum(1)
        u = np.stack([(c[:, 1] * b2 - b[:, 1] * c2) / den, (b[:, 0] * c2 - c[:, 0] * b2) / den], 1)
        r2 = (u * u).sum(1)
        good &= 2.0 * np.sqrt(r2) <= coverage[ii]
        nb = idx[ii]
        q = points[np.maximum(nb, 0)] - points[ii][:, None] - u[:, None]
        inside = ((q * q).sum(-1) < r2[:, None] * (1.0 - 1e-9)) & (nb >= 0)
        inside &= (nb != jj[:, None]) & (nb != ll[:, None])
        good &= ~inside.any(1)
        t = np.stack([ii, jj, ll], 1)[good]
        flip = cr[good] < 0
        t[flip] = t[flip][:, [0, 2, 1]]
        keep.append(t)
    tris = np.concatenate(keep) if keep else np.zeros((0, 3), np.int64)
    # Each triangle is found from up to three of its corners: deduplicate, keep orientation.
    srt = np.sort(tris, 1)
    _, first = np.unique(srt, axis=0, return_index=True)
    return tris[np.sort(first)]


def _mesh_panel(panel: Panel, counts: list[int], pd: float, rng: np.random.Generator,
                jitter: float):
    """Mesh one panel. Returns (points (N, 2), faces (F, 3), side_ranges [(start, n)])."""
    sides = [np.asarray(s, np.float64) for s in panel.sides]
    boundary, ranges = [], []
    start = 0
    for s, n in zip(sides, counts, strict=True):
        pts = _resample(s, n)
        boundary.append(pts[:-1])
        ranges.append((start, n))
        start += n
    loop = np.concatenate(boundary)
    area = 0.5 * float(np.sum(loop[:, 0] * np.roll(loop[:, 1], -1)
                              - np.roll(loop[:, 0], -1) * loop[:, 1]))
    if area <= 0:
        raise PatternError(f"panel {panel.name!r}: outline must be counter-clockwise "
                           f"(signed area {area:.4g} m^2)")
    lo, hi = loop.min(0) - pd, loop.max(0) + pd
    dy = pd * math.sqrt(3.0) / 2.0
    off = rng.uniform(0.0, 1.0, 2) * np.array([pd, dy])
    rows = np.arange(int((hi[1] - lo[1]) / dy) + 2)
    cols = np.arange(int((hi[0] - lo[0]) / pd) + 2)
    r, c = np.meshgrid(rows, cols, indexing="ij")
    lat = np.stack([lo[0] + off[0] + (c + 0.5 * (r % 2)) * pd, lo[1] + off[1] + r * dy],
                   -1).reshape(-1, 2)
    ang = rng.uniform(0.0, 2.0 * np.pi, len(lat))
    rad = jitter * pd * np.sqrt(rng.uniform(0.0, 1.0, len(lat)))
    lat = lat + rad[:, None] * np.stack([np.cos(ang), np.sin(ang)], 1)
    inside, dist = _inside_and_distance(lat, loop)
    interior = lat[inside & (dist >= 0.55 * pd)]
    pts = np.concatenate([loop, interior])
    tris = _local_delaunay(pts, pd)
    cen = pts[tris].mean(1)
    tris = tris[_inside_and_distance(cen, loop)[0]]
    e = pts[tris]
    got = 0.5 * np.sum((e[:, 1, 0] - e[:, 0, 0]) * (e[:, 2, 1] - e[:, 0, 1])
                       - (e[:, 1, 1] - e[:, 0, 1]) * (e[:, 2, 0] - e[:, 0, 0]))
    if abs(got - area) > 1e-6 * area:
        raise PatternError(f"panel {panel.name!r}: meshing at pd={pd} m covered {got:.6f} of "
                           f"{area:.6f} m^2 (holes or overlaps)")
    _, counts_e = np.unique(np.sort(np.concatenate(
        [tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]]), 1), axis=0, return_counts=True)
    if counts_e.max() > 2:
        raise PatternError(f"panel {panel.name!r}: non-manifold triangulation at pd={pd} m")
    return pts, tris, ranges


def mesh_pattern(pattern: Pattern, pd: float, seed: int = 0, jitter: float = 0.2,
                 gap: float = 0.05) -> PatternMesh:
    """Mesh a pattern at particle distance `pd` (meters) and weld its seams.

    Args:
      pattern: panels, seams, drape.
      pd: target edge length, meters (30 mm coarse, 10 mm fine in the paper).
      seed: NumPy seed of the lattice offset and jitter (deterministic meshes).
      jitter: interior point jitter radius as a fraction of pd.
      gap: spacing between panels in the UV layout, meters.
    Returns:
      PatternMesh (validated Garment; UVs in meters).
    Raises:
      PatternError: unknown seam sides, seam sides of different length, or a meshing failure.
    """
    if not pd > 0:
        raise PatternError(f"{pattern.name}: pd must be positive, got {pd}")
    lengths = {(p.name, s): _polyline_length(np.asarray(side)) for p in pattern.panels
               for s, side in enumerate(p.sides)}
    counts = {k: max(1, math.ceil(v / pd - 1e-9)) for k, v in lengths.items()}
    for seam in pattern.seams:
        for side in (seam.a, seam.b):
            if tuple(side) not in lengths:
                raise PatternError(f"{pattern.name}: seam names unknown side {side}")
        la, lb = lengths[tuple(seam.a)], lengths[tuple(seam.b)]
        if abs(la - lb) > 1e-3 * max(la, lb):
            raise PatternError(f"{pattern.name}: seam {seam.a}-{seam.b} joins sides of "
                               f"different length ({la:.4f} vs {lb:.4f} m)")
        n = max(counts[tuple(seam.a)], counts[tuple(seam.b)])
        counts[tuple(seam.a)] = counts[tuple(seam.b)] = n
    rng = np.random.default_rng(seed)
    uvs, faces, panel_of, local_all, owner, offsets = [], [], [], [], [], []
    side_uv: dict = {}
    base, cursor = 0, 0.0
    for pi, panel in enumerate(pattern.panels):
        pts, tris, ranges = _mesh_panel(
            panel, [counts[(panel.name, s)] for s in range(len(panel.sides))], pd, rng, jitter)
        off = np.array([cursor - pts[:, 0].min(), -pts[:, 1].min()])
        cursor += float(np.ptp(pts[:, 0])) + gap
        offsets.append(off)
        nb = sum(n for _, n in ranges)
        for s, (start, n) in enumerate(ranges):
            side_uv[(panel.name, s)] = base + (start + np.arange(n + 1)) % nb
        uvs.append(pts + off)
        local_all.append(pts)
        faces.append(tris + base)
        panel_of.append(np.full(len(tris), pi, np.int32))
        owner.append(np.full(len(pts), pi))
        base += len(pts)
    uv = np.concatenate(uvs)
    uv_faces = np.concatenate(faces)
    # Weld: union-find over the seam pairs (a's k-th point meets b's (n-k)-th).
    parent = np.arange(len(uv))

    def find(a):
        while parent[a] != a:
            parent[a] = parent[parent[a]]
            a = parent[a]
        return a

    for seam in pattern.seams:
        sa, sb = side_uv[tuple(seam.a)], side_uv[tuple(seam.b)][::-1]
        for x, y in zip(sa.tolist(), sb.tolist(), strict=True):
            rx, ry = find(x), find(y)
            if rx != ry:
                parent[max(rx, ry)] = min(rx, ry)
    roots = np.array([find(a) for a in range(len(uv))])
    uniq, weld = np.unique(roots, return_inverse=True)
    owner = np.concatenate(owner)
    local = np.concatenate(local_all)
    pos_uv = np.zeros((len(uv), 3))
    for pi in range(len(pattern.panels)):
        m = owner == pi
        pos_uv[m] = pattern.drape(pi, local[m])
    pos = np.zeros((len(uniq), 3))
    np.add.at(pos, weld, pos_uv)
    pos /= np.bincount(weld, minlength=len(uniq))[:, None]
    mismatch = float(np.abs(pos[weld] - pos_uv).max())
    if mismatch > 2e-3:
        raise PatternError(f"{pattern.name}: the drape places seam partners {mismatch:.4f} m "
                           "apart (sides sewn together must meet in 3D)")
    garment = make_garment(pos, weld[uv_faces], uv, uv_faces, np.concatenate(panel_of),
                           source=f"pattern {pattern.name} (pd={pd})")
    side_vertices = {k: weld[v].astype(np.int32) for k, v in side_uv.items()}
    return PatternMesh(garment, float(pd), side_vertices, np.asarray(offsets))


def mesh_quality(garment: Garment) -> dict:
    """UV-space quality: min/mean triangle angle (degrees) and edge-length spread (NumPy)."""
    uv = np.asarray(garment.uvs, np.float64)[np.asarray(garment.uv_faces)]
    e = [uv[:, 1] - uv[:, 0], uv[:, 2] - uv[:, 1], uv[:, 0] - uv[:, 2]]
    angles = []
    for k in range(3):
        a, b = -e[k - 1], e[k]
        cos = (a * b).sum(1) / np.maximum(np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1),
                                          1e-300)
        angles.append(np.degrees(np.arccos(np.clip(cos, -1, 1))))
    angles = np.stack(angles, 1)
    lengths = np.linalg.norm(np.concatenate(e), axis=1)
    edges = unique_edges(garment.faces)
    return {
        "vertices": int(garment.num_vertices),
        "faces": int(garment.num_faces),
        "edges": int(len(edges)),
        "min_angle_deg": float(angles.min()),
        "p01_angle_deg": float(np.percentile(angles.min(1), 1)),
        "mean_min_angle_deg": float(angles.min(1).mean()),
        "edge_mean_m": float(lengths.mean()),
        "edge_cv": float(lengths.std() / lengths.mean()),
    }


# --------------------------------------------------------------------------------------------
# Garments
# --------------------------------------------------------------------------------------------

WAIST_Z = 1.03          # meters: skirt waistband height on the mannequin
WAIST_RADII = (0.152, 0.132)  # ellipse half-axes (x, y) of the waistband, meters


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
                    "hem": tuple((f"gore{i}", 0) for i in range(gores))})


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

    return Pattern("pleated_skirt", ps, seams, drape,
                   {"waist": tuple((f"panel{i}", 2) for i in range(panels)),
                    "hem": tuple((f"panel{i}", 0) for i in range(panels))})


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

    return Pattern("cape", panels, (), drape, {"neck": (("cape", 2),), "hem": (("cape", 0),)})


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
