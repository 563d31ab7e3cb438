"""The training recipe's command-line flags: one flag per setting of `train.RECIPE` (the shipped
model's recipe), so every script that trains it varies the same knobs with the same defaults.

    ap = argparse.ArgumentParser()
    recipe.add_recipe_args(ap)                   # --width, --style-layers, --w-s, ...
    config = recipe.config_from_args(ap.parse_args(argv))      # a train.TrainConfig

`experiments.train_default` (the shipped model), `experiments.short_runs` (one-knob studies of
the same recipe) and any later study share these flags from here, so no script imports another.
`material_gains` reads `--material-gains` (per-material initial unsharp gains).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
from pathlib import Path

from wrinkle_jax import MATERIALS, train

__all__ = ["UNSHARP_SWEEP", "add_recipe_args", "config_from_args", "material_gains"]

# The per-material unsharp-mask sweep on the val split (written by experiments.fidelity in
# the project checkout), which `material_gains("sweep", sigma)` reads.
UNSHARP_SWEEP = (Path(__file__).resolve().parents[1] / "experiments" / "results" / "fidelity"
                 / "unsharp_sweep_material.json")


def add_recipe_args(ap: argparse.ArgumentParser) -> None:
    """Add the training recipe's flags to `ap` (defaults: `train.RECIPE`, the shipped model's);
    `config_from_args` reads them back."""
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
    ap.add_argument("--band-weight", type=float, default=r.band_weight,
                    help="weight of the detail band-energy term (train.TrainConfig.band_weight)")
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
                    help="decoder up-sampling (UNetConfig.upsample; bilinear: no checkerboard)")
    ap.add_argument("--batch-size", type=int, default=r.batch_size)
    ap.add_argument("--keep-checkpoints", type=int, default=r.keep_checkpoints,
                    help="checkpoints kept (every checkpoint_every steps), so a later "
                         "checkpoint choice on validation data has candidates")
    ap.add_argument("--eval-batches", type=int, default=r.eval_batches,
                    help="batches of the periodic evaluation (evenly spaced over its split)")


def config_from_args(args: argparse.Namespace) -> train.TrainConfig:
    """`train.RECIPE` with the flags of `add_recipe_args` (whose defaults are the recipe's, so
    no flags give `train.RECIPE` itself); a `--relative-floor` <= 0 means the absolute loss."""
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
        relative_log=bool(args.relative_log), band_weight=args.band_weight,
        batch_size=args.batch_size, keep_checkpoints=args.keep_checkpoints,
        eval_batches=args.eval_batches)


def material_gains(spec: str, sigma: float,
                   sweep_path: str | os.PathLike = UNSHARP_SWEEP) -> list[float]:
    """Per-material initial unsharp gains, in `wrinkle_jax.MATERIALS` order, from a
    `--material-gains` value.

    Args:
      spec: comma-separated gains, one per material, or "sweep": each material's best amount
        at `sigma` in the per-material unsharp sweep (`sweep_path`, JSON ``{"scores":
        {material: {"sigma=S,amount=A": {"median": score, ...}}}}``).
      sigma: unsharp radius in texels (the recipe's `--unsharp-sigma`), for "sweep".
    Raises:
      ValueError: wrong number of gains, or no sweep setting at `sigma`.
    """
    if spec != "sweep":
        gains = [float(x) for x in spec.split(",")]
        if len(gains) != len(MATERIALS):
            raise ValueError(f"--material-gains: {len(MATERIALS)} values, got {len(gains)}")
        return gains
    sweep = json.loads(Path(sweep_path).read_text())["scores"]
    out = []
    for mat in MATERIALS:
        at = {k: v["median"] for k, v in sweep[mat].items()
              if float(_setting(k)["sigma"]) == sigma}
        if not at:
            raise ValueError(f"--material-gains sweep: no setting at sigma {sigma:g}")
        best = max(at, key=at.get)
        out.append(float(_setting(best)["amount"]))
    return out


def _setting(key: str) -> dict[str, str]:
    """'sigma=16,amount=1.5' -> {'sigma': '16', 'amount': '1.5'}."""
    return dict(p.split("=") for p in key.split(","))
