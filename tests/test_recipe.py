"""`wrinkle_jax.recipe`: the training recipe's flags (shared by `experiments.train_default` and
`experiments.short_runs`) default to `train.RECIPE`, a known command line sets exactly its
settings, and `--material-gains` parses."""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path

import pytest

from wrinkle_jax import MATERIALS, enhancer, hostcpu, recipe, train
from wrinkle_jax.nn import unet

ROOT = Path(__file__).resolve().parents[1]


def _parse(argv):
    ap = argparse.ArgumentParser()
    recipe.add_recipe_args(ap)
    return recipe.config_from_args(ap.parse_args(argv))


def test_recipe_is_the_shipped_models_and_the_flags_default_to_it():
    assert _parse([]) == train.RECIPE
    assert train.RECIPE.unet == unet.RECIPE_UNET
    shipped = train.TrainConfig.from_json(enhancer.load_enhancer().meta["train_config"])
    # The form is the host's, not the recipe's: the shipped model trained in "im2col_bf16"
    # (same parameters in every form), the recipe says "auto".
    assert shipped.conv_impl == "im2col_bf16" and train.RECIPE.conv_impl == "auto"
    assert dataclasses.replace(shipped, conv_impl="auto") == train.RECIPE
    assert enhancer.load_enhancer().config.unet == unet.RECIPE_UNET


def test_the_detail_recipe_command_line_sets_exactly_its_flags():
    argv = ("--detail-sigma 8 --noise-channels 4 --noise-scale 4 --upsample bilinear "
            "--residual-base unsharp --unsharp-sigma 16 --unsharp-amount 1 "
            "--residual-highpass 16 --style-layers relu1_2,relu2_1,relu3_1,relu4_1 "
            "--relative-floor 300 --w-s 10 --w-c 0.1 --width 16 --lr 2e-4").split()
    got = _parse(argv)
    net = dataclasses.replace(unet.RECIPE_UNET, detail_sigma=8.0, noise_channels=4,
                              noise_scale=4, upsample="bilinear", residual_highpass=16.0)
    assert got == dataclasses.replace(
        train.RECIPE, unet=net, relative_floor=300.0,
        style_layers=("relu1_2", "relu2_1", "relu3_1", "relu4_1"))
    # ... which is the committed detail model's training config, as that run wrote it
    meta = enhancer.load_enhancer(ROOT / "experiments/results/fidelity/detail_bilinear.npz").meta
    saved = train.TrainConfig.from_json(meta["train_config"])
    assert saved.unet == got.unet and saved.style_layers == got.style_layers
    assert _parse(["--relative-floor", "0"]).relative_floor is None


def test_a_command_line_sets_every_flag_to_its_setting():
    """Each flag lands in its own field (none swapped, none dropped), with the flag's type."""
    argv = ("--width 24 --residual 0 --style-layers relu2_2,relu3_1 --normalize-channels 1 "
            "--w-c 0.5 --steps 123 --lr 3e-4 --w-s 7.5 --relative-floor 50 --relative-log 1 "
            "--residual-base input --unsharp-sigma 4 --unsharp-amount 0.75 "
            "--residual-highpass 6 --blur-order 0 --detail-sigma 2 --noise-channels 3 "
            "--noise-scale 2 --upsample nearest --batch-size 4 --keep-checkpoints 9 "
            "--eval-batches 5").split()
    got = _parse(argv)
    assert got.unet == unet.UNetConfig(
        width=24, residual=False, input_norm=unet.RECIPE_UNET.input_norm, residual_base="input",
        unsharp_sigma=4.0, unsharp_amount=0.75, residual_highpass=6.0, blur_order=0,
        detail_sigma=2.0, noise_channels=3, noise_scale=2, upsample="nearest")
    assert (got.style_layers, got.normalize_channels, got.w_c, got.steps, got.learning_rate,
            got.w_s, got.relative_floor, got.relative_log, got.batch_size, got.keep_checkpoints,
            got.eval_batches) == (
        ("relu2_2", "relu3_1"), True, 0.5, 123, 3e-4, 7.5, 50.0, True, 4, 9, 5)
    # Settings without a flag stay the recipe's.
    assert dataclasses.replace(got, unet=train.RECIPE.unet, style_layers=train.RECIPE.style_layers,
                               normalize_channels=train.RECIPE.normalize_channels,
                               w_c=train.RECIPE.w_c, steps=train.RECIPE.steps,
                               learning_rate=train.RECIPE.learning_rate, w_s=train.RECIPE.w_s,
                               relative_floor=train.RECIPE.relative_floor,
                               relative_log=train.RECIPE.relative_log,
                               batch_size=train.RECIPE.batch_size,
                               keep_checkpoints=train.RECIPE.keep_checkpoints,
                               eval_batches=train.RECIPE.eval_batches) == train.RECIPE
    with pytest.raises(SystemExit):  # argparse rejects a value outside the choices
        _parse(["--upsample", "cubic"])


