"""Small cloth-on-cloth scenes that exercise self-collision (tests, benchmark, experiments).

  two_sheets     two square sheets (the upper one turned 45 degrees, 4 cm above) fall onto a
                 ball on the floor: the upper drapes over the lower, which drapes over the ball
  folded_sheet   a strip folded in half (2 cm between the layers, a round fold) falls onto a
                 ball on the floor: the top layer settles onto the bottom one

Both are one garment (the two sheets are two panels), so the solver sees one mesh and every
cloth-cloth contact is a self-contact. Without self-collision the layers pass through each
other (see `experiments/self_collision.py` for the numbers).
"""

from __future__ import annotations

import dataclasses
import math

import jax.numpy as jnp
import numpy as np

from wrinkle_jax.sim import patterns, xpbd
from wrinkle_jax.sim.colliders import Colliders


@dataclasses.dataclass(frozen=True, eq=False)
class ContactScene:
    """A mesh, its solver model, initial positions (V, 3) m and drives (frames + 1)."""

    mesh: patterns.PatternMesh
    model: xpbd.ClothModel
    x0: np.ndarray
    drives: xpbd.Drive


def _square(size: float) -> tuple:
    c = np.array([[0, 0], [size, 0], [size, size], [0, size]], np.float64)
    return tuple(patterns._poly([c[i], c[(i + 1) % 4]]) for i in range(4))


def _ball_and_floor(frames: int, center, radius: float) -> Colliders:
    n = frames + 1
    return Colliders(
        sphere_centers=jnp.asarray(np.broadcast_to(np.asarray(center, np.float32), (n, 1, 3))),
        sphere_radii=jnp.full((n, 1), radius, jnp.float32),
        planes=jnp.asarray(np.broadcast_to(np.array([0, 0, 1, 0], np.float32), (n, 1, 4))))


def _scene(pattern, pd: float, frames: int, colliders: Colliders, seed: int) -> ContactScene:
    mesh = patterns.mesh_pattern(pattern, pd, seed=seed)
    g = mesh.garment
    model = xpbd.build_cloth(g, None, use_aero=False)
    n = frames + 1
    drives = xpbd.Drive(time=jnp.arange(n, dtype=jnp.float32) / 30.0, pins=None,
                        colliders=colliders, extra_damping=jnp.zeros(n, jnp.float32))
    return ContactScene(mesh, model, np.asarray(g.vertices, np.float32), drives)


def two_sheets(pd: float = 0.03, frames: int = 45, size: float = 0.3, gap: float = 0.04,
               seed: int = 0) -> ContactScene:
    """Two size x size sheets, 45 degrees apart, `gap` m apart, over a ball (r = 0.1 m)."""
    z0 = 0.25
    rot = math.pi / 4

    def drape(i, p):
        q = p - size / 2
        if i == 1:
            c, s = math.cos(rot), math.sin(rot)
            q = q @ np.array([[c, s], [-s, c]])
        return np.concatenate([q, np.full((len(p), 1), z0 + i * gap)], 1)

    pat = patterns.Pattern("two_sheets", (patterns.Panel("lower", _square(size)),
                                          patterns.Panel("upper", _square(size))), (), drape, {})
    return _scene(pat, pd, frames, _ball_and_floor(frames, (0.0, 0.0, 0.1), 0.1), seed)


def folded_sheet(pd: float = 0.03, frames: int = 300, length: float = 0.6, width: float = 0.3,
                 gap: float = 0.02, seed: int = 0) -> ContactScene:
    """A length x width strip folded in half across its length (round fold of diameter
    `gap`), the fold at x = 0.1, falling onto a ball (r = 0.08 m) on the floor."""
    r = gap / 2
    z0 = 0.2
    half = 0.5 * (length - math.pi * r)  # flat length of each layer

    def drape(_, p):
        u, v = p[:, 0], p[:, 1] - width / 2
        theta = np.clip((u - half) / r, 0.0, math.pi)
        x = np.where(u < half, u - half,
                     np.where(u > half + math.pi * r, -(u - half - math.pi * r),
                              r * np.sin(theta)))
        z = np.where(u < half, 0.0,
                     np.where(u > half + math.pi * r, 2 * r, r * (1 - np.cos(theta))))
        return np.stack([x + 0.1, v, z + z0], 1)

    pat = patterns.Pattern("folded_sheet", (patterns.Panel("strip", patterns._rect(length,
                                                                                   width)),),
                           (), drape, {})
    return _scene(pat, pd, frames, _ball_and_floor(frames, (-0.05, 0.0, 0.0), 0.08), seed)
