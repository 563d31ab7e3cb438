"""Tests for the detail band energies (detail.band_rms), the band-energy loss
(nn.losses.band_loss) and its use in training (train.TrainConfig.band_weight)."""

from __future__ import annotations

import argparse
import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from wrinkle_jax import data, detail, recipe, train
from wrinkle_jax.evaluation import bands as np_bands
from wrinkle_jax.nn import losses, unet, vgg


def _disc_mask(n, size, radius):
    yy, xx = np.mgrid[:size, :size] - (size - 1) / 2
    m = (np.hypot(yy, xx) <= radius).astype(np.float32)[None, ..., None]
    return np.repeat(m, n, axis=0)


def _detail_rgb(tx, ty, mask):
    """RGB form of unit normals with tangential parts (tx, ty), 0 outside the mask."""
    n = np.stack([tx, ty, np.sqrt(1 - tx**2 - ty**2)], -1)
    return ((n + 1) / 2 * np.asarray(mask).reshape(*np.shape(tx), 1)).astype(np.float32)


def _waves(size, wavelength_texels, amp, phase=0.0):
    yy, xx = np.mgrid[:size, :size].astype(np.float64)
    k = 2 * np.pi / wavelength_texels
    return amp * np.sin(k * (0.8 * xx + 0.6 * yy) + phase), amp * np.cos(k * xx + phase)


def test_band_rms_matches_the_numpy_reference():
    rng = np.random.default_rng(0)
    mask = _disc_mask(3, 48, 21.0)
    mask[2, :, 30:] = 0  # a cut disc: irregular border
    t = rng.normal(size=(3, 48, 48, 2)) * 0.08
    x = _detail_rgb(t[..., 0].clip(-0.5, 0.5), t[..., 1].clip(-0.5, 0.5), mask)
    got = detail.band_rms(x, mask)
    want = np_bands.band_rms(x, mask)
    assert set(got) == set(want) == set(detail.BAND_SIGMAS)
    for k in want:
        assert np.all(want[k] > 1e-3)
        np.testing.assert_allclose(np.asarray(got[k]), want[k], rtol=2e-4)


def test_band_rms_puts_each_wavelength_in_its_band():
    size, mask = 64, _disc_mask(1, 64, 30.0)
    fine = _detail_rgb(*_waves(size, 4.0, 0.1), mask[0])[None]   # 8 mm
    wrinkle = _detail_rgb(*_waves(size, 16.0, 0.1), mask[0])[None]  # 32 mm
    f, w = detail.band_rms(fine, mask), detail.band_rms(wrinkle, mask)
    assert float(f["lt16mm"][0]) > 10 * float(f["16_64mm"][0])
    assert float(w["16_64mm"][0]) > 3 * float(w["lt16mm"][0])


def test_band_loss_is_zero_for_equal_energy_and_the_squared_log_ratio_for_scaled_detail():
    size, mask = 64, _disc_mask(2, 64, 30.0)
    tx, ty = _waves(size, 6.0, 0.02)
    ux, uy = _waves(size, 20.0, 0.02, phase=1.0)
    x, y = tx + ux, ty + uy
    m = mask[0]
    target = np.stack([_detail_rgb(x, y, m)] * 2)
    # The same waves with other phases (displaced wrinkles): no alignment needed.
    (sx, sy), (vx, vy) = _waves(size, 6.0, 0.02, phase=2.0), _waves(size, 20.0, 0.02, phase=3.0)
    shifted = np.stack([_detail_rgb(sx + vx, sy + vy, m)] * 2)
    doubled = np.stack([_detail_rgb(2 * x, 2 * y, m)] * 2)
    assert float(jnp.max(losses.band_loss(target, target, mask))) == 0.0
    # Small tangents: the RGB form is linear in them to O(t^2), so doubling doubles each band.
    got = np.asarray(losses.band_loss(doubled, target, mask, eps=0.0))
    np.testing.assert_allclose(got, 2 * np.log(2.0) ** 2, rtol=2e-3)
    assert float(jnp.max(losses.band_loss(shifted, target, mask))) < 0.05 * got[0]


def test_band_loss_of_an_empty_mask_or_flat_band_is_finite_with_finite_gradients():
    mask = np.zeros((1, 32, 32, 1), np.float32)
    flat = np.zeros((1, 32, 32, 3), np.float32)
    f = jax.jit(jax.value_and_grad(
        lambda o, m: jnp.sum(losses.band_loss(o, flat * 0 + 0.5 * m, m))))
    v, g = f(flat + 0.5, mask)
    assert float(v) == 0.0 and np.isfinite(np.asarray(g)).all()
    full = np.ones_like(mask)
    flat_rgb = np.broadcast_to(np.float32([0.5, 0.5, 1.0]), flat.shape).copy()
    v, g = f(flat_rgb, full)
    assert np.isfinite(float(v)) and np.isfinite(np.asarray(g)).all()


@pytest.fixture(scope="module")
def tiny_vgg():
    return vgg.init_vgg19(jax.random.key(0, impl="rbg"), widths=(4, 8, 8, 8, 8), num_convs=4,
                          spec=vgg.VGGSpec("custom", "REFLECT"))


def test_training_objective_adds_the_weighted_band_term_and_eval_reports_band_ratios(
        tiny_patch_root, tiny_vgg):
    net = unet.UNetConfig(width=4, residual=True, detail_sigma=4.0, input_norm="none")
    base = train.TrainConfig(net, batch_size=4, style_layers=("relu1_2",), w_s=1e7)
    banded = dataclasses.replace(base, band_weight=2.5)
    ds = data.PatchDataset(tiny_patch_root, "train")
    batch = next(data.BatchIterator(ds, 4, seed=0))
    state = train.create_train_state(base, jax.random.key(1, impl="rbg"), patch_size=32)

    @jax.jit
    def parts(params):
        _, p1 = train.loss_fn(params, batch, tiny_vgg, banded)
        _, out, tgt = train.loss_images(base, batch, train._forward(base, params, batch))
        return p1, losses.band_loss(out, tgt, batch["mask"]), out, tgt

    p1, band, out, tgt = parts(state.params)
    assert float(jnp.max(band)) > 0.01  # the untrained output (= input) misses the target
    np.testing.assert_allclose(np.asarray(p1["band"]), np.asarray(band), rtol=1e-5)
    want = base.w_c * p1["content"] + base.w_s * p1["style"] + 2.5 * band
    np.testing.assert_allclose(np.asarray(p1["total"]), np.asarray(want), rtol=1e-5)
    ev = train.evaluate(train.make_eval_step(banded, tiny_vgg), state.params, [batch])
    rms = detail.band_rms(jnp.concatenate([out, tgt]), jnp.concatenate([batch["mask"]] * 2))
    for k, v in rms.items():
        ratio = np.asarray(v[:4] / v[4:])
        assert ev[f"heldout_band_{k}_median"] == pytest.approx(float(np.median(ratio)), rel=1e-4)


def test_band_weight_flag_and_run_config_round_trip():
    ap = argparse.ArgumentParser()
    recipe.add_recipe_args(ap)
    cfg = recipe.config_from_args(ap.parse_args(["--band-weight", "3", "--detail-sigma", "8"]))
    assert cfg.band_weight == 3.0
    assert train.TrainConfig.from_json(cfg.to_json()) == cfg
    assert recipe.config_from_args(ap.parse_args([])).band_weight == 0.0
    # Run configs written before the field existed read as "no band term".
    old = {k: v for k, v in train.RECIPE.to_json().items() if k != "band_weight"}
    assert train.TrainConfig.from_json(old).band_weight == 0.0
