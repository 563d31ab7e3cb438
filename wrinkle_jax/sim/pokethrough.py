"""Poke-through repair for the vertex-triangle self-collision contacts.

The contact of `selfcollision` keeps a vertex on the side of a triangle it starts the substep
on. That is right while the mesh is free of intersections and wrong once a vertex has been
pressed through another layer (a shin or a ball pushing one layer into the next): from then on
the contact holds the vertex on the wrong side, and the crossing persists (measured on the
data set's episodes: 33-62 % of the crossing edges have a vertex poked through its own
one-ring's side).

The repair reads the crossing from the geometry, not from history. For a contact (v, t), count
the edges v-u of v's one-ring that cross the triangle t or one of its (up to three) edge
neighbours (the surface patch around t's closest point). Where more than a fraction `f` of
v's ring edges cross, v is on the other side of that layer than its own neighbourhood: the
contact's direction is turned to the ring's side, so the projection moves v back through the
layer to the thickness on the side its ring lies on. The sides are decided at each candidate
rebuild (`repair_sides`) and kept until the next one: the test reads every ring edge against
four triangles per contact (decided at every substep it cost 1.3-1.4x the fine solver's time).
A mesh free of intersections has no crossing edge, so the repair never changes a contact
there: it only acts where the mesh already intersects.

What it does not undo: two regions crossed along a curve (each vertex keeps most of its ring on
its own side); that needs a global analysis of the intersection curves.

Shapes: V vertices, F faces, D the largest vertex degree, M contacts. Units: meters.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from wrinkle_jax import mesh


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class PokeTopology:
    """ring (V, D) int32, one-ring neighbours (padding repeats the vertex); ring_valid (V, D)
    bool; face_nbr (F, 3) int32, the face across each edge (the face itself on a boundary)."""

    ring: Any
    ring_valid: Any
    face_nbr: Any


def poke_topology(faces, num_vertices: int) -> PokeTopology:
    """One-ring and face-adjacency tables of a mesh (NumPy, once per mesh)."""
    f = np.asarray(faces, np.int64)
    ring, valid = mesh.one_ring_padded(f, num_vertices)
    num_f = len(f)
    nbr = np.repeat(np.arange(num_f), 3)            # default: the face itself
    a, b = mesh.shared_sides(f)                      # sides 3 i + k of face i
    nbr[a], nbr[b] = b // 3, a // 3
    return PokeTopology(jnp.asarray(ring, jnp.int32), jnp.asarray(valid),
                        jnp.asarray(nbr.reshape(num_f, 3), jnp.int32))


def segment_crosses_triangle(p, q, a, b, c):
    """(...) bool: segment p-q crosses triangle a-b-c (all (..., 3) m; Moller-Trumbore, a
    segment in the triangle's plane never crosses)."""
    d = q - p
    e1, e2 = b - a, c - a
    h = jnp.cross(d, e2)
    det = jnp.sum(e1 * h, -1)
    ok = jnp.abs(det) > 1e-18
    inv = 1.0 / jnp.where(ok, det, 1.0)
    s = p - a
    u = inv * jnp.sum(s * h, -1)
    qv = jnp.cross(s, e1)
    v = inv * jnp.sum(d * qv, -1)
    t = inv * jnp.sum(e2 * qv, -1)
    return ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t >= 0) & (t <= 1)


def crossing_fraction(x, faces, topo: PokeTopology, vertex, tri):
    """Per contact, the fraction of the vertex's one-ring edges that cross the contact's
    triangle or its edge neighbours.

    Args: x (V, 3) m; faces (F, 3) int32; vertex (M,) int32; tri (M,) int32.
    Returns: (M,) in [0, 1].
    """
    patch = jnp.concatenate([tri[:, None], topo.face_nbr[tri]], axis=1)      # (M, 4)
    pidx = faces[patch]                                                      # (M, 4, 3)
    corners = x[pidx]                                                        # (M, 4, 3, 3)
    ring = topo.ring[vertex]                                                 # (M, D)
    ok = topo.ring_valid[vertex]
    p = x[vertex][:, None, None]                                             # (M, 1, 1, 3)
    q = x[ring][:, :, None]                                                  # (M, D, 1, 3)
    a, b, c = (corners[:, None, :, i] for i in range(3))                     # (M, 1, 4, 3)
    # An edge that shares a vertex with a patch triangle touches it there: not a crossing.
    shared = (jnp.any(pidx == vertex[:, None, None], -1)[:, None]
              | jnp.any(pidx[:, None] == ring[:, :, None, None], -1))        # (M, D, 4)
    hit = segment_crosses_triangle(p, q, a, b, c) & ~shared
    hit = jnp.any(hit, axis=-1) & ok                                         # (M, D)
    return hit.sum(-1) / jnp.maximum(ok.sum(-1), 1)


def repair_sides(x, faces, topo: PokeTopology, vertex, tri, fraction: float):
    """The side of its triangle each contact's vertex must return to, where it has poked
    through (computed at a candidate rebuild and kept until the next one).

    Args:
      x: (V, 3) positions, m. faces: (F, 3) int32. vertex, tri: (M,) int32, the contacts.
      fraction: a contact is repaired where more than this fraction of its vertex's ring
        edges cross the triangle's patch (in (0, 1)).
    Returns:
      (M,) float32: +1 / -1 where repaired, the side of the triangle's (right-handed) normal
      opposite the vertex, which its crossing ring edges lead to; 0 elsewhere (the contact
      keeps the vertex's start side).
    """
    xt = x[faces[tri]]
    n = jnp.cross(xt[:, 1] - xt[:, 0], xt[:, 2] - xt[:, 0])
    side = jnp.sum((x[vertex] - xt[:, 0]) * n, -1)
    poked = crossing_fraction(x, faces, topo, vertex, tri) > fraction
    return jnp.where(poked, jnp.where(side >= 0, -1.0, 1.0), 0.0).astype(jnp.float32)
