"""Regenerate the bundled demo sequence `wrinkle_jax/assets/demo_skirt.npz`.

A two-panel flared skirt (welded side seams, split UVs) whose hem swings and forms travelling
folds: a stand-in coarse animation until the simulator produces real ones. Deterministic.

    python -m experiments.make_demo_garment
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from wrinkle_jax import primitives
from wrinkle_jax.meshio import make_sequence, save_sequence

OUT = Path(__file__).resolve().parents[1] / "wrinkle_jax" / "assets" / "demo_skirt.npz"


def skirt_frames(garment, num_frames: int = 12, fps: float = 30.0) -> np.ndarray:
    """(T, V, 3) frames: radial folds that grow towards the hem and drift around the body,
    plus a sideways swing of the hem."""
    v = np.asarray(garment.vertices, np.float64)
    r = np.hypot(v[:, 0], v[:, 1])
    theta = np.arctan2(v[:, 1], v[:, 0])
    depth = -v[:, 2] / -v[:, 2].min()  # 0 at the waist, 1 at the hem
    frames = []
    for t in range(num_frames):
        phase = 2 * np.pi * t / num_frames
        waves = np.sin(7 * theta + phase) + 0.4 * np.sin(13 * theta - 2 * phase)
        folds = 0.025 * depth**1.5 * waves
        rr = r + folds
        swing = 0.06 * depth**2 * np.sin(phase)
        frames.append(np.stack([rr * np.cos(theta) + swing, rr * np.sin(theta), v[:, 2]], -1))
    return np.asarray(frames, np.float32)


def main() -> None:
    g = primitives.flared_skirt(n_theta=64, n_s=20)
    frames = skirt_frames(g)
    seq = make_sequence(frames, g.replace(vertices=frames[0]), fps=30.0,
                        metadata={"name": "demo_skirt", "material": "silk_charmeuse",
                                  "source": "experiments/make_demo_garment.py", "pd": 0.03})
    save_sequence(OUT, seq)
    print(f"wrote {OUT} ({OUT.stat().st_size / 1024:.0f} KiB, {len(seq)} frames, "
          f"{g.num_vertices} vertices)")


if __name__ == "__main__":
    main()
