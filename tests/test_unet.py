"""Tests for wrinkle_jax.nn.unet: architecture, CIN, and the PyTorch interop against an
independent NumPy implementation of the authors' forward pass."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from torch_checkpoint_writer import save_state_dict  # tests/ is on sys.path

from wrinkle_jax import evaluation
from wrinkle_jax.nn import torch_interop, unet


def test_width64_parameter_count():
    model = unet.CINUNet(unet.UNetConfig(width=64), num_materials=5)
    shapes = jax.eval_shape(lambda: unet.init_params(model, jax.random.PRNGKey(0)))
    assert unet.count_params(shapes) == 8_510_083


@pytest.fixture(scope="module")
def small():
    model = unet.CINUNet(unet.UNetConfig(width=4, input_norm="none"), num_materials=3)
    # rbg keys: threefry draws compile slowly on CPU (see unet.init_params).
    params = unet.init_params(model, jax.random.key(0, impl="rbg"), patch_size=32)
    # Give the CIN tables distinct per-material values (init is ones/zeros for all materials).
    # NumPy draws: each new shape of an op-by-op jax.random draw compiles its own program.
    rng = np.random.default_rng(1)
    for name in ("cin1", "cin2", "cin3", "cin4"):
        c = params[name]["scale"].shape[1]
        params[name] = {"scale": jnp.asarray(1 + 0.5 * rng.standard_normal((3, c)), jnp.float32),
                        "shift": jnp.asarray(0.5 * rng.standard_normal((3, c)), jnp.float32)}
    return model, params


def test_output_shape_and_materials_matter(small):
    model, params = small
    x = jnp.asarray(np.random.default_rng(2).uniform(size=(2, 32, 32, 3)), jnp.float32)
    apply = jax.jit(model.apply)
    y0 = apply({"params": params}, x, jnp.array([0, 0]))
    y1 = apply({"params": params}, x, jnp.array([1, 1]))
    assert y0.shape == (2, 32, 32, 3) and y0.dtype == jnp.float32
    assert float(jnp.abs(y0 - y1).max()) > 1e-3
    # One batch may mix materials: each sample uses its own row of the CIN tables.
    mixed = apply({"params": params}, x, jnp.array([0, 1]))
    np.testing.assert_allclose(mixed[0], y0[0], atol=1e-5)
    np.testing.assert_allclose(mixed[1], y1[1], atol=1e-5)


def test_constant_patch_is_finite(small):
    model, params = small
    x = jnp.full((1, 32, 32, 3), 0.5)

    def f(p):
        y = model.apply({"params": p}, x, jnp.array([2]))
        return jnp.sum(y**2), y

    # Output and gradient from one jitted program (op-by-op dispatch of the U-Net compiles
    # every primitive separately).
    (_, y), g = jax.jit(jax.value_and_grad(f, has_aux=True))(params)
    assert np.isfinite(np.asarray(y)).all()
    assert all(np.isfinite(np.asarray(v)).all() for v in jax.tree_util.tree_leaves(g))


def test_residual_adds_input(small):
    _, params = small
    x = jnp.asarray(np.random.default_rng(3).uniform(size=(1, 32, 32, 3)), jnp.float32)
    plain = unet.CINUNet(unet.UNetConfig(width=4, input_norm="none"), num_materials=3)
    res = unet.CINUNet(unet.UNetConfig(width=4, input_norm="none", residual=True), num_materials=3)
    m = jnp.array([1])
    # Both networks in one program (op by op, each primitive of a U-Net compiles on its own).
    both = jax.jit(lambda p: (res.apply({"params": p}, x, m), plain.apply({"params": p}, x, m)))
    out_res, out_plain = both(params)
    np.testing.assert_allclose(out_res, x + out_plain, atol=1e-6)


def test_rejects_bad_patch_size(small):
    model, params = small
    with pytest.raises(ValueError, match="divisible by 16"):
        model.apply({"params": params}, jnp.zeros((1, 30, 30, 3)), jnp.array([0]))


def test_max_pool2_values_and_gradient_shared_at_ties():
    rng = np.random.default_rng(3)
    x = rng.standard_normal((2, 6, 8, 3)).astype(np.float32)
    x[0, 0:2, 0:2, 0] = 0.5                      # a 4-way tie
    x[1, 2, 4:6, 1] = x[1, 3, 4:6, 1].max() + 1  # a 2-way tie in the top row
    x = jnp.asarray(x)
    np.testing.assert_array_equal(unet._max_pool2(x),
                                  jax.lax.reduce_window(x, -jnp.inf, jax.lax.max,
                                                        (1, 2, 2, 1), (1, 2, 2, 1), "VALID"))
    g = jnp.asarray(rng.standard_normal((2, 3, 4, 3)), jnp.float32)
    got = jax.grad(lambda v: jnp.sum(unet._max_pool2(v) * g))(x)
    # jnp.max's gradient (shared equally among tied maxima) of the reshape-and-reduce form.
    want = jax.grad(lambda v: jnp.sum(v.reshape(2, 3, 2, 4, 2, 3).max(axis=(2, 4)) * g))(x)
    np.testing.assert_allclose(got, want, rtol=1e-6, atol=0)
    assert float(got[0, 0, 0, 0]) == pytest.approx(float(g[0, 0, 0, 0]) / 4)
    np.testing.assert_allclose(got[1, 2, 4:6, 1], g[1, 1, 2, 1] / 2, rtol=1e-6)


# ---------------------------------------------------------------- NumPy reference


def _np_conv(x, w, b, pad):
    """x (H, W, I), torch weight w (O, I, kh, kw), zero padding -> (H', W', O)."""
    o, i, kh, kw = w.shape
    xp = np.pad(x, ((pad, pad), (pad, pad), (0, 0)))
    h, wd = xp.shape[0] - kh + 1, xp.shape[1] - kw + 1
    out = np.zeros((h, wd, o))
    for a in range(kh):
        for c in range(kw):
            out += xp[a:a + h, c:c + wd] @ w[:, :, a, c].T
    return out + b


def _np_deconv(x, w, b, stride=2, pad=1):
    """PyTorch ConvTranspose2d by its scatter definition; w (I, O, kh, kw)."""
    h, wd, _ = x.shape
    _, o, kh, kw = w.shape
    full = np.zeros(((h - 1) * stride + kh, (wd - 1) * stride + kw, o))
    for a in range(kh):
        for c in range(kw):
            full[a:a + (h - 1) * stride + 1:stride, c:c + (wd - 1) * stride + 1:stride] += (
                x @ w[:, :, a, c])
    return full[pad:full.shape[0] - pad, pad:full.shape[1] - pad] + b


def _np_instance_norm(x, gamma, beta, eps=1e-5):
    mean = x.mean((0, 1))
    var = x.var((0, 1))
    return (x - mean) / np.sqrt(var + eps) * gamma + beta


def _np_maxpool(x):
    h, w, c = x.shape
    return x.reshape(h // 2, 2, w // 2, 2, c).max((1, 3))


def _np_forward(sd, x, k):
    """The authors' forward pass for one image x (H, W, 3) in [0, 1] and material k."""
    h = (x - np.array(unet.IMAGENET_MEAN)) / np.array(unet.IMAGENET_STD)
    skips = []
    for level in range(1, 5):
        h = np.maximum(_np_conv(h, sd[f"E{level}_Conv2d.weight"], sd[f"E{level}_Conv2d.bias"], 1),
                       0)
        skips.append(h)
        h = _np_maxpool(h)
    for level in range(1, 5):
        h = _np_deconv(h, sd[f"D{level}_Deconv2d.weight"], sd[f"D{level}_Deconv2d.bias"])
        h = h + skips[4 - level]
        h = _np_instance_norm(h, sd[f"D{level}_CIN.inns.{k}.weight"],
                              sd[f"D{level}_CIN.inns.{k}.bias"])
        h = np.maximum(h, 0)
    return _np_conv(h, sd["out_Conv2d.weight"], sd["out_Conv2d.bias"], 1)


