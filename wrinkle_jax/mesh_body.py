"""Triangle-mesh collision bodies that are rebuilt every pose: signed distance, nearest
surface point and outward normal of a closed triangle mesh (`bodies.query` dispatches here).

Contract:
  * `mesh_template(vertices, faces)` (NumPy, once per topology): checks the mesh is closed
    and manifold, orients it outward, groups its triangles into spatially compact clusters
    of C and sizes a hash grid, at the pose given (the rest pose of a skinned character).
  * `pose_mesh_body(template, vertices)` (jitted, per pose; static shapes, so one compile per
    template): corners, face and angle-weighted pseudo-normals, cluster boxes, and a hash
    table listing each cluster in every grid cell within `band` of its box (one sort of the
    (cell, cluster) pairs, O(P log P)). `mesh_body(vertices, faces)` does both.
  * `query` (via `bodies.query`; jittable) is exact for every point (up to float32
    rounding): distance (N,) signed, negative inside; closest (N, 3); normal (N, 3).

Method. Fast path: a point reads the clusters of its cell's hash slot, tests the triangles of
the k whose boxes are nearest, and is done when the nearest triangle found is within `band`
and no other listed box is nearer (every cluster within `band` of the point is listed, so the
answer is certified exact). Every other point (farther than `band` from the body, or in an
overfull slot, or when the pose's pairs exceeded the table) goes to the exact fallback, in
batches of fixed size: branch and bound over groups of 16 clusters, then their clusters,
nearest box first. Nothing is dropped: capacities only decide how many points take the slower
path (`mesh_query_stats`). Inside/outside comes from the angle-weighted pseudo-normal of the
nearest feature (face, edge or vertex; Baerentzen and Aanaes 2005), exact for a closed
manifold mesh.

Cost (benchmarks/bench_bodies.py, 2 loaded cores, load 7): the 26,756-triangle MakeHuman body
builds in about 50 ms of CPU per pose; a query costs about 40 us of CPU per point, dominated
by the points the fallback answers (the fast path certifies ~40 % of a skirt's points). For a
skinned character: `tpl = mesh_template(rest_vertices, faces)` once, then the pipeline's body
callable `lambda t: pose_mesh_body(tpl, posed_vertices[t])`.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from wrinkle_jax import mesh
from wrinkle_jax.numerics import normalize, positive_div, safe_div, safe_norm, to_device

# Distance (meters) below which a point is treated as lying on the surface: its outward
# direction then comes from the surface normal instead of (point - closest).
_ON_SURFACE = 1e-9


class BodyError(ValueError):
    """Invalid body definition (the message says what is wrong)."""


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class BodyQuery:
    """Result of `query`: signed distance (N,), nearest surface point (N, 3), outward unit
    normal (N, 3); all in meters."""

    distance: Any
    closest: Any
    normal: Any




@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class MeshTemplate:
    """Everything about a mesh body that does not change with its pose (built by
    `mesh_template`, NumPy, once per topology); `pose_mesh_body` turns it and a pose's
    vertices into a `MeshBody`.

    Attributes:
      faces: (T, 3) int32, outward at the template pose. face_edges: (T, 3) int32, edge id of
        face edge k (corners k -> k+1).
      clusters: (Q, C) int32, triangles grouped into spatially compact clusters of C (the
        last one padded by repeating a triangle; the nearest of a repeated set is unchanged).
      cell_size: () float32 meters, edge of the hash-grid cells.
      band: () float32 meters; a cluster is listed in every cell within `band` of its box.
      num_vertices, num_edges: static counts.
      table_size: static, hash slots (a power of two). entry_capacity: static, (cell,
        cluster) pairs kept per pose. cell_capacity: static, clusters read per query cell.
      near_clusters: static, clusters tested per point on the fast path.
      batch: static, points per round of the exact fallback.
    """

    faces: Any
    face_edges: Any
    clusters: Any
    cell_size: Any
    band: Any
    num_vertices: int = dataclasses.field(metadata=dict(static=True))
    num_edges: int = dataclasses.field(metadata=dict(static=True))
    table_size: int = dataclasses.field(metadata=dict(static=True))
    entry_capacity: int = dataclasses.field(metadata=dict(static=True))
    cell_capacity: int = dataclasses.field(metadata=dict(static=True))
    near_clusters: int = dataclasses.field(metadata=dict(static=True))
    batch: int = dataclasses.field(metadata=dict(static=True))


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class MeshBody:
    """A closed triangle mesh in one pose with its query structure (`pose_mesh_body`).

    Attributes:
      template: the `MeshTemplate` (topology, clusters, capacities).
      vertices: (Nv, 3) float32 meters. corners: (T, 3, 3) triangle corners.
      face_normals: (T, 3) unit outward normals.
      vertex_normals: (Nv, 3) angle-weighted pseudo-normals.
      edge_normals: (E, 3) pseudo-normals of edges (sum of the two adjacent face normals).
      cluster_lo, cluster_hi: (Q, 3) bounding boxes of the clusters, meters.
      slot_start, slot_count: (S,) int32, where each hash slot's clusters start in
        `slot_clusters` and how many there are.
      slot_clusters: (entry_capacity,) int32 cluster ids sorted by slot.
      dropped: () int32, (cell, cluster) pairs beyond `entry_capacity` (then every query
        takes the exact fallback; see `query`).
    """

    template: MeshTemplate
    vertices: Any
    corners: Any
    face_normals: Any
    vertex_normals: Any
    edge_normals: Any
    cluster_lo: Any
    cluster_hi: Any
    slot_start: Any
    slot_count: Any
    slot_clusters: Any
    dropped: Any

    @property
    def faces(self):
        return self.template.faces

    @property
    def cell_size(self):
        return self.template.cell_size


def closest_point_on_triangle(p, a, b, c):
    """Nearest point of triangles (a, b, c) to points p (all broadcastable (..., 3)).

    Ericson's Voronoi-region walk ("Real-Time Collision Detection", 5.1.5), vectorized with
    `where`; degenerate triangles fall back to a finite point of the triangle.

    Returns:
      closest (..., 3) and region (...) int32: 0 face interior, 1/2/3 vertex a/b/c,
      4/5/6 edge ab/bc/ca.
    """

    def dot(x, y):
        return jnp.sum(x * y, -1)

    ab, ac, ap = b - a, c - a, p - a
    d1, d2 = dot(ab, ap), dot(ac, ap)
    bp = p - b
    d3, d4 = dot(ab, bp), dot(ac, bp)
    cp = p - c
    d5, d6 = dot(ab, cp), dot(ac, cp)
    vc = d1 * d4 - d3 * d2
    vb = d5 * d2 - d1 * d6
    va = d3 * d6 - d5 * d4
    # Candidate points of every region, then pick by the region tests in priority order.
    s = lambda x: x[..., None]  # noqa: E731
    p_ab = a + s(jnp.clip(positive_div(d1, d1 - d3), 0, 1)) * ab
    p_ac = a + s(jnp.clip(positive_div(d2, d2 - d6), 0, 1)) * ac
    w_bc = jnp.clip(positive_div(d4 - d3, (d4 - d3) + (d5 - d6)), 0, 1)
    p_bc = b + s(w_bc) * (c - b)
    den = va + vb + vc
    p_face = a + s(positive_div(vb, den)) * ab + s(positive_div(vc, den)) * ac
    in_a = (d1 <= 0) & (d2 <= 0)
    in_b = (d3 >= 0) & (d4 <= d3)
    in_ab = (vc <= 0) & (d1 >= 0) & (d3 <= 0)
    in_c = (d6 >= 0) & (d5 <= d6)
    in_ac = (vb <= 0) & (d2 >= 0) & (d6 <= 0)
    in_bc = (va <= 0) & ((d4 - d3) >= 0) & ((d5 - d6) >= 0)
    closest, region = p_face, jnp.zeros(d1.shape, jnp.int32)
    # Later assignments win: apply the tests from the lowest to the highest priority.
    for test, point, code in ((in_bc, p_bc, 5), (in_ac, p_ac, 6), (in_c, c, 3),
                              (in_ab, p_ab, 4), (in_b, b, 2), (in_a, a, 1)):
        closest = jnp.where(s(test), jnp.broadcast_to(point, closest.shape), closest)
        region = jnp.where(test, code, region)
    return closest, region


def _outward_mesh(vertices, faces) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Checked float64 vertices (V, 3), int64 faces (T, 3) wound so the signed volume is
    positive (faces outward), and the (T, 3, 3) triangle corners. Raises BodyError on
    non-finite or malformed input (closedness is checked by `_closed_mesh_normals`)."""
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64)
    if v.ndim != 2 or v.shape[1] != 3 or not np.isfinite(v).all():
        raise BodyError(f"mesh body vertices must be finite (Nv, 3), got {v.shape}")
    if f.ndim != 2 or f.shape[1] != 3 or len(f) == 0 or f.min() < 0 or f.max() >= len(v):
        raise BodyError(f"mesh body faces must be (T, 3) indices into {len(v)} vertices")
    p = v[f]
    if np.sum(p[:, 0] * np.cross(p[:, 1], p[:, 2])) < 0:  # signed volume: face outward
        f = f[:, ::-1].copy()
        p = v[f]
    return v, f, p


