"""The MakeHuman rig: skeleton, skinning weights, poses, forward kinematics and linear blend
skinning (LBS).

Frame and units: the character frame (meters, Z up, facing -Y; see `wrinkle_jax.character`).

Contract (shapes; B bones, V vertices, K influences per vertex, T frames):
  * `load_skeleton(rig_path, base)` reads an MPFB rig json once in NumPy: rest joints
    recomputed from the base mesh with the rig's placement rules, plus MPFB's IK helper bones
    (`IK_LIMBS`) that the walk cycles animate. `load_skin_weights` reads top-K weights.
  * `Skeleton` is a pytree: rest matrices (B, 4, 4) float32 are leaves; bone names and parent
    indices are static. Bones are ordered by depth (every parent before its children).
  * `Pose`: per-bone `rotations` (B, 3, 3) and `locations` (B, 3) meters, both in the bone's
    rest frame (Blender pose-bone semantics: basis = T(location) R(rotation)).
  * `forward_kinematics(skel, pose) -> (B, 4, 4)` posed bone matrices (armature space), by
    pointer jumping over the hierarchy (ceil(log2 depth) batched matmuls, 5 for this rig);
    `skinning_matrices -> (B, 3, 4)` maps rest to posed.
  * `skin(vertices, weights, mats) -> (V, 3)`: blocked sparse LBS over the K padded
    influences (gathers, no dense V x B product); `skin_frames` over (T, B, 3, 4) matrices
    -> (T, V, 3). All the JAX functions here are jittable and vmap over frames.
  * Bad input raises `CharacterError` naming the file and the problem.

Asset formats (MPFB2):
  * rig.*.json: {bone: {"parent": name or "", "roll": radians, "head"/"tail": {"strategy":
    "CUBE" (mean of the vertices of group `cube_name`, e.g. "joint-l-knee") | "VERTEX"
    (`vertex_index`) | "MEAN" (mean of `vertex_indices`), "default_position": [x, y, z]
    (character frame, for MPFB's default human)}, "use_connect", "use_inherit_rotation",
    "use_local_location", "inherit_scale"}}. Every bone of the standard rigs inherits
    rotation and uses local location, the only mode implemented (checked at load time).
  * weights.*.json: {"weights": {bone: [[vertex_id, weight], ...]}, ...}; vertex ids index
    base.obj (helpers included), weights per vertex sum to 1 (we renormalize after top-K).
"""

from __future__ import annotations

import dataclasses
import math
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from wrinkle_jax.character.assets import CharacterError, read_json
from wrinkle_jax.character.mesh import BaseMesh
from wrinkle_jax.numerics import normalize, safe_norm

# --------------------------------------------------------------------------------------------
# Skeleton
# --------------------------------------------------------------------------------------------


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Skeleton:
    """Bone hierarchy and rest pose. Bones are ordered by depth (parents first).

    Attributes:
      rest: (B, 4, 4) float32 rest matrices in armature space: columns x, y, z are the bone
        axes (y from head to tail), translation is the head (meters).
      rest_inv: (B, 4, 4) float32 inverses of `rest`.
      rest_rel: (B, 4, 4) float32 parent-relative rest matrices inv(rest[parent]) rest[b]
        (`rest[b]` for roots).
      lengths: (B,) float32 head-to-tail lengths (meters).
      names: static bone names.
      parents: static parent index of each bone (-1 for roots).
    """

    rest: Any
    rest_inv: Any
    rest_rel: Any
    lengths: Any
    names: tuple[str, ...] = dataclasses.field(metadata=dict(static=True))
    parents: tuple[int, ...] = dataclasses.field(metadata=dict(static=True))

    @property
    def num_bones(self) -> int:
        return len(self.names)

    def index(self, name: str) -> int:
        """Index of bone `name` (KeyError naming the missing bone)."""
        try:
            return self.names.index(name)
        except ValueError:
            raise KeyError(f"no bone {name!r} in the skeleton") from None

    @property
    def heads(self) -> np.ndarray:
        """(B, 3) rest head positions (NumPy)."""
        return np.asarray(self.rest)[:, :3, 3]

    @property
    def tails(self) -> np.ndarray:
        """(B, 3) rest tail positions (NumPy)."""
        r = np.asarray(self.rest)
        return r[:, :3, 3] + r[:, :3, 1] * np.asarray(self.lengths)[:, None]


