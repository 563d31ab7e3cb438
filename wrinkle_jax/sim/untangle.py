"""Untangling inside the solver: intersection-contour minimisation on the contact candidates.

The vertex-triangle contacts of `selfcollision` keep each vertex on the side of a triangle it
starts a substep on. Once two layers have crossed along a curve (a shin or a ball pressed one
through the other between two rebuilds), that rule holds the crossing in place: every vertex
near the curve is kept on its wrong side. This step reads the crossings from the geometry
alone and shrinks them (Volino & Magnenat-Thalmann 2006, "Resolving surface collisions through
intersection contour minimization"):

  * face pairs: each contact (v, t) of the flat list pairs t with every face incident to v
    (`SelfTopology.vertex_faces`); pairs sharing a vertex are skipped (adjacent faces touch).
    An edge that crosses t has an end within half its length of t, inside the contacts' reach
    (thickness + margin) at the data set's settings, so the crossed pairs are among these
    unless the contact list dropped them (its overflow is counted) or `rest_exclusion` skips
    them (same-panel neighbours in the pattern).
  * per face pair, the length of the segment where the two triangles intersect (Moeller 1997:
    each triangle's edges cut the other's plane in an interval of the planes' common line; the
    segment is the overlap), 0 where they do not; the sum is the contour length (a pair found
    through several contacts counts that many times: a positive weight, same zero set).
  * every free vertex with a non-zero gradient of that sum (a vertex of a crossed face) moves
    `untangle` m against its own gradient direction, the per-vertex normalised step that
    removed the stored episodes' crossings in `experiments.untangle_study` (session 35);
    its contacts, and those of triangles it belongs to, are dropped until the next rebuild, so
    the thickness constraint does not push it back to the side it crossed to.
  * static shapes: the crossed pairs are compacted into a list of at most
    ceil(`untangle_pairs` x V) before the gradient; pairs beyond it are counted (the fourth
    entry of `ClothState.self_overflow`), never dropped silently.

It runs at every candidate rebuild, on the substep's start positions, before the contact frames
are taken; velocities are not changed (a position correction, no impulse). A mesh free of
intersections has no crossed pair, so nothing moves and no contact is dropped.

Shapes: V vertices, F faces, D the largest vertex degree, M contacts. Units: meters.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from wrinkle_jax.numerics import safe_norm


def segment_lengths(x, fa, fb):
    """Length of the intersection segment of each pair of triangles, 0 where they do not cross.

    Args:
      x: (V, 3) positions, m. fa, fb: (N, 3) int vertex ids of the two triangles of each pair
        (they must not share a vertex: two adjacent faces touch along it).
    Returns:
      (N,) m. Touching or coplanar pairs count 0. Differentiable almost everywhere (autodiff
      gives the gradient of the segment's end points, which lie on edges of either triangle).
    """
    # Relative to one corner: positions along the line then keep float32's precision.
    origin = x[fa[:, 0]][:, None]
    a, b = x[fa] - origin, x[fb] - origin                            # (N, 3, 3)
    na = jnp.cross(a[:, 1] - a[:, 0], a[:, 2] - a[:, 0])
    nb = jnp.cross(b[:, 1] - b[:, 0], b[:, 2] - b[:, 0])
    line = jnp.cross(na, nb)                                         # the planes' common line

    def interval(tri, dist):
        # Where the triangle's edges cut the other plane, as positions along `line`.
        nxt = jnp.roll(dist, -1, axis=1)
        cut = dist * nxt < 0
        s = dist / jnp.where(cut, dist - nxt, 1.0)
        pts = tri + s[..., None] * (jnp.roll(tri, -1, axis=1) - tri)
        t = jnp.einsum("nkd,nd->nk", pts, line)
        lo = jnp.min(jnp.where(cut, t, jnp.inf), axis=1)
        hi = jnp.max(jnp.where(cut, t, -jnp.inf), axis=1)
        return lo, hi, jnp.sum(cut, axis=1) == 2

    da = jnp.einsum("nkd,nd->nk", a - b[:, :1], nb)                 # a's corners vs b's plane
    db = jnp.einsum("nkd,nd->nk", b - a[:, :1], na)
    lo_a, hi_a, ok_a = interval(a, da)
    lo_b, hi_b, ok_b = interval(b, db)
    ok = ok_a & ok_b
    # Double where: the untaken branch holds infinities, which must not reach the gradient.
    lo = jnp.where(ok, jnp.maximum(lo_a, lo_b), 0.0)
    hi = jnp.where(ok, jnp.minimum(hi_a, hi_b), 0.0)
    scale = safe_norm(line)                     # 0 for parallel planes: no crossing
    ok = ok & (hi > lo) & (scale > 0)
    return jnp.where(ok, (hi - lo) / jnp.where(ok, scale, 1.0), 0.0)


def face_pairs(vertex, tri, valid, vertex_faces, faces):
    """The face pairs the contacts name: each contact's triangle against every face incident to
    its vertex.

    Args:
      vertex, tri: (M,) int32 contacts (vertex, triangle); valid (M,) bool.
      vertex_faces: (V, D) int32 incident faces padded with F. faces: (F, 3) int32.
    Returns:
      fa, fb (M D,) int32 face ids; ok (M D,) bool (a real contact, a real incident face, no
      shared vertex).
    """
    num_f = faces.shape[0]
    inc = vertex_faces[vertex]                                       # (M, D)
    fb = jnp.broadcast_to(tri[:, None], inc.shape)
    ok = valid[:, None] & (inc < num_f)
    inc = jnp.minimum(inc, num_f - 1)
    share = jnp.any(faces[inc][..., :, None] == faces[fb][..., None, :], axis=(-1, -2))
    return inc.reshape(-1), fb.reshape(-1), (ok & ~share).reshape(-1)


def contour_length(x, faces, fa, fb, ok):
    """Total intersection-segment length (m) over the face pairs (fa, fb) where ok."""
    return jnp.sum(jnp.where(ok, segment_lengths(x, faces[fa], faces[fb]), 0.0))


def max_crossed(num_vertices: int, per_vertex: float) -> int:
    """The static bound on crossed face pairs given the gradient: ceil(per_vertex x V)."""
    return max(int(np.ceil(per_vertex * num_vertices)), 1)


def untangle_contacts(x, free, faces, vertex_faces, vertex, tri, valid, step: float,
                      bound: int):
    """One contour-minimisation step on the contact candidates (see the module docstring).

    The face pairs are first tested (lengths only, no gradient); the crossed ones, at most
    `bound` (in pair order; the others are counted), are moved into a short list whose contour
    length is differentiated: measured on a skirt_dance2 fine frame, 40 k contacts name 0.4 M
    face pairs, of which a few thousand cross, and the gradient over all of them cost as much
    as the candidate rebuild.

    Args:
      x: (V, 3) positions, m. free: (V,) 1 for free vertices, 0 for kinematic (never moved).
      faces: (F, 3) int32; vertex_faces: (V, D) int32 padded with F.
      vertex, tri, valid: the flat contact list (M,) (`selfcollision.Pairs`).
      step: m moved by each vertex of a crossed face. bound: static, see above.
    Returns:
      (x (V, 3) moved, valid (M,) with the contacts of moved vertices and of triangles holding
      one dropped, on_curve (V,) bool: the vertices of crossed faces, lost: int32, crossed
      pairs beyond `bound`).
    """
    fa, fb, ok = face_pairs(vertex, tri, valid, vertex_faces, faces)
    crossed = ok & (segment_lengths(x, faces[fa], faces[fb]) > 0)
    count = jnp.sum(crossed, dtype=jnp.int32)
    (sel,) = jnp.nonzero(crossed, size=bound, fill_value=0)
    use = jnp.arange(bound) < count
    g = jax.grad(contour_length)(x, faces, fa[sel], fb[sel], use)
    norm = safe_norm(g)
    on_curve = norm > 0
    unit = g / jnp.maximum(norm, 1e-30)[:, None]
    move = jnp.where((on_curve & (free > 0))[:, None], unit, 0.0)
    keep = valid & ~on_curve[vertex] & ~jnp.any(on_curve[faces[tri]], axis=-1)
    return x - step * move, keep, on_curve, jnp.maximum(count - bound, 0)
