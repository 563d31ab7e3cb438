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
    unless the contact list dropped them (its overflow is counted). Pairs that
    `rest_exclusion` keeps out of the contacts (one panel, close in the pattern: a fold through
    itself) come from a static list (`SelfTopology.near_faces`, `near_face_pairs`).
  * per face pair, the length of the segment where the two triangles intersect (Moeller 1997:
    each triangle's edges cut the other's plane in an interval of the planes' common line; the
    segment is the overlap), 0 where they do not; the sum is the contour length (a pair found
    through several contacts counts that many times: a positive weight, same zero set).
  * every free vertex with a non-zero gradient of that sum (a vertex of a crossed face) moves
    `untangle` m against its own gradient direction, the per-vertex normalised step that
    removed the stored episodes' crossings in `experiments.untangle_study` (session 35);
    with `untangle_smooth` > 0 the rings around the curve move along (each vertex off the
    curve takes its ring's mean step, once per pass). The contacts that named a crossed pair
    are dropped until the next rebuild, so the thickness constraint does not push the vertex
    back to the side it crossed to.
  * static shapes: the crossed pairs are compacted into a list of at most
    ceil(`untangle_pairs` x V) before the gradient; pairs beyond it are counted (the fourth
    entry of `ClothState.self_overflow`), never dropped silently.

It runs at every candidate rebuild, on the substep's start positions, before the contact frames
are taken; velocities are not changed (a position correction, no impulse). A mesh free of
intersections has no crossed pair, so nothing moves and no contact is dropped.

Measured (session 37, experiments/results/sim/README.md): on stored frames alone it removes a
skirt_dance2 episode (0.88 % of faces -> 0 in 20 steps of 0.5 mm), and in the tests a patch
pushed through a settled sheet; inside the solver on skirt_dance2's episodes it changes little
(peaks 0.68-0.84 % against 0.73 %), because the cloth and the body re-form the crossings as
fast as it removes them. Off by default.

Shapes: V vertices, F faces, D the largest vertex degree, M contacts. Units: meters.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from wrinkle_jax.numerics import safe_norm
from wrinkle_jax.sim import intersect


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


def near_face_pairs(faces, face_uv, face_panel, edges: float = 2.4) -> np.ndarray:
    """Pairs of faces of one panel that share no vertex and whose rest (pattern) centroids lie
    closer than `edges` median rest edge lengths (NumPy, once per mesh).

    These are the pairs the contacts' `rest_exclusion` skips (24 mm at PD 10 mm, 42 mm at PD
    30 mm, both under 2.4 edges), and they cross where a fold passes through itself: on a
    skirt_dance2 fine episode frame (knit_terry, frame 23) 263 of the 364 intersecting pairs
    were of this kind, 14-18 mm apart in the pattern. About 13 pairs per face.

    Args:
      faces: (F, 3) int; face_uv: (F, 3, 2) m; face_panel: (F,) int.
    Returns:
      (P, 2) int32, each pair once (first < second).
    """
    f = np.asarray(faces, np.int64)
    uv = np.asarray(face_uv, np.float64)
    radius = edges * np.median(np.linalg.norm(uv - np.roll(uv, 1, axis=1), axis=-1))
    c = uv.mean(1)
    pairs = intersect.grid_pairs(c, radius)
    pairs = pairs[np.linalg.norm(c[pairs[:, 0]] - c[pairs[:, 1]], axis=1) < radius]
    panel = np.asarray(face_panel)
    pairs = pairs[panel[pairs[:, 0]] == panel[pairs[:, 1]]]
    share = (f[pairs[:, 0]][:, :, None] == f[pairs[:, 1]][:, None, :]).any(axis=(1, 2))
    pairs = pairs[~share]
    return pairs[np.lexsort((pairs[:, 1], pairs[:, 0]))].astype(np.int32).reshape(-1, 2)


def contour_length(x, faces, fa, fb, ok):
    """Total intersection-segment length (m) over the face pairs (fa, fb) where ok."""
    return jnp.sum(jnp.where(ok, segment_lengths(x, faces[fa], faces[fb]), 0.0))


def max_crossed(num_vertices: int, per_vertex: float) -> int:
    """The static bound on crossed face pairs given the gradient: ceil(per_vertex x V)."""
    return max(int(np.ceil(per_vertex * num_vertices)), 1)


def untangle_contacts(x, free, faces, vertex_faces, vertex, tri, valid, step: float,
                      bound: int, near=None, ring=None, smooth: int = 0):
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
      near: optional (P, 2) int32 face pairs tested as well (`near_face_pairs`).
      ring, smooth: (V, D) int32 one-ring padded with the vertex itself; `smooth` passes carry
        the step to the rings around the curve (each vertex off the curve takes the mean of
        its ring's steps), so the cloth around a curve moves with it.
    Returns:
      (x (V, 3) moved, valid (M,) with the contacts that name a crossed pair dropped,
      on_curve (V,) bool: the vertices of crossed faces, lost: int32, crossed
      pairs beyond `bound`).
    """
    fa, fb, ok = face_pairs(vertex, tri, valid, vertex_faces, faces)
    num_contact_pairs = fa.shape[0]
    if near is not None:
        fa = jnp.concatenate([fa, near[:, 0]])
        fb = jnp.concatenate([fb, near[:, 1]])
        ok = jnp.concatenate([ok, jnp.ones(near.shape[0], bool)])
    crossed = ok & (segment_lengths(x, faces[fa], faces[fb]) > 0)
    count = jnp.sum(crossed, dtype=jnp.int32)
    (sel,) = jnp.nonzero(crossed, size=bound, fill_value=0)
    use = jnp.arange(bound) < count
    g = jax.grad(contour_length)(x, faces, fa[sel], fb[sel], use)
    norm = safe_norm(g)
    on_curve = norm > 0
    unit = g / jnp.maximum(norm, 1e-30)[:, None]
    move = jnp.where(on_curve[:, None], unit, 0.0)
    for _ in range(smooth):
        move = jnp.where(on_curve[:, None], move, jnp.mean(move[ring], axis=1))
    move = move * (free > 0)[:, None]
    # Only the contacts that name a crossed pair are dropped: the others of the same vertices
    # and triangles still keep the layers apart where they have not crossed (dropping every
    # contact of a crossed face's vertices let the skirt's layers pass through each other
    # next to the curves: 5.4 % of faces crossed against 0.7 % without the step).
    keep = valid & ~jnp.any(crossed[:num_contact_pairs].reshape(vertex.shape[0], -1), axis=1)
    return x - step * move, keep, on_curve, jnp.maximum(count - bound, 0)
