"""Simulator test helpers shared by test_sim_xpbd.py and test_sim_colliders.py: a sheet mesh,
per-frame drives and a run of the XPBD step over them."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from wrinkle_jax.sim import colliders as C
from wrinkle_jax.sim import patterns as P
from wrinkle_jax.sim import xpbd as X


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
