"""experiments.classifier_motion: the study refuses sequences simulated with different solver
settings (the classifier would learn the solver, not the fabric) and keys its cache by them."""

import json

import numpy as np
import pytest

from experiments import classifier_motion
from wrinkle_jax.sim import scenes


def _fake(path, substeps, contacts):
    path.parent.mkdir(parents=True, exist_ok=True)
    meta = {"substeps": substeps, "self_collision": {"thickness": 0.009} if contacts else None}
    np.savez(path, metadata=np.str_(json.dumps(meta)))


def test_sim_settings_key(tmp_path):
    _fake(tmp_path / "a.npz", 80, True)
    _fake(tmp_path / "b.npz", 20, False)
    np.savez(tmp_path / "c.npz", frames=np.zeros(1))
    assert classifier_motion.sim_settings(tmp_path / "a.npz") == "sub80_sc"
    assert classifier_motion.sim_settings(tmp_path / "b.npz") == "sub20"
    assert classifier_motion.sim_settings(tmp_path / "c.npz") == "sub?"


def test_build_cache_refuses_mixed_settings(tmp_path):
    train, heldout, cache = tmp_path / "train", tmp_path / "heldout", tmp_path / "cache"
    _fake(train / scenes.TRAINING_SCENES[0] / "silk_charmeuse_coarse_s0.npz", 20, True)
    _fake(heldout / "dress_dance" / "silk_charmeuse_coarse_s1.npz", 80, True)
    with pytest.raises(SystemExit, match="different solver settings"):
        classifier_motion.build_cache(train, heldout, cache, None)
    assert not cache.exists()  # refused before any feature was computed
