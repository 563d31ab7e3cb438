"""XPBD cloth model: the pytrees the solver (`xpbd`) runs on, and their allocation (NumPy, once
per mesh).

`build_cloth(garment, pinned, ...)` -> `ClothModel`: topology, rest data and graph-coloured
constraints (stretch per edge, isometric bending per interior edge, multi-scale stretch limits,
long-range attachments to the pins), optional wind and self-collision topology.
`fabric_params(fabric)` -> `SimParams` (scalars), so one compiled solver serves every material
of a scene. `Drive` and `ClothState` are the solver's kinematic inputs and state. Units: meters,
seconds, kilograms. `xpbd` re-exports every name here (old import paths keep working).
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from wrinkle_jax.mesh import Garment
from wrinkle_jax.numerics import to_device
from wrinkle_jax.sim import aero, selfcollision
from wrinkle_jax.sim.colliders import Colliders
from wrinkle_jax.sim.materials import Fabric

GRAVITY = (0.0, 0.0, -9.81)


# --------------------------------------------------------------------------------------------
# Pytrees
# --------------------------------------------------------------------------------------------


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class StretchColor:
    """One colour of edge constraints (no vertex appears twice).

    Attributes: i, j (n,) int32 vertices; rest (n,) rest length, m; inv_area (n,) 1 / A_e,
    1/m^2 (A_e = a third of the adjacent faces' rest area).
    """

    i: Any
    j: Any
    rest: Any
    inv_area: Any


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class BendColor:
    """One colour of bending hinges: idx (n, 4) int32 (edge x0 x1, opposite x2 x3) and
    weights (n, 4) = sqrt(1 / (A_1 + A_2)) * cotangent weights, 1/m (sqrt(1 / A_free) on
    the rim of a pinned 2-D region, see `_hinges`)."""

    idx: Any
    weights: Any


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class LimitColor:
    """One colour of unilateral distance limits |x_j - x_i| <= max_dist (n,) m."""

    i: Any
    j: Any
    max_dist: Any


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Attachments:
    """Long-range attachments: vertex (n,) int32, slot (n,) index into the pins, max_dist (n,) m."""

    vertex: Any
    slot: Any
    max_dist: Any


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class ClothModel:
    """Topology and rest data of a garment (NumPy/JAX arrays; a pytree).

    Attributes:
      faces: (F, 3) int32.
      vertex_area: (V,) rest area lumped to vertices, m^2 (mass = density * area).
      free: (V,) float32, 0 on pinned vertices, 1 elsewhere.
      pin_idx: (P,) int32 pinned vertices, or None.
      stretch: tuple of StretchColor; bend: tuple of BendColor.
      limits: tuple of LimitColor (multi-scale stretch limits, see `stretch_limits`).
      attach: Attachments or None.
      wind: aero.WindField or None (still air).
      aero: () bool-like marker array or None: None disables aerodynamics entirely.
      vertex_faces: (V, D) int32 incident faces padded with F (aero force gathering).
      self_topo: selfcollision.SelfTopology (rest geometry; used only when the config
        enables self-collision).
    """

    faces: Any
    vertex_area: Any
    free: Any
    pin_idx: Any
    stretch: tuple
    bend: tuple
    limits: tuple = ()
    attach: Any = None
    wind: Any = None
    aero: Any = None
    vertex_faces: Any = None
    self_topo: Any = None


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class SimParams:
    """Material and environment scalars (a pytree of float32 arrays, see `fabric_params`)."""

    density: Any
    stretch: Any
    bending: Any
    damping: Any
    friction: Any
    offset: Any
    drag: Any
    lift: Any
    gravity: Any


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Drive:
    """Kinematic inputs at one frame boundary: time (s), pins (P, 3) or None, colliders,
    extra_damping (1/s, e.g. during the pre-roll)."""

    time: Any
    pins: Any
    colliders: Colliders
    extra_damping: Any


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class ClothState:
    """Positions (V, 3) m and velocities (V, 3) m/s; with self-collision also
    self_overflow (3,) int32, candidates dropped since `init_fn` (held at the int32 maximum
    rather than wrapping; `xpbd.simulate_frames` returns int64 totals): the two counts of
    `selfcollision.Candidates.overflow`, then contacts beyond the flat list
    (`SelfCollisionConfig.pairs_per_vertex`); with the flat build (`build_pairs`) cell
    entries not read, triangles not given the exact test, contacts beyond the list (the
    nearest kept); with `SelfCollisionConfig.untangle` a fourth count (4,): crossed face
    pairs beyond the untangling step's list; else None."""

    x: Any
    v: Any
    self_overflow: Any = None

    def replace(self, **changes) -> ClothState:
        return dataclasses.replace(self, **changes)


def fabric_params(f: Fabric, gravity=GRAVITY) -> SimParams:
    """Solver scalars of a fabric."""
    c = functools.partial(to_device, dtype=jnp.float32)
    # `gravity` may be a tuple, which to_device would read as a pytree of three scalars.
    g = gravity if isinstance(gravity, jax.Array) else np.asarray(gravity)
    return SimParams(c(f.density), c(f.stretch), c(f.bending), c(f.damping), c(f.friction),
                     c(f.contact_offset), c(f.drag), c(f.lift), c(g))


# --------------------------------------------------------------------------------------------
# Allocation (NumPy)
# --------------------------------------------------------------------------------------------


def color_constraints(idx: np.ndarray, num_vertices: int, seed: int = 0) -> list[np.ndarray]:
    """Partition constraints so that no two in a colour share a vertex (vectorized).

    Each colour is grown as a maximal independent set by rounds of random priorities (Luby):
    a constraint joins when its priority is the largest among the remaining constraints at
    each of its vertices.

    Args:
      idx: (n, k) vertex indices of n constraints.
    Returns:
      list of constraint-id arrays, largest colours first.
    """
    rng = np.random.default_rng(seed)
    remaining = np.arange(len(idx))
    colors = []
    k = idx.shape[1]
    while remaining.size:
        used = np.zeros(num_vertices, bool)
        cand = remaining
        chosen = []
        while cand.size:
            pr = rng.random(cand.size)
            best = np.full(num_vertices, -1.0)
            np.maximum.at(best, idx[cand].reshape(-1), np.repeat(pr, k))
            win = np.all(best[idx[cand]] == pr[:, None], axis=1)
            chosen.append(cand[win])
            used[idx[cand[win]].reshape(-1)] = True
            cand = cand[~win]
            cand = cand[~used[idx[cand]].any(axis=1)]
        col = np.concatenate(chosen)
        colors.append(np.sort(col))
        remaining = np.setdiff1d(remaining, col, assume_unique=True)
    return colors


def _uv_corner_geometry(garment: Garment):
    uv = np.asarray(garment.uvs, np.float64)[np.asarray(garment.uv_faces)]
    e1, e2 = uv[:, 1] - uv[:, 0], uv[:, 2] - uv[:, 0]
    area = 0.5 * np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0])
    return uv, area


