"""A DeepWrinkles-style conditional PatchGAN baseline (Lähner et al. 2018, after pix2pix,
Isola et al. 2017): the paper's Fig. 9 comparison.

DeepWrinkles adds high-frequency detail to a low-resolution normal map with a conditional GAN:
a generator maps the coarse map to a detailed one, a convolutional PatchGAN discriminator
judges (coarse, detailed) pairs patch by patch, and an L1 data term ties the output to the
registered ground truth. The model is garment-specific and has no material input.

Here, to compare LOSSES rather than architectures, the generator is this library's U-Net
(`nn.unet.CINUNet`) with the shipped model's residual structure (`GANConfig.unet` defaults to
`nn.unet.RECIPE_UNET`: width 16, unsharp-mask base with a learnable gain, high-passed
residual) but ONE row of normalization parameters (no material conditioning: every sample
uses row 0, i.e. instance normalization with a learned affine), trained with

    L_D = BCE(D(x, y), 1) + BCE(D(x, G(x)), 0)                       (halved)
    L_G = BCE(D(x, G(x)), 1) + l1_weight * |G(x) - y|_1 (masked mean)

instead of the VGG Gram-matrix style loss. x: coarse patch, y: fine patch of the same frame
and cloth (RGB form in [0, 1]), both cut to the garment mask. Every logit of D sees a
~70-texel window (pix2pix's 70 x 70 PatchGAN: 4 x 4 convolutions, three of stride 2); the
BCE is averaged over the logits weighted by the garment coverage of their cell, so background
does not train D. Optimizer: Adam lr 2e-4, b1 0.5, b2 0.999 for both (pix2pix's).

Functions are pure; the jitted `make_gan_step` updates D, then G against the updated D.
`GANConfig.enhancer_config` turns a trained generator into an `enhancer.Enhancer` file (one
material named "any"), so every evaluation script can run it like the shipped model.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import flax.linen as nn
import jax
import jax.numpy as jnp
import optax

from wrinkle_jax.nn import unet

ANY_MATERIAL = "any"


@dataclasses.dataclass(frozen=True)
class GANConfig:
    """PatchGAN baseline configuration (static, hashable, JSON-serializable).

    Attributes:
      unet: the generator's architecture (`nn.unet.UNetConfig`, built with one material
        row); default: the shipped model's (`nn.unet.RECIPE_UNET`).
      zero_init_output, conv_impl: the generator's initialization (with a residual U-Net, its
        output conv starts at zero) and convolution form.
      disc_width: channels of D's first convolution (doubling per stride-2 layer).
      disc_layers: stride-2 convolutions of D after the first (3: the 70 x 70 PatchGAN).
      l1_weight: weight of the masked L1 data term (pix2pix: 100).
      learning_rate, b1, b2: Adam for G and D.
      batch_size: patches per step.
      seed: initialization and data order.
    """

    unet: unet.UNetConfig = unet.RECIPE_UNET
    zero_init_output: bool = True
    conv_impl: str = "auto"
    disc_width: int = 32
    disc_layers: int = 3
    l1_weight: float = 100.0
    learning_rate: float = 2e-4
    b1: float = 0.5
    b2: float = 0.999
    batch_size: int = 8
    seed: int = 0

    def generator(self) -> unet.CINUNet:
        return self.unet.module(1, self.conv_impl)

    def discriminator(self) -> PatchDiscriminator:
        return PatchDiscriminator(width=self.disc_width, layers=self.disc_layers)

    def enhancer_config(self, patch_size: int, texel_size: float, coarse_pd: float):
        """The `enhancer.EnhancerConfig` of the generator (one material, `ANY_MATERIAL`)."""
        from wrinkle_jax import enhancer

        return enhancer.EnhancerConfig(unet=self.unet, materials=(ANY_MATERIAL,),
                                       patch_size=patch_size, texel_size=texel_size,
                                       coarse_pd=coarse_pd)

    def to_json(self) -> dict:
        """Flat: the generator's U-Net settings among the GAN's own fields."""
        own = {f.name: getattr(self, f.name) for f in dataclasses.fields(self) if f.name != "unet"}
        return {**self.unet.to_json(), **own}

    @classmethod
    def from_json(cls, d: dict) -> GANConfig:
        """Read `to_json`'s form, including files written before `unet` was nested."""
        net, rest = unet.UNetConfig.split_json(d, cls.__dataclass_fields__["unet"].default)
        return cls(unet=net, **rest)


class PatchDiscriminator(nn.Module):
    """Conditional PatchGAN: (coarse x, candidate y) -> a grid of real/fake logits.

    4 x 4 convolutions, "SAME" padding: C(w, stride 2) - LReLU, then `layers - 1` of
    C(2^i w, stride 2) - IN - LReLU, C(2^layers w, stride 1) - IN - LReLU, C(1, stride 1).
    For 128 x 128 patches and layers=3: (N, 16, 16, 1) logits, each seeing ~70 texels.
    """

    width: int = 32
    layers: int = 3

    @nn.compact
    def __call__(self, condition, candidate, mask):
        """condition, candidate: (N, S, S, 3) RGB form; mask (N, S, S, 1) -> (N, S/2^L, S/2^L,
        1) logits (L = layers)."""
        # The mask is an input too: D may not call a patch fake for where the garment ends.
        x = jnp.concatenate([condition * mask, candidate * mask, mask], -1) * 2.0 - 1.0
        x = nn.leaky_relu(nn.Conv(self.width, (4, 4), strides=2, padding="SAME")(x), 0.2)
        for i in range(1, self.layers):
            x = nn.Conv(self.width * 2**i, (4, 4), strides=2, padding="SAME")(x)
            x = nn.leaky_relu(nn.InstanceNorm()(x), 0.2)
        x = nn.Conv(self.width * 2**self.layers, (4, 4), padding="SAME")(x)
        x = nn.leaky_relu(nn.InstanceNorm()(x), 0.2)
        return nn.Conv(1, (4, 4), padding="SAME")(x)


