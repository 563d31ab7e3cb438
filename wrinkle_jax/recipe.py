"""The training recipe's command-line flags: one flag per setting of `train.RECIPE` (the shipped
model's recipe), so every script that trains it varies the same knobs with the same defaults.

    ap = argparse.ArgumentParser()
    recipe.add_recipe_args(ap)                   # --width, --style-layers, --w-s, ...
    config = recipe.config_from_args(ap.parse_args(argv))      # a train.TrainConfig

`experiments.train_default` (the shipped model), `wrinkle-jax train-enhancer`,
`experiments.short_runs` (one-knob studies of the same recipe) and any later study share these
flags from here, so no script imports another. `add_run_args` adds the options of a training
run (warm start, per-material gains, evaluation split, scene subset, exported checkpoints,
budget), `train_from_args` runs one, and `material_gains` reads `--material-gains`.

The parser builds without importing `wrinkle_jax.train` (and so jax): the recipe's defaults are
read from `train.RECIPE` only when a command line is parsed, which keeps `wrinkle-jax --help`
and every other subcommand's start free of it.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

from wrinkle_jax import MATERIALS

if TYPE_CHECKING:
    from wrinkle_jax import train

__all__ = ["UNSHARP_SWEEP", "RecipeError", "add_recipe_args", "add_run_args",
           "config_from_args", "initial_params", "material_gains", "train_from_args",
           "train_scenes"]

# The per-material unsharp-mask sweep on the val split (written by experiments.fidelity in
# the project checkout), which `material_gains("sweep", sigma)` reads.
UNSHARP_SWEEP = (Path(__file__).resolve().parents[1] / "experiments" / "results" / "fidelity"
                 / "unsharp_sweep_material.json")


class RecipeError(ValueError):
    """Run options that contradict each other or the recipe (the message names the flag)."""


class _FromRecipe:
    """A flag's default, `read(train.RECIPE)`, evaluated when a command line is parsed."""

    def __init__(self, read: Callable[[Any], Any]):
        self.read = read


class _StoreRecipeDefault(argparse.Action):
    """argparse's "store" action whose default (a `_FromRecipe`) is read on first use: argparse
    reads `action.default` only while parsing (or for a help text naming it), so building the
    parser imports nothing heavy. The value is kept once read, so argparse sees one object."""

    def __call__(self, parser, namespace, values, option_string=None):
        setattr(namespace, self.dest, values)

    @property
    def default(self):
        if isinstance(self._default, _FromRecipe):
            from wrinkle_jax import train

            self._default = self._default.read(train.RECIPE)
        return self._default

    @default.setter
    def default(self, value):  # argparse's __init__ and `set_defaults` assign it
        self._default = value


class _RecipeFlags:
    """`ap.add_argument` for flags whose `default` reads the recipe: `r` is `train.RECIPE`, `u`
    its `unet` (e.g. ``default=lambda r, u: u.width``)."""

    def __init__(self, ap: argparse.ArgumentParser):
        self.ap = ap

    def add_argument(self, *names, default, **kw):
        self.ap.add_argument(*names, action=_StoreRecipeDefault,
                             default=_FromRecipe(lambda r: default(r, r.unet)), **kw)