def bone_rest_matrix(head, tail, roll: float) -> np.ndarray:
    """Blender's edit-bone matrix (4, 4) from head, tail (meters) and roll (radians).

    y is the unit head -> tail direction; x and z come from the smallest rotation taking the
    armature's Y axis onto y, then a rotation by `roll` about y (Blender's vec_roll_to_mat3).
    """
    head, tail = np.asarray(head, np.float64), np.asarray(tail, np.float64)
    y = tail - head
    n = np.linalg.norm(y)
    if n <= 1e-9:
        raise CharacterError(f"zero-length bone at {head.tolist()}")
    y = y / n
    c = y[1]
    if 1.0 + c < 1e-9:  # y == -Y: the smallest rotation is not unique; Blender's choice
        base = np.diag([-1.0, -1.0, 1.0])
    else:
        v = np.array([y[2], 0.0, -y[0]])  # Y x y
        vx = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
        base = np.eye(3) + vx + vx @ vx / (1.0 + c)
    m = np.eye(4)
    m[:3, :3] = _axis_angle_np(y, roll) @ base
    m[:3, 3] = head
    return m


def _axis_angle_np(axis, angle) -> np.ndarray:
    x, y, z = axis
    k = np.array([[0, -z, y], [z, 0, -x], [-y, x, 0]])
    return np.eye(3) + math.sin(angle) * k + (1 - math.cos(angle)) * k @ k


def make_skeleton(names: Sequence[str], parents: Sequence[str | None], heads, tails,
                  rolls) -> Skeleton:
    """Build a `Skeleton` from per-bone parent names, heads, tails (meters) and rolls."""
    names = list(names)
    index = {n: i for i, n in enumerate(names)}
    par = [index[p] if p else -1 for p in parents]
    missing = [p for p in parents if p and p not in index]
    if missing:
        raise CharacterError(f"unknown parent bone(s) {missing}")
    depth = [-1] * len(names)

    def depth_of(i, seen=()):
        if depth[i] < 0:
            if i in seen:
                raise CharacterError(f"cycle in the bone hierarchy at {names[i]!r}")
            depth[i] = 0 if par[i] < 0 else depth_of(par[i], (*seen, i)) + 1
        return depth[i]

    for i in range(len(names)):
        depth_of(i)
    order = sorted(range(len(names)), key=lambda i: (depth[i], names[i]))
    new = {old: k for k, old in enumerate(order)}
    rest = np.stack([bone_rest_matrix(heads[i], tails[i], rolls[i]) for i in order])
    parents_new = tuple(new[par[i]] if par[i] >= 0 else -1 for i in order)
    rel = np.stack([rest[k] if p < 0 else np.linalg.solve(rest[p], rest[k])
                    for k, p in enumerate(parents_new)])
    lengths = np.array([np.linalg.norm(np.subtract(tails[i], heads[i])) for i in order])
    return Skeleton(rest.astype(np.float32), np.linalg.inv(rest).astype(np.float32),
                    rel.astype(np.float32), lengths.astype(np.float32),
                    tuple(names[i] for i in order), parents_new)


# MPFB's default IK helper set-up for the standard rig (RigHelpers with LOWERUPPER legs and
# arms): the end target copies the end bone's rest matrix, the pole sits at the middle joint
# and points along the upper segment (1/5 of it for knees, 1/3 for elbows, roll 0). Leg helpers
# have no parent (parenting strategy NONE), arm helpers hang from spine01 (strategy SPINE).
IK_LIMBS = {
    # limb: (upper1, upper2, lower1, lower2, end, target, pole, pole length, helper parent,
    #        anatomical direction the middle joint points to, character frame)
    "left_leg": ("upperleg01.L", "upperleg02.L", "lowerleg01.L", "lowerleg02.L", "foot.L",
                 "left_foot_ik", "left_knee_ik", 0.2, None, (0.0, -1.0, 0.0)),
    "right_leg": ("upperleg01.R", "upperleg02.R", "lowerleg01.R", "lowerleg02.R", "foot.R",
                  "right_foot_ik", "right_knee_ik", 0.2, None, (0.0, -1.0, 0.0)),
    "left_arm": ("upperarm01.L", "upperarm02.L", "lowerarm01.L", "lowerarm02.L", "wrist.L",
                 "left_hand_ik", "left_elbow_ik", 1 / 3, "spine01", (0.0, 1.0, 0.0)),
    "right_arm": ("upperarm01.R", "upperarm02.R", "lowerarm01.R", "lowerarm02.R", "wrist.R",
                  "right_hand_ik", "right_elbow_ik", 1 / 3, "spine01", (0.0, 1.0, 0.0)),
}


