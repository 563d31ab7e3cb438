"""Patch-based material classifier with temporal voting (paper Sec. 4.2, Fig. 6).

Pipeline, for a coarse garment sequence of unknown fabric::

    frames (T, V, 3) --bake at config.texel_size--> normal maps (H, W, 3) + mask
      --random valid crops (>= min_coverage garment texels), spread over time--> (P, S, S, 3)
      --VGG19 features (config.feature)--> (P, D) --4 fully connected layers--> (P, M) logits
      --sigmoid, normalized to sum 1--> per-patch probabilities
      --vote: per-material histogram of patch probabilities (Fig. 6)--> material + scores

Contract:
  * Patches are the RGB form ``(n + 1) / 2`` of coarse normal maps, multiplied by the mask
    (background 0), exactly like the enhancer's inputs (`wrinkle_jax.data`).
  * ``config.feature`` names a VGG layer and a reduction, ``"<layer>:<reduce>"``:
    ``grid4`` averages the layer to a 4 x 4 grid and flattens it (``relu5_4:grid4`` is the
    paper's pool5, 4 x 4 x 512 = 8,192 values with average pooling), ``stats`` takes the
    per-channel mean and standard deviation over the garment texels (2 C values; a
    translation-invariant texture statistic, like the Gram matrices of the style loss).
    Features go through ``log1p`` (VGG activations are heavy-tailed) and are standardized by
    the training set's mean and std (stored with the model).
  * The MLP is four Dense layers (three hidden ReLU layers with dropout, then M outputs);
    probabilities are ``sigmoid(z) / sum(sigmoid(z))`` and the loss is the cross-entropy
    ``-log p[label]`` (paper).
  * Classification is a pure function of the key: same key, same answer.
  * Measured (experiments/results/classifier/README.md): on this project's simulated data the
    classifier is at chance on held-out scenes for every feature tried (the five fabrics give
    nearly the same coarse geometry at PD 30 mm), so no trained model ships yet and
    `load_classifier()` raises ClassifierError until one does. The default feature and sizes
    are the cheapest candidate of equal (chance-level) accuracy, not a validated choice.
  * The shipped model (``wrinkle_jax/assets/classifier.npz``) is a plain ``.npz`` (no
    pickle): ``params/<module>/<leaf>`` float16, ``norm/mean`` and ``norm/std`` float32,
    ``config.json`` and ``meta.json`` as uint8 bytes. The VGG19 weights are not in it; they come
    from `wrinkle_jax.nn.vgg.load_vgg19` (``meta["vgg"]`` records which).

Example:
    >>> import jax, numpy as np
    >>> from wrinkle_jax.nn import vgg
    >>> tiny = vgg.init_vgg19(jax.random.key(0, impl="rbg"), widths=(4, 8, 8, 8, 8),
    ...                       num_convs=4, spec=vgg.VGGSpec("custom", "REFLECT"))
    >>> cfg = ClassifierConfig(feature="relu2_1:stats", hidden=(16, 16, 16), patch_size=32)
    >>> clf = init_classifier(jax.random.key(1, impl="rbg"), cfg, tiny)
    >>> probs = predict_patches(clf, np.full((2, 32, 32, 3), 0.5, np.float32),
    ...                         np.ones((2, 32, 32, 1), np.float32))
    >>> probs.shape
    (2, 5)
"""

from __future__ import annotations

import dataclasses
import functools
import os
from pathlib import Path
from typing import Any, NamedTuple

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import optax

from wrinkle_jax import MATERIALS, modelfile, normalmap, patches
from wrinkle_jax.mesh import Garment
from wrinkle_jax.nn import vgg
from wrinkle_jax.numerics import normalize, safe_div

__all__ = [
    "DEFAULT_PATH",
    "Classification",
    "Classifier",
    "ClassifierConfig",
    "ClassifierError",
    "MaterialMLP",
    "classify_patches",
    "classify_sequence",
    "feature_dim",
    "init_classifier",
    "load_classifier",
    "patch_features",
    "predict_patches",
    "probabilities",
    "sample_patches",
    "save_classifier",
    "train_classifier",
    "vote",
]