def _random_state_dict(width=4, materials=2, seed=0):
    rng = np.random.default_rng(seed)
    sd = {}
    chans = [3, width, 2 * width, 4 * width, 8 * width]
    for level in range(1, 5):
        i, o = chans[level - 1], chans[level]
        sd[f"E{level}_Conv2d.weight"] = rng.normal(0, (2 / (9 * i)) ** 0.5, (o, i, 3, 3))
        sd[f"E{level}_Conv2d.bias"] = rng.normal(0, 0.1, o)
    dec = [8 * width, 8 * width, 4 * width, 2 * width, width]
    for level in range(1, 5):
        i, o = dec[level - 1], dec[level]
        sd[f"D{level}_Deconv2d.weight"] = rng.normal(0, (2 / (4 * i)) ** 0.5, (i, o, 4, 4))
        sd[f"D{level}_Deconv2d.bias"] = rng.normal(0, 0.1, o)
        for k in range(materials):
            sd[f"D{level}_CIN.inns.{k}.weight"] = rng.normal(1, 0.3, o)
            sd[f"D{level}_CIN.inns.{k}.bias"] = rng.normal(0, 0.3, o)
    sd["out_Conv2d.weight"] = rng.normal(0, 0.1, (3, width, 3, 3))
    sd["out_Conv2d.bias"] = rng.normal(0, 0.1, 3)
    return {k: v.astype(np.float32) for k, v in sd.items()}


