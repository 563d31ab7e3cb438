"""Tests for wrinkle_jax.patches: tiling coverage, exact extract/merge round trips, window
blending, random valid crops and the dihedral group (with vector components for normals)."""

from __future__ import annotations

import functools
import itertools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from wrinkle_jax import patches as pt

# --------------------------------------------------------------------------------------------
# Fixtures and NumPy references
# --------------------------------------------------------------------------------------------


def blobby_mask(seed: int, height: int, width: int, n_blobs: int = 4) -> np.ndarray:
    """(H, W, 1) float32 union of random ellipses plus isolated texels, corners included."""
    rng = np.random.default_rng(seed)
    rows, cols = np.mgrid[0:height, 0:width]
    inside = np.zeros((height, width), bool)
    for _ in range(n_blobs):
        r0, c0 = rng.uniform(0, height), rng.uniform(0, width)
        ar, ac = rng.uniform(5, height / 3 + 5), rng.uniform(5, width / 3 + 5)
        inside |= ((rows - r0) / ar) ** 2 + ((cols - c0) / ac) ** 2 <= 1.0
    # Isolated texels, the hardest case for coverage: corners, borders and random spots.
    inside[0, 0] = inside[-1, -1] = inside[0, -1] = inside[-1, 0] = True
    inside[rng.integers(0, height, 8), rng.integers(0, width, 8)] = True
    return inside[..., None].astype(np.float32)


def union_of_patches(origins: np.ndarray, shape, size: int) -> np.ndarray:
    """(H, W) int count of patches covering each texel (reference loop, test only)."""
    count = np.zeros(shape[:2], np.int64)
    for r, c in np.asarray(origins):
        count[r : r + size, c : c + size] += 1
    return count


def normals_from_height(height: np.ndarray) -> np.ndarray:
    """(S, S, 3) unit normals of a height field h(row, col), x = +col, y = -row, z up."""
    dh_drow, dh_dcol = np.gradient(height.astype(np.float64))
    gx, gy = dh_dcol, -dh_drow
    n = np.stack([-gx, -gy, np.ones_like(gx)], axis=-1)
    return (n / np.linalg.norm(n, axis=-1, keepdims=True)).astype(np.float32)


