"""Train the default enhancer and export it into the package (resumable, background-friendly).

    nohup nice -n 2 python -m experiments.train_default [--minutes 40] [--width 16] \
        [--run outputs/default_run] [--warm-start] > /dev/null 2>&1 &
    python -m experiments.train_default --export-only

Trains the shipped recipe `train.RECIPE` (each flag changes one of its settings) on
`data/patches` (built by `experiments.make_dataset`), checkpointing to `--run` every 100 steps;
running the command again resumes from the last checkpoint (`--resume` semantics) until
`--steps` or the wall-clock budget `--minutes` is used up. `--warm-start` starts a fresh run
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
import dataclasses
import json
import time
from pathlib import Path

import jax
import numpy as np

from wrinkle_jax import MATERIALS, data, enhancer, train
from wrinkle_jax.nn import vgg

ROOT = Path(__file__).resolve().parents[1]


def config_from_args(args) -> train.TrainConfig:
    """`train.RECIPE` with the flags of `add_recipe_args` (whose defaults are the recipe's)."""
    net = dataclasses.replace(
        train.RECIPE.unet, width=args.width, residual=bool(args.residual),
        residual_base=args.residual_base, unsharp_sigma=args.unsharp_sigma,
        unsharp_amount=args.unsharp_amount, residual_highpass=args.residual_highpass,
        blur_order=args.blur_order, detail_sigma=args.detail_sigma,
        noise_channels=args.noise_channels, noise_scale=args.noise_scale, upsample=args.upsample)
    return dataclasses.replace(
        train.RECIPE, unet=net, style_layers=tuple(args.style_layers.split(",")),
        steps=args.steps, learning_rate=args.lr, w_s=args.w_s, w_c=args.w_c,
        normalize_channels=bool(args.normalize_channels),
        relative_floor=args.relative_floor if args.relative_floor > 0 else None,
        relative_log=bool(args.relative_log),
        batch_size=args.batch_size)


def export(run: Path, out: Path, data_root: Path, wall_s: float | None = None,
           train_scenes: tuple[str, ...] | None = None) -> Path:
    return train.export_run(run, out, data_root, wall_s, train_scenes)


def material_gains(spec: str, sigma: float) -> list[float]:
    """Per-material unsharp gains (wrinkle_jax.MATERIALS order) from `--material-gains`."""
    if spec != "sweep":
        gains = [float(x) for x in spec.split(",")]
        if len(gains) != len(MATERIALS):
            raise SystemExit(f"--material-gains: {len(MATERIALS)} values, got {len(gains)}")
        return gains
    sweep = json.loads((ROOT / "experiments" / "results" / "fidelity"
                        / "unsharp_sweep_material.json").read_text())["scores"]
    out = []
    for mat in MATERIALS:
        at = {k: v["median"] for k, v in sweep[mat].items()
              if float(dict(p.split("=") for p in k.split(","))["sigma"]) == sigma}
        if not at:
            raise SystemExit(f"--material-gains sweep: no setting at sigma {sigma:g}")
        best = max(at, key=at.get)
        out.append(float(dict(p.split("=") for p in best.split(","))["amount"]))
    return out


def add_recipe_args(ap: argparse.ArgumentParser) -> None:
    """The training recipe's flags (defaults: `train.RECIPE`, the shipped model's), read by
    `config_from_args`; shared with `experiments.short_runs` so its studies vary one knob of
    the same recipe."""
    r, u = train.RECIPE, train.RECIPE.unet
    ap.add_argument("--width", type=int, default=u.width,
                    help="the width study's choice (experiments/results/width_unsharp2_study)")
    ap.add_argument("--residual", type=int, default=int(u.residual))
    ap.add_argument("--style-layers", default=",".join(r.style_layers),
                    help="layer_selection's relu2_2,relu3_1,relu3_2 plus relu1_2,relu2_1, where "
                         "the content term otherwise undoes the sharpening "
                         "(experiments.per_layer_ratios)")
    ap.add_argument("--normalize-channels", type=int, default=int(r.normalize_channels))
    ap.add_argument("--w-c", type=float, default=r.w_c, help="content weight")
    ap.add_argument("--steps", type=int, default=r.steps)
    ap.add_argument("--lr", type=float, default=r.learning_rate)
    ap.add_argument("--w-s", type=float, default=r.w_s)
    ap.add_argument("--relative-floor", type=float, default=r.relative_floor,
                    help="per-patch relative style loss floor; <= 0 for the paper's absolute loss")
    ap.add_argument("--relative-log", type=int, default=int(r.relative_log),
                    help="1: the log of the per-patch relative style loss (median-seeking)")
    ap.add_argument("--residual-base", default=u.residual_base, choices=("input", "unsharp"))
    ap.add_argument("--unsharp-sigma", type=float, default=u.unsharp_sigma,
                    help="texels; the best sigma of the unsharp-mask sweep on training patches")
    ap.add_argument("--unsharp-amount", type=float, default=u.unsharp_amount,
                    help="initial per-material gain (learned)")
    ap.add_argument("--residual-highpass", type=float, default=u.residual_highpass,
                    help="texels; the residual can add detail but not shift orientation")
    ap.add_argument("--blur-order", type=int, default=u.blur_order, choices=(0, 1),
                    help="masked blur of the unsharp base and the high-pass: 1 = local plane "
                         "(flat tilted panels pass unchanged), 0 = local mean (pre-session-4)")
    ap.add_argument("--detail-sigma", type=float, default=u.detail_sigma,
                    help="texels; > 0: the model and the loss work on detail maps "
                         "(wrinkle_jax.detail), for real coarse/fine pairs (data/pairs)")
    ap.add_argument("--noise-channels", type=int, default=u.noise_channels,
                    help="fixed per-texel noise inputs (nn.unet.texel_noise)")
    ap.add_argument("--noise-scale", type=int, default=u.noise_scale,
                    help="texels between the noise's lattice points (1: per-texel noise)")
    ap.add_argument("--upsample", default=u.upsample,
                    choices=("transpose", "nearest", "bilinear"),
                    help="decoder up-sampling (CINUNet.upsample; bilinear: no checkerboard)")
    ap.add_argument("--batch-size", type=int, default=r.batch_size)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=str(ROOT / "data" / "patches"))
    ap.add_argument("--run", default=str(ROOT / "outputs" / "default_run"))
    ap.add_argument("--out", default=str(enhancer.DEFAULT_PATH))
    add_recipe_args(ap)
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
    ap.add_argument("--eval-split", default="heldout",
                    help="split of the periodic evaluation: heldout, or val (pair data: frames "
                         "of the training scenes, so no held-out data guides the recipe)")
    ap.add_argument("--train-scenes", default=None,
                    help="train on these scenes only (comma-separated; e.g. sheet_balls_wind "
                         "for the sheet-only ablation, paper Fig. 8)")
    args = ap.parse_args(argv)
    scenes = tuple(args.train_scenes.split(",")) if args.train_scenes else None
    run, data_root = Path(args.run), Path(args.data)
    t0 = time.time()
    if not args.export_only:
        cfg = config_from_args(args)
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
            gains = material_gains(args.material_gains, cfg.unet.unsharp_sigma)
            if init is None:
                init = train.create_train_state(cfg, jax.random.key(cfg.seed, impl="rbg"),
                                                data.PatchDataset(data_root).patch_size).params
            init = {**init, "unsharp_amount": np.asarray(gains, np.float32)}
            print(json.dumps({"material_gains": dict(zip(MATERIALS, gains, strict=True))}))
        train.train(cfg, data_root, run, resume=True, vgg_params=vgg.load_vgg19(),
                    progress=False, time_limit_s=60 * args.minutes, init_params=init,
                    train_scenes=scenes, eval_split=args.eval_split)
    path = export(run, Path(args.out), data_root, round(time.time() - t0, 1), scenes)
    size = path.stat().st_size
    print(json.dumps({"exported": str(path), "bytes": size,
                      "params": int(sum(np.size(x) for x in jax.tree.leaves(
                          enhancer.load_enhancer(path).params)))}))


if __name__ == "__main__":
    main()
