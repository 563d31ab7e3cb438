"""Tests for wrinkle_jax.train: learning, checkpoints, exact resume, data-parallel equivalence."""

from __future__ import annotations

import dataclasses
import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from wrinkle_jax import data, train
from wrinkle_jax.nn import unet, vgg

CONFIG = train.TrainConfig(unet.UNetConfig(width=4, residual=True), batch_size=4, steps=4,
                           learning_rate=1e-3, style_layers=("relu1_2", "relu2_1"), w_s=10.0,
                           eval_every=2, eval_batches=1, checkpoint_every=2)


@pytest.fixture(scope="module")
def tiny_vgg():
    return vgg.init_vgg19(jax.random.key(0, impl="rbg"), widths=(4, 8, 8, 8, 8), num_convs=4,
                          spec=vgg.VGGSpec("custom", "REFLECT"))


@pytest.fixture(scope="module")
def data_root(tiny_patch_root):
    return tiny_patch_root


def test_overfits_four_patches(data_root, tiny_vgg):
    ds = data.PatchDataset(data_root, "train")
    batch = train.shard_batch(ds.get(np.arange(4)), train.data_mesh())
    # Random output layer: the start is far from the targets, so learning shows in 50 steps
    # (the identity start is tested in test_residual_network_starts_as_identity). CONFIG's
    # network: its step is the program `train.train` runs in the tests below (compiled once).
    cfg = dataclasses.replace(CONFIG, zero_init_output=False)
    state = train.place_state(
        train.create_train_state(cfg, jax.random.key(1, impl="rbg"), patch_size=32))
    step = train.make_train_step(cfg, tiny_vgg)
    losses = []
    for _ in range(50):
        state, m = step(state, batch)
        losses.append(float(m["loss"]))
    assert np.isfinite(losses).all()
    assert losses[-1] <= 0.5 * losses[0], (losses[0], losses[-1])
    assert int(state.step) == 50
    # The placed start is the input type the step returns: 50 steps, one program.
    assert step._cache_size() == 1


