"""A bank of fine-target Gram features per material, and the set-level "realism" distance.

The paired style loss compares each output with its own target; where the target's detail is
not predictable from the input (on unseen garments the fine wrinkles' local energy is at most
~60 % explained by anything coarse), its minimiser is the conditional mean of the targets'
Gram statistics, i.e. a sharpened input. Table 2 judges the output *set* instead: the
Chamfer distance between the outputs' Gram features and the fine patches'. This module gives
the training side of that: a fixed bank of fine Gram feature vectors per material and, per
output patch, the distance to its nearest bank entry of the same material (one direction of
the Chamfer distance: every output should look like *some* fine patch of its material).

Features are Table 2's (`wrinkle_jax.evaluation.sets`): per layer the upper triangle of the
normalized masked Gram matrix G_l / R_l (`nn.losses.gram`), divided by the layer's median
vector norm over the bank (so every layer weighs alike), concatenated over the layers.

Shapes: a bank holds M = materials x K rows of D = sum_l C_l (C_l + 1) / 2 float32 features
(D = 174,560 for relu1_2, relu2_1, relu3_1, relu4_1); at K = 128 per material and 5 materials
that is 447 MB.
"""

from __future__ import annotations

import dataclasses
import io
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from wrinkle_jax.evaluation import sets as set_lib
from wrinkle_jax.fileio import NPZ_READ_ERRORS, atomic_write_bytes
from wrinkle_jax.nn import losses, vgg

__all__ = ["GramBank", "build_bank", "feature_vectors", "load_bank", "nearest_distance",
           "save_bank"]


@dataclasses.dataclass(frozen=True)
class GramBank:
    """Bank rows and how they were scaled.

    Attributes:
      vectors: (M, D) float32 scaled features.
      material: (M,) int32 material id of each row.
      layers: the VGG layers, in concatenation order.
      scales: (L,) float32 divisor of each layer's block (its median row norm in the bank).
    """

    vectors: np.ndarray
    material: np.ndarray
    layers: tuple[str, ...]
    scales: np.ndarray


def _blocks(feats: dict, mask, layers) -> list:
    """Per layer, (N, C_l (C_l + 1) / 2) upper triangles of the normalized masked Grams."""
    masks = losses.mask_pyramid(mask, max(vgg.layer_level(n) for n in layers) + 1)
    out = []
    for name in layers:
        g = losses.gram(feats[name], masks[vgg.layer_level(name)], normalize=True)
        rows, cols = np.triu_indices(g.shape[-1])
        out.append(g[:, rows, cols])
    return out


def feature_vectors(feats: dict, mask, bank: GramBank):
    """A batch's features in the bank's space.

    Args:
      feats: layer -> (N, h_l, w_l, C_l) VGG features (`vgg.features`), at least `bank.layers`.
      mask: (N, H, W, 1) full-resolution mask in [0, 1].
      bank: gives the layers, their order and scales.
    Returns:
      (N, D) float32: each layer's upper-triangle normalized Gram divided by its bank scale,
      concatenated.
    """
    blocks = _blocks(feats, mask, bank.layers)
    return jnp.concatenate([b / s for b, s in zip(blocks, bank.scales.tolist(), strict=True)],
                           axis=1)


def nearest_distance(x, material, bank_vectors, bank_material, eps: float = 1e-8):
    """Per row of `x`, the Euclidean distance to the nearest bank row of the same material.

    Args:
      x: (N, D) scaled features (`feature_vectors` with the bank's scales).
      material: (N,) int material ids.
      bank_vectors: (M, D); bank_material: (M,) int.
      eps: floor of the squared distance (a finite gradient at a bank row).
    Returns:
      (N,) float32; +inf where the bank has no row of that material.
    """
    x = x.astype(jnp.float32)
    d2 = (jnp.sum(x * x, axis=1)[:, None] + jnp.sum(bank_vectors * bank_vectors, axis=1)[None]
          - 2.0 * x @ bank_vectors.T)
    same = material[:, None] == bank_material[None, :]
    d2 = jnp.where(same, d2, jnp.inf)
    return jnp.sqrt(jnp.maximum(jnp.min(d2, axis=1), eps))


def build_bank(vgg_params, images, mask, material, layers, batch_size: int = 8,
               conv_impl: str = "xla") -> GramBank:
    """Scaled Gram features of (M, S, S, 3) RGB-form images with (M, S, S, 1) masks.

    `material`: (M,) int. Run in fixed-size batches (the last one padded with empty masks,
    whose rows are dropped). Each layer's scale is its median row norm over the M rows.
    """
    layers = tuple(layers)

    @jax.jit
    def blocks(img, m):
        f = vgg.features(vgg_params, img, layers=layers, conv_impl=conv_impl)
        return _blocks(f, m, layers)

    n = len(images)
    parts: list[list[np.ndarray]] = [[] for _ in layers]
    for i in range(0, n, batch_size):
        img = np.zeros((batch_size, *images.shape[1:]), np.float32)
        m = np.zeros((batch_size, *mask.shape[1:]), np.float32)
        k = min(batch_size, n - i)
        img[:k], m[:k] = images[i:i + k], mask[i:i + k]
        for j, b in enumerate(blocks(img, m)):
            parts[j].append(np.asarray(b)[:k])
    flat = {name: np.concatenate(p) for name, p in zip(layers, parts, strict=True)}
    scales = set_lib.layer_scales(flat)  # Table 2's own scaling and concatenation
    v = set_lib.scaled_features(flat, scales).astype(np.float32)
    return GramBank(v, np.asarray(material, np.int32), layers,
                    np.array([scales[name] for name in layers], np.float32))


def save_bank(path: str | Path, bank: GramBank) -> None:
    """Write `bank` to `path` (.npz) atomically: a training run killed while saving leaves no
    partial bank for its resumed run to load."""
    buf = io.BytesIO()
    np.savez(buf, vectors=bank.vectors, material=bank.material,
             layers=np.array(bank.layers), scales=bank.scales)
    atomic_write_bytes(path, buf.getvalue())


def load_bank(path: str | Path) -> GramBank:
    """The bank `save_bank` wrote to `path`.

    Raises:
      ValueError: naming the file, if it is unreadable or not a bank.
    """
    try:
        with np.load(path, allow_pickle=False) as z:
            return GramBank(z["vectors"], z["material"], tuple(str(s) for s in z["layers"]),
                            z["scales"])
    except NPZ_READ_ERRORS as e:
        raise ValueError(f"{path}: not a readable Gram bank ({type(e).__name__}: {e})") from None
