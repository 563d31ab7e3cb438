"""Tests for the fine-target Gram bank (nn.gram_bank) and its set-level training term
(train.TrainConfig.bank_weight). `tiny_vgg` is conftest's session fixture."""

from __future__ import annotations

import argparse
import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from wrinkle_jax import data, recipe, train
from wrinkle_jax.evaluation import sets as set_lib
from wrinkle_jax.nn import gram_bank, unet, vgg

LAYERS = ("relu1_2", "relu2_1")


def _images(seed, n, size=16):
    rng = np.random.default_rng(seed)
    img = rng.uniform(0.2, 0.8, (n, size, size, 3)).astype(np.float32)
    mask = np.ones((n, size, size, 1), np.float32)
    mask[0, :, size // 2:] = 0  # a partial mask: its features are over the valid texels only
    return img * mask, mask


def test_bank_features_are_table2s_scaled_upper_triangles_and_rows_find_themselves(tiny_vgg):
    img, mask = _images(0, 6)
    material = np.array([0, 0, 0, 1, 1, 1])
    bank = gram_bank.build_bank(tiny_vgg, img, mask, material, LAYERS, batch_size=4)
    # Table 2's features (evaluation.sets / evaluation.gram) of the same images.
    f = vgg.features(tiny_vgg, img, layers=LAYERS)
    from wrinkle_jax.nn import losses
    masks = losses.mask_pyramid(mask, 2)
    grams = {n: np.asarray(losses.gram(f[n], masks[vgg.layer_level(n)], normalize=True))
             for n in LAYERS}
    flat = set_lib.upper_triangle(grams)
    scales = set_lib.layer_scales(flat)
    np.testing.assert_allclose(bank.scales, [scales[n] for n in LAYERS], rtol=1e-5)
    np.testing.assert_allclose(bank.vectors, set_lib.scaled_features(flat, scales),
                               rtol=1e-4, atol=1e-6)
    # A bank row's own image is at distance ~0; the features run batch-padded or not alike.
    x = gram_bank.feature_vectors(f, mask, bank)
    d = gram_bank.nearest_distance(x, jnp.asarray(material), jnp.asarray(bank.vectors),
                                   jnp.asarray(bank.material))
    assert float(jnp.max(d)) < 1e-3


def test_nearest_distance_is_the_brute_force_minimum_over_the_same_material():
    rng = np.random.default_rng(1)
    bank_v = rng.normal(size=(7, 5)).astype(np.float32)
    bank_m = np.array([0, 1, 1, 0, 2, 1, 0])
    x = rng.normal(size=(4, 5)).astype(np.float32)
    m = np.array([1, 0, 2, 3])
    got = np.asarray(gram_bank.nearest_distance(jnp.asarray(x), jnp.asarray(m),
                                                jnp.asarray(bank_v), jnp.asarray(bank_m)))
    for i in range(3):
        rows = bank_v[bank_m == m[i]]
        assert got[i] == pytest.approx(np.linalg.norm(rows - x[i], axis=1).min(), rel=1e-5)
    assert np.isinf(got[3])  # no bank row of material 3
    # The gradient pulls a row straight towards its nearest bank row.
    g = np.asarray(jax.grad(lambda v: gram_bank.nearest_distance(
        v, jnp.asarray(m[:1]), jnp.asarray(bank_v), jnp.asarray(bank_m))[0])(jnp.asarray(x[:1])))
    rows = bank_v[bank_m == m[0]]
    near = rows[np.argmin(np.linalg.norm(rows - x[0], axis=1))]
    np.testing.assert_allclose(g[0], (x[0] - near) / np.linalg.norm(x[0] - near), atol=1e-5)


def test_bank_save_load_round_trip(tmp_path, tiny_vgg):
    img, mask = _images(2, 3)
    bank = gram_bank.build_bank(tiny_vgg, img, mask, np.array([0, 1, 1]), LAYERS)
    gram_bank.save_bank(tmp_path / "b.npz", bank)
    got = gram_bank.load_bank(tmp_path / "b.npz")
    assert got.layers == bank.layers
    for a, b in ((got.vectors, bank.vectors), (got.material, bank.material),
                 (got.scales, bank.scales)):
        np.testing.assert_array_equal(a, b)


def test_training_objective_adds_the_weighted_bank_term(tiny_patch_root, tiny_vgg, tmp_path):
    net = unet.UNetConfig(width=4, residual=True, detail_sigma=4.0, input_norm="none")
    base = train.TrainConfig(net, batch_size=4, style_layers=("relu1_2", "relu2_1"), w_s=1e7,
                             bank_size=3, conv_impl="xla")
    banked = dataclasses.replace(base, bank_weight=0.5)
    ds = data.PatchDataset(tiny_patch_root, "train")
    bank = train.training_bank(banked, ds, tiny_vgg, tmp_path / "bank.npz")
    per_material = np.bincount(bank.material)
    assert per_material[per_material > 0].max() <= 3 and len(bank.vectors) >= 3
    assert (tmp_path / "bank.npz").exists()
    again = train.training_bank(banked, ds, tiny_vgg, tmp_path / "bank.npz")
    np.testing.assert_array_equal(again.vectors, bank.vectors)
    batch = next(data.BatchIterator(ds, 4, seed=0))
    state = train.create_train_state(base, jax.random.key(1, impl="rbg"), patch_size=32)

    @jax.jit
    def parts(params):
        _, p1 = train.loss_fn(params, batch, tiny_vgg, banked, bank)
        _, out, _ = train.loss_images(base, batch, train._forward(base, params, batch))
        f = vgg.features(tiny_vgg, out, layers=bank.layers, conv_impl=base.vgg_conv_impl)
        want = gram_bank.nearest_distance(gram_bank.feature_vectors(f, batch["mask"], bank),
                                          batch["material"], jnp.asarray(bank.vectors),
                                          jnp.asarray(bank.material))
        return p1, want

    p1, want = parts(state.params)
    assert float(jnp.min(want)) > 1e-3  # the untrained output is no bank row
    np.testing.assert_allclose(np.asarray(p1["bank"]), np.asarray(want), rtol=1e-5)
    np.testing.assert_allclose(np.asarray(p1["total"]),
                               np.asarray(base.w_c * p1["content"] + base.w_s * p1["style"]
                                          + 0.5 * want), rtol=1e-5)
    with pytest.raises(ValueError, match="bank"):
        train.loss_fn(state.params, batch, tiny_vgg, banked)


def test_bank_flags_and_run_config_round_trip():
    ap = argparse.ArgumentParser()
    recipe.add_recipe_args(ap)
    cfg = recipe.config_from_args(ap.parse_args(["--bank-weight", "2", "--bank-size", "64"]))
    assert (cfg.bank_weight, cfg.bank_size) == (2.0, 64)
    assert train.TrainConfig.from_json(cfg.to_json()) == cfg
    old = {k: v for k, v in train.RECIPE.to_json().items() if k not in ("bank_weight",
                                                                         "bank_size")}
    assert train.TrainConfig.from_json(old).bank_weight == 0.0


def test_a_damaged_or_foreign_bank_file_is_a_value_error_naming_it(tmp_path, tiny_vgg):
    img, mask = _images(2, 3)
    bank = gram_bank.build_bank(tiny_vgg, img, mask, np.array([0, 1, 1]), LAYERS)
    path = tmp_path / "b.npz"
    gram_bank.save_bank(path, bank)
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])  # cut short
    with pytest.raises(ValueError, match="b.npz: not a readable Gram bank"):
        gram_bank.load_bank(path)
    np.savez(path, vectors=bank.vectors)  # another file: no materials
    with pytest.raises(ValueError, match="b.npz: not a readable Gram bank.*KeyError"):
        gram_bank.load_bank(path)
