"""Tests for seams of merged patch grids (`wrinkle_jax.evaluation.seams`)."""

from __future__ import annotations

import numpy as np
import pytest

from wrinkle_jax.evaluation import seams as seam_lib


def test_border_pairs_mark_the_neighbour_pairs_across_tile_starts_and_ends():
    origins = np.array([[0, 0], [16, 0], [28, 0]])  # rows 0, 16 and the clamped last row
    got = seam_lib.border_pairs(origins, 32, 60, axis=0)
    # tiles start at 16, 28 and end after 31, 47, 59 (the last, at the map's edge, has no pair)
    assert np.flatnonzero(got).tolist() == [15, 27, 31, 47]
    assert np.flatnonzero(seam_lib.border_pairs(origins, 32, 60, axis=1)).tolist() == [31]


def test_seam_ratio_is_one_for_uniform_bending_and_sees_a_kink_at_a_tile_border():
    h = w = 64
    y, x = np.mgrid[0:h, 0:w].astype(np.float64)
    ang = np.radians(0.5) * (x + y)  # the normal turns 0.5 degrees per texel along x and y
    nrm = np.stack([np.sin(ang), np.zeros_like(ang), np.cos(ang)], -1)
    mask = np.ones((h, w), bool)
    origins = np.array([[r, c] for r in (0, 16, 32) for c in (0, 16, 32)])
    assert seam_lib.seam_ratio(seam_lib.seam_sums(nrm, mask, origins, 32)) == pytest.approx(1.0)
    kinked = nrm.copy()
    kinked[:, 16:] = nrm[:, 16:] @ np.array([[np.cos(0.1), 0, -np.sin(0.1)], [0, 1, 0],
                                              [np.sin(0.1), 0, np.cos(0.1)]]).T
    assert seam_lib.seam_ratio(seam_lib.seam_sums(kinked, mask, origins, 32)) > 1.5
    off_border = nrm.copy()
    off_border[:, 20:] = kinked[:, 16:60]  # the same kink between tiles' borders
    assert seam_lib.seam_ratio(seam_lib.seam_sums(off_border, mask, origins, 32)) < 1.0
    assert np.isnan(seam_lib.seam_ratio(np.zeros(4)))