def random_unit_normals(seed: int, height: int, width: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    n = rng.normal(size=(height, width, 3))
    n[..., 2] = np.abs(n[..., 2]) + 0.5
    return (n / np.linalg.norm(n, axis=-1, keepdims=True)).astype(np.float32)


jit_extract = jax.jit(pt.extract, static_argnames="size")
jit_merge = jax.jit(pt.merge, static_argnames=("shape", "window", "renormalize"))
jit_crops = jax.jit(
    pt.random_crops, static_argnames=("n", "size", "augment", "vector_mode")
)


# --------------------------------------------------------------------------------------------
# tile
# --------------------------------------------------------------------------------------------

SHAPES = [(300, 517), (517, 300), (128, 128), (129, 255), (200, 200)]


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("shape", SHAPES)
def test_tile_covers_every_mask_texel(seed, shape):
    size, stride = 128, 64
    mask = blobby_mask(seed, *shape)
    origins = pt.tile(mask, size, stride)
    assert origins.dtype == np.int32 and origins.ndim == 2 and origins.shape[1] == 2
    h, w = shape
    assert np.all(origins >= 0)
    assert np.all(origins[:, 0] <= h - size) and np.all(origins[:, 1] <= w - size)
    # Each origin lies on the regular grid or on the clamped last row/column.
    assert np.all((origins[:, 0] % stride == 0) | (origins[:, 0] == h - size))
    assert np.all((origins[:, 1] % stride == 0) | (origins[:, 1] == w - size))
    # Row-major, no duplicates.
    keys = origins[:, 0].astype(np.int64) * w + origins[:, 1]
    assert np.all(np.diff(keys) > 0)
    count = union_of_patches(origins, shape, size)
    assert np.all(count[mask[..., 0] > 0] > 0), "a mask texel is not covered"
    for r, c in origins:
        assert mask[r : r + size, c : c + size].sum() > 0, "empty patch kept"


@pytest.mark.parametrize("size,stride", [(32, 16), (32, 32), (32, 7), (16, 1)])
def test_tile_covers_with_other_strides(size, stride):
    mask = blobby_mask(7, 61, 95, n_blobs=2)
    origins = pt.tile(mask, size, stride)
    count = union_of_patches(origins, mask.shape, size)
    assert np.all(count[mask[..., 0] > 0] > 0)
    assert np.all(origins[:, 0] <= 61 - size) and np.all(origins[:, 1] <= 95 - size)


def test_tile_full_mask_grid_count():
    assert pt.tile(np.ones((512, 512, 1), np.float32), 128, 64).shape == (7 * 7, 2)
    assert pt.tile(np.ones((512, 640), np.float32), 128, 128).shape == (4 * 5, 2)
    # Ragged: rows 0, 64, 128, 172; cols 0, 64, ..., 384, 389.
    origins = pt.tile(np.ones((300, 517, 1), np.float32), 128, 64)
    assert origins.shape == (4 * 8, 2)
    assert set(origins[:, 0]) == {0, 64, 128, 172}
    assert set(origins[:, 1]) == {0, 64, 128, 192, 256, 320, 384, 389}


def test_tile_empty_mask_gives_no_origins():
    origins = pt.tile(np.zeros((300, 517, 1), np.float32), 128, 64)
    assert origins.shape == (0, 2) and origins.dtype == np.int32
    patches = jit_extract(jnp.ones((300, 517, 3)), origins, size=128)
    assert patches.shape == (0, 128, 128, 3)
    merged, coverage = jit_merge(patches, origins, shape=(300, 517))
    assert merged.shape == (300, 517, 3) and coverage.shape == (300, 517, 1)
    assert not np.any(np.asarray(merged)) and not np.any(np.asarray(coverage))


def test_tile_rejects_bad_stride_and_size():
    mask = np.ones((64, 64, 1), np.float32)
    with pytest.raises(ValueError, match="stride"):
        pt.tile(mask, 32, 33)
    with pytest.raises(ValueError, match="stride"):
        pt.tile(mask, 32, 0)
    with pytest.raises(ValueError, match="size"):
        pt.tile(mask, 0, 1)
    with pytest.raises(ValueError, match="shape"):
        pt.tile(np.ones((4, 64, 64)), 32, 16)


@pytest.mark.parametrize("shape", [(50, 300), (300, 90), (20, 30)])
def test_small_map_must_be_padded(shape):
    size = 128
    mask = blobby_mask(3, *shape, n_blobs=2)
    with pytest.raises(ValueError, match="pad_to_patch"):
        pt.tile(mask, size, 64)
    padded, original = pt.pad_to_patch(mask, size)
    assert original == mask.shape
    assert padded.shape == (max(shape[0], size), max(shape[1], size), 1)
    np.testing.assert_array_equal(padded[: shape[0], : shape[1]], mask)
    assert padded.sum() == mask.sum()  # zeros added only
    origins = pt.tile(padded, size, 64)
    count = union_of_patches(origins, padded.shape, size)
    assert np.all(count[: shape[0], : shape[1]][mask[..., 0] > 0] > 0)
    # Full pipeline at the padded shape, then crop back: exact.
    image = random_unit_normals(4, *shape)
    padded_image, _ = pt.pad_to_patch(jnp.asarray(image), size)
    assert isinstance(padded_image, jax.Array)
    merged, _ = jit_merge(jit_extract(padded_image, origins, size=size), origins,
                          shape=padded_image.shape, mask=padded)
    cropped = np.asarray(merged)[: shape[0], : shape[1]]
    np.testing.assert_array_equal(cropped, image * (mask > 0))


# --------------------------------------------------------------------------------------------
# extract / merge
# --------------------------------------------------------------------------------------------


def test_extract_matches_slicing():
    image = np.random.default_rng(0).normal(size=(70, 90, 4)).astype(np.float32)
    origins = np.array([[0, 0], [38, 58], [10, 3]], np.int32)
    patches = np.asarray(jit_extract(image, origins, size=32))
    assert patches.shape == (3, 32, 32, 4)
    for p, (r, c) in zip(patches, origins, strict=True):
        np.testing.assert_array_equal(p, image[r : r + 32, c : c + 32])


@pytest.mark.parametrize("seed", [0, 1])
def test_uniform_round_trip_is_exact(seed):
    shape, size = (300, 517), 128
    mask = blobby_mask(seed, *shape)
    image = np.random.default_rng(seed).uniform(-1, 1, (*shape, 3)).astype(np.float32)
    origins = pt.tile(mask, size, 64)
    merged, coverage = jit_merge(jit_extract(image, origins, size=size), origins, shape=shape)
    merged, coverage = np.asarray(merged), np.asarray(coverage)[..., 0]
    count = union_of_patches(origins, shape, size)
    # Texels covered 3, 6 or 9 times make the naive float32 average inexact; check they exist.
    assert {3, 9} <= set(np.unique(count))
    covered = count > 0
    np.testing.assert_array_equal(merged[covered], image[covered])
    np.testing.assert_array_equal(merged[~covered], 0.0)
    np.testing.assert_array_equal(coverage, count.astype(np.float32))


def test_merge_mask_zeroes_background():
    shape, size = (150, 170), 64
    mask = blobby_mask(5, *shape, n_blobs=3)
    image = np.random.default_rng(5).normal(size=(*shape, 2)).astype(np.float32)
    origins = pt.tile(mask, size, 32)
    merged, coverage = jit_merge(jit_extract(image, origins, size=size), origins, shape=shape,
                                 mask=mask)
    inside = mask[..., 0] > 0
    np.testing.assert_array_equal(np.asarray(merged), image * inside[..., None])
    assert np.all(np.asarray(coverage)[inside] > 0)
    assert np.all(np.asarray(coverage)[~inside] == 0)


def test_hann_window_strictly_positive_and_symmetric():
    for size in (8, 33, 128):
        w = np.asarray(pt.window_weights(size, "hann"))
        assert w.shape == (size, size) and w.dtype == np.float32
        assert w.min() > pt.HANN_FLOOR**2 * 0.999 and w.max() <= 1.0
        assert w.min() < 0.01 * w.max()  # the border really fades
        np.testing.assert_allclose(w, w.T)
        np.testing.assert_allclose(w, w[::-1, ::-1])
    np.testing.assert_array_equal(np.asarray(pt.window_weights(16, "uniform")), 1.0)
    with pytest.raises(ValueError, match="window"):
        pt.window_weights(16, "gauss")


def test_hann_merge_of_constant_is_constant():
    shape, size = (300, 517), 128
    mask = blobby_mask(11, *shape)
    origins = pt.tile(mask, size, 64)
    value = np.array([0.3, -0.7, 0.64], np.float32)
    image = np.broadcast_to(value, (*shape, 3))
    merged, coverage = jit_merge(jit_extract(image, origins, size=size), origins, shape=shape,
                                 window="hann")
    merged, coverage = np.asarray(merged), np.asarray(coverage)[..., 0]
    covered = union_of_patches(origins, shape, size) > 0
    np.testing.assert_array_equal(coverage > 0, covered)
    np.testing.assert_allclose(merged[covered], np.broadcast_to(value, merged[covered].shape),
                               rtol=1e-6, atol=1e-7)
    np.testing.assert_array_equal(merged[~covered], 0.0)


@pytest.mark.parametrize("window", ["uniform", "hann"])
def test_merge_of_constant_patches_stays_in_range(window):
    shape, size = (200, 230), 64
    origins = pt.tile(np.ones((*shape, 1)), size, 32)
    values = np.random.default_rng(2).uniform(-3, 5, (len(origins), 1)).astype(np.float32)
    patches = np.broadcast_to(values[:, None, None, :], (len(origins), size, size, 1))
    merged = np.asarray(jit_merge(patches, origins, shape=shape, window=window)[0])
    lo, hi = values.min(), values.max()
    assert merged.min() >= lo - 1e-5 and merged.max() <= hi + 1e-5
    # It is a blend: plenty of texels strictly between neighbouring patch values.
    assert len(np.unique(np.round(merged, 4))) > len(values)


def test_hann_seams_are_smoother_than_uniform():
    shape, size = (200, 230), 64
    origins = pt.tile(np.ones((*shape, 1)), size, 32)
    values = np.random.default_rng(3).uniform(-1, 1, (len(origins), 1)).astype(np.float32)
    patches = np.broadcast_to(values[:, None, None, :], (len(origins), size, size, 1))

    def max_jump(window):
        merged = np.asarray(jit_merge(patches, origins, shape=shape, window=window)[0])
        return max(np.abs(np.diff(merged, axis=0)).max(), np.abs(np.diff(merged, axis=1)).max())

    assert max_jump("hann") < 0.5 * max_jump("uniform")


def test_merge_renormalize_gives_unit_vectors():
    shape, size = (100, 120), 32
    mask = blobby_mask(8, *shape, n_blobs=2)
    normals = random_unit_normals(8, *shape)
    origins = pt.tile(mask, size, 16)
    patches = jit_extract(normals, origins, size=size)
    # Perturb each patch differently so the plain average is no longer unit length.
    # NumPy noise: an op-by-op jax.random draw compiles a threefry program of its shape.
    noise = jnp.asarray(np.random.default_rng(0).standard_normal(patches.shape) * 0.3,
                        jnp.float32)
    merged, coverage = jit_merge(patches + noise, origins, shape=shape, window="hann",
                                 renormalize=True)
    lengths = np.linalg.norm(np.asarray(merged), axis=-1)
    covered = np.asarray(coverage)[..., 0] > 0
    np.testing.assert_allclose(lengths[covered], 1.0, atol=1e-6)
    np.testing.assert_array_equal(lengths[~covered], 0.0)
    plain = np.linalg.norm(np.asarray(jit_merge(patches + noise, origins, shape=shape,
                                                window="hann")[0]), axis=-1)
    assert np.abs(plain[covered] - 1.0).max() > 1e-2


@pytest.mark.parametrize("window", ["uniform", "hann"])
def test_jit_equals_eager(window):
    shape, size = (90, 110), 32
    mask = blobby_mask(9, *shape, n_blobs=3)
    image = random_unit_normals(9, *shape)
    origins = pt.tile(mask, size, 16)
    eager_patches = pt.extract(image, origins, size)
    np.testing.assert_array_equal(np.asarray(jit_extract(image, origins, size=size)),
                                  np.asarray(eager_patches))
    eager = pt.merge(eager_patches, origins, shape, window=window, mask=mask, renormalize=True)
    jitted = jit_merge(eager_patches, origins, shape=shape, window=window, mask=mask,
                       renormalize=True)
    for a, b in zip(eager, jitted, strict=True):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-6, atol=1e-7)


