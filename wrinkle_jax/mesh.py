"""Garment meshes: the `Garment` pytree, topology helpers and sparse mesh geometry.

A garment is a welded triangle mesh (3D topology `faces`) plus a UV layout whose topology
(`uv_faces`) may split along seams, exactly like OBJ's separate `v` / `vt` indices:

    vertices  (V, 3) float32, meters        faces     (F, 3) int32 into vertices
    uvs       (T, 2) float32, UV units      uv_faces  (F, 3) int32 into uvs
    panels    (F,)   int32 or None (sewing-pattern panel of each face)

Contract of this module:
  * Setup that depends only on topology (edges, one-rings, Laplacian structure) is NumPy,
    computed once, outside `jit`.
  * Geometry that depends on positions (normals, areas, cotangent weights, applying a sparse
    operator) is pure JAX: jittable, vmappable over frames, differentiable, and never builds a
    dense V x V matrix (sparse products are gathers + `segment_sum`).
  * Bad input raises `GarmentError` naming the source and what is wrong.

OBJ and sequence IO live in `wrinkle_jax.meshio`, subdivision in `wrinkle_jax.subdivision`.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from wrinkle_jax.numerics import EPS_SQ, normalize, safe_div, safe_norm, to_device


class GarmentError(ValueError):
    """Invalid garment, OBJ file or sequence (the message names the source and the problem)."""


# --------------------------------------------------------------------------------------------
# The Garment pytree
# --------------------------------------------------------------------------------------------


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Garment:
    """A garment mesh with a (possibly seamed) UV layout. A pytree: every field is a leaf.

    Attributes:
      vertices: (V, 3) float32, meters.
      faces: (F, 3) int32, welded 3D triangles (counter-clockwise seen from the front side).
      uvs: (T, 2) float32, UV coordinates (any unit; see `uv_scale`).
      uv_faces: (F, 3) int32, per-corner UV indices; face f's corner k sits at
        `uvs[uv_faces[f, k]]` and at `vertices[faces[f, k]]`.
      panels: (F,) int32 panel (sewing-pattern piece) id per face, or None.
    """

    vertices: Any
    faces: Any
    uvs: Any
    uv_faces: Any
    panels: Any = None

    @property
    def num_vertices(self) -> int:
        return int(self.vertices.shape[-2])

    @property
    def num_faces(self) -> int:
        return int(self.faces.shape[0])

    def replace(self, **changes) -> Garment:
        """A copy with some fields replaced (e.g. `g.replace(vertices=frame)`)."""
        return dataclasses.replace(self, **changes)


def make_garment(vertices, faces, uvs, uv_faces, panels=None, source: str = "<garment>") -> Garment:
    """Build a validated `Garment` from array-likes (NumPy, float32 / int32).

    Raises:
      GarmentError: naming `source`, on missing UVs, wrong shapes, out-of-range indices or
        non-finite coordinates.
    """
    g = Garment(
        vertices=np.asarray(vertices, dtype=np.float32),
        faces=np.asarray(faces, dtype=np.int32),
        uvs=np.asarray(uvs, dtype=np.float32),
        uv_faces=np.asarray(uv_faces, dtype=np.int32),
        panels=None if panels is None else np.asarray(panels, dtype=np.int32),
    )
    validate_garment(g, source)
    return g


def validate_garment(g: Garment, source: str = "<garment>") -> None:
    """Check shapes, index ranges and finiteness of a garment (NumPy, outside jit).

    Raises:
      GarmentError: the message names `source` and the first problem found.
    """
    v, f = np.asarray(g.vertices), np.asarray(g.faces)
    if v.ndim != 2 or v.shape[1] != 3:
        raise GarmentError(f"{source}: vertices must have shape (V, 3), got {v.shape}")
    if f.ndim != 2 or f.shape[1] != 3:
        raise GarmentError(f"{source}: faces must have shape (F, 3), got {f.shape}")
    if f.shape[0] == 0:
        raise GarmentError(f"{source}: the mesh has no faces")
    if g.uvs is None or g.uv_faces is None or np.asarray(g.uvs).size == 0:
        raise GarmentError(f"{source}: the mesh has no UV coordinates (a UV layout is required)")
    uv, uf = np.asarray(g.uvs), np.asarray(g.uv_faces)
    if uv.ndim != 2 or uv.shape[1] != 2:
        raise GarmentError(f"{source}: uvs must have shape (T, 2), got {uv.shape}")
    if uf.shape != f.shape:
        raise GarmentError(f"{source}: uv_faces shape {uf.shape} differs from faces {f.shape}")
    if f.min() < 0 or f.max() >= v.shape[0]:
        raise GarmentError(
            f"{source}: face indices out of range [0, {v.shape[0]}): min {f.min()}, max {f.max()}"
        )
    if uf.min() < 0 or uf.max() >= uv.shape[0]:
        raise GarmentError(
            f"{source}: UV face indices out of range [0, {uv.shape[0]}): "
            f"min {uf.min()}, max {uf.max()}"
        )
    _check_finite(v, source, "vertex")
    _check_finite(uv, source, "UV")
    if g.panels is not None and np.asarray(g.panels).shape != (f.shape[0],):
        raise GarmentError(
            f"{source}: panels must have shape ({f.shape[0]},), got {np.asarray(g.panels).shape}"
        )


def _check_finite(a: np.ndarray, source: str, what: str) -> None:
    bad = ~np.isfinite(a)
    if bad.any():
        rows = np.unique(np.nonzero(bad)[0 if a.ndim < 3 else 1])
        raise GarmentError(
            f"{source}: {len(rows)} non-finite {what} coordinate(s), first at index {rows[0]}"
        )


# --------------------------------------------------------------------------------------------
# Per-position geometry (JAX: jittable, vmappable, differentiable)
# --------------------------------------------------------------------------------------------
# Jitted where they are defined: called eagerly (set-up code, notebooks, tests) each primitive
# would compile a program of its own (jax 0.10: ~25 ms of CPU each, per shape); jitted they
# compile one program per shape, and inside another jit they are inlined.


@jax.jit
def face_cross(vertices, faces):
    """Unnormalized face normals (e1 x e2): length = 2 * area.

    Args:
      vertices: (V, 3) float, meters.
      faces: (F, 3) int.
    Returns:
      (F, 3) float, square meters.
    """
    p = vertices[faces]
    return jnp.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])


@jax.jit
def face_areas(vertices, faces):
    """Triangle areas (F,) in square meters (0 for degenerate triangles, finite gradients)."""
    return 0.5 * safe_norm(face_cross(vertices, faces))


@jax.jit
def face_normals(vertices, faces):
    """Unit face normals (F, 3) (right-hand rule on corner order; zero for degenerate faces)."""
    return normalize(face_cross(vertices, faces))


@jax.jit
def vertex_normals(vertices, faces):
    """Area-weighted unit vertex normals (V, 3): sum of adjacent face cross products, normalized.

    Isolated vertices and vertices whose faces are all degenerate get a zero normal.
    """
    c = face_cross(vertices, faces)
    acc = jax.ops.segment_sum(jnp.repeat(c, 3, axis=0), faces.reshape(-1),
                              num_segments=vertices.shape[0])
    return normalize(acc)


def uv_scale(garment: Garment) -> np.ndarray:
    """Meters per UV unit, per panel: sqrt(3D area / UV area) of each panel (NumPy).

    Returns:
      (num_panels,) float64, indexed by panel id (one entry when `panels` is None); panels with
      zero UV area get NaN. Faces with a degenerate UV triangle are ignored.
    """
    v = np.asarray(garment.vertices, np.float64)
    f = np.asarray(garment.faces)
    uv = np.asarray(garment.uvs, np.float64)
    uf = np.asarray(garment.uv_faces)
    a3 = 0.5 * np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1)
    e1, e2 = uv[uf[:, 1]] - uv[uf[:, 0]], uv[uf[:, 2]] - uv[uf[:, 0]]
    a2 = 0.5 * np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0])
    panels = np.zeros(len(f), np.int64) if garment.panels is None else np.asarray(garment.panels)
    n = int(panels.max()) + 1
    # Faces whose UV triangle is degenerate have no place in the layout: leave their 3D area
    # out too, or one broken UV triangle would inflate the whole garment's scale.
    a3 = np.where(a2 > 0, a3, 0.0)
    s3 = np.bincount(panels, a3, minlength=n)
    s2 = np.bincount(panels, a2, minlength=n)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(s2 > 0, np.sqrt(s3 / np.where(s2 > 0, s2, 1.0)), np.nan)


def global_uv_scale(garment: Garment) -> float:
    """Meters per UV unit over the whole garment: sqrt(total 3D area / total UV area)."""
    g = garment.replace(panels=None)
    s = float(uv_scale(g)[0])
    if not np.isfinite(s) or s <= 0:
        raise GarmentError("the UV layout has zero area; cannot derive a texel size")
    return s


def mean_edge_length(vertices, edges):
    """Mean length (meters) of the given edges (E, 2)."""
    return jnp.mean(safe_norm(vertices[edges[:, 1]] - vertices[edges[:, 0]]))


def mean_edge_length_np(vertices, edges) -> float:
    """`mean_edge_length` in NumPy float64, for set-up code (compiles nothing); lengths at or
    below sqrt(EPS_SQ) count as 0, as in `safe_norm`."""
    d = np.asarray(vertices, np.float64)
    d = d[edges[:, 1]] - d[edges[:, 0]]
    sq = np.einsum("ij,ij->i", d, d)
    return float(np.mean(np.where(sq > EPS_SQ, np.sqrt(sq), 0.0)))


# --------------------------------------------------------------------------------------------
# Topology (NumPy, once per mesh)
# --------------------------------------------------------------------------------------------


def face_sides(faces) -> np.ndarray:
    """(3F, 2) int64 vertex pairs of the faces' sides: side 3 i + k of face i runs from corner k
    to corner k + 1."""
    f = np.asarray(faces, np.int64)
    return np.stack([f, np.roll(f, -1, axis=1)], -1).reshape(-1, 2)


def unique_rows(rows, return_index: bool = False, return_inverse: bool = False,
                return_counts: bool = False):
    """`np.unique(rows, axis=0, ...)` of an (N, K) integer array through one int64 key per row.

    Same outputs as NumPy's row form (the unique rows in lexicographic order, then, as asked,
    the index of each one's first occurrence, the (N,) inverse and the counts), without its
    structured-record comparison: that is slower, and a KeyboardInterrupt raised inside it
    surfaces as a TypeError. Rows whose mixed-radix key would not fit in 63 bits (and empty,
    uint64 or non-integer input) go to NumPy's row form.
    """
    a = np.asarray(rows)
    flags = dict(return_index=return_index, return_inverse=return_inverse,
                 return_counts=return_counts)
    if (a.ndim != 2 or a.shape[0] == 0 or not np.issubdtype(a.dtype, np.integer)
            or a.dtype == np.uint64):  # (its values need not fit in int64)
        return np.unique(a, axis=0, **flags)
    lo = a.min(0).astype(np.int64)
    span = [int(s) for s in a.max(0).astype(np.int64) - lo + 1]
    if math.prod(span) >= 2**63:
        return np.unique(a, axis=0, **flags)
    key = np.zeros(a.shape[0], np.int64)
    for k, s in enumerate(span):  # column 0 most significant: key order = row order
        key = key * s + (a[:, k].astype(np.int64) - lo[k])
    _, first, *rest = np.unique(key, return_index=True, return_inverse=return_inverse,
                                return_counts=return_counts)
    out = (a[first], *([first] if return_index else []), *rest)
    return out if len(out) > 1 else out[0]


def unique_edges(faces) -> np.ndarray:
    """Unique undirected edges (E, 2) int32, each sorted (i < j), lexicographically ordered."""
    return unique_rows(np.sort(face_sides(faces), axis=1)).astype(np.int32)


def edge_face_counts(faces) -> tuple[np.ndarray, np.ndarray]:
    """Unique edges (E, 2) and how many faces share each (1 = boundary, 2 = interior)."""
    edges, counts = unique_rows(np.sort(face_sides(faces), axis=1), return_counts=True)
    return edges.astype(np.int32), counts


def shared_sides(faces) -> tuple[np.ndarray, np.ndarray]:
    """Face sides (`face_sides` numbering) that lie on one edge. Returns (a, b): (E,) int64
    side indices, the consecutive pairs of sides of each edge in lexicographic order of the
    edge's sorted vertices (one pair per interior edge; a non-manifold edge gives each
    consecutive pair)."""
    key = np.sort(face_sides(faces), axis=1)
    order = np.lexsort((key[:, 1], key[:, 0]))
    k = key[order]
    first = np.nonzero(np.all(k[1:] == k[:-1], axis=1))[0]
    return order[first], order[first + 1]


def boundary_vertices(faces, num_vertices: int) -> np.ndarray:
    """(V,) bool: vertex lies on a boundary (or non-manifold) edge."""
    edges, counts = edge_face_counts(faces)
    out = np.zeros(num_vertices, bool)
    out[edges[counts != 2].reshape(-1)] = True
    return out


def one_ring_csr(faces, num_vertices: int) -> tuple[np.ndarray, np.ndarray]:
    """One-ring neighbours in CSR form.

    Returns:
      offsets (V + 1,) int32 and neighbors (2E,) int32; vertex i's neighbours are
      `neighbors[offsets[i]:offsets[i + 1]]`, sorted ascending.
    """
    e = unique_edges(faces).astype(np.int64)
    src = np.concatenate([e[:, 0], e[:, 1]])
    dst = np.concatenate([e[:, 1], e[:, 0]])
    order = np.lexsort((dst, src))
    src, dst = src[order], dst[order]
    counts = np.bincount(src, minlength=num_vertices)
    offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int32)
    return offsets, dst.astype(np.int32)


def one_ring_padded(faces, num_vertices: int, max_degree: int | None = None):
    """One-ring neighbours as a padded table.

    Args:
      max_degree: table width K; defaults to the largest degree. A vertex with more
        neighbours raises GarmentError (never silently truncated).
    Returns:
      neighbors (V, K) int32 (padding repeats the vertex itself, so gathers stay in range and
      `p[nbr] - p` is 0 there) and valid (V, K) bool.
    """
    offsets, nbrs = one_ring_csr(faces, num_vertices)
    deg = np.diff(offsets)
    k = int(deg.max()) if max_degree is None else int(max_degree)
    if deg.size and deg.max() > k:
        raise GarmentError(f"a vertex has {deg.max()} neighbours, more than max_degree={k}")
    col = np.arange(len(nbrs)) - np.repeat(offsets[:-1], deg)
    row = np.repeat(np.arange(num_vertices), deg)
    table = np.repeat(np.arange(num_vertices, dtype=np.int32)[:, None], max(k, 1), axis=1)
    valid = np.zeros((num_vertices, max(k, 1)), bool)
    table[row, col] = nbrs
    valid[row, col] = True
    return table, valid


# --------------------------------------------------------------------------------------------
# Sparse operators
# --------------------------------------------------------------------------------------------


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class SparseOperator:
    """A sparse (rows x cols) matrix in coordinate form, applied as gather + `segment_sum`.

    Attributes:
      rows, cols: (nnz,) int32 indices.
      values: (nnz,) float32 weights (may depend on positions, e.g. cotangent weights).
      shape: static (n_rows, n_cols).
    """

    rows: Any
    cols: Any
    values: Any
    shape: tuple[int, int] = dataclasses.field(metadata=dict(static=True))

    def __matmul__(self, x):
        return apply(self, x)

    def apply_numpy(self, x) -> np.ndarray:
        """y = A x in NumPy (float64), for setup code outside jit (no compilation)."""
        x = np.asarray(x, np.float64)
        rows, cols = np.asarray(self.rows), np.asarray(self.cols)
        w = np.asarray(self.values, np.float64)
        flat = x.reshape(x.shape[0], -1)
        out = np.stack([np.bincount(rows, w * flat[cols, c], minlength=self.shape[0])
                        for c in range(flat.shape[1])], axis=1)
        return out.reshape((self.shape[0],) + x.shape[1:])

    def todense(self) -> np.ndarray:
        """Dense NumPy copy, for tests and small debugging only."""
        out = np.zeros(self.shape, np.float64)
        np.add.at(out, (np.asarray(self.rows), np.asarray(self.cols)), np.asarray(self.values))
        return out


@jax.jit
def apply(op: SparseOperator, x):
    """y = A x for x (n_cols, ...) -> (n_rows, ...); jittable, vmappable and differentiable."""
    w = op.values.reshape(op.values.shape + (1,) * (x.ndim - 1))
    return jax.ops.segment_sum(w * x[op.cols], op.rows, num_segments=op.shape[0])


def sparse_operator(rows, cols, values, shape) -> SparseOperator:
    """A `SparseOperator` of the (rows, cols, values) triplets (NumPy, int32 / float32)."""
    return SparseOperator(np.asarray(rows, np.int32), np.asarray(cols, np.int32),
                          np.asarray(values, np.float32), (int(shape[0]), int(shape[1])))


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class RowTable:
    """A sparse (rows x cols) matrix as a padded table of each row's entries, applied by
    gathers only: y_i = sum_j values[i, j] x[cols[i, j]] (padding: value 0, column 0).

    For operators applied in inner loops: on CPU `SparseOperator`'s scatter-add runs on one
    thread, several times slower than these gathers (session 43: the push-out's coarse
    correction, ~0.9 ms of scatter-adds per CG iteration at 20k vertices).

    Attributes:
      cols: (n_rows, J) int32 column indices. values: (n_rows, J) float32 weights.
      shape: static (n_rows, n_cols).
    """

    cols: Any
    values: Any
    shape: tuple[int, int] = dataclasses.field(metadata=dict(static=True))

    def __matmul__(self, x):
        return apply_rows(self, x)

    def todense(self) -> np.ndarray:
        """Dense NumPy copy, for tests and small debugging only."""
        out = np.zeros(self.shape, np.float64)
        rows = np.repeat(np.arange(self.shape[0]), np.asarray(self.cols).shape[1])
        np.add.at(out, (rows, np.asarray(self.cols).reshape(-1)),
                  np.asarray(self.values, np.float64).reshape(-1))
        return out


def row_table(op: SparseOperator) -> RowTable:
    """The `RowTable` of a `SparseOperator` (NumPy, once; J = the most entries in a row)."""
    rows, cols = np.asarray(op.rows, np.int64), np.asarray(op.cols, np.int64)
    order = np.argsort(rows, kind="stable")
    rows, cols, vals = rows[order], cols[order], np.asarray(op.values, np.float32)[order]
    counts = np.bincount(rows, minlength=op.shape[0])
    slot = np.arange(rows.size) - np.repeat(np.cumsum(counts) - counts, counts)
    width = max(int(counts.max(initial=0)), 1)
    table = np.zeros((op.shape[0], width), np.int32)
    weights = np.zeros((op.shape[0], width), np.float32)
    table[rows, slot] = cols
    weights[rows, slot] = vals
    return RowTable(*to_device((table, weights)), op.shape)


@jax.jit
def apply_rows(op: RowTable, x):
    """y = A x for x (n_cols, ...) -> (n_rows, ...): J gathers and multiply-adds (no
    reduction: see `lift_energy`'s note on short reductions); jittable, differentiable."""
    tail = (1,) * (x.ndim - 1)
    y = op.values[:, 0].reshape((-1,) + tail) * x[op.cols[:, 0]]
    for j in range(1, op.cols.shape[1]):
        y = y + op.values[:, j].reshape((-1,) + tail) * x[op.cols[:, j]]
    return y


def uniform_laplacian(faces, num_vertices: int) -> SparseOperator:
    """Uniform ("umbrella") Laplacian: (L p)_i = mean_{j in ring(i)} p_j - p_i.

    Exactly zero on affine fields wherever the one-ring is point-symmetric (regular grids).
    Isolated vertices get a zero row.
    """
    e = unique_edges(faces).astype(np.int64)
    src = np.concatenate([e[:, 0], e[:, 1]])
    dst = np.concatenate([e[:, 1], e[:, 0]])
    deg = np.bincount(src, minlength=num_vertices).astype(np.float64)
    w = 1.0 / deg[src]
    diag = np.where(deg > 0, -1.0, 0.0)
    idx = np.arange(num_vertices)
    return sparse_operator(np.r_[src, idx], np.r_[dst, idx], np.r_[w, diag],
                     (num_vertices, num_vertices))


# Cotangents are clipped to this magnitude: a near-degenerate triangle (angle -> 0 or pi) would
# otherwise give unbounded weights that make any solver using the Laplacian ill-conditioned.
COT_CLIP = 1e3


def cotangent_laplacian(vertices, faces, normalized: bool = False) -> SparseOperator:
    """Cotangent Laplacian with position-dependent values (jittable, differentiable).

    (L p)_i = sum_j w_ij (p_j - p_i), w_ij = (cot a_ij + cot b_ij) / 2 over the angles opposite
    edge ij. With `normalized=True` row i is divided by the vertex's barycentric area (a third
    of its faces' areas), giving the Laplace-Beltrami operator in 1/m^2. Zero on affine fields
    at interior vertices of any planar mesh. Degenerate triangles contribute clipped, finite
    weights.

    Args:
      vertices: (V, 3) meters. faces: (F, 3) int (NumPy or JAX).
    Returns:
      SparseOperator (V x V) with 6F off-diagonal entries and V diagonal entries.
    """
    nv = vertices.shape[0]
    p = vertices[faces]  # (F, 3, 3)
    cots = []
    for k in range(3):  # angle at corner k is opposite edge (k+1, k+2)
        a = p[:, (k + 1) % 3] - p[:, k]
        b = p[:, (k + 2) % 3] - p[:, k]
        cot = safe_div(jnp.sum(a * b, -1), safe_norm(jnp.cross(a, b)))
        cots.append(jnp.clip(cot, -COT_CLIP, COT_CLIP))
    cot = jnp.stack(cots, axis=1)  # (F, 3)
    i = jnp.stack([faces[:, 1], faces[:, 2], faces[:, 0]], axis=1)  # edge opposite corner k
    j = jnp.stack([faces[:, 2], faces[:, 0], faces[:, 1]], axis=1)
    w = 0.5 * cot.reshape(-1)
    i, j = i.reshape(-1), j.reshape(-1)
    rows = jnp.concatenate([i, j])
    cols = jnp.concatenate([j, i])
    off = jnp.concatenate([w, w])
    diag = -jax.ops.segment_sum(off, rows, num_segments=nv)
    vals = jnp.concatenate([off, diag])
    rows = jnp.concatenate([rows, jnp.arange(nv)])
    cols = jnp.concatenate([cols, jnp.arange(nv)])
    if normalized:
        area = jax.ops.segment_sum(jnp.repeat(face_areas(vertices, faces) / 3.0, 3),
                                   faces.reshape(-1), num_segments=nv)
        vals = safe_div(vals, area[rows])
    return SparseOperator(rows.astype(jnp.int32), cols.astype(jnp.int32),
                          vals.astype(vertices.dtype), (nv, nv))
