"""The classifier model: a four-layer MLP on standardized features, its probabilities and
loss, initialization and prediction (per patch, (N, M) probabilities over the materials)."""

from __future__ import annotations

import functools
from typing import Any, NamedTuple

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from wrinkle_jax import MATERIALS
from wrinkle_jax.classifier.config import ClassifierConfig, feature_dim
from wrinkle_jax.classifier.features import _preprocess, patch_features
from wrinkle_jax.nn import vgg
from wrinkle_jax.numerics import safe_div


class MaterialMLP(nn.Module):
    """Four fully connected layers: 3 hidden (ReLU, dropout) and the material logits.

    Input (N, D) standardized features; output (N, num_materials) logits.
    """

    hidden: tuple[int, ...] = (256, 128, 64)
    num_materials: int = len(MATERIALS)
    dropout: float = 0.3

    @nn.compact
    def __call__(self, x, train: bool = False):
        for i, width in enumerate(self.hidden):
            x = nn.relu(nn.Dense(width, name=f"dense{i}")(x))
            x = nn.Dropout(self.dropout, deterministic=not train)(x)
        return nn.Dense(self.num_materials, name=f"dense{len(self.hidden)}")(x)


def probabilities(logits):
    """Paper's output layer: sigmoid, then normalized to sum 1. (N, M) -> (N, M)."""
    s = jax.nn.sigmoid(logits)
    # sigmoid > 0, but may underflow to 0 for every class at extreme logits: guard the sum.
    return safe_div(s, jnp.sum(s, axis=-1, keepdims=True), fill=1.0 / logits.shape[-1])


def cross_entropy(logits, labels):
    """Per-sample cross-entropy -log p[label] of the normalized sigmoid outputs.

    Computed in log space (log_sigmoid minus the log of the sum) so it stays finite.
    Args: logits (N, M), labels (N,) int. Returns (N,) float32 (the caller reduces).
    """
    log_s = jax.nn.log_sigmoid(logits)
    log_p = log_s - jax.nn.logsumexp(log_s, axis=-1, keepdims=True)
    return -jnp.take_along_axis(log_p, labels[:, None], axis=-1)[:, 0]


class Classifier(NamedTuple):
    """A ready-to-use classifier.

    Attributes:
      config: ClassifierConfig.
      params: MLP parameter pytree.
      norm: {'mean', 'std'} (D,) float32 feature standardization.
      vgg: VGG19 parameter pytree used for the features.
      meta: free-form JSON (training data, accuracies, VGG source, ...).
    """

    config: ClassifierConfig
    params: Any
    norm: dict
    vgg: Any
    meta: dict

    @property
    def model(self) -> MaterialMLP:
        return _model(self.config)


def _model(config: ClassifierConfig) -> MaterialMLP:
    return MaterialMLP(tuple(config.hidden), len(config.materials), config.dropout)


def init_classifier(key, config: ClassifierConfig = ClassifierConfig(),  # noqa: B008 (frozen)
                    vgg_params=None, norm=None, meta=None) -> Classifier:
    """An untrained classifier (random MLP, identity standardization unless `norm` is given).

    Args:
      key: PRNG key.
      vgg_params: VGG19 params (default: `vgg.load_vgg19()`).
    """
    vgg_params = vgg.load_vgg19() if vgg_params is None else vgg_params
    d = feature_dim(vgg_params, config.feature, config.patch_size)
    params = _init_params(key, config, d)
    if norm is None:
        norm = {"mean": np.zeros(d, np.float32), "std": np.ones(d, np.float32)}
    norm = {k: jnp.asarray(v, jnp.float32) for k, v in norm.items()}
    return Classifier(config, params, norm, vgg_params, dict(meta or {}))


@functools.partial(jax.jit, static_argnames=("config", "dim"))
def _init_params(key, config: ClassifierConfig, dim: int):
    # Jitted: an eager Flax init compiles every small op separately (seconds on a busy CPU).
    return _model(config).init(key, jnp.zeros((1, dim), jnp.float32))["params"]


@functools.partial(jax.jit, static_argnames=("config",))
def _logits_from_raw(params, norm, raw, config: ClassifierConfig):
    return _model(config).apply({"params": params}, _preprocess(raw, norm))


@functools.partial(jax.jit, static_argnames=("config", "conv_impl"))
def _raw_features(vgg_params, rgb, mask, config: ClassifierConfig, conv_impl: str):
    return patch_features(vgg_params, rgb, mask, (config.feature,), conv_impl)[config.feature]


def predict_from_features(classifier: Classifier, raw, chunk: int = 512) -> np.ndarray:
    """Per-patch probabilities (N, M) from raw features (N, D) (as `patch_features` returns).

    Runs in padded chunks of `chunk` rows, so any N reuses one compiled function.
    """
    raw = np.asarray(raw)
    out = []
    for start in range(0, len(raw), chunk):
        part = raw[start:start + chunk]
        padded = np.resize(part, (chunk, raw.shape[1])) if len(part) < chunk else part
        logits = _logits_from_raw(classifier.params, classifier.norm, padded, classifier.config)
        out.append(np.asarray(probabilities(logits))[: len(part)])
    if not out:
        return np.zeros((0, len(classifier.config.materials)), np.float32)
    return np.concatenate(out)


def predict_patches(classifier: Classifier, rgb, mask, batch_size: int = 16,
                    conv_impl: str = "auto") -> np.ndarray:
    """Per-patch material probabilities.

    Args:
      rgb: (N, S, S, 3) RGB-form coarse normal-map patches in [0, 1], background 0.
      mask: (N, S, S, 1) garment masks.
      batch_size: patches per VGG call (the last batch is padded, so one compile serves all).
    Returns:
      (N, M) float32 NumPy probabilities (rows sum to 1).
    """
    rgb = np.asarray(rgb, np.float32)
    mask = np.asarray(mask, np.float32)
    n = len(rgb)
    raws = []
    for start in range(0, n, batch_size):
        idx = np.resize(np.arange(start, min(start + batch_size, n)), batch_size)
        raw = _raw_features(classifier.vgg, jnp.asarray(rgb[idx]), jnp.asarray(mask[idx]),
                            classifier.config, conv_impl)
        raws.append(np.asarray(raw)[: min(batch_size, n - start)])
    raw = np.concatenate(raws) if raws else np.zeros((0, 1), np.float32)
    return np.asarray(predict_from_features(classifier, raw))