def test_extract_and_merge_vmap_over_batches():
    shape, size = (64, 80), 32
    images = np.random.default_rng(1).normal(size=(3, *shape, 2)).astype(np.float32)
    origins = pt.tile(np.ones((*shape, 1)), size, 16)
    batched = jax.jit(jax.vmap(functools.partial(pt.extract, size=size), in_axes=(0, None)))
    patches = batched(images, origins)
    assert patches.shape == (3, len(origins), size, size, 2)
    for b in range(3):
        np.testing.assert_array_equal(np.asarray(patches[b]),
                                      np.asarray(pt.extract(images[b], origins, size)))
    merge_batch = jax.jit(jax.vmap(
        functools.partial(pt.merge, shape=shape, window="hann"), in_axes=(0, None)))
    merged, coverage = merge_batch(patches, origins)
    assert merged.shape == (3, *shape, 2) and coverage.shape == (3, *shape, 1)
    for b in range(3):
        ref = pt.merge(patches[b], origins, shape, window="hann")[0]
        np.testing.assert_allclose(np.asarray(merged[b]), np.asarray(ref), rtol=1e-6, atol=1e-6)
    # Per-frame origins (traced) work too.
    per_frame = jax.jit(jax.vmap(functools.partial(pt.merge, shape=shape)))
    merged2, _ = per_frame(patches, jnp.stack([jnp.asarray(origins)] * 3))
    np.testing.assert_array_equal(np.asarray(merged2), images)


