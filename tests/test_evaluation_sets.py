"""Tests for table 2's set metrics: Gram features, Chamfer distances, DR, embeddings
(`wrinkle_jax.evaluation.sets`)."""

from __future__ import annotations

import numpy as np
import pytest

from wrinkle_jax import evaluation
from wrinkle_jax.evaluation import sets as set_lib


def test_chamfer_scores_hold_both_distances_and_both_ratios():
    assert set_lib.chamfer_scores(2.0, 3.0) == {"c1": 2.0, "c2": 3.0, "dr": 50.0,
                                               "dr_signed": -50.0}


def test_gram_features_are_upper_triangles_with_layers_scaled_to_unit_median_norm():
    rng = np.random.default_rng(1)

    def sym(n, c, scale):
        m = rng.normal(size=(n, c, c)) * scale
        return m + m.transpose(0, 2, 1)

    grams = {"small": sym(3, 2, 1.0), "big": sym(3, 4, 1000.0)}
    flat = set_lib.upper_triangle(grams)
    assert list(flat) == ["small", "big"]
    assert flat["small"].shape == (3, 3) and flat["big"].shape == (3, 10)
    assert flat["big"].dtype == np.float32
    g = grams["small"][1]
    np.testing.assert_allclose(flat["small"][1], [g[0, 0], g[0, 1], g[1, 1]], rtol=1e-6)
    scales = set_lib.layer_scales(flat)
    assert scales["big"] == pytest.approx(np.median(np.linalg.norm(flat["big"], axis=1)))
    feats = set_lib.scaled_features(flat, scales)
    assert feats.shape == (3, 13)
    for block in (feats[:, :3], feats[:, 3:]):
        assert np.median(np.linalg.norm(block, axis=1)) == pytest.approx(1.0)
    # A layer's overall magnitude is scaled away.
    louder = dict(flat, big=flat["big"] * 1e3)
    np.testing.assert_allclose(set_lib.scaled_features(louder, set_lib.layer_scales(louder)), feats,
                               rtol=1e-5)
    # Layer-by-layer distances equal the distances of the concatenated features.
    np.testing.assert_allclose(set_lib.scaled_sq_dists(flat, None, scales),
                               evaluation.sq_dists(feats), rtol=1e-9, atol=1e-12)
    other = set_lib.upper_triangle({"small": sym(2, 2, 1.0), "big": sym(2, 4, 1000.0)})
    np.testing.assert_allclose(set_lib.scaled_sq_dists(other, flat, scales),
                               evaluation.sq_dists(set_lib.scaled_features(other, scales), feats),
                               rtol=1e-9)
    assert set_lib.layer_scales({"zero": np.zeros((2, 3), np.float32)}) == {"zero": 1.0}
    with pytest.raises(ValueError, match="Gram"):
        set_lib.upper_triangle({"x": np.zeros((2, 3, 4))})


def test_embedding_from_the_distance_matrix_equals_the_embedding_of_the_points():
    x = np.random.default_rng(2).normal(size=(30, 50))
    d2 = evaluation.sq_dists(x)
    pts = set_lib.points_from_sq_dists(d2)
    np.testing.assert_allclose(evaluation.sq_dists(pts), d2, atol=1e-9)
    # Eigenvectors are defined up to sign.
    np.testing.assert_allclose(np.abs(evaluation.spectral_embedding(pts)),
                               np.abs(evaluation.spectral_embedding(x)), atol=1e-9)


def test_unit_rows_keeps_the_direction_and_drops_the_amount():
    rng = np.random.default_rng(4)
    x = rng.normal(size=(3, 5))
    flat = {"a": np.vstack([x, np.zeros((1, 5))]), "b": 7.0 * np.vstack([x, x[:1]])}
    got = set_lib.unit_rows(flat)
    assert list(got) == ["a", "b"]
    np.testing.assert_allclose(np.linalg.norm(got["a"][:3], axis=1), 1.0, rtol=1e-6)
    assert not got["a"][3].any()  # an empty row stays empty
    # Scaling a patch's vector (more detail of the same texture) does not move it.
    np.testing.assert_allclose(got["b"][:3], got["a"][:3], rtol=1e-6)
    np.testing.assert_allclose(got["b"][3], got["a"][0], rtol=1e-6)
