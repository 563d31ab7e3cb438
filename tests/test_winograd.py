"""Tests for wrinkle_jax.nn.winograd and the U-Net's "winograd_bf16" form.

Tolerances as in test_fastconv: float32 Winograd against XLA to float32 rounding (the
transforms are exact in exact arithmetic, so this proves the tiling, padding and phase
arithmetic); one bfloat16 layer within `fastconv.BF16_RTOL` / `BF16_MAX_RTOL` of the float32
result (measured ~3.5e-3 RMS).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from test_fastconv import _rel_max, _rel_rms, _xla_conv3x3, _xla_deconv  # tests/ on sys.path

from wrinkle_jax.nn import fastconv, unet, winograd

F32_RTOL = 1e-5


def _normal(seed, shape, scale=1.0):
    return jnp.asarray(np.random.default_rng(seed).normal(0, scale, shape), jnp.float32)


@pytest.mark.parametrize("m, r, points", [(2, 3, (0, 1, -1)), (3, 2, (0, 1, -1)),
                                          (4, 3, (0, 1, -1, 2, -2)), (2, 2, (0, 0.5))])
def test_toom_cook_is_a_correlation(m, r, points):
    at, g, bt = winograd.toom_cook(m, r, points)
    assert at.shape == (m, m + r - 1) and g.shape == (m + r - 1, r) and bt.shape == (m + r - 1,) * 2
    rng = np.random.default_rng(m * 10 + r)
    for _ in range(3):
        d, k = rng.normal(size=m + r - 1), rng.normal(size=r)
        direct = np.array([d[i:i + r] @ k for i in range(m)])
        np.testing.assert_allclose(at @ ((g @ k) * (bt @ d)), direct, atol=1e-12)


def test_toom_cook_rejects_bad_points():
    with pytest.raises(ValueError, match="distinct"):
        winograd.toom_cook(2, 3, (0, 1, 1))
    with pytest.raises(ValueError, match="needs 3"):
        winograd.toom_cook(2, 3, (0, 1))


@pytest.mark.parametrize("shape", [(2, 8, 8, 5), (1, 7, 10, 3), (2, 1, 3, 4), (1, 16, 5, 2)])
@pytest.mark.parametrize("padding", ["ZERO", "REFLECT"])
def test_conv3x3_float32_matches_xla(shape, padding):
    if padding == "REFLECT" and min(shape[1:3]) < 2:
        pytest.skip("reflection padding needs 2 texels")
    x = _normal(1, shape)
    k = _normal(2, (3, 3, shape[-1], 6), 0.3)
    b = _normal(3, (6,))
    got = jax.jit(lambda x, k, b: winograd.conv3x3(x, k, b, compute_dtype=jnp.float32,
                                                   padding=padding))(x, k, b)
    ref = _xla_conv3x3(x, k, padding) + b
    assert got.shape == ref.shape and got.dtype == jnp.float32
    assert _rel_max(got, ref) < F32_RTOL


@pytest.mark.parametrize("shape", [(2, 8, 8, 5), (1, 7, 10, 3), (2, 1, 3, 4), (1, 5, 16, 2)])
def test_conv_transpose_float32_matches_xla(shape):
    x = _normal(4, shape)
    k = _normal(5, (4, 4, shape[-1], 3), 0.3)
    got = jax.jit(lambda x, k: winograd.conv_transpose4x4s2(x, k, compute_dtype=jnp.float32))(
        x, k)
    ref = _xla_deconv(x, k)
    assert got.shape == (shape[0], 2 * shape[1], 2 * shape[2], 3)
    assert _rel_max(got, ref) < F32_RTOL


def test_bfloat16_layers_within_the_one_layer_bounds():
    x = jax.nn.relu(_normal(6, (2, 16, 16, 64)))
    k3, k4 = _normal(7, (3, 3, 64, 64), 0.05), _normal(8, (4, 4, 64, 32), 0.05)
    for fn, k in ((winograd.conv3x3, k3), (winograd.conv_transpose4x4s2, k4)):
        fast = jax.jit(fn)(x, k)
        exact = jax.jit(lambda x, k, fn=fn: fn(x, k, compute_dtype=jnp.float32))(x, k)
        err = _rel_rms(fast, exact)
        assert 1e-4 < err < fastconv.BF16_RTOL  # rounded, but within the bound
        assert _rel_max(fast, exact) < fastconv.BF16_MAX_RTOL


def test_docstring_example():
    x = jnp.ones((1, 8, 8, 4))
    y = jax.jit(winograd.conv3x3)(x, jnp.ones((3, 3, 4, 5)) / 36)
    assert y.shape == (1, 8, 8, 5)
    assert round(float(y[0, 4, 4, 0]), 2) == 1.0 and round(float(y[0, 0, 0, 0]), 2) == 0.44


def test_gradients_match_xla():
    """float32: the Winograd input gradients and the im2col kernel gradients agree with XLA's
    to float32 rounding (odd sizes: partial tiles in the backward too)."""
    x = _normal(9, (2, 6, 7, 3))
    k3, k4 = _normal(10, (3, 3, 3, 4), 0.3), _normal(11, (4, 4, 3, 4), 0.3)
    w = _normal(12, (2, 12, 14, 4))
    cases = [(lambda x, k, p=p: winograd.conv3x3(x, k, compute_dtype=jnp.float32, padding=p),
              lambda x, k, p=p: _xla_conv3x3(x, k, p), k3, _normal(13, (2, 6, 7, 4)))
             for p in ("ZERO", "REFLECT")]
    cases.append((lambda x, k: winograd.conv_transpose4x4s2(x, k, compute_dtype=jnp.float32),
                  _xla_deconv, k4, w))
    for fast, ref, k, wt in cases:
        # Jitted: op by op, the six gradients compiled ~300 one-op programs (14 s in the suite).
        g = jax.jit(jax.grad(lambda x, k, f=fast, wt=wt: jnp.sum(wt * f(x, k)), (0, 1)))(x, k)
        gr = jax.jit(jax.grad(lambda x, k, f=ref, wt=wt: jnp.sum(wt * f(x, k)), (0, 1)))(x, k)
        for a, b in zip(g, gr, strict=True):
            assert _rel_max(a, b) < 1e-4


def test_rule():
    assert winograd.use_winograd(64, 128, 16)
    assert not winograd.use_winograd(32, 64, 32)   # too few channels
    assert not winograd.use_winograd(512, 512, 8)  # too few texels


def _small_net():
    model = unet.UNetConfig(width=4, residual=True).module(3)
    params = unet.init_params(model, jax.random.key(0, impl="rbg"), patch_size=32)
    x = jnp.asarray(np.random.default_rng(2).uniform(size=(2, 32, 32, 3)), jnp.float32)
    return model, params, x, jnp.array([0, 2])


def test_unet_winograd_form(monkeypatch):
    """Below the rule's thresholds the form is the im2col form, bit for bit; with the
    thresholds lowered to 16 channels the deeper layers run by Winograd (one 3x3 conv and
    both transposed convs; the rest by im2col, so the forms meet inside one network), the
    output changes by rounding only, and output and parameter gradient stay within the
    bfloat16 bounds of the exact form (the gradient's as for im2col_bf16, test_fastconv).
    (Every layer by Winograd compiled the gradient in ~20 s of CPU, these three in ~9.)"""
    model, params, x, m = _small_net()

    def run(impl):
        return jax.jit(model.clone(conv_impl=impl).apply)({"params": params}, x, m)

    def value_and_grad(impl):  # output and the parameter gradient of a training-like loss
        def loss(p):
            y = model.clone(conv_impl=impl).apply({"params": p}, x, m)
            return jnp.sum(y**2), y

        (_, y), g = jax.jit(jax.value_and_grad(loss, has_aux=True))(params)
        return y, np.concatenate([np.ravel(a) for a in jax.tree_util.tree_leaves(g)])

    im2col = run("im2col_bf16")
    np.testing.assert_array_equal(run("winograd_bf16"), im2col)  # width 4: no layer qualifies
    exact, g_exact = value_and_grad("im2col_f32")
    monkeypatch.setattr(winograd, "MIN_CHANNELS", 16)
    monkeypatch.setattr(winograd, "MIN_SIDE", 1)
    calls = []

    def spy(name):
        real = getattr(winograd, name)

        def layer(x, *a, **k):
            calls.append((name, x.shape[-1]))
            return real(x, *a, **k)
        return layer

    for name in ("conv3x3", "conv_transpose4x4s2"):
        monkeypatch.setattr(winograd, name, spy(name))
    wino, g_wino = value_and_grad("winograd_bf16")
    assert sorted(calls) == [("conv3x3", 16), ("conv_transpose4x4s2", 32),
                             ("conv_transpose4x4s2", 32)]
    assert np.any(np.asarray(wino) != np.asarray(im2col))
    assert _rel_rms(wino, exact) < fastconv.BF16_RTOL
    assert _rel_max(wino, exact) < fastconv.BF16_MAX_RTOL
    assert np.linalg.norm(g_wino - g_exact) / np.linalg.norm(g_exact) < 2e-2
