"""Benchmark VGG19 features and style-loss gradients on 128x128 patches; prints JSON.

For each style-layer set (ending at relu2_1 / relu3_1 / relu4_1 / relu5_1) and compute dtype
(float32, bfloat16 conv inputs/weights with float32 accumulation) it reports milliseconds per
patch for the forward pass and for forward + backward (gradient of the masked style loss
w.r.t. the input images), median over repetitions after a warm-up compile; the relative error
bfloat16 introduces in the style loss and its gradient against float32; and whether the
compiled CPU program keeps bfloat16 convolutions (native bf16 / AMX kernels) or converts them
back to float32.

With `--train-step`: where one training step's time goes instead (`train.make_train_step`
at the authors' recipe -- width 64, style relu1_2 .. relu5_1, content relu2_1, AdamW -- with
random U-Net and VGG19 weights), each part jitted on its own and timed alternately with the
whole step: U-Net forward, U-Net forward + backward (vjp w.r.t. the parameters), VGG19 on the
output forward + backward (style and content loss w.r.t. the output images, Grams included),
VGG19 on target and input (forward only), Gram and content loss alone (forward + backward
w.r.t. the features), the optimizer update; wall and process CPU ms, and each part's share of
the whole step.

Usage: python benchmarks/bench_vgg.py [--batch 8] [--size 128] [--reps 5]
       python benchmarks/bench_vgg.py --train-step [--batch 32] [--conv-impl im2col_bf16]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import re
import statistics
import time
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np

from wrinkle_jax import primitives, timing
from wrinkle_jax.nn import losses, vgg

LAYER_SETS = {
    "relu2_1": ("relu1_2", "relu2_1"),
    "relu3_1": ("relu1_2", "relu2_1", "relu3_1"),
    "relu4_1": ("relu1_2", "relu2_1", "relu3_1", "relu4_1"),
    "relu5_1": ("relu1_2", "relu2_1", "relu3_1", "relu4_1", "relu5_1"),
}
DTYPES = {"float32": None, "bfloat16": jnp.bfloat16}


def timed_interleaved(runs, reps):
    """Median wall time (s) per entry of `runs` ({key: (jitted fn, args)}).

    Each function is compiled and run once first; the timed repetitions then cycle through all
    entries, so slow drifts in background load hit every variant alike.
    """
    compile_s, samples = {}, {key: [] for key in runs}
    for key, (fn, args) in runs.items():
        start = time.perf_counter()
        jax.block_until_ready(fn(*args))
        compile_s[key] = time.perf_counter() - start
    for _ in range(reps):
        for key, (fn, args) in runs.items():
            start = time.perf_counter()
            jax.block_until_ready(fn(*args))
            samples[key].append(time.perf_counter() - start)
    return {key: statistics.median(v) for key, v in samples.items()}, compile_s


def hlo_conv_dtypes(fn, *args):
    """Operand dtypes of the convolutions in the optimized (compiled) CPU HLO of `fn`."""
    text = fn.lower(*args).compile().as_text()
    # Every instruction is defined once as `%name = dtype[shape]{layout} op(...)`.
    types = dict(re.findall(r"%([\w.\-]+) = (\w+)\[", text))
    operand_dtypes = []
    for line in text.splitlines():
        match = re.search(r"= (\w+)\[[^=]*?\bconvolution\(([^)]*)\)", line)
        if match:
            names = re.findall(r"%([\w.\-]+)", match.group(2))
            operand_dtypes.append("/".join(types.get(n, "?") for n in names))
    counts = {k: operand_dtypes.count(k) for k in sorted(set(operand_dtypes))}
    return {
        "convolution_operand_dtypes": counts,
        "bf16_convolutions": sum(v for k, v in counts.items() if "bf16" in k),
        "onednn_custom_calls": len(re.findall(r"__onednn", text)),
        "xnn_or_ynn_fusions": len(re.findall(r"%[xy]nn_fusion[\w.]* = ", text)),
    }


def cpu_flags():
    try:
        with open("/proc/cpuinfo") as f:
            flags = next(line for line in f if line.startswith("flags")).split()
    except (OSError, StopIteration):
        return []
    return sorted(f for f in flags if f.startswith(("amx", "avx512_bf16", "avx512f", "avx2")))


AUTHORS_STYLE = ("relu1_2", "relu2_1", "relu3_1", "relu4_1", "relu5_1")


def train_step_profile(args) -> dict:
    """The `--train-step` report (see the module docstring); random weights, all-ones mask."""
    import optax

    from wrinkle_jax import train
    from wrinkle_jax.nn import unet

    n, size, rng = args.batch, args.size, np.random.default_rng(0)
    net = unet.UNetConfig(width=64, input_norm="imagenet", residual=False,
                          output_norm="imagenet")
    cfg = train.TrainConfig(unet=net, batch_size=n, learning_rate=1e-4, b1=0.9, b2=0.999,
                            weight_decay=1e-5, style_layers=AUTHORS_STYLE,
                            content_layer="relu2_1", normalize_channels=False,
                            conv_impl=args.conv_impl)
    model, impl = cfg.model(), cfg.vgg_conv_impl
    params = unet.init_params(model, jax.random.key(0), size)
    vp = vgg.init_vgg19(jax.random.key(1), spec=vgg.VGGSpec("imagenet_rgb", "ZERO"))
    x = jnp.asarray(primitives.wavy_normal_maps(rng, n, size))
    tgt = jnp.asarray(primitives.wavy_normal_maps(rng, n, size, waves=16))
    mats = jnp.asarray(rng.integers(0, cfg.num_materials, n), jnp.int32)
    mask = jnp.ones((n, size, size, 1), jnp.float32)
    cot = jnp.asarray(rng.normal(size=(n, size, size, 3)), jnp.float32)
    layers = tuple(sorted(set(AUTHORS_STYLE) | {"relu2_1"}))

    def feats(names):
        return jax.jit(lambda v, im: vgg.features(v, im, layers=names, conv_impl=impl))

    f_tgt, f_inp = feats(AUTHORS_STYLE)(vp, tgt), feats(("relu2_1",))(vp, x)
    f_out = feats(layers)(vp, tgt)

    def loss_from(fo, ft, fi, m):
        return jnp.mean(cfg.w_c * losses.content_loss(fo, fi, m, "relu2_1")
                        + cfg.w_s * losses.style_loss(fo, ft, m, AUTHORS_STYLE))

    unet_fwd = jax.jit(lambda p, im, m: model.apply({"params": p}, im, m))
    # Every array is an argument: closed-over constants would be folded at compile time.
    unet_vjp = jax.jit(jax.grad(lambda p, im, m, c: jnp.sum(model.apply({"params": p}, im, m)
                                                            * c)))
    vgg_out = jax.jit(jax.grad(lambda im, v, ft, fi, m: loss_from(
        vgg.features(v, im, layers=layers, conv_impl=impl), ft, fi, m)))
    gram = jax.jit(jax.grad(loss_from))
    target_input = (feats(AUTHORS_STYLE), feats(("relu2_1",)))
    tx = train.optimizer(cfg)
    opt_state, ones = tx.init(params), jax.tree.map(jnp.ones_like, params)

    @jax.jit
    def opt_step(p, o, g):
        updates, o = tx.update(g, o, p)
        return optax.apply_updates(p, updates), o

    step = train.make_train_step(cfg, vp)
    box = {"state": train.place_state(train.TrainState(
        jnp.zeros((), jnp.int32), jax.tree.map(jnp.copy, params), tx.init(params)))}
    batch = train.shard_batch({"input": np.asarray(x), "target": np.asarray(tgt),
                               "mask": np.asarray(mask), "material": np.asarray(mats)},
                              train.data_mesh())

    def whole():
        box["state"], metrics = step(box["state"], batch)
        return metrics["loss"]

    runs = {"unet_fwd": lambda: unet_fwd(params, x, mats),
            "unet_fwd_bwd": lambda: unet_vjp(params, x, mats, cot),
            "vgg_output_fwd_bwd": lambda: vgg_out(tgt, vp, f_tgt, f_inp, mask),
            "vgg_target_input_fwd": lambda: (target_input[0](vp, tgt),
                                             target_input[1](vp, x)),
            "gram_content_fwd_bwd": lambda: gram(f_out, f_tgt, f_inp, mask),
            "optimizer": lambda: opt_step(params, opt_state, ones),
            "whole_step": whole}
    t = timing.alternate(runs, args.reps)
    return {"benchmark": "train_step_profile", "jax": jax.__version__, "batch": n,
            "patch": size, "conv_impl": args.conv_impl, "vgg_conv_impl": impl,
            "unet_params": unet.count_params(params), "style_layers": list(AUTHORS_STYLE),
            "content_layer": "relu2_1",
            "note": "parts jitted separately; vgg_output_fwd_bwd includes the Grams and "
                    "content loss (gram_content_fwd_bwd alone beside it)",
            **t.to_json("whole_step")}


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--batch", type=int, default=8)
    parser.add_argument("--size", type=int, default=128)
    parser.add_argument("--reps", type=int, default=5)
    parser.add_argument("--train-step", action="store_true",
                        help="profile one training step instead (see the docstring)")
    parser.add_argument("--conv-impl", default="im2col_bf16",
                        help="with --train-step: the U-Net's and VGG's convolution form")
    args = parser.parse_args()
    if args.train_step:
        print(json.dumps(train_step_profile(args), indent=1))
        return

    params = vgg.load_vgg19()
    rng = np.random.default_rng(0)
    images = jnp.asarray(primitives.wavy_normal_maps(rng, args.batch, args.size, waves=12))
    target = jnp.asarray(primitives.wavy_normal_maps(rng, args.batch, args.size, waves=12))
    mask = np.ones((args.batch, args.size, args.size, 1), np.float32)
    mask[:, :, : args.size // 5] = 0.0  # some background, as in real UV patches
    mask = jnp.asarray(mask)

    results, hlo, speedups = [], {}, {}
    load_before = os.getloadavg()[0]
    for last, layers in LAYER_SETS.items():
        target_feats = vgg.features(params, target, layers=layers)  # float32 reference

        # Target features and mask are arguments, not closed-over constants: XLA would
        # otherwise constant-fold the target Grams at compile time.
        def loss(p, x, target_feats, mask, layers=layers, dtype=None):
            feats = vgg.features(p, x, layers=layers, dtype=dtype)
            per_sample = losses.style_loss(feats, target_feats, mask, layers)
            return jnp.sum(per_sample), per_sample

        runs = {}
        for dtype_name, dtype in DTYPES.items():
            fwd = jax.jit(partial(vgg.features, layers=layers, dtype=dtype))
            fwd_bwd = jax.jit(jax.value_and_grad(partial(loss, dtype=dtype), argnums=1,
                                                 has_aux=True))
            runs[(dtype_name, "fwd")] = (fwd, (params, images))
            runs[(dtype_name, "fwd_bwd")] = (fwd_bwd, (params, images, target_feats, mask))
            if dtype is not None and last == "relu5_1":
                hlo = hlo_conv_dtypes(fwd, params, images)
        times, compile_s = timed_interleaved(runs, reps=args.reps)

        ref_loss, ref_grad = None, None
        for dtype_name in DTYPES:
            fwd_bwd, fb_args = runs[(dtype_name, "fwd_bwd")]
            (_, per_sample), grad = fwd_bwd(*fb_args)
            row = {
                "dtype": dtype_name,
                "last_layer": last,
                "layers": list(layers),
                "forward_ms_per_patch": round(1e3 * times[(dtype_name, "fwd")] / args.batch, 2),
                "fwd_bwd_ms_per_patch": round(
                    1e3 * times[(dtype_name, "fwd_bwd")] / args.batch, 2),
                "compile_s": round(compile_s[(dtype_name, "fwd")]
                                   + compile_s[(dtype_name, "fwd_bwd")], 2),
                "style_loss_mean": float(jnp.mean(per_sample)),
            }
            if ref_loss is None:
                ref_loss, ref_grad = per_sample, grad
            else:
                row["style_loss_rel_err_vs_f32"] = float(
                    jnp.max(jnp.abs(per_sample - ref_loss) / jnp.abs(ref_loss)))
                row["grad_rel_err_vs_f32"] = float(
                    jnp.linalg.norm(grad - ref_grad) / jnp.linalg.norm(ref_grad))
            results.append(row)
        speedups[last] = {
            kind: round(times[("float32", kind)] / times[("bfloat16", kind)], 3)
            for kind in ("fwd", "fwd_bwd")
        }

    flags = cpu_flags()
    native = hlo.get("bf16_convolutions", 0) > 0
    median_speedup = statistics.median(v for s in speedups.values() for v in s.values())
    report = {
        "benchmark": "vgg19_features",
        "jax": jax.__version__,
        "backend": jax.default_backend(),
        "cpu": platform.processor() or platform.machine(),
        "cpu_count": os.cpu_count(),
        "cpu_flags": flags,
        "amx_available": any(f.startswith("amx") for f in flags),
        "weights": params["spec"].preprocess,
        "pool": "avg",
        "batch": args.batch,
        "patch": args.size,
        "reps": args.reps,
        "results": results,
        "bf16_speedup_vs_f32": speedups,
        "bf16_compiled_hlo_relu5_1_forward": hlo,
        "loadavg_1min_before_after": [round(load_before, 2), round(os.getloadavg()[0], 2)],
        "bf16_verdict": (
            ("bf16 convolutions kept in the compiled program" if native
             else "XLA:CPU converts bf16 convolutions back to f32 (no native bf16/AMX kernels)")
            + f"; median f32/bf16 time ratio {median_speedup:.2f}"
        ),
    }
    print(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()