def _closed_mesh_normals(v: np.ndarray, f: np.ndarray):
    """Face normals, angle-weighted vertex pseudo-normals, edge pseudo-normals, face edges."""
    p = v[f]
    cr = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    ln = np.linalg.norm(cr, axis=1, keepdims=True)
    fn = np.where(ln > 0, cr / np.where(ln > 0, ln, 1.0), 0.0)
    vn = np.zeros_like(v)
    for k in range(3):
        e1 = p[:, (k + 1) % 3] - p[:, k]
        e2 = p[:, (k + 2) % 3] - p[:, k]
        cosang = np.sum(e1 * e2, 1) / np.maximum(
            np.linalg.norm(e1, axis=1) * np.linalg.norm(e2, axis=1), 1e-300)
        np.add.at(vn, f[:, k], fn * np.arccos(np.clip(cosang, -1.0, 1.0))[:, None])
    he = mesh.face_sides(f)
    edges, inv, counts = mesh.unique_rows(np.sort(he, axis=1), return_inverse=True,
                                          return_counts=True)
    if (counts != 2).any():
        bad = edges[counts != 2][0]
        raise BodyError(
            f"a mesh body must be closed and manifold: {(counts != 2).sum()} edge(s) have "
            f"{sorted(set(counts[counts != 2].tolist()))} faces instead of 2 "
            f"(first: vertices {bad[0]}-{bad[1]})")
    en = np.zeros((len(edges), 3))
    np.add.at(en, inv.reshape(-1), np.repeat(fn, 3, axis=0))
    return fn, vn, en, inv.reshape(-1, 3).astype(np.int32)


