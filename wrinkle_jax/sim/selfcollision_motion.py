"""When the self-collision candidates must be rebuilt: a bound on the relative motion of
every vertex-triangle pair that can be in contact (`SelfCollisionConfig.rebuild_every = 0`).

Why: a candidate build costs ~150 ms on a fine garment (PD 10 mm, 20 k vertices) and ran
every 4 substeps whatever the motion (session 18: ~70 % of self-collision's added cost). A
build at positions x0 keeps every pair closer than reach = thickness + margin. The distance
of a vertex to a triangle moves by at most max_i |d_v - d_i| when the vertex moves by d_v and
the triangle's corners by d_i (the old closest point's barycentric combination bounds the new
distance, and vice versa), so a pair left out (distance >= reach at x0) cannot come closer
than the thickness while that relative displacement stays below the margin. The Verlet-list
rule (rebuild when the largest displacement exceeds half the margin) bounds it by 2 max |d|,
which on a dancing garment is its absolute speed; this bound is local:

  * a pair closer than the thickness at positions y has all four points within
    thickness + the longest edge of the vertex, so with that as the cell of a grid (folded
    periodically, `_PERIOD` cells per axis), they lie in the 3 x 3 x 3 cells around the
    vertex's cell;
  * per cell the box of the displacements d = y - x0 of the points in it (a scatter-min and
    -max), grown to the 27 cells around it (a separable running min/max), bounds |d_v - d_i|
    by its diagonal; the largest diagonal over the cells bounds every such pair.

Folding merges distant cells and only grows the boxes (never unsafe). Several position sets
(the substep's start and its predicted end) go into one grid: each set's pairs see boxes
that hold at least their own points.

Shapes: N points; F faces. Units: meters.
"""

from __future__ import annotations

import jax.numpy as jnp

_PERIOD = 32  # cells per axis (32 x ~20 mm on a fine garment: wider than the garment)


def motion_bound(ys, ds, faces, thickness: float):
    """The largest relative displacement (m, scalar) of a vertex and a triangle's corners over
    every pair closer than `thickness` at any of the position sets.

    Args: ys, ds: lists of (V, 3) positions and the displacements since the last build at
    them, m; faces (F, 3) int32.
    """
    # The longest edge at ys[0], and at the other sets at most 2 x their largest distance
    # from it longer (one gather of the faces instead of one per set).
    t = ys[0][faces]
    e = t - jnp.roll(t, 1, axis=1)
    edge = jnp.sqrt(jnp.max(jnp.sum(e * e, -1)))
    for y in ys[1:]:
        edge = edge + 2 * jnp.sqrt(jnp.max(jnp.sum((y - ys[0]) ** 2, -1)))
    cell = thickness + edge + 1e-6
    y = jnp.concatenate(ys)
    d = jnp.concatenate(ds)
    m = _PERIOD
    g = jnp.mod(jnp.floor(y / cell).astype(jnp.int32), m)
    b = g[:, 0] + m * (g[:, 1] + m * g[:, 2])
    # Per cell the box's upper corner and the negated lower one in one array, so one running
    # max serves both (the 6 rolls of a (32^3, 6) array: 1.1 ms against 1.9 ms for separate
    # min and max arrays on a 2 k-vertex garment, 2.2 against 3.5 ms at 20 k, measured).
    a = (jnp.full((m ** 3, 6), -jnp.inf, d.dtype).at[b].max(jnp.concatenate([d, -d], 1))
         .reshape(m, m, m, 6))
    for axis in range(3):  # the 27 cells around each: a running max per axis
        a = jnp.maximum(a, jnp.maximum(jnp.roll(a, 1, axis), jnp.roll(a, -1, axis)))
    ext = jnp.maximum(a[..., :3] + a[..., 3:], 0.0)  # hi - lo; empty: -inf -> 0
    return jnp.sqrt(jnp.max(jnp.sum(ext * ext, -1)))
