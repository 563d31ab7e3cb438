"""Function-preserving widening of a trained U-Net (`wrinkle_jax.nn.widen`)."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from wrinkle_jax.nn import unet
from wrinkle_jax.nn.widen import widen_params

# Tiny: texel noise (extra input channels) and bilinear up-sampling as in the fidelity recipe;
# widening touches only conv kernels, biases and CIN tables, which every variant shares.
CFG = unet.UNetConfig(width=2, residual=True, noise_channels=2, noise_scale=2,
                      upsample="bilinear")
S = 16


def _trained_like(params, seed):
    """Random non-zero values everywhere (a 'trained' network: the zero-initialized output
    conv would make any widening trivially function-preserving)."""
    rng = np.random.default_rng(seed)
    return jax.tree_util.tree_map(
        lambda v: np.asarray(v) + np.float32(0.3) * rng.standard_normal(v.shape, np.float32),
        params)


def _patches(n=2, s=S):
    yy, xx = np.mgrid[0:s, 0:s] / s
    rng = np.random.default_rng(0)
    n3 = np.stack([0.3 * np.sin(7 * xx + 3 * yy), 0.2 * np.cos(5 * yy), np.ones_like(xx)], -1)
    n3 = n3[None] + 0.05 * rng.normal(size=(n, s, s, 3))
    n3 /= np.linalg.norm(n3, axis=-1, keepdims=True)
    mask = np.ones((n, s, s, 1))
    mask[1, :, : s // 4] = 0.0  # a garment border in the second patch
    return jnp.asarray((n3 + 1) / 2 * mask, jnp.float32), np.int32([0, 2])


def test_widened_network_computes_the_same_output(new_width=4):
    x, mat = _patches()
    origins = jnp.int32([[0, 0], [5, 9]])
    narrow = CFG.module(3)
    old = _trained_like(unet.init_params(narrow, jax.random.key(0, impl="rbg"), S),
                        1)
    wide = dataclasses.replace(CFG, width=new_width).module(3)
    fresh = unet.init_params(wide, jax.random.key(2, impl="rbg"), S)
    params = widen_params(old, fresh)
    y_old = jax.jit(narrow.apply)({"params": old}, x, mat, origins)
    wide_apply = jax.jit(wide.apply)
    y_new = wide_apply({"params": params}, x, mat, origins)
    assert float(jnp.std(y_old - x)) > 1e-3  # the network does something
    np.testing.assert_allclose(np.asarray(y_new), np.asarray(y_old), atol=2e-5)
    # and the fresh wide network alone is a different function (the test can fail)
    y_fresh = wide_apply({"params": _trained_like(fresh, 3)}, x, mat, origins)
    assert float(jnp.max(jnp.abs(y_fresh - y_old))) > 1e-2


def test_new_channels_receive_gradient():
    x, mat = _patches()
    narrow, wide = CFG.module(3), dataclasses.replace(CFG, width=4).module(3)
    old = _trained_like(unet.init_params(narrow, jax.random.key(0, impl="rbg"), S),
                        1)
    params = widen_params(old, unet.init_params(wide, jax.random.key(2, impl="rbg"), S))

    def loss(p):
        return jnp.sum(jnp.square(wide.apply({"params": p}, x, mat) - 0.5))

    grad = jax.jit(jax.grad(loss))  # eager: ~5x the CPU
    g = grad(params)
    # the output conv's weights from the new channels start at zero and must be able to move
    assert float(jnp.max(jnp.abs(g["out"]["kernel"][:, :, 2:, :]))) > 0.0
    # the new channels' own weights get no gradient while those are zero (as with a
    # zero-initialized output conv) ...
    assert float(jnp.max(jnp.abs(g["enc1"]["kernel"][..., 2:]))) == 0.0
    # ... and do after one step
    stepped = jax.tree_util.tree_map(lambda p, d: p - 1e-3 * d, params, g)
    g2 = grad(stepped)
    assert float(jnp.max(jnp.abs(g2["enc1"]["kernel"][..., 2:]))) > 0.0


def test_widen_rejects_shrinking_and_other_trees():
    small = unet.init_params(CFG.module(3), jax.random.key(0, impl="rbg"), S)
    big = unet.init_params(dataclasses.replace(CFG, width=4).module(3),
                           jax.random.key(0, impl="rbg"), S)
    with pytest.raises(ValueError, match="cannot widen"):
        widen_params(big, small)
    with pytest.raises(ValueError, match="different leaves"):
        widen_params({k: v for k, v in small.items() if k != "out"}, big)
