"""Scoring with shared Gram matrices: the improvement score of several methods on the same
patches, with the VGG Gram matrices of the input and the target computed once and reused by
every method (`method_losses` + `scores.scores_from_losses` == `scores.score_patches`).

Patches (N, S, S, 3) in the RGB form, (N, S, S, 1) mask.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from wrinkle_jax.evaluation.scores import EVAL_LAYERS
from wrinkle_jax.evaluation.sets import upper_triangle
from wrinkle_jax.nn import losses, vgg

__all__ = ["flat_grams", "gram_matrices", "method_losses", "pairwise_losses", "set_features"]


@functools.lru_cache(maxsize=8)
def _gram_fn(layers: tuple[str, ...], pool: str):
    def fn(vgg_params, images, mask):
        feats = vgg.features(vgg_params, images, layers=layers, pool=pool)
        levels = losses.mask_pyramid(mask, max(vgg.layer_level(n) for n in layers) + 1)
        return {n: losses.gram(feats[n], levels[vgg.layer_level(n)], normalize=True)
                for n in layers}
    return jax.jit(fn)


@jax.jit
def _gram_loss(grams_a: dict, grams_b: dict):
    """sum_l ||G_l(a)/R_l - G_l(b)/R_l||_F^2 / 4, per sample (N,): `losses.style_loss` with unit
    layer weights, from precomputed normalized Gram matrices."""
    total = 0.0
    for name in sorted(grams_a):
        d = grams_a[name] - grams_b[name]
        total = total + jnp.sum(d * d, axis=(1, 2)) / 4.0
    return total


def gram_matrices(vgg_params, images, mask, layers=EVAL_LAYERS, pool: str = "avg"):
    """Normalized masked Gram matrices G_l / R_l of a batch: dict layer -> (N, C_l, C_l).

    images: (N, S, S, 3) RGB form; mask: (N, S, S, 1). One jitted VGG pass (compiled per
    batch shape: pass fixed-size batches).
    """
    return _gram_fn(tuple(layers), pool)(vgg_params, jnp.asarray(images, jnp.float32),
                                         jnp.asarray(mask, jnp.float32))


def method_losses(vgg_params, inp, target, mask, outputs: dict[str, np.ndarray],
                  layers=EVAL_LAYERS, pool: str = "avg", batch_size: int = 16,
                  counter: dict | None = None) -> dict[str, np.ndarray]:
    """Style losses against the target of the input and of every method's output.

    The target's and the input's Gram matrices are computed once per batch and shared by all
    methods; an output equal to the input (identity) reuses the input's. VGG passes per patch:
    2 + (number of outputs that differ from the input), against 3 per method for
    `evaluation.score_patches`.

    Args:
      inp, target: (N, S, S, 3) RGB form; mask: (N, S, S, 1); outputs: name -> (N, S, S, 3).
      counter: optional dict; "vgg_passes" accumulates image-batches run through VGG.
    Returns:
      {"input": L(N) (N,), <name>: L(N*) (N,) for every output} float32.
    """
    n = len(inp)
    counter = {} if counter is None else counter
    parts: dict[str, list] = {"input": [], **{k: [] for k in outputs}}

    def grams(x, idx):
        counter["vgg_passes"] = counter.get("vgg_passes", 0) + 1
        return gram_matrices(vgg_params, np.asarray(x)[idx], np.asarray(mask)[idx], layers, pool)

    for s in range(0, n, batch_size):
        k = min(batch_size, n - s)
        idx = np.resize(np.arange(s, s + k), batch_size)  # fixed shape: one compile
        g_t = grams(target, idx)
        g_i = grams(inp, idx)
        loss_in = _gram_loss(g_i, g_t)
        parts["input"].append(np.asarray(loss_in)[:k])
        for name, out in outputs.items():
            if np.array_equal(np.asarray(out)[s:s + k], np.asarray(inp)[s:s + k]):
                loss = loss_in
            else:
                loss = _gram_loss(grams(out, idx), g_t)
            parts[name].append(np.asarray(loss)[:k])
    return {k: (np.concatenate(v) if v else np.zeros(0, np.float32)).astype(np.float32)
            for k, v in parts.items()}


def _batched_grams(vgg_params, images, mask, batch_size: int, layers=EVAL_LAYERS,
                   counter: dict | None = None):
    """Yield the normalized masked Grams of consecutive batches of (N, S, S, 3) images:
    layer -> (k, C_l, C_l) NumPy for the k real rows of each batch. Every VGG pass has the
    fixed shape `batch_size` (the last batch padded), so it compiles once;
    counter["vgg_passes"] accumulates batches."""
    counter = {} if counter is None else counter
    images, mask = np.asarray(images), np.asarray(mask)
    for s in range(0, len(images), batch_size):
        k = min(batch_size, len(images) - s)
        idx = np.resize(np.arange(s, s + k), batch_size)
        grams = gram_matrices(vgg_params, images[idx], mask[idx], layers)
        counter["vgg_passes"] = counter.get("vgg_passes", 0) + 1
        yield {name: np.asarray(g)[:k] for name, g in grams.items()}


def set_features(vgg_params, images, mask, batch_size: int, counter: dict | None = None
                 ) -> dict[str, np.ndarray]:
    """Upper triangles of the normalized masked Grams (`gram_matrices` on
    `EVAL_LAYERS`) of (N, S, S, 3) RGB-form images with (N, S, S, 1) masks:
    layer -> (N, C_l (C_l + 1) / 2) float32. Fixed batch shape (the last batch padded);
    counter["vgg_passes"] accumulates batches."""
    parts: dict[str, list] = {}
    for grams in _batched_grams(vgg_params, images, mask, batch_size, counter=counter):
        for name, v in upper_triangle(grams).items():
            parts.setdefault(name, []).append(v)
    return {name: np.concatenate(v) for name, v in parts.items()}


def flat_grams(vgg_params, images, mask, batch_size: int = 16, layers=EVAL_LAYERS
               ) -> dict[str, np.ndarray]:
    """Flattened normalized masked Grams of (N, S, S, 3) RGB-form images with (N, S, S, 1)
    masks: layer -> (N, C_l * C_l) float32 (fixed batch shape, the last batch padded). The
    rows feed `pairwise_losses`."""
    parts: dict[str, list] = {name: [] for name in layers}
    for grams in _batched_grams(vgg_params, images, mask, batch_size, layers):
        for name in layers:
            parts[name].append(grams[name].reshape(len(grams[name]), -1))
    return {name: np.concatenate(v) if v else np.zeros((0, 0), np.float32)
            for name, v in parts.items()}


def pairwise_losses(grams_a: dict[str, np.ndarray], grams_b: dict[str, np.ndarray]
                    ) -> np.ndarray:
    """(Na, Nb) style losses between every row of two `flat_grams` sets: entry (i, j) is the
    loss `method_losses` would give for image i against target j (unit layer weights,
    ||G_a - G_b||_F^2 / 4 summed over layers), from ||a||^2 + ||b||^2 - 2 a.b. Both sets are
    first centred on b's mean row (distances do not change; Grams share a large common part,
    whose cancellation would otherwise cost float32 digits); norms accumulate in float64;
    clipped at 0 against rounding."""
    total = 0.0
    for name in sorted(grams_a):
        centre = np.mean(np.asarray(grams_b[name], np.float64), axis=0)
        a = (np.asarray(grams_a[name], np.float64) - centre).astype(np.float32)
        b = (np.asarray(grams_b[name], np.float64) - centre).astype(np.float32)
        na = np.einsum("ij,ij->i", a, a, dtype=np.float64)
        nb = np.einsum("ij,ij->i", b, b, dtype=np.float64)
        total = total + (na[:, None] + nb[None] - 2.0 * (a @ b.T).astype(np.float64)) / 4.0
    return np.maximum(total, 0.0)
