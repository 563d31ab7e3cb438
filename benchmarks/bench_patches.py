"""Benchmark wrinkle_jax.patches: tiling (NumPy), jitted extract + merge, random crops.

A 1024x1024 normal map whose mask is four elliptical UV panels covering about half the texels,
patches of 128 texels. Prints one JSON object: median wall times in milliseconds (after a
warm-up call that compiles), patch counts, and the round-trip error of each merge window. A
stride sweep shows how the patch count (the enhancer's cost) and the merge time grow with
overlap.

Run: python benchmarks/bench_patches.py [--reps N]
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import time

import jax
import jax.numpy as jnp
import numpy as np

from wrinkle_jax import patches as pt

SIZE = 128
MAP = 1024


def panel_mask(size: int = MAP) -> np.ndarray:
    """(size, size, 1) float32: four disjoint elliptical panels, ~50% of the texels."""
    rows, cols = np.mgrid[0:size, 0:size].astype(np.float64)
    inside = np.zeros((size, size), bool)
    quarter = size / 4
    for r0, c0, ar, ac in [(1, 1, 0.84, 0.78), (1, 3, 0.78, 0.84),
                           (3, 1, 0.80, 0.82), (3, 3, 0.82, 0.80)]:
        inside |= (((rows - r0 * quarter) / (ar * quarter)) ** 2
                   + ((cols - c0 * quarter) / (ac * quarter)) ** 2) <= 1.0
    return inside[..., None].astype(np.float32)


def unit_normals(shape, seed: int = 0) -> np.ndarray:
    n = np.random.default_rng(seed).normal(size=(*shape, 3))
    n[..., 2] = np.abs(n[..., 2]) + 1.0
    return (n / np.linalg.norm(n, axis=-1, keepdims=True)).astype(np.float32)


def median_ms(fn, reps: int, warmup: int = 1) -> float:
    for _ in range(warmup):
        jax.block_until_ready(fn())
    times = []
    for _ in range(reps):
        start = time.perf_counter()
        jax.block_until_ready(fn())
        times.append((time.perf_counter() - start) * 1e3)
    return round(statistics.median(times), 3)


def compile_ms(fn) -> float:
    start = time.perf_counter()
    jax.block_until_ready(fn())
    return round((time.perf_counter() - start) * 1e3, 1)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--reps", type=int, default=10)
    args = parser.parse_args()

    mask = panel_mask()
    normals = jnp.asarray(unit_normals(mask.shape[:2]) * mask)
    mask_j = jnp.asarray(mask)
    result = {
        "benchmark": "patches",
        "jax": jax.__version__,
        "device": str(jax.devices()[0]),
        "machine": platform.machine(),
        "map": [MAP, MAP],
        "mask_fraction": round(float(mask.mean()), 4),
        "patch_size": SIZE,
        "reps": args.reps,
    }

    stride = 64
    origins_np = pt.tile(mask, SIZE, stride)
    result["tile_ms"] = median_ms(lambda: pt.tile(mask, SIZE, stride), max(args.reps, 20), 0)
    full_grid = len(pt.grid_starts(MAP, SIZE, stride)) ** 2
    result["stride"] = stride
    result["patches"] = int(len(origins_np))
    result["grid_patches_before_skipping_empty"] = full_grid
    origins = jnp.asarray(origins_np)

    extract = jax.jit(pt.extract, static_argnames="size")
    result["extract_compile_ms"] = compile_ms(lambda: extract(normals, origins, size=SIZE))
    result["extract_ms"] = median_ms(lambda: extract(normals, origins, size=SIZE), args.reps)
    patches = extract(normals, origins, size=SIZE)
    covered = np.asarray(pt.merge(patches, origins, (MAP, MAP))[1])[..., 0] > 0

    for window in pt.WINDOWS:
        merge = jax.jit(lambda p, o, w=window: pt.merge(p, o, (MAP, MAP), window=w, mask=mask_j))

        def round_trip(x, o, w=window):
            return pt.merge(pt.extract(x, o, SIZE), o, (MAP, MAP), window=w, mask=mask_j)

        both = jax.jit(round_trip)
        entry = {
            "compile_ms": compile_ms(lambda b=both: b(normals, origins)),
            "merge_ms": median_ms(lambda m=merge: m(patches, origins), args.reps),
            "extract_merge_ms": median_ms(lambda b=both: b(normals, origins), args.reps),
        }
        merged = np.asarray(both(normals, origins)[0])
        entry["round_trip_max_abs_error"] = float(
            np.abs(merged[covered] - np.asarray(normals)[covered]).max())
        result[f"merge_{window}"] = entry

    crops = jax.jit(pt.random_crops, static_argnames=("n", "size", "augment", "vector_mode"))
    key = jax.random.key(0)
    for mode in pt.VECTOR_MODES:
        def run(m=mode):
            return crops(key, normals, mask_j, n=64, size=SIZE, min_coverage=0.09, vector_mode=m)

        result[f"random_crops_64_{mode}"] = {
            "compile_ms": compile_ms(run),
            "ms": median_ms(run, args.reps),
        }
    valid = np.asarray(pt.crop_mask_counts(mask, SIZE)) >= 0.09 * SIZE * SIZE
    result["random_crops_valid_origins"] = int(valid.sum())
    result["random_crops_candidate_origins"] = int(valid.size)

    sweep = []
    for s in (128, 64, 32):
        o = jnp.asarray(pt.tile(mask, SIZE, s))
        run = jax.jit(lambda x, oo: pt.merge(pt.extract(x, oo, SIZE), oo, (MAP, MAP)))
        jax.block_until_ready(run(normals, o))
        sweep.append({"stride": s, "patches": int(o.shape[0]),
                      "extract_merge_uniform_ms": median_ms(lambda r=run, oo=o: r(normals, oo),
                                                            max(args.reps // 2, 3))})
    result["stride_sweep"] = sweep
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
