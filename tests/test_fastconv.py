"""Tests for wrinkle_jax.nn.fastconv and the U-Net's fast forms (`CINUNet(conv_impl=...)`).

Tolerances (see the fastconv module docstring):
  * float32 im2col forms vs XLA: the same sums in another order, so they agree to float32
    rounding -- 1e-5 relative to the output's RMS (`F32_ATOL` on O(1) data). This is what proves
    the index arithmetic (patch order, sub-pixel phases, flips, padding adjoints) exact.
  * bfloat16 forms, one layer (value and gradients): RMS error <= `BF16_RTOL` (1e-2, ~3x the
    expected 3.2e-3) and max error <= `BF16_MAX_RTOL` (5e-2), both relative to the reference RMS.
  * the whole U-Net in bfloat16: nine layers, each with ~2.5e-3 relative error; CIN
    re-normalizes in between, so the errors do not compound (measured 2.4e-3 RMS, 1.5e-2 max,
    4.6e-3 on the parameter gradient's norm) -> the same one-layer bounds, and 2e-2 on the
    relative norm of the parameter gradient.
  * fused instance norm: one-pass variance, ~1e-6 * (mean / std)^2 relative (8e-4 measured at
    |mean| / std = 30); bound 1e-5 * (1 + (mean / std)^2).
"""

from __future__ import annotations

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from wrinkle_jax.nn import fastconv, torch_interop, unet

F32_RTOL = 1e-5


def _rel_rms(a, ref):
    a, ref = np.asarray(a, np.float64), np.asarray(ref, np.float64)
    return np.sqrt(np.mean((a - ref) ** 2) / np.mean(ref**2))


def _rel_max(a, ref):
    a, ref = np.asarray(a, np.float64), np.asarray(ref, np.float64)
    return np.max(np.abs(a - ref)) / np.sqrt(np.mean(ref**2))


def _check(a, ref, dtype):
    if dtype == jnp.float32:
        assert _rel_max(a, ref) < F32_RTOL
    else:
        assert _rel_rms(a, ref) < fastconv.BF16_RTOL
        assert _rel_max(a, ref) < fastconv.BF16_MAX_RTOL


def _xla_conv3x3(x, k, padding):
    if padding == "REFLECT":
        x = jnp.pad(x, ((0, 0), (1, 1), (1, 1), (0, 0)), mode="reflect")
        pads = ((0, 0), (0, 0))
    else:
        pads = ((1, 1), (1, 1))
    return jax.lax.conv_general_dilated(x, k, (1, 1), pads, dimension_numbers=("NHWC", "HWIO",
                                                                              "NHWC"),
                                        precision=jax.lax.Precision.HIGHEST)


def _xla_deconv(x, k):
    return nn.ConvTranspose(k.shape[-1], (4, 4), strides=(2, 2), padding=((2, 2), (2, 2)),
                            use_bias=False, precision=jax.lax.Precision.HIGHEST).apply(
        {"params": {"kernel": k}}, x)


def _np_deconv_torch(x, w):
    """PyTorch ConvTranspose2d(k=4, s=2, p=1) by its scatter definition; x (H, W, I), w (I, O,
    4, 4) in PyTorch layout."""
    h, wd, _ = x.shape
    full = np.zeros((2 * h + 2, 2 * wd + 2, w.shape[1]))
    for a in range(4):
        for c in range(4):
            full[a:a + 2 * h - 1:2, c:c + 2 * wd - 1:2] += x @ w[:, :, a, c]
    return full[1:-1, 1:-1]


def _normal(seed, shape, scale=1.0, offset=0.0):
    """Standard normal test data, float32. NumPy's generator, not jax.random: each new shape
    of an op-by-op `jax.random.normal` compiles its own threefry program (~1 s of CPU each)."""
    rng = np.random.default_rng(seed)
    return jnp.asarray(offset + scale * rng.standard_normal(shape), jnp.float32)