def load_skeleton(rig_path: str | os.PathLike, base: BaseMesh | None,
                  ik_helpers: bool = True, placement: str = "mesh") -> Skeleton:
    """Read an MPFB rig json.

    Args:
      rig_path: rig.*.json.
      base: the base mesh whose vertices (and `joint-*` cube groups) place heads and tails.
      ik_helpers: add MPFB's IK helper bones (`IK_LIMBS`) used by the walk cycles.
      placement: "mesh" places joints on `base` with the rig's strategies (what MPFB does
        when it rigs a human); "default" uses the stored `default_position`s (MPFB's default
        human: the frames animations were authored in, used to retarget them).
    """
    rig_path = Path(rig_path)
    rig = read_json(rig_path)
    if placement not in ("mesh", "default") or (placement == "mesh" and base is None):
        raise ValueError(f"placement must be 'mesh' (with a base mesh) or 'default', "
                         f"got {placement!r}")
    verts = None if base is None else np.asarray(base.mesh.vertices, np.float64)
    names, parents, heads, tails, rolls = [], [], [], [], []
    for name, bone in rig.items():
        try:
            if not (bone.get("use_inherit_rotation", True) and bone.get("use_local_location",
                                                                         True)):
                raise CharacterError(f"{rig_path}: bone {name!r} uses an unsupported "
                                     "inheritance mode")
            if placement == "mesh":
                head = _joint_position(bone["head"], verts, base)
                tail = _joint_position(bone["tail"], verts, base)
            else:
                head = np.asarray(bone["head"]["default_position"], np.float64)
                tail = np.asarray(bone["tail"]["default_position"], np.float64)
            names.append(name)
            parents.append(bone.get("parent") or None)
            heads.append(head)
            tails.append(tail)
            rolls.append(float(bone.get("roll", 0.0)))
        except (KeyError, TypeError, IndexError) as e:
            raise CharacterError(f"{rig_path}: bone {name!r} is malformed ({e!r})") from None
    if ik_helpers:
        index = {n: i for i, n in enumerate(names)}
        for (_, u2, _, _, end, target, pole, frac, parent, _) in IK_LIMBS.values():
            if end not in index or u2 not in index:
                continue
            e, u = index[end], index[u2]
            names += [target, pole]
            parents += [parent, parent]
            heads += [heads[e], tails[u]]
            tails += [tails[e], tails[u] + frac * (tails[u] - heads[u])]
            rolls += [rolls[e], 0.0]
    return make_skeleton(names, parents, np.array(heads), np.array(tails), np.array(rolls))


def _joint_position(spec: dict, verts: np.ndarray, base: BaseMesh) -> np.ndarray:
    strategy = spec.get("strategy")
    if strategy == "CUBE":
        return verts[base.group_vertex_ids(spec["cube_name"])].mean(0)
    if strategy == "VERTEX":
        return verts[int(spec["vertex_index"])]
    if strategy == "MEAN":
        return verts[np.asarray(spec["vertex_indices"], np.int64)].mean(0)
    if "default_position" in spec:  # unknown rule: MPFB's position for its default human
        return np.asarray(spec["default_position"], np.float64)
    raise KeyError(f"unknown placement strategy {strategy!r}")


# --------------------------------------------------------------------------------------------
# Skinning weights
# --------------------------------------------------------------------------------------------


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class SkinWeights:
    """Top-K bone influences per vertex (padded with weight 0 on bone 0).

    Attributes:
      bone_ids: (V, K) int32 bone indices into the skeleton.
      weights: (V, K) float32, rows sum to 1, sorted by decreasing weight.
    """

    bone_ids: Any
    weights: Any

    def subset(self, vertex_ids) -> SkinWeights:
        """Rows for `vertex_ids`, with K trimmed to the largest count among them (NumPy)."""
        ids = np.asarray(self.bone_ids)[vertex_ids]
        w = np.asarray(self.weights)[vertex_ids]
        k = max(int((w > 0).sum(1).max()), 1)
        return SkinWeights(ids[:, :k], w[:, :k])