def cell_weights(mask, logits_shape) -> jnp.ndarray:
    """Garment coverage of each logit's cell: the mask average-pooled to the logit grid,
    (N, S, S, 1) -> (N, h, w, 1) in [0, 1]."""
    n, s = mask.shape[0], mask.shape[1]
    h = logits_shape[1]
    f = s // h
    return mask.reshape(n, h, f, h, f, 1).mean(axis=(2, 4))


def _bce(logits, label: float, weights) -> jnp.ndarray:
    """Per-sample coverage-weighted mean BCE of `logits` against a constant label, (N,)."""
    loss = optax.sigmoid_binary_cross_entropy(logits, jnp.full_like(logits, label))
    return jnp.sum(loss * weights, axis=(1, 2, 3)) / jnp.maximum(
        jnp.sum(weights, axis=(1, 2, 3)), 1e-6)


def masked_l1(out, target, mask) -> jnp.ndarray:
    """Per-sample mean |out - target| over the garment texels and channels, (N,)."""
    num = jnp.sum(jnp.abs(out - target) * mask, axis=(1, 2, 3))
    return num / jnp.maximum(3.0 * jnp.sum(mask, axis=(1, 2, 3)), 1.0)


def discriminator_loss(d_real, d_fake, weights) -> jnp.ndarray:
    """0.5 (BCE(real, 1) + BCE(fake, 0)), batch mean."""
    return 0.5 * jnp.mean(_bce(d_real, 1.0, weights) + _bce(d_fake, 0.0, weights))


def generator_loss(d_fake, out, target, mask, weights, l1_weight: float):
    """(total, adversarial, l1): BCE(D(x, G(x)), 1) + l1_weight * masked L1, batch means."""
    adv = jnp.mean(_bce(d_fake, 1.0, weights))
    l1 = jnp.mean(masked_l1(out, target, mask))
    return adv + l1_weight * l1, adv, l1


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class GANState:
    """step () int32; g_params, d_params; g_opt, d_opt (optax states)."""

    step: Any
    g_params: Any
    d_params: Any
    g_opt: Any
    d_opt: Any


def _tx(config: GANConfig) -> optax.GradientTransformation:
    return optax.adam(config.learning_rate, b1=config.b1, b2=config.b2)


def create_gan_state(config: GANConfig, key, patch_size: int = 128) -> GANState:
    """Fresh G (zero output layer with `zero_init_output`: it starts as its base) and D."""
    kg, kd = jax.random.split(key)
    g = unet.init_params(config.generator(), kg, patch_size)
    if config.unet.residual and config.zero_init_output:
        g = {**g, "out": jax.tree.map(jnp.zeros_like, g["out"])}
    x = jnp.zeros((1, patch_size, patch_size, 3), jnp.float32)
    m = jnp.ones((1, patch_size, patch_size, 1), jnp.float32)
    d = jax.jit(lambda k: config.discriminator().init(k, x, x, m)["params"])(kd)
    tx = _tx(config)
    return GANState(jnp.zeros((), jnp.int32), g, d, tx.init(g), tx.init(d))


def generate(config: GANConfig, g_params, inputs, mask) -> jnp.ndarray:
    """G's output (N, S, S, 3) in the RGB form, cut to the mask (material row 0)."""
    material = jnp.zeros((inputs.shape[0],), jnp.int32)
    return config.generator().apply({"params": g_params}, inputs, material) * mask


def make_gan_step(config: GANConfig):
    """Jitted `(state, batch) -> (state, metrics)`: one D update, then one G update against
    the updated D. batch: {"input", "target" (N, S, S, 3), "mask" (N, S, S, 1)} (others
    ignored). Metrics: d_loss, g_adv, g_l1, d_real and d_fake (mean D probabilities)."""
    tx = _tx(config)
    disc = config.discriminator()

    def step(state: GANState, batch: dict):
        x, y, m = batch["input"], batch["target"], batch["mask"]
        fake = jax.lax.stop_gradient(generate(config, state.g_params, x, m))

        def d_loss_fn(d_params):
            real = disc.apply({"params": d_params}, x, y, m)
            fk = disc.apply({"params": d_params}, x, fake, m)
            w = cell_weights(m, real.shape)
            return discriminator_loss(real, fk, w), (real, fk)

        (d_loss, (real, fk)), d_grads = jax.value_and_grad(d_loss_fn, has_aux=True)(
            state.d_params)
        d_upd, d_opt = tx.update(d_grads, state.d_opt, state.d_params)
        d_params = optax.apply_updates(state.d_params, d_upd)

        def g_loss_fn(g_params):
            out = generate(config, g_params, x, m)
            logits = disc.apply({"params": d_params}, x, out, m)
            total, adv, l1 = generator_loss(logits, out, y, m, cell_weights(m, logits.shape),
                                            config.l1_weight)
            return total, (adv, l1)

        (_, (adv, l1)), g_grads = jax.value_and_grad(g_loss_fn, has_aux=True)(state.g_params)
        g_upd, g_opt = tx.update(g_grads, state.g_opt, state.g_params)
        g_params = optax.apply_updates(state.g_params, g_upd)
        metrics = {"d_loss": d_loss, "g_adv": adv, "g_l1": l1,
                   "d_real": jnp.mean(jax.nn.sigmoid(real)),
                   "d_fake": jnp.mean(jax.nn.sigmoid(fk))}
        return GANState(state.step + 1, g_params, d_params, g_opt, d_opt), metrics

    return jax.jit(step, donate_argnums=(0,))
