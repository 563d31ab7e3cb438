"""Meshing machinery of the sewing patterns (`patterns`): 2D panels (polygons in meters) meshed
at a particle distance into seamed garments whose UVs ARE the pattern coordinates. The garment
catalogue is in `patterns`, which re-exports every name here (old import paths keep working).

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
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable

import numpy as np

from wrinkle_jax.mesh import Garment, make_garment, unique_edges, unique_rows


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
      pin_targets: {landmark name: f(initial (P, 3) float64) -> (P, 3) float64}: where a
        scene that pins this landmark attaches its vertices, in the rest pose of the body
        frame it follows (meters; e.g. a skirt's waist closes onto the waistband ellipse).
        A landmark not listed is pinned where `drape` put it. The pattern carries this, not
        the scene, so every garment a pattern function builds is pinned the same way.
    """

    name: str
    panels: tuple
    seams: tuple
    drape: Callable
    landmarks: dict
    pin_targets: dict = dataclasses.field(default_factory=dict)


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
    _, first = unique_rows(srt, return_index=True)
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