def _denormalized(ref):
    """The authors' ImageNet-normalized output as the RGB form: ref * std + mean."""
    return ref * np.array(unet.IMAGENET_STD) + np.array(unet.IMAGENET_MEAN)


def test_torch_state_dict_reproduces_reference_forward():
    sd = _random_state_dict(width=4, materials=2)
    params, kwargs = torch_interop.from_torch_state_dict(sd)
    assert kwargs == dict(num_materials=2, config=unet.UNetConfig(
        width=4, input_norm="imagenet", residual=False, output_norm="imagenet"))
    model = unet.CINUNet(**kwargs)
    raw = unet.CINUNet(num_materials=2, config=dataclasses.replace(kwargs["config"],
                                                                   output_norm="none"))
    x = np.random.default_rng(1).uniform(size=(2, 32, 48, 3)).astype(np.float32)
    y = np.asarray(jax.jit(model.apply)({"params": params}, x, jnp.array([0, 1])))
    y_raw = np.asarray(jax.jit(raw.apply)({"params": params}, x, jnp.array([0, 1])))
    for n, k in ((0, 0), (1, 1)):
        ref = _np_forward({kk: v.astype(np.float64) for kk, v in sd.items()}, x[n], k)
        # The raw network is the authors' forward pass; the converted one de-normalizes it once.
        np.testing.assert_allclose(y_raw[n], ref, rtol=1e-4, atol=1e-4)
        np.testing.assert_allclose(y[n], _denormalized(ref), rtol=1e-4, atol=1e-4)


def test_state_dict_errors():
    sd = _random_state_dict()
    del sd["D3_Deconv2d.bias"]
    with pytest.raises(torch_interop.StateDictError, match="D3_Deconv2d.bias"):
        torch_interop.from_torch_state_dict(sd)


def test_load_torch_checkpoint(tmp_path):
    sd = _random_state_dict(width=4, materials=5, seed=3)
    path = tmp_path / "authors.pth"
    save_state_dict(path, sd, wrap_key="model")
    model, params = torch_interop.load_torch_checkpoint(path)
    assert model.config.width == 4 and model.num_materials == 5
    x = np.random.default_rng(2).uniform(size=(1, 32, 32, 3)).astype(np.float32)
    # Jitted (op by op, each primitive of the U-Net compiles on its own).
    y = np.asarray(jax.jit(model.apply)({"params": params}, x, jnp.array([4])))
    ref = _np_forward({k: v.astype(np.float64) for k, v in sd.items()}, x[0], 4)
    np.testing.assert_allclose(y[0], _denormalized(ref), rtol=1e-4, atol=1e-4)