def load_skin_weights(path: str | os.PathLike, skeleton: Skeleton, num_vertices: int,
                      max_influences: int | None = None) -> SkinWeights:
    """Read weights.*.json into top-K form (renormalized to sum to 1 per vertex).

    Args:
      max_influences: K; default keeps every influence (12 for the default rig).
    Raises:
      CharacterError: unknown bone, vertex id out of range, or a vertex without weights.
    """
    path = Path(path)
    data = read_json(path)
    table = data.get("weights") if isinstance(data, dict) else None
    if not isinstance(table, dict):
        raise CharacterError(f"{path}: no 'weights' table")
    rows, cols, vals = [], [], []
    for bone, pairs in table.items():
        if not pairs:
            continue
        if bone not in skeleton.names:
            raise CharacterError(f"{path}: weights for unknown bone {bone!r}")
        a = np.asarray(pairs, np.float64).reshape(-1, 2)
        rows.append(a[:, 0].astype(np.int64))
        vals.append(a[:, 1])
        cols.append(np.full(len(a), skeleton.index(bone), np.int64))
    if not rows:
        raise CharacterError(f"{path}: the weights table is empty")
    rows, cols, vals = np.concatenate(rows), np.concatenate(cols), np.concatenate(vals)
    if rows.min() < 0 or rows.max() >= num_vertices:
        raise CharacterError(f"{path}: vertex ids outside [0, {num_vertices})")
    if not np.all(np.isfinite(vals)) or (vals < 0).any():
        raise CharacterError(f"{path}: negative or non-finite weights")
    counts = np.bincount(rows, minlength=num_vertices)
    if (counts == 0).any():
        raise CharacterError(f"{path}: {int((counts == 0).sum())} vertices have no weights, "
                             f"first {int(np.flatnonzero(counts == 0)[0])}")
    k_all = int(counts.max())
    k = k_all if max_influences is None else min(int(max_influences), k_all)
    # Sort by (vertex, -weight) and scatter each vertex's influences into its row.
    order = np.lexsort((-vals, rows))
    rows, cols, vals = rows[order], cols[order], vals[order]
    slot = np.arange(len(rows)) - np.repeat(np.cumsum(counts) - counts, counts)
    keep = slot < k
    ids = np.zeros((num_vertices, k), np.int32)
    w = np.zeros((num_vertices, k), np.float64)
    ids[rows[keep], slot[keep]] = cols[keep]
    w[rows[keep], slot[keep]] = vals[keep]
    total = w.sum(1, keepdims=True)
    if (total <= 0).any():
        raise CharacterError(f"{path}: {int((total <= 0).sum())} vertices have zero total weight")
    w /= total
    return SkinWeights(ids, w.astype(np.float32))


# --------------------------------------------------------------------------------------------
# Poses and forward kinematics (JAX)
# --------------------------------------------------------------------------------------------


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Pose:
    """Per-bone pose channels in each bone's rest frame (Blender pose-bone semantics).

    Attributes:
      rotations: (B, 3, 3) float32 rotation matrices.
      locations: (B, 3) float32 translations, meters.
    """

    rotations: Any
    locations: Any

    def replace(self, **changes) -> Pose:
        return dataclasses.replace(self, **changes)


def rest_pose(skel: Skeleton) -> Pose:
    """The identity pose (every bone at rest)."""
    b = skel.num_bones
    return Pose(jnp.broadcast_to(jnp.eye(3, dtype=jnp.float32), (b, 3, 3)),
                jnp.zeros((b, 3), jnp.float32))


def euler_xyz_to_matrix(angles):
    """Blender 'XYZ' Euler angles (..., 3) radians -> (..., 3, 3): R = Rz(z) Ry(y) Rx(x)."""
    cx, cy, cz = jnp.cos(angles[..., 0]), jnp.cos(angles[..., 1]), jnp.cos(angles[..., 2])
    sx, sy, sz = jnp.sin(angles[..., 0]), jnp.sin(angles[..., 1]), jnp.sin(angles[..., 2])
    rows = [
        [cy * cz, sx * sy * cz - cx * sz, cx * sy * cz + sx * sz],
        [cy * sz, sx * sy * sz + cx * cz, cx * sy * sz - sx * cz],
        [-sy, sx * cy, cx * cy],
    ]
    return jnp.stack([jnp.stack(r, -1) for r in rows], -2)


