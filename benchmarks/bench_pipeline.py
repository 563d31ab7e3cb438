"""Benchmark the end-to-end pipeline on the bundled demo garment; prints one JSON object.

Reported:
  * the per-frame budget of the default pipeline (the CLI's settings: batch 16, chunk 4,
    stride 3/4 of a patch, lifting on) by stage -- bake, tile, network, merge, lift, write -- in
    ms/frame, on the demo skirt (`wrinkle_jax/assets/demo_skirt.npz`, what `make demo` runs),
    plus setup and compile once. "write" is what the CLI writes per frame (the 16-bit normal
    map PNG and the detailed OBJ, into a temporary folder; no previews);
  * the network's FLOPs per patch, counted from the parameter shapes (convolutions and
    transposed convolutions: multiply-adds x 2 of the useful taps; and the masked blurs of the
    unsharp base and the high-pass as the dense banded matmuls `sharpen.masked_blur` runs),
    and the achieved GFLOP/s of the network stage (wall and process-CPU time);
  * patches/s of the jitted enhancer (`enhancer.make_apply`) against the batch size, each batch
    size compiled first, then timed over the same number of patches, the batch sizes
    alternating (`wrinkle_jax.timing.alternate`; median of `--reps` rounds, wall time and
    process CPU time); skipped with --quick.

The model is the shipped one (`wrinkle_jax/assets/enhancer.npz`) when present, else a random
width-32 enhancer of the default configuration (128-texel patches, 2 mm texels); the JSON
says which. The machine is shared: the 1-minute load average is recorded before and after.

With --network-sweep (alone): the network stage on one chunk of demo frames for batch
sizes 4, 8, 16 x 1 or 4 frames per network call (`PipelineConfig.frames_per_batch`),
alternating in one run (`wrinkle_jax.timing.alternate`), ms/frame and ratios.

Usage: python benchmarks/bench_pipeline.py [--quick] [--frames N] [--no-lift] [--reps R]
       python benchmarks/bench_pipeline.py --network-sweep [--reps R] [--stride S]
       python benchmarks/bench_pipeline.py --lift-sweep [--frames N]
  --quick: 4 frames (one chunk), no batch-size sweep (< 2 min on a quiet 2-core machine).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import tempfile
import time
from collections.abc import Mapping
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from wrinkle_jax import enhancer, meshio, normalmap, pipeline, timing
from wrinkle_jax.cli import _demo_sequence_path
from wrinkle_jax.nn import fastconv, unet

BATCH_SIZES = (1, 4, 8, 16)
STAGES = ("bake", "tile", "network", "merge", "lift", "write")


def load_model() -> tuple[enhancer.Enhancer, str]:
    if enhancer.DEFAULT_PATH.is_file():
        return enhancer.load_enhancer(), f"shipped ({enhancer.DEFAULT_PATH.name})"
    model = enhancer.init_enhancer(jax.random.key(0, impl="rbg"),
                                   enhancer.EnhancerConfig(unet.UNetConfig(width=32)))
    return model, "random width-32 (no shipped model yet)"


def network_flops(model) -> dict:
    """FLOPs per patch of the enhancer's forward, from its parameter shapes.

    Convolutions: enc{k} (3x3 at size S / 2^(k-1)), dec{k} (4x4 stride-2 transposed: input
    S / 2^(5-k); or a 3x3 conv after 2x up-sampling), out (3x3 at S): multiply-adds x 2.
    Blurs: `sharpen.masked_blur`'s dense banded matmuls (order 1: 2 (C+1) + 1 row and
    4 (C+1) + 2 column passes of C = 3 values; order 0: C + 1 of each), 2 S^3 FLOPs a pass.
    """
    cfg, params = model.config, model.params
    s = cfg.patch_size
    conv = 0
    for name, layer in params.items():
        if not isinstance(layer, Mapping) or "kernel" not in layer:
            continue
        k = np.shape(layer["kernel"])
        if name.startswith("enc"):
            size = s >> (int(name[3:]) - 1)
            conv += fastconv.conv3x3_flops(size, size, k[2], k[3])
        elif name.startswith("dec"):
            size = (s >> 4) << (int(name[3:]) - 1)  # input size
            conv += (fastconv.conv_transpose4x4s2_flops(size, size, k[2], k[3]) if k[0] == 4
                     else fastconv.conv3x3_flops(2 * size, 2 * size, k[2], k[3]))
        elif name == "out":
            conv += fastconv.conv3x3_flops(s, s, k[2], k[3])
    net = cfg.unet
    passes = (2 * 4 + 1) + (4 * 4 + 2) if net.blur_order == 1 else 2 * 4
    blurs = (net.residual and net.residual_base == "unsharp") + (net.residual_highpass > 0)
    blur = blurs * passes * 2 * s**3
    return {"conv": conv, "blur": blur, "total": conv + blur}


def frame_writer(folder: Path, pipe_mask, fine):
    """What the CLI writes per frame (normal map PNG, detailed OBJ), previews excluded."""
    def write(frame: pipeline.EnhancedFrame) -> None:
        normalmap.save_normal_map_png(folder / f"normal_map_{frame.index:05d}.png",
                                      frame.normal_map, pipe_mask)
        if frame.detailed is not None:
            meshio.save_obj(folder / f"frame_{frame.index:05d}.obj", fine, frame.detailed)
    return write


def stage_times(model, frames: int, lift: bool, batch: int, chunk: int) -> dict:
    seq = meshio.load_sequence(_demo_sequence_path())
    sel = list(range(min(frames, len(seq))))
    config = pipeline.PipelineConfig(batch_size=batch, chunk_size=chunk, lift=lift,
                                     frames_per_batch=chunk, warm_start=True)  # as the CLI
    pipe = pipeline.make_pipeline(seq.garment, model, config)
    fine = None if pipe.fine_garment is None else jax.tree.map(np.asarray, pipe.fine_garment)
    cpu0 = time.process_time()
    with tempfile.TemporaryDirectory(prefix="bench-pipeline-") as tmp:
        res = pipeline.enhance_sequence(seq, "silk_charmeuse", frames=sel, keep=False,
                                        writer=frame_writer(Path(tmp), pipe.mask, fine),
                                        pipeline=pipe)
    cpu = time.process_time() - cpu0
    n = len(sel)
    per_frame = {k: round(1e3 * res.timings[k] / n, 2) for k in STAGES}
    flops = network_flops(model)
    patches = res.patches["network"] + res.patches["padding"]  # patches the network ran
    net_s = res.timings["network"]
    return {
        "garment": "demo_skirt", "frames": n, "coarse_vertices": seq.garment.num_vertices,
        "detailed_vertices": None if res.fine_garment is None else
        res.fine_garment.num_vertices,
        "map_shape": list(res.mask.shape[:2]), "patches": res.patches,
        "batch_size": batch, "chunk_size": chunk,
        "ms_per_frame": per_frame, "ms_per_frame_total": round(sum(per_frame.values()), 2),
        "network": {
            "gflop_per_patch": {k: round(v / 1e9, 4) for k, v in flops.items()},
            "patches_per_frame_run": patches / n,
            "gflops_per_s": round(flops["total"] * patches / net_s / 1e9, 2),
            "conv_gflops_per_s": round(flops["conv"] * patches / net_s / 1e9, 2),
        },
        "cpu_s_per_frame_all_stages": round(cpu / n, 3),
        "setup_s": round(res.timings["setup"], 3), "compile_s": round(res.timings["compile"], 3),
        "wall_s": round(res.timings["total"], 3),
    }


def throughput(model, patches: int, reps: int) -> dict:
    """Patches/s of the jitted enhancer against the batch size: each batch size compiled and
    run once, then the repetitions alternate between the batch sizes (`timing.alternate`),
    each running about `patches` patches."""
    apply = enhancer.make_apply(model)
    size = model.config.patch_size
    rng = np.random.default_rng(0)
    runs, compile_s, count = {}, {}, {}
    for b in BATCH_SIZES:
        x = jnp.asarray(rng.uniform(0.3, 0.7, (b, size, size, 3)).astype(np.float32))
        m = jnp.zeros((b,), jnp.int32)
        t0 = time.perf_counter()
        apply.lower(model.params, x, m).compile()
        compile_s[b] = time.perf_counter() - t0
        calls = max(1, patches // b)
        count[b] = calls * b

        def run(x=x, m=m, calls=calls):
            return [apply(model.params, x, m) for _ in range(calls)]
        runs[str(b)] = run
    t = timing.alternate(runs, reps)
    return {k: {"patches_per_s": count[int(k)] / t.wall[k],
                "cpu_s_per_patch": t.cpu[k] / count[int(k)],
                "compile_s": compile_s[int(k)]} for k in runs} | {
        "load_avg_1m": {"before": t.load_before, "after": t.load_after}}


def network_sweep(model, reps: int, chunk: int, batches=(4, 8, 16), frames_per_batch=(1, 4),
                  stride: int | None = None) -> dict:
    """The network stage of the streaming pipeline (`pipeline._run_network` on one chunk of
    demo frames) for every batch size x frames per network call, alternating
    (`timing.alternate`): ms/frame and the ratio to the CLI default (batch 16, one frame per
    call), plus the padding each setting adds. Every setting is compiled first."""
    from wrinkle_jax import stages

    seq = meshio.load_sequence(_demo_sequence_path())
    mid = model.config.material_id(seq.metadata.get("material") or "silk_charmeuse")
    runs, padding, pipes = {}, {}, {}
    tiles = None
    for b in batches:
        for f in frames_per_batch:
            cfg = pipeline.PipelineConfig(batch_size=b, chunk_size=chunk, frames_per_batch=f,
                                          stride=stride, lift=False)
            pipe = pipeline.make_pipeline(seq.garment, model, cfg)
            if tiles is None:
                size = model.config.patch_size
                mask = pipeline._padded_mask(pipe)
                _, rgb = stages._bake_chunk(pipe.plan, jnp.asarray(seq.frames[:chunk]), mask,
                                            smooth=True, padded_shape=pipe.padded_shape)
                tiles = stages._extract_chunk(rgb, jnp.asarray(pipe.origins), size=size)
            counts = {"network": 0, "padding": 0, "batches": 0}
            pipeline._run_network(pipe, tiles, mid, counts)
            name = f"b{b}_f{f}"
            padding[name] = counts["padding"] / chunk
            pipes[name] = pipe
            runs[name] = (lambda pipe=pipe, tiles=tiles: pipeline._run_network(
                pipe, tiles, mid, {"network": 0, "padding": 0, "batches": 0}))
    t = timing.alternate(runs, reps)
    base = f"b{max(batches)}_f1" if 1 in frames_per_batch else next(iter(runs))
    return {"frames_per_chunk": chunk, "patches_per_frame": pipes[base].num_patches,
            "stride": pipes[base].config.stride,
            "ms_per_frame_wall": {k: round(1e3 * v / chunk, 1) for k, v in t.wall.items()},
            "ms_per_frame_cpu": {k: round(1e3 * v / chunk, 1) for k, v in t.cpu.items()},
            "ratio_to": base,
            "ratio_wall": {k: round(v, 3) for k, v in t.ratios(base, "wall").items()},
            "ratio_cpu": {k: round(v, 3) for k, v in t.ratios(base, "cpu").items()},
            "padding_patches_per_frame": padding, "reps": reps,
            "load_avg_1m": {"before": t.load_before, "after": t.load_after}}


def lift_sweep(model, iters=(20, 3, 2, 1), frames: int = 12) -> dict:
    """The lift stage of the CLI's pipeline (warm-started Gauss-Newton) on the demo frames for
    each GN iteration cap: ms/frame (after a 4-frame warm-up with the same pipeline), the
    iterations run, and how far the lifted vertices land from the first cap's (mm, RMS and
    max over all frames and vertices). Caps run one after another, not alternating."""
    import dataclasses

    from wrinkle_jax.solvers import SolverConfig

    seq = meshio.load_sequence(_demo_sequence_path())
    material = seq.metadata.get("material") or "silk_charmeuse"
    out, ref = {}, None
    for k in iters:
        cfg = pipeline.PipelineConfig(batch_size=16, warm_start=True,
                                      solver=dataclasses.replace(SolverConfig(), max_iters=k))
        pipe = pipeline.make_pipeline(seq.garment, model, cfg)
        pipeline.enhance_sequence(seq, material, pipeline=pipe, config=cfg, frames=range(4))
        load = os.getloadavg()[0]
        res = pipeline.enhance_sequence(seq, material, pipeline=pipe, config=cfg,
                                        frames=range(min(frames, len(seq))))
        det = np.asarray(res.detailed_frames)
        ref = det if ref is None else ref
        d = 1e3 * np.linalg.norm(det - ref, axis=-1)
        out[str(k)] = {"lift_ms_per_frame": round(1e3 * res.timings["lift"] / len(det), 1),
                       "iterations_per_frame": res.lift_iterations / len(det),
                       "vs_first_mm_rms": round(float(np.sqrt((d ** 2).mean())), 3),
                       "vs_first_mm_max": round(float(d.max()), 3), "load_avg_1m": load}
    return {"first": str(iters[0]), "frames": int(len(ref)), "caps": out}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true",
                    help="4 frames (one chunk), no batch-size sweep")
    ap.add_argument("--frames", type=int, default=12, help="demo frames to enhance")
    ap.add_argument("--no-lift", action="store_true", help="skip the lifting stage")
    ap.add_argument("--batch", type=int, default=16, help="pipeline patches per U-Net call")
    ap.add_argument("--chunk", type=int, default=4, help="pipeline frames per chunk")
    ap.add_argument("--patches", type=int, default=32, help="patches per timed repetition")
    ap.add_argument("--reps", type=int, default=3)
    ap.add_argument("--network-sweep", action="store_true",
                    help="only the network stage: batch size x frames per call, alternating")
    ap.add_argument("--stride", type=int, default=None, help="patch stride (--network-sweep)")
    ap.add_argument("--lift-sweep", action="store_true",
                    help="only the lift: Gauss-Newton iteration caps 20, 3, 2, 1 (warm start)")
    args = ap.parse_args()
    if args.lift_sweep:
        model, which = load_model()
        print(json.dumps({"benchmark": "pipeline_lift_sweep", "model": which,
                          **lift_sweep(model, frames=args.frames)}, indent=2))
        return
    if args.network_sweep:
        model, which = load_model()
        print(json.dumps({"benchmark": "pipeline_network_sweep", "model": which,
                          **network_sweep(model, args.reps, args.chunk, stride=args.stride)},
                         indent=2))
        return
    frames = min(args.frames, args.chunk) if args.quick else args.frames
    load_before = os.getloadavg()[0]
    model, which = load_model()
    report = {
        "benchmark": "pipeline",
        "quick": args.quick,
        "model": which,
        "model_config": model.config.to_json(),
        "conv_impl": getattr(model.model, "conv_impl", None),
        "machine": {"cpus": os.cpu_count(), "platform": platform.platform(),
                    "jax": jax.__version__, "load_avg_1m_before": load_before},
    }
    report["stages"] = stage_times(model, frames, not args.no_lift, args.batch, args.chunk)
    if not args.quick:
        report["enhancer_patches_per_s_by_batch"] = throughput(model, args.patches, args.reps)
    report["machine"]["load_avg_1m_after"] = os.getloadavg()[0]
    print(json.dumps(report, indent=2))


if __name__ == "__main__":
    main()
