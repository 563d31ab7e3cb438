"""`wrinkle-jax train-enhancer`: train a run, resume it, and export a ready model file."""

from __future__ import annotations

import dataclasses
import json

import jax
import numpy as np
import pytest

import wrinkle_jax
from experiments import train_default
from wrinkle_jax import cli, data, enhancer, recipe, train
from wrinkle_jax.nn import vgg

# The fidelity recipe's command line (experiments.train_default), with every run option.
FIDELITY = (
    "--detail-sigma 8 --noise-channels 4 --noise-scale 4 --upsample bilinear "
    "--residual-base unsharp --unsharp-sigma 16 --unsharp-amount 1 --residual-highpass 16 "
    "--style-layers relu1_2,relu2_1,relu3_1,relu4_1 --relative-floor 300 --relative-log 1 "
    "--band-weight 10 --w-s 10 --w-c 0.1 --width 16 --lr 2e-4 --eval-split valgarment "
    "--init-from outputs/run6 --material-gains sweep --export-steps 300,400 --minutes 40 "
    "--train-scenes dress_dance,cape_walk").split()
RUN_OPTIONS = ("init_from", "material_gains", "eval_split", "export_steps", "minutes",
               "train_scenes")


# The training runs of this file share one network and loss (`NET`), and the same VGG object
# below: `train.cached_step` keys its compiled steps on the configuration (loop settings aside)
# and the VGG object, so the file compiles one train step and one eval step, not one per test.
NET = ["--width", "4", "--batch", "4", "--style-layers", "relu1_2", "--residual-base", "unsharp",
       "--unsharp-sigma", "4"]


@pytest.fixture(scope="module")
def module_vgg():
    return vgg.init_vgg19(jax.random.key(0, impl="rbg"), widths=(4, 8, 8, 8, 8), num_convs=4,
                          spec=vgg.VGGSpec("custom", "REFLECT"))


@pytest.fixture
def tiny_vgg(monkeypatch, module_vgg):
    """The real VGG19 is 80 MB of weights: the command gets a tiny random one instead."""
    monkeypatch.setattr(vgg, "load_vgg19", lambda *a, **k: module_vgg)
    return module_vgg


