"""The previous mesh body: a per-cell candidate grid built in NumPy (the reference form).

`bodies.mesh_body` replaced it as the default (see there); this form stays as the reference
the fast one is tested and benchmarked against (`tests/test_bodies_mesh.py`,
`benchmarks/bench_bodies.py`). Query it with `grid_query`, not `bodies.query`.

Method. A uniform grid covers the body's bounding box plus a margin. For every cell we store
a fixed number K of candidate triangles, so a query is a fixed-shape gather: point -> cell ->
K exact point-triangle distances -> the nearest. The candidates of a cell are the triangles t
with d(c, t) <= min_t' d(c, t') + 2 r (c the cell center, r its half-diagonal), which provably
contains the nearest triangle of every point of the cell (they are found in two levels, blocks
of cells first; see `grid_mesh_body`). K is the largest such set over the cells that touch the
surface, so queries there are exact. Inside/outside comes from the angle-weighted pseudo-normal
of the nearest feature, exact for a closed manifold mesh. Cells that do not touch the surface
(d(c) > r) take their sign from a flood fill of the empty cells from the grid border, and, if
their candidate list was cut at K, their distance and nearest point are within 2 r of exact.
Points outside the grid are outside. The build is NumPy once per body pose (about 1 s for a
few hundred triangles, minutes for the 27k-triangle MakeHuman body, where posed cells can need
more than 128 candidates and the build raises `BodyError`); a query costs N * K tests.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from wrinkle_jax.mesh_body import (
    BodyError,
    BodyQuery,
    _closed_mesh_normals,
    _outward_mesh,
    closest_point_on_triangle,
    feature_pseudo_normal,
    signed_answer,
)
from wrinkle_jax.numerics import to_device

_closest_point_jit = jax.jit(closest_point_on_triangle)


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class GridMeshBody:
    """A closed triangle mesh with its query grid (built by `grid_mesh_body`).

    Attributes:
      vertices: (Nv, 3) float32 meters. faces: (T, 3) int32, outward (counter-clockwise).
      face_normals: (T, 3) unit outward normals.
      vertex_normals: (Nv, 3) angle-weighted pseudo-normals.
      edge_normals: (E, 3) pseudo-normals of edges (sum of the two adjacent face normals).
      face_edges: (T, 3) int32, edge id of face edge k (corners k -> k+1).
      origin: (3,) float32 grid corner, meters. cell_size: () float32 meters.
      candidates: (cells, K) int32 candidate triangles per cell (x-major flat cell index).
      cell_far: (cells,) bool, the cell does not touch the surface.
      cell_inside: (cells,) bool, for far cells: inside the body.
      dims: static (nx, ny, nz) cell counts.
    """

    vertices: Any
    faces: Any
    face_normals: Any
    vertex_normals: Any
    edge_normals: Any
    face_edges: Any
    origin: Any
    cell_size: Any
    candidates: Any
    cell_far: Any
    cell_inside: Any
    dims: tuple[int, int, int] = dataclasses.field(metadata=dict(static=True))

    @property
    def max_candidates(self) -> int:
        return int(self.candidates.shape[1])


def grid_query(body: GridMeshBody, points) -> BodyQuery:
    """`bodies.query` for a `GridMeshBody` (jittable)."""
    points = jnp.asarray(points)
    dims = jnp.asarray(body.dims, jnp.int32)
    cell = jnp.floor((points - body.origin) / body.cell_size).astype(jnp.int32)
    outside_grid = jnp.any((cell < 0) | (cell >= dims), axis=-1)
    cell = jnp.clip(cell, 0, dims - 1)
    flat = (cell[:, 0] * body.dims[1] + cell[:, 1]) * body.dims[2] + cell[:, 2]
    cand = body.candidates[flat]  # (N, K)
    tri = body.vertices[body.faces[cand]]  # (N, K, 3, 3)
    p = points[:, None, :]
    cp, region = closest_point_on_triangle(p, tri[..., 0, :], tri[..., 1, :], tri[..., 2, :])
    d2 = jnp.sum((p - cp) ** 2, -1)
    k = jnp.argmin(d2, axis=1)
    rows = jnp.arange(points.shape[0])
    closest, reg, t = cp[rows, k], region[rows, k], cand[rows, k]
    pseudo = feature_pseudo_normal(body.face_normals, body.vertex_normals, body.edge_normals,
                                   body.faces, body.face_edges, t, reg)
    near_inside = jnp.sum((points - closest) * pseudo, -1) < 0
    far = body.cell_far[flat] | outside_grid
    inside = jnp.where(far, body.cell_inside[flat] & ~outside_grid, near_inside)
    return signed_answer(points, closest, pseudo, inside)


def _center_distances(c: np.ndarray, centroid: np.ndarray) -> np.ndarray:
    """|c_i - centroid_j| (n, T) via one matrix product (float64, clamped at 0)."""
    sq = (c * c).sum(1)[:, None] + (centroid * centroid).sum(1)[None] - 2.0 * c @ centroid.T
    return np.sqrt(np.maximum(sq, 0.0))


def grid_mesh_body(vertices, faces, cell_size: float | None = None, max_candidates: int = 16,
              max_cells: int = 1 << 18, block: int = 4, block_candidates: int = 1024,
              chunk: int = 256) -> GridMeshBody:
    """Build a `GridMeshBody` from a closed triangle mesh (NumPy, once per body pose).

    Candidates are found in two levels: blocks of `block`^3 cells keep the (at most
    `block_candidates`) triangles that can be nearest to any point of the block, using
    bounding-sphere bounds; each cell then computes exact distances from its center to its
    block's triangles only. Build cost is O(blocks * T + cells * block_candidates).

    Args:
      vertices: (Nv, 3) meters. faces: (T, 3) int, consistently oriented (either way: a
        mesh with negative signed volume is flipped to face outward).
      cell_size: grid cell edge in meters; default: half the mean edge length (grown by
        1.25x steps until the grid has at most `max_cells` cells).
      max_candidates: minimum K; K grows to the largest candidate set of any cell touching
        the surface (at most 128).
      max_cells, block, block_candidates: grid size bound, block edge in cells, and the
        block-level candidate cap.
      chunk: blocks (8 * chunk cells) processed per vectorized batch (bounds build memory).
    Raises:
      BodyError: the mesh is not closed/manifold, has non-finite coordinates, or a cell near
        the surface needs more candidates than allowed (pass a smaller `cell_size`).
    """
    v, f, p = _outward_mesh(vertices, faces)
    fn, vn, en, fe = _closed_mesh_normals(v, f)
    edge_len = np.linalg.norm(p - np.roll(p, 1, axis=1), axis=2).mean()
    lo, hi = v.min(0), v.max(0)
    extent = hi - lo
    cell_size = 0.5 * float(edge_len) if cell_size is None else float(cell_size)
    if not cell_size > 0:
        raise BodyError(f"cell_size must be positive, got {cell_size}")
    while True:  # grow cells until the grid (body + two-cell margin, whole blocks) fits
        margin = 2.0 * cell_size
        nb = [int(math.ceil(x / (block * cell_size))) for x in extent + 2 * margin]
        dims = tuple(block * n for n in nb)
        if dims[0] * dims[1] * dims[2] <= max_cells:
            break
        cell_size *= 1.25
    origin = lo - margin
    hd = 0.5 * math.sqrt(3.0) * cell_size  # cell half-diagonal
    hd_b = block * hd  # block half-diagonal
    n_tri = len(f)
    centroid = p.mean(1)
    tri_r = np.linalg.norm(p - centroid[:, None], axis=2).max(1) + 1e-9 * (1 + extent.max())
    # Block level: a superset of every cell's candidates (the cell rule's bounds hold for the
    # block center too, with the block's half-diagonal, since every cell lies in its block).
    bi, bj, bk = np.meshgrid(*[np.arange(n) for n in nb], indexing="ij")
    bidx = np.stack([bi, bj, bk], -1).reshape(-1, 3)
    bcenters = origin + (bidx + 0.5) * block * cell_size
    mb = min(n_tri, block_candidates)
    bsets = np.zeros((len(bidx), mb), np.int64)  # sorted by lower bound, best first
    blower = np.zeros((len(bidx), mb))  # their lower bounds (inf: ruled out)
    brest = np.full(len(bidx), np.inf)  # every triangle outside the set has lower >= brest
    for s0 in range(0, len(bidx), chunk):
        dc = _center_distances(bcenters[s0:s0 + chunk], centroid)
        lower = np.maximum(dc - tri_r, 0.0)
        upper_min = (dc + tri_r).min(1)
        lower = np.where(lower <= upper_min[:, None] + 2 * hd_b, lower, np.inf)
        if mb < n_tri:
            part = np.argpartition(lower, mb - 1, axis=1)[:, :mb]
            brest[s0:s0 + chunk] = np.take_along_axis(lower, part, 1).max(1)
        else:
            part = np.broadcast_to(np.arange(n_tri), lower.shape)
        lw = np.take_along_axis(lower, part, 1)
        order = np.argsort(lw, axis=1)
        bsets[s0:s0 + chunk] = np.take_along_axis(part, order, 1)
        blower[s0:s0 + chunk] = np.take_along_axis(lw, order, 1)
    # A block whose every triangle is farther than its half-diagonal has only far cells.
    block_near = blower[:, 0] <= hd_b
    # Cell level: exact distances from each cell center to (the start of) its block's set.
    ci, cj, ck = np.meshgrid(*[np.arange(n) for n in dims], indexing="ij")
    cidx = np.stack([ci, cj, ck], -1).reshape(-1, 3)
    centers = origin + (cidx + 0.5) * cell_size
    cblock = ((cidx[:, 0] // block) * nb[1] + cidx[:, 1] // block) * nb[2] + cidx[:, 2] // block
    k_store = min(128, mb)
    cand = np.zeros((len(cidx), k_store), np.int64)
    filled = np.zeros(len(cidx), np.int64)
    near = np.zeros(len(cidx), bool)
    k_needed, n_bad = 0, 0
    finite = np.isfinite(blower).sum(1)
    for is_near in (True, False):
        cells = np.flatnonzero(block_near[cblock] == is_near)
        if len(cells) == 0:
            continue
        blocks = np.unique(cblock[cells])
        m = int(finite[blocks].max()) if is_near else min(mb, 2 * max_candidates)
        for s0 in range(0, len(cells), chunk * 8):
            sel = cells[s0:s0 + chunk * 8]
            b = cblock[sel]
            c = centers[sel]
            idx = bsets[b, :m]
            # Cell-level bounding-sphere filter, then exact distances to the survivors only
            # (the true nearest triangle always survives: its lower bound <= upper_min).
            dcc = np.linalg.norm(c[:, None, :] - centroid[idx], axis=2)
            lower = np.where(np.isfinite(blower[b, :m]), np.maximum(dcc - tri_r[idx], 0), np.inf)
            upper_min = (dcc + tri_r[idx]).min(1)
            lower = np.where(lower <= upper_min[:, None] + 2 * hd, lower, np.inf)
            keep = np.argsort(lower, axis=1)
            mc = int(np.isfinite(lower).sum(1).max())
            # Powers of two and full-size row batches keep the number of compilations small.
            mc = min(m, max(1 << max(mc - 1, 1).bit_length(), 2 * max_candidates))
            keep = keep[:, :mc]
            idx = np.take_along_axis(idx, keep, 1)
            rows = np.resize(np.arange(len(sel)), chunk * 8)
            cp, _ = _closest_point_jit(c[rows, None, :], p[idx[rows], 0], p[idx[rows], 1],
                                       p[idx[rows], 2])
            d = np.linalg.norm(np.asarray(cp)[:len(sel)] - c[:, None, :], axis=2)
            d = np.where(np.isfinite(np.take_along_axis(lower, keep, 1)), d, np.inf)
            order = np.argsort(d, axis=1)[:, :k_store]
            cand[sel, :order.shape[1]] = np.take_along_axis(idx, order, 1)
            filled[sel] = np.minimum(np.isfinite(d).sum(1), k_store)
            if not is_near:
                continue
            dmin = d.min(1)
            # Lower bound on the distance from anywhere in the cell to an unexamined triangle.
            rest = brest[b] - (hd_b - hd)
            nc = (dmin <= hd) | (rest <= hd)
            count = (d <= dmin[:, None] + 2 * hd).sum(1)
            bad = nc & ((count > k_store) | (rest <= dmin + 2 * hd))
            n_bad += int(bad.sum())
            near[sel] = nc
            if nc.any():
                k_needed = max(k_needed, int(count[nc].max()))
    if n_bad:
        raise BodyError(f"{n_bad} grid cells near the surface need more than {k_store} "
                        f"candidate triangles; pass a smaller cell_size (now {cell_size:.4g} m)")
    k = min(max(max_candidates, k_needed), k_store)
    # Pad short rows by repeating their best candidate (the minimum is unchanged).
    col = np.arange(k)[None, :]
    cand = np.where(col < np.maximum(filled, 1)[:, None], cand[:, :k], cand[:, :1])
    cand = cand.astype(np.int32)
    far = ~near
    inside = _flood_inside(far.reshape(dims))
    # `to_device`: host casts and copies, no one-op compile per array.
    return GridMeshBody(
        **to_device(dict(vertices=v, face_normals=fn, vertex_normals=vn, edge_normals=en,
                         origin=origin, cell_size=cell_size), np.float32),
        faces=to_device(f, np.int32),
        **to_device(dict(face_edges=fe, candidates=cand, cell_far=far,
                         cell_inside=inside.reshape(-1))),
        dims=dims,
    )


def _flood_inside(free: np.ndarray) -> np.ndarray:
    """Cells not reachable from the grid border through free (surface-free) cells.

    Two face-adjacent free cells lie on the same side of the surface (their union is a box
    the surface does not touch), so this labels every free cell exactly.
    """
    outside = np.zeros_like(free)
    for axis in range(3):
        for end in (0, -1):
            sl = [slice(None)] * 3
            sl[axis] = end
            outside[tuple(sl)] = free[tuple(sl)]
    while True:
        grown = outside.copy()
        grown[1:] |= outside[:-1]
        grown[:-1] |= outside[1:]
        grown[:, 1:] |= outside[:, :-1]
        grown[:, :-1] |= outside[:, 1:]
        grown[:, :, 1:] |= outside[:, :, :-1]
        grown[:, :, :-1] |= outside[:, :, 1:]
        grown &= free
        if (grown == outside).all():
            return free & ~outside
        outside = grown