# Hash-grid constants: cell coordinates are clipped to +-2^20 cells (a query far outside that
# range lands in a boundary cell, whose candidates then fail the certificate and go to the
# exact fallback), then mixed into table slots.
_CELL_LIMIT = 1 << 20
# A cluster box spanning more cells than this along an axis is not listed at all: the pose
# counts it as dropped and every query takes the exact fallback.
_SPAN_LIMIT = 256


def _slots(cells, table_size: int, xp=jnp):
    """Hash slots (...,) int32 of integer cells (..., 3) (NumPy or JAX, bit-identical)."""
    if xp is np:
        c = np.asarray(cells, np.int32).view(np.uint32)
    else:
        c = jax.lax.bitcast_convert_type(cells.astype(jnp.int32), jnp.uint32)
    u = np.uint32
    h = (c[..., 0] * u(0x8DA6B343)) ^ (c[..., 1] * u(0xD8163841)) ^ (c[..., 2] * u(0xCB1AB31F))
    h = h ^ (h >> u(16))  # mix the high bits into the low ones the mask keeps
    h = h * u(0x7FEB352D)
    h = h ^ (h >> u(15))
    return (h & u(table_size - 1)).astype(xp.int32)


def _cell_of(points, cell_size, xp=jnp):
    c = xp.floor(points / cell_size)
    return xp.clip(c, -_CELL_LIMIT, _CELL_LIMIT).astype(xp.int32)


def _cluster_triangles(centroids: np.ndarray, size: int) -> np.ndarray:
    """(Q, size) triangle ids: median splits along the longest axis down to `size` triangles
    (splits at multiples of `size`, so only the last cluster is short; it is padded by
    repeating its first triangle)."""
    leaves, stack = [], [np.arange(len(centroids))]
    while stack:
        idx = stack.pop()
        if len(idx) <= size:
            leaves.append(idx)
            continue
        pts = centroids[idx]
        axis = int(np.argmax(pts.max(0) - pts.min(0)))
        half = size * int(math.ceil(len(idx) / size / 2))
        order = np.argpartition(pts[:, axis], half - 1)
        stack += [idx[order[half:]], idx[order[:half]]]
    out = np.empty((len(leaves), size), np.int64)
    for i, leaf in enumerate(leaves):
        out[i] = np.concatenate([leaf, np.full(size - len(leaf), leaf[0])])
    return out