def test_material_gains_from_values_and_from_a_sweep(tmp_path):
    values = [0.5, 1.0, 1.5, 2.0, 2.5]
    assert recipe.material_gains(",".join(map(str, values)), 16.0) == values
    with pytest.raises(ValueError, match="5 values, got 2"):
        recipe.material_gains("1,2", 16.0)
    # A sweep: per material, the best median at the asked sigma (not the best overall).
    scores = {}
    for i, mat in enumerate(MATERIALS):
        scores[mat] = {f"sigma=16,amount={a}": {"median": -abs(a - 0.25 * (i + 1))}
                       for a in (0.25, 0.5, 0.75, 1.0, 1.25)}
        scores[mat]["sigma=8,amount=3"] = {"median": 100.0}
    path = tmp_path / "sweep.json"
    path.write_text(json.dumps({"scores": scores}))
    assert recipe.material_gains("sweep", 16.0, path) == [0.25, 0.5, 0.75, 1.0, 1.25]
    assert recipe.material_gains("sweep", 8.0, path) == [3.0] * len(MATERIALS)
    with pytest.raises(ValueError, match="no setting at sigma 4"):
        recipe.material_gains("sweep", 4.0, path)
    # The committed sweep reads (the default file).
    assert len(recipe.material_gains("sweep", 16.0)) == len(MATERIALS)


def test_building_the_parser_imports_no_jax():
    """The recipe's defaults are read when a command line is parsed, not when the parser is
    built: `wrinkle-jax --help` and the other subcommands start without jax."""
    import subprocess
    import sys

    code = ("import argparse, sys\n"
            "from wrinkle_jax import recipe\n"
            "ap = argparse.ArgumentParser()\n"
            "recipe.add_recipe_args(ap); recipe.add_run_args(ap); ap.format_help()\n"
            "print(sorted(m for m in ('jax', 'flax', 'wrinkle_jax.train') if m in sys.modules))\n"
            "ap.parse_args([])\n"
            "print('wrinkle_jax.train' in sys.modules)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True, cwd=ROOT).stdout.split("\n")
    assert out[:2] == ["[]", "True"]


def test_parse_time_defaults_behave_as_argparse_defaults():
    ap = argparse.ArgumentParser()
    recipe.add_recipe_args(ap)
    args = ap.parse_args([])
    assert (args.width, args.style_layers, args.relative_floor, args.upsample) == (
        train.RECIPE.unet.width, ",".join(train.RECIPE.style_layers),
        train.RECIPE.relative_floor, train.RECIPE.unet.upsample)
    assert ap.get_default("w_s") == train.RECIPE.w_s
    ap.set_defaults(width=24, upsample="nearest")  # a script may change a default
    got = recipe.config_from_args(ap.parse_args(["--batch", "2"]))  # --batch: --batch-size
    assert (got.unet.width, got.unet.upsample, got.batch_size) == (24, "nearest", 2)
    assert ap.parse_args(["--width", "8"]).width == 8


def test_init_from_a_narrower_run_widens_it_and_refuses_other_differences():
    import jax
    import numpy as np

    from wrinkle_jax.nn.widen import widen_params

    base = train.TrainConfig(unet=unet.UNetConfig(width=2, residual=True))
    wide = dataclasses.replace(base, unet=dataclasses.replace(base.unet, width=4))
    old = train.create_train_state(base, jax.random.key(0, impl="rbg"), 16).params
    other = dataclasses.replace(wide, unet=dataclasses.replace(wide.unet, residual=False))
    with pytest.raises(recipe.RecipeError, match="more than"):
        recipe._widened(old, base.unet, other, 16, print)
    with pytest.raises(recipe.RecipeError, match="more than"):  # narrowing
        recipe._widened(old, wide.unet, base, 16, print)
    logged = []
    got = recipe._widened(old, base.unet, wide, 16, logged.append)
    fresh = train.create_train_state(wide, jax.random.key(wide.seed, impl="rbg"), 16).params
    want = widen_params(old, fresh)
    for a, b in zip(jax.tree_util.tree_leaves(got), jax.tree_util.tree_leaves(want),
                    strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    assert np.asarray(got["enc1"]["kernel"]).shape[-1] == 4
    assert '"widened_from": 2' in logged[0]


def test_conv_impl_flag_sets_the_form_only():
    got = _parse(["--conv-impl", "winograd_bf16"])
    assert got == dataclasses.replace(train.RECIPE, conv_impl="winograd_bf16")
    assert got.vgg_conv_impl == "winograd_bf16"  # the loss's VGG follows


def test_conv_impl_choices_are_the_networks_forms():
    """The parser lists the forms literally (it imports no JAX); they must be the U-Net's."""
    ap = argparse.ArgumentParser()
    recipe.add_recipe_args(ap)
    action = next(a for a in ap._actions if "--conv-impl" in a.option_strings)
    assert tuple(action.choices) == unet.CONV_IMPL_CHOICES
    for impl in unet.CONV_IMPLS:  # each parses to a config that builds
        assert _parse(["--conv-impl", impl]).model().conv_impl == impl
    # "auto" builds the host's fast form (a concrete one), and the loss's VGG runs it too
    auto = _parse(["--conv-impl", "auto"])
    assert auto.model().conv_impl == hostcpu.fast_conv_impl(auto.unet.width) == auto.vgg_conv_impl
