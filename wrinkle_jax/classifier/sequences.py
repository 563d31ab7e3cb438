"""Classifying a garment sequence: valid random crops of its baked normal maps, spread over
time, then the model and the vote. Vertices are meters."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from wrinkle_jax import normalmap, patches
from wrinkle_jax.classifier.config import ClassifierConfig, ClassifierError
from wrinkle_jax.classifier.model import Classifier, predict_patches
from wrinkle_jax.classifier.voting import Classification, classify_patches
from wrinkle_jax.mesh import Garment
from wrinkle_jax.numerics import normalize


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
