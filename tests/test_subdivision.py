"""Tests for wrinkle_jax.subdivision: midpoint and Loop 1-to-4 splits as sparse operators."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from wrinkle_jax import mesh, primitives, subdivision


def _j(g):
    return jnp.asarray(g.vertices), jnp.asarray(g.faces)


def _edge_lengths(g):
    e = mesh.unique_edges(g.faces)
    return np.linalg.norm(g.vertices[e[:, 1]] - g.vertices[e[:, 0]], axis=1)


@pytest.mark.parametrize("scheme", ["midpoint", "loop"])
def test_subdivision_keeps_plane_planar(scheme):
    g = primitives.grid_sheet(6, 5, jitter=0.3, seed=2)
    rot = np.linalg.qr(np.random.default_rng(0).normal(size=(3, 3)))[0]
    g = g.replace(vertices=(g.vertices @ rot.T + 0.3).astype(np.float32))
    sub = subdivision.build(g, levels=2, scheme=scheme)
    fine = sub.garment(g)
    assert fine.num_faces == 16 * g.num_faces
    mesh.validate_garment(fine)
    normal = rot[:, 2]
    offset = (fine.vertices - 0.3) @ normal
    np.testing.assert_allclose(offset, 0.0, atol=1e-5)


def test_midpoint_subdivision_halves_edges_and_keeps_uv_seams(cube):
    sub = subdivision.build(cube, levels=1)
    fine = sub.garment(cube)
    before, after = _edge_lengths(cube), _edge_lengths(fine)
    np.testing.assert_allclose(after.max(), before.max() / 2, rtol=1e-5)
    np.testing.assert_allclose(after.min(), before.min() / 2, rtol=1e-5)
    np.testing.assert_allclose(after.mean(), before.mean() / 2, rtol=0.05)
    # Still closed in 3D, still 6 UV panels, UVs stay exactly linear (uv scale unchanged).
    assert not mesh.boundary_vertices(fine.faces, fine.num_vertices).any()
    np.testing.assert_array_equal(np.unique(fine.panels), np.arange(6))
    np.testing.assert_allclose(mesh.uv_scale(fine), 1.0, rtol=1e-5)
    # Vertex count: V + E.
    assert fine.num_vertices == cube.num_vertices + len(mesh.unique_edges(cube.faces))


def _max_dihedral(g):
    fn = np.asarray(mesh.face_normals(*_j(g)))
    a, b = mesh.shared_sides(g.faces)  # the two sides of each interior edge
    cos = np.clip((fn[a // 3] * fn[b // 3]).sum(1), -1, 1)
    return np.degrees(np.arccos(cos)).max()


def test_loop_subdivision_is_smoother_than_midpoint():
    cap = primitives.sphere_cap(radius=1.0, max_polar=1.0, n_rings=6, n_segments=12)
    fine_mid = subdivision.build(cap, 2, "midpoint").garment(cap)
    fine_loop = subdivision.build(cap, 2, "loop").garment(cap)
    # Midpoint keeps the original creases; Loop's limit surface is smooth.
    assert _max_dihedral(fine_loop) < 0.5 * _max_dihedral(fine_mid)


def test_loop_weights_regular_vertex():
    g = primitives.grid_sheet(6, 6, alternate=False)  # every interior vertex has valence 6
    sub = subdivision.build(g, 1, "loop")
    dense = sub.vertex_ops[0].todense()
    i = 3 * 7 + 3  # an interior vertex
    row = dense[i]
    np.testing.assert_allclose(row[i], 10 / 16)
    np.testing.assert_allclose(np.sort(row[row > 0])[:-1], np.full(6, 1 / 16))
    # Interior edge vertices: 3/8 for the endpoints, 1/8 for the two opposite vertices.
    odd = dense[g.num_vertices:]
    interior_odd = np.isclose(odd.max(1), 3 / 8)
    assert interior_odd.any()
    np.testing.assert_allclose(np.sort(odd[interior_odd], 1)[:, -4:],
                               np.tile([1 / 8, 1 / 8, 3 / 8, 3 / 8], (interior_odd.sum(), 1)))
    # Boundary edge vertices are plain midpoints.
    assert np.isclose(np.sort(odd[~interior_odd], 1)[:, -2:], 0.5).all()


def test_subdivision_apply_is_jittable_vmappable_and_linear(skirt):
    sub = subdivision.build(skirt, levels=1, scheme="loop")
    frames = jnp.stack([jnp.asarray(skirt.vertices), 2 * jnp.asarray(skirt.vertices)])
    out = jax.jit(jax.vmap(sub.apply))(frames)
    np.testing.assert_allclose(out[1], 2 * out[0], rtol=1e-5, atol=1e-6)
    # The NumPy path used at setup time agrees with the jitted one.
    np.testing.assert_allclose(sub.garment(skirt).vertices, out[0], rtol=1e-5, atol=1e-6)
    # Partition of unity: every row of every operator sums to 1 (affine invariance).
    for op in sub.vertex_ops + sub.uv_ops:
        np.testing.assert_allclose(op.todense().sum(1), 1.0, atol=1e-6)


def test_subdivide_to_edge_length(sheet):
    mean = _edge_lengths(sheet).mean()
    sub = subdivision.to_edge_length(sheet, mean / 3.5)
    assert sub.levels == 2
    assert _edge_lengths(sub.garment(sheet)).mean() <= mean / 3.5 * 1.05
    assert subdivision.to_edge_length(sheet, mean * 2).levels == 0
    with pytest.raises(ValueError):
        subdivision.to_edge_length(sheet, 0.0)
