"""Tests for wrinkle_jax.evaluation.improvement_score (paper Sec. 5)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from wrinkle_jax import evaluation
from wrinkle_jax.nn import losses, vgg

LAYERS = ("relu1_2", "relu2_1", "relu3_1")


@pytest.fixture(scope="module")
def tiny_vgg():
    # rbg key: threefry draws compile ~4x slower on CPU (see unet.init_params)
    return vgg.init_vgg19(jax.random.key(1, impl="rbg"), widths=(4, 8, 8, 8, 8), num_convs=5,
                          spec=vgg.VGGSpec("custom", "REFLECT"))


@pytest.fixture(scope="module")
def patches():
    rng = np.random.default_rng(0)
    inp, out, tgt = (jnp.asarray(rng.uniform(size=(3, 16, 16, 3)), jnp.float32) for _ in range(3))
    mask = jnp.ones((3, 16, 16, 1)).at[:, :, :4].set(0.0)
    return inp, out, tgt, mask


score_jit = jax.jit(evaluation.improvement_score, static_argnames=("layers",))


def test_from_losses_conventions():
    s = evaluation.improvement_score_from_losses(
        loss_input=jnp.array([4.0, 4.0, 4.0, 4.0, 0.0, 0.0]),
        loss_output=jnp.array([0.0, 4.0, 1.0, 10.0, 0.0, 3.0]),
    )
    np.testing.assert_allclose(s.score, [100.0, 0.0, 75.0, 150.0, 100.0, 0.0])
    np.testing.assert_allclose(s.signed_score, [100.0, 0.0, 75.0, -150.0, 100.0, 0.0])
    np.testing.assert_array_equal(s.valid, [True, True, True, True, False, False])
    # A nonzero L(N_hat) enters the denominator as in the paper's formula.
    s = evaluation.improvement_score_from_losses(jnp.array([5.0]), jnp.array([3.0]), 1.0)
    np.testing.assert_allclose(s.score, [50.0])


def test_output_equal_target_scores_100(tiny_vgg, patches):
    inp, _, tgt, mask = patches
    s = score_jit(inp, tgt, tgt, mask, tiny_vgg, layers=LAYERS)
    assert np.all(np.asarray(s.valid))
    np.testing.assert_allclose(s.loss_output, 0.0, atol=1e-6)
    np.testing.assert_allclose(s.score, 100.0, rtol=1e-5)


def test_output_equal_input_scores_0(tiny_vgg, patches):
    inp, _, tgt, mask = patches
    s = score_jit(inp, inp, tgt, mask, tiny_vgg, layers=LAYERS)
    np.testing.assert_allclose(s.score, 0.0, atol=1e-4)
    assert np.all(np.asarray(s.loss_input) > 0)


def test_generic_output_matches_style_losses(tiny_vgg, patches):
    inp, out, tgt, mask = patches
    s = score_jit(inp, out, tgt, mask, tiny_vgg, layers=LAYERS)
    feats = {name: vgg.features(tiny_vgg, x, layers=LAYERS) for name, x in
             (("inp", inp), ("out", out), ("tgt", tgt))}
    l_in = losses.style_loss(feats["inp"], feats["tgt"], mask, LAYERS)
    l_out = losses.style_loss(feats["out"], feats["tgt"], mask, LAYERS)
    np.testing.assert_allclose(s.score, 100 * np.abs(l_in - l_out) / l_in, rtol=1e-4)


def test_degenerate_denominator(tiny_vgg, patches):
    inp, out, tgt, mask = patches
    # Input already matches the target: flagged invalid, 100 if out matches too, else 0.
    s = score_jit(tgt, tgt, tgt, mask, tiny_vgg, layers=LAYERS)
    np.testing.assert_array_equal(s.valid, False)
    np.testing.assert_array_equal(s.score, 100.0)
    s = score_jit(tgt, out, tgt, mask, tiny_vgg, layers=LAYERS)
    np.testing.assert_array_equal(s.valid, False)
    np.testing.assert_array_equal(s.score, 0.0)
    # An empty mask makes every loss 0: invalid, finite.
    s = score_jit(inp, out, tgt, jnp.zeros_like(mask), tiny_vgg, layers=LAYERS)
    assert np.all(np.isfinite(np.asarray(s.score))) and not np.any(np.asarray(s.valid))


def test_chamfer_distance_is_zero_symmetric_translation_invariant_and_hand_computed():
    rng = np.random.default_rng(0)
    x, y = rng.normal(size=(5, 3)), rng.normal(size=(7, 3))
    assert evaluation.chamfer_distance(x, x) == 0.0
    cd = evaluation.chamfer_distance(x, y)
    assert cd > 0 and evaluation.chamfer_distance(y, x) == pytest.approx(cd, rel=1e-12)
    shift = np.array([10.0, -3.0, 0.5])
    assert evaluation.chamfer_distance(x + shift, y + shift) == pytest.approx(cd, rel=1e-9)
    # Both directions count: a subset is at distance 0 one way only.
    assert evaluation.chamfer_distance(x[:2], x) > 0
    # a = {(0, 0), (2, 0)}, c = {(0, 1)}: a -> c 1 and sqrt(5), c -> a 1.
    a, c = [[0.0, 0.0], [2.0, 0.0]], [[0.0, 1.0]]
    hand = ((1.0 + np.sqrt(5.0)) / 2 + 1.0) / 2
    assert evaluation.chamfer_distance(a, c) == pytest.approx(hand, rel=1e-12)
    assert (evaluation.chamfer_from_sq_dists(evaluation.sq_dists(a, c))
            == pytest.approx(hand, rel=1e-12))
    np.testing.assert_array_equal(np.diag(evaluation.sq_dists(x)), 0.0)


def test_decrease_ratio_paper_form_and_signed_form():
    assert evaluation.decrease_ratio(2.0, 0.5) == 75.0
    assert evaluation.decrease_ratio(2.0, 0.5, signed=True) == 75.0
    # The paper's |.| form cannot tell "further from the fine patches" from "closer".
    assert evaluation.decrease_ratio(1.0, 1.5) == 50.0
    assert evaluation.decrease_ratio(1.0, 1.5, signed=True) == -50.0
    assert evaluation.decrease_ratio(1.0, 1.0, signed=True) == 0.0
    assert np.isnan(evaluation.decrease_ratio(0.0, 0.1))
    assert np.isnan(evaluation.decrease_ratio(np.nan, 1))


def test_normal_angles_are_accurate_for_tiny_angles_and_zero_for_zero_vectors():
    a = np.array([0.0, 0.0, 1.0])
    for deg in (1e-4, 0.01, 1.0, 90.0, 179.0):
        r = np.radians(deg)
        b = np.array([np.sin(r), 0.0, np.cos(r)]) * 3.0  # length does not matter
        assert evaluation.normal_angles(a, b) == pytest.approx(deg, rel=1e-9)
    assert evaluation.normal_angles(a, np.zeros(3)) == 0.0
    assert evaluation.mean_angular_change(np.ones((2, 2, 3)), np.ones((2, 2, 3)),
                                       np.ones((2, 2))) == 0.0


def test_spectral_embedding_separates_two_clusters():
    rng = np.random.default_rng(1)
    x = np.concatenate([rng.normal(0, 0.1, (20, 5)), rng.normal(3, 0.1, (20, 5))])
    emb = evaluation.spectral_embedding(x, dim=2)
    assert emb.shape == (40, 2)
    first = np.sign(emb[:, 0])
    assert abs(first[:20].sum()) == 20 and abs(first[20:].sum()) == 20
    assert first[0] != first[-1]
