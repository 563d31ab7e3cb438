"""Tests for wrinkle_jax.mesh: validation, normals, topology, Laplacians."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from wrinkle_jax import mesh, primitives
from wrinkle_jax.mesh import GarmentError


def _j(g):
    return jnp.asarray(g.vertices), jnp.asarray(g.faces)


# ---------------------------------------------------------------- validation


def test_make_garment_rejects_bad_input(sheet):
    v, f, uv, uf = sheet.vertices, sheet.faces, sheet.uvs, sheet.uv_faces
    bad = v.copy()
    bad[3, 1] = np.nan
    with pytest.raises(GarmentError, match="non-finite vertex.*index 3"):
        mesh.make_garment(bad, f, uv, uf, source="x.obj")
    with pytest.raises(GarmentError, match="no UV"):
        mesh.make_garment(v, f, np.zeros((0, 2)), uf, source="x.obj")
    f2 = f.copy()
    f2[0, 0] = len(v)
    with pytest.raises(GarmentError, match="face indices out of range"):
        mesh.make_garment(v, f2, uv, uf)
    uf2 = uf.copy()
    uf2[0, 0] = -1
    with pytest.raises(GarmentError, match="UV face indices out of range"):
        mesh.make_garment(v, f, uv, uf2)
    with pytest.raises(GarmentError, match="uv_faces shape"):
        mesh.make_garment(v, f, uv, uf[:-1])
    with pytest.raises(GarmentError, match="panels"):
        mesh.make_garment(v, f, uv, uf, panels=np.zeros(3))


def test_garment_is_a_pytree(sheet):
    leaves = jax.tree_util.tree_leaves(sheet)
    assert len(leaves) == 4  # panels is None
    doubled = jax.tree_util.tree_map(lambda x: x * 2, sheet)
    np.testing.assert_allclose(doubled.vertices, sheet.vertices * 2)

    @jax.jit
    def centroid(g):
        return jnp.mean(g.vertices, axis=0)

    np.testing.assert_allclose(centroid(sheet), sheet.vertices.mean(0), atol=1e-6)


# ---------------------------------------------------------------- normals


def test_vertex_normals_analytic_sphere():
    # Icosphere-like analytic check: on a sphere cap the area-weighted normal approaches p/|p|.
    cap = primitives.sphere_cap(radius=0.3, max_polar=1.2, n_rings=24, n_segments=72)
    n = np.asarray(mesh.vertex_normals(*_j(cap)))
    exact = cap.vertices / np.linalg.norm(cap.vertices, axis=1, keepdims=True)
    interior = ~mesh.boundary_vertices(cap.faces, cap.num_vertices)
    err = np.degrees(np.arccos(np.clip((n * exact).sum(1), -1, 1)))
    assert err[interior].max() < 0.5
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-6)


def test_face_normals_orientation_and_area(sheet):
    v, f = _j(sheet)
    fn = np.asarray(mesh.face_normals(v, f))
    np.testing.assert_allclose(fn, np.tile([0, 0, 1.0], (len(fn), 1)), atol=1e-6)
    np.testing.assert_allclose(float(mesh.face_areas(v, f).sum()), 0.6 * 0.5, rtol=1e-5)


def test_normals_finite_on_degenerate_faces():
    v = jnp.array([[0, 0, 0], [1, 0, 0], [2, 0, 0], [0, 1, 0], [5, 5, 5.0]])
    f = jnp.array([[0, 1, 2], [0, 1, 3]])  # first face collinear; vertex 4 isolated
    n = mesh.vertex_normals(v, f)
    assert np.isfinite(np.asarray(n)).all()
    np.testing.assert_allclose(n[4], 0.0)
    np.testing.assert_allclose(n[2], 0.0)  # only touches the degenerate face
    g = jax.grad(lambda x: jnp.sum(mesh.vertex_normals(x, f) ** 2)
                 + jnp.sum(mesh.face_areas(x, f)))(v)
    assert np.isfinite(np.asarray(g)).all()


def test_vertex_normals_vmap_equals_loop(sheet):
    # NumPy noise: an op-by-op jax.random draw compiles a threefry program of its shape.
    noise = np.random.default_rng(0).standard_normal((4, sheet.num_vertices, 3))
    frames = jnp.asarray(sheet.vertices + 0.01 * noise, jnp.float32)
    f = jnp.asarray(sheet.faces)
    batched = jax.jit(jax.vmap(mesh.vertex_normals, in_axes=(0, None)))(frames, f)
    for t in range(4):
        np.testing.assert_allclose(batched[t], mesh.vertex_normals(frames[t], f), atol=1e-6)


# ---------------------------------------------------------------- topology


def test_edges_and_rings_on_grid():
    g = primitives.grid_sheet(3, 2)
    e = mesh.unique_edges(g.faces)
    # (nx+1)*ny + nx*(ny+1) axis edges plus one diagonal per cell.
    assert len(e) == 4 * 2 + 3 * 3 + 6
    assert (e[:, 0] < e[:, 1]).all()
    offsets, nbrs = mesh.one_ring_csr(g.faces, g.num_vertices)
    table, valid = mesh.one_ring_padded(g.faces, g.num_vertices)
    assert offsets[-1] == 2 * len(e)
    for i in range(g.num_vertices):
        ring = set(nbrs[offsets[i]:offsets[i + 1]].tolist())
        assert ring == set(table[i][valid[i]].tolist())
        assert ring == {int(b) for a, b in e if a == i} | {int(a) for a, b in e if b == i}
        assert (table[i][~valid[i]] == i).all()
    with pytest.raises(GarmentError, match="max_degree"):
        mesh.one_ring_padded(g.faces, g.num_vertices, max_degree=2)


def test_boundary_vertices(cube, sheet):
    assert not mesh.boundary_vertices(cube.faces, cube.num_vertices).any()  # closed
    b = mesh.boundary_vertices(sheet.faces, sheet.num_vertices).reshape(11, 13)
    assert b[0].all() and b[-1].all() and b[:, 0].all() and b[:, -1].all()
    assert not b[1:-1, 1:-1].any()


def test_uv_scale(skirt, cube):
    np.testing.assert_allclose(mesh.uv_scale(cube), 1.0, rtol=1e-5)
    np.testing.assert_allclose(mesh.uv_scale(skirt), 1.0, rtol=2e-3)
    scaled = skirt.replace(uvs=skirt.uvs * 0.25)  # UVs in quarter-meters -> 4 m per unit
    np.testing.assert_allclose(mesh.global_uv_scale(scaled), 4.0, rtol=2e-3)
    # Panel 2's UV copies shrunk by half: only that panel's scale doubles.
    in_panel2 = np.isin(np.arange(len(cube.uvs)), cube.uv_faces[cube.panels == 2])
    per_panel = cube.replace(uvs=np.where(in_panel2[:, None], 0.5, 1.0) * cube.uvs)
    np.testing.assert_allclose(mesh.uv_scale(per_panel), [1, 1, 2, 1, 1, 1], rtol=1e-5)


# ---------------------------------------------------------------- Laplacians


def test_uniform_laplacian_vanishes_on_linear_field_regular_grid():
    g = primitives.grid_sheet(8, 8, alternate=True)
    op = mesh.uniform_laplacian(g.faces, g.num_vertices)
    field = jnp.asarray(g.vertices @ np.array([[0.3, -1.2, 0.7], [2.0, 0.1, -0.4],
                                               [0.0, 0.0, 0.0]]) + 0.5)
    lap = np.asarray(mesh.apply(op, field))
    interior = ~mesh.boundary_vertices(g.faces, g.num_vertices)
    np.testing.assert_allclose(lap[interior], 0.0, atol=1e-5)
    assert np.abs(lap[~interior]).max() > 1e-2  # boundary rows are not zero: the test has teeth
    # Rows sum to zero: constants are in the kernel everywhere.
    np.testing.assert_allclose(op.todense().sum(1), 0.0, atol=1e-6)


@pytest.mark.parametrize("normalized", [False, True])
def test_cotangent_laplacian_vanishes_on_linear_field_irregular(normalized):
    g = primitives.grid_sheet(10, 9, size=(0.5, 0.4), jitter=0.35, seed=3)
    v = jnp.asarray(g.vertices)
    op = jax.jit(mesh.cotangent_laplacian, static_argnames="normalized")(
        v, jnp.asarray(g.faces), normalized=normalized)
    field = v[:, :2] @ jnp.array([[1.5, -0.2], [0.3, 2.0]]) + 0.1
    lap = np.asarray(mesh.apply(op, field))
    interior = ~mesh.boundary_vertices(g.faces, g.num_vertices)
    scale = 1.0 if not normalized else 1e-3  # normalized rows carry 1/area (~1/m^2)
    np.testing.assert_allclose(lap[interior] * scale, 0.0, atol=1e-4)
    # The uniform Laplacian does NOT vanish on this irregular mesh (so the check is meaningful).
    uni = np.asarray(mesh.apply(mesh.uniform_laplacian(g.faces, g.num_vertices), field))
    assert np.abs(uni[interior]).max() > 1e-3


def test_cotangent_laplacian_matches_dense_reference():
    g = primitives.grid_sheet(4, 3, jitter=0.3, seed=1, height_fn=lambda x, y: 0.1 * x * y)
    v = np.asarray(g.vertices, np.float64)
    dense = np.zeros((g.num_vertices, g.num_vertices))
    for f in g.faces:
        for k in range(3):
            i, j, o = f[(k + 1) % 3], f[(k + 2) % 3], f[k]
            a, b = v[i] - v[o], v[j] - v[o]
            cot = a @ b / np.linalg.norm(np.cross(a, b))
            dense[i, j] += cot / 2
            dense[j, i] += cot / 2
    dense -= np.diag(dense.sum(1))
    op = mesh.cotangent_laplacian(jnp.asarray(g.vertices), jnp.asarray(g.faces))
    np.testing.assert_allclose(op.todense(), dense, atol=1e-4)
    # Symmetric, negative semi-definite.
    np.testing.assert_allclose(op.todense(), op.todense().T, atol=1e-5)
    assert np.linalg.eigvalsh(dense).max() < 1e-8


def test_cotangent_laplacian_finite_on_degenerate_mesh():
    v = jnp.array([[0, 0, 0], [1, 0, 0], [1, 0, 0], [0, 1, 0], [2, 2, 0.0]])  # 1 == 2
    f = jnp.array([[0, 1, 2], [0, 2, 3], [1, 4, 3]])
    op = mesh.cotangent_laplacian(v, f, normalized=True)
    assert np.isfinite(np.asarray(op.values)).all()
    assert np.abs(np.asarray(op.values)).max() <= 10 * mesh.COT_CLIP / 1e-3  # bounded

    def energy(x):
        return jnp.sum(mesh.apply(mesh.cotangent_laplacian(x, f), x) ** 2)

    assert np.isfinite(np.asarray(jax.grad(energy)(v))).all()


def test_shared_sides_pair_the_sides_of_each_interior_edge():
    faces = np.array([[0, 1, 2], [2, 1, 3], [1, 0, 4], [1, 0, 5]])
    sides = mesh.face_sides(faces)
    assert sides[3].tolist() == [2, 1] and sides[5].tolist() == [3, 2]  # side 3 i + k: k -> k+1
    a, b = mesh.shared_sides(faces)
    # Edge (0, 1) is non-manifold (faces 0, 2, 3): consecutive pairs; edge (1, 2): faces 0, 1.
    assert [sorted((int(i), int(j))) for i, j in zip(a, b, strict=True)] == [[0, 6], [6, 9], [1, 3]]
    assert all(sorted(sides[i]) == sorted(sides[j]) for i, j in zip(a, b, strict=True))


@pytest.mark.parametrize("shape,low,high", [((500, 2), 0, 40), ((300, 3), -7, 5), ((50, 1), 0, 3),
                                            ((1, 2), 2, 3), ((64, 2), -2**40, 2**40)])
def test_unique_rows_equals_numpy_row_form(shape, low, high):
    # Negative entries and one-column rows too: the key is shifted and mixed-radix.
    a = np.random.default_rng(shape[0]).integers(low, high, shape)
    for flags in ({}, dict(return_index=True), dict(return_inverse=True),
                  dict(return_counts=True),
                  dict(return_index=True, return_inverse=True, return_counts=True)):
        got, want = mesh.unique_rows(a, **flags), np.unique(a, axis=0, **flags)
        got, want = (got, want) if flags else ((got,), (want,))
        for g, w in zip(got, want, strict=True):
            assert g.dtype == w.dtype
            np.testing.assert_array_equal(g, w)
    # (The +-2^40 case's key would need 82 bits: NumPy's row form answers it, and empty input.)
    assert mesh.unique_rows(np.zeros((0, 2), np.int64)).shape == (0, 2)
    big = np.array([[2**63 + 5, 1], [3, 1], [2**63 + 5, 1]], np.uint64)
    np.testing.assert_array_equal(mesh.unique_rows(big), np.unique(big, axis=0))


def test_row_table_applies_the_sparse_operator():
    """RowTable (gathers) against SparseOperator (scatter-add) and the dense matrix: duplicate
    entries summed, an empty row giving zeros, trailing dimensions, and the gradient."""
    rng = np.random.default_rng(2)
    rows = np.array([0, 0, 2, 2, 2, 3, 0])  # row 1 empty; (0, 4) twice
    cols = np.array([4, 1, 0, 3, 3, 2, 4])
    op = mesh.sparse_operator(rows, cols, rng.normal(size=7), (4, 5))
    table = mesh.row_table(op)
    assert table.shape == (4, 5) and table.cols.shape == (4, 3)
    np.testing.assert_allclose(table.todense(), op.todense(), atol=1e-7)
    x = jnp.asarray(rng.normal(size=(5, 2, 3)), jnp.float32)
    np.testing.assert_allclose(table @ x, mesh.apply(op, x), atol=1e-6)
    assert not np.asarray((table @ x)[1]).any()
    g = jax.grad(lambda x: jnp.sum(jnp.sin(table @ x)))(x)
    want = jax.grad(lambda x: jnp.sum(jnp.sin(mesh.apply(op, x))))(x)
    np.testing.assert_allclose(g, want, atol=1e-6)
