"""Train the default enhancer and export it into the package (resumable, background-friendly).

    nohup nice -n 2 python -m experiments.train_default [--minutes 40] [--width 16] \
        [--run outputs/default_run] [--warm-start] > /dev/null 2>&1 &
    python -m experiments.train_default --export-only

Trains the shipped recipe `train.RECIPE` (each flag of `wrinkle_jax.recipe.add_recipe_args`
changes one of its settings) on `data/patches` (built by `experiments.make_dataset`),
checkpointing to `--run` every 100 steps; running the command again resumes from the last
checkpoint (`--resume` semantics) until `--steps` or the wall-clock budget `--minutes` is used
up. `--warm-start` starts a fresh run
from the shipped weights (`wrinkle_jax/assets/enhancer.npz`) -- for a later session on a new
machine. At the end (or with `--export-only`) the last checkpoint's parameters are written,
float16, to `--out` (default `wrinkle_jax/assets/enhancer.npz`) with the training facts in its
metadata (`train.export_run`).

Sheet-only ablation (paper Fig. 8), same recipe and budget, trained on the sheet scene only:

    python -m experiments.train_default --train-scenes sheet_balls_wind \
        --run outputs/sheet_only --out experiments/results/sheet_only/enhancer.npz --minutes 45
    python -m experiments.model_card --model experiments/results/sheet_only/enhancer.npz \
        --out experiments/results/sheet_only
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import jax
import numpy as np

from wrinkle_jax import enhancer, recipe, train

ROOT = Path(__file__).resolve().parents[1]


def build_parser() -> argparse.ArgumentParser:
    """The command line: `recipe.add_recipe_args` and `recipe.add_run_args` plus this script's
    run folder, data set, output and warm-start/export-only switches."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=str(ROOT / "data" / "patches"))
    ap.add_argument("--run", default=str(ROOT / "outputs" / "default_run"))
    ap.add_argument("--out", default=str(enhancer.DEFAULT_PATH))
    recipe.add_recipe_args(ap)
    recipe.add_run_args(ap, minutes=40.0)
    ap.add_argument("--warm-start", action="store_true")
    ap.add_argument("--export-only", action="store_true")
    return ap


def main(argv=None) -> None:
    args = build_parser().parse_args(argv)
    run, data_root = Path(args.run), Path(args.data)
    t0 = time.time()
    if not args.export_only:
        try:
            # (the full VGG19 is loaded after the run options are checked)
            recipe.train_from_args(recipe.config_from_args(args), args, data_root, run,
                                   warm_start=args.warm_start)
        except recipe.RecipeError as e:
            raise SystemExit(str(e)) from None
    path = train.export_run(run, Path(args.out), data_root, round(time.time() - t0, 1),
                            recipe.train_scenes(args), recipe.export_steps(args))
    size = path.stat().st_size
    print(json.dumps({"exported": str(path), "bytes": size,
                      "params": int(sum(np.size(x) for x in jax.tree.leaves(
                          enhancer.load_enhancer(path).params)))}))


if __name__ == "__main__":
    main()
