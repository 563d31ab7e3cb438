"""Benchmark the end-to-end pipeline on the bundled demo garment; prints one JSON object.

Reported:
  * per-frame time by stage (bake, tile, network, merge, lift) of `pipeline.enhance_sequence`
    on the demo skirt (`wrinkle_jax/assets/demo_skirt.npz`), plus setup and compile once;
  * patches/s of the jitted enhancer (`enhancer.make_apply`) against the batch size (1, 4, 8,
    16), each batch size compiled first, then timed over the same number of patches (median of
    `--reps` repetitions, wall time and process CPU time).

The model is the shipped one (`wrinkle_jax/assets/enhancer.npz`) when present, else a random
width-32 enhancer of the default configuration (128-texel patches, 2 mm texels); the JSON
says which. The machine is shared: the 1-minute load average is recorded.

Usage: python benchmarks/bench_pipeline.py [--frames N] [--no-lift] [--reps R] [--patches P]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import time

import jax
import jax.numpy as jnp
import numpy as np

from wrinkle_jax import enhancer, meshio, pipeline
from wrinkle_jax.cli import _demo_sequence_path
from wrinkle_jax.nn import unet

BATCH_SIZES = (1, 4, 8, 16)


def load_model() -> tuple[enhancer.Enhancer, str]:
    if enhancer.DEFAULT_PATH.is_file():
        return enhancer.load_enhancer(), f"shipped ({enhancer.DEFAULT_PATH.name})"
    model = enhancer.init_enhancer(jax.random.key(0, impl="rbg"),
                                   enhancer.EnhancerConfig(unet.UNetConfig(width=32)))
    return model, "random width-32 (no shipped model yet)"


def stage_times(model, frames: int, lift: bool, batch: int, chunk: int) -> dict:
    seq = meshio.load_sequence(_demo_sequence_path())
    sel = list(range(min(frames, len(seq))))
    res = pipeline.enhance_sequence(seq, "silk_charmeuse", enhancer=model, lift=lift,
                                    batch_size=batch, chunk_size=chunk, frames=sel, keep=False,
                                    writer=lambda frame: None)
    n = len(sel)
    per_frame = {k: 1e3 * res.timings[k] / n
                 for k in ("bake", "tile", "network", "merge", "lift")}
    return {
        "garment": "demo_skirt", "frames": n, "coarse_vertices": seq.garment.num_vertices,
        "detailed_vertices": None if res.fine_garment is None else
        res.fine_garment.num_vertices,
        "map_shape": list(res.mask.shape[:2]), "patches": res.patches,
        "batch_size": batch, "chunk_size": chunk,
        "ms_per_frame": per_frame, "ms_per_frame_total": sum(per_frame.values()),
        "setup_s": res.timings["setup"], "compile_s": res.timings["compile"],
        "wall_s": res.timings["total"],
    }


def throughput(model, patches: int, reps: int) -> dict:
    apply = enhancer.make_apply(model)
    size = model.config.patch_size
    rng = np.random.default_rng(0)
    out = {}
    for b in BATCH_SIZES:
        x = jnp.asarray(rng.uniform(0.3, 0.7, (b, size, size, 3)).astype(np.float32))
        m = jnp.zeros((b,), jnp.int32)
        t0 = time.perf_counter()
        apply.lower(model.params, x, m).compile()
        compile_s = time.perf_counter() - t0
        apply(model.params, x, m).block_until_ready()  # warm-up
        calls = max(1, patches // b)
        wall, cpu = [], []
        for _ in range(reps):
            t0, c0 = time.perf_counter(), time.process_time()
            for _ in range(calls):
                y = apply(model.params, x, m)
            y.block_until_ready()
            wall.append(time.perf_counter() - t0)
            cpu.append(time.process_time() - c0)
        out[str(b)] = {"patches_per_s": calls * b / statistics.median(wall),
                       "cpu_s_per_patch": statistics.median(cpu) / (calls * b),
                       "compile_s": compile_s}
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=12, help="demo frames to enhance")
    ap.add_argument("--no-lift", action="store_true", help="skip the lifting stage")
    ap.add_argument("--batch", type=int, default=8, help="pipeline patches per U-Net call")
    ap.add_argument("--chunk", type=int, default=4, help="pipeline frames per chunk")
    ap.add_argument("--patches", type=int, default=32, help="patches per timed repetition")
    ap.add_argument("--reps", type=int, default=3)
    args = ap.parse_args()
    model, which = load_model()
    report = {
        "benchmark": "pipeline",
        "model": which,
        "model_config": model.config.to_json(),
        "conv_impl": getattr(model.model, "conv_impl", None),
        "machine": {"cpus": os.cpu_count(), "platform": platform.platform(),
                    "jax": jax.__version__, "load_avg_1m_before": os.getloadavg()[0]},
    }
    report["stages"] = stage_times(model, args.frames, not args.no_lift, args.batch, args.chunk)
    report["enhancer_patches_per_s_by_batch"] = throughput(model, args.patches, args.reps)
    report["machine"]["load_avg_1m_after"] = os.getloadavg()[0]
    print(json.dumps(report, indent=2))


if __name__ == "__main__":
    main()
