"""Tests for `wrinkle_jax.nn.patchgan`: the DeepWrinkles-style conditional PatchGAN baseline."""

from __future__ import annotations

import dataclasses
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from wrinkle_jax import enhancer
from wrinkle_jax.nn import patchgan, unet

SIZE = 32
TINY = patchgan.GANConfig(unet.UNetConfig(width=4, residual=True), disc_width=4, batch_size=4)
# Most of this file's time is compiling the GAN step: every test that steps uses this one
# configuration on batches of 4 (32 px), so the step is compiled once for the file (a learning
# rate is a constant of the compiled program).
FAST = dataclasses.replace(TINY, learning_rate=2e-3)
# G's forward as one program (op-by-op dispatch compiles each primitive on its own).
_generate = jax.jit(patchgan.generate, static_argnums=0)


def _key(seed=0):
    return jax.random.key(seed, impl="rbg")


def _batch(n=4, seed=0):
    """Coarse patches (smooth bumps) and targets = coarse + fixed fine stripes, RGB form; a mask
    covering the left three quarters."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:SIZE, 0:SIZE] / SIZE
    inp, tgt = [], []
    for _ in range(n):
        a = rng.uniform(1, 2)
        gx = 0.3 * np.sin(2 * np.pi * a * x)
        fine = gx + 0.4 * np.sin(2 * np.pi * 6 * y)  # predictable from the input
        for g, out in ((gx, inp), (fine, tgt)):
            nrm = np.stack([-g, np.zeros_like(g), np.ones_like(g)], -1)
            out.append((nrm / np.linalg.norm(nrm, axis=-1, keepdims=True) + 1) / 2)
    mask = np.zeros((n, SIZE, SIZE, 1), np.float32)
    mask[:, :, : SIZE * 3 // 4] = 1
    return {"input": jnp.asarray(np.asarray(inp, np.float32) * mask),
            "target": jnp.asarray(np.asarray(tgt, np.float32) * mask),
            "mask": jnp.asarray(mask)}


def test_discriminator_is_a_grid_of_logits_one_per_8x8_cell():
    b = _batch(2)
    d = TINY.discriminator()
    # Shapes only: traced abstractly (nothing compiled or run).
    params = jax.eval_shape(lambda: d.init(_key(), b["input"], b["target"], b["mask"]))["params"]
    logits = jax.eval_shape(lambda p: d.apply({"params": p}, b["input"], b["target"], b["mask"]),
                            params)
    assert logits.shape == (2, SIZE // 8, SIZE // 8, 1)
    w = patchgan.cell_weights(b["mask"], logits.shape)
    assert w.shape == logits.shape
    # columns 0..23 covered: cells 0-2 full, cell 3 empty
    np.testing.assert_allclose(np.asarray(w[0, :, :, 0]), [[1, 1, 1, 0]] * 4)


def test_losses_hand_values_and_background_cells_do_not_count():
    w = jnp.asarray([[[[1.0], [0.0]]]])  # (1, 1, 2, 1): the second cell is background
    zero = jnp.zeros((1, 1, 2, 1))
    np.testing.assert_allclose(patchgan.discriminator_loss(zero, zero, w), np.log(2), rtol=1e-6)
    shifted = zero.at[0, 0, 1, 0].set(50.0)  # a confident wrong logit on the background cell
    np.testing.assert_allclose(patchgan.discriminator_loss(shifted, zero, w), np.log(2),
                               rtol=1e-6)
    confident = jnp.asarray([[[[20.0], [0.0]]]])
    assert float(patchgan.discriminator_loss(confident, -confident, w)) < 1e-6
    out = jnp.zeros((1, 2, 2, 3))
    tgt = out.at[0, 0, 0].set(0.6)
    mask = jnp.zeros((1, 2, 2, 1)).at[0, 0, :].set(1.0)
    np.testing.assert_allclose(patchgan.masked_l1(out, tgt, mask), [0.6 * 3 / 6], rtol=1e-6)
    total, adv, l1 = patchgan.generator_loss(zero, out, tgt, mask, w, 100.0)
    np.testing.assert_allclose(total, np.log(2) + 100 * 0.3, rtol=1e-6)


def test_fresh_generator_is_its_base_and_the_state_is_deterministic():
    b = _batch(4)
    s1 = patchgan.create_gan_state(FAST, _key(3), SIZE)
    s2 = patchgan.create_gan_state(FAST, _key(3), SIZE)
    for a, c in zip(jax.tree.leaves(s1), jax.tree.leaves(s2), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(c))
    out = _generate(FAST, s1.g_params, b["input"], b["mask"])
    np.testing.assert_allclose(np.asarray(out), np.asarray(b["input"]), atol=1e-6)
    step = patchgan.make_gan_step(FAST)
    (s1, m1), (s2, m2) = step(s1, b), step(s2, b)
    assert m1 == m2 or all(float(m1[k]) == float(m2[k]) for k in m1)


def test_gan_training_fits_the_data_term():
    """On a fixed batch whose detail is predictable from the input, the L1 term falls."""
    b = _batch(4, seed=1)
    config = FAST
    state = patchgan.create_gan_state(config, _key(1), SIZE)
    step = patchgan.make_gan_step(config)
    history = []
    for _ in range(40):
        state, m = step(state, b)
        history.append({k: float(v) for k, v in m.items()})
    assert int(state.step) == 40
    assert history[-1]["g_l1"] < 0.5 * history[0]["g_l1"]
    assert all(np.isfinite(list(h.values())).all() for h in history)


def test_discriminator_learns_to_tell_real_pairs_from_a_frozen_generator():
    """G held at its base (no stripes): D's real and fake probabilities separate."""
    b = _batch(4, seed=2)
    config = FAST
    state = patchgan.create_gan_state(config, _key(2), SIZE)
    g0, g_opt0 = state.g_params, state.g_opt
    frozen = (jax.tree.map(jnp.copy, g0), jax.tree.map(jnp.copy, g_opt0))
    step = patchgan.make_gan_step(config)
    for _ in range(30):
        state = dataclasses.replace(state, g_params=jax.tree.map(jnp.copy, frozen[0]),
                                    g_opt=jax.tree.map(jnp.copy, frozen[1]))
        state, m = step(state, b)
    assert float(m["d_real"]) - float(m["d_fake"]) > 0.3
    assert float(m["d_loss"]) < 0.5