def _hinges(garment: Garment, pinned=None):
    """Interior edges with their two faces: (x0, x1, x2, x3) (n, 4), the rest weights (n, 4),
    1/m, and the rest distance x2-x3 (n,) m (NaN across a seam).

    pinned: optional (P,) vertex ids held by kinematic tracks; hinges on the rim of a pinned
    2-D region (a clamp) get the clamped-boundary normalisation (see below)."""
    f = np.asarray(garment.faces, np.int64)
    uv, area = _uv_corner_geometry(garment)
    nf = len(f)
    k = np.tile(np.arange(3), nf)
    fi = np.repeat(np.arange(nf), 3)
    a, b = f[fi, k], f[fi, (k + 1) % 3]
    key = np.minimum(a, b) * (f.max() + 1) + np.maximum(a, b)
    order = np.argsort(key, kind="stable")
    ks = key[order]
    pair = np.flatnonzero((ks[1:] == ks[:-1]) & np.r_[True, ks[1:-1] != ks[:-2]]
                          & np.r_[ks[2:] != ks[1:-1], True])
    h0, h1 = order[pair], order[pair + 1]

    def cot_at(face, corner, other, opp):
        p, q, r = uv[face, corner], uv[face, other], uv[face, opp]
        u, w = q - p, r - p
        cross = np.abs(u[:, 0] * w[:, 1] - u[:, 1] * w[:, 0])
        return (u * w).sum(1) / np.maximum(cross, 1e-300)

    fa, ka = fi[h0], k[h0]
    fb, kb = fi[h1], k[h1]
    x0, x1 = f[fa, ka], f[fa, (ka + 1) % 3]
    x2, x3 = f[fa, (ka + 2) % 3], f[fb, (kb + 2) % 3]
    # Corner indices of x0 / x1 inside face b (its half-edge may run either way).
    kb0 = np.where(f[fb, kb] == x0, kb, (kb + 1) % 3)
    kb1 = np.where(f[fb, kb] == x0, (kb + 1) % 3, kb)
    ca0 = cot_at(fa, ka, (ka + 1) % 3, (ka + 2) % 3)        # angle at x0 in face a
    ca1 = cot_at(fa, (ka + 1) % 3, ka, (ka + 2) % 3)        # angle at x1 in face a
    cb0 = cot_at(fb, kb0, kb1, (kb + 2) % 3)                # angle at x0 in face b
    cb1 = cot_at(fb, kb1, kb0, (kb + 2) % 3)                # angle at x1 in face b
    w = np.stack([ca1 + cb1, ca0 + cb0, -(ca0 + ca1), -(cb0 + cb1)], 1)
    # Bergou et al. weight the hinge by 3 / (A_1 + A_2); we use 1 / (A_1 + A_2) so that a
    # cylinder of radius R stores B / (2 R^2) per unit area, the energy of the cylindrical
    # bend that defines a measured (KES) bending rigidity B (checked in the tests).
    # Clamped boundary: a hinge whose edge x0-x1 and one wing are pinned lies on the rim of a
    # clamp (the textile tests' platform and support disc). Its pinned face is held flat, so
    # the stencil sees the mean of zero and the free side's curvature, while the continuum
    # energy of its domain lies on the free side only: normalising by the free face's area
    # A_f instead of A_1 + A_2 restores first-order consistency (1-D: the clamp spring must be
    # B / h_free, not B / mean(h)). Measured on static cantilever minima (experiments/
    # bend_calibration.py): the error in the bending length falls from O(PD) (16 % at PD
    # 10 mm for denim) to O(PD^2) (2.4 %). A pinned row (waistbands, shawl tops) has no
    # pinned wing and keeps the interior weights.
    norm = area[fa] + area[fb]
    if pinned is not None and len(pinned):
        pin = np.zeros(garment.num_vertices, bool)
        pin[np.asarray(pinned)] = True
        clamp = pin[x0] & pin[x1] & (pin[x2] ^ pin[x3])
        norm = np.where(clamp, np.where(pin[x2], area[fb], area[fa]), norm)
    w *= np.sqrt(1.0 / np.maximum(norm, 1e-300))[:, None]
    # Rest distance across the hinge (x2 to x3), valid when both faces share a UV panel.
    diag = np.linalg.norm(uv[fa, (ka + 2) % 3] - uv[fb, (kb + 2) % 3], axis=1)
    same = np.asarray(garment.uv_faces)[fa, ka] == np.asarray(garment.uv_faces)[fb, kb0]
    return np.stack([x0, x1, x2, x3], 1), w, np.where(same, diag, np.nan)


