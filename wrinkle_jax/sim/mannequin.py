"""A procedural capsule mannequin and its motions, as kinematic tracks for the cloth solver.

Contract (NumPy, computed once per scene):
  * The body is 14 capsules (`CAPSULES`): pelvis, abdomen, chest, shoulders, neck, head (a
    zero-length capsule), thighs, shins, upper arms and forearms. It stands at the origin,
    z up, facing +y, hips at z = 0.93 m, ~1.73 m tall.
  * `body_tracks(motion, times, seed)` returns capsule ends (T, 14, 2, 3) m, radii (14,) m and
    the rigid frames (T, 3, 4) of the pelvis and the chest (attachments follow them).
  * Motions are smooth procedural joint-angle curves (`MOTIONS`), seeded for variety:
      dance  - samba-like: hip sway and roll, torso twist, alternating steps, slow turns
               (training: `skirt_dance`)
      dance2 - modern: continuous spins, high kicks, side leg raises, small jumps
               (training: `pleated_skirt_dance2`)
      walk   - a straight walk at ~1.1 m/s with arm swing (UNSEEN: test scenes only)
      rest   - the rest (A-) pose
    For t < 0 (the pre-roll) every motion holds the rest pose; it fades in over 0.6 s.
"""

from __future__ import annotations

import math

import numpy as np

CAPSULES = ("pelvis", "abdomen", "chest", "shoulders", "neck", "head",
            "thigh_r", "shin_r", "thigh_l", "shin_l",
            "upper_arm_r", "forearm_r", "upper_arm_l", "forearm_l")
RADII = np.array([0.105, 0.12, 0.14, 0.06, 0.05, 0.10,
                  0.075, 0.05, 0.075, 0.05,
                  0.045, 0.04, 0.045, 0.04], np.float32)
HIP_HEIGHT = 0.93
MOTIONS = ("rest", "dance", "dance2", "walk")
TRAINING_MOTIONS = ("dance", "dance2")
TEST_MOTIONS = ("walk",)


def _rx(a):
    c, s, o, z = np.cos(a), np.sin(a), np.ones_like(a), np.zeros_like(a)
    return np.stack([np.stack([o, z, z], -1), np.stack([z, c, -s], -1),
                     np.stack([z, s, c], -1)], -2)


def _ry(a):
    c, s, o, z = np.cos(a), np.sin(a), np.ones_like(a), np.zeros_like(a)
    return np.stack([np.stack([c, z, s], -1), np.stack([z, o, z], -1),
                     np.stack([-s, z, c], -1)], -2)


def _rz(a):
    c, s, o, z = np.cos(a), np.sin(a), np.ones_like(a), np.zeros_like(a)
    return np.stack([np.stack([c, -s, z], -1), np.stack([s, c, z], -1),
                     np.stack([z, z, o], -1)], -2)


def _mv(r, v):
    """(T, 3, 3) @ (3,) or (T, 3) -> (T, 3)."""
    return np.einsum("tij,tj->ti", r, np.broadcast_to(v, r.shape[:1] + (3,)))


def _smoothstep(x):
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3 - 2 * x)