def test_train_enhancer_exports_a_model_file_that_load_enhancer_reads(
        tiny_patch_root, tmp_path, tiny_vgg, capsys):
    run, model = tmp_path / "run", tmp_path / "model.npz"
    args = ["train-enhancer", "--data", str(tiny_patch_root), "--out", str(run), "--steps", "2",
            *NET]
    assert cli.main([*args, "--export", str(model)]) == 0
    out = capsys.readouterr().out.strip().splitlines()
    assert json.loads(out[-1])["exported"] == str(model)
    assert json.loads("\n".join(out[:-1]))["step"] == 2  # the last metrics, then the export
    cfg, state = train.restore_run(run)
    # The shipped recipe, with the flags' changes only.
    assert train.RECIPE.unet.residual_base == "unsharp"  # so only the width and sigma change
    assert cfg.unet == dataclasses.replace(train.RECIPE.unet, width=4, unsharp_sigma=4.0)
    assert (cfg.steps, cfg.batch_size, cfg.style_layers) == (2, 4, ("relu1_2",))
    assert cfg.w_c == train.RECIPE.w_c and cfg.relative_floor == train.RECIPE.relative_floor
    enh = wrinkle_jax.load_enhancer(model, conv_impl="im2col_f32")
    assert enh.config.unet == cfg.unet and enh.meta["steps"] == 2
    assert (enh.config.patch_size, enh.config.texel_size) == (32, 0.004)
    x = data.PatchDataset(tiny_patch_root, "heldout").get(np.arange(2))
    apply = enhancer.make_apply(enh, clip=False)
    got = apply(enh.params, x["input"], x["material"])
    # The run's own weights through the same program (one compile; the configs are equal, as
    # asserted above, and the conv forms' agreement is tests/test_fastconv.py's).
    want = apply(state.params, x["input"], x["material"])
    assert np.abs(np.asarray(got) - np.asarray(want)).max() < 2e-2  # float16 weights
    # --export-only exports the run again without training (and without --data: the run
    # recorded its data set's facts).
    again = tmp_path / "again.npz"
    assert cli.main(["train-enhancer", "--out", str(run), "--export", str(again),
                     "--export-only"]) == 0
    other = enhancer.load_enhancer(again, conv_impl="im2col_f32")
    assert other.config == enh.config and other.meta["steps"] == 2
    for a, b in zip(jax.tree.leaves(enh.params), jax.tree.leaves(other.params), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def test_train_enhancer_usage_errors(tmp_path, capsys):
    assert cli.main(["train-enhancer", "--out", str(tmp_path / "run"), "--export-only"]) == 2
    assert "--export-only needs --export" in capsys.readouterr().err
    assert cli.main(["train-enhancer", "--out", str(tmp_path / "run")]) == 2
    assert "--data" in capsys.readouterr().err
    assert cli.main(["train-enhancer", "--out", str(tmp_path / "none"), "--export",
                     str(tmp_path / "m.npz"), "--export-only"]) == 1
    assert "no checkpoint" in capsys.readouterr().err
    assert not (tmp_path / "m.npz").exists()


def test_the_cli_reads_the_fidelity_recipe_as_train_default_does():
    cli_args = cli.build_parser().parse_args(["train-enhancer", "--out", "run", *FIDELITY])
    script_args = train_default.build_parser().parse_args(FIDELITY)
    got = cli.train_config(cli_args)
    assert got == recipe.config_from_args(script_args)  # by value
    # ... and the flags landed (not the recipe's defaults on both sides)
    assert (got.unet.detail_sigma, got.unet.noise_channels, got.unet.upsample,
            got.relative_floor, got.relative_log, got.band_weight, got.style_layers) == (
        8.0, 4, "bilinear", 300.0, True, 10.0, ("relu1_2", "relu2_1", "relu3_1", "relu4_1"))
    assert [getattr(cli_args, k) for k in RUN_OPTIONS] == [
        "outputs/run6", "sweep", "valgarment", "300,400", 40.0, "dress_dance,cape_walk"]
    assert [getattr(script_args, k) for k in RUN_OPTIONS] == [
        getattr(cli_args, k) for k in RUN_OPTIONS]
    assert recipe.export_steps(cli_args) == [300, 400]
    assert recipe.train_scenes(cli_args) == ("dress_dance", "cape_walk")
    # No flags: both the shipped recipe, every shared option at the same value except the
    # budget (the script's 40 minutes; the command's none).
    bare_cli = cli.build_parser().parse_args(["train-enhancer", "--out", "run"])
    bare_script = train_default.build_parser().parse_args([])
    assert cli.train_config(bare_cli) == recipe.config_from_args(bare_script) == train.RECIPE
    shared = set(vars(bare_cli)) & set(vars(bare_script)) - {"out", "data", "export_only"}
    assert {"width", "style_layers", "band_weight", *RUN_OPTIONS} <= shared
    assert {k: getattr(bare_cli, k) for k in shared - {"minutes"}} == {
        k: getattr(bare_script, k) for k in shared - {"minutes"}}
    assert (bare_cli.minutes, bare_script.minutes) == (None, 40.0)
    # The command's own settings go on top of the recipe.
    seeded = cli.build_parser().parse_args(["train-enhancer", "--out", "run", "--seed", "3",
                                            "--eval-every", "7", *FIDELITY])
    assert cli.train_config(seeded) == dataclasses.replace(got, seed=3, eval_every=7)


def test_train_enhancer_run_options_reach_the_run(tiny_patch_root, tmp_path, tiny_vgg, capsys):
    """--init-from, --material-gains, --eval-split, --train-scenes and --export-steps: a run
    warm-started from a 1-step run, with its own gains, on the one training scene, evaluated
    on the train split (the tiny set has no val split), exported as the average of two
    checkpoints."""
    base = ["--data", str(tiny_patch_root), *NET, "--checkpoint-every", "1", "--eval-every", "2"]
    donor = tmp_path / "donor"
    assert cli.main(["train-enhancer", "--out", str(donor), "--steps", "1", *base]) == 0
    capsys.readouterr()  # the donor's metrics
    run, model = tmp_path / "run", tmp_path / "model.npz"
    gains = "0.5,1,1.5,2,2.5"
    assert cli.main(["train-enhancer", "--out", str(run), "--steps", "2", *base,
                     "--init-from", str(donor), "--material-gains", gains,
                     "--train-scenes", "sheet", "--eval-split", "train",
                     "--export", str(model), "--export-steps", "1,2"]) == 0
    out = capsys.readouterr().out
    assert json.loads(out.splitlines()[0])["material_gains"]["silk_charmeuse"] == 0.5
    facts = json.loads((run / "data.json").read_text())
    assert facts["train_scenes_selected"] == ["sheet"] and facts["eval_split"] == "train"
    assert facts["train_scenes"] == ["sheet"]
    enh = enhancer.load_enhancer(model, conv_impl="im2col_f32")
    assert enh.meta["checkpoint_steps"] == [1, 2] and enh.meta["train_scenes"] == ["sheet"]
    _, p1 = train.restore_run(run, 1)
    _, p2 = train.restore_run(run, 2)
    want = jax.tree.map(lambda a, b: (np.asarray(a) + np.asarray(b)) / 2, p1.params, p2.params)
    for a, b in zip(jax.tree.leaves(want), jax.tree.leaves(enh.params), strict=True):
        np.testing.assert_allclose(np.asarray(b, np.float32), a, rtol=2e-3, atol=2e-3)
    # The first step started from the donor's weights (not the seed's) with the given gains:
    # one Adam step moves each entry by at most the learning rate.
    _, d = train.restore_run(donor)
    lr = train.RECIPE.learning_rate
    for a, b in zip(jax.tree.leaves({**d.params, "unsharp_amount": 0}),
                    jax.tree.leaves({**p1.params, "unsharp_amount": 0}), strict=True):
        assert np.abs(np.asarray(a) - np.asarray(b)).max() <= 1.001 * lr
    np.testing.assert_allclose(np.asarray(p1.params["unsharp_amount"]),
                               [0.5, 1, 1.5, 2, 2.5], atol=1.001 * lr)
    # An exported model file is a warm start too; another network is a usage error.
    run2 = tmp_path / "run2"
    assert cli.main(["train-enhancer", "--out", str(run2), "--steps", "1", *base,
                     "--init-from", str(model)]) == 0
    _, q1 = train.restore_run(run2, 1)
    for a, b in zip(jax.tree.leaves(enh.params), jax.tree.leaves(q1.params), strict=True):
        assert np.abs(np.asarray(a, np.float32) - np.asarray(b)).max() <= 1.001 * lr
    capsys.readouterr()
    assert cli.main(["train-enhancer", "--out", str(tmp_path / "bad2"), *base,
                     "--unsharp-sigma", "3", "--init-from", str(model)]) == 2
    assert "differs from the flags" in capsys.readouterr().err
    # A recipe contradiction is a usage error, before any training.
    assert cli.main(["train-enhancer", "--out", str(tmp_path / "bad"), "--data",
                     str(tiny_patch_root), "--residual-base", "input",
                     "--material-gains", gains]) == 2
    assert "--residual-base unsharp" in capsys.readouterr().err