def _tilted_wrinkles(n=2, size=32, seed=0):
    """RGB-form patches: smooth tilted panels (one facing away from +z) with fine ripples."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:size, 0:size].astype(np.float32)
    out = []
    for k in range(n):
        base = np.array([0.4, 0.3, 0.8 if k % 2 == 0 else -0.8], np.float32)
        rip = 0.15 * np.sin(2 * np.pi * x / 6 + rng.uniform(0, 6))
        nrm = base + np.stack([rip, 0 * rip, 0 * rip], -1)
        nrm /= np.linalg.norm(nrm, axis=-1, keepdims=True)
        out.append((nrm + 1) / 2)
    return jnp.asarray(np.asarray(out, np.float32))


def test_detail_space_model_starts_as_identity_and_keeps_the_large_scale():
    from wrinkle_jax import detail

    model = unet.UNetConfig(width=4, input_norm="none", residual=True, detail_sigma=4.0,
                            residual_highpass=16.0).module(2)
    params = unet.init_params(model, jax.random.key(0, impl="rbg"), patch_size=32)
    params = {**params, "out": jax.tree.map(lambda p: 0.05 * p, params["out"])}
    x = _tilted_wrinkles()
    m = jnp.array([0, 1])
    zero = {**params, "out": jax.tree.map(jnp.zeros_like, params["out"])}
    apply = jax.jit(model.apply)  # one program for both parameter sets
    np.testing.assert_allclose(apply({"params": zero}, x, m), x, atol=2e-5)
    # With a random output layer the network adds detail, and with the residual high-passed
    # at a radius above the detail's the large scale stays the input's: the low-pass of the
    # output agrees with the input's within a few degrees (measured 2.7; 6.0 without it).
    out = apply({"params": params}, x, m)
    assert float(jnp.abs(out - x).max()) > 1e-2
    # Both large scales from one program (op by op, each primitive of the blur compiles on
    # its own); the blur is per patch, so the four patches are blurred in one call.
    large = jax.jit(lambda a: detail.large_scale(a * 2 - 1, jnp.ones((4, 32, 32, 1)), 4.0))
    lin, lout = jnp.split(large(jnp.concatenate([x, out])), 2)
    cos = np.sum(np.asarray(lin) * np.asarray(lout), -1)
    assert np.degrees(np.arccos(np.clip(cos, -1, 1))).max() < 4.0
    np.testing.assert_allclose(np.linalg.norm(np.asarray(out) * 2 - 1, axis=-1), 1.0, atol=1e-5)


# One program per noise shape (op by op, each of the hash's integer and float primitives
# compiles on its own for every shape); the U-Net calls it inside its own jit likewise.
_texel_noise = jax.jit(unet.texel_noise, static_argnums=(1, 2, 3), static_argnames="scale")


def test_texel_noise_is_fixed_to_the_texel():
    a = _texel_noise(jnp.array([[10, 20]]), 16, 16, 3)
    b = _texel_noise(jnp.array([[14, 25], [10, 20]]), 16, 16, 3)
    # The same absolute texel gets the same value in every patch that covers it ...
    np.testing.assert_array_equal(a[0, 4:, 5:], b[0, :12, :11])
    np.testing.assert_array_equal(a[0], b[1])
    # ... and the field is white: zero mean, unit variance, uncorrelated neighbours/channels.
    big = np.asarray(_texel_noise(jnp.array([[0, 0], [512, 77]]), 128, 128, 4))
    assert abs(big.mean()) < 0.02 and abs(big.var() - 1) < 0.03
    assert abs(np.mean(big[:, 1:] * big[:, :-1])) < 0.02
    assert abs(np.mean(big[..., 0] * big[..., 1])) < 0.02
    assert abs(np.mean(big[0] * big[1])) < 0.02


def test_noise_model_depends_on_origins_only_through_the_noise():
    model = unet.UNetConfig(width=4, input_norm="none", residual=True, detail_sigma=4.0,
                            noise_channels=2).module(2)
    params = unet.init_params(model, jax.random.key(1, impl="rbg"), patch_size=32)
    assert params["enc1"]["kernel"].shape == (3, 3, 5, 4)
    x = _tilted_wrinkles(1)
    m = jnp.array([1])
    apply = jax.jit(model.apply)
    o1 = apply({"params": params}, x, m, jnp.array([[0, 0]]))
    o2 = apply({"params": params}, x, m, jnp.array([[0, 0]]))
    o3 = apply({"params": params}, x, m, jnp.array([[64, 3]]))
    np.testing.assert_array_equal(o1, o2)
    assert float(jnp.abs(o1 - o3).max()) > 1e-3
    np.testing.assert_array_equal(apply({"params": params}, x, m), o1)  # None = (0, 0)


def test_lattice_noise_is_smooth_unit_and_fixed_to_the_texel():
    s = 4
    # Overlapping patches (negative origins too: floor division near the layout's border).
    a = _texel_noise(jnp.array([[-6, 10]]), 24, 24, 2, scale=s)
    b = _texel_noise(jnp.array([[-3, 15]]), 24, 24, 2, scale=s)
    np.testing.assert_allclose(a[0, 3:, 5:], b[0, :21, :19], rtol=0, atol=1e-6)
    # On the lattice the field is the white field of lattice coordinates, rescaled to unit
    # variance; between lattice points it is the bilinear interpolation of those values.
    white = np.asarray(_texel_noise(jnp.array([[0, 0]]), 8, 8, 2))
    fine = np.asarray(_texel_noise(jnp.array([[0, 0]]), 29, 29, 2, scale=s))
    t = np.arange(s) / s
    gain = 1.0 / np.mean((1 - t) ** 2 + t**2)
    np.testing.assert_allclose(fine[0, ::s, ::s], white[0] * gain, rtol=1e-5)
    np.testing.assert_allclose(fine[0, 2, 0], 0.5 * (fine[0, 0, 0] + fine[0, 4, 0]), rtol=1e-5)
    big = np.asarray(_texel_noise(jnp.array([[0, 0], [512, 77]]), 128, 128, 4, scale=s))
    assert abs(big.mean()) < 0.05 and abs(big.var() - 1) < 0.06
    # Smooth: neighbours are strongly correlated, and the 2-texel checkerboard is weak.
    assert np.mean(big[:, 1:] * big[:, :-1]) > 0.8
    w = np.asarray(_texel_noise(jnp.array([[0, 0], [512, 77]]), 128, 128, 4))
    assert _checker_std(big) < 0.1 * _checker_std(w)
    with pytest.raises(ValueError, match="scale"):
        _texel_noise(jnp.array([[0, 0]]), 8, 8, 1, scale=0)


def _checker_std(v):
    return np.std(v[:, :-1, :-1] - v[:, 1:, :-1] - v[:, :-1, 1:] + v[:, 1:, 1:])


def test_upsample2_bilinear_interpolates_and_keeps_constants():
    x = jnp.asarray(np.random.default_rng(0).standard_normal((2, 5, 7, 3)), jnp.float32)
    y = np.asarray(unet.upsample2(x, "bilinear"))
    assert y.shape == (2, 10, 14, 3)
    xn = np.asarray(x)
    # Interior texel 2i+1 along rows: 3/4 of row i, 1/4 of row i+1 (half-texel centres).
    np.testing.assert_allclose(y[:, 3, 4], 0.75 * (0.75 * xn[:, 1, 2] + 0.25 * xn[:, 2, 2])
                               + 0.25 * (0.75 * xn[:, 1, 1] + 0.25 * xn[:, 2, 1]), rtol=1e-5)
    np.testing.assert_allclose(unet.upsample2(jnp.ones((1, 4, 4, 2)) * 3.0), 3.0)
    np.testing.assert_array_equal(unet.upsample2(x, "nearest")[:, ::2, ::2], x)
    with pytest.raises(ValueError, match="up-sampling"):
        unet.upsample2(x, "cubic")


def test_resize_decoders_avoid_the_transposed_conv_checkerboard():
    """Untrained networks on a smooth patch: the transposed conv's 2-texel checkerboard is of
    the order of the output's own variation; bilinear resize + conv has several times less."""
    yy, xx = np.mgrid[0:32, 0:32] / 32.0
    n = np.stack([0.3 * np.sin(6 * xx + 2 * yy), 0.2 * np.cos(5 * yy), np.ones_like(xx)], -1)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    x = jnp.asarray((n + 1) / 2, jnp.float32)[None].repeat(2, 0)
    mask = np.ones((2, 32, 32, 1))
    ratio = {}
    for up in ("transpose", "bilinear"):
        model = unet.UNetConfig(width=8, input_norm="none", residual=False,
                                upsample=up).module(2, "im2col_f32")
        params = unet.init_params(model, jax.random.key(0, impl="rbg"), patch_size=32)
        # Jitted: op-by-op dispatch of a U-Net compiles every primitive separately.
        y = jax.jit(model.apply)({"params": params}, x, jnp.array([0, 1]))
        ratio[up] = float(evaluation.checker_rms(y, mask).mean() / np.asarray(y).std())
        if up == "bilinear":
            assert params["dec1"]["kernel"].shape == (3, 3, 64, 64)
            ref = unet.UNetConfig(width=8, input_norm="none", residual=False,
                                  upsample=up).module(2, "xla")
            np.testing.assert_allclose(jax.jit(ref.apply)({"params": params}, x,
                                                          jnp.array([0, 1])), y,
                                       rtol=1e-4, atol=1e-4)
    assert ratio["transpose"] > 0.5
    assert ratio["bilinear"] < 0.25 * ratio["transpose"]
    # Raised while tracing: eval_shape traces init without running it (op by op, the
    # encoder's threefry draws before the check cost ~7 s of CPU).
    with pytest.raises(ValueError, match="upsample"):
        jax.eval_shape(unet.CINUNet(unet.UNetConfig(width=4, upsample="pixelshuffle"),
                                    num_materials=2).init, jax.random.key(0), x,
                       jnp.array([0, 1]))


