"""Patches of UV maps: regular tiling, weighted merging, random valid crops, dihedral augmentation.

The enhancer network works on fixed-size square patches of a normal map (128 x 128 texels by
default; a texel has the same physical size on every garment, so a patch always covers the same
cloth area). This module cuts maps into patches and puts them back together.

Contract:

- Maps are ``(H, W, C)`` float32 images (a normal map has ``C = 3`` unit vectors in ``[-1, 1]``);
  masks are ``(H, W, 1)`` (or ``(H, W)``) float32, ``> 0`` on garment texels, ``0`` on the
  background. Batches of patches are ``(P, size, size, C)``; patch origins are ``(P, 2)`` int32
  ``(row, col)`` of the top-left texel; `extract` and `merge` clamp them into
  ``[0, H - size] x [0, W - size]``.
- Setup that depends only on the mask runs once in NumPy: `tile` (inference-time grid) and
  `pad_to_patch`. Everything else is jittable JAX with static shapes: patch ``size``, patch count
  ``n``, the merge output ``shape``, ``window``, ``augment`` and ``vector_mode`` are static
  (``static_argnames``); origins, images, masks, keys and dihedral indices may be traced.
- `tile` requires the map to be at least ``size`` texels in both dimensions and raises a
  ValueError otherwise: pad first with `pad_to_patch` (zeros on the bottom/right), tile, enhance
  and merge at the padded shape, then crop back with ``merged[:h, :w]``.
- ``merge(extract(x, o, s), o, x.shape)`` with ``window="uniform"`` reproduces ``x`` bit for bit on
  every texel covered by a patch (see `merge` for how the float32 sum is kept exact), and returns
  0 with coverage 0 elsewhere.
- `random_crops` (training) samples origins uniformly among those whose patch has a mask
  fraction ``>= min_coverage`` (a summed-area table gives every origin's coverage at once) and
  raises a ValueError when there is none (under jit it falls back, see `sample_origins`).
- Dihedral index ``k`` in ``0..7``: ``k % 4`` counter-clockwise quarter turns applied after a
  left-right mirror when ``k >= 4``, i.e. ``rot90(fliplr(x) if k >= 4 else x, k % 4)``.
  Vector convention for `dihedral_normals`: x = +column (right), y = -row (up), z = out of the
  image; the (x, y) components turn with the image, z is unchanged.

Example:
  >>> import numpy as np, jax.numpy as jnp
  >>> mask = np.zeros((200, 300, 1), np.float32); mask[40:160, 50:250] = 1
  >>> normals = jnp.zeros((200, 300, 3)).at[..., 2].set(1.0)
  >>> origins = tile(mask, size=128, stride=64)              # NumPy, once per UV layout
  >>> patches = extract(normals, origins, 128)               # (P, 128, 128, 3)
  >>> merged, coverage = merge(patches, origins, (200, 300), window="hann", mask=mask)
  >>> merged.shape, coverage.shape
  ((200, 300, 3), (200, 300, 1))
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from wrinkle_jax.numerics import normalize, safe_div

# Number of elements of the dihedral group of the square (4 rotations x optional mirror).
DIHEDRAL_COUNT = 8
# Floor of the 1D Hann weight (reached half a texel outside the patch): every texel keeps a
# weight > 0, about HANN_FLOOR at the edges and about HANN_FLOOR**2 in the corners.
HANN_FLOOR = 1e-2
WINDOWS = ("uniform", "hann")
VECTOR_MODES = ("none", "rotate")

# Inverse of each dihedral index: quarter turns undo with the opposite turn, mirrors are
# involutions.
DIHEDRAL_INVERSE = (0, 3, 2, 1, 4, 5, 6, 7)

# Linear map of the in-plane vector components (x = +column, y = -row) for each dihedral index:
# a mirror (x -> -x) first, then k % 4 counter-clockwise quarter turns ((x, y) -> (-y, x)).
_QUARTER_TURN = np.array([[0, -1], [1, 0]], np.int64)
_MIRROR_X = np.array([[-1, 0], [0, 1]], np.int64)
_DIHEDRAL_VECTOR_MAPS = np.stack(
    [
        np.linalg.matrix_power(_QUARTER_TURN, k % 4) @ np.linalg.matrix_power(_MIRROR_X, k // 4)
        for k in range(DIHEDRAL_COUNT)
    ]
).astype(np.float32)  # (8, 2, 2)

# Significand bits cleared to form the "high" half of a float32 in the exact uniform merge.
_SPLIT_MASK = np.uint32(0xFFFFF000)


# --------------------------------------------------------------------------------------------
# Inference-time tiling (NumPy, once per mask)
# --------------------------------------------------------------------------------------------


def _mask_2d(mask) -> np.ndarray:
    """(H, W) bool of garment texels from an (H, W) or (H, W, 1) NumPy-convertible mask."""
    m = np.asarray(mask)
    if m.ndim == 3 and m.shape[-1] == 1:
        m = m[..., 0]
    if m.ndim != 2:
        raise ValueError(f"mask must have shape (H, W) or (H, W, 1), got {m.shape}")
    return m > 0


def _check_size_stride(size: int, stride: int) -> None:
    if int(size) <= 0:
        raise ValueError(f"patch size must be positive, got {size}")
    if not 0 < int(stride) <= int(size):
        raise ValueError(
            f"stride must be in 1..size={size} so that the patches cover the map without gaps, "
            f"got {stride}"
        )


def grid_starts(length: int, size: int, stride: int) -> np.ndarray:
    """Patch start positions along one axis: ``0, stride, 2*stride, ...`` clamped at the end.

    The last start is ``length - size`` (added if the regular grid does not land on it), so the
    patches cover ``[0, length)`` without leaving it.

    Args:
      length: axis length in texels, ``>= size``.
      size: patch size in texels.
      stride: step between starts, ``1 <= stride <= size``.
    Returns:
      (K,) int64 strictly increasing starts.
    """
    _check_size_stride(size, stride)
    if length < size:
        raise ValueError(f"axis of length {length} is shorter than a patch of size {size}")
    starts = np.arange(0, length - size + 1, stride, dtype=np.int64)
    if starts[-1] != length - size:
        starts = np.append(starts, length - size)
    return starts


def _patch_mask_counts(m: np.ndarray, rows: np.ndarray, cols: np.ndarray, size: int):
    """Number of mask texels in each grid patch, from a summed-area table: (R, C) int64."""
    sat = np.zeros((m.shape[0] + 1, m.shape[1] + 1), np.int64)
    sat[1:, 1:] = np.cumsum(np.cumsum(m, axis=0, dtype=np.int64), axis=1)
    r0, c0 = rows[:, None], cols[None, :]
    r1, c1 = r0 + size, c0 + size
    return sat[r1, c1] - sat[r0, c1] - sat[r1, c0] + sat[r0, c0]


def tile(mask, size: int = 128, stride: int = 64) -> np.ndarray:
    """Origins of a regular grid of overlapping patches covering every garment texel.

    The grid steps by ``stride``; its last row/column is clamped to ``H - size`` / ``W - size``
    (ragged border), so patches never leave the map and together cover every texel. Patches
    without any mask texel are skipped.

    Args:
      mask: (H, W, 1) or (H, W) array, ``> 0`` on garment texels; ``H, W >= size``.
      size: patch size in texels.
      stride: grid step in texels, ``1 <= stride <= size`` (``size // 2`` gives 2x overlap).
    Returns:
      (P, 2) int32 ``(row, col)`` origins in row-major order; (0, 2) for an empty mask.
    Raises:
      ValueError: if the map is smaller than a patch (pad it with `pad_to_patch` first), or if
        ``size``/``stride`` are invalid.
    """
    m = _mask_2d(mask)
    _check_size_stride(size, stride)
    h, w = m.shape
    if h < size or w < size:
        raise ValueError(
            f"map of shape {(h, w)} is smaller than a {size}x{size} patch; pad the mask and "
            f"the image with pad_to_patch(x, {size}) first and crop the merged result back"
        )
    rows, cols = grid_starts(h, size, stride), grid_starts(w, size, stride)
    keep = _patch_mask_counts(m, rows, cols, size) > 0
    rr, cc = np.meshgrid(rows, cols, indexing="ij")
    return np.stack([rr[keep], cc[keep]], axis=-1).astype(np.int32).reshape(-1, 2)


def pad_to_patch(image, size: int = 128):
    """Zero-pad the bottom/right of a map so both spatial dimensions are at least ``size``.

    Args:
      image: (H, W) or (H, W, C) NumPy or JAX array (a map or its mask).
      size: patch size in texels.
    Returns:
      ``(padded, shape)``: padded (max(H, size), max(W, size), ...) array of the same kind and
      dtype, and the original ``image.shape`` (crop back with ``x[:shape[0], :shape[1]]``).
    """
    shape = tuple(image.shape)
    if len(shape) < 2:
        raise ValueError(f"image must have at least 2 dimensions (H, W, ...), got {shape}")
    pad = [(0, max(int(size) - shape[0], 0)), (0, max(int(size) - shape[1], 0))]
    pad += [(0, 0)] * (len(shape) - 2)
    xp = jnp if isinstance(image, jax.Array) else np
    return xp.pad(image, pad), shape


# --------------------------------------------------------------------------------------------
# Extraction and merging (jittable; size and shape static)
# --------------------------------------------------------------------------------------------


def _clamp_origins(origins, height: int, width: int, size: int):
    """(P, 2) int32 origins clamped to [0, H - size] x [0, W - size] (no negative wrap-around)."""
    origins = jnp.asarray(origins, jnp.int32).reshape(-1, 2)
    return jnp.clip(origins, 0, jnp.array([height - size, width - size], jnp.int32))


def extract(image, origins, size: int):
    """Cut square patches out of a map.

    Jittable with ``size`` static; origins may be traced. Origins outside
    ``[0, H - size] x [0, W - size]`` are clamped into it (as in `merge`).

    Args:
      image: (H, W, C) array.
      origins: (P, 2) int ``(row, col)`` top-left texels.
      size: patch size in texels (static).
    Returns:
      (P, size, size, C) patches, same dtype as ``image``.
    """
    # One jitted program (not a dozen eager ops, each compiled on first use in a notebook).
    return _extract(image, _index_array(origins), size=int(size))


def _index_array(origins):
    """Origins that are not JAX values as a NumPy array (a jitted call's argument)."""
    return origins if isinstance(origins, jax.Array) else np.asarray(origins)


@functools.partial(jax.jit, static_argnames=("size",))
def _extract(image, origins, size: int):
    image = jnp.asarray(image)
    if image.ndim != 3:
        raise ValueError(f"image must have shape (H, W, C), got {image.shape}")
    height, width, channels = image.shape
    if height < size or width < size:
        raise ValueError(f"image of shape {image.shape} is smaller than {size}x{size} patches")
    origins = _clamp_origins(origins, height, width, size)
    zero = jnp.zeros((), jnp.int32)

    def one(origin):
        return lax.dynamic_slice(image, (origin[0], origin[1], zero), (size, size, channels))

    return jax.vmap(one)(origins)


@functools.lru_cache(maxsize=32)
def _window_np(size: int, window: str) -> np.ndarray:
    if window == "uniform":
        return np.ones((size, size), np.float32)
    if window == "hann":
        t = (np.arange(size, dtype=np.float64) + 0.5) / size
        w1 = HANN_FLOOR + (1.0 - HANN_FLOOR) * np.sin(np.pi * t) ** 2
        return np.outer(w1, w1).astype(np.float32)
    raise ValueError(f"unknown window {window!r}; expected one of {', '.join(WINDOWS)}")


def window_weights(size: int, window: str = "uniform"):
    """Per-texel blending weights of one patch.

    ``"uniform"`` is all ones (plain averaging, as in the paper). ``"hann"`` is the separable
    ``w(r) * w(c)`` with ``w(t) = HANN_FLOOR + (1 - HANN_FLOOR) * sin^2(pi * (t + 0.5) / size)``:
    about 1 at the centre, falling smoothly to about ``HANN_FLOOR`` at the border and never 0,
    so every covered texel keeps a positive weight while seams between patches fade out.

    Args:
      size: patch size in texels.
      window: ``"uniform"`` or ``"hann"``.
    Returns:
      (size, size) float32 weights in ``(0, 1]``.
    """
    return jnp.asarray(_window_np(int(size), window))


def _patch_indices(origin, size: int):
    """Row (size, 1) and column (1, size) target indices of the texels of one patch."""
    offsets = jnp.arange(size, dtype=jnp.int32)
    return (origin[0] + offsets)[:, None], (origin[1] + offsets)[None, :]


def _split_float32(x):
    """x = hi + lo exactly, each with at most 12 significant bits (hi has no gradient).

    Summing up to 4096 copies of either half is exact in float32, which keeps the uniform merge
    an exact inverse of `extract` even where 3, 5, 6, ... patches overlap.
    """
    bits = lax.bitcast_convert_type(x, jnp.uint32) & _SPLIT_MASK
    hi = lax.stop_gradient(lax.bitcast_convert_type(bits, jnp.float32))
    return hi, x - hi


def merge(
    patches,
    origins,
    shape,
    window: str = "uniform",
    mask=None,
    renormalize: bool = False,
):
    """Weighted average of overlapping patches back into a map.

    A scatter-add (``.at[rows, cols].add`` with the per-patch texel indices built under
    `jax.vmap`; no Python loop over patches) accumulates ``weight * patch`` and ``weight`` in
    float32, then a guarded division averages. Texels that no patch covers (or, given ``mask``,
    background texels) are 0 with coverage 0. Origins are clamped into the map exactly as
    `extract` clamps them. Jittable with ``shape``, ``window`` and ``renormalize`` static;
    origins may be traced; differentiable with respect to ``patches``.

    With ``window="uniform"`` and float32 patches, the values are split into two 12-bit halves
    that are accumulated separately, so every partial sum is exact: merging patches that agree
    where they overlap (e.g. ``extract`` output) returns the map bit for bit, also where 3, 5,
    6, ... patches overlap (a plain float32 average is off by an ulp there). This costs C extra
    channels in the scatter.

    Args:
      patches: (P, size, size, C) float array.
      origins: (P, 2) int ``(row, col)`` origins (clamped to ``[0, H - size] x [0, W - size]``).
      shape: static ``(H, W)`` or ``(H, W, C)`` of the output map, ``H, W >= size``.
      window: ``"uniform"`` (plain average) or ``"hann"`` (see `window_weights`).
      mask: optional (H, W, 1) or (H, W) mask; texels with ``mask <= 0`` are set to 0 and get
        coverage 0.
      renormalize: if True, rescale the merged vectors (last axis) to unit length with the
        guarded `normalize` (for normal maps; zero vectors stay zero).
    Returns:
      ``(merged, coverage)``: (H, W, C) merged map in the dtype of ``patches`` and (H, W, 1)
      float32 sum of window weights per texel (the number of covering patches for "uniform").
    """
    # One jitted program (not ~25 eager ops, each compiled on first use in a notebook).
    return _merge(patches, _index_array(origins), mask,
                  shape=tuple(int(s) for s in shape), window=window,
                  renormalize=bool(renormalize))


@functools.partial(jax.jit, static_argnames=("shape", "window", "renormalize"))
def _merge(patches, origins, mask, shape, window: str, renormalize: bool):
    patches = jnp.asarray(patches)
    if patches.ndim != 4 or patches.shape[1] != patches.shape[2]:
        raise ValueError(f"patches must have shape (P, size, size, C), got {patches.shape}")
    n_patches, size, _, channels = patches.shape
    height, width = shape[0], shape[1]
    if len(shape) > 2 and shape[2] != channels:
        raise ValueError(f"shape {shape} does not match {channels} patch channels")
    origins = jnp.asarray(origins).reshape(-1, 2)
    if origins.shape[0] != n_patches:
        raise ValueError(f"{origins.shape[0]} origins for {n_patches} patches")
    if height < size or width < size:
        raise ValueError(f"output shape {(height, width)} is smaller than {size}x{size} patches")

    weights = window_weights(size, window)[None, :, :, None]  # (1, size, size, 1)
    origins = _clamp_origins(origins, height, width, size)  # as in `extract`
    rows, cols = jax.vmap(_patch_indices, in_axes=(0, None))(origins, size)  # (P,S,1), (P,1,S)

    def scatter_add(values):  # (P, S, S, K) -> (H, W, K) float32
        out = jnp.zeros((height, width, values.shape[-1]), jnp.float32)
        return out.at[rows, cols].add(values.astype(jnp.float32), mode="drop")

    # Layouts below were the fastest measured on CPU (one scatter for 'hann'; for the exact
    # uniform path a separate all-ones weight scatter beat concatenating a weight channel).
    if window == "uniform" and patches.dtype == jnp.float32:
        halves = scatter_add(jnp.concatenate(_split_float32(patches), axis=-1))  # (H, W, 2C)
        weight_sum = scatter_add(jnp.ones((n_patches, size, size, 1), jnp.float32))
        merged = (safe_div(halves[..., :channels], weight_sum)
                  + safe_div(halves[..., channels:], weight_sum))
    else:
        weighted = weights.astype(jnp.float32) * patches.astype(jnp.float32)
        stacked = scatter_add(jnp.concatenate(
            [weighted, jnp.broadcast_to(weights, (n_patches, size, size, 1))], axis=-1))
        weight_sum = stacked[..., -1:]
        merged = safe_div(stacked[..., :-1], weight_sum)
    merged = merged.astype(patches.dtype)

    if renormalize:
        merged = normalize(merged)
    if mask is not None:
        inside = jnp.asarray(mask).reshape(height, width, 1) > 0
        merged = jnp.where(inside, merged, jnp.zeros_like(merged))
        weight_sum = jnp.where(inside, weight_sum, 0.0)
    return merged, weight_sum


# --------------------------------------------------------------------------------------------
# Dihedral augmentation
# --------------------------------------------------------------------------------------------


def _static_index(k):
    """k as a Python int if it is concrete (int, NumPy or concrete JAX scalar), else None."""
    if isinstance(k, int | np.integer):
        return int(k)
    try:
        return int(k)
    except (jax.errors.ConcretizationTypeError, jax.errors.TracerIntegerConversionError):
        return None


def _dihedral_static(x, k: int):
    if not 0 <= k < DIHEDRAL_COUNT:
        raise ValueError(f"dihedral index must be in 0..{DIHEDRAL_COUNT - 1}, got {k}")
    if k >= 4:
        x = jnp.flip(x, axis=-2)
    return jnp.rot90(x, k % 4, axes=(-3, -2))


def dihedral(patch, k):
    """Apply one of the 8 symmetries of the square to the pixel grid (values untouched).

    ``k % 4`` counter-clockwise quarter turns (as displayed, row 0 at the top) of the patch,
    preceded by a left-right mirror when ``k >= 4``. ``dihedral(dihedral(x, k),
    DIHEDRAL_INVERSE[k])`` is ``x``.

    Args:
      patch: (..., H, W, C) array; must be square (H == W) when ``k`` is traced.
      k: int in ``0..7``; a Python/NumPy int (any shape) or a traced int32 scalar (e.g. under
        `jax.vmap`, then the 8 variants are selected with `jax.lax.switch`).
    Returns:
      (..., W, H, C) array for odd quarter turns, else (..., H, W, C).
    """
    patch = jnp.asarray(patch)
    if patch.ndim < 3:
        raise ValueError(f"patch must have shape (..., H, W, C), got {patch.shape}")
    static = _static_index(k)
    if static is not None:
        return _dihedral_static(patch, static)
    if patch.shape[-3] != patch.shape[-2]:
        raise ValueError(f"a traced dihedral index needs a square patch, got {patch.shape}")
    branches = [functools.partial(_dihedral_static, k=i) for i in range(DIHEDRAL_COUNT)]
    return lax.switch(jnp.clip(k, 0, DIHEDRAL_COUNT - 1), branches, patch)


def dihedral_normals(patch, k):
    """`dihedral` for maps of vectors expressed in the image frame (e.g. tangent-space normals).

    The pixel grid moves as in `dihedral` and each vector turns with it: axes are x = +column
    (right), y = -row (up), z = out of the image. A mirror maps ``x -> -x``; a counter-clockwise
    quarter turn maps ``(x, y) -> (-y, x)``; z is unchanged. The maps are signed permutations,
    so vector lengths are preserved exactly.

    Note: this project's normal maps hold *object-space* normals, whose components do not
    depend on the UV layout, so `random_crops` uses plain `dihedral` by default
    (``vector_mode="none"``); use this function for maps whose vectors live in the image plane.

    Args:
      patch: (..., H, W, C) array with C a multiple of 3 (consecutive (x, y, z) triples, e.g.
        coarse and fine normals stacked as C = 6).
      k: dihedral index in ``0..7``, static or traced (see `dihedral`).
    Returns:
      transformed array, same shape rules as `dihedral`.
    """
    patch = jnp.asarray(patch)
    channels = patch.shape[-1]
    if channels % 3:
        raise ValueError(f"vector maps need (x, y, z) channel triples, got {channels} channels")
    moved = dihedral(patch, k)
    static = _static_index(k)
    index = static if static is not None else jnp.clip(k, 0, DIHEDRAL_COUNT - 1)
    linear = jnp.asarray(_DIHEDRAL_VECTOR_MAPS)[index].astype(moved.dtype)  # (2, 2)
    triples = moved.reshape(*moved.shape[:-1], channels // 3, 3)
    xy = jnp.einsum("ij,...j->...i", linear, triples[..., :2],
                    precision=lax.Precision.HIGHEST)
    return jnp.concatenate([xy, triples[..., 2:]], axis=-1).reshape(moved.shape)


# --------------------------------------------------------------------------------------------
# Random valid crops (training and material classification)
# --------------------------------------------------------------------------------------------


@functools.partial(jax.jit, static_argnames="size")
def crop_mask_counts(mask, size: int):
    """Number of mask texels (``> 0``) in the patch at every possible origin.

    One summed-area table gives all windows at once. Jitted (``size`` static).

    Args:
      mask: (H, W, 1) or (H, W) array with H, W >= size.
      size: patch size in texels (static).
    Returns:
      (H - size + 1, W - size + 1) int32 counts; divide by ``size**2`` for coverage.
    """
    mask = jnp.asarray(mask)
    if mask.ndim == 3:
        mask = mask[..., 0]
    height, width = mask.shape
    if height < size or width < size:
        raise ValueError(
            f"map of shape {(height, width)} is smaller than a {size}x{size} patch; "
            f"pad it with pad_to_patch first"
        )
    inside = (mask > 0).astype(jnp.int32)
    sat = jnp.pad(jnp.cumsum(jnp.cumsum(inside, axis=0), axis=1), ((1, 0), (1, 0)))
    return sat[size:, size:] - sat[:-size, size:] - sat[size:, :-size] + sat[:-size, :-size]


def _concrete_bool(flag):
    """bool(flag) when it is concrete, None under tracing (jit, vmap)."""
    try:
        return bool(flag)
    except jax.errors.ConcretizationTypeError:
        return None


def sample_origins(key, mask, n: int, size: int = 128, min_coverage: float = 0.09):
    """Sample patch origins uniformly (with replacement) among the valid ones.

    An origin is valid when its ``size x size`` patch has a fraction ``>= min_coverage`` of mask
    texels. Sampling is `jax.random.choice` with validity weights over all origins, so shapes
    stay static. Jittable with ``n`` and ``size`` static.

    If no origin is valid: with concrete inputs a ValueError is raised; under `jax.jit`/`vmap`
    (where it cannot be raised) the origins are drawn among those of maximal coverage instead
    (all origins for an empty mask) -- check ``crop_mask_counts`` beforehand if that matters.

    Args:
      key: PRNG key.
      mask: (H, W, 1) or (H, W) mask, H, W >= size.
      n: number of origins (static).
      size: patch size in texels (static).
      min_coverage: minimum fraction of mask texels in a patch, in [0, 1].
    Returns:
      (n, 2) int32 ``(row, col)`` origins.
    """
    counts = crop_mask_counts(mask, size)
    n_cols = counts.shape[1]
    counts = counts.reshape(-1)
    valid = counts.astype(jnp.float32) >= min_coverage * float(size * size)
    any_valid = jnp.any(valid)
    if _concrete_bool(any_valid) is False:
        raise ValueError(
            f"no {size}x{size} patch reaches min_coverage={min_coverage} of mask texels "
            f"(best: {int(jnp.max(counts))} of {size * size}); lower min_coverage or the size"
        )
    chosen = jnp.where(any_valid, valid, counts == jnp.max(counts))
    # Unnormalised 0/1 weights: `choice` scales its uniform draw by the cumulative total, and
    # the float32 cumulative sum of integers stays exact, so every valid origin is equally likely.
    flat = jax.random.choice(key, counts.shape[0], (n,), replace=True,
                             p=chosen.astype(jnp.float32))
    return jnp.stack([flat // n_cols, flat % n_cols], axis=-1).astype(jnp.int32)


def random_crops(
    key,
    image,
    mask,
    n: int,
    size: int = 128,
    min_coverage: float = 0.09,
    augment: bool = True,
    vector_mode: str = "none",
):
    """Random valid crops of a map and its mask, optionally with dihedral augmentation.

    Origins come from `sample_origins` (uniform among patches with mask coverage
    ``>= min_coverage``; same error/fallback when none is valid). With ``augment`` each crop and
    its mask get one of the 8 `dihedral` transforms, drawn uniformly and independently.
    ``vector_mode`` decides what happens to vector components:

    - ``"none"`` (default): only the pixel grid moves. This project's normal maps are
      object-space normals; their components are defined in the garment's 3D frame, not in the
      UV image plane, so re-orienting a patch does not change them (augmentation then acts as
      the "rotating and reflecting the patches" of the paper).
    - ``"rotate"``: use `dihedral_normals`, turning the in-plane (x, y) components with the
      image, for tangent-space-like maps (C must be a multiple of 3).

    To crop aligned pairs (coarse input and fine target) identically, stack them on the channel
    axis. Jittable with ``n``, ``size``, ``augment`` and ``vector_mode`` static. The key is split
    into ``(origin_key, transform_key)``.

    Args:
      key: PRNG key.
      image: (H, W, C) map, H, W >= size.
      mask: (H, W, 1) or (H, W) mask.
      n: number of crops (static).
      size: crop size in texels (static).
      min_coverage: minimum fraction of mask texels in a crop.
      augment: apply random dihedral transforms (static).
      vector_mode: ``"none"`` or ``"rotate"`` (static).
    Returns:
      ``(crops, crop_masks, origins)``: (n, size, size, C) crops, (n, size, size, 1) crop masks
      (dtype of ``mask``) and (n, 2) int32 origins of the crops before augmentation.
    """
    if vector_mode not in VECTOR_MODES:
        raise ValueError(f"unknown vector_mode {vector_mode!r}; expected one of {VECTOR_MODES}")
    image = jnp.asarray(image)
    mask = jnp.asarray(mask)
    if mask.ndim == 2:
        mask = mask[..., None]
    if image.ndim != 3 or mask.shape != (*image.shape[:2], 1):
        raise ValueError(
            f"image must be (H, W, C) and mask (H, W, 1); got {image.shape} and {mask.shape}"
        )
    origin_key, transform_key = jax.random.split(key)
    origins = sample_origins(origin_key, mask, n, size, min_coverage)
    crops = extract(image, origins, size)
    crop_masks = extract(mask, origins, size)
    if augment:
        ks = jax.random.randint(transform_key, (n,), 0, DIHEDRAL_COUNT)
        transform = dihedral_normals if vector_mode == "rotate" else dihedral
        crops = jax.vmap(transform)(crops, ks)
        crop_masks = jax.vmap(dihedral)(crop_masks, ks)
    return crops, crop_masks, origins
