"""Equal-wall-clock short training runs: the residual-vs-plain comparison and the width study.

    python -m experiments.short_runs residual [--minutes 6]   # width 32, residual vs plain
    python -m experiments.short_runs width [--minutes 6] [--residual 1|0]   # widths 16, 32, 64
        [--residual-base unsharp --unsharp-sigma S --unsharp-amount A --tag unsharp]

Every variant trains from scratch on `data/patches` (train split, `experiments.make_dataset`)
for the same wall-clock budget with the same seed, data order, loss and optimizer
(`train.TrainConfig` defaults otherwise), then is scored on the same fixed held-out patches
(test-only garments and motion) with `evaluation.score_patches` on `evaluation.EVAL_LAYERS`, and
its inference speed is timed (ms/patch, batch 16, `conv_impl="im2col_bf16"`, best of 5).
Runs go to `outputs/short_runs/<study>/<variant>/` (checkpoints: a later, longer run can resume
from them); results to `experiments/results/<study>_study/{results.json,pareto.png}`.

Caveat: the machine is shared, so the step rate of a run depends on the load while it ran; the
number of steps each variant reached is recorded next to its score.
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

from wrinkle_jax import data, enhancer, evaluation, train
from wrinkle_jax.nn import vgg

ROOT = Path(__file__).resolve().parents[1]


def variants(study: str, residual: bool, **recipe) -> dict[str, train.TrainConfig]:
    # The default model's recipe (experiments.train_default): selected style layers and the
    # per-patch relative style loss; `recipe` overrides TrainConfig fields (e.g. the base).
    base = train.TrainConfig(steps=100_000, eval_every=100, checkpoint_every=100,
                             style_layers=("relu2_2", "relu3_1", "relu3_2"), w_s=10.0,
                             relative_floor=0.01, learning_rate=2e-4)
    base = dataclasses.replace(base, **recipe)
    if study == "residual":
        return {"residual": dataclasses.replace(base, width=32, residual=True),
                "plain": dataclasses.replace(base, width=32, residual=False)}
    return {f"w{w}": dataclasses.replace(base, width=w, residual=residual) for w in (16, 32, 64)}


def heldout_eval_set(root, n: int = 96) -> dict:
    ds = data.PatchDataset(root, "heldout")
    idx = np.unique(np.linspace(0, len(ds) - 1, n).round().astype(int))
    batch = ds.get(idx)
    batch["scene"] = np.array([ds.entries[j]["scene"] for j in ds.sequence_of[idx]])
    return batch


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


def enhance(config: train.TrainConfig, params, batch, size: int = 16) -> np.ndarray:
    """A training run's unit-normal outputs on a batch of patches."""
    model = config.model()
    fn = jax.jit(lambda p, x, m: jnp.clip(model.apply({"params": p}, x, m), 0.0, 1.0))
    return enhancer.enhance_patches(fn, params, batch["input"], batch["material"],
                                    batch["mask"], size)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("study", choices=("residual", "width"))
    ap.add_argument("--minutes", type=float, default=6.0)
    ap.add_argument("--residual", type=int, default=1)
    ap.add_argument("--data", default=str(ROOT / "data" / "patches"))
    ap.add_argument("--only", default=None,
                    help="comma-separated variant names, in run order ('none': no training)")
    ap.add_argument("--residual-base", default="input", choices=("input", "unsharp"))
    ap.add_argument("--unsharp-sigma", type=float, default=8.0)
    ap.add_argument("--unsharp-amount", type=float, default=1.0)
    ap.add_argument("--style-layers", default="relu2_2,relu3_1,relu3_2")
    ap.add_argument("--normalize-channels", type=int, default=1)
    ap.add_argument("--w-c", type=float, default=1.0, help="content weight")
    ap.add_argument("--relative-floor", type=float, default=0.01)
    ap.add_argument("--tag", default="", help="suffix of the run and results folders")
    args = ap.parse_args(argv)
    study = args.study + (f"_{args.tag}" if args.tag else "")
    runs_dir = ROOT / "outputs" / "short_runs" / study
    res_dir = ROOT / "experiments" / "results" / f"{study}_study"
    res_dir.mkdir(parents=True, exist_ok=True)
    results_path = res_dir / "results.json"
    results = json.loads(results_path.read_text()) if results_path.exists() else {}
    vgg_params = vgg.load_vgg19()
    held = heldout_eval_set(args.data)
    if args.residual_base == "unsharp" and "unsharp base (untrained)" not in results:
        # The starting point every variant must beat: the base alone, on the same patches.
        out = evaluation.unsharp_mask(held["input"], held["mask"], args.unsharp_sigma,
                                      args.unsharp_amount)
        sc = evaluation.score_patches(vgg_params, held["input"], out, held["target"],
                                      held["mask"])
        results["unsharp base (untrained)"] = {
            "steps": 0, "infer_ms_per_patch": 0.0,
            "heldout": evaluation.summarize(sc, held["scene"])}
        results_path.write_text(json.dumps(results, indent=1) + "\n")
    recipe = {"residual_base": args.residual_base, "unsharp_sigma": args.unsharp_sigma,
              "unsharp_amount": args.unsharp_amount,
              "style_layers": tuple(args.style_layers.split(",")),
              "normalize_channels": bool(args.normalize_channels), "w_c": args.w_c,
              "relative_floor": args.relative_floor}
    configs = variants(args.study, bool(args.residual), **recipe)
    for name in (args.only.split(",") if args.only else configs):  # --only also sets the order
        if name == "none":  # --only none: just the untrained base on the eval patches
            continue
        cfg = configs[name]
        t0 = time.time()
        got = train.train(cfg, args.data, runs_dir / name, vgg_params=vgg_params,
                          progress=False, time_limit_s=60 * args.minutes)
        wall = time.time() - t0
        params = got["state"].params
        out = enhance(cfg, params, held)
        sc = evaluation.score_patches(vgg_params, held["input"], out, held["target"],
                                      held["mask"])
        summary = evaluation.summarize(sc, held["scene"])
        results[name] = {"config": cfg.to_json(), "steps": int(got["state"].step),
                         "wall_s": round(wall, 1), "minutes_budget": args.minutes,
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
    ax.set_title(f"{study} study, {args.minutes:g} min each")
    fig.tight_layout()
    fig.savefig(res_dir / "pareto.png", dpi=100)


if __name__ == "__main__":
    main()
