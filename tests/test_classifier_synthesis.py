"""Analysis-by-synthesis material classifier (wrinkle_jax.classifier.synthesis): a tiny skirt
scene (PD 0.1 m, 211 vertices, 24 frames, 4 substeps, the mannequin dancing)."""

from __future__ import annotations

import dataclasses

import jax
import numpy as np
import pytest

from wrinkle_jax.classifier import synthesis as syn
from wrinkle_jax.sim import scenes, xpbd

SUBSTEPS = 4
FRAMES = 24


def _scene():
    # A short pre-roll keeps the test fast; the body moves from frame 0 on.
    return dataclasses.replace(scenes.get_scene("skirt_dance"), preroll_s=0.2, attach_s=0.1)


def _arrays(seq) -> dict:
    g = seq.garment
    out = {"frames": np.asarray(seq.frames), "faces": np.asarray(g.faces),
           "uvs": np.asarray(g.uvs), "uv_faces": np.asarray(g.uv_faces),
           "panels": np.asarray(g.panels), "fps": np.float64(seq.fps),
           "metadata": np.array('{"uv_units": "meters"}')}
    out.update({k: np.asarray(v) for k, v in seq.tracks.items()})
    return out


@pytest.fixture(scope="module")
def tiny():
    sc = _scene()
    setup = scenes.setup_scene(sc, 0.1, FRAMES)
    seqs = {m: scenes.simulate(sc, m, 0.1, frames=FRAMES, substeps=SUBSTEPS, setup=setup)
            for m in ("wool_melton", "silk_chiffon")}
    return sc, setup, {m: _arrays(s) for m, s in seqs.items()}


def test_own_fabric_and_state_reproduce_the_input(tiny):
    sc, setup, arrays = tiny
    a = arrays["wool_melton"]
    # The solver state at the input's frame 0: the scene's pre-roll, run the same way.
    cfg = xpbd.SimConfig(fps=30.0, substeps=SUBSTEPS, stretch_sweeps=sc.stretch_sweeps)
    init_fn, _ = xpbd.cloth_simulator(cfg)
    state0 = init_fn(setup.model, setup.mesh.garment.vertices)
    pre = jax.tree_util.tree_map(lambda x: x[:setup.preroll_frames + 1], setup.drives)
    state, _ = xpbd.simulate_frames(cfg, setup.model, xpbd.fabric_params(
        syn.fabric("wool_melton")), state0, pre)
    np.testing.assert_allclose(np.asarray(state.x), a["frames"][0], atol=1e-6)
    config = syn.SynthesisConfig(frames=FRAMES, settle_frames=0, substeps=SUBSTEPS)
    x = syn.synthesize(a, "wool_melton", config, start=(state.x, state.v))
    assert x.shape == a["frames"].shape
    np.testing.assert_allclose(x, a["frames"], atol=2e-5)
    # Another fabric from the same state moves differently.
    y = syn.synthesize(a, "silk_chiffon", config, start=(state.x, state.v))
    assert np.abs(y[-1] - a["frames"][-1]).max() > 1e-3


def test_right_fabric_is_nearest_on_a_tiny_two_fabric_case(tiny):
    _, _, arrays = tiny
    config = syn.SynthesisConfig(frames=FRAMES, settle_frames=4, substeps=SUBSTEPS)
    mask = syn.feature_mask(("kinematic", "curvature", "rigidity"))
    names = ("wool_melton", "silk_chiffon")
    d = {}
    for m, a in arrays.items():
        fab = {n: syn.fabric(n) for n in names}
        synth = syn.synthesize_all(a, config, fab)
        fi = syn.window_features(a, a["frames"], window=8, stride=4)
        fs = np.stack([syn.window_features(a, synth[n], window=8, stride=4) for n in names])
        d[m] = syn.distances(syn.differences(fi, fs)[..., mask], np.ones(mask.sum()))
    assert d["wool_melton"].argmin() == 0 and d["silk_chiffon"].argmin() == 1


def test_a_shift_common_to_input_and_syntheses_cancels():
    rng = np.random.default_rng(0)
    x, s = rng.normal(size=(5, 7)), rng.normal(size=(3, 5, 7))
    shift = rng.normal(size=7) * 10  # a garment/motion offset, the same in both
    scale = rng.uniform(0.5, 2.0, 7)
    d0 = syn.distances(syn.differences(x, s), scale)
    d1 = syn.distances(syn.differences(x + shift, s + shift), scale)
    np.testing.assert_allclose(d0, d1, rtol=1e-10)
    assert d0.shape == (3,) and np.all(d0 > 0)
    # The input's own synthesis is at distance 0; probabilities favour it.
    d = syn.distances(syn.differences(x, np.concatenate([s, x[None]])), scale)
    assert d[-1] == 0 and syn.scores_to_probs(d, 1.0).argmax() == 3
    with pytest.raises(ValueError):
        syn.differences(x, s[:, :4])


def test_inputs_without_pins_or_pattern_are_refused():
    a = {"frames": np.zeros((4, 3, 3)), "faces": np.zeros((1, 3), int),
         "uvs": np.zeros((3, 2)), "uv_faces": np.zeros((1, 3), int)}
    assert "pin" in syn.check_input(a)
    with pytest.raises(syn.SynthesisError):
        syn.build_model(a)
    a.update(pins=np.zeros((4, 1, 3)), pin_vertices=np.zeros(1, int),
             metadata=np.array('{"uv_units": "texture"}'))
    assert "meters" in syn.check_input(a)


def test_scaled_fabric_and_metadata_config():
    f = syn.scaled_fabric("denim_light", density=1.25, stiffness=0.8)
    base = syn.fabric("denim_light")
    assert f.density == pytest.approx(1.25 * base.density)
    assert f.stretch == pytest.approx(0.8 * base.stretch)
    assert f.bending == pytest.approx(0.8 * base.bending) and f.damping == base.damping
    meta = {"substeps": 80, "stretch_sweeps": 2,
            "self_collision": dataclasses.asdict(scenes.self_collision_config("coarse", 80))}
    c = syn.config_from_metadata(meta, frames=10)
    assert c.substeps == 80 and c.frames == 10 and c.self_collision.rebuild_every == 16


def test_fitted_weights_pick_the_informative_feature():
    rng = np.random.default_rng(1)
    s_count, m, d = 60, 5, 4
    labels = rng.integers(0, m, s_count)
    q = rng.uniform(0.5, 1.5, (s_count, m, d))  # features 1-3: noise
    q[:, :, 0] = 1.0
    q[np.arange(s_count), labels, 0] = 0.0      # feature 0: zero only for the true fabric
    w = syn.fit_weights(q, labels, l2=1e-3)
    assert w.shape == (d,) and np.all(w >= 0) and w[0] > 3 * w[1:].max()
    assert np.mean((q @ w).argmin(1) == labels) == 1.0
    np.testing.assert_allclose(syn.mean_squares(np.ones((2, 3, 4)), 2.0, "mean"), 0.25)
