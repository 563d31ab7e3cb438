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

from wrinkle_jax import MATERIALS, data, enhancer, recipe, train
from wrinkle_jax.nn import vgg

ROOT = Path(__file__).resolve().parents[1]


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=str(ROOT / "data" / "patches"))
    ap.add_argument("--run", default=str(ROOT / "outputs" / "default_run"))
    ap.add_argument("--out", default=str(enhancer.DEFAULT_PATH))
    recipe.add_recipe_args(ap)
    ap.add_argument("--init-from", default=None,
                    help="start a fresh run from another run's last checkpoint (warm start)")
    ap.add_argument("--material-gains", default=None,
                    help="initial per-material unsharp gains of a fresh run (residual base "
                         "unsharp): 'sweep' = each material's best amount at --unsharp-sigma "
                         "in experiments/results/fidelity/unsharp_sweep_material.json (val "
                         "split), or comma-separated values in wrinkle_jax.MATERIALS order")
    ap.add_argument("--minutes", type=float, default=40.0)
    ap.add_argument("--warm-start", action="store_true")
    ap.add_argument("--export-only", action="store_true")
    ap.add_argument("--export-steps", default=None,
                    help="export these checkpoints (comma-separated steps), their parameters "
                         "averaged (train.averaged_params); default the last checkpoint")
    ap.add_argument("--eval-split", default="heldout",
                    help="split of the periodic evaluation: heldout, val (pair data: frames "
                         "of the training scenes) or valgarment (pair data: the validation-only "
                         "garment), so no held-out data guides the recipe")
    ap.add_argument("--train-scenes", default=None,
                    help="train on these scenes only (comma-separated; e.g. sheet_balls_wind "
                         "for the sheet-only ablation, paper Fig. 8)")
    args = ap.parse_args(argv)
    scenes = tuple(args.train_scenes.split(",")) if args.train_scenes else None
    run, data_root = Path(args.run), Path(args.data)
    t0 = time.time()
    if not args.export_only:
        cfg = recipe.config_from_args(args)
        init = None
        if args.warm_start and not (run / "checkpoints").exists():
            shipped = enhancer.load_enhancer()
            c, n = shipped.config.unet, cfg.unet
            if ((c.width, c.residual, c.residual_base, c.unsharp_sigma, c.blur_order)
                    != (n.width, n.residual, n.residual_base, n.unsharp_sigma, n.blur_order)):
                raise SystemExit("--warm-start: the shipped model's width/residual/base/"
                                 "unsharp sigma/blur order differ from the flags")
            init = shipped.params
        if args.init_from and not (run / "checkpoints").exists():
            init = train.restore_run(args.init_from)[1].params
        if args.material_gains and not (run / "checkpoints").exists():
            if cfg.unet.residual_base != "unsharp":
                raise SystemExit("--material-gains needs --residual-base unsharp")
            try:
                gains = recipe.material_gains(args.material_gains, cfg.unet.unsharp_sigma)
            except ValueError as e:
                raise SystemExit(str(e)) from None
            if init is None:
                init = train.create_train_state(cfg, jax.random.key(cfg.seed, impl="rbg"),
                                                data.PatchDataset(data_root).patch_size).params
            init = {**init, "unsharp_amount": np.asarray(gains, np.float32)}
            print(json.dumps({"material_gains": dict(zip(MATERIALS, gains, strict=True))}))
        train.train(cfg, data_root, run, resume=True, vgg_params=vgg.load_vgg19(),
                    progress=False, time_limit_s=60 * args.minutes, init_params=init,
                    train_scenes=scenes, eval_split=args.eval_split)
    steps = [int(x) for x in args.export_steps.split(",")] if args.export_steps else None
    path = train.export_run(run, Path(args.out), data_root, round(time.time() - t0, 1), scenes,
                            steps)
    size = path.stat().st_size
    print(json.dumps({"exported": str(path), "bytes": size,
                      "params": int(sum(np.size(x) for x in jax.tree.leaves(
                          enhancer.load_enhancer(path).params)))}))


if __name__ == "__main__":
    main()