def add_recipe_args(ap: argparse.ArgumentParser) -> None:
    """Add the training recipe's flags to `ap` (defaults: `train.RECIPE`, the shipped model's,
    read at parse time); `config_from_args` reads them back."""
    ap = _RecipeFlags(ap)
    ap.add_argument("--width", type=int, default=lambda r, u: u.width,
                    help="the width study's choice (experiments/results/width_unsharp2_study)")
    ap.add_argument("--residual", type=int, default=lambda r, u: int(u.residual))
    ap.add_argument("--style-layers", default=lambda r, u: ",".join(r.style_layers),
                    help="layer_selection's relu2_2,relu3_1,relu3_2 plus relu1_2,relu2_1, where "
                         "the content term otherwise undoes the sharpening "
                         "(experiments.per_layer_ratios)")
    ap.add_argument("--normalize-channels", type=int,
                    default=lambda r, u: int(r.normalize_channels))
    ap.add_argument("--w-c", type=float, default=lambda r, u: r.w_c, help="content weight")
    ap.add_argument("--steps", type=int, default=lambda r, u: r.steps)
    ap.add_argument("--lr", type=float, default=lambda r, u: r.learning_rate)
    ap.add_argument("--w-s", type=float, default=lambda r, u: r.w_s)
    ap.add_argument("--relative-floor", type=float, default=lambda r, u: r.relative_floor,
                    help="per-patch relative style loss floor; <= 0 for the paper's absolute loss")
    ap.add_argument("--relative-log", type=int, default=lambda r, u: int(r.relative_log),
                    help="1: the log of the per-patch relative style loss (median-seeking)")
    ap.add_argument("--band-weight", type=float, default=lambda r, u: r.band_weight,
                    help="weight of the detail band-energy term (train.TrainConfig.band_weight)")
    ap.add_argument("--bank-weight", type=float, default=lambda r, u: r.bank_weight,
                    help="weight of the set-level term: distance to the nearest fine Gram of "
                         "the material (train.TrainConfig.bank_weight)")
    ap.add_argument("--bank-size", type=int, default=lambda r, u: r.bank_size,
                    help="fine training patches per material in that term's bank")
    ap.add_argument("--residual-base", default=lambda r, u: u.residual_base,
                    choices=("input", "unsharp"))
    ap.add_argument("--unsharp-sigma", type=float, default=lambda r, u: u.unsharp_sigma,
                    help="texels; the best sigma of the unsharp-mask sweep on training patches")
    ap.add_argument("--unsharp-amount", type=float, default=lambda r, u: u.unsharp_amount,
                    help="initial per-material gain (learned)")
    ap.add_argument("--residual-highpass", type=float, default=lambda r, u: u.residual_highpass,
                    help="texels; the residual can add detail but not shift orientation")
    ap.add_argument("--blur-order", type=int, default=lambda r, u: u.blur_order, choices=(0, 1),
                    help="masked blur of the unsharp base and the high-pass: 1 = local plane "
                         "(flat tilted panels pass unchanged), 0 = local mean (pre-session-4)")
    ap.add_argument("--detail-sigma", type=float, default=lambda r, u: u.detail_sigma,
                    help="texels; > 0: the model and the loss work on detail maps "
                         "(wrinkle_jax.detail), for real coarse/fine pairs (data/pairs)")
    ap.add_argument("--noise-channels", type=int, default=lambda r, u: u.noise_channels,
                    help="fixed per-texel noise inputs (nn.unet.texel_noise)")
    ap.add_argument("--noise-scale", type=int, default=lambda r, u: u.noise_scale,
                    help="texels between the noise's lattice points (1: per-texel noise)")
    ap.add_argument("--upsample", default=lambda r, u: u.upsample,
                    choices=("transpose", "nearest", "bilinear"),
                    help="decoder up-sampling (UNetConfig.upsample; bilinear: no checkerboard)")
    ap.add_argument("--batch-size", "--batch", type=int, default=lambda r, u: r.batch_size)
    ap.add_argument("--keep-checkpoints", type=int, default=lambda r, u: r.keep_checkpoints,
                    help="checkpoints kept (every checkpoint_every steps), so a later "
                         "checkpoint choice on validation data has candidates")
    ap.add_argument("--eval-batches", type=int, default=lambda r, u: r.eval_batches,
                    help="batches of the periodic evaluation (evenly spaced over its split)")
    ap.add_argument("--conv-impl", default=lambda r, u: r.conv_impl,
                    choices=("auto", "xla", "im2col_f32", "im2col_bf16", "winograd_bf16",
                             "winograd_f32"),
                    help="convolution form of the U-Net and the loss's VGG (auto: im2col_bf16 "
                         "on CPUs with bfloat16 dot units, else im2col_f32, winograd_f32 from "
                         "width 32): winograd_bf16 "
                         "stepped 1.46x (session 26), 1.06x (session 27) and 1.42x "
                         "(session 28) as fast as the "
                         "recipe's im2col_bf16 in the authors' recipe (bench_reference; "
                         "experiments/results/timing/reference_train.json)")


def config_from_args(args: argparse.Namespace) -> train.TrainConfig:
    """`train.RECIPE` with the flags of `add_recipe_args` (whose defaults are the recipe's, so
    no flags give `train.RECIPE` itself); a `--relative-floor` <= 0 means the absolute loss."""
    from wrinkle_jax import train

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
        bank_weight=args.bank_weight, bank_size=args.bank_size, batch_size=args.batch_size,
        keep_checkpoints=args.keep_checkpoints,
        eval_batches=args.eval_batches, conv_impl=args.conv_impl)


def add_run_args(ap: argparse.ArgumentParser, minutes: float | None = None) -> None:
    """Add a training run's options (not recipe settings) to `ap`: --init-from,
    --material-gains, --minutes (default `minutes`; None: no wall-clock budget),
    --export-steps, --eval-split and --train-scenes; `train_from_args` reads them."""
    ap.add_argument("--init-from", default=None,
                    help="start a fresh run from another run's last checkpoint, or from an "
                         "enhancer file (.npz, e.g. an exported model; its weights as stored) "
                         "(warm start)")
    ap.add_argument("--material-gains", default=None,
                    help="initial per-material unsharp gains of a fresh run (residual base "
                         "unsharp): 'sweep' = each material's best amount at --unsharp-sigma "
                         "in experiments/results/fidelity/unsharp_sweep_material.json (val "
                         "split), or comma-separated values in wrinkle_jax.MATERIALS order")
    ap.add_argument("--minutes", type=float, default=minutes,
                    help="stop after this much wall time (with a checkpoint; running again "
                         "resumes)")
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


def train_scenes(args: argparse.Namespace) -> tuple[str, ...] | None:
    """`--train-scenes` as a tuple of scene names (None: every training scene)."""
    return tuple(args.train_scenes.split(",")) if args.train_scenes else None


def export_steps(args: argparse.Namespace) -> list[int] | None:
    """`--export-steps` as checkpoint steps (None: the last checkpoint)."""
    return [int(x) for x in args.export_steps.split(",")] if args.export_steps else None


