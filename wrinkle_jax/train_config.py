"""The enhancer's training configuration and state: `TrainConfig` (static, hashable,
JSON-serializable), `RECIPE` (the shipped model's recipe), `TrainState` (params + optimizer
state + step) and its fresh creation. `train` re-exports every name here (old import paths,
run configs and pickles keep working).
"""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp
import optax

from wrinkle_jax import hostcpu
from wrinkle_jax.nn import unet


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    """Enhancer training configuration (static, hashable, JSON-serializable).

    Attributes:
      unet: the U-Net's architecture (`nn.unet.UNetConfig`; e.g. ``detail_sigma`` > 0 makes
        the model AND the loss work on detail maps -- input, output and target each with its
        own large scale removed, on the input's branch -- so coarse-input/fine-target pairs
        whose large scales diverge can be used without pixel alignment; ``noise_channels`` > 0
        makes the batches carry random "origins" that place each patch in a noise field).
      num_materials: rows of the CIN tables.
      batch_size: global batch (divisible by the number of devices).
      steps: total optimizer steps.
      learning_rate, b1, b2, weight_decay: Adam(W).
      style_layers, content_layer, w_c, w_s, normalize_channels, pool: the loss (see
        `nn.losses.enhancer_loss`).
      conv_impl: convolution form of the U-Net and of the loss's VGG ("auto": this host's fast
        form, `hostcpu.fast_conv_impl`; "xla", "im2col_f32" (exact), "im2col_bf16",
        "winograd_bf16" or "winograd_f32"; see `nn.unet`). Parameters are the same for all
        forms, so a run may resume with another one.
      relative_floor: None for the paper's absolute style loss, or the floor of the per-patch
        relative style loss (`nn.losses.enhancer_loss`); the "style" metric is then a ratio.
      relative_log: the log of that ratio instead (the median-seeking form; "style" is then
        a log ratio, 0 = as far from the target as the input).
      band_weight: weight of the band-energy term (`nn.losses.band_loss`: log band RMS of the
        output's detail against the target's, < 16 mm and 16-64 mm); 0 leaves it out. Needs
        ``unet.detail_sigma`` > 0 (the bands are those of detail maps).
      bank_weight: weight of the set-level term (`nn.gram_bank`): each output's distance, in
        Table 2's scaled Gram-feature space, to the nearest of `bank_size` fine training
        targets of its material; 0 leaves it out.
      bank_size: fine patches per material in that bank.
      zero_init_output: with a residual U-Net, start the output conv at zero so the untrained
        network is the identity (improvement 0) instead of input + random noise, whose style
        loss starts ~40x above the input's.
      seed: parameter init and data order.
      eval_every, eval_batches: held-out evaluation cadence and size.
      checkpoint_every, keep_checkpoints: Orbax cadence and retention.
    """

    unet: unet.UNetConfig = unet.UNetConfig(width=32, residual=True)
    num_materials: int = 5
    batch_size: int = 8
    steps: int = 1000
    learning_rate: float = 1e-4
    b1: float = 0.9
    b2: float = 0.9
    weight_decay: float = 0.0
    style_layers: tuple[str, ...] = ("relu1_2", "relu2_1", "relu3_1", "relu4_1")
    content_layer: str = "relu2_1"
    w_c: float = 1.0
    w_s: float = 1e4
    normalize_channels: bool = True
    pool: str = "avg"
    conv_impl: str = "auto"
    zero_init_output: bool = True
    relative_floor: float | None = None
    relative_log: bool = False
    band_weight: float = 0.0
    bank_weight: float = 0.0
    bank_size: int = 128
    seed: int = 0
    eval_every: int = 50
    eval_batches: int = 4
    checkpoint_every: int = 100
    keep_checkpoints: int = 3

    def model(self) -> unet.CINUNet:
        return self.unet.module(self.num_materials, self.conv_impl)

    @property
    def vgg_conv_impl(self) -> str:
        # Every U-Net form is one of VGG's; "auto" follows the U-Net's width.
        return hostcpu.resolve_conv_impl(self.conv_impl, self.unet.width)

    def to_json(self) -> dict:
        """Flat: the U-Net's settings among the training fields (the run-config format)."""
        own = {f.name: getattr(self, f.name) for f in dataclasses.fields(self) if f.name != "unet"}
        return {**self.unet.to_json(), **own}

    @classmethod
    def from_json(cls, d: dict) -> TrainConfig:
        """Read `to_json`'s form, including run configs written before `unet` was nested."""
        net, rest = unet.UNetConfig.split_json(d, cls.__dataclass_fields__["unet"].default)
        rest["style_layers"] = tuple(rest["style_layers"])
        return cls(unet=net, **rest)


# The shipped model's training recipe (wrinkle_jax/assets/MODEL_CARD.md): its U-Net
# (`unet.RECIPE_UNET`), the style loss on relu1_2..relu3_2 (layer_selection's relu2_2, relu3_1,
# relu3_2, plus relu1_2 and relu2_1, where the content term otherwise undoes the sharpening:
# experiments.per_layer_ratios) relative to each patch's input with floor 100, a light content
# term, Adam at 2e-4. `experiments.train_default` and `wrinkle-jax train-enhancer` start here.
RECIPE = TrainConfig(unet=unet.RECIPE_UNET, batch_size=8, steps=20_000, learning_rate=2e-4,
                     style_layers=("relu1_2", "relu2_1", "relu2_2", "relu3_1", "relu3_2"),
                     w_c=0.1, w_s=10.0, normalize_channels=False, relative_floor=100.0,
                     eval_every=100, eval_batches=8, checkpoint_every=100)


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class TrainState:
    """step () int32, params (CINUNet pytree), opt_state (optax state)."""

    step: Any
    params: Any
    opt_state: Any


def optimizer(config: TrainConfig) -> optax.GradientTransformation:
    if config.weight_decay > 0:
        return optax.adamw(config.learning_rate, b1=config.b1, b2=config.b2,
                           weight_decay=config.weight_decay)
    return optax.adam(config.learning_rate, b1=config.b1, b2=config.b2)


def create_train_state(config: TrainConfig, key, patch_size: int = 128) -> TrainState:
    """Fresh parameters and optimizer state (step 0)."""
    params = unet.init_params(config.model(), key, patch_size)
    if config.unet.residual and config.zero_init_output:
        params = {**params, "out": jax.tree.map(jnp.zeros_like, params["out"])}
    return TrainState(jnp.zeros((), jnp.int32), params, optimizer(config).init(params))
