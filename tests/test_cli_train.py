"""`wrinkle-jax train-enhancer`: train a run, resume it, and export a ready model file."""

from __future__ import annotations

import dataclasses
import json

import jax
import numpy as np
import pytest

import wrinkle_jax
from wrinkle_jax import cli, data, enhancer, train
from wrinkle_jax.nn import vgg


@pytest.fixture
def tiny_vgg(monkeypatch):
    """The real VGG19 is 80 MB of weights: the command gets a tiny random one instead."""
    tiny = vgg.init_vgg19(jax.random.key(0, impl="rbg"), widths=(4, 8, 8, 8, 8), num_convs=4,
                          spec=vgg.VGGSpec("custom", "REFLECT"))
    monkeypatch.setattr(vgg, "load_vgg19", lambda *a, **k: tiny)
    return tiny


def test_train_enhancer_exports_a_model_file_that_load_enhancer_reads(
        tiny_patch_root, tmp_path, tiny_vgg, capsys):
    run, model = tmp_path / "run", tmp_path / "model.npz"
    args = ["train-enhancer", "--data", str(tiny_patch_root), "--out", str(run), "--steps", "2",
            "--width", "4", "--batch", "4", "--style-layers", "relu1_2", "relu2_1"]
    assert cli.main([*args, "--export", str(model)]) == 0
    out = capsys.readouterr().out.strip().splitlines()
    assert json.loads(out[-1])["exported"] == str(model)
    assert json.loads("\n".join(out[:-1]))["step"] == 2  # the last metrics, then the export
    cfg, state = train.restore_run(run)
    # The shipped recipe, with the flags' changes only.
    assert cfg.unet == dataclasses.replace(train.RECIPE.unet, width=4)
    assert (cfg.steps, cfg.batch_size, cfg.style_layers) == (2, 4, ("relu1_2", "relu2_1"))
    assert cfg.w_c == train.RECIPE.w_c and cfg.relative_floor == train.RECIPE.relative_floor
    enh = wrinkle_jax.load_enhancer(model, conv_impl="im2col_f32")
    assert enh.config.unet == cfg.unet and enh.meta["steps"] == 2
    assert (enh.config.patch_size, enh.config.texel_size) == (32, 0.004)
    x = data.PatchDataset(tiny_patch_root, "heldout").get(np.arange(2))
    got = enhancer.make_apply(enh, clip=False)(enh.params, x["input"], x["material"])
    # The run's own network, jitted (op-by-op dispatch of the im2col U-Net compiles each of
    # its many slices and dots separately).
    want = jax.jit(cfg.model().apply)({"params": state.params}, x["input"], x["material"])
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
