"""Benchmark the U-Net's masked blurs in the network stage; prints one JSON object.

The network stage (`stages.network_stage`, jitted as the streaming pipeline runs it) of the
shipped model on one frame of the bundled demo skirt, with `sharpen.masked_blur` as it is now
(moments shared, planes laid out so that both separable passes are plain matmuls) against the
original formula, `sharpen.masked_blur_reference` (every moment its own separable filter
on NHWC). The shipped model has an order-1 unsharp base (sigma 16) and an order-1 high-passed
residual (sigma 8): two blurs per patch. Also timed: the stage as the pipeline runs it, with
the blurs' mask-only weights computed once per garment (`stages.batch_blur_weights`; the
patches' masks are the same every frame), the network without any blur (a lower bound), and
each blur on its own, with and without precomputed weights.

Timing (`wrinkle_jax.timing.alternate`): every variant compiled first, run once, then the
repetitions alternate between the variants (A B C A B C ...) so that the load on this shared
machine hits all alike; medians of process CPU time (all threads; the steadier number under
load) and of wall time. The 1-minute load average is recorded before and after. Ratios are
new / reference (lower is faster), the median of the per-round ratios.

Usage: python benchmarks/bench_blur.py [--reps R] [--batch B (default: the pipeline's)]
"""

from __future__ import annotations

import argparse
import json
import os

import jax
import jax.numpy as jnp
import numpy as np

from wrinkle_jax import enhancer, meshio, normalmap, patches, pipeline, sharpen, stages, timing
from wrinkle_jax.cli import _demo_sequence_path


def _no_blur(n, mask, sigma, order=1, weights=None):
    return jnp.zeros_like(n)


def _reference(n, mask, sigma, order=1, weights=None):
    """`sharpen.masked_blur_reference` in `masked_blur`'s signature (no weights to use)."""
    return sharpen.masked_blur_reference(n, mask, sigma, order)