def _angles(motion: str, t: np.ndarray, seed: int) -> dict:
    """Joint angles (radians) and root motion (meters) per time (T,)."""
    rng = np.random.default_rng(seed)
    z = np.zeros_like(t)
    a = {k: z.copy() for k in ("x", "y", "z", "yaw", "roll", "pitch", "twist", "bend",
                               "hip_r", "hip_l", "abd_r", "abd_l", "knee_r", "knee_l",
                               "sh_r", "sh_l", "sha_r", "sha_l", "elbow_r", "elbow_l")}
    if motion == "rest":
        return a
    w = _smoothstep(t / 0.6)
    tp = np.maximum(t, 0.0)
    jit = lambda lo=0.85, hi=1.15: rng.uniform(lo, hi)  # noqa: E731
    ph = lambda: rng.uniform(0, 2 * np.pi)  # noqa: E731
    d = np.radians
    if motion == "dance":
        f = 0.9 * jit()
        s = 2 * np.pi * f * tp
        step = np.sin(s + ph())
        a["x"] = 0.05 * jit() * np.sin(s)
        a["y"] = 0.08 * jit() * np.sin(0.5 * s + ph())
        a["z"] = -0.02 * np.abs(np.sin(s))
        a["roll"] = d(8) * jit() * np.sin(s + np.pi / 2)
        a["twist"] = d(20) * jit() * np.sin(0.5 * s + ph())
        a["yaw"] = d(60) * jit() * np.sin(2 * np.pi * 0.12 * tp + ph())
        a["hip_r"] = d(28) * jit() * np.maximum(step, 0) - d(8) * np.maximum(-step, 0)
        a["hip_l"] = d(28) * jit() * np.maximum(-step, 0) - d(8) * np.maximum(step, 0)
        a["knee_r"] = d(45) * jit() * np.maximum(step, 0)
        a["knee_l"] = d(45) * jit() * np.maximum(-step, 0)
        a["sh_r"] = d(35) * jit() * np.sin(s + ph())
        a["sh_l"] = d(35) * jit() * np.sin(s + ph())
        a["sha_r"] = d(20) * (1 + np.sin(0.5 * s + ph()))
        a["sha_l"] = d(20) * (1 + np.sin(0.5 * s + ph()))
        a["elbow_r"] = d(40) + d(25) * np.sin(s + ph())
        a["elbow_l"] = d(40) + d(25) * np.sin(s + ph())
    elif motion == "dance2":
        f = 0.6 * jit()
        s = 2 * np.pi * f * tp
        kick = np.sin(s + ph())
        a["yaw"] = 2 * np.pi * 0.22 * jit() * tp + d(30) * np.sin(0.5 * s)
        a["z"] = 0.06 * jit() * np.maximum(np.sin(2 * s), 0) ** 3
        a["bend"] = d(5) * jit() * np.sin(s + ph())
        a["twist"] = d(25) * jit() * np.sin(0.5 * s + ph())
        a["roll"] = d(6) * np.sin(s)
        a["hip_r"] = d(55) * jit() * np.maximum(kick, 0) ** 2
        a["hip_l"] = d(55) * jit() * np.maximum(-kick, 0) ** 2
        a["abd_r"] = d(25) * jit() * np.maximum(np.sin(0.5 * s + ph()), 0)
        a["abd_l"] = d(25) * jit() * np.maximum(np.sin(0.5 * s + ph()), 0)
        a["knee_r"] = d(30) * np.maximum(kick, 0)
        a["knee_l"] = d(30) * np.maximum(-kick, 0)
        a["sh_r"] = d(40) * np.sin(s + ph())
        a["sh_l"] = d(40) * np.sin(s + ph())
        a["sha_r"] = d(50) * jit() * (1 + np.sin(s + ph())) / 2
        a["sha_l"] = d(50) * jit() * (1 + np.sin(s + ph())) / 2
        a["elbow_r"] = d(20) * (1 + np.sin(s))
        a["elbow_l"] = d(20) * (1 + np.sin(s + np.pi))
    elif motion == "walk":
        f = 0.9 * jit(0.95, 1.05)
        s = 2 * np.pi * f * tp
        speed = 1.1 * jit(0.9, 1.1)
        a["y"] = speed * (tp - 0.3 * (1 - np.exp(-tp / 0.3)))  # eases in from rest
        a["z"] = -0.015 * (1 - np.cos(2 * s)) / 2
        a["yaw"] = d(6) * np.sin(s)
        a["roll"] = d(3) * np.sin(s)
        a["twist"] = -d(8) * np.sin(s)
        a["hip_r"] = d(25) * np.sin(s)
        a["hip_l"] = -d(25) * np.sin(s)
        a["knee_r"] = d(50) * np.maximum(np.sin(s - 1.2), 0) ** 1.5
        a["knee_l"] = d(50) * np.maximum(-np.sin(s - 1.2), 0) ** 1.5
        a["sh_r"] = -d(22) * np.sin(s)
        a["sh_l"] = d(22) * np.sin(s)
        a["elbow_r"] = d(20) + d(10) * np.sin(s)
        a["elbow_l"] = d(20) - d(10) * np.sin(s)
    else:
        raise ValueError(f"unknown motion {motion!r}; expected one of {', '.join(MOTIONS)}")
    for k in a:
        a[k] = a[k] * w
    return a


