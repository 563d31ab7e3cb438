"""Tests for wrinkle_jax.bodies: analytic and triangle-mesh signed distances."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import trimesh

from wrinkle_jax import bodies
from wrinkle_jax.bodies import BodyError

query = jax.jit(bodies.query)


def _points(n=4000, scale=0.3, seed=0):
    return np.random.default_rng(seed).uniform(-scale, scale, (n, 3)).astype(np.float32)


def _box_sdf(p, half):
    d = np.abs(p) - half
    return np.linalg.norm(np.maximum(d, 0), axis=1) + np.minimum(d.max(1), 0)


def _brute_force_distance(p, v, f):
    tri = jnp.asarray(v[f], jnp.float32)
    cp, _ = bodies.closest_point_on_triangle(jnp.asarray(p)[:, None], tri[:, 0], tri[:, 1],
                                             tri[:, 2])
    return np.linalg.norm(np.asarray(cp) - p[:, None], axis=2).min(1)


@pytest.fixture(scope="module")
def box_body():
    box = trimesh.creation.box(extents=(0.3, 0.2, 0.4))
    return bodies.mesh_body(box.vertices, box.faces)


@pytest.fixture(scope="module")
def ico():
    return trimesh.creation.icosphere(subdivisions=2, radius=0.1)


def test_sphere_and_capsule_are_exact():
    p = _points()
    c, r = np.array([0.05, -0.02, 0.01]), 0.1
    q = query(bodies.primitive_body(spheres=(c, r)), p)
    np.testing.assert_allclose(q.distance, np.linalg.norm(p - c, axis=1) - r, atol=1e-6)
    np.testing.assert_allclose(np.linalg.norm(q.closest - c, axis=1), r, atol=1e-6)
    np.testing.assert_allclose(np.linalg.norm(q.normal, axis=1), 1.0, atol=1e-6)
    a, b, rc = np.array([0.0, 0.0, -0.1]), np.array([0.0, 0.0, 0.1]), 0.05
    q = query(bodies.primitive_body(capsules=(a, b, rc)), p)
    axis_pt = np.stack([np.zeros(len(p)), np.zeros(len(p)), np.clip(p[:, 2], -0.1, 0.1)], 1)
    np.testing.assert_allclose(q.distance, np.linalg.norm(p - axis_pt, axis=1) - rc, atol=1e-6)
    # The closest point lies on the surface, along the outward normal from the point.
    np.testing.assert_allclose(q.closest + q.distance[:, None] * q.normal, p, atol=1e-6)


def test_union_takes_the_nearest_primitive():
    p = _points()
    body = bodies.primitive_body(spheres=([[0.1, 0, 0], [-0.1, 0, 0]], [0.05, 0.08]),
                                 capsules=([0, 0.1, 0], [0, 0.2, 0], 0.03))
    q = query(body, p)
    d1 = np.linalg.norm(p - [0.1, 0, 0], axis=1) - 0.05
    d2 = np.linalg.norm(p - [-0.1, 0, 0], axis=1) - 0.08
    t = np.clip(p[:, 1], 0.1, 0.2)
    d3 = np.linalg.norm(p - np.stack([0 * t, t, 0 * t], 1), axis=1) - 0.03
    np.testing.assert_allclose(q.distance, np.minimum(np.minimum(d1, d2), d3), atol=1e-6)


def test_point_on_capsule_axis_gets_a_finite_direction():
    body = bodies.primitive_body(capsules=([0, 0, 0], [0, 0, 1.0], 0.1), spheres=([2, 0, 0], 0.1))
    q = query(body, np.array([[0, 0, 0.5], [2, 0, 0]], np.float32))
    np.testing.assert_allclose(q.distance, [-0.1, -0.1], atol=1e-6)
    np.testing.assert_allclose(np.linalg.norm(q.normal, axis=1), 1.0, atol=1e-6)
    np.testing.assert_allclose(np.abs(q.normal[0, 2]), 0.0, atol=1e-6)  # perpendicular


def test_mesh_box_matches_analytic_sdf(box_body):
    p = _points(8000)
    q = query(box_body, p)
    sdf = _box_sdf(p, np.array([0.15, 0.1, 0.2]))
    np.testing.assert_allclose(q.distance, sdf, atol=1e-6)
    np.testing.assert_allclose(np.abs(_box_sdf(np.asarray(q.closest), [0.15, 0.1, 0.2])), 0,
                               atol=1e-6)


def test_mesh_sphere_sign_and_near_surface_distance_are_exact(ico):
    body = bodies.mesh_body(ico.vertices, ico.faces)
    p = _points(3000, 0.15, seed=1)
    q = query(body, p)
    exact = _brute_force_distance(p, ico.vertices, ico.faces)
    near = exact < 0.02  # cells touching the surface are exact by construction
    np.testing.assert_allclose(np.abs(q.distance)[near], exact[near], atol=1e-6)
    r = np.linalg.norm(p, axis=1)
    inner_radius = 0.1 * np.cos(np.radians(12))  # safely inside the inscribed polyhedron
    sure = (r < inner_radius - 1e-3) | (r > 0.1 + 1e-3)
    np.testing.assert_array_equal((np.asarray(q.distance) < 0)[sure], (r < 0.1)[sure])
    # Far cells: distances within two cell half-diagonals.
    tol = np.sqrt(3.0) * float(body.cell_size) + 1e-6
    assert np.all(np.abs(np.abs(q.distance) - exact) <= tol)


def test_mesh_orientation_does_not_matter(ico):
    p = _points(500, 0.15)
    a = query(bodies.mesh_body(ico.vertices, ico.faces), p)
    b = query(bodies.mesh_body(ico.vertices, ico.faces[:, ::-1]), p)
    np.testing.assert_allclose(a.distance, b.distance, atol=1e-7)
    np.testing.assert_allclose(a.normal, b.normal, atol=1e-6)


def test_open_mesh_is_rejected(ico):
    with pytest.raises(BodyError, match="closed"):
        bodies.mesh_body(ico.vertices, ico.faces[:-1])
    with pytest.raises(BodyError, match="finite"):
        bodies.mesh_body(np.full((3, 3), np.nan), [[0, 1, 2]])
    with pytest.raises(BodyError, match="positive"):
        bodies.primitive_body(spheres=([0, 0, 0], -1.0))


def test_closest_point_on_triangle_regions_and_degenerate():
    a, b, c = (jnp.array(x, jnp.float32) for x in ([0, 0, 0], [1, 0, 0], [0, 1, 0]))
    pts = jnp.array([[0.2, 0.2, 1], [-1, -1, 0], [2, -0.5, 0], [-0.5, 2, 0], [0.5, -1, 0],
                     [1, 1, 0], [-1, 0.5, 0]], jnp.float32)
    cp, region = bodies.closest_point_on_triangle(pts, a, b, c)
    np.testing.assert_array_equal(region, [0, 1, 2, 3, 4, 5, 6])
    np.testing.assert_allclose(cp[0], [0.2, 0.2, 0], atol=1e-7)
    np.testing.assert_allclose(cp[5], [0.5, 0.5, 0], atol=1e-7)
    # Degenerate (collinear, then point) triangles give finite points and gradients.
    g = jax.grad(lambda p: jnp.sum(bodies.closest_point_on_triangle(p, a, b, b * 2)[0]))(pts)
    assert np.isfinite(g).all()
    cp, _ = bodies.closest_point_on_triangle(pts, a, a, a)
    np.testing.assert_allclose(cp, np.zeros_like(pts), atol=1e-7)
