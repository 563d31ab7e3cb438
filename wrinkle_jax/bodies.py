"""Collision bodies for the interpenetration step: signed distance, nearest surface point and
outward normal of spheres, capsules and closed triangle meshes.

Contract:
  * A body is a frozen pytree: `PrimitiveBody` (a union of spheres and capsules, analytic) or
    `MeshBody` (a closed, consistently oriented triangle mesh in one pose with its query
    structure; `wrinkle_jax.mesh_body`, re-exported here).
  * `query(body, points)` is pure JAX (jittable, vmappable) and returns a `BodyQuery`:

        distance (N,)   float32 meters, signed: negative inside the body
        closest  (N, 3) float32 meters, nearest point on the body surface
        normal   (N, 3) float32 unit outward surface normal at `closest`

  * Mesh bodies: `mesh_template(vertices, faces)` once per topology (NumPy), then
    `pose_mesh_body(template, posed_vertices)` per pose (jitted, static shapes: one compile
    for every pose of a skinned character; `wrinkle_jax.mesh_body`). `mesh_body(vertices,
    faces)` builds one static body: up to `GRID_MAX_TRIANGLES` triangles as a per-cell
    candidate grid (`bodies_grid`, built in NumPy; its queries cost ~1/10 of the clustered
    form's on small bodies, benchmarks/bench_bodies.py), larger ones in the clustered form
    (the grid raised BodyError after 68 s on the 27k-triangle MakeHuman body).
"""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from wrinkle_jax import mesh_body as _clustered
from wrinkle_jax.bodies_grid import GridMeshBody, grid_mesh_body, grid_query
from wrinkle_jax.mesh_body import (  # noqa: F401  (re-exported: the public body API)
    _ON_SURFACE,
    BodyError,
    BodyQuery,
    MeshBody,
    MeshTemplate,
    closest_point_on_triangle,
    mesh_query,
    mesh_query_stats,
    mesh_template,
    pose_mesh_body,
)
from wrinkle_jax.numerics import dot3, norm3, normalize3, safe_div, to_device

__all__ = ["BodyError", "BodyQuery", "Capsules", "GridMeshBody", "MeshBody", "MeshTemplate",
           "PrimitiveBody",
           "Spheres", "closest_point_on_triangle", "mesh_body", "mesh_query_stats",
           "mesh_template", "pose_mesh_body", "primitive_body", "query"]


# --------------------------------------------------------------------------------------------
# Analytic bodies
# --------------------------------------------------------------------------------------------


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Spheres:
    """Spheres: center (S, 3) meters, radius (S,) meters."""

    center: Any
    radius: Any


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Capsules:
    """Capsules (segment start -> end, swept by a ball): start, end (C, 3), radius (C,)."""

    start: Any
    end: Any
    radius: Any


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class PrimitiveBody:
    """The union of some spheres and capsules (either may be None)."""

    spheres: Spheres | None = None
    capsules: Capsules | None = None


def _f32(x, shape_tail, what):
    a = np.asarray(x, np.float32)
    if a.ndim == len(shape_tail):
        a = a[None]
    if a.shape[1:] != shape_tail or not np.isfinite(a).all():
        raise BodyError(f"{what} must be finite with shape (N, {', '.join(map(str, shape_tail))})"
                        f", got {np.asarray(x).shape}")
    return a


def primitive_body(spheres=None, capsules=None) -> PrimitiveBody:
    """A union of spheres and capsules.

    Args:
      spheres: None or (center (S, 3) | (3,), radius (S,) | scalar) in meters.
      capsules: None or (start (C, 3) | (3,), end (C, 3) | (3,), radius (C,) | scalar).
    Example:
      >>> body = primitive_body(spheres=([0.0, 0.0, 0.0], 0.1),
      ...                       capsules=([0, 0, 0.1], [0, 0, 0.5], 0.05))
    """
    sp = cp = None
    if spheres is not None:
        c = _f32(spheres[0], (3,), "sphere centers")
        r = np.broadcast_to(np.asarray(spheres[1], np.float32), (len(c),)).copy()
        if not (r > 0).all():
            raise BodyError("sphere radii must be positive")
        sp = Spheres(*to_device((c, r)))
    if capsules is not None:
        a = _f32(capsules[0], (3,), "capsule starts")
        b = _f32(capsules[1], (3,), "capsule ends")
        if a.shape != b.shape:
            raise BodyError(f"capsule starts {a.shape} and ends {b.shape} differ")
        r = np.broadcast_to(np.asarray(capsules[2], np.float32), (len(a),)).copy()
        if not (r > 0).all():
            raise BodyError("capsule radii must be positive")
        cp = Capsules(*to_device((a, b, r)))
    if sp is None and cp is None:
        raise BodyError("a primitive body needs at least one sphere or capsule")
    return PrimitiveBody(sp, cp)