def body_tracks(motion: str, times, seed: int = 0):
    """Capsule tracks and attachment frames of the mannequin.

    Args:
      motion: one of `MOTIONS`.
      times: (T,) seconds (negative = pre-roll, rest pose).
      seed: varies amplitudes, frequencies and phases.
    Returns:
      (ends (T, 14, 2, 3) float32 m, radii (14,) float32 m,
       frames {"pelvis": (T, 3, 4), "chest": (T, 3, 4)} float64 rotation | translation).
    """
    t = np.asarray(times, np.float64)
    a = _angles(motion, t, seed)
    n = len(t)
    r_pel = _rz(a["yaw"]) @ _ry(a["roll"]) @ _rx(a["pitch"])
    o_pel = np.stack([a["x"], a["y"], HIP_HEIGHT + a["z"]], -1)
    r_ch = r_pel @ _rz(a["twist"]) @ _rx(a["bend"])
    o_ch = o_pel + _mv(r_pel, np.array([0.0, 0.0, 0.02]))

    def pel(v):
        return o_pel + _mv(r_pel, np.asarray(v, np.float64))

    def ch(v):
        return o_ch + _mv(r_ch, np.asarray(v, np.float64))

    ends = np.zeros((n, len(CAPSULES), 2, 3))
    ends[:, 0] = np.stack([pel([-0.085, 0, 0]), pel([0.085, 0, 0])], 1)
    ends[:, 1] = np.stack([pel([0, 0, 0.02]), ch([0, 0, 0.17])], 1)
    ends[:, 2] = np.stack([ch([0, 0, 0.17]), ch([0, 0, 0.35])], 1)
    ends[:, 3] = np.stack([ch([-0.17, 0, 0.47]), ch([0.17, 0, 0.47])], 1)
    ends[:, 4] = np.stack([ch([0, 0, 0.47]), ch([0, 0, 0.57])], 1)
    ends[:, 5] = np.stack([ch([0, 0, 0.68]), ch([0, 0, 0.68])], 1)
    down = np.array([0.0, 0.0, -1.0])
    for k, (side, sx) in enumerate((("r", 1.0), ("l", -1.0))):
        hip = pel([sx * 0.09, 0, -0.03])
        r_th = r_pel @ _rx(a[f"hip_{side}"]) @ _ry(-sx * a[f"abd_{side}"])
        knee = hip + 0.42 * _mv(r_th, down)
        ankle = knee + 0.40 * _mv(r_th @ _rx(-a[f"knee_{side}"]), down)
        ends[:, 6 + 2 * k] = np.stack([hip, knee], 1)
        ends[:, 7 + 2 * k] = np.stack([knee, ankle], 1)
        sh = ch([sx * 0.19, 0, 0.45])
        r_arm = r_ch @ _rx(a[f"sh_{side}"]) @ _ry(-sx * (math.radians(25) + a[f"sha_{side}"]))
        elbow = sh + 0.28 * _mv(r_arm, down)
        wrist = elbow + 0.26 * _mv(r_arm @ _rx(a[f"elbow_{side}"]), down)
        ends[:, 10 + 2 * k] = np.stack([sh, elbow], 1)
        ends[:, 11 + 2 * k] = np.stack([elbow, wrist], 1)
    frames = {"pelvis": np.concatenate([r_pel, o_pel[..., None]], -1),
              "chest": np.concatenate([r_ch, o_ch[..., None]], -1)}
    return ends.astype(np.float32), RADII.copy(), frames