def _geodesic_to_pins(garment: Garment, pinned: np.ndarray, edges, rest):
    """Graph distance (V,) from every vertex to its nearest pin and that pin's slot (V,)."""
    n = garment.num_vertices
    dist = np.full(n, np.inf)
    slot = np.full(n, -1)
    dist[pinned] = 0.0
    slot[pinned] = np.arange(len(pinned))
    a = np.r_[edges[:, 0], edges[:, 1]]
    b = np.r_[edges[:, 1], edges[:, 0]]
    length = np.r_[rest, rest]
    for _ in range(n):
        cand = dist[a] + length
        new = dist.copy()
        np.minimum.at(new, b, cand)
        improved = new < dist
        if not improved.any():
            break
        hit = improved[b] & (cand == new[b])
        slot[b[hit]] = slot[a[hit]]
        dist = new
    return dist, slot


def _nearest(points: np.ndarray, queries: np.ndarray, cell: float):
    """Index and distance of the nearest of `points` to each query (grid, 5x5 cells)."""
    lo = points.min(0) - 3 * cell
    gp = np.floor((points - lo) / cell).astype(np.int64)
    ny = int(gp[:, 1].max()) + 8
    key = gp[:, 0] * ny + gp[:, 1]
    order = np.argsort(key, kind="stable")
    skey = key[order]
    per = int(np.unique(skey, return_counts=True)[1].max())
    gq = np.floor((queries - lo) / cell).astype(np.int64)
    best = np.full(len(queries), -1)
    bd = np.full(len(queries), np.inf)
    for dx in range(-2, 3):
        for dy in range(-2, 3):
            q = (gq[:, 0] + dx) * ny + gq[:, 1] + dy
            a = np.searchsorted(skey, q, "left")
            b = np.searchsorted(skey, q, "right")
            for k in range(per):
                ok = a + k < b
                j = order[np.minimum(a + k, len(order) - 1)]
                d = np.where(ok, np.linalg.norm(points[j] - queries, axis=1), np.inf)
                better = d < bd
                best = np.where(better, j, best)
                bd = np.where(better, d, bd)
    return best, bd