def test_unet_config_builds_the_module_it_describes():
    """`CINUNet` holds its settings only as a `UNetConfig` (no field of the config repeated as
    a module attribute, so they cannot disagree), and `module` passes the config whole."""
    import dataclasses

    names = [f.name for f in dataclasses.fields(unet.UNetConfig)]
    own = {f.name for f in dataclasses.fields(unet.CINUNet)}
    assert not own & set(names)
    assert unet.CINUNet().config == unet.UNetConfig()
    changed = {"width": 8, "residual": True, "input_norm": "none", "output_norm": "imagenet",
               "residual_base": "unsharp",
               "unsharp_sigma": 3.0, "unsharp_amount": 0.5, "residual_highpass": 5.0,
               "blur_order": 0, "detail_sigma": 4.0, "noise_channels": 2, "noise_scale": 3,
               "upsample": "bilinear", "residual_gain": 0.5}
    assert sorted(changed) == sorted(names)
    assert all(getattr(unet.UNetConfig(), n) != v for n, v in changed.items())
    cfg = unet.UNetConfig(**changed)
    model = cfg.module(num_materials=3, conv_impl="im2col_f32")
    assert model.config is cfg
    assert (model.num_materials, model.conv_impl) == (3, "im2col_f32")
    # The settings reach the computation: the noise channels widen the first conv, the
    # unsharp base adds its per-material gain (initialized to unsharp_amount), the width sets
    # the first level, and the bilinear decoder has 3x3 kernels.
    shapes = jax.eval_shape(lambda: unet.init_params(model, jax.random.key(0, impl="rbg"), 32))
    assert shapes["enc1"]["kernel"].shape == (3, 3, 3 + 2, 8)
    assert shapes["unsharp_amount"].shape == (3,)
    assert shapes["dec4"]["kernel"].shape == (3, 3, 16, 8)
    params = unet.init_params(model, jax.random.key(0, impl="rbg"), 32)
    np.testing.assert_array_equal(params["unsharp_amount"], 0.5)
    # Flat JSON of an outer config: own keys stay, missing settings take the outer default
    # except blur_order (files from before it existed used order 0).
    net, rest = unet.UNetConfig.split_json({"width": 8, "steps": 3}, unet.RECIPE_UNET)
    assert rest == {"steps": 3}
    assert net == dataclasses.replace(unet.RECIPE_UNET, width=8, blur_order=0)


