"""The torch-free parts of benchmarks/bench_reference.py: the inputs it builds for the authors'
lifting loop from our mesh (their cross edges, their adjacency) and the lifting test case.
Anything that needs torch or their code is exercised by running the benchmark, not here."""


import numpy as np
import pytest

from wrinkle_jax import mesh, primitives


def _irregular_mesh():
    """A jittered sheet with alternating diagonals (valences 3 to 8)."""
    g = primitives.grid_sheet(4, 3, size=(0.4, 0.3), jitter=0.2, seed=3)
    return np.asarray(g.faces, np.int64), g.num_vertices


def test_cross_edges_are_each_faces_opposite_edge_once(bench):
    faces, v = _irregular_mesh()
    e0, e1, counts = bench.cross_edges(faces, v)
    assert counts.sum() == e0.size == e1.size == 3 * len(faces)
    assert np.array_equal(counts, np.bincount(faces.reshape(-1), minlength=v))
    owner = np.repeat(np.arange(v), counts)  # their layout: vertex 0's edges first
    got = sorted(tuple(sorted((int(o), int(a), int(b)))) for o, a, b in zip(owner, e0, e1,
                                                                            strict=True))
    want = sorted(tuple(sorted(map(int, f))) for f in faces for _ in range(3))
    assert got == want  # every (owner, edge) is a face, and each face once per corner
    assert np.all(owner != e0) and np.all(owner != e1)


def test_cross_edges_are_perpendicular_to_a_flat_sheets_normal(bench):
    # Their normal term n_p . (q0 - q1) / |q0 - q1| vanishes on a flat mesh with the true
    # normal, and not once one vertex is lifted out of the plane.
    g = primitives.grid_sheet(5, 5, size=(0.5, 0.5))
    faces, verts = np.asarray(g.faces), np.asarray(g.vertices, np.float64)
    e0, e1, _ = bench.cross_edges(faces, g.num_vertices)
    e = verts[e0] - verts[e1]
    assert np.max(np.abs(e[:, 2])) == 0.0
    verts[g.num_vertices // 2, 2] = 0.02
    e = verts[e0] - verts[e1]
    assert np.max(np.abs(e[:, 2])) > 0.01


def test_adjacency_gives_the_uniform_laplacian(bench):
    faces, v = _irregular_mesh()
    adj = bench.adjacency_with_self(faces, v)
    assert np.array_equal(adj, adj.T) and np.all(np.diag(adj) == 1)
    # Their Laplacian: rows of (adjacency without the diagonal) over the degree, minus I;
    # it must be ours (mesh.uniform_laplacian: mean of the one-ring minus the vertex).
    off = adj - np.eye(v, dtype=adj.dtype)
    theirs_style = off / off.sum(1, keepdims=True) - np.eye(v)
    ours = mesh.uniform_laplacian(faces, v)
    np.testing.assert_allclose(theirs_style, ours.todense(), atol=1e-6)


def test_lift_case_targets_are_the_ideal_surfaces_normals(bench):
    case = bench.make_lift_case(20)
    p0, faces, n, ideal = case["p0"], case["faces"], case["normals"], case["ideal"]
    assert p0.shape == n.shape == ideal.shape == (21 * 21, 3)
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-6)
    edges = mesh.unique_edges(faces)
    lengths = np.linalg.norm(p0[edges[:, 0]] - p0[edges[:, 1]], axis=1)
    assert 0.0099 < np.median(lengths) < 0.0106  # 10 mm grid edges (diagonals are longer)
    # The anchors: the first num_coarse fine vertices are the coarse grid's own vertices.
    coarse = primitives.grid_sheet(5, 5, size=(0.2, 0.2), height_fn=primitives.draped_height)
    assert case["num_coarse"] == coarse.num_vertices
    np.testing.assert_allclose(p0[: coarse.num_vertices], coarse.vertices, atol=1e-7)
    # The analytic normals agree with the discrete normals of the ideal mesh (to the
    # discretization error of 10 mm facets over 10 cm wrinkles, a few degrees) and not with
    # the start's: the targets carry the wrinkles.
    def mean_angle(v):
        vn = np.asarray(mesh.vertex_normals(v, faces), np.float64)
        return np.degrees(np.mean(np.arccos(np.clip(np.sum(vn * n, 1), -1, 1))))
    assert mean_angle(ideal) < 1.5
    assert mean_angle(p0) > 4.0
    with pytest.raises(ValueError, match="multiple of 4"):
        bench.make_lift_case(30)