def stretch_limits(garment: Garment, spans=(3, 9, 27), slack: float = 0.005, seed: int = 0):
    """Multi-scale unilateral stretch limits (NumPy): pairs (i, j) and max distances.

    One Gauss-Seidel sweep per substep moves a correction ~one edge, so under gravity a long
    fine mesh sags (numerically) by ~N^2 g h^2 for N rows. Each vertex therefore also gets,
    per span s (in mean edge lengths), a random partner of its own panel ~s edges away with
    |x_i - x_j| <= (1 + slack) * d_uv: exact geodesics when the UV chord stays inside the
    panel (chords leaving it are dropped), so bending and compression are never resisted.
    """
    rng = np.random.default_rng(seed)
    uv = np.asarray(garment.uvs, np.float64)
    uf = np.asarray(garment.uv_faces).reshape(-1)
    vf = np.asarray(garment.faces).reshape(-1)
    uv2v = np.zeros(len(uv), np.int64)
    uv2v[uf] = vf
    panel = np.zeros(len(uv), np.int64)
    if garment.panels is not None:
        panel[uf] = np.repeat(np.asarray(garment.panels), 3)
    f = np.asarray(garment.uv_faces)
    pd = float(np.mean(np.linalg.norm(uv[f[:, 1]] - uv[f[:, 0]], axis=1)))
    pairs, dists = [], []
    for pid in np.unique(panel):
        ids = np.flatnonzero(panel == pid)
        pts = uv[ids]
        for span in spans:
            ang = rng.uniform(0, 2 * np.pi, len(ids))
            target = pts + span * pd * np.stack([np.cos(ang), np.sin(ang)], 1)
            j, dj = _nearest(pts, target, pd)
            ok = dj < 0.75 * pd
            for frac in (0.25, 0.5, 0.75):  # the chord must stay on the panel
                _, dm = _nearest(pts, pts + frac * (pts[np.maximum(j, 0)] - pts), pd)
                ok &= dm < 0.75 * pd
            a, b = ids[ok], ids[j[ok]]
            d = np.linalg.norm(uv[a] - uv[b], axis=1)
            keep = d > 1.5 * pd
            pairs.append(np.stack([uv2v[a[keep]], uv2v[b[keep]]], 1))
            dists.append(d[keep] * (1 + slack))
    pairs = np.concatenate(pairs) if pairs else np.zeros((0, 2), np.int64)
    dists = np.concatenate(dists) if dists else np.zeros(0)
    return pairs, dists


def build_cloth(garment: Garment, pinned=None, wind: aero.WindField | None = None,
                use_aero: bool = True, attachments: bool = True, seed: int = 0,
                attach_slack: float = 0.01, limit_spans: bool = True) -> ClothModel:
    """Allocate a `ClothModel` for a garment (rest state = its UV pattern, in meters).

    Args:
      garment: welded mesh whose UVs are pattern coordinates in meters.
      pinned: (P,) vertex ids driven by kinematic tracks, or None.
      wind: a WindField, or None for still air.
      use_aero: include aerodynamic drag/lift (still-air drag when `wind` is None).
      attachments: add long-range attachments to the pins (ignored without pins).
      seed: colouring seed.
      attach_slack: relative slack of the attachments over the graph geodesic distance.
      limit_spans: add the multi-scale stretch limits of `stretch_limits`.
    """
    faces = np.asarray(garment.faces, np.int32)
    n = garment.num_vertices
    uv, area = _uv_corner_geometry(garment)
    vertex_area = np.bincount(faces.reshape(-1), np.repeat(area / 3.0, 3), minlength=n)
    # Edges with rest lengths from any face that holds them (UV corners of that face).
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    euv = np.concatenate([uv[:, [0, 1]], uv[:, [1, 2]], uv[:, [2, 0]]])
    ea = np.tile(area / 3.0, 3)
    key = np.minimum(e[:, 0], e[:, 1]).astype(np.int64) * n + np.maximum(e[:, 0], e[:, 1])
    uniq, first, inv = np.unique(key, return_index=True, return_inverse=True)
    edges = np.sort(e[first], axis=1)
    rest = np.linalg.norm(euv[first, 1] - euv[first, 0], axis=1)
    e_area = np.bincount(inv, ea, minlength=len(uniq))
    stretch = tuple(
        StretchColor(to_device(edges[c, 0]), to_device(edges[c, 1]),
                     to_device(rest[c], jnp.float32), to_device(1.0 / e_area[c], jnp.float32))
        for c in color_constraints(edges, n, seed))
    hidx, hw, diag = _hinges(garment, pinned)
    bend = tuple(BendColor(to_device(hidx[c].astype(np.int32)),
                           to_device(hw[c], jnp.float32))
                 for c in color_constraints(hidx, n, seed + 1))
    lp, ld = stretch_limits(garment, seed=seed + 2) if limit_spans else (None, None)
    limits = () if lp is None or not len(lp) else tuple(
        LimitColor(to_device(lp[c, 0].astype(np.int32)), to_device(lp[c, 1].astype(np.int32)),
                   to_device(ld[c], jnp.float32))
        for c in color_constraints(lp, n, seed + 3))
    free = np.ones(n, np.float32)
    pin_idx = attach = None
    if pinned is not None and len(pinned):
        pinned = np.asarray(pinned, np.int32)
        free[pinned] = 0.0
        pin_idx = to_device(pinned)
        if attachments:
            # Graph distances over edges plus across-hinge diagonals (same panel) overestimate
            # geodesics by at most a few percent; attachments stop gross (global) stretching
            # that one Gauss-Seidel sweep per substep converges slowly on.
            ok_d = np.isfinite(diag)
            g_edges = np.concatenate([edges, hidx[ok_d][:, 2:]])
            g_rest = np.concatenate([rest, diag[ok_d]])
            dist, slot = _geodesic_to_pins(garment, pinned, g_edges, g_rest)
            ok = (free > 0) & np.isfinite(dist)
            verts = np.flatnonzero(ok)
            attach = Attachments(to_device(verts.astype(np.int32)),
                                 to_device(slot[verts].astype(np.int32)),
                                 to_device((dist[verts] * (1 + attach_slack)).astype(np.float32)))
    self_topo = selfcollision.self_topology(garment)
    return ClothModel(
        faces=to_device(faces), vertex_area=to_device(vertex_area, jnp.float32),
        free=to_device(free), pin_idx=pin_idx, stretch=stretch, bend=bend, limits=limits,
        attach=attach,
        wind=wind, aero=jnp.zeros(()) if use_aero else None,
        # The same incident-face table as the self-collision topology's: built once.
        vertex_faces=self_topo.vertex_faces if use_aero else None,
        self_topo=self_topo)


