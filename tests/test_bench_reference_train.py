"""The training-step section of benchmarks/bench_reference.py: the loss weights that make our
objective equal to the authors' (`wrinkle_jax.reference`, checked against their formula
written out in NumPy), and -- only where torch is installed (an optional extra; skipped
otherwise) -- the benchmark's seeded VGG19 in their torchvision layout read into ours."""


import jax
import jax.numpy as jnp
import numpy as np
import pytest

from wrinkle_jax import reference
from wrinkle_jax.nn import losses, vgg


def _authors_objective(f_out, f_inp, f_tgt, style_layers, content_layer,
                       c_alpha=1.0, s_beta=1e4):
    """Their BatchFeatureLoss_Model on an all-ones mask, in NumPy (float64): content
    1/2 sum (F_out - F_in)^2 over batch, pixels and channels; style sum over the batch of
    sum_l ||G_out - G_tgt||^2 / (L (2 R_l)^2), G = F^T F unnormalized, R_l the layer's pixels."""
    f = {k: {name: np.asarray(v[name], np.float64) for name in v}
         for k, v in (("out", f_out), ("inp", f_inp), ("tgt", f_tgt))}
    content = 0.5 * np.sum((f["out"][content_layer] - f["inp"][content_layer]) ** 2)
    style = 0.0
    for name in style_layers:
        n, h, w, c = f["out"][name].shape
        g_out = np.einsum("nhwc,nhwd->ncd", f["out"][name], f["out"][name])
        g_tgt = np.einsum("nhwc,nhwd->ncd", f["tgt"][name], f["tgt"][name])
        style += np.sum((g_out - g_tgt) ** 2) / (len(style_layers) * (2.0 * h * w) ** 2)
    return c_alpha * content, s_beta * style


@pytest.mark.parametrize("batch", [1, 3])
def test_loss_weights_make_our_objective_theirs(tiny_vgg, batch):
    rng = np.random.default_rng(batch)
    size = 32
    out, inp, tgt = (jnp.asarray(rng.uniform(0, 1, (batch, size, size, 3)), jnp.float32)
                     for _ in range(3))
    mask = jnp.ones((batch, size, size, 1), jnp.float32)
    c_layer = reference.CONTENT_LAYER
    channels = int(tiny_vgg[c_layer.replace("relu", "conv")]["kernel"].shape[-1])
    w_c, w_s = reference.authors_loss_weights(batch, channels, (size // 2) ** 2)
    total, parts = losses.enhancer_loss(tiny_vgg, out, inp, tgt, mask,
                                        style_layers=reference.STYLE_LAYERS, content_layer=c_layer,
                                        w_c=w_c, w_s=w_s, normalize_channels=False)
    layers = tuple(sorted(set(reference.STYLE_LAYERS) | {c_layer}))
    feats = [vgg.features(tiny_vgg, im, layers=layers) for im in (out, inp, tgt)]
    content, style = _authors_objective(*feats, reference.STYLE_LAYERS, c_layer)
    assert content > 0 and style > 0
    np.testing.assert_allclose(w_c * float(jnp.mean(parts["content"])), content, rtol=1e-5)
    np.testing.assert_allclose(w_s * float(jnp.mean(parts["style"])), style, rtol=1e-5)
    np.testing.assert_allclose(float(total), content + style, rtol=1e-5)


def test_seeded_vgg_reads_into_ours_with_the_same_features(bench):
    torch = pytest.importorskip("torch")  # the optional `reference` extra
    features = bench.seeded_vgg19_features(torch)
    again = bench.seeded_vgg19_features(torch)
    for a, b in zip(features.state_dict().values(), again.state_dict().values(), strict=True):
        assert torch.equal(a, b)  # seeded: their module and ours see the same weights
    params = bench.vgg_to_ours(torch, features)
    assert params["spec"] == vgg.VGGSpec("imagenet_rgb", "ZERO")
    rng = np.random.default_rng(0)
    rgb = rng.uniform(0, 1, (2, 32, 32, 3)).astype(np.float32)
    mean = np.asarray(bench.unet.IMAGENET_MEAN, np.float32)
    std = np.asarray(bench.unet.IMAGENET_STD, np.float32)
    x = torch.from_numpy(((rgb - mean) / std).transpose(0, 3, 1, 2).copy())
    # Their style layers are prefixes of `features`: [:4] relu1_2 ... [:30] relu5_1.
    ours = jax.jit(vgg.features, static_argnames=("layers", "pool"))(
        params, jnp.asarray(rgb), layers=reference.STYLE_LAYERS, pool="max")
    with torch.no_grad():
        for name, end in zip(reference.STYLE_LAYERS, (4, 7, 12, 21, 30), strict=True):
            ref = features[:end](x).numpy().transpose(0, 2, 3, 1)
            got = np.asarray(ours[name])
            assert got.shape == ref.shape
            scale = np.sqrt(np.mean(ref**2))
            assert scale > 0
            assert np.max(np.abs(got - ref)) < 1e-4 * max(scale, 1.0), name
