"""wrinkle_jax.reference, the torch-free side of benchmarks/bench_reference.py: the inputs it
builds for the authors' lifting loop from our mesh (their cross edges, their adjacency, their
text files), the lifting test case, the agreement and speed measures and the targets. Anything
that needs torch or their code is exercised by running the benchmark, not here."""


import numpy as np
import pytest

from wrinkle_jax import mesh, primitives, reference, timing


def _irregular_mesh():
    """A jittered sheet with alternating diagonals (valences 3 to 8)."""
    g = primitives.grid_sheet(4, 3, size=(0.4, 0.3), jitter=0.2, seed=3)
    return np.asarray(g.faces, np.int64), g.num_vertices


def test_cross_edges_are_each_faces_opposite_edge_once():
    faces, v = _irregular_mesh()
    e0, e1, counts = reference.cross_edges(faces, v)
    assert counts.sum() == e0.size == e1.size == 3 * len(faces)
    assert np.array_equal(counts, np.bincount(faces.reshape(-1), minlength=v))
    owner = np.repeat(np.arange(v), counts)  # their layout: vertex 0's edges first
    got = sorted(tuple(sorted((int(o), int(a), int(b)))) for o, a, b in zip(owner, e0, e1,
                                                                            strict=True))
    want = sorted(tuple(sorted(map(int, f))) for f in faces for _ in range(3))
    assert got == want  # every (owner, edge) is a face, and each face once per corner
    assert np.all(owner != e0) and np.all(owner != e1)


def test_cross_edges_are_perpendicular_to_a_flat_sheets_normal():
    # Their normal term n_p . (q0 - q1) / |q0 - q1| vanishes on a flat mesh with the true
    # normal, and not once one vertex is lifted out of the plane.
    g = primitives.grid_sheet(5, 5, size=(0.5, 0.5))
    faces, verts = np.asarray(g.faces), np.asarray(g.vertices, np.float64)
    e0, e1, _ = reference.cross_edges(faces, g.num_vertices)
    e = verts[e0] - verts[e1]
    assert np.max(np.abs(e[:, 2])) == 0.0
    verts[g.num_vertices // 2, 2] = 0.02
    e = verts[e0] - verts[e1]
    assert np.max(np.abs(e[:, 2])) > 0.01


def test_adjacency_gives_the_uniform_laplacian():
    faces, v = _irregular_mesh()
    adj = reference.adjacency_with_self(faces, v)
    assert np.array_equal(adj, adj.T) and np.all(np.diag(adj) == 1)
    # Their Laplacian: rows of (adjacency without the diagonal) over the degree, minus I;
    # it must be ours (mesh.uniform_laplacian: mean of the one-ring minus the vertex).
    off = adj - np.eye(v, dtype=adj.dtype)
    theirs_style = off / off.sum(1, keepdims=True) - np.eye(v)
    ours = mesh.uniform_laplacian(faces, v)
    np.testing.assert_allclose(theirs_style, ours.todense(), atol=1e-6)


def test_lift_case_targets_are_the_ideal_surfaces_normals():
    case = reference.make_lift_case(20)
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
        reference.make_lift_case(30)


def test_tree_rel_rms_all_worst_and_negligible_leaves():
    theirs = {"a": np.array([3.0, 4.0]), "b": np.array([1.0, 0.0]), "z": np.array([1e-9])}
    ours = {"a": np.array([3.0, 4.0]), "b": np.array([1.5, 0.0]), "z": np.array([-1e-9])}
    r = reference.tree_rel_rms(ours, theirs)
    # |d| = 0.5 over the whole tree, whose norm is sqrt(25 + 1 + 1e-18).
    np.testing.assert_allclose(r["all"], 0.5 / np.sqrt(26.0), rtol=1e-9)
    # "z" (1e-9 of the largest leaf) is left out although its own error is 200 %.
    assert r["worst_leaf_name"] == "['b']" and r["worst_leaf"] == pytest.approx(0.5)
    assert reference.tree_rel_rms(theirs, theirs)["all"] == 0.0


def test_agreement_is_relative_to_the_rms_of_theirs():
    theirs = np.array([[3.0, -4.0], [0.0, 0.0]])  # RMS 2.5
    ours = theirs + np.array([[0.5, 0.0], [0.0, -0.5]])
    a = reference.agreement(ours, theirs)
    assert a["output_rms"] == pytest.approx(2.5) and a["max_abs"] == pytest.approx(0.5)
    assert a["max_abs_over_output_rms"] == pytest.approx(0.2)
    assert a["rel_rms"] == pytest.approx(np.sqrt(0.125) / 2.5)
    assert reference.agreement(theirs, theirs)["rel_rms"] == 0.0


def test_speedups_are_median_per_round_ratios_and_the_targets_read_them():
    t = timing.Timing(wall_rounds={"authors_torch": [6.0, 8.0, 30.0], "ours": [1.0, 2.0, 3.0]},
                      cpu_rounds={"authors_torch": [4.0, 4.0, 4.0], "ours": [2.0, 1.0, 4.0]},
                      reps=3, load_before=None, load_after=None)
    s = reference.speedups(t)
    assert s == {"speedup_vs_authors_wall": {"ours": 6.0},  # median of 6, 4, 10
                 "speedup_vs_authors_cpu": {"ours": 2.0}}
    unet_part = {"speedup_vs_authors_wall": {"ours_xla": 1.0, "ours_im2col_bf16": 6.0,
                                             "ours_winograd_bf16": 2.5},
                 "agreement_vs_authors": {"xla": {"rel_rms": 0.5},
                                          "im2col_bf16": {"rel_rms": 0.004},
                                          "winograd_bf16": {"rel_rms": 0.02}}}
    report = {"unet": unet_part, "lift": {"speedup_vs_authors_wall": {"ours_default": 80.0}}}
    got = reference.target_summary(report)
    assert got["unet_inference_x_authors_best"] == 6.0 and got["unet_inference_goal_3x_met"]
    assert got["unet_inference_best_form"] == "im2col_bf16"
    assert got["im2col_bf16_error_goal_1pct_met"]
    assert not got["winograd_bf16_error_goal_1pct_met"]  # each bfloat16 form bounded
    assert "xla_error_goal_1pct_met" not in got  # the float32 form has no such goal
    assert got["lift_default_x_authors"] == 80.0 and not got["lift_goal_100x_met"]
    assert not any(k.startswith("train") for k in got)  # no training section, no targets
    assert reference.target_summary({}) == {}


def test_their_text_files_and_the_surface_distance(tmp_path):
    verts = np.array([[0.0, 1.5, -2.0], [1e-3, 0.125, 3.0]])
    reference.write_vertex_text(tmp_path / "v.txt", verts)
    np.testing.assert_array_equal(np.loadtxt(tmp_path / "v.txt"), verts)
    reference.write_flag_text(tmp_path / "f.txt", np.array([True, False, True]))
    assert (tmp_path / "f.txt").read_text() == "3\n1\n0\n1\n"
    assert reference.surface_rms_mm(verts, verts) == 0.0
    assert reference.surface_rms_mm(verts + [0.0, 0.003, 0.004], verts) == pytest.approx(5.0)