def color_groups(sizes, max_waste: float = 0.15) -> list[tuple[int, int]]:
    """Split a colour sequence into the fewest runs of consecutive colours whose padding wastes
    at most `max_waste` of the work (pure Python, on static sizes).

    The solver pads every colour of a run to the run's largest size and scans over the run, so
    its traced program grows with the number of runs, not of colours; the colour order (the
    Gauss-Seidel order) is kept.

    Args:
      sizes: constraint count of each colour, in solver order.
      max_waste: allowed padded work over real work, minus 1 (0 = runs of equal size only).
    Returns:
      [(start, stop), ...] covering range(len(sizes)) in order.
    """
    sizes = [int(s) for s in sizes]
    n = len(sizes)
    if n == 0:
        return []
    budget = (1.0 + max_waste) * sum(sizes)
    # cost[k][j]: least padded work of the first j colours in k runs (dynamic programming
    # over run boundaries; n is a few tens).
    inf = float("inf")
    cost = [[inf] * (n + 1) for _ in range(n + 1)]
    back = [[0] * (n + 1) for _ in range(n + 1)]
    cost[0][0] = 0.0
    for k in range(1, n + 1):
        for j in range(1, n + 1):
            top = 0
            for i in range(j - 1, -1, -1):  # run = colours i .. j-1
                top = max(top, sizes[i])
                c = cost[k - 1][i] + top * (j - i)
                if c < cost[k][j]:
                    cost[k][j], back[k][j] = c, i
        if cost[k][n] <= budget:
            runs, j = [], n
            for kk in range(k, 0, -1):
                runs.append((back[kk][j], j))
                j = back[kk][j]
            return runs[::-1]
    raise AssertionError("unreachable: n runs of one colour waste nothing")


def model_summary(model: ClothModel) -> dict:
    """Sizes of a model: vertices, faces, constraints and colours."""
    return {
        "vertices": int(model.vertex_area.shape[0]),
        "faces": int(model.faces.shape[0]),
        "stretch_constraints": int(sum(c.i.shape[0] for c in model.stretch)),
        "stretch_colors": len(model.stretch),
        "bend_hinges": int(sum(c.idx.shape[0] for c in model.bend)),
        "bend_colors": len(model.bend),
        "limits": int(sum(c.i.shape[0] for c in model.limits)),
        "limit_colors": len(model.limits),
        "pins": 0 if model.pin_idx is None else int(model.pin_idx.shape[0]),
        "attachments": 0 if model.attach is None else int(model.attach.vertex.shape[0]),
        "wind": model.wind is not None,
        "aero": model.aero is not None,
    }
