"""Simulator test helpers shared by test_sim_xpbd.py and test_sim_colliders.py (a sheet mesh,
per-frame drives and a run of the XPBD step over them) and by test_sim_pokethrough.py and
test_sim_untangle.py (two sheets settled on each other with self-collision)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from wrinkle_jax.sim import colliders as C
from wrinkle_jax.sim import contact_scenes as CS
from wrinkle_jax.sim import materials as M
from wrinkle_jax.sim import patterns as P
from wrinkle_jax.sim import selfcollision as S
from wrinkle_jax.sim import xpbd as X

# The blocked build of test_sim_selfcollision (roomy bounds: nothing dropped on these scenes).
BLOCKED = S.SelfCollisionConfig(thickness=0.006, margin=0.006, raw_per_vertex=512,
                                box_per_vertex=32, pairs_per_vertex=16, block=4)


def sheet(size=0.3, pd=0.03, z=1.0, horizontal=False, seed=0):
    """A size x size (m) sheet meshed at `pd` (m): in the x-z plane, its top edge at height `z`,
    or lying flat at height `z` centred on the origin (`horizontal`). Returns (pattern, mesh)."""
    pat = P.sheet_pattern(size, size, top=z)
    if horizontal:
        pat = P.Pattern("table", pat.panels, (), lambda i, p: np.stack(
            [p[:, 0] - size / 2, p[:, 1] - size / 2, np.full(len(p), z)], 1), {})
    return pat, P.mesh_pattern(pat, pd, seed=seed)


def drives(frames, pins=None, colliders=None):
    """`X.Drive` of frames + 1 instants at 30 fps: optional pin tracks and colliders."""
    n = frames + 1
    return X.Drive(time=jnp.arange(n, dtype=jnp.float32) / 30.0,
                   pins=None if pins is None else jnp.asarray(pins),
                   colliders=colliders or C.Colliders(),
                   extra_damping=jnp.zeros(n, jnp.float32))


def run(model, params, x0, drives, config=None):
    """Simulate from rest positions `x0` over `drives` (`X.simulate_frames`)."""
    config = config or X.SimConfig()
    init_fn, _ = X.cloth_simulator(config)
    return X.simulate_frames(config, model, params, init_fn(model, x0), drives)


# Frames per compiled chunk of `run_scene`: one length for the settling and the tests' runs,
# so a test's run without its feature is the settling's program (the suite's JAX cache hands it
# over instead of compiling the solver again).
SCENE_CHUNK = 12


def run_scene(scene, params, cfg, state, k0, n):
    """n frames of a `contact_scenes` scene from frame k0 and `state`, self-collision `cfg`, in
    chunks of SCENE_CHUNK: (final ClothState, positions (n, V, 3))."""
    drives = jax.tree_util.tree_map(lambda a: a[k0:k0 + n + 1], scene.drives)
    return X.simulate_frames(X.SimConfig(self_collision=cfg), scene.model, params, state,
                             drives, chunk=SCENE_CHUNK)


def settled_two_sheets():
    """`contact_scenes.two_sheets` (PD 20 mm, 20 cm) after 24 frames of silk_charmeuse with
    BLOCKED: the upper layer resting on the lower over the ball. (scene, params, state)."""
    scene = CS.two_sheets(pd=0.02, size=0.2, frames=40)
    params = X.fabric_params(M.fabric("silk_charmeuse"))
    init_fn, _ = X.cloth_simulator(X.SimConfig(self_collision=BLOCKED))
    state, _ = run_scene(scene, params, BLOCKED, init_fn(scene.model, scene.x0), 0, 24)
    return scene, params, state


def upper_layer(scene):
    """(V,) bool: the vertices of a `two_sheets` scene's upper sheet (panel 1)."""
    faces = np.asarray(scene.model.faces)
    upper = np.zeros(len(scene.x0), bool)
    upper[faces[np.asarray(scene.mesh.garment.panels) == 1].reshape(-1)] = True
    return upper


def push_below(x, verts, upper, depth=0.005):
    """x (V, 3) with each vertex of `verts` set `depth` m below the lower-layer vertex nearest
    to it in x-y (in place; returned)."""
    lo = np.flatnonzero(~upper)
    for v in verts:
        x[v, 2] = x[lo[np.argmin(np.linalg.norm(x[lo, :2] - x[v, :2], axis=1))], 2] - depth
    return x
