"""Tests for coarse and fine maps on one grid and aligned patch sets
(`wrinkle_jax.evaluation.patchsets`)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from evaluation_fixtures import FOLD, PATCH, TEXEL, sheet_sequence  # tests/ is on sys.path

from wrinkle_jax import evaluation, normalmap, patches
from wrinkle_jax.evaluation import patchsets


def _analytic_normals(layout, t=0):
    """Normals of the fold (no ripple) at every texel center of `layout`: (H, W, 3)."""
    h, w = layout.shape
    col, row = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    u = (col - layout.margin) / layout.pixels_per_uv + layout.u_min
    dzdx = 0.02 * 2 * np.pi / FOLD * np.cos(2 * np.pi * u / FOLD + 0.5 * t)
    n = np.stack([-dzdx, np.zeros_like(dzdx), np.ones_like(dzdx)], -1)
    return n / np.linalg.norm(n, axis=-1, keepdims=True)


def test_coarse_and_fine_maps_share_one_grid_and_their_patches_align_in_uv():
    fine, coarse = sheet_sequence(60, 40, 1), sheet_sequence(10, 7, 1)
    # Stretch the coarse rest mesh by 1 %: its own layout_for scale would differ.
    coarse = dataclasses.replace(coarse, garment=coarse.garment.replace(
        vertices=np.asarray(coarse.garment.vertices) * 1.01))
    pair = patchsets.aligned_pair(fine.garment, coarse.garment, TEXEL)
    assert pair.fine.layout == pair.coarse.layout == pair.layout
    assert pair.layout.pixels_per_uv == pytest.approx(1.0 / TEXEL)  # the fine (reference) scale
    fm, cm = np.asarray(pair.fine.mask), np.asarray(pair.coarse.mask)
    assert (pair.mask <= fm).all() and (pair.mask <= cm).all() and pair.mask.sum() > 0.9 * fm.sum()
    truth = _analytic_normals(pair.layout)
    inside = pair.mask[..., 0] > 0
    for plan, tol in ((pair.fine, 0.5), (pair.coarse, 4.0)):
        baked = patchsets.bake_map(plan, fine.frames[0] if plan is pair.fine else coarse.frames[0])
        assert evaluation.mean_angular_change(baked, truth, pair.mask) < tol
    # The coarse mesh's own layout (scale from its stretched 3D areas) drifts off the grid.
    own = normalmap.make_plan(coarse.garment, texel_size=TEXEL)
    assert own.layout.pixels_per_uv != pytest.approx(pair.layout.pixels_per_uv)
    # Patches cut at the same origins show the same cloth: input and target agree everywhere
    # on the fold (the fine map's ripples tilt normals by < 33 degrees).
    size = PATCH
    mask = np.asarray(patches.pad_to_patch(pair.mask, size)[0])
    origins, cov = patchsets.candidate_origins(mask, size, size // 2, 0.5)
    ps = patchsets.aligned_patches(pair, fine.frames[0], coarse.frames[0], origins, size, 0)
    assert ps.input.shape == ps.target.shape == (len(origins), size, size, 3)
    truth_p = patchsets.cut(np.asarray(patches.pad_to_patch(truth, size)[0]), origins, size)
    for k in range(len(origins)):
        assert evaluation.mean_angular_change(ps.input[k] * 2 - 1, truth_p[k], ps.mask[k]) < 4.0
        # The fine map resolves the fold: a patch one texel off would be > 1 degree away.
        assert evaluation.mean_angular_change(ps.target[k] * 2 - 1, truth_p[k], ps.mask[k]) < 0.5
    fine_rgb = np.asarray(patches.pad_to_patch(
        normalmap.to_rgb(patchsets.bake_map(pair.fine, fine.frames[0])), size)[0]) * mask
    np.testing.assert_array_equal(ps.target, np.asarray(patches.extract(fine_rgb, origins, size)))
    np.testing.assert_array_equal(ps.mask, patchsets.cut(mask, origins, size))
    assert inside.any() and not ps.input[ps.mask[..., 0] == 0].any()


def test_candidate_origins_are_exactly_the_grid_patches_with_enough_coverage():
    mask = np.zeros((100, 130, 1), np.float32)
    mask[10:70, 20:110] = 1
    origins, cov = patchsets.candidate_origins(mask, 32, 16, 0.5)
    all_origins = patches.tile(mask, 32, 16)
    brute = np.array([mask[r:r + 32, c:c + 32].mean() for r, c in all_origins])
    np.testing.assert_array_equal(origins, all_origins[brute >= 0.5])
    np.testing.assert_allclose(cov, brute[brute >= 0.5], rtol=1e-6)
    chosen = patchsets.choose_origins(origins, 3, (1, 2))
    assert len(chosen) == 3 and {tuple(o) for o in chosen} <= {tuple(o) for o in origins}
    np.testing.assert_array_equal(chosen, patchsets.choose_origins(origins, 3, (1, 2)))  # seeded