def _grads(f, *args):
    """f(*args) and the gradients w.r.t. all args of sum(f(*args) * cotangent), in one jit;
    the cotangent is a fixed standard normal draw of the output's shape."""
    cotangent = _normal(7, jax.eval_shape(f, *args).shape)

    @jax.jit
    def run(ct, *a):
        y, vjp = jax.vjp(f, *a)
        return y, vjp(ct)

    return run(cotangent, *args)


DTYPES = [jnp.float32, jnp.bfloat16]


@pytest.mark.parametrize("c_in,c_out,padding", [
    (5, 7, "ZERO"),       # patches ("input-side") form
    (16, 3, "ZERO"),      # few outputs: dot first, shifted partial sums ("output-side") form
    (3, 32, "ZERO"),      # few inputs (the U-Net's first conv): channel-major kernel gradient
    (5, 7, "REFLECT"),
    (3, 32, "REFLECT"),   # VGG's first conv: output-side input gradient
])
def test_conv3x3_matches_xla(c_in, c_out, padding):
    x = _normal(c_in * 10 + c_out, (2, 6, 10, c_in))
    k = _normal(c_in * 10 + c_out + 1, (3, 3, c_in, c_out), 1 / np.sqrt(9 * c_in))
    ref, (rx, rk) = _grads(lambda x, k: _xla_conv3x3(x, k, padding), x, k)
    for dtype in DTYPES:
        y, (gx, gk) = _grads(lambda x, k, dtype=dtype: fastconv.conv3x3(
            x, k, compute_dtype=dtype, padding=padding), x, k)
        assert y.shape == ref.shape and y.dtype == jnp.float32
        assert gx.dtype == x.dtype and gk.dtype == k.dtype
        for a, b in ((y, ref), (gx, rx), (gk, rk)):
            _check(a, b, dtype)


def test_conv3x3_bias_and_docstring_values():
    x = jnp.ones((1, 8, 8, 4))
    k = jnp.ones((3, 3, 4, 5)) / 36
    y = jax.jit(lambda x, k: fastconv.conv3x3(x, k, jnp.arange(5.0)))(x, k)
    assert y.shape == (1, 8, 8, 5)
    np.testing.assert_allclose(y[0, 4, 4], 1.0 + np.arange(5), rtol=1e-2)
    np.testing.assert_allclose(y[0, 0, 0], 4 / 9 + np.arange(5), rtol=1e-2)


@pytest.mark.parametrize("c_in,c_out", [(5, 7), (8, 3)])
def test_conv_transpose_matches_flax_and_torch_semantics(c_in, c_out):
    x = _normal(c_in + c_out, (2, 5, 6, c_in))
    k = _normal(c_in + c_out + 100, (4, 4, c_in, c_out), 1 / np.sqrt(4 * c_in))
    ref, (rx, rk) = _grads(_xla_deconv, x, k)
    # PyTorch semantics: the U-Net stores the torch weight flipped, as (kH, kW, in, out).
    w_torch = np.asarray(k)[::-1, ::-1].transpose(2, 3, 0, 1).astype(np.float64)
    torch_ref = _np_deconv_torch(np.asarray(x[1], np.float64), w_torch)
    for dtype in DTYPES:
        y, (gx, gk) = _grads(lambda x, k, dtype=dtype: fastconv.conv_transpose4x4s2(
            x, k, compute_dtype=dtype), x, k)
        assert y.shape == (2, 10, 12, c_out)
        for a, b in ((y, ref), (gx, rx), (gk, rk), (y[1], torch_ref)):
            _check(a, b, dtype)


def _plain_instance_norm(x, scale, shift, eps=1e-5):
    mean = jnp.mean(x, axis=(1, 2), keepdims=True)
    var = jnp.mean(jnp.square(x - mean), axis=(1, 2), keepdims=True)
    return (x - mean) * jax.lax.rsqrt(var + eps) * scale[:, None, None] + shift[:, None, None]