# ---------------------------------------------------------------- converted checkpoints in the
# pipeline: the authors' output is ImageNet-normalized; the converted model de-normalizes it
# exactly once, wherever it runs (its own forward pass, recorded in its config).


def _sheet_pipeline(enh, **config):
    from wrinkle_jax import pipeline, primitives

    g = primitives.grid_sheet(4, 4, size=(0.1, 0.1))
    return pipeline.make_pipeline(g, enh, pipeline.PipelineConfig(lift=False, **config),
                                  compile=False), g


def test_converted_checkpoint_runs_in_the_pipeline_like_the_reference(tmp_path):
    from wrinkle_jax import enhancer, patches, stages

    sd = _random_state_dict(width=4, materials=5, seed=5)
    path = tmp_path / "authors.pth"
    save_state_dict(path, sd, wrap_key="model")
    enh = enhancer.from_torch_checkpoint(path, patch_size=32, texel_size=0.004,
                                         conv_impl="im2col_f32")
    assert enh.config.unet.output_norm == "imagenet" and enh.config.unet.input_norm == "imagenet"
    assert enh.config.materials == enhancer.MATERIALS
    # The setting survives a model file, so a loaded model de-normalizes too (and only once).
    saved = enhancer.save_enhancer(tmp_path / "converted.npz", enh.params, enh.config,
                                   dtype=np.float32)
    loaded = enhancer.load_enhancer(saved, conv_impl="im2col_f32")
    assert loaded.config == enh.config
    pipe, g = _sheet_pipeline(loaded, batch_size=3)
    padded_mask = jnp.asarray(patches.pad_to_patch(pipe.mask, 32)[0])
    _, rgb = stages.bake_stage(pipe.plan, jnp.asarray(g.vertices), padded_mask,
                               padded_shape=pipe.padded_shape)
    tiles = stages.tile_stage(rgb, jnp.asarray(pipe.origins), size=32)
    out = np.asarray(stages.network_stage(enhancer.make_apply(loaded), loaded.params, tiles, 2,
                                          batch_size=3))
    assert pipe.num_patches >= 4 and pipe.num_patches % 3  # a zero-padded last batch
    ref_sd = {k: v.astype(np.float64) for k, v in sd.items()}
    for n in range(pipe.num_patches):
        ref = np.clip(_denormalized(_np_forward(ref_sd, np.asarray(tiles[n], np.float64), 2)),
                      0, 1)
        np.testing.assert_allclose(out[n], ref, atol=2e-4)


