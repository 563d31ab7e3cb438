"""Tests for sim.selfcollision_motion (the on-motion rebuild, `rebuild_every = 0`): the bound
covers the relative displacement of every pair within the thickness (brute force), a rigid
translation needs no rebuild, and through the solver a layer shot at another within one
frame is stopped only when the rebuild follows the motion (one build per frame misses it)."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from wrinkle_jax.sim import contact_scenes as CS
from wrinkle_jax.sim import intersect
from wrinkle_jax.sim import materials as M
from wrinkle_jax.sim import selfcollision as S
from wrinkle_jax.sim import selfcollision_motion as SM
from wrinkle_jax.sim import xpbd as X

_bound = jax.jit(SM.motion_bound, static_argnums=3)
_closest = jax.jit(S.closest_point_triangle)


def test_bound_covers_every_close_pair_and_ignores_rigid_motion():
    # A folded strip (two layers 2 cm apart) with a smooth and a noisy displacement field.
    scene = CS.folded_sheet(pd=0.03, frames=1)
    x = np.asarray(scene.x0, np.float64)
    faces = np.asarray(scene.model.faces)
    rng = np.random.default_rng(0)
    y = x + 0.003 * rng.standard_normal(x.shape)
    d = 0.01 * np.sin(9 * x[:, [1, 2, 0]]) + 0.004 * rng.standard_normal(x.shape)
    thickness = 0.025  # wide enough that the layers' vertices meet the other layer
    got = float(_bound([jnp.asarray(y, jnp.float32)], [jnp.asarray(d, jnp.float32)],
                       scene.model.faces, thickness))
    tri = y[faces]
    _, d2, _ = _closest(jnp.asarray(y[:, None]), *(jnp.asarray(tri[None, :, k])
                                                    for k in range(3)))
    v, t = np.nonzero(np.sqrt(np.asarray(d2)) < thickness)
    rel = np.linalg.norm(d[v][:, None] - d[faces[t]], axis=-1).max()
    assert len(v) > 1000 and rel > 0.01
    assert got >= rel * (1 - 1e-5)
    # A step in the displacement on a cell boundary (cell = thickness + longest edge, as the
    # bound computes it): each cell moves rigidly, so only the 27-cell neighbourhood sees the
    # pairs across the step (a per-cell box would give 0).
    e = tri - np.roll(tri, 1, axis=1)
    cell = np.float32(thickness + np.sqrt((e * e).sum(-1).max()) + 1e-6)
    cut = cell * np.round(np.median(y[:, 0]) / cell)
    step = np.where(y[:, :1] >= cut, [[0.0, 0.0, 0.008]], 0.0)
    across = np.linalg.norm(step[v][:, None] - step[faces[t]], axis=-1).max()
    assert across == 0.008
    got = float(_bound([jnp.asarray(y, jnp.float32)], [jnp.asarray(step, jnp.float32)],
                       scene.model.faces, thickness))
    assert got >= across * (1 - 1e-5)
    # A rigid translation moves no pair relative to another: no rebuild needed (the Verlet
    # rule, twice the largest displacement, would ask for one at 0.77 m).
    shift = np.broadcast_to(np.array([0.3, -0.2, 0.1]), x.shape)
    rigid = float(_bound([jnp.asarray(y, jnp.float32)], [jnp.asarray(shift, jnp.float32)],
                         scene.model.faces, thickness))
    assert rigid < 1e-6


def test_on_motion_rebuild_stops_a_fast_layer_that_one_build_per_frame_misses():
    # The upper sheet starts 4 cm above the lower one at 3 m/s down: 5 mm per substep, past
    # the lower sheet within the frame. The frame's first build (reach 12 mm) finds no pair,
    # so with one build per frame the sheets pass through; on motion the candidates follow.
    scene = CS.two_sheets(pd=0.03, size=0.2, frames=1)
    g = scene.mesh.garment
    upper = np.zeros(len(scene.x0), bool)
    upper[np.asarray(g.faces)[np.asarray(g.panels) == 1].reshape(-1)] = True
    params = X.fabric_params(M.fabric("silk_charmeuse"))
    d0, d1 = (jax.tree_util.tree_map(lambda a, k=k: a[k], scene.drives) for k in (0, 1))
    v0 = jnp.asarray(np.where(upper[:, None], [0.0, 0.0, -3.0], 0.0), jnp.float32)
    base = S.SelfCollisionConfig(thickness=0.006, margin=0.006, raw_per_vertex=512,
                                 box_per_vertex=32, pairs_per_vertex=16, block=4)
    out = {}
    for every in (0, 20):
        init_fn, step_fn = X.cloth_simulator(X.SimConfig(
            substeps=20, self_collision=dataclasses.replace(base, rebuild_every=every)))
        state = init_fn(scene.model, scene.x0).replace(v=v0)
        out[every] = jax.jit(step_fn)(scene.model, params, state, d0, d1)
    faces = np.asarray(scene.model.faces)
    moving, once = (np.asarray(out[k].x) for k in (0, 20))
    assert np.isfinite(moving).all()
    # One build per frame: the upper sheet passes through the lower one.
    assert (len(intersect.intersecting_pairs(once, faces)) > 0
            or np.median(once[upper, 2]) < np.median(once[~upper, 2]))
    # On motion: rebuilt while the layers close in, no crossing, layers in order.
    over = np.asarray(out[0].self_overflow)
    assert over[:3].tolist() == [0, 0, 0] and 3 <= over[3] <= 20
    assert len(intersect.intersecting_pairs(moving, faces)) == 0
    assert np.median(moving[upper, 2]) > np.median(moving[~upper, 2])


def test_run_frames_carries_the_candidates_across_frames():
    # Two sheets in free fall (2 frames, 2.4 cm, before the lower one meets the ball) move
    # rigidly relative to each other: within one run_frames call the only build is the first
    # substep's; frame by frame, every frame builds once.
    scene = CS.two_sheets(pd=0.03, size=0.2, frames=2)
    params = X.fabric_params(M.fabric("silk_charmeuse"))
    sc = S.SelfCollisionConfig(thickness=0.006, margin=0.006, rebuild_every=0,
                               raw_per_vertex=512, box_per_vertex=32, pairs_per_vertex=16,
                               block=4)
    config = X.SimConfig(substeps=4, self_collision=sc)
    init_fn, step_fn = X.cloth_simulator(config)
    state, xs = X.run_frames(config, scene.model, params, init_fn(scene.model, scene.x0),
                             scene.drives)
    assert np.asarray(state.self_overflow).tolist() == [0, 0, 0, 1]
    one = init_fn(scene.model, scene.x0)
    step = jax.jit(step_fn)
    for k in range(2):
        d0, d1 = (jax.tree_util.tree_map(lambda a, i=i: a[i], scene.drives) for i in (k, k + 1))
        one = step(scene.model, params, one, d0, d1)
    assert np.asarray(one.self_overflow).tolist() == [0, 0, 0, 2]
    np.testing.assert_allclose(np.asarray(one.x), np.asarray(xs[-1]), atol=1e-5)