DEFAULT_PATH = Path(__file__).resolve().parents[1] / "assets" / "classifier.npz"
_FORMAT = "wrinkle-jax-classifier/1"
REDUCTIONS = ("grid4", "stats")
GRID = 4  # cells per side of the "grid4" reduction


class ClassifierError(ValueError):
    """A classifier file is missing, unreadable or inconsistent, or a sequence cannot be
    classified (the message names the file or the problem)."""


@dataclasses.dataclass(frozen=True)
class ClassifierConfig:
    """What a classifier needs at inference (static, hashable).

    Attributes:
      feature: ``"<vgg layer>:<grid4|stats>"`` (see the module docstring).
      hidden: widths of the three hidden Dense layers.
      dropout: dropout rate after each hidden layer (training only).
      materials: material names in output order.
      patch_size: patch side in texels.
      texel_size: meters of cloth per texel of the baked coarse maps.
      min_coverage: minimum fraction of garment texels in a sampled patch.
      downsample_factor: coarse PD / fine PD used to make coarse-looking maps from fine
        simulations for training (`normalmap.downsample_like_coarse`).
      normal_frame: "object" (normals as baked) or "patch" (each patch rotated so its mean
        normal is +z, see `to_patch_frame`).
    """

    feature: str = "relu4_1:stats"
    hidden: tuple[int, ...] = (256, 128, 64)
    dropout: float = 0.3
    materials: tuple[str, ...] = MATERIALS
    patch_size: int = 128
    texel_size: float = 0.004
    min_coverage: float = 0.09
    downsample_factor: float = 3.0
    normal_frame: str = "object"

    def __post_init__(self):
        _parse_feature(self.feature)  # raises on a malformed spec
        if len(self.hidden) != 3:
            raise ValueError(f"hidden must give 3 widths (4 Dense layers), got {self.hidden}")
        if not 0.0 <= self.dropout < 1.0:
            raise ValueError(f"dropout must be in [0, 1), got {self.dropout}")
        if self.normal_frame not in ("object", "patch"):
            raise ValueError(f"normal_frame must be 'object' or 'patch', got "
                             f"{self.normal_frame!r}")

    def to_json(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_json(cls, d: dict) -> ClassifierConfig:
        d = dict(d)
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = set(d) - names
        if unknown:
            raise ValueError(f"unknown classifier config fields {sorted(unknown)}")
        for k in ("hidden", "materials"):
            if k in d:
                d[k] = tuple(d[k])
        return cls(**d)


def _parse_feature(feature: str) -> tuple[str, str]:
    layer, sep, reduce = feature.partition(":")
    if not sep or reduce not in REDUCTIONS:
        raise ValueError(f"feature must look like '<vgg layer>:<{'|'.join(REDUCTIONS)}>', "
                         f"got {feature!r}")
    vgg.layer_level(layer)  # validates the layer name
    return layer, reduce


def _layer_channels(vgg_params, layer: str) -> int:
    """Output channels of a VGG layer, read from the parameters (tiny test VGGs differ)."""
    level = vgg.layer_level(layer)
    if layer.startswith("pool"):
        conv = [n for n in vgg.CONV_NAMES if int(n[4]) == level][-1]
    else:
        conv = "conv" + layer[4:]
    if conv not in vgg_params:
        raise ClassifierError(f"VGG parameters have no {conv!r} (needed for feature {layer!r})")
    return int(vgg_params[conv]["kernel"].shape[-1])


def feature_dim(vgg_params, feature: str, patch_size: int = 128) -> int:
    """Length D of the feature vector of one patch."""
    layer, reduce = _parse_feature(feature)
    c = _layer_channels(vgg_params, layer)
    if reduce == "stats":
        return 2 * c
    side = patch_size // 2 ** vgg.layer_level(layer)
    if side < GRID or side % GRID:
        raise ValueError(f"{layer} of a {patch_size}-texel patch is {side}x{side}, not "
                         f"divisible into a {GRID}x{GRID} grid")
    return GRID * GRID * c


# ---------------------------------------------------------------------------------------------
# Features


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
                   conv_impl: str = "im2col_bf16") -> dict[str, Any]:
    """VGG features of patches, for one or several feature specs from a single VGG pass.

    Args:
      vgg_params: VGG19 parameter pytree (`vgg.load_vgg19` or `vgg.init_vgg19`).
      rgb: (N, S, S, 3) float32 RGB form of coarse normal maps, background 0.
      mask: (N, S, S, 1) float32 garment mask of the patches.
      features: tuple of ``"<layer>:<reduce>"`` specs (static).
      conv_impl: VGG convolution form (static; "im2col_bf16" is ~2x faster on CPU).
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


# ---------------------------------------------------------------------------------------------
# Model


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


def init_classifier(key, config: ClassifierConfig = ClassifierConfig(), vgg_params=None,
                    norm=None, meta=None) -> Classifier:
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
                    conv_impl: str = "im2col_bf16") -> np.ndarray:
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


# ---------------------------------------------------------------------------------------------
# Voting


class Classification(NamedTuple):
    """Result of classifying a set of patches or a sequence.

    Attributes:
      material: the winning material name.
      scores: material -> vote share (floats summing to 1).
      num_patches: number of patches that voted.
      histogram: (M, B) int counts: for material m, how many patches have p_m in bin b
        (the paper's Fig. 6).
      bin_edges: (B + 1,) float bin edges in [0, 1].
      patch_probs: (N, M) per-patch probabilities.
      frame_ids: (N,) frame of each patch (empty for bare patches).
    """

    material: str
    scores: dict
    num_patches: int
    histogram: np.ndarray
    bin_edges: np.ndarray
    patch_probs: np.ndarray
    frame_ids: np.ndarray

    def to_json(self) -> dict:
        return {"material": self.material, "scores": self.scores,
                "num_patches": self.num_patches,
                "histogram": {m: [int(c) for c in row] for m, row in
                              zip(self.scores, self.histogram, strict=True)},
                "bin_edges": [float(e) for e in self.bin_edges]}


def vote(probs, bins: int = 10, method: str = "histogram"):
    """Votes over per-patch probabilities (paper Fig. 6).

    For each material m the patches are histogrammed by p_m into `bins` equal bins of [0, 1].
    ``method="histogram"``: the score of m is the histogram's centroid (sum of bin centers
    weighted by counts, / N), i.e. how far the mass of m's histogram sits towards 1; scores
    are normalized to sum 1. ``method="majority"``: the share of patches whose most likely
    material is m. Ties go to the lower material index.

    Args:
      probs: (N, M) probabilities, N >= 1.
      bins: number of histogram bins B.
      method: "histogram" or "majority".
    Returns:
      (scores (M,) float64 summing to 1, histogram (M, B) int64, edges (B + 1,)).
    """
    p = np.asarray(probs, np.float64)
    if p.ndim != 2 or len(p) == 0:
        raise ClassifierError(f"vote needs (N, M) probabilities with N >= 1, got {p.shape}")
    edges = np.linspace(0.0, 1.0, bins + 1)
    # Bin index with 1.0 falling into the last bin.
    idx = np.clip((p * bins).astype(np.int64), 0, bins - 1)
    hist = np.stack([np.bincount(idx[:, m], minlength=bins) for m in range(p.shape[1])])
    if method == "histogram":
        centers = 0.5 * (edges[:-1] + edges[1:])
        raw = hist @ centers / len(p)
    elif method == "majority":
        raw = np.bincount(np.argmax(p, axis=1), minlength=p.shape[1]).astype(np.float64)
    else:
        raise ValueError(f"unknown vote method {method!r}; expected 'histogram' or 'majority'")
    total = raw.sum()
    scores = raw / total if total > 0 else np.full(p.shape[1], 1.0 / p.shape[1])
    return scores, hist, edges


def classify_patches(classifier: Classifier, probs, frame_ids=None, bins: int = 10,
                     method: str = "histogram") -> Classification:
    """Vote over already computed per-patch probabilities (N, M) -> Classification."""
    scores, hist, edges = vote(probs, bins, method)
    names = classifier.config.materials
    return Classification(
        material=names[int(np.argmax(scores))],
        scores={m: float(s) for m, s in zip(names, scores, strict=True)},
        num_patches=int(len(probs)), histogram=hist, bin_edges=edges,
        patch_probs=np.asarray(probs, np.float32),
        frame_ids=np.asarray([] if frame_ids is None else frame_ids, np.int64))


# ---------------------------------------------------------------------------------------------
# Sampling patches from a sequence


def _padded_shape(shape, size: int) -> tuple[int, int]:
    return max(shape[0], size), max(shape[1], size)


def to_patch_frame(normals, mask):
    """Rotate each patch's normals so that its mean garment normal becomes +z.

    Removes the garment's orientation in object space (a skirt faces sideways, a hanging
    sheet faces the wind), keeping the folds' shape. Rodrigues rotation taking the mean m to
    z: R = I + [v]x + [v]x^2 / (1 + c), v = m x z, c = m . z; a mean pointing to -z uses a
    half turn about x instead (the formula's denominator vanishes there).

    Args:
      normals: (N, S, S, 3) unit normals (zero on the background).
      mask: (N, S, S, 1) garment masks.
    Returns:
      (N, S, S, 3) rotated normals, zero on the background. Jittable.
    """
    mean = normalize(jnp.sum(normals * mask, axis=(1, 2)))  # (N, 3)
    z = jnp.array([0.0, 0.0, 1.0], normals.dtype)
    v = jnp.cross(mean, z)
    c = mean @ z
    vx = jnp.stack([jnp.stack([jnp.zeros_like(c), -v[:, 2], v[:, 1]], -1),
                    jnp.stack([v[:, 2], jnp.zeros_like(c), -v[:, 0]], -1),
                    jnp.stack([-v[:, 1], v[:, 0], jnp.zeros_like(c)], -1)], -2)
    flipped = c < -1.0 + 1e-6
    scale = jnp.where(flipped, 0.0, 1.0 / jnp.where(flipped, 1.0, 1.0 + c))
    rot = jnp.eye(3) + vx + (vx @ vx) * scale[:, None, None]
    rot = jnp.where(flipped[:, None, None], jnp.diag(jnp.array([1.0, -1.0, -1.0])), rot)
    return jnp.einsum("nij,nhwj->nhwi", rot, normals) * mask


@functools.partial(jax.jit, static_argnames=("n", "size", "min_coverage", "factor", "augment",
                                             "shape", "patch_frame"))
def _frame_crops(plan, vertices, key, n: int, size: int, min_coverage: float, factor: float,
                 augment: bool, shape: tuple[int, int], patch_frame: bool = False):
    """Bake one frame, optionally make it coarse-looking, and cut n valid crops.

    Returns (n, S, S, 3) RGB form (background 0), (n, S, S, 1) masks, (n, 2) origins.
    """
    n_map = normalmap.bake(plan, vertices)
    mask = plan.mask
    if factor > 1.0:
        n_map = normalmap.downsample_like_coarse(n_map, mask, factor)
    h, w = mask.shape[:2]
    pad = ((0, shape[0] - h), (0, shape[1] - w), (0, 0))
    n_map = jnp.pad(n_map * mask, pad)
    mask = jnp.pad(mask, pad)
    stacked = jnp.concatenate([n_map, mask], axis=-1)
    crops, _, origins = patches.random_crops(key, stacked, mask, n, size, min_coverage,
                                             augment=augment)
    normals, masks = crops[..., :3], crops[..., 3:]
    if patch_frame:
        normals = to_patch_frame(normals, masks)
    return normalmap.to_rgb(normals) * masks, masks, origins


def valid_origin_count(mask, size: int, min_coverage: float) -> int:
    """Number of patch origins whose patch has >= min_coverage garment texels (NumPy)."""
    m = np.asarray(mask, np.float32)
    m = np.asarray(patches.pad_to_patch(m, size)[0]) if min(m.shape[:2]) < size else m
    counts = np.asarray(patches.crop_mask_counts(m, size))
    return int(np.sum(counts >= min_coverage * size * size))


def sample_patches(plan: normalmap.RasterPlan, frames, key, config: ClassifierConfig,
                   patches_per_frame: int = 4, num_frames: int = 32, downsample: bool = False,
                   augment: bool = False, source: str = "sequence"):
    """Random valid patches of a sequence's baked normal maps, spread over time.

    `num_frames` frames are taken evenly over the sequence (all frames if it is shorter), and
    `patches_per_frame` crops are drawn per frame uniformly among the origins whose patch has
    at least ``config.min_coverage`` garment texels (with replacement: a small garment with few
    valid origins still yields patches, some repeated).

    Args:
      plan: raster plan at ``config.texel_size``.
      frames: (T, V, 3) float32 vertex positions, meters.
      key: PRNG key (the result is a deterministic function of it).
      downsample: apply `normalmap.downsample_like_coarse` with ``config.downsample_factor``
        (to make training inputs from FINE simulations).
      augment: random dihedral transform of each crop (training).
      source: name used in error messages.
    Returns:
      (rgb (N, S, S, 3) float32, mask (N, S, S, 1) float32, frame_ids (N,) int64) NumPy.
    Raises:
      ClassifierError: if no patch position reaches the coverage.
    """
    size = config.patch_size
    frames = np.asarray(frames, np.float32)
    if frames.ndim != 3 or frames.shape[0] == 0:
        raise ClassifierError(f"{source}: frames must be (T, V, 3) with T >= 1, got "
                              f"{frames.shape}")
    if valid_origin_count(plan.mask, size, config.min_coverage) == 0:
        raise ClassifierError(
            f"{source}: no {size}x{size} patch at texel size {config.texel_size} m covers "
            f"{config.min_coverage:.0%} garment texels (the garment's UV layout is "
            f"{plan.shape[0]}x{plan.shape[1]} texels with {plan.num_covered} covered); "
            f"nothing to classify")
    t = len(frames)
    ids = np.unique(np.round(np.linspace(0, t - 1, min(num_frames, t))).astype(np.int64))
    shape = _padded_shape(plan.shape, size)
    factor = float(config.downsample_factor) if downsample else 1.0
    keys = jax.random.split(key, len(ids))
    rgbs, masks, fids = [], [], []
    for k, i in zip(keys, ids, strict=True):
        rgb, m, _ = _frame_crops(plan, jnp.asarray(frames[i]), k, patches_per_frame, size,
                                 float(config.min_coverage), factor, augment, shape,
                                 config.normal_frame == "patch")
        rgbs.append(np.asarray(rgb))
        masks.append(np.asarray(m))
        fids.append(np.full(patches_per_frame, i, np.int64))
    return np.concatenate(rgbs), np.concatenate(masks), np.concatenate(fids)


def classify_sequence(classifier: Classifier, frames, garment: Garment, key,
                      patches_per_frame: int = 4, num_frames: int = 16, bins: int = 10,
                      method: str = "histogram", batch_size: int = 16) -> Classification:
    """The material of a coarse garment sequence, by voting over patches sampled across time.

    Args:
      classifier: from `load_classifier` (or training).
      frames: (T, V, 3) float32 coarse vertex positions, meters.
      garment: the garment's topology and UVs (`mesh.Garment`).
      key: PRNG key; the answer is a deterministic function of it.
      patches_per_frame: crops per sampled frame.
      num_frames: frames sampled evenly over the sequence (fewer if T is smaller).
      bins, method: see `vote`.
    Returns:
      Classification (``.material``, ``.scores``, ``.num_patches``, ``.histogram``).
    Raises:
      ClassifierError (a ValueError): if no patch of the garment has enough garment texels.

    Cost: ``patches_per_frame * num_frames`` VGG passes (64 patches by default; see the report
    in experiments/results/classifier for accuracy against the number of patches).
    """
    cfg = classifier.config
    frames = np.asarray(frames, np.float32)
    if frames.ndim != 3 or frames.shape[1:] != (garment.num_vertices, 3):
        raise ClassifierError(f"frames must be (T, {garment.num_vertices}, 3) for this garment, "
                              f"got {frames.shape}")
    if not np.isfinite(frames).all():
        raise ClassifierError("frames contain non-finite vertex positions")
    plan = normalmap.make_plan(garment, texel_size=cfg.texel_size)
    rgb, mask, fids = sample_patches(plan, frames, key, cfg, patches_per_frame, num_frames)
    probs = predict_patches(classifier, rgb, mask, batch_size)
    return classify_patches(classifier, probs, fids, bins, method)


# ---------------------------------------------------------------------------------------------
# Training (on cached features)


@functools.lru_cache(maxsize=8)
def _optimizer(learning_rate: float, weight_decay: float) -> optax.GradientTransformation:
    # Cached: the same object (hash) for the same settings, so the jitted step is reused.
    return optax.adamw(learning_rate, weight_decay=weight_decay)


@functools.partial(jax.jit, static_argnames=("config", "tx"))
def _train_step(params, opt_state, norm, x, y, key, config, tx):
    """One Adam step on a batch of raw features x (B, D) and labels y (B,)."""
    x = _preprocess(x, norm)

    def loss_fn(p):
        logits = _model(config).apply({"params": p}, x, train=True, rngs={"dropout": key})
        return jnp.mean(cross_entropy(logits, y)), logits

    (loss, logits), grads = jax.value_and_grad(loss_fn, has_aux=True)(params)
    updates, opt_state = tx.update(grads, opt_state, params)
    acc = jnp.mean((jnp.argmax(logits, -1) == y).astype(jnp.float32))
    return optax.apply_updates(params, updates), opt_state, {"loss": loss, "accuracy": acc}


def train_classifier(features, labels, config: ClassifierConfig, key, vgg_params=None,
                     steps: int = 2000, batch_size: int = 128, learning_rate: float = 1e-3,
                     weight_decay: float = 1e-4, eval_fn=None, eval_every: int = 0,
                     meta: dict | None = None):
    """Train the MLP on precomputed raw features (VGG is frozen).

    Args:
      features: (N, D) raw features of training patches (float16 or float32, from
        `patch_features` with ``config.feature``).
      labels: (N,) int material indices into ``config.materials``.
      config: ClassifierConfig.
      key: PRNG key (init and dropout derive from it; batches from a NumPy generator
        seeded by it).
      vgg_params: stored in the returned classifier (default: `vgg.load_vgg19()`).
      steps, batch_size, learning_rate, weight_decay: optimization (optax.adamw; the paper
        uses Adam; weight_decay=0 makes it plain Adam).
      eval_fn: optional callable(classifier) -> dict, called every `eval_every` steps.
    Returns:
      (Classifier, history list of dicts with step, loss, accuracy and eval metrics).
    """
    feats = np.asarray(features)
    labels = np.asarray(labels, np.int32)
    if feats.ndim != 2 or len(feats) != len(labels) or len(feats) == 0:
        raise ValueError(f"features (N, D) and labels (N,) must match, got {feats.shape} and "
                         f"{labels.shape}")
    if labels.min() < 0 or labels.max() >= len(config.materials):
        raise ValueError(f"labels must be in [0, {len(config.materials)}), got "
                         f"[{labels.min()}, {labels.max()}]")
    vgg_params = vgg.load_vgg19() if vgg_params is None else vgg_params
    d = feature_dim(vgg_params, config.feature, config.patch_size)
    if feats.shape[1] != d:
        raise ValueError(f"features have {feats.shape[1]} values per patch, {config.feature} "
                         f"gives {d}")
    norm = {k: jnp.asarray(v) for k, v in feature_stats(feats).items()}
    init_key, drop_key = jax.random.split(key)
    clf = init_classifier(init_key, config, vgg_params, norm, meta)
    tx = _optimizer(float(learning_rate), float(weight_decay))
    params, opt_state = clf.params, tx.init(clf.params)
    rng = np.random.default_rng(np.asarray(jax.random.key_data(key)).ravel().tolist())
    drop_keys = jax.random.split(drop_key, steps)
    n = len(feats)
    history = []
    batch_size = min(batch_size, n)
    for step in range(1, steps + 1):
        # Batches gathered on the host: the jitted step sees (B, D) whatever N is, so one
        # compile serves every training set (cross-validation folds included).
        idx = rng.integers(0, n, batch_size)
        params, opt_state, m = _train_step(params, opt_state, norm, feats[idx], labels[idx],
                                           drop_keys[step - 1], config, tx)
        if eval_every and (step % eval_every == 0 or step == steps):
            rec = {"step": step, **{k: float(v) for k, v in m.items()}}
            if eval_fn is not None:
                rec.update(eval_fn(clf._replace(params=params)))
            history.append(rec)
    return clf._replace(params=params), history


# ---------------------------------------------------------------------------------------------
# Files


def save_classifier(path: str | os.PathLike, classifier: Classifier, meta: dict | None = None,
                    dtype=np.float16) -> Path:
    """Write the MLP parameters (float16), standardization and config to `path` atomically.

    The VGG weights are not written (``meta["vgg"]`` should say which were used).
    """
    path = Path(path)
    arrays = modelfile.cast_params(classifier.params, dtype, path, ClassifierError)
    for k, v in classifier.norm.items():
        arrays[f"norm/{k}"] = np.asarray(v, np.float32)
    return modelfile.write(path, arrays, classifier.config.to_json(),
                           {**classifier.meta, **(meta or {})}, _FORMAT)


def load_classifier(path: str | os.PathLike | None = None, vgg_params=None) -> Classifier:
    """Load a classifier file (default: the shipped ``wrinkle_jax/assets/classifier.npz``).

    Args:
      path: an ``.npz`` written by `save_classifier`; None for `DEFAULT_PATH`.
      vgg_params: the VGG19 to compute features with (default: `vgg.load_vgg19()`, the
        weights the shipped model was trained with).
    Raises:
      ClassifierError: naming the file, if it is missing, not a classifier file, or its
        parameters do not match its config and the VGG.
    """
    path = Path(DEFAULT_PATH if path is None else path)
    if not path.is_file():
        hint = (" (the shipped model is trained by "
                "`python -m experiments.classifier_report --ship`)" if path == DEFAULT_PATH
                else "")
        raise ClassifierError(f"{path}: no such classifier file{hint}")
    files, config, meta = modelfile.read(path, "classifier", _FORMAT, ClassifierError)
    try:
        config = ClassifierConfig.from_json(config)
    except (TypeError, ValueError, KeyError) as e:
        raise ClassifierError(f"{path}: not a readable classifier file ({e})") from None
    vgg_params = vgg.load_vgg19() if vgg_params is None else vgg_params
    flat = modelfile.float32_params(files)
    norm = {k[len("norm/"):]: jnp.asarray(v, jnp.float32) for k, v in files.items()
            if k.startswith("norm/")}
    try:
        d = feature_dim(vgg_params, config.feature, config.patch_size)
    except ValueError as e:
        raise ClassifierError(f"{path}: {e}") from None
    want = jax.eval_shape(lambda: _model(config).init(jax.random.key(0, impl="rbg"),
                                                      jnp.zeros((1, d)))["params"])
    want_shapes = modelfile.flatten(want, lambda s: tuple(s.shape))
    got_shapes = {k: v.shape for k, v in flat.items()}
    if want_shapes != got_shapes or set(norm) != {"mean", "std"} or any(
            v.shape != (d,) for v in norm.values()):
        raise ClassifierError(f"{path}: parameters do not match the config ({config.feature}, "
                              f"hidden {config.hidden}, {d} features with this VGG)")
    if not all(np.all(np.isfinite(v)) for v in flat.values()):
        raise ClassifierError(f"{path}: non-finite parameters")
    params = jax.tree.map(jnp.asarray, modelfile.unflatten(flat))
    return Classifier(config, params, norm, vgg_params, meta)