def initial_params(cfg: train.TrainConfig, run: Path, data_root: Path,
                   init_from: str | None = None, gains: str | None = None,
                   warm_start: bool = False, log: Callable[[str], Any] = print):
    """Starting parameters of a fresh run in `run` (None: the config's random initialization,
    or a run that already has checkpoints, which resumes instead).

    Args:
      warm_start: start from the shipped model's weights (`enhancer.load_enhancer()`).
      init_from: start from this run folder's last checkpoint, or from this enhancer file's
        weights (`enhancer.load_enhancer`; e.g. a model exported by an earlier run); after
        `warm_start`, so it wins. A narrower network is widened; any other architecture
        difference is an error.
      gains: a `--material-gains` value: these per-material unsharp gains replace the
        starting parameters' ``unsharp_amount`` (needs residual base "unsharp"); the chosen
        gains are logged as one JSON line through `log`.
    Raises:
      RecipeError: the shipped model's architecture differs from `cfg` (`warm_start`), the
        `init_from` network differs in more than a narrower width (or its file knows other
        materials), or bad `gains`.
    """
    import jax
    import numpy as np

    from wrinkle_jax import data, enhancer, train

    if (Path(run) / "checkpoints").exists():
        return None
    init = None
    if warm_start:
        shipped = enhancer.load_enhancer()
        c, n = shipped.config.unet, cfg.unet
        if ((c.width, c.residual, c.residual_base, c.unsharp_sigma, c.blur_order)
                != (n.width, n.residual, n.residual_base, n.unsharp_sigma, n.blur_order)):
            raise RecipeError("--warm-start: the shipped model's width/residual/base/"
                              "unsharp sigma/blur order differ from the flags")
        init = shipped.params
    if init_from and Path(init_from).is_file():
        donor = enhancer.load_enhancer(init_from)
        if donor.config.materials != MATERIALS:
            raise RecipeError(f"--init-from {init_from}: the model knows the materials "
                              f"{donor.config.materials}, not {MATERIALS}")
        old_unet, init = donor.config.unet, donor.params
    elif init_from:
        old_cfg, state = train.restore_run(init_from)
        old_unet, init = old_cfg.unet, state.params
    if init_from:
        # The gain's starting value is no part of the network: the donor's learned gains come
        # with its parameters.
        old_unet = dataclasses.replace(old_unet, unsharp_amount=cfg.unet.unsharp_amount)
        if old_unet != cfg.unet:
            init = _widened(init, old_unet, cfg, data.PatchDataset(data_root).patch_size, log)
    if gains:
        if cfg.unet.residual_base != "unsharp":
            raise RecipeError("--material-gains needs --residual-base unsharp")
        try:
            values = material_gains(gains, cfg.unet.unsharp_sigma)
        except ValueError as e:
            raise RecipeError(str(e)) from None
        if init is None:
            init = train.create_train_state(cfg, jax.random.key(cfg.seed, impl="rbg"),
                                            data.PatchDataset(data_root).patch_size).params
        init = {**init, "unsharp_amount": np.asarray(values, np.float32)}
        log(json.dumps({"material_gains": dict(zip(MATERIALS, values, strict=True))}))
    return init


def train_from_args(cfg: train.TrainConfig, args: argparse.Namespace, data_root: Path,
                    run: Path, resume: bool = True, warm_start: bool = False, vgg_params=None,
                    progress: bool = False, log: Callable[[str], Any] = print) -> dict:
    """Train `cfg` into `run` with the options of `add_run_args` in `args` (`initial_params`
    for a fresh run, then `train.train`); returns `train.train`'s result.

    Raises:
      RecipeError: see `initial_params`.
    """
    from wrinkle_jax import train
    from wrinkle_jax.nn import vgg

    init = initial_params(cfg, run, data_root, args.init_from, args.material_gains,
                          warm_start, log)
    return train.train(cfg, data_root, run, resume=resume,
                       vgg_params=vgg.load_vgg19() if vgg_params is None else vgg_params,
                       progress=progress,
                       time_limit_s=None if args.minutes is None else 60 * args.minutes,
                       init_params=init, train_scenes=train_scenes(args),
                       eval_split=args.eval_split)


def _widened(params, old_unet, cfg, patch_size: int, log: Callable[[str], Any]):
    """`--init-from` a narrower network (`old_unet`, a UNetConfig): embedded in `cfg`'s width,
    computing the same function (`nn.widen.widen_params`); any other architecture difference
    is an error."""
    import jax

    from wrinkle_jax import train
    from wrinkle_jax.nn.widen import widen_params

    if (old_unet.width > cfg.unet.width
            or dataclasses.replace(old_unet, width=cfg.unet.width) != cfg.unet):
        raise RecipeError("--init-from: the run's network differs from the flags in more than "
                          f"a wider --width ({old_unet} vs {cfg.unet})")
    fresh = train.create_train_state(cfg, jax.random.key(cfg.seed, impl="rbg"),
                                     patch_size).params
    log(json.dumps({"widened_from": old_unet.width, "width": cfg.unet.width}))
    return widen_params(params, fresh)


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
