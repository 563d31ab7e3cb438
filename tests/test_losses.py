"""Tests for wrinkle_jax.nn.losses: Gram matrices, masked style / content losses."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from wrinkle_jax.nn import losses, vgg

LAYERS = ("relu1_1", "relu2_1")


def _block_mask(rng, n, h, w):
    """Binary mask built from aligned 2x2 blocks, so it stays binary one level down."""
    coarse = (rng.uniform(size=(n, h // 2, w // 2, 1)) > 0.4).astype(np.float32)
    return np.repeat(np.repeat(coarse, 2, axis=1), 2, axis=2)


def _feats(rng, n=2, h=8, w=8, c=(5, 7)):
    return {
        "relu1_1": rng.normal(size=(n, h, w, c[0])).astype(np.float32),
        "relu2_1": rng.normal(size=(n, h // 2, w // 2, c[1])).astype(np.float32),
    }


def _ref_style(out, tgt, mask, layers):
    """Paper formula in float64: sum_l ||G(out) - G(tgt)||^2 / (4 R_l^2), per sample."""
    total = np.zeros(mask.shape[0])
    for name in layers:
        m = mask.astype(np.float64)
        for _ in range(vgg.layer_level(name)):
            n, h, w, _ = m.shape
            m = m.reshape(n, h // 2, 2, w // 2, 2, 1).mean(axis=(2, 4))
        r = m.sum(axis=(1, 2, 3))
        g_out = np.einsum("nhwc,nhwd->ncd", out[name] * m, out[name] * m)
        g_tgt = np.einsum("nhwc,nhwd->ncd", tgt[name] * m, tgt[name] * m)
        total += ((g_out - g_tgt) ** 2).sum(axis=(1, 2)) / (4 * r**2)
    return total


def test_mask_pyramid():
    mask = jnp.zeros((1, 8, 8, 1)).at[0, :4, :2, 0].set(1.0).at[0, 5, 5, 0].set(1.0)
    levels = losses.mask_pyramid(mask, 3)
    assert [m.shape for m in levels] == [(1, 8, 8, 1), (1, 4, 4, 1), (1, 2, 2, 1)]
    np.testing.assert_allclose(levels[1][0, :2, 0, 0], [1.0, 1.0])
    np.testing.assert_allclose(levels[1][0, 2, 2, 0], 0.25)
    np.testing.assert_allclose(levels[2][0, :, :, 0], [[0.5, 0.0], [0.0, 0.0625]])
    with pytest.raises(ValueError, match="mask must be"):
        losses.mask_pyramid(jnp.zeros((8, 8)), 2)


def test_gram_symmetric_psd_and_reference():
    rng = np.random.default_rng(0)
    f = rng.normal(size=(3, 6, 5, 4)).astype(np.float32)
    m = rng.uniform(size=(3, 6, 5, 1)).astype(np.float32)
    g = np.asarray(jax.jit(losses.gram)(f, m))
    np.testing.assert_allclose(g, np.swapaxes(g, 1, 2), rtol=1e-6)
    assert np.linalg.eigvalsh(g.astype(np.float64)).min() > -1e-4
    want = np.einsum("nhw,nhwc,nhwd->ncd", m[..., 0] ** 2, f, f)
    np.testing.assert_allclose(g, want, rtol=1e-5, atol=1e-5)
    gn = losses.gram(f, m, normalize=True)
    np.testing.assert_allclose(gn, want / m.sum(axis=(1, 2, 3))[:, None, None], rtol=1e-5)


def test_style_loss_matches_paper_formula():
    rng = np.random.default_rng(1)
    out, tgt = _feats(rng), _feats(rng)
    mask = _block_mask(rng, 2, 8, 8)
    got = jax.jit(losses.style_loss, static_argnames="layers")(out, tgt, mask, layers=LAYERS)
    assert got.shape == (2,)
    np.testing.assert_allclose(got, _ref_style(out, tgt, mask, LAYERS), rtol=1e-4)


def test_style_loss_of_identical_features_is_zero():
    rng = np.random.default_rng(2)
    f = _feats(rng)
    mask = _block_mask(rng, 2, 8, 8)
    np.testing.assert_array_equal(losses.style_loss(f, f, mask, LAYERS), np.zeros(2))


def test_style_loss_invariant_to_pixel_permutation_inside_mask():
    rng = np.random.default_rng(3)
    out, tgt = _feats(rng), _feats(rng)
    mask = _block_mask(rng, 2, 8, 8)
    permuted = {}
    for name, f in out.items():
        level_mask = np.asarray(losses.mask_pyramid(jnp.asarray(mask), 2)[vgg.layer_level(name)])
        g = f.copy()
        for i in range(f.shape[0]):
            inside = np.flatnonzero(level_mask[i, ..., 0].ravel() == 1.0)
            flat = g[i].reshape(-1, f.shape[-1])
            flat[inside] = flat[rng.permutation(inside)]
        permuted[name] = g
    assert not np.array_equal(permuted["relu1_1"], out["relu1_1"])
    np.testing.assert_allclose(losses.style_loss(permuted, tgt, mask, LAYERS),
                               losses.style_loss(out, tgt, mask, LAYERS), rtol=1e-5)


def test_background_has_no_effect():
    rng = np.random.default_rng(4)
    out, tgt = _feats(rng), _feats(rng)
    mask = _block_mask(rng, 2, 8, 8)
    changed_out, changed_tgt = {}, {}
    for name in LAYERS:
        level_mask = np.asarray(losses.mask_pyramid(jnp.asarray(mask), 2)[vgg.layer_level(name)])
        noise = 100.0 * rng.normal(size=out[name].shape).astype(np.float32)
        changed_out[name] = np.where(level_mask == 0, noise, out[name])
        changed_tgt[name] = np.where(level_mask == 0, -noise, tgt[name])
    base = losses.style_loss(out, tgt, mask, LAYERS)
    np.testing.assert_allclose(losses.style_loss(changed_out, changed_tgt, mask, LAYERS), base,
                               rtol=1e-6)
    np.testing.assert_allclose(losses.content_loss(changed_out, tgt, mask, "relu2_1"),
                               losses.content_loss(out, tgt, mask, "relu2_1"), rtol=1e-6)


def test_empty_mask_gives_zero_loss_and_finite_gradients():
    rng = np.random.default_rng(5)
    out, tgt = _feats(rng), _feats(rng)
    mask = np.zeros((2, 8, 8, 1), np.float32)

    def total(o):
        return jnp.sum(losses.style_loss(o, tgt, mask, LAYERS)
                       + losses.content_loss(o, tgt, mask, "relu2_1"))

    value, grads = jax.jit(jax.value_and_grad(total))(out)
    assert value == 0.0
    for g in jax.tree_util.tree_leaves(grads):
        assert np.all(np.isfinite(g))


def test_partially_empty_batch():
    rng = np.random.default_rng(6)
    out, tgt = _feats(rng), _feats(rng)
    mask = _block_mask(rng, 2, 8, 8)
    mask[1] = 0.0
    loss = losses.style_loss(out, tgt, mask, LAYERS)
    assert loss[0] > 0 and loss[1] == 0.0


def test_jit_and_vmap_agree_with_per_sample_calls():
    rng = np.random.default_rng(7)
    out, tgt = _feats(rng, n=3), _feats(rng, n=3)
    mask = _block_mask(rng, 3, 8, 8)
    batched = jax.jit(losses.style_loss, static_argnames="layers")(out, tgt, mask, layers=LAYERS)

    def one(o, t, m):
        add = lambda d: {k: v[None] for k, v in d.items()}  # noqa: E731
        return losses.style_loss(add(o), add(t), m[None], LAYERS)[0]

    vmapped = jax.vmap(one)(out, tgt, mask)
    singles = [one({k: v[i] for k, v in out.items()}, {k: v[i] for k, v in tgt.items()}, mask[i])
               for i in range(3)]
    np.testing.assert_allclose(vmapped, batched, rtol=1e-5)
    np.testing.assert_allclose(singles, batched, rtol=1e-5)


def test_style_gradient_matches_finite_differences():
    rng = np.random.default_rng(8)
    out, tgt = _feats(rng, n=1), _feats(rng, n=1)
    mask = _block_mask(rng, 1, 8, 8)
    f = lambda o: losses.style_loss(o, tgt, mask, LAYERS)[0]  # noqa: E731
    grad = jax.grad(f)(out)
    direction = {k: rng.normal(size=v.shape).astype(np.float32) for k, v in out.items()}
    h = 1e-2
    plus = f({k: out[k] + h * direction[k] for k in out})
    minus = f({k: out[k] - h * direction[k] for k in out})
    directional = sum(float(jnp.vdot(grad[k], direction[k])) for k in out)
    np.testing.assert_allclose((plus - minus) / (2 * h), directional, rtol=1e-2)


def test_layer_weights_and_channel_normalization():
    rng = np.random.default_rng(9)
    out, tgt = _feats(rng), _feats(rng)
    mask = _block_mask(rng, 2, 8, 8)
    per_layer = [losses.style_loss(out, tgt, mask, (name,)) for name in LAYERS]
    weighted = losses.style_loss(out, tgt, mask, LAYERS, layer_weights=(2.0, 0.5))
    np.testing.assert_allclose(weighted, 2.0 * per_layer[0] + 0.5 * per_layer[1], rtol=1e-6)
    as_dict = losses.style_loss(out, tgt, mask, LAYERS, layer_weights={"relu1_1": 2.0,
                                                                       "relu2_1": 0.5})
    np.testing.assert_allclose(as_dict, weighted, rtol=1e-6)
    normed = losses.style_loss(out, tgt, mask, LAYERS, normalize_channels=True)
    np.testing.assert_allclose(normed, per_layer[0] / 25 + per_layer[1] / 49, rtol=1e-6)


def test_content_loss_is_masked_mse():
    rng = np.random.default_rng(10)
    out, inp = _feats(rng), _feats(rng)
    mask = rng.uniform(size=(2, 8, 8, 1)).astype(np.float32)
    m = mask.reshape(2, 4, 2, 4, 2, 1).mean(axis=(2, 4))
    sq = ((out["relu2_1"] - inp["relu2_1"]) ** 2).sum(-1, keepdims=True)
    want = (m * sq).sum(axis=(1, 2, 3)) / (m.sum(axis=(1, 2, 3)) * 7)
    np.testing.assert_allclose(losses.content_loss(out, inp, mask, "relu2_1"), want, rtol=1e-5)
    np.testing.assert_array_equal(losses.content_loss(out, out, mask, "relu2_1"), np.zeros(2))


def test_mask_shape_mismatch_is_reported():
    rng = np.random.default_rng(11)
    f = _feats(rng)
    with pytest.raises(ValueError, match="does not match"):
        losses.style_loss(f, f, np.ones((2, 10, 10, 1), np.float32), LAYERS)


# --- enhancer_loss with a tiny random VGG ------------------------------------------------------


# `tiny_vgg` is the session fixture of tests/conftest.py: 16 convs of widths (4, 8, 8, 8, 8),
# identity input map (keeps random-network activations O(1)), rbg key (a threefry init compiled
# a draw per kernel shape: 6.3 s of CPU against 1.6 s), built once per worker.


def test_enhancer_loss(tiny_vgg):
    rng = np.random.default_rng(12)
    out, inp, tgt = (jnp.asarray(rng.uniform(size=(2, 16, 16, 3)), jnp.float32) for _ in range(3))
    mask = jnp.asarray(_block_mask(rng, 2, 16, 16))
    style_layers = ("relu1_2", "relu2_1", "relu3_1")
    loss_fn = jax.jit(losses.enhancer_loss, static_argnames=("style_layers", "content_layer"))
    total, parts = loss_fn(tiny_vgg, out, inp, tgt, mask, style_layers=style_layers)
    assert total.shape == () and parts["style"].shape == (2,)
    np.testing.assert_allclose(parts["total"], parts["content"] + 1e4 * parts["style"], rtol=1e-6)
    np.testing.assert_allclose(total, parts["total"].mean(), rtol=1e-6)

    # VGG runs only to the deepest layer needed: a tree without block 4-5 suffices.
    shallow = {k: v for k, v in tiny_vgg.items() if not k.startswith(("conv4", "conv5"))}
    total_shallow, _ = loss_fn(shallow, out, inp, tgt, mask, style_layers=style_layers)
    np.testing.assert_allclose(total_shallow, total, rtol=1e-6)

    # out == inp == target gives zero (up to rounding: the three VGG passes stop at different
    # depths, so XLA may fuse them differently); an empty mask gives zero, finite gradients.
    zero, _ = loss_fn(tiny_vgg, out, out, out, mask, style_layers=style_layers)
    assert abs(float(zero)) <= 1e-6 * float(total)
    grad_fn = jax.jit(jax.grad(lambda o, m: loss_fn(tiny_vgg, o, inp, tgt, m,
                                                    style_layers=style_layers)[0]))
    g_empty = grad_fn(out, jnp.zeros_like(mask))
    assert np.all(np.asarray(g_empty) == 0.0)
    g = grad_fn(out, mask)
    assert np.all(np.isfinite(np.asarray(g))) and np.any(np.asarray(g) != 0.0)


def test_relative_style_loss_divides_by_the_input_loss(tiny_vgg):
    rng = np.random.default_rng(13)
    out, inp, tgt = (jnp.asarray(rng.uniform(size=(3, 16, 16, 3)), jnp.float32) for _ in range(3))
    mask = jnp.asarray(_block_mask(rng, 3, 16, 16))
    layers = ("relu1_2", "relu2_1")
    loss_fn = jax.jit(losses.enhancer_loss,
                      static_argnames=("style_layers", "content_layer", "relative_floor"))
    _, absolute = loss_fn(tiny_vgg, out, inp, tgt, mask, style_layers=layers)
    _, rel = loss_fn(tiny_vgg, out, inp, tgt, mask, style_layers=layers, relative_floor=1e-3)
    feats = {k: vgg.features(tiny_vgg, x, layers=layers) for k, x in (("i", inp), ("t", tgt))}
    style_in = losses.style_loss(feats["i"], feats["t"], mask, layers)
    np.testing.assert_allclose(rel["style"], absolute["style"] / (style_in + 1e-3), rtol=1e-5)
    np.testing.assert_allclose(rel["content"], absolute["content"], rtol=1e-6)
    # The input itself scores a ratio of ~1 (exactly style_in / (style_in + floor)).
    _, ident = loss_fn(tiny_vgg, inp, inp, tgt, mask, style_layers=layers, relative_floor=1e-3)
    np.testing.assert_allclose(ident["style"], style_in / (style_in + 1e-3), rtol=1e-4)


def test_relative_log_style_loss_is_the_log_ratio_and_weighs_gains_like_losses(tiny_vgg):
    rng = np.random.default_rng(14)
    out, inp, tgt = (jnp.asarray(rng.uniform(size=(3, 16, 16, 3)), jnp.float32) for _ in range(3))
    mask = jnp.asarray(_block_mask(rng, 3, 16, 16))
    layers, floor = ("relu1_2", "relu2_1"), 1e-3
    loss_fn = jax.jit(losses.enhancer_loss, static_argnames=(
        "style_layers", "content_layer", "relative_floor", "relative_log"))
    _, absolute = loss_fn(tiny_vgg, out, inp, tgt, mask, style_layers=layers)
    _, log_rel = loss_fn(tiny_vgg, out, inp, tgt, mask, style_layers=layers,
                         relative_floor=floor, relative_log=True)
    feats = {k: vgg.features(tiny_vgg, x, layers=layers) for k, x in (("i", inp), ("t", tgt))}
    style_in = losses.style_loss(feats["i"], feats["t"], mask, layers)
    np.testing.assert_allclose(log_rel["style"],
                               np.log((absolute["style"] + floor) / (style_in + floor)),
                               rtol=1e-4, atol=1e-5)
    # The input itself scores exactly 0: no gain, no loss.
    _, ident = loss_fn(tiny_vgg, inp, inp, tgt, mask, style_layers=layers,
                       relative_floor=floor, relative_log=True)
    np.testing.assert_allclose(ident["style"], 0.0, atol=1e-5)
    # Gradient: the ratio form's, scaled by (style_in + floor) / (style_out + floor), so a
    # patch whose output is far worse than its input pulls less than under the ratio form.
    def style_sum(o, log):
        return loss_fn(tiny_vgg, o, inp, tgt, mask, style_layers=layers, relative_floor=floor,
                       relative_log=log)[1]["style"].sum()

    g_log, g_ratio = (jax.grad(style_sum)(out, lg) for lg in (True, False))
    scale = (style_in + floor) / (absolute["style"] + floor)
    np.testing.assert_allclose(g_log, g_ratio * scale[:, None, None, None], rtol=2e-3,
                               atol=1e-6 * float(jnp.abs(g_ratio).max()))