def _cell_ranges(lo, hi, cell_size, band, xp=jnp):
    """First cell (Q, 3) int32 and cell counts (Q, 3) of every cluster box grown by `band`."""
    first = _cell_of(lo - band, cell_size, xp)
    span = _cell_of(hi + band, cell_size, xp) - first + 1
    return first, span


def mesh_template(vertices, faces, cell_size: float | None = None, cluster_size: int = 16,
                  band: float | None = None, near_clusters: int = 4, batch: int = 128,
                  slack: float = 1.5, quantile: float = 0.95) -> MeshTemplate:
    """The pose-independent part of a mesh body (NumPy, once per topology).

    Triangles are grouped into clusters of `cluster_size` by median splits of their centroids
    at this pose (skinning moves them together, so clusters stay compact in other poses).
    Capacities (hash slots, (cell, cluster) pairs, clusters per cell) are measured at this
    pose and multiplied by `slack`; a pose that needs more still gets exact answers, through
    the slower fallback (`query`).

    Args:
      vertices: (Nv, 3) meters, any pose (the rest pose for a skinned character).
      faces: (T, 3) int, consistently oriented (either way: a mesh with negative signed
        volume is flipped to face outward).
      cell_size: hash-grid cell edge, meters; default: the median cluster box edge.
      cluster_size: triangles per cluster (C).
      band: meters; points whose nearest triangle is within `band` are answered by the fast
        path; default: `cell_size`.
      near_clusters: clusters tested per point on the fast path (k).
      batch: points per round of the exact fallback.
      slack: capacity factor over what this pose needs.
      quantile: the per-slot cluster count read by the fast path is `slack` times this
        quantile of the pose's non-empty slots.
    Raises:
      BodyError: non-finite or malformed input, or a mesh that is not closed and manifold.
    """
    v, f, p = _outward_mesh(vertices, faces)
    _, _, en, fe = _closed_mesh_normals(v, f)
    clusters = _cluster_triangles(p.mean(1), int(cluster_size))
    cp = p.astype(np.float32)[clusters]
    lo, hi = cp.min(axis=(1, 2)), cp.max(axis=(1, 2))
    h = float(np.median((hi - lo).max(1))) if cell_size is None else float(cell_size)
    h = max(h, 1e-6 * float(np.abs(v).max() + 1.0))  # a single flat triangle has no extent
    band = h if band is None else float(band)
    if not (h > 0 and band >= 0):
        raise BodyError(f"cell_size must be positive and band non-negative, got {h}, {band}")
    first, span = _cell_ranges(lo, hi, np.float32(h), np.float32(band), np)
    count = span.prod(1)
    # The pairs of this pose, to size the table and the per-cell reads.
    q = np.repeat(np.arange(len(clusters)), count)
    local = np.arange(len(q)) - np.repeat(np.cumsum(count) - count, count)
    sp = span[q]
    offs = np.stack([local // (sp[:, 1] * sp[:, 2]), (local // sp[:, 2]) % sp[:, 1],
                     local % sp[:, 2]], 1)
    cells = first[q] + offs
    n_cells = len(mesh.unique_rows(cells))
    table = 1 << max(10, int(math.ceil(math.log2(4 * n_cells))))
    per_slot = np.bincount(_slots(cells, table, np), minlength=table)
    # Read a quantile, not the maximum: a few dense slots (fingers, face) would otherwise set
    # the cost of every query; points in fuller slots take the exact fallback.
    per_slot = np.quantile(per_slot[per_slot > 0], quantile)
    k = int(near_clusters)
    return MeshTemplate(
        **to_device(dict(faces=f, clusters=clusters), np.int32), face_edges=to_device(fe),
        **to_device(dict(cell_size=h, band=band), np.float32), num_vertices=len(v),
        num_edges=len(en),
        table_size=table, entry_capacity=1024 * int(math.ceil(slack * len(q) / 1024)),
        cell_capacity=max(8 * int(math.ceil(slack * per_slot / 8)), 8 * (k // 8 + 1)),
        near_clusters=k, batch=int(batch))


def _saturating_cumsum(x, cap: int):
    return jax.lax.associative_scan(lambda a, b: jnp.minimum(a + b, cap), x)


@jax.jit
def pose_mesh_body(template: MeshTemplate, vertices) -> MeshBody:
    """A template's mesh body in the pose `vertices` (Nv, 3) meters (jitted; O(T log T)).

    Refits the pose-dependent parts: triangle corners, face and pseudo-normals, cluster
    boxes, and the hash table of (cell, cluster) pairs (one sort). Every pose of a template
    has the same shapes, so the build and the queries compile once per template.
    """
    t = template
    v = jnp.asarray(vertices, jnp.float32)
    p = v[t.faces]  # (T, 3, 3)
    fn = normalize(jnp.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]))
    vn = jnp.zeros_like(v)
    for k in range(3):  # angle-weighted vertex pseudo-normals (Baerentzen and Aanaes)
        e1 = p[:, (k + 1) % 3] - p[:, k]
        e2 = p[:, (k + 2) % 3] - p[:, k]
        cos = safe_div(jnp.sum(e1 * e2, -1), safe_norm(e1) * safe_norm(e2))
        vn = vn.at[t.faces[:, k]].add(fn * jnp.arccos(jnp.clip(cos, -1.0, 1.0))[:, None])
    en = jax.ops.segment_sum(jnp.repeat(fn, 3, axis=0), t.face_edges.reshape(-1),
                             num_segments=t.num_edges)
    cp = p[t.clusters]  # (Q, C, 3, 3)
    lo, hi = cp.min(axis=(1, 2)), cp.max(axis=(1, 2))
    first, span = _cell_ranges(lo, hi, t.cell_size, t.band)
    too_wide = jnp.any(span > _SPAN_LIMIT, axis=1)
    span = jnp.where(too_wide[:, None], 0, span)
    count = jnp.prod(span, axis=1)
    cap = t.entry_capacity
    ends = _saturating_cumsum(count, cap + 1)
    # Pair e belongs to the first cluster whose pairs end after e (fixed-size expansion).
    e = jnp.arange(cap, dtype=jnp.int32)
    q = jnp.searchsorted(ends, e, side="right").astype(jnp.int32)
    valid = q < len(count)
    q = jnp.minimum(q, len(count) - 1)
    local = e - (ends[q] - count[q])
    sp = span[q]
    offs = jnp.stack([local // (sp[:, 1] * sp[:, 2]), (local // sp[:, 2]) % sp[:, 1],
                      local % sp[:, 2]], 1)
    slot = jnp.where(valid, _slots(first[q] + offs, t.table_size), t.table_size)
    slot, q = jax.lax.sort((slot, q), num_keys=1)
    per_slot = jnp.zeros(t.table_size + 1, jnp.int32).at[slot].add(1)[:-1]
    total = jnp.sum(count.astype(jnp.float32))
    dropped = jnp.maximum(total - cap, 0.0).astype(jnp.int32)
    dropped = jnp.where(jnp.any(too_wide), jnp.maximum(dropped, 1), dropped)
    return MeshBody(template=t, vertices=v, corners=p, face_normals=fn, vertex_normals=vn,
                    edge_normals=en, cluster_lo=lo, cluster_hi=hi,
                    slot_start=jnp.cumsum(per_slot) - per_slot, slot_count=per_slot,
                    slot_clusters=q, dropped=dropped)


