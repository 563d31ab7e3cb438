"""Tests for train.checkpoint_steps, train.averaged_params and export_run(steps=...): choosing
and averaging a run's checkpoints (no training: the run folder is written directly)."""

from __future__ import annotations

import dataclasses
import json

import jax
import numpy as np
import pytest

from wrinkle_jax import enhancer, train
from wrinkle_jax.data import IteratorState
from wrinkle_jax.nn import unet

CONFIG = train.TrainConfig(unet.UNetConfig(width=4, residual=True), batch_size=4, steps=10,
                           style_layers=("relu1_2",), keep_checkpoints=5)
FACTS = {"patch_size": 32, "texel_size": 0.004, "coarse_pd": 0.03, "train_patches": 7,
         "train_sequences": ["s__denim_light"], "train_scenes": ["s"]}


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    """A run folder with checkpoints at steps 2, 4, 6 whose parameters differ by step."""
    run = tmp_path_factory.mktemp("run")
    (run / "config.json").write_text(json.dumps(CONFIG.to_json(), indent=1))
    (run / "data.json").write_text(json.dumps(FACTS))
    (run / "metrics.jsonl").write_text(json.dumps({"kind": "train", "step": 1, "step_s": 0.5})
                                       + "\n")
    # Random leaves of the train state's shapes (running the init would only cost compile time).
    rng = np.random.default_rng(0)
    shapes = jax.eval_shape(lambda: train.create_train_state(CONFIG, jax.random.key(0, impl="rbg")))
    state = jax.tree.map(lambda s: rng.standard_normal(s.shape).astype(s.dtype), shapes)
    manager = train._manager(run / "checkpoints", CONFIG)
    for step in (2, 4, 6):
        params = jax.tree.map(lambda x, s=step: x + 0.01 * s, state.params)
        saved = dataclasses.replace(state, step=np.asarray(step, state.step.dtype), params=params)
        train.save_checkpoint(manager, saved, IteratorState(), CONFIG)
    return run, state.params


def test_steps_are_listed_and_averaged(run):
    path, base = run
    assert train.checkpoint_steps(path) == [2, 4, 6]
    cfg, one = train.averaged_params(path, [4])
    assert cfg == CONFIG
    for a, b in zip(jax.tree.leaves(one), jax.tree.leaves(base), strict=True):
        np.testing.assert_allclose(a, np.asarray(b) + 0.04, atol=1e-6)
    _, mean = train.averaged_params(path, [2, 6])  # (b + .02 + b + .06) / 2 = b + .04
    for a, b in zip(jax.tree.leaves(mean), jax.tree.leaves(one), strict=True):
        np.testing.assert_allclose(a, b, atol=1e-6)
    with pytest.raises(ValueError, match="at least one"):
        train.averaged_params(path, [])


def test_export_of_chosen_and_averaged_checkpoints(run, tmp_path):
    path, base = run
    last = enhancer.load_enhancer(train.export_run(path, tmp_path / "last.npz"))
    avg = enhancer.load_enhancer(train.export_run(path, tmp_path / "avg.npz", steps=[2, 4]))
    assert last.meta["steps"] == 6 and last.meta["checkpoint_steps"] is None
    assert avg.meta["steps"] == 4 and avg.meta["checkpoint_steps"] == [2, 4]
    for a, b, c in zip(jax.tree.leaves(avg.params), jax.tree.leaves(last.params),
                       jax.tree.leaves(base), strict=True):
        # float16 storage: compare at its rounding
        np.testing.assert_allclose(np.asarray(a, np.float32), np.asarray(c) + 0.03,
                                   atol=2e-3 * (1 + np.abs(np.asarray(c)).max()))
        np.testing.assert_allclose(np.asarray(b, np.float32), np.asarray(c) + 0.06,
                                   atol=2e-3 * (1 + np.abs(np.asarray(c)).max()))
