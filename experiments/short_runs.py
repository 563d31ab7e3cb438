"""Short training runs of one recipe, varying one knob: residual vs plain, and network width.

    python -m experiments.short_runs residual [--minutes 6]   # width 32, residual vs plain
    python -m experiments.short_runs width [--widths 8,16,32] [--minutes 6 | --steps N \
        --minutes 1000] [--tag shipped] [recipe flags: wrinkle_jax.recipe.add_recipe_args]

The recipe is `experiments.train_default`'s (same flags, `wrinkle_jax.recipe`, same defaults:
the shipped model's); the study changes only the width (or residual). Every variant trains
from scratch on `data/patches` (train split, `experiments.make_dataset`) with the same seed,
data order, loss and optimizer until `--steps` or `--minutes` of wall time, whichever comes
first, then is scored on the same fixed held-out patches (test-only garments and motion) with
`evaluation.score_patches` on `evaluation.EVAL_LAYERS`, and its inference speed is timed
(ms/patch, batch 16, `conv_impl="im2col_bf16"`, best of 5). Runs go to
`outputs/short_runs/<study>/<variant>/` (checkpoints: a later, longer run can resume from them);
results to `experiments/results/<study>_study/{results.json,pareto.png}`.

An equal-step budget (`--steps`) does not depend on the machine's load; an equal wall-clock
budget (`--minutes`) charges wider networks for their cost but is only fair on an idle machine:
the steps each variant reached and its wall time are recorded next to its score.

The session-2 study `width_unsharp2_study` used an older recipe, reproduced by
`--residual-base unsharp --unsharp-sigma 8 --style-layers relu2_2,relu3_1,relu3_2
--normalize-channels 1 --w-c 1 --relative-floor 0.01 --blur-order 0 --residual-highpass 0
--widths 16,32,64 --minutes 5 --tag unsharp2`.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from wrinkle_jax import data, evaluation, recipe, train
from wrinkle_jax.evaluation import patchsets
from wrinkle_jax.nn import vgg

ROOT = Path(__file__).resolve().parents[1]


def variants(study: str, base: train.TrainConfig,
             widths: tuple[int, ...] = (16, 32, 64)) -> dict[str, train.TrainConfig]:
    """The study's configurations: `base` with only the width (or residual) changed."""
    if study == "residual":
        return {name: dataclasses.replace(
                    base, unet=dataclasses.replace(base.unet, width=32, residual=residual))
                for name, residual in (("residual", True), ("plain", False))}
    return {f"w{w}": dataclasses.replace(base, unet=dataclasses.replace(base.unet, width=w))
            for w in widths}


def infer_ms_per_patch(config: train.TrainConfig, params, reps: int = 5, batch: int = 16) -> float:
    model = dataclasses.replace(config, conv_impl="im2col_bf16").model()
    fn = jax.jit(lambda p, x, m: model.apply({"params": p}, x, m))
    x = jnp.asarray(np.random.default_rng(0).uniform(size=(batch, 128, 128, 3)), jnp.float32)
    m = jnp.zeros((batch,), jnp.int32)
    fn(params, x, m).block_until_ready()
    best = np.inf
    for _ in range(reps):
        t0 = time.perf_counter()
        fn(params, x, m).block_until_ready()
        best = min(best, time.perf_counter() - t0)
    return 1e3 * best / batch


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("study", choices=("residual", "width"))
    ap.add_argument("--minutes", type=float, default=6.0, help="wall-clock budget per variant")
    ap.add_argument("--widths", default="16,32,64", help="the width study's widths")
    ap.add_argument("--data", default=str(ROOT / "data" / "patches"))
    ap.add_argument("--only", default=None,
                    help="comma-separated variant names, in run order ('none': no training)")
    ap.add_argument("--tag", default="", help="suffix of the run and results folders")
    recipe.add_recipe_args(ap)
    args = ap.parse_args(argv)
    study = args.study + (f"_{args.tag}" if args.tag else "")
    runs_dir = ROOT / "outputs" / "short_runs" / study
    res_dir = ROOT / "experiments" / "results" / f"{study}_study"
    res_dir.mkdir(parents=True, exist_ok=True)
    results_path = res_dir / "results.json"
    results = json.loads(results_path.read_text()) if results_path.exists() else {}
    vgg_params = vgg.load_vgg19()
    held = patchsets.take(data.PatchDataset(args.data, "heldout"), 96)
    if args.residual_base == "unsharp" and "unsharp base (untrained)" not in results:
        # The starting point every variant must beat: the base alone, on the same patches.
        out = evaluation.unsharp_mask(held["input"], held["mask"], args.unsharp_sigma,
                                      args.unsharp_amount, args.blur_order)
        sc = evaluation.score_patches(vgg_params, held["input"], out, held["target"],
                                      held["mask"])
        results["unsharp base (untrained)"] = {
            "steps": 0, "infer_ms_per_patch": 0.0,
            "heldout": evaluation.summarize(sc, held["scene"])}
        results_path.write_text(json.dumps(results, indent=1) + "\n")
    base = recipe.config_from_args(args)
    configs = variants(args.study, base, tuple(int(w) for w in args.widths.split(",")))
    for name in (args.only.split(",") if args.only else configs):  # --only also sets the order
        if name == "none":  # --only none: just the untrained base on the eval patches
            continue
        cfg = configs[name]
        t0 = time.time()
        got = train.train(cfg, args.data, runs_dir / name, vgg_params=vgg_params,
                          progress=False, time_limit_s=60 * args.minutes)
        wall = time.time() - t0
        params = got["state"].params
        out = train.enhance_batch(cfg, params, held)
        sc = evaluation.score_patches(vgg_params, held["input"], out, held["target"],
                                      held["mask"])
        summary = evaluation.summarize(sc, held["scene"])
        results[name] = {"config": cfg.to_json(), "steps": int(got["state"].step),
                         "wall_s": round(wall, 1), "minutes_budget": args.minutes,
                         "steps_budget": args.steps,
                         "infer_ms_per_patch": round(infer_ms_per_patch(cfg, params), 2),
                         "heldout": summary, "last_train": got["last"]}
        results_path.write_text(json.dumps(results, indent=1) + "\n")
        print(name, json.dumps({k: results[name][k] for k in ("steps", "infer_ms_per_patch")}),
              json.dumps(summary["all"]), flush=True)

    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(figsize=(5, 3.6))
    for name, r in results.items():
        a = r["heldout"]["all"]
        ax.scatter(r["infer_ms_per_patch"], a["signed_mean"], s=30)
        ax.annotate(f"{name} ({r['steps']} steps)", (r["infer_ms_per_patch"], a["signed_mean"]),
                    fontsize=8, xytext=(4, 4), textcoords="offset points")
    ax.set_xlabel("inference ms / 128^2 patch (2 cores, bf16)")
    ax.set_ylabel("held-out improvement (signed %, higher better)")
    ax.set_title(f"{study} study, up to {args.steps} steps / {args.minutes:g} min each")
    fig.tight_layout()
    fig.savefig(res_dir / "pareto.png", dpi=100)


if __name__ == "__main__":
    main()