def demo_tiles(enh):
    """One demo frame's network input patches (P, S, S, 3), as the pipeline cuts them, with
    the padded garment mask (Hp, Wp, 1) and the patch origins (P, 2) they were cut at."""
    seq = meshio.load_sequence(_demo_sequence_path())
    size = enh.config.patch_size
    plan = normalmap.make_plan(seq.garment, texel_size=enh.config.texel_size)
    padded, _ = patches.pad_to_patch(np.asarray(plan.mask), size)
    origins = patches.tile(padded, size=size, stride=size // 2)
    _, rgb = stages.bake_stage(plan, jnp.asarray(seq.frames[0]), jnp.asarray(padded),
                               padded_shape=tuple(padded.shape[:2]))
    return stages.tile_stage(rgb, jnp.asarray(origins), size=size), padded, origins


def compiled_stage(enh, blur, tiles, batch: int, weights=None):
    """The jitted network stage compiled with `blur` as `sharpen.masked_blur` (and the
    precomputed blur `weights`, if any)."""
    saved = sharpen.masked_blur
    sharpen.masked_blur = blur
    # Jitted callers (`sharpen.unsharp_rgb`) keep the trace of the blur they first saw:
    # without clearing, every variant after the first ran the first variant's unsharp blur.
    jax.clear_caches()
    try:
        apply = enhancer.make_apply(enh)
        fn = jax.jit(stages.network_stage, static_argnames=("apply", "batch_size"))
        return fn.lower(apply, enh.params, tiles, jnp.int32(0), batch_size=batch,
                        blur_weights=weights).compile()
    finally:
        sharpen.masked_blur = saved


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--reps", type=int, default=5, help="alternating rounds")
    ap.add_argument("--batch", type=int, default=pipeline.PipelineConfig().batch_size,
                    help="patches per U-Net call (default: the pipeline's)")
    args = ap.parse_args()
    load_before = os.getloadavg()[0]
    enh = enhancer.load_enhancer()
    cfg = enh.config.unet  # the U-Net settings (UNetConfig)
    tiles, padded_mask, origins = demo_tiles(enh)
    p = int(tiles.shape[0])
    variants = {"shared": sharpen.masked_blur, "reference": _reference,
                "no_blur": _no_blur}
    weights = stages.batch_blur_weights(cfg, padded_mask, origins, size=int(tiles.shape[1]),
                                        batch_size=args.batch)
    stage = {k: compiled_stage(enh, f, tiles, args.batch) for k, f in variants.items()}
    stage["precomputed"] = compiled_stage(enh, sharpen.masked_blur, tiles, args.batch, weights)
    params, mat = enh.params, jnp.int32(0)
    weights_of = {k: weights if k == "precomputed" else None for k in stage}
    out = {k: s(params, tiles, mat, blur_weights=weights_of[k]) for k, s in stage.items()}
    err = float(jnp.abs(out["shared"] - out["reference"]).max())
    err_pre = float(jnp.abs(out["precomputed"] - out["shared"]).max())
    tt = timing.alternate({k: (lambda k=k, s=s: s(params, tiles, mat, blur_weights=weights_of[k]))
                           for k, s in stage.items()}, args.reps)
    t = {k: (tt.cpu[k], tt.wall[k]) for k in stage}

    # Each blur on its own, on one batch of the frame's patches (values in [-1, 1]).
    x = tiles[: args.batch] * 2.0 - 1.0
    mask = sharpen.mask_from_rgb(tiles[: args.batch])
    blur_runs = {}
    for sigma in sorted({cfg.unsharp_sigma, cfg.residual_highpass} - {0.0}):
        for name, f in (("shared", sharpen.masked_blur),
                        ("reference", sharpen.masked_blur_reference)):
            jf = jax.jit(lambda v, m, f=f, s=sigma: f(v, m, s, cfg.blur_order))
            blur_runs[f"{name}_sigma{sigma:g}"] = lambda jf=jf: jf(x, mask)
        w = sharpen.blur_weights(mask, sigma, cfg.blur_order)
        jw = jax.jit(lambda v, m, w, s=sigma: sharpen.masked_blur(v, m, s, cfg.blur_order, w))
        blur_runs[f"precomputed_sigma{sigma:g}"] = lambda jw=jw, w=w: jw(x, mask, w)
    tb = timing.alternate(blur_runs, args.reps)

    def ms(sec, count):
        return round(1e3 * sec / count, 3)

    report = {
        "benchmark": "blur",
        "model": {"width": cfg.width, "unsharp_sigma": cfg.unsharp_sigma,
                  "residual_highpass": cfg.residual_highpass, "blur_order": cfg.blur_order},
        "frame": {"garment": "demo_skirt", "patches": p, "batch_size": args.batch},
        "network_stage_ms_per_frame": {k: {"cpu": ms(c, 1), "wall": ms(w, 1)}
                                       for k, (c, w) in t.items()},
        "network_stage_ratio_shared_over_reference": {
            c: round(tt.ratio("shared", "reference", c), 3) for c in ("cpu", "wall")},
        "network_stage_ratio_precomputed_over_shared": {
            c: round(tt.ratio("precomputed", "shared", c), 3) for c in ("cpu", "wall")},
        "blur_share_of_stage_cpu": {
            k: round(1 - t["no_blur"][0] / t[k][0], 3)
            for k in ("shared", "reference", "precomputed")},
        "max_abs_output_difference": err,
        "max_abs_output_difference_precomputed_vs_shared": err_pre,
        "blur_alone_ms_per_patch": {k: {"cpu": ms(tb.cpu[k], args.batch),
                                        "wall": ms(tb.wall[k], args.batch)} for k in tb.wall},
        "reps": args.reps,
        "load_avg_1m": {"before": round(load_before, 2), "after": round(os.getloadavg()[0], 2)},
        "cpus": os.cpu_count(),
    }
    print(json.dumps(report, indent=2))


if __name__ == "__main__":
    main()