def test_merge_gradient_is_finite_and_averages():
    shape, size = (40, 40), 16
    origins = pt.tile(np.ones((*shape, 1)), size, 8)
    patches = jnp.ones((len(origins), size, size, 1))

    def total(p):
        return pt.merge(p, origins, shape)[0].sum()

    grad = np.asarray(jax.jit(jax.grad(total))(patches))
    assert np.all(np.isfinite(grad))
    # d(sum of merged)/d(patch texel) = 1 / (number of patches covering that texel).
    count = union_of_patches(origins, shape, size)
    for p, (r, c) in enumerate(origins):
        np.testing.assert_allclose(grad[p, ..., 0], 1.0 / count[r : r + size, c : c + size],
                                   rtol=1e-6)


# --------------------------------------------------------------------------------------------
# dihedral group
# --------------------------------------------------------------------------------------------


def _generic_image(size=6, channels=2, seed=0):
    return np.random.default_rng(seed).normal(size=(size, size, channels)).astype(np.float32)


def test_dihedral_group_structure():
    x = _generic_image()
    images = [np.asarray(pt.dihedral(x, k)) for k in range(pt.DIHEDRAL_COUNT)]
    assert pt.DIHEDRAL_COUNT == 8
    # All 8 distinct on a generic image; k = 0 is the identity.
    for a, b in itertools.combinations(range(8), 2):
        assert not np.array_equal(images[a], images[b]), (a, b)
    np.testing.assert_array_equal(images[0], x)

    def index_of(y):
        hits = [k for k in range(8) if np.array_equal(images[k], y)]
        assert len(hits) == 1
        return hits[0]

    # Closure: every composition is again one of the 8.
    table = np.array([[index_of(np.asarray(pt.dihedral(images[a], b))) for b in range(8)]
                      for a in range(8)])
    # Latin square (group table): each row and column is a permutation.
    for i in range(8):
        assert sorted(table[i]) == list(range(8)) and sorted(table[:, i]) == list(range(8))
    # Inverses: exist, match DIHEDRAL_INVERSE.
    for k in range(8):
        assert table[k, pt.DIHEDRAL_INVERSE[k]] == 0
        np.testing.assert_array_equal(
            np.asarray(pt.dihedral(images[k], pt.DIHEDRAL_INVERSE[k])), x)
    # Quarter turns generate the rotations; k = 1 is counter-clockwise as displayed.
    np.testing.assert_array_equal(images[1], np.rot90(x, 1, axes=(0, 1)))
    np.testing.assert_array_equal(images[4], x[:, ::-1])