def mesh_body(vertices, faces, **template_kwargs) -> MeshBody:
    """A `MeshBody` from a closed triangle mesh in one pose (`mesh_template` then
    `pose_mesh_body`). For many poses of one mesh, build the template once and call
    `pose_mesh_body(template, vertices)` per pose.

    Args:
      vertices: (Nv, 3) meters. faces: (T, 3) int, consistently oriented (either way).
      **template_kwargs: `mesh_template`'s options (cell_size, cluster_size, band, ...).
    Raises:
      BodyError: the mesh is not closed/manifold or has non-finite coordinates.
    Example:
      >>> import trimesh
      >>> box = trimesh.creation.box(extents=(0.3, 0.2, 0.4))
      >>> body = mesh_body(box.vertices, box.faces)
      >>> round(float(mesh_query(body, jnp.zeros((1, 3))).distance[0]), 6)  # 0.1 m inside
      -0.1
    """
    template = mesh_template(vertices, faces, **template_kwargs)
    return pose_mesh_body(template, np.asarray(vertices, np.float32))


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class _Nearest:
    d2: Any  # (n,) squared distance to the nearest triangle found (inf: none yet)
    closest: Any  # (n, 3)
    region: Any  # (n,) int32, `closest_point_on_triangle`'s region code
    tri: Any  # (n,) int32


