"""Character animation: MPFB walk cycles (keyframe curves, retargeting, analytic limb IK) and
procedural poses from a few joint angles.

Contract (shapes; B bones, C curves, T frames):
  * `load_walk_cycle(path, skel, author) -> Animation` (NumPy, once): the F-curves packed by
    `make_curves`, the per-bone change of rest frame and the per-cycle offsets.
  * `evaluate_curves(curves, t) -> (C,)`; `animation_pose(anim, skel, t) -> Pose` (the keyed
    channels); `evaluate_walk(anim, skel, t) -> (Pose, (B, 4, 4))` with the IK solved
    (`solve_limb_ik`); `walk_skinning_matrices(anim, skel, times) -> (T, B, 3, 4)`. All
    jittable; vmap over t.
  * `pose_from_angles(skel, {bone: (axis, angle)}) -> Pose` and `gait_pose(skel, phase)`:
    jittable and differentiable in the angles.
  * Bad input raises `CharacterError` naming the file and the problem.

Asset format (MPFB2): walkcycles/*.json: {"metadata": {"rig", "leg_length", "arm_length"},
"animation_data": {bone: {frame: {"location" | "rotation_euler" | "rotation_quaternion" |
"scale": {"values": [...], "metadata": [per component {"interpolation": "BEZIER" | "LINEAR" |
"CONSTANT", "handle_left": [frame, value], "handle_right": [frame, value],
"handle_left_type", "handle_right_type"}]}}}}. Values are Blender pose-bone channels: location
in the bone's rest frame, Euler angles in XYZ order (R = Rz Ry Rx), quaternions (w, x, y, z).
The walk cycle animates MPFB's IK helper bones (`{left,right}_{foot,knee,hand,elbow}_ik`, added
by `rig.load_skeleton` with MPFB's default helper set-up) rather than the limbs;
`evaluate_walk` solves that IK analytically (see `solve_limb_ik`).

Retargeting (`load_walk_cycle`). Our joints sit on the raw base mesh, not on the human the
cycle was keyed on, so channels are moved from the rig's default-position frames into ours
(same armature-space motion), translations are scaled by leg / arm length (metadata), and the
single keyed cycle repeats with the root's horizontal travel carried forward.
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from wrinkle_jax.character.assets import CharacterError, read_json
from wrinkle_jax.character.rig import (
    IK_LIMBS,
    Pose,
    Skeleton,
    axis_angle_to_matrix,
    euler_xyz_to_matrix,
    forward_kinematics,
    quaternion_to_matrix,
    rest_pose,
    skinning_matrices,
)
from wrinkle_jax.numerics import normalize, safe_div, safe_norm

# --------------------------------------------------------------------------------------------
# Procedural poses
# --------------------------------------------------------------------------------------------


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
# Keyframe curves (F-curves)
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


# --------------------------------------------------------------------------------------------
# Walk cycles: loading, retargeting, IK and evaluation
# --------------------------------------------------------------------------------------------


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
    data = read_json(path)
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
