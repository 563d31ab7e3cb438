"""Tests for the poke-through repair (wrinkle_jax.sim.pokethrough)."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from sim_fixtures import (  # tests/ is on sys.path
    BLOCKED,
    push_below,
    run_scene,
    settled_two_sheets,
    upper_layer,
)

from wrinkle_jax import mesh
from wrinkle_jax.sim import intersect
from wrinkle_jax.sim import pokethrough as P
from wrinkle_jax.sim import selfcollision as S
from wrinkle_jax.sim import xpbd as X

_crossing_fraction = jax.jit(P.crossing_fraction)
# Jitted, as the solver runs them: op by op they compiled ~130 one-op programs per test.
_repair_sides = jax.jit(P.repair_sides)
_contact_frame = jax.jit(S.contact_frame)


def _grid(n: int, z: float, offset: int = 0, size: float = 0.1):
    """An n x n vertex grid at height z (vertices (n*n, 3), faces (2 (n-1)^2, 3))."""
    u = np.linspace(0.0, size, n)
    xy = np.stack(np.meshgrid(u, u, indexing="ij"), -1).reshape(-1, 2)
    v = np.concatenate([xy, np.full((len(xy), 1), z)], 1)
    i = np.arange(n - 1)[:, None] * n + np.arange(n - 1)[None]
    i = i.reshape(-1)
    f = np.concatenate([np.stack([i, i + n, i + 1], 1), np.stack([i + 1, i + n, i + n + 1], 1)])
    return v, f + offset


def _two_layers(n: int = 7, gap: float = 0.005):
    lo, flo = _grid(n, 0.0)
    hi, fhi = _grid(n, gap, offset=n * n)
    hi[:, :2] += 0.1 / (n - 1) / 3  # no vertex straight above another
    return np.concatenate([lo, hi]).astype(np.float32), np.concatenate([flo, fhi]).astype(np.int32)


def _all_pairs(x, faces):
    """Every (vertex, triangle) pair of different layers (no shared vertex)."""
    n = len(x) // 2
    layer_v = np.arange(len(x)) >= n
    layer_t = faces[:, 0] >= n
    v, t = np.nonzero(layer_v[:, None] != layer_t[None])
    return jnp.asarray(v, jnp.int32), jnp.asarray(t, jnp.int32)


def test_face_neighbours_share_an_edge_and_are_symmetric():
    _, faces = _grid(5, 0.0)
    topo = P.poke_topology(faces, 25)
    nbr = np.asarray(topo.face_nbr)
    _, counts = mesh.edge_face_counts(faces)
    boundary = 0
    for i, f in enumerate(faces):
        for k in range(3):
            j = nbr[i, k]
            edge = {f[k], f[(k + 1) % 3]}
            if j == i:
                boundary += 1
                continue
            assert edge <= set(faces[j]) and i in nbr[j]
    assert boundary == int((counts == 1).sum())  # every boundary edge, and only those
    ring = np.asarray(topo.ring)[12][np.asarray(topo.ring_valid)[12]]
    assert sorted(ring) == sorted(set(faces[(faces == 12).any(1)].reshape(-1)) - {12})


def test_segment_test_agrees_with_the_independent_checker():
    rng = np.random.default_rng(0)
    p, q, a, b, c = (rng.normal(size=(4000, 3)) for _ in range(5))
    got = np.asarray(P.segment_crosses_triangle(*(jnp.asarray(t) for t in (p, q, a, b, c))))
    want = intersect.segment_hits_triangle(p, q, a, b, c)
    assert 0.05 < want.mean() < 0.95
    assert (got == want).mean() > 0.999  # float32 against float64: a hit on an edge may flip


def _frame(x, faces, v, t, sides=None):
    pairs = S.Pairs(v, t, jnp.full(v.shape, 0.006), jnp.ones(v.shape, bool))
    return np.asarray(_contact_frame(jnp.asarray(x), jnp.asarray(faces), pairs, sides).d)


def test_layers_apart_have_no_crossing_and_keep_every_direction():
    # An intersection-free mesh has no crossing edge: the repair changes nothing there.
    x, faces = _two_layers()
    topo = P.poke_topology(faces, len(x))
    v, t = _all_pairs(x, faces)
    frac = np.asarray(_crossing_fraction(jnp.asarray(x), jnp.asarray(faces), topo, v, t))
    assert frac.max() == 0.0
    sides = _repair_sides(jnp.asarray(x), jnp.asarray(faces), topo, v, t, 0.5)
    assert not np.asarray(sides).any()
    np.testing.assert_array_equal(_frame(x, faces, v, t, sides), _frame(x, faces, v, t))


def test_a_poked_vertex_is_sent_back_to_its_rings_side():
    x, faces = _two_layers()
    n = len(x) // 2
    poked = n + 3 * 7 + 3                       # an interior vertex of the upper layer
    x[poked, 2] = -0.004                        # pushed 4 mm through the lower layer
    topo = P.poke_topology(faces, len(x))
    v, t = _all_pairs(x, faces)
    frac = np.asarray(_crossing_fraction(jnp.asarray(x), jnp.asarray(faces), topo, v, t))
    vv, tt = np.asarray(v), np.asarray(t)
    # Its contact with the triangle it went through: all six ring edges cross that patch.
    below = intersect.intersecting_pairs(x, faces)
    through = {int(f) for pair in below for f in pair if faces[f][0] < n}
    mine = (vv == poked) & np.isin(tt, list(through))
    assert mine.any() and frac[mine].max() == 1.0
    assert frac[vv != poked].max() <= 0.5      # no other vertex has most of its ring across
    sides = _repair_sides(jnp.asarray(x), jnp.asarray(faces), topo, v, t, 0.5)
    fixed = frac > 0.5
    # Both layers' normals point up (+z): the poked vertex is sent back up, whatever side
    # the start-side rule would keep it on.
    np.testing.assert_array_equal(np.asarray(sides), np.where(fixed, 1.0, 0.0))
    out, plain = _frame(x, faces, v, t, sides), _frame(x, faces, v, t)
    np.testing.assert_allclose(out[fixed], np.tile([0.0, 0.0, 1.0], (fixed.sum(), 1)), atol=1e-6)
    assert (plain[fixed][:, 2] < 0).all()       # without the repair: held below
    np.testing.assert_array_equal(out[~fixed], plain[~fixed])


@pytest.fixture(scope="module")
def settled_sheets():
    return settled_two_sheets()


def test_solver_undoes_poke_throughs_that_the_start_side_rule_keeps(settled_sheets):
    scene, params, state = settled_sheets
    faces = np.asarray(scene.model.faces)
    upper = upper_layer(scene)
    x = np.asarray(state.x).copy()
    assert len(intersect.intersecting_pairs(x, faces)) == 0
    # Four upper vertices over the top of the ball pushed 5 mm below the lower layer.
    up = np.flatnonzero(upper)
    near = up[np.argsort(np.linalg.norm(x[up, :2], axis=1), kind="stable")[:10]]
    push_below(x, near[[0, 3, 6, 9]], upper)
    assert len(intersect.intersecting_pairs(x, faces)) > 10
    start = dataclasses.replace(state, x=jnp.asarray(x))
    counts = {}
    for repair in (0.0, 0.5):
        end, xs = run_scene(scene, params, dataclasses.replace(BLOCKED, poke_repair=repair),
                       start, 24, 12)
        assert np.isfinite(xs).all() and np.asarray(end.self_overflow).tolist() == [0, 0, 0]
        counts[repair] = [len(intersect.intersecting_pairs(y, faces)) for y in np.asarray(xs)]
    # Measured: without the repair the crossings persist and spread (6-20 pairs in every
    # frame); with it they are gone in the first two frames, and 1-3 pairs (other crossings
    # the contacts form later, at PD 20 mm) appear afterwards: 13 pairs in all against 136.
    assert min(counts[0.0]) > 0 and counts[0.5][:2] == [0, 0]
    assert 5 * sum(counts[0.5]) < sum(counts[0.0])


def test_repair_fraction_is_validated():
    with pytest.raises(ValueError, match="poke_repair"):
        X.cloth_simulator(X.SimConfig(self_collision=dataclasses.replace(BLOCKED,
                                                                         poke_repair=1.0)))