def test_dihedral_traced_index_matches_static():
    x = jnp.asarray(_generic_image(size=5, channels=3))
    ks = jnp.arange(8)
    batched = jax.jit(jax.vmap(pt.dihedral, in_axes=(None, 0)))(x, ks)
    normals = jax.jit(jax.vmap(pt.dihedral_normals, in_axes=(None, 0)))(x, ks)
    for k in range(8):
        np.testing.assert_array_equal(np.asarray(batched[k]), np.asarray(pt.dihedral(x, k)))
        np.testing.assert_array_equal(np.asarray(normals[k]),
                                      np.asarray(pt.dihedral_normals(x, k)))
    # Static indices also work on non-square images and batches of patches.
    assert pt.dihedral(jnp.zeros((2, 4, 7, 1)), 1).shape == (2, 7, 4, 1)
    with pytest.raises(ValueError, match="0..7"):
        pt.dihedral(x, 8)


def test_dihedral_normals_tilted_plane_quarter_turn():
    # Plane h = a x + b y (x = col, y = -row): normal ~ (-a, -b, 1). Turned 90 degrees
    # counter-clockwise its gradient becomes (-b, a), so its normal is ~ (b, -a, 1).
    a, b = 0.4, -0.25
    size = 9
    rows, cols = np.mgrid[0:size, 0:size].astype(np.float64)
    plane = a * cols + b * (-rows)
    normals = normals_from_height(plane)
    np.testing.assert_allclose(normals[4, 4], np.array([-a, -b, 1]) / np.linalg.norm([a, b, 1]),
                               rtol=1e-6)
    turned = np.asarray(pt.dihedral_normals(normals, 1))
    expected = np.array([b, -a, 1]) / np.linalg.norm([a, b, 1])
    np.testing.assert_allclose(turned, np.broadcast_to(expected, turned.shape), rtol=1e-6,
                               atol=1e-7)
    # ... which is the normal map of the rotated height field.
    rotated_plane = np.asarray(pt.dihedral(plane[..., None], 1))[..., 0]
    np.testing.assert_allclose(turned, normals_from_height(rotated_plane), atol=1e-6)


@pytest.mark.parametrize("k", range(8))
def test_dihedral_normals_commute_with_baking(k):
    size = 24
    rows, cols = np.mgrid[0:size, 0:size].astype(np.float64)
    height = np.sin(0.31 * rows + 0.05 * cols) * np.cos(0.17 * cols) + 0.002 * rows * cols \
        + 0.01 * cols**1.5
    normals = normals_from_height(height)
    transformed = np.asarray(jax.jit(pt.dihedral_normals)(normals, k))
    expected = normals_from_height(np.asarray(pt.dihedral(height[..., None], k))[..., 0])
    np.testing.assert_allclose(transformed, expected, atol=2e-6)
    np.testing.assert_allclose(np.linalg.norm(transformed, axis=-1),
                               np.linalg.norm(normals, axis=-1), atol=1e-7)
    if k not in (0,):
        # Moving pixels without turning the vectors is wrong for image-frame vectors.
        plain = np.asarray(pt.dihedral(normals, k))
        assert np.abs(plain - expected).max() > 1e-2