@pytest.mark.parametrize("offset", [0.0, 30.0])  # |mean| / std up to 30
def test_instance_norm_matches_two_pass(offset):
    x = _normal(3, (3, 8, 8, 5), offset=offset)
    scale = _normal(4, (3, 5), 0.3, 1.0)
    shift = _normal(5, (3, 5), 0.3)
    y, grads = _grads(lambda *a: jax.nn.relu(fastconv.instance_norm(*a)), x, scale, shift)
    ref, rgrads = _grads(lambda *a: jax.nn.relu(_plain_instance_norm(*a)), x, scale, shift)
    y_relu = jax.jit(lambda *a: fastconv.instance_norm(*a, relu=True))(x, scale, shift)
    np.testing.assert_array_equal(y_relu, y)
    # One-pass variance: ~1e-6 * (mean / std)^2 relative (module docstring).
    tol = F32_RTOL * (1 + offset**2)
    assert _rel_max(y, ref) < tol
    for a, b in zip(grads, rgrads, strict=True):
        assert _rel_max(a, b) < 10 * tol


def test_instance_norm_constant_patch_is_finite():
    x = jnp.full((2, 8, 8, 3), 0.7)
    scale, shift = jnp.ones((2, 3)), jnp.full((2, 3), 0.25)
    y, grads = _grads(lambda *a: fastconv.instance_norm(*a), x, scale, shift)
    np.testing.assert_allclose(y, 0.25, atol=1e-3)
    assert all(np.isfinite(np.asarray(g)).all() for g in grads)


def test_bad_arguments():
    with pytest.raises(ValueError, match="padding"):
        fastconv.conv3x3(jnp.zeros((1, 4, 4, 2)), jnp.zeros((3, 3, 2, 2)), padding="SAME")
    with pytest.raises(ValueError, match="do not match"):
        fastconv.conv3x3(jnp.zeros((1, 4, 4, 2)), jnp.zeros((3, 3, 3, 2)))
    with pytest.raises(ValueError, match="do not"):
        fastconv.conv_transpose4x4s2(jnp.zeros((1, 4, 4, 2)), jnp.zeros((3, 3, 2, 2)))
    with pytest.raises(ValueError, match="float32 or bfloat16"):
        fastconv.conv3x3(jnp.zeros((1, 4, 4, 2)), jnp.zeros((3, 3, 2, 2)),
                         compute_dtype=jnp.float16)


def test_flop_counts():
    # Width 64, 128 x 128: the 5.68 GFLOP per patch of the benchmark.
    w = 64
    enc = sum(fastconv.conv3x3_flops(128 >> i, 128 >> i, c, o)
              for i, (c, o) in enumerate([(3, w), (w, 2 * w), (2 * w, 4 * w), (4 * w, 8 * w)]))
    dec = sum(fastconv.conv_transpose4x4s2_flops(8 << i, 8 << i, c, o)
              for i, (c, o) in enumerate([(8 * w, 8 * w), (8 * w, 4 * w), (4 * w, 2 * w),
                                          (2 * w, w)]))
    total = enc + dec + fastconv.conv3x3_flops(128, 128, w, 3)
    assert abs(total / 1e9 - 5.68) < 0.01


# ---------------------------------------------------------------------------- the U-Net


@pytest.fixture(scope="module")
def net():
    model = unet.UNetConfig(width=4, input_norm="imagenet", residual=True).module(3)
    params = unet.init_params(model, jax.random.key(0, impl="rbg"), patch_size=32)
    for i, name in enumerate(("cin1", "cin2", "cin3", "cin4")):
        c = params[name]["scale"].shape[1]
        params[name] = {"scale": _normal(10 + i, (3, c), 0.5, 1.0),
                        "shift": _normal(20 + i, (3, c), 0.5)}
    x = jnp.asarray(np.random.default_rng(2).uniform(size=(2, 32, 48, 3)), jnp.float32)
    m = jnp.array([0, 2])
    ref = jax.jit(model.apply)({"params": params}, x, m)
    ref_grad = jax.jit(jax.grad(_sq_loss(model, x, m)))(params)
    return model, params, x, m, ref, ref_grad