def _perpendicular(axis):
    """A unit vector perpendicular to each axis (N, ..., 3); +z where the axis is zero."""
    ex = jnp.zeros_like(axis).at[..., 0].set(1.0)
    ey = jnp.zeros_like(axis).at[..., 1].set(1.0)
    ez = jnp.zeros_like(axis).at[..., 2].set(1.0)
    a = normalize3(axis)
    use_y = jnp.abs(a[..., :1]) > 0.9
    perp = normalize3(jnp.cross(a, jnp.where(use_y, ey, ex)))
    zero = dot3(axis, axis)[..., None] <= 0
    return jnp.where(zero, ez, perp)


def _primitive_query(body: PrimitiveBody, points) -> BodyQuery:
    """Each point's nearest ball around a sphere centre or a capsule's nearest axis point; the
    union is the one with the smallest signed distance. The outward direction is computed for
    that one only; a point on a centre or axis gets a direction perpendicular to the axis
    (+z for a sphere)."""
    centers, radii, axes = [], [], []  # per primitive: (N, P, 3) centres, (P,) radii, (P, 3)
    if body.spheres is not None:
        c = body.spheres.center
        centers.append(jnp.broadcast_to(c, (points.shape[0],) + c.shape))
        radii.append(body.spheres.radius)
        axes.append(jnp.zeros_like(c))
    if body.capsules is not None:
        a, b = body.capsules.start, body.capsules.end
        ab = b - a
        t = safe_div(dot3(points[:, None, :] - a, ab), dot3(ab, ab))
        centers.append(a + jnp.clip(t, 0.0, 1.0)[..., None] * ab)  # nearest axis point
        radii.append(body.capsules.radius)
        axes.append(ab)
    center = jnp.concatenate(centers, axis=1)
    radius, axis = jnp.concatenate(radii), jnp.concatenate(axes)
    # The 3-component forms of safe_norm / normalize (see numerics.dot3): several times faster.
    sdf = norm3(points[:, None, :] - center) - radius
    k = jnp.argmin(sdf, axis=1)  # union: the primitive with the smallest signed distance
    c = jnp.take_along_axis(center, k[:, None, None], axis=1)[:, 0]
    v = points - c
    d = norm3(v)  # the picked primitive's distance, by sdf's formula
    on_axis = (d <= _ON_SURFACE)[:, None]
    normal = jnp.where(on_axis, _perpendicular(axis[k]), normalize3(v))
    r = radius[k]
    return BodyQuery(d - r, c + r[:, None] * normal, normal)


# --------------------------------------------------------------------------------------------
# Static mesh bodies
# --------------------------------------------------------------------------------------------

GRID_MAX_TRIANGLES = 8192


def mesh_body(vertices, faces, **options) -> GridMeshBody | MeshBody:
    """A body from a closed triangle mesh in one pose (static: e.g. a `--body` file).

    Args:
      vertices: (Nv, 3) meters. faces: (T, 3) int, consistently oriented (either way).
      **options: the chosen form's options (`bodies_grid.grid_mesh_body` for at most
        `GRID_MAX_TRIANGLES` triangles, else `mesh_body.mesh_template`).
    Raises:
      BodyError: the mesh is not closed/manifold or has non-finite coordinates.
    """
    if len(np.asarray(faces)) <= GRID_MAX_TRIANGLES:
        return grid_mesh_body(vertices, faces, **options)
    return _clustered.mesh_body(vertices, faces, **options)


# --------------------------------------------------------------------------------------------
# Dispatch
# --------------------------------------------------------------------------------------------


def query(body: PrimitiveBody | GridMeshBody | MeshBody, points) -> BodyQuery:
    """Signed distance, nearest surface point and outward normal of a body at points (N, 3).

    Jittable and vmappable; the body type is resolved at trace time, so only the code for
    the body given is compiled.
    """
    points = jnp.asarray(points)
    if isinstance(body, PrimitiveBody):
        return _primitive_query(body, points)
    if isinstance(body, MeshBody):
        return mesh_query(body, points)
    if isinstance(body, GridMeshBody):
        return grid_query(body, points)
    raise BodyError(f"unknown body type {type(body).__name__}; use primitive_body or mesh_body")