def test_checkpoint_round_trip_is_bit_identical(tmp_path, tiny_vgg):
    state = train.create_train_state(CONFIG, jax.random.key(2, impl="rbg"), patch_size=32)
    manager = train._manager(tmp_path / "ck", CONFIG)
    it = data.IteratorState(epoch=3, cursor=12)
    train.save_checkpoint(manager, state, it, CONFIG)
    template = train.create_train_state(CONFIG, jax.random.key(9, impl="rbg"), patch_size=32)
    restored, it2 = train.restore_checkpoint(manager, template, CONFIG)
    assert it2 == it
    for a, b in zip(jax.tree_util.tree_leaves(state), jax.tree_util.tree_leaves(restored),
                    strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    with pytest.raises(ValueError, match="different config.*width"):
        train.restore_checkpoint(manager, template, dataclasses.replace(
            CONFIG, unet=dataclasses.replace(CONFIG.unet, width=8)))


def test_resume_equals_straight_run(data_root, tmp_path, tiny_vgg):
    straight = train.train(CONFIG, data_root, tmp_path / "a", vgg_params=tiny_vgg,
                           progress=False)
    train.train(dataclasses.replace(CONFIG, steps=2), data_root, tmp_path / "b",
                vgg_params=tiny_vgg, progress=False)
    resumed = train.train(CONFIG, data_root, tmp_path / "b", resume=True, vgg_params=tiny_vgg,
                          progress=False)
    for a, b in zip(jax.tree_util.tree_leaves(straight["state"]),
                    jax.tree_util.tree_leaves(resumed["state"]), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    rows = [json.loads(x) for x in (tmp_path / "b" / "metrics.jsonl").read_text().splitlines()]
    assert [r["step"] for r in rows if r["kind"] == "train"] == [1, 2, 3, 4]
    evals = [r for r in rows if r["kind"] == "eval"]
    assert [r["step"] for r in evals] == [2, 4]
    assert all(np.isfinite(r["heldout_improvement"]) for r in evals)
    assert (tmp_path / "b" / "loss_curve.png").stat().st_size > 1000
    # A time limit stops after the first step that ends past it, with an eval and a
    # checkpoint, and --resume continues from there to the same parameters.
    cut = train.train(CONFIG, data_root, tmp_path / "c", vgg_params=tiny_vgg, progress=False,
                      time_limit_s=0.0)
    assert int(cut["state"].step) == 1 and "heldout_style" in cut["last"]
    again = train.train(CONFIG, data_root, tmp_path / "c", resume=True, vgg_params=tiny_vgg,
                        progress=False)
    for a, b in zip(jax.tree_util.tree_leaves(straight["state"]),
                    jax.tree_util.tree_leaves(again["state"]), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    # Five calls (two step counts) share one jitted train step and one eval step
    # (train.cached_step), yet every run above matched the straight one bit for bit. Each was
    # compiled once: `train.train` places a fresh, a stepped and a restored state alike (placed
    # as they came, they were three input types: 3 entries). Without the sharing, the steps
    # looked up here would never have run (0 entries).
    for kind in ("train", "eval"):
        assert train.cached_step(kind, CONFIG, tiny_vgg)._cache_size() == 1


def test_warm_start_from_params(data_root, tmp_path, tiny_vgg):
    # CONFIG's learning rate, so the step is the program the other tests compiled (a rate of 0
    # would be a new program). Adam's first update is lr * g / (|g| + eps): below lr in every
    # entry, so one step stays within lr of the donor, while a fresh start is far from it.
    cfg = dataclasses.replace(CONFIG, steps=1)
    donor = train.create_train_state(cfg, jax.random.key(5, impl="rbg"), patch_size=32).params
    fresh = train.create_train_state(cfg, jax.random.key(cfg.seed, impl="rbg"),
                                     patch_size=32).params
    got = train.train(cfg, data_root, tmp_path, vgg_params=tiny_vgg, progress=False,
                      init_params=donor)
    assert int(got["state"].step) == 1
    for a, b in zip(jax.tree_util.tree_leaves(donor),
                    jax.tree_util.tree_leaves(got["state"].params), strict=True):
        # read after training: the donated train state did not take the caller's arrays
        assert np.abs(np.asarray(a) - np.asarray(b)).max() <= 1.001 * cfg.learning_rate
    assert max(float(np.abs(np.asarray(a) - np.asarray(b)).max()) for a, b in zip(
        jax.tree_util.tree_leaves(donor), jax.tree_util.tree_leaves(fresh), strict=True)) > 0.05


SHARDED = textwrap.dedent("""
    import json, dataclasses, sys
    import jax, jax.numpy as jnp, numpy as np
    from wrinkle_jax import train
    from wrinkle_jax.nn import unet, vgg
    assert jax.device_count() == 2, jax.devices()
    # float32 convolutions: bfloat16 rounding would turn reduction-order differences between
    # the 1- and 2-device programs into ~1e-4 gradient differences.
    cfg = train.TrainConfig(unet.UNetConfig(width=4, residual=True), batch_size=4,
                            style_layers=("relu1_2", "relu2_1"),
                            w_s=10.0, learning_rate=1e-3, conv_impl="im2col_f32")
    tiny = vgg.init_vgg19(jax.random.key(0, impl="rbg"), widths=(4, 8, 8, 8, 8), num_convs=4,
                          spec=vgg.VGGSpec("custom", "REFLECT"))
    rng = np.random.default_rng(0)
    batch = {"input": rng.uniform(size=(4, 32, 32, 3)).astype(np.float32),
             "target": rng.uniform(size=(4, 32, 32, 3)).astype(np.float32),
             "mask": np.ones((4, 32, 32, 1), np.float32),
             "material": np.array([0, 1, 2, 3], np.int32)}
    state = train.create_train_state(cfg, jax.random.key(1, impl="rbg"), patch_size=32)
    # The loss and its gradient through the jit on one device ...
    (loss, _), grad = jax.jit(jax.value_and_grad(train.loss_fn, has_aux=True),
                              static_argnums=3)(state.params, batch, tiny, cfg)
    # ... and the data-parallel train step on two: its Adam first moment after one step from
    # zero is (1 - b1) * g exactly, so the step's own gradient is read back from its state
    # (no third program: a separate data-parallel gradient would be another compile).
    mesh = train.data_mesh(jax.devices()[:2])
    stepped, m = train.make_train_step(cfg, tiny, mesh)(state, train.shard_batch(batch, mesh))
    adam = stepped.opt_state[0]
    assert int(adam.count) == 1
    grad2 = jax.tree.map(lambda mu: np.asarray(mu) / (1 - cfg.b1), adam.mu)
    g1, g2 = (jax.tree_util.tree_leaves(jax.device_get(g)) for g in (grad, grad2))
    scale = max(float(np.abs(g).max()) for g in g1)
    diff = max(float(np.abs(a - b).max()) for a, b in zip(g1, g2, strict=True))
    print(json.dumps({"grad_diff_rel": diff / scale, "grad_scale": scale,
                      "loss": [float(loss), float(m["loss"])]}))
""")


def test_sharded_step_matches_single_device():
    # Keep the suite's XLA_FLAGS (tests/conftest.py's compile-time setting) and add two devices.
    flags = f"{os.environ.get('XLA_FLAGS', '')} --xla_force_host_platform_device_count=2"
    env = dict(os.environ, XLA_FLAGS=flags.strip())
    root = Path(__file__).resolve().parents[1]
    res = subprocess.run([sys.executable, "-c", SHARDED], capture_output=True, text=True,
                         env=env, cwd=root, timeout=600)
    assert res.returncode == 0, res.stderr[-2000:]
    got = json.loads(res.stdout.strip().splitlines()[-1])
    # Gradients, not Adam-updated parameters: Adam's first step is ~lr * sign(g), so entries
    # with |g| near 0 amplify float reduction-order differences up to lr.
    assert got["grad_diff_rel"] < 1e-5 and got["grad_scale"] > 0, got
    np.testing.assert_allclose(got["loss"][0], got["loss"][1], rtol=1e-5)
    assert jnp.isfinite(got["loss"][0])


def test_residual_network_starts_as_identity():
    cfg = CONFIG
    plain = dataclasses.replace(cfg, zero_init_output=False)
    assert plain.model() == cfg.model()  # zero_init_output changes the start, not the network
    # One jitted forward for both starts (op-by-op dispatch of the U-Net compiles every
    # primitive separately, several times slower than one program).
    forward = jax.jit(lambda p, x: cfg.model().apply({"params": p}, x, jnp.array([0, 1])))
    state = train.create_train_state(cfg, jax.random.key(2, impl="rbg"), patch_size=32)
    x = jnp.asarray(np.random.default_rng(0).uniform(size=(2, 32, 32, 3)), jnp.float32)
    out = forward(state.params, x)
    np.testing.assert_allclose(np.asarray(out), np.asarray(x), atol=1e-7)
    state = train.create_train_state(plain, jax.random.key(2, impl="rbg"), patch_size=32)
    out = forward(state.params, x)
    assert np.abs(np.asarray(out) - np.asarray(x)).max() > 1e-3



def test_enhance_batch_of_an_untrained_residual_run_returns_its_masked_input():
    """The zero-initialized residual network is the identity, so `enhance_batch` gives back
    each patch's unit normals inside its mask and 0 outside, in order, across chunks (5
    patches in chunks of 2: the last chunk repeats a patch)."""
    rng = np.random.default_rng(3)
    n = rng.normal(size=(5, 32, 32, 3)) + [0.0, 0.0, 2.0]
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    mask = np.zeros((5, 32, 32, 1), np.float32)
    for k in range(5):
        mask[k, 2 * k:20 + 2 * k, 3:29] = 1.0
    x = ((n + 1) / 2 * mask).astype(np.float32)
    batch = {"input": x, "material": np.array([0, 1, 2, 3, 4]), "mask": mask}
    state = train.create_train_state(CONFIG, jax.random.key(2, impl="rbg"), patch_size=32)
    got = train.enhance_batch(CONFIG, state.params, batch, batch_size=2)
    assert got.shape == x.shape and got.dtype == np.float32
    np.testing.assert_allclose(got, x, atol=2e-6)

def test_detail_noise_recipe_trains_and_scores_detail(data_root, tiny_vgg):
    """The detail-space, texel-noise configuration: starts as the identity, learns, and its
    loss ignores a large-scale tilt of the target (only detail counts)."""
    # The tiny random VGG's Gram entries are ~1e-4 of the real one's: scale the style term.
    net = unet.UNetConfig(width=4, residual=True, detail_sigma=4.0, residual_highpass=8.0,
                          noise_channels=2, input_norm="none")
    cfg = dataclasses.replace(CONFIG, unet=net, w_s=1e7)
    ds = data.PatchDataset(data_root, "train")
    it = data.BatchIterator(ds, 4, seed=0, origins=True)
    batch = train.shard_batch(next(it), train.data_mesh())
    state = train.place_state(
        train.create_train_state(cfg, jax.random.key(3, impl="rbg"), patch_size=32))
    ev = train.make_eval_step(cfg, tiny_vgg)
    start = jax.device_get(ev(state.params, batch))
    # The identity up to the float32 round trip through the detail frame.
    np.testing.assert_allclose(start["improvement_signed"][start["valid"]], 0.0, atol=1e-2)
    step = train.make_train_step(cfg, tiny_vgg)
    losses = []
    for _ in range(12):
        state, m = step(state, batch)
        losses.append(float(m["loss"]))
    assert np.isfinite(losses).all() and losses[-1] < 0.8 * losses[0], losses
    end = jax.device_get(ev(state.params, batch))
    assert np.median(end["improvement_signed"][end["valid"]]) > 10
    # A global tilt of the target (its large scale) leaves the detail images unchanged.
    a = np.deg2rad(25.0)
    q = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]], np.float32)
    tilted = ((np.asarray(batch["target"]) * 2 - 1) @ q.T + 1) / 2 * np.asarray(batch["mask"])
    # Placed as the batch's target is: one program for both calls (a host array would be
    # another input type to the jit, a second compile).
    tilted = dict(batch, target=jax.device_put(tilted, batch["target"].sharding))
    images = jax.jit(train.loss_images, static_argnums=0)
    _, _, t0 = images(cfg, batch, batch["input"])
    _, _, t1 = images(cfg, tilted, batch["input"])
    m_ = np.asarray(batch["mask"])[..., 0] > 0
    np.testing.assert_allclose(np.asarray(t1)[..., 2][m_], np.asarray(t0)[..., 2][m_], atol=1e-4)