def quaternion_to_matrix(q):
    """Quaternions (..., 4) as (w, x, y, z), any norm (0 -> identity) -> (..., 3, 3)."""
    n = safe_norm(q, keepdims=True)
    q = jnp.where(n > 0, q / jnp.where(n > 0, n, 1.0), jnp.array([1.0, 0, 0, 0], q.dtype))
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    rows = [
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ]
    return jnp.stack([jnp.stack(r, -1) for r in rows], -2)


def axis_angle_to_matrix(axis, angle):
    """Rodrigues rotation about `axis` (..., 3) (normalized here) by `angle` (...) radians."""
    k = normalize(axis)
    x, y, z = k[..., 0], k[..., 1], k[..., 2]
    zero = jnp.zeros_like(x)
    kx = jnp.stack([jnp.stack([zero, -z, y], -1), jnp.stack([z, zero, -x], -1),
                    jnp.stack([-y, x, zero], -1)], -2)
    s, c = jnp.sin(angle)[..., None, None], jnp.cos(angle)[..., None, None]
    return jnp.eye(3, dtype=kx.dtype) + s * kx + (1 - c) * kx @ kx


def forward_kinematics(skel: Skeleton, pose: Pose):
    """Posed bone matrices in armature space.

    world[b] = world[parent] rest_rel[b] T(location_b) R(rotation_b). The products along the
    chains are formed by pointer jumping: every step multiplies each bone's partial product
    by its current ancestor's and doubles the ancestor distance, so a D-level hierarchy needs
    ceil(log2 D) batched (B, 4, 4) matmuls instead of D sequential levels.

    Returns:
      (B, 4, 4) float32.
    """
    b = skel.num_bones
    basis = jnp.zeros((b, 4, 4), jnp.float32)
    basis = basis.at[:, :3, :3].set(pose.rotations).at[:, :3, 3].set(pose.locations)
    basis = basis.at[:, 3, 3].set(1.0)
    world = skel.rest_rel @ basis
    eye = jnp.eye(4, dtype=world.dtype)[None]
    for anc in _jump_tables(skel.parents):  # static ancestor tables; -1 -> padded identity
        world = jnp.concatenate([world, eye])[anc] @ world
    return world


def _jump_tables(parents: tuple[int, ...]) -> list[np.ndarray]:
    """Ancestor index tables of the pointer-jumping steps (-1 mapped to the padding slot)."""
    anc = np.asarray(parents, np.int64)
    pad = len(anc)
    tables = []
    while (anc >= 0).any():
        tables.append(np.where(anc >= 0, anc, pad))
        anc = np.where(anc >= 0, anc[np.maximum(anc, 0)], -1)
    return tables


def skinning_matrices(skel: Skeleton, world):
    """(B, 3, 4) maps from rest to posed armature space: (world @ rest_inv)[:3]."""
    return (world @ skel.rest_inv)[:, :3, :]


# --------------------------------------------------------------------------------------------
# Linear blend skinning (JAX)
# --------------------------------------------------------------------------------------------


def skin(vertices, weights: SkinWeights, mats):
    """Linear blend skinning of rest `vertices` (V, 3) with skinning matrices (B, 3, 4).

    v' = sum_k w_k (R_{b_k} v + t_{b_k}), accumulated over the K padded influences (one gather
    of (V, 3, 4) per k), never forming a dense V x B weight matrix.

    Returns:
      (V, 3) posed vertices, meters.
    """
    vh = jnp.concatenate([vertices, jnp.ones_like(vertices[:, :1])], -1)  # (V, 4)
    out = jnp.zeros_like(vertices)
    for k in range(weights.bone_ids.shape[1]):  # K is small and static
        m = mats[weights.bone_ids[:, k]]  # (V, 3, 4)
        out = out + weights.weights[:, k, None] * jnp.einsum("vij,vj->vi", m, vh)
    return out


def skin_frames(vertices, weights: SkinWeights, mats):
    """`skin` over frames: rest vertices (V, 3), mats (T, B, 3, 4) -> (T, V, 3) meters."""
    return jax.vmap(skin, in_axes=(None, None, 0))(vertices, weights, mats)