def test_dihedral_normals_on_stacked_triples_and_unit_length():
    n = random_unit_normals(0, 8, 8)
    stacked = np.concatenate([n, n[::-1]], axis=-1)  # (8, 8, 6)
    for k in range(8):
        out = np.asarray(pt.dihedral_normals(stacked, k))
        np.testing.assert_array_equal(out[..., :3], np.asarray(pt.dihedral_normals(n, k)))
        np.testing.assert_array_equal(out[..., 3:],
                                      np.asarray(pt.dihedral_normals(n[::-1], k)))
        np.testing.assert_allclose(np.linalg.norm(out[..., :3], axis=-1), 1.0, atol=1e-6)
        np.testing.assert_array_equal(out[..., 2], np.asarray(pt.dihedral(n, k))[..., 2])
    with pytest.raises(ValueError, match="triples"):
        pt.dihedral_normals(np.zeros((4, 4, 2)), 1)


# --------------------------------------------------------------------------------------------
# random crops
# --------------------------------------------------------------------------------------------


def _crop_fixture():
    shape = (120, 150)
    mask = blobby_mask(21, *shape, n_blobs=3)
    image = random_unit_normals(21, *shape)
    return image, mask


def _find_transform(crop, source, transform):
    hits = [k for k in range(8) if np.array_equal(np.asarray(transform(source, k)), crop)]
    assert hits, "crop is no dihedral transform of the patch at its origin"
    return hits


@pytest.mark.parametrize("vector_mode", ["none", "rotate"])
def test_random_crops_are_valid_and_consistent(vector_mode):
    image, mask = _crop_fixture()
    size, n, min_coverage = 32, 40, 0.3
    crops, crop_masks, origins = jit_crops(jax.random.key(3), image, mask, n=n, size=size,
                                           min_coverage=min_coverage, vector_mode=vector_mode)
    crops, crop_masks, origins = map(np.asarray, (crops, crop_masks, origins))
    assert crops.shape == (n, size, size, 3) and crop_masks.shape == (n, size, size, 1)
    assert origins.shape == (n, 2) and origins.dtype == np.int32
    assert np.all(origins >= 0) and np.all(origins <= np.array(mask.shape[:2]) - size)
    coverage = (crop_masks > 0).sum(axis=(1, 2, 3)) / size**2
    assert np.all(coverage >= min_coverage)
    transform = pt.dihedral_normals if vector_mode == "rotate" else pt.dihedral
    used = set()
    for crop, crop_mask, (r, c) in zip(crops, crop_masks, origins, strict=True):
        ks = _find_transform(crop, image[r : r + size, c : c + size], transform)
        assert any(np.array_equal(np.asarray(pt.dihedral(mask[r : r + size, c : c + size], k)),
                                  crop_mask) for k in ks), "mask transformed differently"
        used.update(ks)
    assert len(used) == 8  # 40 draws: all transforms show up
    # Unit length survives either mode.
    np.testing.assert_allclose(np.linalg.norm(crops, axis=-1), 1.0, atol=1e-6)


def test_random_crops_keys_and_jit():
    image, mask = _crop_fixture()
    kwargs = dict(n=16, size=32, min_coverage=0.2)
    a = jit_crops(jax.random.key(0), image, mask, **kwargs)
    b = jit_crops(jax.random.key(0), image, mask, **kwargs)
    c = jit_crops(jax.random.key(1), image, mask, **kwargs)
    eager = pt.random_crops(jax.random.key(0), image, mask, **kwargs)
    for x, y, z in zip(a, b, eager, strict=True):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
        np.testing.assert_array_equal(np.asarray(x), np.asarray(z))
    assert not np.array_equal(np.asarray(a[2]), np.asarray(c[2]))
    assert not np.array_equal(np.asarray(a[0]), np.asarray(c[0]))


def test_random_crops_without_augmentation_are_plain_extracts():
    image, mask = _crop_fixture()
    crops, crop_masks, origins = jit_crops(jax.random.key(5), image, mask, n=8, size=32,
                                           augment=False)
    np.testing.assert_array_equal(np.asarray(crops),
                                  np.asarray(pt.extract(image, origins, 32)))
    np.testing.assert_array_equal(np.asarray(crop_masks),
                                  np.asarray(pt.extract(mask, origins, 32)))


