"""Tests for experiments/self_collision_restart.py's variant settings (the runs themselves need
the data set; `sim.scenes.resimulate` is tested in test_sim_scenes)."""

from __future__ import annotations

import dataclasses

import pytest

from experiments import self_collision_restart as R
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
