"""Capsule collision proxies of the character's body, rigidly attached to bones.

Contract (shapes; B bones, C capsules, N points):
  * `fit_capsules(skel, vertices, weights) -> Capsules` (NumPy, once): one capsule per major
    bone (`BODY_CAPSULE_BONES`), fitted to the body vertices that bone dominates.
  * `pose_capsules(caps, mats) -> (C, 2, 3)` posed endpoints from skinning matrices
    (B, 3, 4); `capsule_distance(points, ends, radii) -> (N,)` signed distance to the union
    (negative inside). Both jittable; vmap over frames.
  * A bone dominating too few vertices raises `CharacterError`.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from wrinkle_jax.character.assets import CharacterError
from wrinkle_jax.character.rig import Skeleton, SkinWeights
from wrinkle_jax.numerics import safe_div, safe_norm


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Capsules:
    """Capsules rigidly attached to bones.

    Attributes:
      ends: (C, 2, 3) float32 rest segment endpoints, armature space, meters.
      radii: (C,) float32 meters.
      bone_ids: (C,) int32 bone of each capsule.
      names: static bone names.
    """

    ends: Any
    radii: Any
    bone_ids: Any
    names: tuple[str, ...] = dataclasses.field(metadata=dict(static=True))


# Bones that get a capsule by default: trunk, head and limbs (not the face, fingers or toes).
BODY_CAPSULE_BONES = (
    "spine05", "spine04", "spine03", "spine02", "spine01", "neck01", "neck02", "head",
    "breast.L", "breast.R",
    *(f"{b}.{s}" for s in "LR" for b in ("upperleg01", "upperleg02", "lowerleg01",
                                         "lowerleg02", "foot", "upperarm01", "upperarm02",
                                         "lowerarm01", "lowerarm02", "wrist")),
)


def fit_capsules(skel: Skeleton, vertices, weights: SkinWeights,
                 bones: Sequence[str] | None = BODY_CAPSULE_BONES, min_vertices: int = 40,
                 coverage: float = 0.8, end_quantile: float = 0.05) -> Capsules:
    """Fit one capsule per bone to the body vertices that bone dominates (NumPy, once).

    The axis is the bone's direction through its head; the segment spans the `end_quantile`
    to 1 - `end_quantile` quantiles of the vertices' positions along it; the radius is the
    `coverage` quantile of their distances to that segment (so about `coverage` of the
    vertices are inside; the trunk's cross-section is an ellipse, so a round capsule that
    holds most of it bulges out front and back).

    Args:
      vertices: (V, 3) rest body vertices; weights: their `SkinWeights`.
      bones: bones to fit (those present in `skel`); None fits every bone dominating at
        least `min_vertices` vertices (face, fingers and toes included).
    """
    v = np.asarray(vertices, np.float64)
    dominant = np.asarray(weights.bone_ids)[:, 0]
    if bones is None:
        counts = np.bincount(dominant, minlength=skel.num_bones)
        ids = [b for b in range(skel.num_bones) if counts[b] >= min_vertices]
    else:
        ids = [skel.index(b) for b in bones if b in skel.names]
    rest = np.asarray(skel.rest, np.float64)
    ends, radii = [], []
    for b in ids:
        pts = v[dominant == b]
        if len(pts) < 4:
            raise CharacterError(f"bone {skel.names[b]!r} dominates too few vertices "
                                 f"({len(pts)}) for a capsule")
        axis, head = rest[b, :3, 1], rest[b, :3, 3]
        s = (pts - head) @ axis
        s0, s1 = np.quantile(s, [end_quantile, 1 - end_quantile])
        seg = np.stack([head + s0 * axis, head + s1 * axis])
        ends.append(seg)
        radii.append(np.quantile(_segment_distance_np(pts, seg), coverage))
    return Capsules(np.asarray(ends, np.float32), np.asarray(radii, np.float32),
                    np.asarray(ids, np.int32), tuple(skel.names[b] for b in ids))


def _segment_distance_np(p, seg):
    d = seg[1] - seg[0]
    t = np.clip((p - seg[0]) @ d / max(d @ d, 1e-30), 0.0, 1.0)
    return np.linalg.norm(p - (seg[0] + t[:, None] * d), axis=1)


def pose_capsules(caps: Capsules, mats):
    """Posed capsule endpoints (C, 2, 3) from skinning matrices (B, 3, 4)."""
    m = mats[caps.bone_ids]  # (C, 3, 4)
    return jnp.einsum("cij,ckj->cki", m[..., :3], caps.ends) + m[:, None, :, 3]


def capsule_distance(points, ends, radii):
    """Signed distance (N,) from points (N, 3) to the union of capsules (negative inside).

    Args:
      ends: (C, 2, 3) endpoints (e.g. `pose_capsules`); radii: (C,).
    """
    a, d = ends[:, 0], ends[:, 1] - ends[:, 0]  # (C, 3)
    rel = points[:, None, :] - a[None]  # (N, C, 3)
    t = jnp.clip(safe_div(jnp.sum(rel * d, -1), jnp.sum(d * d, -1)), 0.0, 1.0)
    dist = safe_norm(rel - t[..., None] * d) - radii
    return jnp.min(dist, axis=1)
