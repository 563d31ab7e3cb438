"""Checkpoints of a running simulation, so that a long one survives being killed.

A fine data-set sequence takes hours on two shared cores, and a session's processes die
with it; `scenes.simulate(..., checkpoint=PATH)` writes the solver state and the frames done
so far here every few minutes and picks them up on the next call with the same settings.
The solver is deterministic and chunks start at the same frames, so a resumed run is
bit-identical to an uninterrupted one (tested). The key holds the settings and the package
version, not the code: like the finished files of a resumed data set, a checkpoint assumes the
solver did not change in between.

File (`.npz`, written atomically): `key` (JSON of everything the result depends on),
`done` (frames simulated, pre-roll included), `wall_s` (seconds spent so far), the state
(`x`, `v` (V, 3) float32 m, m/s; `self_overflow` (3,) or (4,) int64 totals if
self-collision is on: int32, and possibly wrapped round, in checkpoints written before
session 39) and `frames` (done, V, 3) float32 m.
"""

from __future__ import annotations

import os
import time
import warnings
from pathlib import Path

import numpy as np

from wrinkle_jax.fileio import NPZ_READ_ERRORS, atomic_open
from wrinkle_jax.sim.cloth_model import ClothState


def load(path: str | os.PathLike, key: str):
    """The checkpoint at `path` if it exists and was written with `key`, else None.

    Returns:
      (done frames, ClothState of NumPy arrays, frames (done, V, 3) float32, wall seconds).
      A checkpoint written with another key (other settings), or unreadable, is ignored with a
      warning (the run starts over and overwrites it).
    """
    path = Path(path)
    if not path.exists():
        return None
    try:
        with np.load(path, allow_pickle=False) as z:
            if str(z["key"]) != key:
                warnings.warn(f"{path}: a checkpoint of other settings; starting from frame 0",
                              stacklevel=2)
                return None
            over = z["self_overflow"] if "self_overflow" in z.files else None
            state = ClothState(x=z["x"], v=z["v"], self_overflow=over)
            return int(z["done"]), state, z["frames"], float(z["wall_s"])
    except NPZ_READ_ERRORS as e:
        # e.g. a disk that filled up: starting over beats failing on it at every rerun
        warnings.warn(f"{path}: unreadable checkpoint ({type(e).__name__}: {e}); starting "
                      f"from frame 0", stacklevel=2)
        return None


def save(path: str | os.PathLike, key: str, done: int, state: ClothState, frames: np.ndarray,
         wall_s: float) -> None:
    """Write a checkpoint atomically (`fileio.atomic_open`: a temporary file in the same
    folder, then a rename; the usual file mode, umask applied)."""
    arrays = {"key": np.array(key), "done": np.int64(done), "wall_s": np.float64(wall_s),
              "x": np.asarray(state.x), "v": np.asarray(state.v), "frames": frames}
    if state.self_overflow is not None:
        arrays["self_overflow"] = np.asarray(state.self_overflow)
    with atomic_open(path) as fh:
        np.savez(fh, **arrays)


class Writer:
    """`simulate_frames`'s `on_chunk` callback: writes a checkpoint (the frames before the
    resumed run, `prior`, then the run's chunks so far) when `every_s` seconds have passed
    since the last one (0: after every chunk)."""

    def __init__(self, path, key: str, every_s: float, prior: list, wall_s: float):
        self.path, self.key, self.every_s = path, key, float(every_s)
        self.prior = list(prior)
        self.wall0 = wall_s
        self.t0 = self.last = time.perf_counter()

    def __call__(self, done: int, state: ClothState, chunks: list) -> None:
        now = time.perf_counter()
        if now - self.last >= self.every_s:
            save(self.path, self.key, done, state, np.concatenate(self.prior + chunks),
                 self.wall0 + now - self.t0)
            self.last = now
