"""Temporal coherence of an enhanced sequence: the frame-to-frame change (flicker) of the
enhanced normal maps, streamed through the pipeline without lifting, beside that of the coarse
input and of the fine simulation (per frame pair, the mean over a map's garment texels of the
angle in degrees between the unit normals at t and t+1; `flicker.mean_angular_change`).
"""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np

from wrinkle_jax import enhancer as enhancer_lib
from wrinkle_jax import normalmap, pipeline
from wrinkle_jax.evaluation import patchsets
from wrinkle_jax.evaluation.flicker import mean_angular_change
from wrinkle_jax.meshio import GarmentSequence

__all__ = ["SERIES", "sequence_flicker"]

SERIES = ("coarse", "output", "fine")


def sequence_flicker(coarse: GarmentSequence, fine: GarmentSequence | None,
                     enh: enhancer_lib.Enhancer, material: str, frames: list[int],
                     batch_size: int = 8, chunk_size: int = 4,
                     progress: Callable[[int], None] | None = None) -> dict:
    """Flicker series of the enhanced, coarse and fine maps over consecutive frames.

    Args:
      coarse: the coarse sequence (frames (T, V, 3) meters) the pipeline enhances.
      fine: the fine simulation of the same frames (None: no "fine" series).
      enh: the enhancer; material: one of its material names.
      frames: consecutive frame indices (t, t+1, ...), at least 2.
      batch_size, chunk_size: `pipeline.PipelineConfig` (results do not depend on them).
      progress: called with 1 after each frame.
    Returns:
      {"coarse", "output"[, "fine"]: (len(frames) - 1,) float64 degrees per frame pair,
       "patches_per_frame": int, "timings": pipeline stage seconds (compile separate),
       "texels": {"output": garment texels of the coarse map, "fine": of the fine map}}.
    """
    frames = [int(t) for t in frames]
    if len(frames) < 2 or np.any(np.diff(frames) != 1):
        raise ValueError(f"frames must be at least 2 consecutive indices, got {frames[:5]}...")
    config = pipeline.PipelineConfig(batch_size=batch_size, chunk_size=chunk_size, lift=False)
    pipe = pipeline.make_pipeline(coarse.garment, enh, config)
    mid = enh.config.material_id(material)
    fine_plan = (normalmap.make_plan(fine.garment, texel_size=enh.config.texel_size)
                 if fine is not None else None)
    timings = dict(pipe.timings)
    series = {k: [] for k in SERIES if k != "fine" or fine is not None}
    prev = None
    t_fine = 0.0
    for fr in pipeline.iter_enhance(pipe, coarse.frames, mid, frames, timings):
        cur = {"output": fr.normal_map, "coarse": patchsets.bake_map(pipe.plan, fr.coarse)}
        if fine_plan is not None:
            t0 = time.perf_counter()
            cur["fine"] = patchsets.bake_map(fine_plan, fine.frames[fr.index])
            t_fine += time.perf_counter() - t0
        if prev is not None:
            for k in series:
                mask = fine_plan.mask if k == "fine" else pipe.mask
                series[k].append(mean_angular_change(prev[k], cur[k], mask))
        prev = cur
        if progress is not None:
            progress(1)
    timings["fine_bake"] = t_fine
    return {**{k: np.asarray(v) for k, v in series.items()},
            "patches_per_frame": pipe.num_patches, "timings": timings,
            "texels": {"output": int(np.asarray(pipe.mask).sum()),
                       "fine": int(np.asarray(fine_plan.mask).sum()) if fine_plan else None}}