def test_converted_checkpoint_denormalizes_to_the_exact_normal(tmp_path):
    # An analytic case: output conv weights 0 and bias (rgb - mean) / std, the ImageNet-
    # normalized RGB form of one tilted normal n. The converted model must output exactly that
    # RGB form on every texel, so the pipeline's N* is n on every garment texel. Without the
    # de-normalization (or with it applied twice) N* would be another direction.
    from wrinkle_jax import enhancer, pipeline

    n = np.array([0.3, -0.2, 0.9])
    n /= np.linalg.norm(n)
    rgb = (n + 1) / 2
    sd = _random_state_dict(width=4, materials=5, seed=6)
    sd["out_Conv2d.weight"] = np.zeros_like(sd["out_Conv2d.weight"])
    sd["out_Conv2d.bias"] = ((rgb - np.array(unet.IMAGENET_MEAN)) /
                             np.array(unet.IMAGENET_STD)).astype(np.float32)
    assert np.abs(sd["out_Conv2d.bias"] - rgb).max() > 0.5  # normalized != RGB form
    path = tmp_path / "authors.pth"
    save_state_dict(path, sd, wrap_key=None)  # a bare state dict
    enh = enhancer.from_torch_checkpoint(path, patch_size=32, texel_size=0.004,
                                         conv_impl="im2col_f32")
    pipe, g = _sheet_pipeline(enh)
    res = pipeline.frame_fn(pipe)(enh.params, jnp.asarray(g.vertices), 1)
    inside = np.asarray(res.mask)[..., 0] > 0
    assert inside.sum() > 100
    np.testing.assert_allclose(np.asarray(res.normal_map)[inside], np.broadcast_to(
        n, (inside.sum(), 3)), atol=1e-5)