def test_sample_origins_uniform_over_valid_positions():
    # 20x20 map, 4x4 patches: valid origins are exactly those whose patch holds >= 8 of the
    # 16 texels of a 6x6 block at rows 5..10, cols 9..14.
    mask = np.zeros((20, 20, 1), np.float32)
    mask[5:11, 9:15] = 1
    size, min_coverage = 4, 0.5
    counts = np.asarray(pt.crop_mask_counts(mask, size))
    ref = np.array([[mask[r : r + size, c : c + size].sum() for c in range(17)]
                    for r in range(17)])
    np.testing.assert_array_equal(counts, ref)
    valid = ref >= min_coverage * size**2
    n = 20000
    origins = np.asarray(jax.jit(pt.sample_origins, static_argnames=("n", "size"))(
        jax.random.key(0), mask, n=n, size=size, min_coverage=min_coverage))
    assert np.all(valid[origins[:, 0], origins[:, 1]])
    hist = np.zeros_like(ref)
    np.add.at(hist, (origins[:, 0], origins[:, 1]), 1)
    expected = n / valid.sum()
    assert np.all(hist[valid] > 0)
    # Every valid origin within 5 binomial standard deviations of uniform.
    assert np.abs(hist[valid] - expected).max() < 5 * np.sqrt(expected)


def test_no_valid_origin_raises_eagerly_and_falls_back_under_jit():
    mask = np.zeros((40, 40, 1), np.float32)
    mask[3:6, 30:33] = 1  # at most 9 of 256 texels in a 16x16 patch
    with pytest.raises(ValueError, match="min_coverage"):
        pt.sample_origins(jax.random.key(0), mask, 4, size=16, min_coverage=0.1)
    with pytest.raises(ValueError, match="min_coverage"):
        pt.random_crops(jax.random.key(0), np.zeros((40, 40, 3)), mask, 4, size=16,
                        min_coverage=0.1)
    origins = np.asarray(jax.jit(pt.sample_origins, static_argnames=("n", "size"))(
        jax.random.key(0), mask, n=64, size=16, min_coverage=0.1))
    counts = np.asarray(pt.crop_mask_counts(mask, 16))
    assert counts.max() == 9
    assert np.all(counts[origins[:, 0], origins[:, 1]] == 9)
    with pytest.raises(ValueError, match="pad_to_patch"):
        pt.crop_mask_counts(np.ones((10, 40)), 16)


def test_random_crops_rejects_bad_arguments():
    image, mask = _crop_fixture()
    with pytest.raises(ValueError, match="vector_mode"):
        pt.random_crops(jax.random.key(0), image, mask, 2, size=32, vector_mode="tangent")
    with pytest.raises(ValueError, match="mask"):
        pt.random_crops(jax.random.key(0), image, mask[:-1], 2, size=32)


def test_merge_clamps_origins_like_extract_and_checks_shapes():
    shape, size = (40, 50), 16
    image = np.random.default_rng(6).normal(size=(*shape, 3)).astype(np.float32)
    origins = np.array([[-5, 3], [30, 45], [10, 10]], np.int32)  # two out of range
    clamped = np.array([[0, 3], [24, 34], [10, 10]], np.int32)
    patches = jit_extract(image, origins, size=size)
    np.testing.assert_array_equal(np.asarray(patches),
                                  np.asarray(jit_extract(image, clamped, size=size)))
    merged, coverage = jit_merge(patches, origins, shape=shape)
    np.testing.assert_array_equal(np.asarray(coverage)[..., 0],
                                  union_of_patches(clamped, shape, size).astype(np.float32))
    covered = np.asarray(coverage)[..., 0] > 0
    np.testing.assert_array_equal(np.asarray(merged)[covered], image[covered])
    half, _ = jit_merge(patches.astype(jnp.float16), origins, shape=shape)
    assert half.dtype == jnp.float16
    np.testing.assert_allclose(np.asarray(half, np.float32)[covered], image[covered], atol=1e-2)
    with pytest.raises(ValueError, match="smaller"):
        pt.merge(patches, origins, (10, 50))
    with pytest.raises(ValueError, match="origins"):
        pt.merge(patches, origins[:2], shape)
