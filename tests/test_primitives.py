"""Tests for the benchmark inputs in wrinkle_jax.primitives (the garments are tested where
they are used: mesh, normal-map and simulator tests)."""

from __future__ import annotations

import numpy as np

from wrinkle_jax import primitives


def test_wavy_normal_maps_are_unit_normals_seeded_and_flat_without_waves():
    a = primitives.wavy_normal_maps(np.random.default_rng(3), 2, 32)
    b = primitives.wavy_normal_maps(np.random.default_rng(3), 2, 32)
    assert a.shape == (2, 32, 32, 3) and a.dtype == np.float32
    np.testing.assert_array_equal(a, b)
    np.testing.assert_allclose(np.linalg.norm(a * 2 - 1, axis=-1), 1.0, atol=1e-5)
    assert np.std(a[..., 0]) > 0.01  # it has relief
    flat = primitives.wavy_normal_maps(np.random.default_rng(3), 1, 8, waves=0)
    np.testing.assert_allclose(flat, np.broadcast_to([0.5, 0.5, 1.0], flat.shape))


def test_wrinkled_sheet_case_grid_size():
    # Its geometry and target normals are checked through `reference.make_lift_case`
    # (tests/test_reference.py::test_lift_case_targets_are_the_ideal_surfaces_normals).
    case = primitives.wrinkled_sheet_case(45)  # bench_lift's 2k size: 11 x 11 cells, 0.45 m
    assert case["coarse"].num_vertices == 12 * 12
    np.testing.assert_allclose(np.ptp(case["coarse"].vertices[:, :2], axis=0), 0.45, atol=1e-6)
    assert case["fine"].num_vertices == 45 * 45