def _sq_loss(model, x, m):
    return lambda p: jnp.sum(model.apply({"params": p}, x, m) ** 2)


def _flat(tree):
    return np.concatenate([np.ravel(a) for a in jax.tree_util.tree_leaves(tree)])


def test_fast_forms_share_parameters():
    """Same names, shapes and initial values (so checkpoints and torch conversion carry over);
    "im2col_f32" builds the identical modules."""
    model = unet.CINUNet(unet.UNetConfig(width=2), num_materials=2)
    key = jax.random.key(5, impl="rbg")
    ref = unet.init_params(model, key, patch_size=16)
    got = unet.init_params(model.clone(conv_impl="im2col_bf16"), key, patch_size=16)
    assert jax.tree_util.tree_structure(got) == jax.tree_util.tree_structure(ref)
    for a, b in zip(jax.tree_util.tree_leaves(got), jax.tree_util.tree_leaves(ref), strict=True):
        np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("impl", ["im2col_f32", "im2col_bf16"])
def test_unet_fast_forms_match_plain(net, impl):
    model, params, x, m, ref, ref_grad = net
    fast = model.clone(conv_impl=impl)

    def loss(p):
        y = fast.apply({"params": p}, x, m)
        return jnp.sum(y**2), y

    (_, y), g = jax.jit(jax.value_and_grad(loss, has_aux=True))(params)
    grad_err = np.linalg.norm(_flat(g) - _flat(ref_grad)) / np.linalg.norm(_flat(ref_grad))
    assert y.shape == ref.shape and y.dtype == jnp.float32
    if impl == "im2col_f32":
        assert _rel_max(y, ref) < 1e-5
        assert grad_err < 1e-4
    else:
        assert _rel_rms(y, ref) < fastconv.BF16_RTOL
        assert _rel_max(y, ref) < fastconv.BF16_MAX_RTOL
        assert grad_err < 2e-2


def test_unet_fast_form_with_torch_weights():
    """The bf16 form on converted PyTorch weights stays within tolerance of the float32 form,
    which test_unet verifies against the NumPy reference of the authors' forward pass."""
    from test_unet import _random_state_dict  # tests/ is on sys.path

    params, config = torch_interop.from_torch_state_dict(_random_state_dict(width=4, materials=2))
    x = np.random.default_rng(1).uniform(size=(2, 32, 32, 3)).astype(np.float32)
    m = jnp.array([0, 1])
    ref = jax.jit(unet.CINUNet(**config).apply)({"params": params}, x, m)
    fast = jax.jit(unet.CINUNet(**config, conv_impl="im2col_bf16").apply)({"params": params}, x, m)
    exact = jax.jit(unet.CINUNet(**config, conv_impl="im2col_f32").apply)({"params": params}, x, m)
    assert _rel_max(exact, ref) < 1e-5
    assert _rel_rms(fast, ref) < fastconv.BF16_RTOL
    assert _rel_max(fast, ref) < fastconv.BF16_MAX_RTOL


def test_cin_fused_matches_plain():
    x = _normal(4, (2, 8, 8, 6))
    m = jnp.array([1, 0])
    plain = unet.CIN(num_materials=2)
    params = plain.init(jax.random.key(0, impl="rbg"), x, m)
    params = jax.tree_util.tree_map(lambda a: a + 0.1 * jnp.arange(a.size).reshape(a.shape),
                                    params)
    y = jax.jit(unet.CIN(num_materials=2, fused=True).apply)(params, x, m)
    ref = jax.jit(plain.apply)(params, x, m)
    assert _rel_max(y, ref) < 1e-5


def test_unknown_conv_impl(net):
    model, params, x, m = net[:4]
    with pytest.raises(ValueError, match="conv_impl"):
        model.clone(conv_impl="cuda").apply({"params": params}, x, m)
