"""Training the classifier's MLP on cached features (the VGG19 is frozen)."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import optax

from wrinkle_jax.classifier.config import ClassifierConfig, feature_dim
from wrinkle_jax.classifier.features import _preprocess, feature_stats
from wrinkle_jax.classifier.model import _model, cross_entropy, init_classifier
from wrinkle_jax.nn import vgg


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