def _box_d2(p, lo, hi):
    """Squared distance from points to axis-aligned boxes (broadcast (..., 3))."""
    d = jnp.maximum(jnp.maximum(lo - p, p - hi), 0.0)
    return jnp.sum(d * d, -1)


def _nearest_in(body: MeshBody, points, q, ok) -> _Nearest:
    """Nearest triangle of each point (n, 3) among the clusters q (n, k) where ok (n, k)."""
    n, k = q.shape
    c = body.template.clusters.shape[1]
    tri = body.template.clusters[q].reshape(n, k * c)
    abc = body.corners[tri]  # (n, k C, 3, 3)
    p = points[:, None, :]
    cp, region = closest_point_on_triangle(p, abc[..., 0, :], abc[..., 1, :], abc[..., 2, :])
    d2 = jnp.where(jnp.repeat(ok, c, axis=1), jnp.sum((p - cp) ** 2, -1), jnp.inf)
    j = jnp.argmin(d2, axis=1)
    rows = jnp.arange(n)
    return _Nearest(d2[rows, j], cp[rows, j], region[rows, j], tri[rows, j])


def _smallest(x, k: int):
    """The k smallest values of each row of x (n, m), ascending, and their columns."""
    neg, cols = jax.lax.top_k(-x, k)
    return -neg, cols


def _better(a: _Nearest, b: _Nearest) -> _Nearest:
    take = b.d2 < a.d2
    return jax.tree.map(lambda x, y: jnp.where(take.reshape((-1,) + (1,) * (x.ndim - 1)), y, x),
                        a, b)


# Clusters per group in the fallback's upper level. Median splits emit clusters in depth-first
# order, so consecutive clusters are neighbours and a group of 16 is about one subtree.
_GROUP = 16


def _branch_and_bound(body: MeshBody, points, best: _Nearest) -> _Nearest:
    """Exact nearest triangles of points (m, 3), branch and bound on two levels: groups of
    `_GROUP` clusters in increasing box distance, and inside a group its clusters, k at a
    time, until no untested box is nearer than the best triangle found."""
    n_clusters = body.cluster_lo.shape[0]
    pad = (-n_clusters) % _GROUP
    lo = jnp.pad(body.cluster_lo, ((0, pad), (0, 0)), constant_values=jnp.inf)
    hi = jnp.pad(body.cluster_hi, ((0, pad), (0, 0)), constant_values=-jnp.inf)
    g_lo = lo.reshape(-1, _GROUP, 3).min(1)
    g_hi = hi.reshape(-1, _GROUP, 3).max(1)
    k = min(body.template.near_clusters, _GROUP)
    p = points[:, None]
    rows = jnp.arange(points.shape[0])[:, None]

    def inner(state):
        lb, ids, best = state
        low, j = _smallest(lb, k)
        q = jnp.minimum(jnp.take_along_axis(ids, j, 1), n_clusters - 1)
        best = _better(best, _nearest_in(body, points, q, low < best.d2[:, None]))
        return lb.at[rows, j].set(jnp.inf), ids, best

    def outer(state):
        lb_g, best = state
        _, g = _smallest(lb_g, 1)  # the nearest untested group of each point
        ids = g * _GROUP + jnp.arange(_GROUP)  # (m, _GROUP) cluster ids (padding: inf box)
        lb = _box_d2(p, lo[ids], hi[ids])
        _, _, best = jax.lax.while_loop(lambda s: jnp.any(jnp.min(s[0], 1) < s[2].d2), inner,
                                        (lb, ids, best))
        return lb_g.at[rows, g].set(jnp.inf), best

    lb_g = _box_d2(p, g_lo[None], g_hi[None])
    return jax.lax.while_loop(lambda s: jnp.any(jnp.min(s[0], 1) < s[1].d2), outer,
                              (lb_g, best))[1]


