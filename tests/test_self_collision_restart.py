"""Tests for experiments/self_collision_restart.py's variant settings (the runs themselves need
the data set; `sim.scenes.resimulate` is tested in test_sim_scenes)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from experiments import self_collision_restart as R
from wrinkle_jax import meshio
from wrinkle_jax.mesh import make_garment
from wrinkle_jax.sim import scenes


def test_variants_change_only_what_they_name():
    walk = scenes.self_collision_config("fine", None, "skirt_walk")
    rec = dataclasses.asdict(walk)
    assert R.variant_settings("recorded", rec, 20) == (walk, 20)
    cfg, n = R.variant_settings("post_passes=3,thickness=0.006", rec, 20)
    assert n == 20 and cfg == dataclasses.replace(walk, post_passes=3, thickness=0.006)
    assert isinstance(cfg.post_passes, int)
    # More substeps keep the rebuild interval in time, as the data set's settings do.
    assert R.variant_settings("substeps=40", rec, 20) == (
        scenes.self_collision_config("fine", 40, "skirt_walk"), 40)
    with pytest.raises(SystemExit, match="post_pases"):
        R.variant_settings("post_pases=3", rec, 20)


def test_jitter_moves_only_the_start_frames_by_the_given_noise():
    rng = np.random.default_rng(0)
    frames = rng.normal(size=(6, 4000, 3)).astype(np.float32)
    tri = np.array([[0, 1, 2]], np.int32)
    garment = make_garment(frames[0], tri, np.zeros((4000, 2), np.float32), tri)
    seq = meshio.make_sequence(frames, garment)
    assert R.jitter_start(seq, 3, 0.0, 1) is seq and R.jitter_start(seq, 3, 1e-3, 0) is seq
    a, b = R.jitter_start(seq, 3, 1e-3, 1), R.jitter_start(seq, 3, 1e-3, 2)
    moved = np.asarray(a.frames) - frames
    np.testing.assert_array_equal(moved[[0, 1, 4, 5]], 0.0)
    assert abs(moved[2:4].std() / 1e-3 - 1) < 0.02 and abs(moved[2:4].mean()) < 5e-5
    assert not np.allclose(a.frames[3], b.frames[3])  # seeds differ
    np.testing.assert_array_equal(R.jitter_start(seq, 3, 1e-3, 1).frames, a.frames)
    np.testing.assert_array_equal(seq.frames, frames)  # the input is left alone
