"""Benchmark the UV normal-map layer; prints JSON.

Garment: a ~40k-vertex, 1 m x 1 m jittered sheet with wrinkles (about 1 m^2 of cloth), baked
at 2 mm texels (a ~520 x 520 map). Reports the raster-plan build time, bake time per frame
(single jitted call and a vmapped batch of 16), forward+backward bake time, and the
tile + extract + merge time of 128-pixel patches at stride 64.

    python benchmarks/bench_normalmap.py [--quick]
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

from wrinkle_jax import normalmap, patches, primitives


def _median_time(fn, reps: int) -> float:
    times = []
    for _ in range(reps):
        t0 = time.perf_counter()
        jax.block_until_ready(fn())
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def bench_texel_size(g, texel_size: float, frames, reps: int) -> dict:
    """Plan build, bake (single, vmap, lax.map batches), forward+backward at one texel size."""
    t0 = time.perf_counter()
    plan = normalmap.make_plan(g, texel_size=texel_size)
    plan_first = time.perf_counter() - t0
    plan_s = _median_time(lambda: normalmap.make_plan(g, texel_size=texel_size), 3)

    v = frames[0]
    n_frames = frames.shape[0]
    bake = normalmap.bake  # jitted where it is defined
    t0 = time.perf_counter()
    jax.block_until_ready(bake(plan, v))
    compile_s = time.perf_counter() - t0
    single = _median_time(lambda: bake(plan, v), reps)

    batched = {}
    bake_frames = normalmap.bake_frames  # jitted, batch_size static
    for bs in (None, 1, 2, 4):
        bake_frames(plan, frames, batch_size=bs).block_until_ready()
        t = _median_time(lambda bs=bs: bake_frames(plan, frames, batch_size=bs), reps)
        batched["vmap_all" if bs is None else f"lax_map_batch{bs}"] = round(1e3 * t / n_frames, 3)

    # Pass the plan as an argument (closing over it would embed it as an XLA constant).
    w = jax.random.normal(jax.random.PRNGKey(1), (*plan.shape, 3))
    grad = jax.jit(jax.grad(lambda x, p: jnp.sum(w * normalmap.bake(p, x))))
    grad(v, plan).block_until_ready()
    grad_s = _median_time(lambda: grad(v, plan), reps)
    return plan, {
        "texel_size_m": texel_size,
        "map_shape": list(plan.shape),
        "covered_texels": plan.num_covered,
        "planned_texels_incl_gutter": int(len(plan.texel_tri)),
        "plan_build_s": {"first": round(plan_first, 4), "median": round(plan_s, 4)},
        "bake_compile_s": round(compile_s, 3),
        "bake_ms_per_frame": {"single": round(1e3 * single, 3),
                              f"batch{n_frames}": batched},
        "bake_fwd_bwd_ms_per_frame": round(1e3 * grad_s, 3),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="fewer repetitions")
    ap.add_argument("--cells", type=int, default=200, help="grid cells per side (200 -> 40k)")
    args = ap.parse_args()
    reps = 3 if args.quick else 10

    g = primitives.grid_sheet(
        args.cells, args.cells, size=(1.0, 1.0), jitter=0.3,
        height_fn=lambda x, y: 0.01 * np.sin(25 * x + 3 * y) * np.cos(18 * y),
    )
    v = jnp.asarray(g.vertices)
    frames = v + 0.002 * jax.random.normal(jax.random.PRNGKey(0), (16, g.num_vertices, 3))
    plan, at_2mm = bench_texel_size(g, 0.002, frames, reps)
    _, at_1mm = bench_texel_size(g, 0.001, frames, reps)

    # Patches at 2 mm: tile (NumPy, once per layout), extract + merge (jitted).
    n_map = normalmap.bake(plan, v)
    t0 = time.perf_counter()
    origins = patches.tile(plan.mask, size=128, stride=64)
    tile_s = time.perf_counter() - t0
    origins_j = jnp.asarray(origins)
    extract = jax.jit(patches.extract, static_argnames="size")
    merge = jax.jit(patches.merge, static_argnames=("shape", "window"))

    def round_trip(window):
        p = extract(n_map, origins_j, size=128)
        return merge(p, origins_j, shape=n_map.shape, window=window)

    round_trip("uniform")
    round_trip("hann")
    em_uniform = _median_time(lambda: round_trip("uniform"), reps)
    em_hann = _median_time(lambda: round_trip("hann"), reps)

    print(json.dumps({
        "benchmark": "normalmap",
        "machine": {"cpu_count": os.cpu_count(), "platform": platform.platform(),
                    "jax": jax.__version__, "backend": jax.default_backend()},
        "garment": {"vertices": g.num_vertices, "faces": g.num_faces, "area_m2": 1.0},
        "texel_2mm": at_2mm,
        "texel_1mm": at_1mm,
        "patches_2mm": {"count": int(len(origins)), "size": 128, "stride": 64,
                        "tile_ms": round(1e3 * tile_s, 3),
                        "extract_merge_ms": {"uniform": round(1e3 * em_uniform, 3),
                                             "hann": round(1e3 * em_hann, 3)}},
    }, indent=2))


if __name__ == "__main__":
    main()