def _fast_path(body: MeshBody, points):
    """Nearest triangles among the point's slot clusters; (best, exact (N,) bool: the
    certificate holds, slot overflow (N,) bool)."""
    t = body.template
    # Fast path: the clusters listed in the point's hash slot, nearest boxes first.
    slot = _slots(_cell_of(points, t.cell_size), t.table_size)
    start, count = body.slot_start[slot], body.slot_count[slot]
    j = jnp.arange(t.cell_capacity)
    ids = body.slot_clusters[jnp.minimum(start[:, None] + j, t.entry_capacity - 1)]
    lb = jnp.where(j < count[:, None],
                   _box_d2(points[:, None], body.cluster_lo[ids], body.cluster_hi[ids]),
                   jnp.inf)
    k = t.near_clusters
    low, pos = _smallest(lb, k + 1)
    best = _nearest_in(body, points, jnp.take_along_axis(ids, pos[:, :k], 1),
                       jnp.isfinite(low[:, :k]))
    # Certificate: every cluster whose box is within `band` of the point is listed in its
    # slot (unless the slot or the table overflowed), so a nearest triangle within `band`
    # that beats the next listed box is the true nearest.
    exact = ((best.d2 <= t.band ** 2) & (low[:, k] >= best.d2) & (count <= t.cell_capacity)
             & (body.dropped == 0))
    return best, exact, count > t.cell_capacity


def mesh_query(body: MeshBody, points) -> BodyQuery:
    """`bodies.query` for a `MeshBody` (points (N, 3) meters; jittable)."""
    t = body.template
    n = points.shape[0]
    best, exact, _ = _fast_path(body, points)
    # Exact fallback for the rest, `batch` points per round (static shapes; no point is
    # ever left unanswered).
    m = min(t.batch, n)

    def round_(state):
        todo, best = state
        idx = jnp.nonzero(todo, size=m, fill_value=n)[0]
        sub = jax.tree.map(lambda x: x[jnp.minimum(idx, n - 1)], best)
        sub = _branch_and_bound(body, points[jnp.minimum(idx, n - 1)], sub)
        best = jax.tree.map(lambda x, y: x.at[idx].set(y, mode="drop"), best, sub)
        return todo.at[idx].set(False, mode="drop"), best

    best = jax.lax.while_loop(lambda s: jnp.any(s[0]), round_, (~exact, best))[1]
    pseudo = feature_pseudo_normal(body.face_normals, body.vertex_normals, body.edge_normals,
                                   t.faces, t.face_edges, best.tri, best.region)
    return signed_answer(points, best.closest, pseudo)


def feature_pseudo_normal(face_normals, vertex_normals, edge_normals, faces, face_edges, tri,
                          region):
    """(N, 3) angle-weighted pseudo-normal of the nearest feature: triangle `tri` (N,)'s face,
    corner or edge by `region` (N,) of `closest_point_on_triangle` (0 face, 1-3 corners,
    4-6 edges). The sign of (p - closest) . pseudo is the inside test (Baerentzen & Aanaes)."""
    corner = jnp.clip(region - 1, 0, 2)
    edge_k = jnp.clip(region - 4, 0, 2)
    return jnp.where(
        (region == 0)[:, None], face_normals[tri],
        jnp.where(((region >= 1) & (region <= 3))[:, None],
                  vertex_normals[faces[tri, corner]],
                  edge_normals[face_edges[tri, edge_k]]))


def signed_answer(points, closest, pseudo, inside=None) -> BodyQuery:
    """The `BodyQuery` of points (N, 3) with nearest surface points `closest` (N, 3) and the
    nearest feature's pseudo-normal (N, 3): inside where (p - closest) . pseudo < 0 unless
    `inside` (N,) bool is given; on the surface the normal is the pseudo-normal."""
    v = points - closest
    dist = safe_norm(v)
    if inside is None:
        inside = jnp.sum(v * pseudo, -1) < 0
    sign = jnp.where(inside, -1.0, 1.0).astype(points.dtype)
    on_surface = (dist <= _ON_SURFACE)[:, None]
    normal = jnp.where(on_surface, normalize(pseudo), normalize(v) * sign[:, None])
    return BodyQuery(sign * dist, closest, normal)


def mesh_query_stats(body: MeshBody, points) -> dict:
    """How `query` answers points (N, 3) on a mesh body (diagnostics; runs the fast path).

    Returns: dict of ints: points answered by the fast path (`fast`), sent to the exact
    fallback (`fallback`), among them because their slot held more than `cell_capacity`
    clusters (`slot_overflow`), and the (cell, cluster) pairs the pose dropped (`dropped`).
    """
    _, exact, over = jax.jit(_fast_path)(body, jnp.asarray(points, jnp.float32))
    return dict(fast=int(exact.sum()), fallback=int((~exact).sum()),
                slot_overflow=int(over.sum()), dropped=int(body.dropped))
