"""Patch features for the classifier: VGG19 layers reduced to a vector per patch, and the
statistics that standardize them.

Patches (N, S, S, 3) in the RGB form of coarse normal maps times the mask; mask (N, S, S, 1).
"""

from __future__ import annotations

from typing import Any

import jax.numpy as jnp
import numpy as np

from wrinkle_jax.classifier.config import GRID, _parse_feature
from wrinkle_jax.nn import vgg
from wrinkle_jax.numerics import safe_div


def _reduce(x, mask, reduce: str):
    """(N, h, w, C) layer activations + (N, h, w, 1) garment fraction -> (N, D) features."""
    n, h, w, c = x.shape
    if reduce == "grid4":
        return x.reshape(n, GRID, h // GRID, GRID, w // GRID, c).mean(axis=(2, 4)).reshape(n, -1)
    # Mean and std over garment texels; a patch always has >= min_coverage garment texels, and
    # the guarded division keeps an all-background patch finite anyway.
    weight = jnp.sum(mask, axis=(1, 2))  # (N, 1)
    mean = safe_div(jnp.sum(x * mask, axis=(1, 2)), weight)
    var = safe_div(jnp.sum(mask * (x - mean[:, None, None]) ** 2, axis=(1, 2)), weight)
    return jnp.concatenate([mean, jnp.sqrt(jnp.maximum(var, 0.0) + 1e-12)], axis=-1)


def _pool_mask(mask, level: int):
    for _ in range(level):
        mask = vgg.pool2x2(mask, "avg")
    return mask


def patch_features(vgg_params, rgb, mask, features=("relu4_1:stats",),
                   conv_impl: str = "auto") -> dict[str, Any]:
    """VGG features of patches, for one or several feature specs from a single VGG pass.

    Args:
      vgg_params: VGG19 parameter pytree (`vgg.load_vgg19` or `vgg.init_vgg19`).
      rgb: (N, S, S, 3) float32 RGB form of coarse normal maps, background 0.
      mask: (N, S, S, 1) float32 garment mask of the patches.
      features: tuple of ``"<layer>:<reduce>"`` specs (static).
      conv_impl: VGG convolution form (static; "auto": the host's fast form, see `hostcpu`).
    Returns:
      dict spec -> (N, D) float32 raw features (before log1p and standardization).
      Jittable with `features` and `conv_impl` static.
    """
    if isinstance(features, str):
        features = (features,)
    parsed = [_parse_feature(f) for f in features]
    layers = tuple(sorted({layer for layer, _ in parsed}))
    acts = vgg.features(vgg_params, rgb, layers=layers, conv_impl=conv_impl)
    out = {}
    for spec, (layer, reduce) in zip(features, parsed, strict=True):
        out[spec] = _reduce(acts[layer], _pool_mask(mask, vgg.layer_level(layer)), reduce)
    return out


def _preprocess(raw, norm):
    """log1p then standardize by the training statistics (norm: mean/std (D,))."""
    return (jnp.log1p(jnp.maximum(raw.astype(jnp.float32), 0.0)) - norm["mean"]) / norm["std"]


def feature_stats(raw) -> dict[str, np.ndarray]:
    """Standardization statistics {'mean', 'std'} (D,) of log1p features (N, D)."""
    x = np.log1p(np.maximum(np.asarray(raw, np.float32), 0.0))
    # Constant features (e.g. dead ReLUs) get std 1 so they standardize to 0, not NaN.
    std = x.std(0)
    return {"mean": x.mean(0).astype(np.float32),
            "std": np.where(std > 1e-6, std, 1.0).astype(np.float32)}
