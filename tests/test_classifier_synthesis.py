"""Analysis-by-synthesis material classifier (wrinkle_jax.classifier.synthesis): a tiny skirt
scene (PD 0.1 m, 211 vertices, 24 frames, 4 substeps, the mannequin dancing)."""

from __future__ import annotations

import dataclasses
import json

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


def _tiny_classifier(**changes):
    from wrinkle_jax.classifier import synthesis_model as sm

    fams = ("kinematic", "curvature", "rigidity")
    d = int(syn.feature_mask(fams).sum())
    kw = dict(materials=("wool_melton", "silk_chiffon"), families=fams, agg="window",
              scale=np.ones(d), weights=None, temperature=1e-3, threshold=0.6,
              group_threshold=0.6, novelty_limit=1e9, solver="fixed", substeps=SUBSTEPS,
              frames=FRAMES, settle_frames=4, window=8, stride=4, meta={"test": True})
    return sm.SynthesisClassifier(**{**kw, **changes})


def test_saved_synthesis_classifier_answers_like_the_study(tiny, tmp_path, capsys):
    from wrinkle_jax.classifier import cli as ccli
    from wrinkle_jax.classifier import synthesis_model as sm

    _, _, arrays = tiny
    clf = _tiny_classifier()
    for m, a in arrays.items():
        r = sm.classify(a, clf)
        assert r.material == m and not r.abstained and r.num_windows == 5
    # "input" falls back to the fixed substeps when the file records no solver
    r_in = sm.classify(arrays["silk_chiffon"], _tiny_classifier(solver="input"))
    assert r_in.scores == sm.classify(arrays["silk_chiffon"], clf).scores
    # a round trip through the file, then the CLI picks the kind from the file
    path = sm.save(tmp_path / "clf.npz", clf)
    back = sm.load(path)
    assert back.families == clf.families and back.meta == {"test": True}
    np.testing.assert_array_equal(back.scale, clf.scale)
    assert back.weights is None and back.solver == "fixed" and back.frames == FRAMES
    seq = tmp_path / "in.npz"
    np.savez(seq, **arrays["wool_melton"])
    capsys.readouterr()
    assert ccli.main(["classify", str(seq), "--model", str(path), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["classifier"] == "synthesis" and out["material"] == "wool_melton"


def test_synthesis_decisions_and_file_errors(tmp_path, capsys, monkeypatch):
    from wrinkle_jax.classifier import cli as ccli
    from wrinkle_jax.classifier import synthesis_model as sm
    from wrinkle_jax.classifier.config import ClassifierError

    clf = _tiny_classifier(materials=("silk_charmeuse", "wool_melton", "knit_terry",
                                      "silk_chiffon", "denim_light"), temperature=1.0,
                           threshold=0.9, novelty_limit=1.0, weights=np.arange(1.0, 1.0 + len(
                               _tiny_classifier().scale)))
    d = np.array([0.0, 5.0, 5.0, 5.0, 5.0])  # p_0 = 1 / (1 + 4 e^-5) = 0.97376
    r = sm.decide(clf, d, 3)
    assert r.material == "silk_charmeuse"
    assert r.confidence == pytest.approx(1.0 / (1.0 + 4.0 * np.exp(-5.0)), rel=1e-12)
    assert r.group == "light_silk"
    assert sm.decide(dataclasses.replace(clf, threshold=0.99), d, 3).reason.startswith("low")
    far = sm.decide(clf, d + 2.0, 3)  # nearest synthesis 2 > limit 1: nothing reproduces it
    assert far.abstained and far.material is None and far.group is None and far.novelty == 2.0
    # an input without pins abstains, saying why
    a = {"frames": np.zeros((30, 3, 3)), "faces": np.zeros((1, 3), int),
         "uvs": np.zeros((3, 2)), "uv_faces": np.zeros((1, 3), int)}
    assert "pin" in sm.classify(a, clf).reason
    path = sm.save(tmp_path / "w.npz", clf)
    np.testing.assert_array_equal(sm.load(path).weights, clf.weights)
    with pytest.raises(ClassifierError, match="do not match"):
        dataclasses.replace(clf, scale=np.ones(3))
    bad = tmp_path / "bad.npz"
    np.savez(bad, head=np.frombuffer(b'{"format": "other"}', np.uint8), scale=np.ones(2))
    with pytest.raises(ClassifierError, match="bad.npz"):
        sm.load(bad)
    assert not sm.is_synthesis_file(bad) and sm.is_synthesis_file(path)
    monkeypatch.setattr(sm, "SYNTHESIS_PATH", tmp_path / "none.npz")  # none ships here
    assert ccli.main(["classify", str(bad), "--kind", "synthesis"]) == 1
    assert "no synthesis classifier ships" in capsys.readouterr().err


def test_a_shipped_synthesis_classifier_answers_material_auto(tiny, tmp_path, monkeypatch,
                                                              capsys):
    from wrinkle_jax import cli_pipeline, validate
    from wrinkle_jax.classifier import cli as ccli
    from wrinkle_jax.classifier import synthesis_model as sm

    _, _, arrays = tiny
    seq = tmp_path / "in.npz"
    np.savez(seq, **arrays["silk_chiffon"])
    names = ("wool_melton", "silk_chiffon")
    monkeypatch.setattr(sm, "SYNTHESIS_PATH", sm.save(tmp_path / "ship.npz", _tiny_classifier()))
    assert ccli.default_kind() == "synthesis"
    name, result, kind = cli_pipeline._classify_auto(seq, names)
    assert (name, kind) == ("silk_chiffon", "synthesis") and not result.abstained
    capsys.readouterr()
    assert ccli.main(["classify", str(seq), "--json"]) == 0  # no --model: the shipped one
    assert json.loads(capsys.readouterr().out)["classifier"] == "synthesis"
    sm.save(sm.SYNTHESIS_PATH, _tiny_classifier(novelty_limit=-1.0))  # reproduces nothing
    with pytest.raises(validate.UsageError, match="abstained.*--material NAME"):
        cli_pipeline._classify_auto(seq, names)
