"""Triangle subdivision as sparse operators: 1-to-4 splits (edge midpoints, or Loop's smooth
weights), precomputed once per topology in NumPy and applied to positions by jittable sparse
products (`mesh.apply`).

    sub = subdivision.build(garment, levels=2)          # or to_edge_length(garment, 0.01)
    fine = sub.garment(garment)                          # the subdivided Garment
    frames_fine = jax.vmap(sub.apply)(frames)            # (T, V, 3) -> (T, V', 3)
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import jax
import numpy as np

from wrinkle_jax.mesh import (
    Garment,
    apply,
    face_sides,
    mean_edge_length_np,
    sparse_operator,
    unique_edges,
    unique_rows,
)


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Subdivision:
    """One or more levels of 1-to-4 triangle subdivision, as sparse operators.

    Positions and UVs are upsampled by jittable sparse products; topology is precomputed.

    Attributes:
      vertex_ops: tuple of SparseOperator, applied in order to (V, ...) per-vertex data.
      uv_ops: tuple of SparseOperator for (T, 2) UVs (always linear: UV layouts stay exact).
      faces, uv_faces: (F', 3) int32 topology after all levels.
      panels: (F',) int32 or None.
    """

    vertex_ops: tuple
    uv_ops: tuple
    faces: Any
    uv_faces: Any
    panels: Any

    @property
    def levels(self) -> int:
        return len(self.vertex_ops)

    def apply(self, vertices):
        """Upsample per-vertex data (V, ...) -> (V', ...) (jittable; vmap for frames)."""
        for op in self.vertex_ops:
            vertices = apply(op, vertices)
        return vertices

    def apply_uv(self, uvs):
        for op in self.uv_ops:
            uvs = apply(op, uvs)
        return uvs

    def garment(self, garment: Garment) -> Garment:
        """The subdivided garment (positions and UVs upsampled in NumPy, topology replaced)."""
        v, uv = np.asarray(garment.vertices, np.float64), np.asarray(garment.uvs, np.float64)
        for op in self.vertex_ops:
            v = op.apply_numpy(v)
        for op in self.uv_ops:
            uv = op.apply_numpy(uv)
        return Garment(vertices=v.astype(np.float32), faces=np.asarray(self.faces),
                       uvs=uv.astype(np.float32), uv_faces=np.asarray(self.uv_faces),
                       panels=self.panels)


def _midpoint_level(faces: np.ndarray, n: int):
    """Edge-midpoint 1-to-4 split of (F,3) over n vertices: new faces, edges, edge id per corner."""
    f = np.asarray(faces, np.int64)
    key = np.sort(face_sides(f), axis=1)  # side 3 i + k: corner k -> k + 1
    edges, inv = unique_rows(key, return_inverse=True)
    mid = n + inv.reshape(-1, 3)  # new vertex id on edge (k, k+1)
    a, b, c = f[:, 0], f[:, 1], f[:, 2]
    ab, bc, ca = mid[:, 0], mid[:, 1], mid[:, 2]
    new_faces = np.stack([
        np.stack([a, ab, ca], 1), np.stack([ab, b, bc], 1),
        np.stack([ca, bc, c], 1), np.stack([ab, bc, ca], 1),
    ], axis=1).reshape(-1, 3)
    return new_faces.astype(np.int32), edges, inv.reshape(-1, 3)


def _linear_operator(faces: np.ndarray, n: int):
    new_faces, edges, _ = _midpoint_level(faces, n)
    ne = len(edges)
    idx = np.arange(n)
    eid = n + np.arange(ne)
    rows = np.r_[idx, eid, eid]
    cols = np.r_[idx, edges[:, 0], edges[:, 1]]
    vals = np.r_[np.ones(n), np.full(ne, 0.5), np.full(ne, 0.5)]
    return sparse_operator(rows, cols, vals, (n + ne, n)), new_faces


def _loop_operator(faces: np.ndarray, n: int):
    """Loop subdivision weights (Loop 1987; boundary and non-manifold edges use the cubic
    B-spline boundary rules, and corner/non-manifold vertices stay fixed)."""
    f = np.asarray(faces, np.int64)
    new_faces, edges, inv = _midpoint_level(f, n)
    ne = len(edges)
    # Opposite vertex of each face edge (k, k+1) is corner k+2.
    opp = f[:, [2, 0, 1]].reshape(-1)
    e_of = inv.reshape(-1)
    count = np.bincount(e_of, minlength=ne)
    interior = count == 2
    rows, cols, vals = [], [], []
    eid = n + np.arange(ne)
    # Odd (edge) vertices.
    w_end = np.where(interior, 3.0 / 8.0, 0.5)
    rows += [eid, eid]
    cols += [edges[:, 0], edges[:, 1]]
    vals += [w_end, w_end]
    sel = interior[e_of]
    rows.append(n + e_of[sel])
    cols.append(opp[sel])
    vals.append(np.full(sel.sum(), 1.0 / 8.0))
    # Even (original) vertices.
    bnd_edges = edges[~interior]
    bdeg = np.bincount(bnd_edges.reshape(-1), minlength=n)
    ue = edges  # the unique sorted edges of f (from the midpoint split), int64
    deg = np.bincount(ue.reshape(-1), minlength=n).astype(np.float64)
    idx = np.arange(n)
    is_bnd = bdeg > 0
    regular_bnd = bdeg == 2
    # Interior vertices: (1 - d beta) p + beta sum(neighbours).
    with np.errstate(divide="ignore", invalid="ignore"):
        beta = (5.0 / 8.0 - (3.0 / 8.0 + 0.25 * np.cos(2 * np.pi / deg)) ** 2) / deg
    beta = np.where(deg > 0, beta, 0.0)
    src = np.r_[ue[:, 0], ue[:, 1]]
    dst = np.r_[ue[:, 1], ue[:, 0]]
    m = ~is_bnd[src]
    rows.append(src[m])
    cols.append(dst[m])
    vals.append(beta[src[m]])
    # Boundary vertices with exactly two boundary edges: 3/4 p + 1/8 (two boundary neighbours).
    bs = np.r_[bnd_edges[:, 0], bnd_edges[:, 1]]
    bd = np.r_[bnd_edges[:, 1], bnd_edges[:, 0]]
    m = regular_bnd[bs]
    rows.append(bs[m])
    cols.append(bd[m])
    vals.append(np.full(m.sum(), 1.0 / 8.0))
    self_w = np.where(is_bnd, np.where(regular_bnd, 0.75, 1.0), 1.0 - deg * beta)
    rows.append(idx)
    cols.append(idx)
    vals.append(self_w)
    return sparse_operator(np.concatenate(rows), np.concatenate(cols), np.concatenate(vals),
                     (n + ne, n)), new_faces


def build(garment: Garment, levels: int = 1, scheme: str = "midpoint") -> Subdivision:
    """Precompute `levels` rounds of 1-to-4 subdivision (NumPy, once per topology).

    Args:
      garment: topology source (faces, uv_faces, panels; positions are not used).
      levels: number of rounds (0 gives identity operators' empty tuple).
      scheme: "midpoint" (linear: the surface is unchanged, edges exactly halve) or "loop"
        (smooth; UVs are still upsampled linearly so the UV layout stays exact).
    """
    if scheme not in ("midpoint", "loop"):
        raise ValueError(f"unknown subdivision scheme {scheme!r}; use 'midpoint' or 'loop'")
    faces = np.asarray(garment.faces)
    uv_faces = np.asarray(garment.uv_faces)
    panels = None if garment.panels is None else np.asarray(garment.panels)
    n, t = garment.num_vertices, int(np.asarray(garment.uvs).shape[0])
    vops, uops = [], []
    for _ in range(levels):
        make = _loop_operator if scheme == "loop" else _linear_operator
        vop, new_faces = make(faces, n)
        uop, new_uv_faces = _linear_operator(uv_faces, t)
        vops.append(vop)
        uops.append(uop)
        faces, uv_faces = new_faces, new_uv_faces
        n, t = vop.shape[0], uop.shape[0]
        if panels is not None:
            panels = np.repeat(panels, 4)
    return Subdivision(tuple(vops), tuple(uops), faces, uv_faces, panels)


def to_edge_length(garment: Garment, target_edge: float, scheme: str = "midpoint",
                   max_levels: int = 6) -> Subdivision:
    """Enough subdivision levels that the mean edge length is at most `target_edge` meters.

    Each level halves edge lengths (exactly for "midpoint"), so the level count is
    ceil(log2(mean_edge / target_edge)), capped at `max_levels`.
    """
    if not target_edge > 0:
        raise ValueError(f"target_edge must be positive, got {target_edge}")
    edges = unique_edges(garment.faces)
    mean = mean_edge_length_np(garment.vertices, edges)
    levels = 0 if mean <= target_edge else math.ceil(math.log2(mean / target_edge))
    return build(garment, min(levels, max_levels), scheme)

