"""Tests for experiments/untangle_study.py's contour length (the study itself needs the data
set)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from experiments import untangle_study as U
from wrinkle_jax.sim import intersect


def _crossed():
    # t1 in the plane z = 0; t2 in the plane x = 0, two of its edges through t1: the
    # intersection runs from (0, -0.5, 0) to (0, 0, 0).
    x = np.array([[-1, -1, 0], [1, -1, 0], [0, 1, 0],
                  [0, -0.5, -1], [0, -0.5, 1], [0, 0.5, 1]], np.float64)
    return x, np.array([[0, 1, 2], [3, 4, 5]])


def test_contour_length_is_the_intersection_segment():
    x, f = _crossed()
    pairs = intersect.intersecting_pairs(x, f)
    e, t = U.crossing_pairs(x, f, pairs)
    assert e.shape == (1, 2, 2) and (t == f[0]).all()  # both crossings are t2's edges
    assert np.isclose(float(U.contour_length(jnp.asarray(x), e, t)), 0.5)


def test_a_descent_step_shortens_the_contour():
    x, f = _crossed()
    e, t = U.crossing_pairs(x, f, intersect.intersecting_pairs(x, f))
    g = np.asarray(jax.grad(U.contour_length)(jnp.asarray(x), e, t))
    # Central difference check of the gradient along a random direction.
    d = np.random.default_rng(0).normal(size=x.shape)
    h = 1e-3  # float32 (the study itself runs in float64)
    fd = (float(U.contour_length(jnp.asarray(x + h * d), e, t))
          - float(U.contour_length(jnp.asarray(x - h * d), e, t))) / (2 * h)
    assert np.isclose(fd, float(np.sum(g * d)), rtol=1e-2, atol=1e-4)
    y = x - 0.01 * g / np.abs(g).max()
    assert float(U.contour_length(jnp.asarray(y), e, t)) < 0.5