def test_converted_checkpoint_material_names(tmp_path):
    from wrinkle_jax import enhancer

    path = tmp_path / "authors.pth"
    save_state_dict(path, _random_state_dict(width=4, materials=3), wrap_key="model")
    with pytest.raises(enhancer.EnhancerError, match="3 materials"):
        enhancer.from_torch_checkpoint(path)
    enh = enhancer.from_torch_checkpoint(path, ("cotton", "leather", "silk"), patch_size=32)
    assert enh.config.material_id("leather") == 1
    with pytest.raises(enhancer.EnhancerError, match="2 material names"):
        enhancer.from_torch_checkpoint(path, ("cotton", "leather"))


@pytest.mark.parametrize("overrides,keys", [
    (dict(residual_base="unsharp", unsharp_sigma=4.0, residual_highpass=2.0),
     {"highpass", "unsharp"}),                                    # the shipped layout
    (dict(residual_base="unsharp", unsharp_sigma=3.0, residual_highpass=3.0), {"highpass"}),
    (dict(residual_base="unsharp", unsharp_sigma=3.0, blur_order=0), {"unsharp"}),
    (dict(residual_highpass=2.0), {"highpass"}),
    (dict(residual=False), set()),
    (dict(detail_sigma=3.0, residual_highpass=4.0), {"detail", "highpass"}),  # issue 21's
    (dict(detail_sigma=3.0, residual=False), {"detail"}),
])
def test_precomputed_blur_weights_give_the_same_output(overrides, keys):
    """`UNetConfig.blur_weights` of the inputs' masks, passed to the network, give the output
    of its in-network blurs (which derive the mask from the input) for every blur layout;
    an empty patch (a batch's zero padding) stays finite."""
    cfg = unet.UNetConfig(width=4, input_norm="none", **{"residual": True, **overrides})
    model = unet.CINUNet(cfg, num_materials=2)
    params = unet.init_params(model, jax.random.key(4, impl="rbg"), patch_size=32)
    rng = np.random.default_rng(5)
    n = rng.normal(size=(3, 32, 32, 3))
    y, x = np.mgrid[:32, :32]
    inside = np.stack([(y - 16) ** 2 + (x - 20) ** 2 < 15**2, x > y, np.zeros((32, 32), bool)])
    rgb = (0.5 + 0.5 * n / np.linalg.norm(n, axis=-1, keepdims=True)) * inside[..., None]
    rgb = jnp.asarray(rgb, jnp.float32)
    weights = cfg.blur_weights(jnp.asarray(inside[..., None], jnp.float32))
    assert set(weights) == keys
    run = jax.jit(lambda w: model.apply({"params": params}, rgb, jnp.array([0, 1, 1]), None, w))
    got, want = np.asarray(run(weights)), np.asarray(run(None))
    assert np.isfinite(got).all()
    # float32 through the network's two blur paths: up to 8e-6 apart on session 37's fresh
    # machine (a wrong weight moves the output by > 1e-3, checked below).
    np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-5)
    if keys:  # the weights do enter: those of another mask change the output
        moved = cfg.blur_weights(jnp.asarray(np.roll(inside, 1, axis=0)[..., None], jnp.float32))
        assert np.abs(np.asarray(run(moved)) - want)[:2].max() > 1e-3