def test_generator_exports_as_an_enhancer_that_reproduces_it(tmp_path):
    b = _batch(4)
    state = patchgan.create_gan_state(TINY, _key(5), SIZE)

    # Perturbed weights (the zero-initialized output layer too), drawn with NumPy: jax.random
    # would compile a program for them.
    rng = np.random.default_rng(6)
    g = jax.tree.map(lambda x: jnp.asarray(x + 0.05 * rng.standard_normal(x.shape), x.dtype),
                     state.g_params)
    cfg = TINY.enhancer_config(SIZE, 0.004, 0.03)
    assert cfg.materials == (patchgan.ANY_MATERIAL,)
    path = enhancer.save_enhancer(tmp_path / "gan.npz", g, cfg, dtype=np.float32)
    enh = enhancer.load_enhancer(path)
    apply = enhancer.make_apply(enh, clip=False)
    got = np.asarray(apply(enh.params, b["input"], jnp.zeros((4,), jnp.int32))) * b["mask"]
    want = np.asarray(_generate(FAST, g, b["input"], b["mask"]))
    np.testing.assert_allclose(got, want, atol=1e-5)
    assert patchgan.GANConfig.from_json(TINY.to_json()) == TINY


@pytest.mark.parametrize("layers", [2, 3])
def test_receptive_layers_set_the_logit_grid(layers):
    b = _batch(1)
    d = patchgan.PatchDiscriminator(width=4, layers=layers)
    # Shapes only: traced abstractly (nothing compiled or run).
    params = jax.eval_shape(lambda: d.init(_key(), b["input"], b["target"], b["mask"]))["params"]
    logits = jax.eval_shape(lambda p: d.apply({"params": p}, b["input"], b["target"], b["mask"]),
                            params)
    assert logits.shape == (1, SIZE // 2**layers, SIZE // 2**layers, 1)


# --------------------------------------------------------------------------------------------
# experiments.patchgan: training driver (resume) and the end-to-end script
# --------------------------------------------------------------------------------------------


def test_training_resumes_exactly(tmp_path, tiny_patch_root):
    from experiments import patchgan as script

    config = FAST  # the file's step program (batches of 4 input/target/mask, 32 px)
    full = script.train(config, tiny_patch_root, tmp_path / "full", 60.0, max_steps=4,
                        checkpoint_every=2, log=lambda s: None)
    script.train(config, tiny_patch_root, tmp_path / "split", 60.0, max_steps=2,
                 checkpoint_every=2, log=lambda s: None)
    logs = []
    resumed = script.train(config, tiny_patch_root, tmp_path / "split", 60.0, max_steps=4,
                           checkpoint_every=2, log=logs.append)
    assert logs and logs[0].startswith("resuming at step 2")
    assert full["steps"] == resumed["steps"] == 4
    for a, b in zip(jax.tree.leaves(full["state"]), jax.tree.leaves(resumed["state"]),
                    strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    lines = (tmp_path / "split" / "metrics.jsonl").read_text().splitlines()
    assert [json.loads(ln)["step"] for ln in lines] == [1, 2, 3, 4]
    # Another configuration does not pick up this checkpoint.
    other = dataclasses.replace(config, l1_weight=1.0)
    assert script.load_state(tmp_path / "split", resumed["state"], other) is None


def test_patchgan_script_trains_exports_and_scores(tmp_path, monkeypatch, tiny_patch_root,
                                                   tiny_vgg, model):
    from experiments import patchgan as script

    # The session's tiny VGG (16 convs, widths 4-8) and tiny enhancer (width-4 residual U-Net,
    # 32 px patches, 4 mm texels): built once per worker (tests/conftest.py).
    assert (model.config.patch_size, model.config.texel_size) == (SIZE, 0.004)
    monkeypatch.setattr(script.vgg, "load_vgg19", lambda *a, **k: tiny_vgg)
    model_path = enhancer.save_enhancer(tmp_path / "model.npz", model.params, model.config)
    out = tmp_path / "out"
    # The file's configuration (FAST), so the script's GAN step is the program the file has
    # compiled already (the session's compilation cache holds it).
    net = ["--width", "4", "--disc-width", "4", "--plain-unet", "--lr", "2e-3", "--batch", "4"]
    assert script.config_from_args(script.build_parser().parse_args(net)) == FAST
    argv = ["--data", str(tiny_patch_root), "--run", str(tmp_path / "run"), "--out", str(out),
            "--model", str(model_path), *net,
            "--train-scenes", "sheet", "--steps", "2", "--n", "4", "--n-seen", "4"]
    assert script.main(argv) == 0
    res = json.loads((out / "results.json").read_text())
    assert res["steps"] == 2 and res["train_scenes"] == ["sheet"]
    assert set(res["scores"]) >= {"identity", "model", "patchgan"}
    assert res["scores"]["identity"]["heldout"]["all"]["signed_mean"] == 0.0
    assert np.isfinite(res["summary"]["patchgan"]["training patches"])
    gan = enhancer.load_enhancer(out / "patchgan.npz")
    assert gan.config.materials == (patchgan.ANY_MATERIAL,) and gan.meta["steps"] == 2
    assert (out / "loss_curve.png").exists() and "patchgan" in (out / "table.md").read_text()
    assert script.main(argv[:-6] + ["--steps", "3", "--n", "4", "--n-seen", "4"]) == 0
    assert json.loads((out / "results.json").read_text())["steps"] == 3  # resumed, one more


def test_patchgan_script_defaults_to_the_shipped_generator():
    from experiments import patchgan as script

    parse = script.build_parser().parse_args
    assert script.config_from_args(parse([])) == patchgan.GANConfig()
    got = script.config_from_args(parse(["--width", "4", "--disc-width", "8"]))
    assert got == dataclasses.replace(
        patchgan.GANConfig(), unet=dataclasses.replace(unet.RECIPE_UNET, width=4), disc_width=8)
    assert got.unet.residual_base == "unsharp" and got.unet.residual_highpass > 0
