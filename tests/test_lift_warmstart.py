"""Warm-started lifting (lift.lift's `start`, stages.local_frames / to_local / from_local):
a frame started from the previous frame's solution, carried in the coarse surface's local
frames, converges to the cold-start minimizer, and gets nearer to it on a fixed budget."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from wrinkle_jax import lift as L
from wrinkle_jax import primitives, stages, subdivision

# Tight enough that cold and warm starts stop at the same minimizer (float32).
TIGHT = L.SolverConfig(max_iters=40, tol=1e-7, cg_tol=1e-6, cg_max_iters=200)
SHORT = L.SolverConfig(max_iters=2)  # a fixed budget of two Gauss-Newton steps


def _rotation(axis, angle):
    a = np.asarray(axis, np.float64) / np.linalg.norm(axis)
    k = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k


def _sequence():
    """Three frames of a 10 x 10 cell coarse sheet (12 mm cells, midpoint-subdivided once):
    frame 1 is frame 0 rotated 35 degrees and moved (an exact rigid motion, targets rotated
    with it), frame 2 bends the drape further. Targets: normals of 8 cm wrinkles (2 mm)."""
    def coarse_height(amp):
        return lambda x, y: amp * np.sin(2 * np.pi * x / 0.3) * np.cos(2 * np.pi * y / 0.4)

    def wrinkled_normals(p, amp):
        x, y = p[:, 0].astype(np.float64), p[:, 1].astype(np.float64)
        k = 2 * np.pi / 0.08
        kc, kd = 2 * np.pi / 0.3, 2 * np.pi / 0.4
        hx = amp * kc * np.cos(kc * x) * np.cos(kd * y) + 0.002 * k * np.cos(k * (x + y))
        hy = -amp * kd * np.sin(kc * x) * np.sin(kd * y) + 0.002 * k * np.cos(k * (x + y))
        n = np.stack([-hx, -hy, np.ones_like(x)], 1)
        return n / np.linalg.norm(n, axis=1, keepdims=True)

    frames = []
    for amp in (0.01, 0.014):
        g = primitives.grid_sheet(10, 10, size=(0.12, 0.12), height_fn=coarse_height(amp))
        sub = subdivision.build(g, 1)
        fine = sub.garment(g)
        frames.append((np.asarray(fine.vertices), wrinkled_normals(fine.vertices, amp)))
    rot = _rotation((0.3, 1.0, 0.2), np.radians(35))
    shift = np.array([0.05, -0.02, 0.3])
    p0, n0 = frames[0]
    seq = [frames[0], (p0 @ rot.T + shift, n0 @ rot.T), frames[1]]
    top = L.lift_topology(fine.faces, fine.num_vertices)
    return [(jnp.asarray(p, jnp.float32), jnp.asarray(n, jnp.float32)) for p, n in seq], top


@jax.jit
def _carry(p, p0, top):
    return stages.to_local(p - p0, stages.local_frames(p0, top))


@jax.jit
def _warm(local, p0, top):
    return p0 + stages.from_local(local, stages.local_frames(p0, top))


@jax.jit
def _solve(p0, top, n, start):
    """One compile for every test: start = p0 is the cold start."""
    return L.lift_with_info(p0, top, n, solver=TIGHT, start=start)


@jax.jit
def _solve_short(p0, top, n, start):
    return L.lift_with_info(p0, top, n, solver=SHORT, start=start)


def test_local_frames_are_orthonormal_and_turn_with_the_surface():
    (f0, f1, _), top = _sequence()
    p0, p1 = f0[0], f1[0]
    frames = np.asarray(stages.local_frames(p0, top))
    eye = np.einsum("vij,vkj->vik", frames, frames)
    np.testing.assert_allclose(eye, np.broadcast_to(np.eye(3), eye.shape), atol=1e-5)
    # Round trip, and invariance: an offset moved rigidly with the surface keeps its local
    # components (frame 1 is frame 0 rotated).
    d = jnp.asarray(np.random.default_rng(0).normal(size=p0.shape) * 1e-3, jnp.float32)
    local = _carry(p0 + d, p0, top)
    np.testing.assert_allclose(_warm(local, p0, top) - p0, d, atol=1e-8)
    rot = np.asarray(jnp.linalg.lstsq(p0 - p0.mean(0), p1 - p1.mean(0))[0]).T
    np.testing.assert_allclose(_carry(p1 + d @ rot.T, p1, top), local, atol=2e-7)


def test_warm_start_reaches_the_cold_solution_sooner():
    frames, top = _sequence()
    prev = None
    for i, (p0, n) in enumerate(frames):
        cold, info_cold = _solve(p0, top, n, p0)
        assert int(info_cold.iterations) >= 3  # a real solve, not an already-flat problem
        if prev is not None:
            guess = _warm(_carry(prev[0], prev[1], top), p0, top)
            warm, info_warm = _solve(p0, top, n, guess)
            # The same minimizer, to a small fraction of the 6 mm edge.
            assert float(jnp.abs(warm - cold).max()) < 2e-5, i
            assert float(info_warm.energy) <= float(info_cold.energy) * (1 + 1e-4)
            if i == 1:
                # After a rigid motion the carried solution is the answer: the solve starts
                # there and does not move it. (Step counts are not compared: at TIGHT's tol
                # of 1e-7 the stopping test compares energy changes of one or two float32
                # ulps, so they follow rounding; the two-step budget below shows "sooner".)
                assert float(jnp.abs(warm - guess).max()) < 1e-6
            # On a budget of two iterations the warm start ends nearer the minimizer, in
            # distance and in energy (frame 2 bends the drape 40 % further: not rigid).
            short = [_solve_short(p0, top, n, s) for s in (p0, guess)]
            dist = [float(jnp.sqrt(jnp.mean(jnp.sum((p - cold) ** 2, -1)))) for p, _ in short]
            excess = [float(info.energy - info_cold.energy) for _, info in short]
            assert dist[1] < 0.5 * dist[0], (i, dist)
            assert excess[1] < 0.5 * excess[0], (i, excess)
        prev = (cold, p0)


def test_a_worse_guess_than_p0_is_ignored():
    (f0, _, _), top = _sequence()
    p0, n = f0
    cold, info_cold = _solve(p0, top, n, p0)
    bad = p0 + jnp.asarray(np.random.default_rng(1).normal(size=p0.shape) * 5e-3, jnp.float32)
    far, info_far = _solve(p0, top, n, bad)
    np.testing.assert_array_equal(far, cold)
    assert int(info_far.iterations) == int(info_cold.iterations)
    # A good guess is taken: the converged solution itself needs one (flat) step.
    again, info_again = _solve(p0, top, n, cold)
    assert int(info_again.iterations) == 1
    assert float(jnp.abs(again - cold).max()) < 1e-5
