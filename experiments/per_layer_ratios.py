"""Per-VGG-layer held-out style-loss ratios of a training run against unsharp masking.

    python -m experiments.per_layer_ratios RUN_DIR [--n 48] [--out FILE.json]

Explains a run's held-out improvement score layer by layer: for the run's last checkpoint
(`RUN_DIR`, e.g. `outputs/short_runs/width_unsharp/w32`) and for the unsharp-mask baseline
(sigma 8, amount 1; masked blur of order 0 and of order 1), on the same `--n` held-out
patches (spread evenly over the held-out split, `evaluation.patchsets.take`), it
prints and writes each layer's mean input loss, its share of the evaluation yardstick
(`evaluation.EVAL_LAYERS`), and the mean and median output/input loss ratio, plus the patches
whose yardstick ratio is worst with their per-layer ratios. This is how the content term on
relu2_1 was found to undo the sharpening on relu1_2/relu2_1 (results/recipe/).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from wrinkle_jax import MATERIALS, data, evaluation, train
from wrinkle_jax.evaluation import patchsets
from wrinkle_jax.nn import losses, vgg

ROOT = Path(__file__).resolve().parents[1]
LAYERS = ("relu1_2", "relu2_1", "relu2_2", "relu3_1", "relu3_2", "relu4_1", "relu5_1")


def per_layer_losses(vgg_params, inp, out, target, mask, batch: int = 8) -> dict:
    """{layer: (loss_in (N,), loss_out (N,))} on `LAYERS` (float32 XLA VGG)."""
    @jax.jit
    def fn(i, o, t, m):
        n = i.shape[0]
        f = vgg.features(vgg_params, jnp.concatenate([i, o, t]), layers=LAYERS)
        fi, fo, ft = ({k: v[j * n:(j + 1) * n] for k, v in f.items()} for j in range(3))
        return {name: (losses.style_loss(fi, ft, m, (name,)), losses.style_loss(fo, ft, m, (name,)))
                for name in LAYERS}

    acc = {name: ([], []) for name in LAYERS}
    for s in range(0, len(inp), batch):
        idx = np.resize(np.arange(s, min(s + batch, len(inp))), batch)
        got = fn(*(jnp.asarray(np.asarray(a)[idx]) for a in (inp, out, target, mask)))
        k = min(batch, len(inp) - s)
        for name in LAYERS:
            acc[name][0].append(np.asarray(got[name][0])[:k])
            acc[name][1].append(np.asarray(got[name][1])[:k])
    return {name: (np.concatenate(a), np.concatenate(b)) for name, (a, b) in acc.items()}


def report(per: dict, scene, material, worst: int = 6) -> dict:
    li = sum(per[name][0] for name in evaluation.EVAL_LAYERS)
    lo = sum(per[name][1] for name in evaluation.EVAL_LAYERS)
    ratio = lo / li
    rows = {name: {"mean_loss_in": float(per[name][0].mean()),
                   "share_of_yardstick": float(per[name][0].mean() / li.mean()),
                   "mean_ratio": float((per[name][1] / np.maximum(per[name][0], 1e-12)).mean()),
                   "median_ratio": float(np.median(per[name][1]
                                                   / np.maximum(per[name][0], 1e-12)))}
            for name in LAYERS}
    bad = [{"patch": int(w), "scene": str(scene[w]), "material": MATERIALS[int(material[w])],
            "yardstick_ratio": float(ratio[w]),
            "layer_ratios": {name: float(per[name][1][w] / max(per[name][0][w], 1e-12))
                             for name in LAYERS}} for w in np.argsort(-ratio)[:worst]]
    by_scene = evaluation.summarize(evaluation.scores_from_losses(li, lo), np.asarray(scene))
    return {"signed_mean": float(100 * (1 - ratio).mean()),
            "median_ratio": float(np.median(ratio)), "by_scene": by_scene, "layers": rows,
            "worst": bad}


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run")
    ap.add_argument("--n", type=int, default=48)
    ap.add_argument("--data", default=str(ROOT / "data" / "patches"))
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    cfg, state = train.restore_run(args.run)
    held = patchsets.take(data.PatchDataset(args.data, "heldout"), args.n)
    vgg_params = vgg.load_vgg19()
    outs = {"run": train.enhance_batch(cfg, state.params, held),
            **{f"unsharp order {o} sigma 8 amount 1":
               evaluation.unsharp_mask(held["input"], held["mask"], 8.0, 1.0, o) for o in (0, 1)}}
    result = {"run": args.run, "steps": int(state.step), "n": len(held["input"]),
              "gains": np.asarray(state.params.get("unsharp_amount", [])).tolist(),
              "methods": {}}
    for name, out in outs.items():
        per = per_layer_losses(vgg_params, held["input"], out, held["target"], held["mask"])
        result["methods"][name] = report(per, held["scene"], held["material"])
        r = result["methods"][name]
        print(f"{name}: yardstick signed mean {r['signed_mean']:+.1f}, median ratio "
              f"{r['median_ratio']:.3f}; by scene "
              + ", ".join(f"{k} {v['signed_mean']:+.1f}" for k, v in r["by_scene"].items()))
        for layer, row in r["layers"].items():
            print(f"  {layer}: share {row['share_of_yardstick']:.2f}, mean ratio "
                  f"{row['mean_ratio']:.2f}, median {row['median_ratio']:.3f}")
    if args.out:
        Path(args.out).write_text(json.dumps(result, indent=1) + "\n")


if __name__ == "__main__":
    main()
