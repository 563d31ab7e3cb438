"""Before/after check for refactors of the U-Net or the model files: every committed model
file's output on one fixed input, with the exact ("xla") and fast ("im2col_bf16") forms.

    python benchmarks/model_outputs.py OUT.npz            # save the outputs
    python benchmarks/model_outputs.py OUT.npz REF.npz    # save, then max |diff| against REF

Run it on the old commit, then on the new one with the old file as REF: a refactor that keeps
the parameter trees and the computation prints 0 for every (file, form).
"""
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from wrinkle_jax import enhancer

ROOT = Path(__file__).resolve().parents[1]
FILES = ["wrinkle_jax/assets/enhancer.npz",
         "experiments/results/sheet_only/enhancer.npz",
         "experiments/results/patchgan/patchgan.npz",
         "experiments/results/fidelity/detail_bilinear.npz",
         "experiments/results/fidelity/detail_logratio.npz",
         "experiments/results/fidelity/detail_noise.npz"]


def fixed_input(n=3, s=128):
    """Deterministic wavy normal field in RGB form with a round mask (zeros outside)."""
    y, x = np.mgrid[0:s, 0:s].astype(np.float32) / s
    out = []
    for k in range(n):
        nx = 0.4 * np.sin(2 * np.pi * (3 + k) * x + k) * np.cos(2 * np.pi * 5 * y)
        ny = 0.3 * np.cos(2 * np.pi * (7 + 2 * k) * y + 0.5 * k)
        nz = np.ones_like(nx)
        v = np.stack([nx, ny, nz], -1)
        v /= np.linalg.norm(v, axis=-1, keepdims=True)
        m = (((x - 0.5) ** 2 + (y - 0.45) ** 2) < 0.16)[..., None]
        out.append(((v + 1) / 2) * m)
    return np.stack(out).astype(np.float32)


def main():
    x = jnp.asarray(fixed_input())
    origins = jnp.asarray([[0, 0], [64, 128], [-32, 300]], jnp.int32)
    res = {}
    for f in FILES:
        for impl in ("xla", "im2col_bf16"):
            enh = enhancer.load_enhancer(ROOT / f, conv_impl=impl)
            m = jnp.arange(3, dtype=jnp.int32) % len(enh.config.materials)
            out = jax.jit(enh.model.apply)({"params": enh.params}, x, m, origins)
            res[f"{f}|{impl}"] = np.asarray(out)
            print(f, impl, enh.config.unet, "out mean", float(np.mean(out)), flush=True)
    np.savez(sys.argv[1], **res)
    if len(sys.argv) > 2:
        ref = np.load(sys.argv[2])
        assert set(ref.files) == set(res), (sorted(ref.files), sorted(res))
        worst = 0.0
        for k in sorted(res):
            d = float(np.max(np.abs(res[k] - ref[k])))
            worst = max(worst, d)
            print(f"max|diff| {d:.3e}  {k}")
        print(f"overall max|diff| {worst:.3e} over {len(res)} (file, conv_impl) outputs")


if __name__ == "__main__":
    main()
