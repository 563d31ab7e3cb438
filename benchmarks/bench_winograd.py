"""Benchmark the Winograd forms against the im2col forms, layer by layer; prints one JSON object.

Every 3x3 conv and 4x4 stride-2 transposed conv of the U-Net (128 x 128 patches) at each
`--widths` (levels w, 2w, 4w, 8w: the encoder convs w -> 2w at 64 x 64 texels, 2w -> 4w at 32,
4w -> 8w at 16; the decoder's transposed convs 8w -> 8w from 8 x 8, 8w -> 4w from 16, 4w -> 2w
from 32, 2w -> w from 64), bfloat16 dots, `--batch` patches: `fastconv` against `winograd`,
jitted, alternating (`wrinkle_jax.timing.alternate`), with the relative RMS error of each
against the float32 im2col form and whether `winograd.use_winograd` picks the layer. This is
the measurement behind the rule (session 26: every picked layer faster at widths 16 and 64).
The first conv (3 channels, float32) and the output conv are never Winograd and are left out.

Usage: python benchmarks/bench_winograd.py [--widths 16,64] [--batch 8] [--reps 3]
"""

from __future__ import annotations

import argparse
import json

import jax
import jax.numpy as jnp
import numpy as np

from wrinkle_jax import timing
from wrinkle_jax.nn import fastconv, winograd
from wrinkle_jax.runtime import retain_freed_memory


def layers(width: int) -> list[tuple[str, int, int, int]]:
    """(kind, input side, in channels, out channels) of the U-Net's wide layers."""
    w = width
    return [("conv", 64, w, 2 * w), ("conv", 32, 2 * w, 4 * w), ("conv", 16, 4 * w, 8 * w),
            ("deconv", 8, 8 * w, 8 * w), ("deconv", 16, 8 * w, 4 * w),
            ("deconv", 32, 4 * w, 2 * w), ("deconv", 64, 2 * w, w)]


def bench_layer(kind: str, side: int, c: int, o: int, batch: int, reps: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    x = jax.nn.relu(jnp.asarray(rng.standard_normal((batch, side, side, c)), jnp.float32))
    taps = 3 if kind == "conv" else 4
    k = jnp.asarray(rng.standard_normal((taps, taps, c, o)) / np.sqrt(taps * taps * c),
                    jnp.float32)
    name = "conv3x3" if kind == "conv" else "conv_transpose4x4s2"
    fns = {"im2col": jax.jit(getattr(fastconv, name)), "winograd": jax.jit(getattr(winograd, name))}
    exact = jax.jit(lambda x, k: getattr(fastconv, name)(x, k, compute_dtype=jnp.float32))(x, k)
    err = {f: float(jnp.sqrt(jnp.mean((fn(x, k) - exact) ** 2) / jnp.mean(exact**2)))
           for f, fn in fns.items()}
    t = timing.alternate({f: (lambda fn=fn: fn(x, k)) for f, fn in fns.items()}, reps)
    summary = t.to_json("im2col")
    return {"kind": kind, "side": side, "c_in": c, "c_out": o,
            "picked": winograd.use_winograd(c, o, side),
            "ms_wall": {f: round(1e3 * v, 2) for f, v in t.wall.items()},
            "winograd_over_im2col_wall": summary["ratio_wall"]["winograd"],
            "rel_rms_vs_float32": {f: round(v, 5) for f, v in err.items()},
            "load_avg_1m": summary["load_avg_1m"]}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--widths", default="16,64")
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--reps", type=int, default=3)
    args = ap.parse_args(argv)
    retained = retain_freed_memory()
    out = {"benchmark": "winograd_vs_im2col_per_layer", "batch": args.batch, "reps": args.reps,
           "rule": {"min_channels": winograd.MIN_CHANNELS, "min_side": winograd.MIN_SIDE},
           "malloc_retained": retained, "widths": {}}
    for w in (int(s) for s in args.widths.split(",")):
        out["widths"][str(w)] = [bench_layer(*layer, args.batch, args.reps)
                                 for layer in layers(w)]
    print(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
