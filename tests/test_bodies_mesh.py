"""Tests for wrinkle_jax.mesh_body: per-pose mesh bodies against brute force and against the
previous grid form (wrinkle_jax.bodies_grid) on a posed, bent torus (a thin limb with a
concave inner side whose two halves nearly touch), including on-surface, near-surface, far
and very far points, and capacity overflows that must fall back, never drop."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import trimesh

from wrinkle_jax import bodies, bodies_grid

_query = jax.jit(bodies.query)
_N = 2048  # every query pads to this many points: one compile per template


def query(body, p):
    p = np.asarray(p, np.float32)
    assert len(p) <= _N
    q = _query(body, np.concatenate([p, np.repeat(p[:1], _N - len(p), 0)]))
    return jax.tree.map(lambda x: np.asarray(x)[:len(p)], q)


def _bend(v, angle=2.4):
    """A smooth skinning-like pose: the x axis is rolled onto a circle (arc length kept), so
    the torus curls up on itself by `angle` radians over its 0.2 m length."""
    r = 0.2 / angle
    x, z = v[:, 0] + 0.1, v[:, 2]
    a = x / r
    return np.stack([r * np.sin(a) - z * np.sin(a) - 0.1, v[:, 1],
                     r * (1 - np.cos(a)) + z * np.cos(a)], 1)


def _brute(p, corners):
    """Exact unsigned distance and nearest point over all triangles (N, 3) -> (N,), (N, 3)."""
    tri = jnp.asarray(corners, jnp.float32)
    cp, _ = bodies.closest_point_on_triangle(jnp.asarray(p)[:, None], tri[:, 0], tri[:, 1],
                                             tri[:, 2])
    cp = np.asarray(cp)
    d = np.linalg.norm(cp - p[:, None], axis=2)
    k = d.argmin(1)
    return d[np.arange(len(p)), k], cp[np.arange(len(p)), k]


@pytest.fixture(scope="module")
def torus():
    t = trimesh.creation.torus(major_radius=0.08, minor_radius=0.015, major_sections=32,
                               minor_sections=12)
    rest = np.asarray(t.vertices, np.float64)
    faces = np.asarray(t.faces)
    posed = _bend(rest).astype(np.float32)
    template = bodies.mesh_template(rest, faces)
    return dict(rest=rest, faces=faces, posed=posed, template=template,
                body=bodies.pose_mesh_body(template, posed))


def _hard_points(v, f, seed=0):
    """Random points around the body plus hard cases: vertices, face centroids and edge
    midpoints (on the surface), points 0.3 mm either side of the surface, far points."""
    rng = np.random.default_rng(seed)
    lo, hi = v.min(0) - 0.05, v.max(0) + 0.05
    box = rng.uniform(lo, hi, (1000, 3))
    tri = v[f]
    cen = tri.mean(1)
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    pick = rng.choice(len(f), 200, replace=False)
    mids = 0.5 * (tri[pick, 0] + tri[pick, 1])
    near = np.concatenate([cen[pick] + 3e-4 * n[pick], cen[pick] - 3e-4 * n[pick]])
    far = rng.normal(size=(40, 3))
    far = 0.5 * far / np.linalg.norm(far, axis=1, keepdims=True)
    pts = np.concatenate([box, v[::7], cen[pick], mids, near, far, [[3.0, -2.0, 40.0]]])
    return pts.astype(np.float32), len(box) + len(v[::7]), len(pick)


def test_posed_body_is_exact_and_agrees_with_the_grid_form(torus):
    v, f = torus["posed"], torus["faces"]
    p, start, n_on = _hard_points(v, f)
    q = query(torus["body"], p)
    d_exact, _ = _brute(p, v[f])
    dist = np.asarray(q.distance)
    np.testing.assert_allclose(np.abs(dist), d_exact, atol=2e-6)
    # On-surface points (vertices, centroids, edge midpoints) are at distance 0.
    on = np.r_[np.arange(len(v[::7])) + 1000, np.arange(start, start + 2 * n_on)]
    np.testing.assert_allclose(dist[on], 0.0, atol=2e-6)
    # The closest point is on the surface and the point lies along the normal from it.
    d_closest, _ = _brute(np.asarray(q.closest), v[f])
    np.testing.assert_allclose(d_closest, 0.0, atol=2e-6)
    np.testing.assert_allclose(np.linalg.norm(q.normal, axis=1), 1.0, atol=1e-5)
    off = d_exact > 1e-4
    np.testing.assert_allclose((q.closest + dist[:, None] * q.normal)[off], p[off], atol=2e-6)
    # The points 0.3 mm inside and outside the faces get the right sign.
    near = np.arange(start + 2 * n_on, start + 4 * n_on)
    np.testing.assert_array_equal(dist[near] < 0, np.r_[np.zeros(n_on, bool),
                                                        np.ones(n_on, bool)])
    # The grid form (exact near the surface, within two cell half-diagonals far from it,
    # sign from a flood fill) agrees: same inside/outside everywhere off the surface.
    grid = bodies_grid.grid_mesh_body(v, f)
    g = jax.jit(bodies_grid.grid_query)(grid, p)
    gd = np.asarray(g.distance)
    tol = np.sqrt(3.0) * float(grid.cell_size) + 1e-6
    lo = np.asarray(grid.origin)
    in_grid = np.all((p >= lo) & (p < lo + np.asarray(grid.dims) * float(grid.cell_size)), 1)
    assert in_grid.sum() > 1000
    assert np.all(np.abs(gd - dist)[in_grid] <= tol)
    np.testing.assert_array_equal((gd < 0)[off], (dist < 0)[off])
    exact_grid = np.abs(np.abs(gd) - d_exact) < 1e-6
    assert exact_grid.mean() > 0.5
    np.testing.assert_allclose(gd[exact_grid & off], dist[exact_grid & off], atol=2e-6)


def test_bent_torus_has_deep_inside_points(torus):
    """Points on the tube's center circle (about 1.5 cm deep) are inside at the exact
    distance."""
    ang = np.linspace(0, 2 * np.pi, 64, endpoint=False)
    ring = np.stack([0.08 * np.cos(ang), 0.08 * np.sin(ang), 0 * ang], 1)
    p = _bend(ring).astype(np.float32)
    d = query(torus["body"], p).distance
    d_exact, _ = _brute(p, torus["posed"][torus["faces"]])
    assert np.all(d_exact > 0.013)
    np.testing.assert_allclose(d, -d_exact, atol=2e-6)


def test_every_pose_shares_one_compile(torus):
    tpl = torus["template"]
    before = bodies.pose_mesh_body._cache_size()
    for angle in (0.5, 1.0, 3.0):
        bodies.pose_mesh_body(tpl, _bend(torus["rest"], angle).astype(np.float32))
    assert bodies.pose_mesh_body._cache_size() - before <= 1


def test_capacity_overflow_falls_back_to_exact(torus):
    """A template sized far too small for the pose drops pairs and overfills slots; every
    point must then take the exact fallback and still get the exact answer."""
    v, f = torus["posed"], torus["faces"]
    tiny = bodies.mesh_template(torus["rest"], f, slack=0.05, quantile=0.1, batch=64)
    body = bodies.pose_mesh_body(tiny, _bend(torus["rest"], 2.4).astype(np.float32) + 10.0)
    p, _, _ = _hard_points(v + 10.0, f, seed=3)
    stats = bodies.mesh_query_stats(body, p)
    assert stats["dropped"] > 0 and stats["fallback"] == len(p)
    d_exact, _ = _brute(p, v[f] + 10.0)
    np.testing.assert_allclose(np.abs(query(body, p).distance), d_exact,
                               atol=4e-6)


def test_moved_pose_and_far_points_stay_exact(torus):
    """The hash grid has no bounds: a pose 50 m away and points 1 km away are exact."""
    v = torus["posed"] + np.float32(50.0)
    body = bodies.pose_mesh_body(torus["template"], v)
    p = np.concatenate([v[:50] + 0.01, [[1000.0, 0.0, 0.0], [50.0, 50.0, -900.0]]])
    p = p.astype(np.float32)
    d_exact, _ = _brute(p, v[torus["faces"]])
    np.testing.assert_allclose(np.abs(query(body, p).distance), d_exact,
                               rtol=1e-6, atol=2e-5)
    assert bodies.mesh_query_stats(body, p)["dropped"] == 0