def test_restore_run_and_export_run_give_a_model_file_of_the_run(data_root, tmp_path, tiny_vgg):
    from wrinkle_jax import enhancer

    run = tmp_path / "run"
    cfg = dataclasses.replace(CONFIG, steps=2, zero_init_output=False)
    got = train.train(cfg, data_root, run, vgg_params=tiny_vgg, progress=False)
    saved_cfg, state = train.restore_run(run)
    assert saved_cfg == cfg and int(state.step) == 2
    for a, b in zip(jax.tree.leaves(got["state"].params), jax.tree.leaves(state.params),
                    strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    path = train.export_run(run, tmp_path / "m.npz")  # the data facts from run/data.json
    enh = enhancer.load_enhancer(path, conv_impl="im2col_f32")
    assert enh.meta["steps"] == 2 and enh.config.unet == cfg.unet
    assert train.TrainConfig.from_json(enh.meta["train_config"]) == cfg
    assert (enh.config.patch_size, enh.config.texel_size) == (32, 0.004)
    ds = data.PatchDataset(data_root, "train")
    assert enh.meta["train_patches"] == len(ds)
    x = ds.get(np.arange(2))
    # The run's own network, jitted (op-by-op dispatch of the im2col U-Net compiles each of
    # its many slices and dots separately).
    ref = jax.jit(dataclasses.replace(cfg, conv_impl="im2col_f32").model().apply)(
        {"params": state.params}, x["input"], x["material"])
    out = enhancer.make_apply(enh, clip=False)(enh.params, x["input"], x["material"])
    # float16 storage: ~5e-4 relative rounding of the weights
    assert np.abs(np.asarray(out) - np.asarray(ref)).max() < 2e-2
    assert np.abs(np.asarray(ref) - x["input"]).max() > 1e-2  # a trained, non-identity net
    # A run as older code wrote it: no data.json, and a config.json from before the detail,
    # noise and up-sampling settings existed. It restores, and exports given its data set.
    (run / "data.json").unlink()
    old = json.loads((run / "config.json").read_text())
    for key in ("detail_sigma", "noise_channels", "noise_scale", "upsample"):
        del old[key]
    (run / "config.json").write_text(json.dumps(old))
    assert train.restore_run(run)[0] == cfg
    with pytest.raises(FileNotFoundError, match="data.json"):
        train.export_run(run, tmp_path / "x.npz")
    again = enhancer.load_enhancer(train.export_run(run, tmp_path / "m2.npz", data_root))
    assert again.config == enh.config and again.meta["train_sequences"] == enh.meta[
        "train_sequences"]
    assert not (tmp_path / "x.npz").exists()
    with pytest.raises(FileNotFoundError, match="no config.json"):
        train.restore_run(tmp_path / "nothing")


def test_cached_steps_are_keyed_on_what_the_step_closes_over(tiny_vgg):
    """Loop-only settings share a step; the loss settings, the VGG object and the kind do not;
    no compile is needed to tell (jit compiles on first call). Last in this file: it evicts
    the steps the other tests share."""
    step = train.cached_step("train", CONFIG, tiny_vgg)
    assert train.cached_step("train", dataclasses.replace(
        CONFIG, steps=7, seed=3, batch_size=2, eval_every=1, checkpoint_every=5), tiny_vgg) is step
    assert train.cached_step("train", dataclasses.replace(CONFIG, w_s=11.0), tiny_vgg) is not step
    assert train.cached_step("eval", CONFIG, tiny_vgg) is not step
    other = jax.tree.map(lambda x: x, tiny_vgg)  # equal values, another object
    assert train.cached_step("train", CONFIG, other) is not step
    # The cache holds few entries, each keeping its VGG pytree alive (so no other object can
    # take its id while the entry lives): filling it drops the oldest.
    for w in range(train._STEP_CACHE_SIZE):
        train.cached_step("train", dataclasses.replace(CONFIG, w_c=float(w + 2)), tiny_vgg)
    assert len(train._STEP_CACHE) == train._STEP_CACHE_SIZE
    assert train.cached_step("train", CONFIG, tiny_vgg) is not step
    with pytest.raises(ValueError, match="kind"):
        train.cached_step("apply", CONFIG, tiny_vgg)

