"""Function-preserving widening of a trained `CINUNet` (warm-start a wider network).

Training is bound by the VGG loss, not by the U-Net (at width 16 the U-Net is a few percent of
a step), so more U-Net channels cost little per step; but a wider network trained from random
weights needs thousands of steps to get back to a trained narrow one. `widen_params` embeds
the narrow network's parameters in a wider parameter tree so that the wide network computes
exactly the same function at step 0 and every new channel can still learn:

- each kernel (kh, kw, C_in, C_out) keeps the old block [:, :, :c_in, :c_out]; weights from
  NEW input channels into OLD output channels are zero (old channels see exactly what they
  saw before); weights into NEW output channels keep the fresh (random) initialization, so
  the new channels compute distinct features (no symmetry to break);
- biases and the CIN tables (materials, C) keep the old entries, new channels keep their
  fresh values (CIN scale 1, shift 0: instance norm is per channel, so new channels never
  mix into old ones);
- the output conv's weights from new channels are zero, so the output is unchanged; their
  gradient is (new activation x output gradient), non-zero, so training moves them.

Every other leaf (e.g. the per-material unsharp gain) is copied. Shapes are checked: a leaf
may only grow, and only in its channel axes.
"""

from __future__ import annotations

import jax
import numpy as np

__all__ = ["widen_params"]


def _widen_leaf(path: str, old: np.ndarray, fresh: np.ndarray) -> np.ndarray:
    old, fresh = np.asarray(old), np.asarray(fresh)
    if old.ndim != fresh.ndim or any(o > f for o, f in zip(old.shape, fresh.shape, strict=True)):
        raise ValueError(f"{path}: cannot widen {old.shape} into {fresh.shape}")
    out = np.array(fresh, dtype=np.result_type(old, fresh), copy=True)
    if old.ndim == 4:  # conv kernel (kh, kw, C_in, C_out)
        if old.shape[:2] != fresh.shape[:2]:
            raise ValueError(f"{path}: kernel size {old.shape[:2]} != {fresh.shape[:2]}")
        ci, co = old.shape[2:]
        out[:, :, :ci, :co] = old
        out[:, :, ci:, :co] = 0.0  # new inputs must not reach old outputs
    elif old.ndim == 2:  # CIN table (materials, C)
        if old.shape[0] != fresh.shape[0]:
            raise ValueError(f"{path}: {old.shape[0]} materials != {fresh.shape[0]}")
        out[:, :old.shape[1]] = old
    elif old.ndim == 1:  # bias (C,) or a per-material vector of the same length
        out[:old.shape[0]] = old
    elif old.shape == fresh.shape:
        out[...] = old
    else:
        raise ValueError(f"{path}: unexpected leaf of shape {old.shape}")
    return out


def widen_params(old_params, fresh_params):
    """Embed a trained U-Net's parameters in a wider network's freshly initialized tree.

    Args:
      old_params: parameters of a `CINUNet` of width w (same config otherwise).
      fresh_params: parameters of the same `CINUNet` at width w' >= w, freshly initialized
        (`unet.init_params`); the same tree structure and leaf names.
    Returns:
      A parameter tree shaped like `fresh_params` whose network computes the same output as
      `old_params`' network (to float32 rounding) for every input.
    Raises:
      ValueError: the trees differ in structure or a leaf would shrink.
    """
    old_leaves = dict(jax.tree_util.tree_leaves_with_path(old_params))
    fresh_flat, treedef = jax.tree_util.tree_flatten_with_path(fresh_params)
    if set(old_leaves) != {p for p, _ in fresh_flat}:
        raise ValueError("widen_params: the parameter trees have different leaves")
    leaves = [_widen_leaf(jax.tree_util.keystr(p), old_leaves[p], v) for p, v in fresh_flat]
    return jax.tree_util.tree_unflatten(treedef, leaves)
