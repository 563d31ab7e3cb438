"""Tests for the material classifier: learning, voting, sampling, files and the CLI."""

from __future__ import annotations

import dataclasses
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from wrinkle_jax import MATERIALS, classifier, normalmap, primitives
from wrinkle_jax.classifier import cli as classify_cli
from wrinkle_jax.classifier import training as classify_train
from wrinkle_jax.meshio import make_sequence, save_sequence
from wrinkle_jax.nn import vgg

SIZE = 32
CONFIG = classifier.ClassifierConfig(feature="relu2_1:stats", hidden=(16, 16, 16), dropout=0.1,
                                     patch_size=SIZE, texel_size=0.004)


def key(seed):
    return jax.random.key(seed, impl="rbg")


@pytest.fixture(scope="module")
def tiny_vgg():
    return vgg.init_vgg19(key(0), widths=(4, 8, 8, 8, 8), num_convs=4,
                          spec=vgg.VGGSpec("custom", "REFLECT"))


@pytest.fixture(scope="module")
def tiny_clf(tiny_vgg):
    return classifier.init_classifier(key(1), CONFIG, tiny_vgg)


def wave_patches(rng, labels, size=SIZE):
    """RGB-form normal maps of height waves whose frequency depends on the label.

    h = a sin(2 pi f (x cos t + y sin t) + phase), f = (2, 5, 10)[label] cycles per patch,
    random direction t, phase and amplitude; normals (-dh/dx, -dh/dy, 1) normalized.
    """
    yy, xx = np.mgrid[0:size, 0:size] / size
    out = []
    for lab in labels:
        f = (2.0, 5.0, 10.0)[lab]
        t, ph = rng.uniform(0, np.pi), rng.uniform(0, 2 * np.pi)
        a = rng.uniform(0.3, 0.6) / (2 * np.pi * f)  # slope amplitude ~0.3-0.6 for all f
        arg = 2 * np.pi * f * (xx * np.cos(t) + yy * np.sin(t)) + ph
        g = a * 2 * np.pi * f * np.cos(arg)
        n = np.stack([-g * np.cos(t), -g * np.sin(t), np.ones_like(g)], -1)
        n /= np.linalg.norm(n, axis=-1, keepdims=True)
        out.append((n + 1) / 2)
    return np.asarray(out, np.float32)


def test_learns_a_separable_synthetic_case(tiny_vgg):
    rng = np.random.default_rng(0)
    cfg = classifier.ClassifierConfig(feature="relu2_1:stats", hidden=(32, 32, 16),
                                      dropout=0.1, materials=MATERIALS[:3], patch_size=SIZE)
    feats = jax.jit(classifier.patch_features, static_argnames=("features", "conv_impl"))

    def make(n):
        labels = rng.integers(0, 3, n)
        rgb = wave_patches(rng, labels)
        raw = feats(tiny_vgg, jnp.asarray(rgb), jnp.ones((n, SIZE, SIZE, 1)),
                    features=(cfg.feature,))[cfg.feature]
        return np.asarray(raw), labels

    x, y = make(144)  # one feature call (one compile), then split
    x_train, y_train, x_test, y_test = x[:96], y[:96], x[96:], y[96:]
    clf, history = classifier.train_classifier(x_train.astype(np.float16), y_train, cfg, key(2),
                                               tiny_vgg, steps=200, batch_size=32,
                                               learning_rate=3e-3, eval_every=50)
    assert [h["step"] for h in history] == [50, 100, 150, 200]
    probs = np.asarray(classifier.predict_from_features(clf, x_test))
    np.testing.assert_allclose(probs.sum(1), 1.0, rtol=1e-5)
    acc = np.mean(np.argmax(probs, 1) == y_test)
    assert acc >= 0.9, acc


def test_probabilities_and_cross_entropy():
    logits = jnp.array([[0.0, 0.0], [50.0, -50.0], [-200.0, -200.0]])
    p = classifier.probabilities(logits)
    np.testing.assert_allclose(p.sum(1), 1.0, rtol=1e-6)
    np.testing.assert_allclose(p[0], [0.5, 0.5])
    np.testing.assert_allclose(p[2], [0.5, 0.5])  # underflowed sigmoids stay finite
    ce = jax.jit(classifier.cross_entropy)(logits, jnp.array([0, 0, 1]))
    want = -np.log(np.asarray(p)[[0, 1, 2], [0, 0, 1]])
    np.testing.assert_allclose(ce, want, rtol=1e-5, atol=1e-6)
    assert np.isfinite(np.asarray(ce)).all()


def test_vote_on_hand_made_probabilities():
    # Material 1 is the runner-up in most patches but near-certain in a third of them;
    # material 0 leads narrowly elsewhere. Histograms (Fig. 6) put m1's mass higher overall.
    probs = np.array([[0.40, 0.35, 0.10, 0.10, 0.05]] * 6 + [[0.02, 0.95, 0.01, 0.01, 0.01]] * 3)
    scores, hist, edges = classifier.vote(probs, bins=10)
    assert hist.shape == (5, 10) and edges.shape == (11,)
    np.testing.assert_array_equal(hist.sum(1), 9)
    assert hist[1, 9] == 3 and hist[1, 3] == 6 and hist[0, 4] == 6 and hist[0, 0] == 3
    np.testing.assert_allclose(scores.sum(), 1.0)
    assert int(np.argmax(scores)) == 1
    # Majority of argmaxes picks material 0 (6 of 9 patches) instead.
    maj, _, _ = classifier.vote(probs, bins=10, method="majority")
    np.testing.assert_allclose(maj, [6 / 9, 3 / 9, 0, 0, 0])
    # p == 1.0 falls into the last bin; one patch still answers.
    s1, h1, _ = classifier.vote(np.array([[0.0, 1.0, 0.0, 0.0, 0.0]]), bins=4)
    assert h1[1, 3] == 1 and int(np.argmax(s1)) == 1
    with pytest.raises(classifier.ClassifierError, match="N >= 1"):
        classifier.vote(np.zeros((0, 5)))


def _sheet_frames(size, n_cells, frames=6):
    g = primitives.grid_sheet(n_cells, n_cells, size=(size, size))
    xy = np.asarray(g.vertices)[:, :2]
    seq = [np.c_[xy, 0.01 * np.sin(40 * xy[:, 0] + 0.5 * t) * np.cos(30 * xy[:, 1])]
           for t in range(frames)]
    return g, np.asarray(seq, np.float32)


@pytest.fixture(scope="module")
def sheet_seq():
    # One garment for the sequence and CLI tests: the jitted bake-and-crop compiles once.
    return _sheet_frames(0.3, 24)


def test_classify_sequence_is_deterministic_for_a_key(tiny_clf, sheet_seq):
    g, frames = sheet_seq
    a = classifier.classify_sequence(tiny_clf, frames, g, key(5), patches_per_frame=2,
                                     num_frames=4)
    b = classifier.classify_sequence(tiny_clf, frames, g, key(5), patches_per_frame=2,
                                     num_frames=4)
    c = classifier.classify_sequence(tiny_clf, frames, g, key(6), patches_per_frame=2,
                                     num_frames=4)
    assert a.num_patches == 8 and a.patch_probs.shape == (8, 5)
    assert a.material in MATERIALS and set(a.scores) == set(MATERIALS)
    assert abs(sum(a.scores.values()) - 1.0) < 1e-9
    np.testing.assert_array_equal(a.patch_probs, b.patch_probs)
    assert a.scores == b.scores and a.material == b.material
    assert not np.array_equal(a.patch_probs, c.patch_probs)
    assert sorted(set(a.frame_ids.tolist())) == [0, 2, 3, 5]  # spread over time
    assert a.histogram.sum() == 8 * 5
    json.dumps(a.to_json())
    with pytest.raises(classifier.ClassifierError, match=r"frames must be \(T, 625, 3\)"):
        classifier.classify_sequence(tiny_clf, frames[:, :10], g, key(5))


def test_few_valid_patches_still_answer_and_none_raises(tiny_clf):
    # A 0.13 m sheet at 4 mm/texel is ~33 texels wide: a 32-texel patch needs a near-full
    # garment at 90% coverage, so only a handful of origins are valid.
    g, frames = _sheet_frames(0.13, 10, frames=3)
    strict = tiny_clf._replace(config=dataclasses.replace(CONFIG, min_coverage=0.9))
    plan = normalmap.make_plan(g, texel_size=CONFIG.texel_size)
    n_valid = classifier.valid_origin_count(plan.mask, SIZE, 0.9)
    assert 1 <= n_valid <= 30, n_valid  # of ~40x40 origins
    res = classifier.classify_sequence(strict, frames, g, key(0), patches_per_frame=4,
                                       num_frames=3)
    assert res.num_patches == 12 and res.material in MATERIALS
    # A 2 cm square garment has no 32x32 patch with 9% of its texels on the garment.
    tiny, tiny_frames = _sheet_frames(0.02, 2, frames=2)
    with pytest.raises(ValueError, match="nothing to classify"):
        classifier.classify_sequence(tiny_clf, tiny_frames, tiny, key(0))


def test_save_load_round_trip(tmp_path, tiny_clf, tiny_vgg):
    rng = np.random.default_rng(3)
    clf = tiny_clf._replace(norm={"mean": jnp.asarray(rng.normal(size=16), jnp.float32),
                                  "std": jnp.asarray(rng.uniform(0.5, 2, 16), jnp.float32)},
                            meta={"note": "test"})
    path = classifier.save_classifier(tmp_path / "c.npz", clf, meta={"acc": 0.5})
    assert path.stat().st_size < 2 << 20
    back = classifier.load_classifier(path, vgg_params=tiny_vgg)
    assert back.config == clf.config
    assert back.meta["note"] == "test" and back.meta["acc"] == 0.5
    raw = rng.uniform(0, 3, (8, 16)).astype(np.float32)
    np.testing.assert_allclose(classifier.predict_from_features(back, raw),
                               classifier.predict_from_features(clf, raw), atol=2e-3)
    with np.load(path, allow_pickle=False) as z:  # plain arrays, no pickle
        assert all(z[k].dtype != object for k in z.files)
    (tmp_path / "bad.npz").write_bytes(b"not a zip")
    with pytest.raises(classifier.ClassifierError, match="bad.npz: not a readable"):
        classifier.load_classifier(tmp_path / "bad.npz", vgg_params=tiny_vgg)
    with pytest.raises(classifier.ClassifierError, match="no such classifier file"):
        classifier.load_classifier(tmp_path / "missing.npz", vgg_params=tiny_vgg)
    other = vgg.init_vgg19(key(0), widths=(4, 6, 8, 8, 8), num_convs=4,
                           spec=vgg.VGGSpec("custom", "REFLECT"))
    with pytest.raises(classifier.ClassifierError, match="do not match"):
        classifier.load_classifier(path, vgg_params=other)


def test_feature_shapes(tiny_vgg):
    x = jnp.full((2, SIZE, SIZE, 3), 0.5)
    m = jnp.ones((2, SIZE, SIZE, 1))
    specs = ("relu1_2:grid4", "relu2_1:stats", "relu2_1:grid4")
    out = jax.jit(classifier.patch_features, static_argnames="features")(tiny_vgg, x, m, specs)
    for s in specs:
        assert out[s].shape == (2, classifier.feature_dim(tiny_vgg, s, SIZE))
    assert out["relu2_1:stats"].shape == (2, 16)
    with pytest.raises(ValueError, match="feature must look like"):
        classifier.ClassifierConfig(feature="relu2_1")


@pytest.fixture(scope="module")
def cli_files(tmp_path_factory, tiny_vgg, tiny_clf, sheet_seq):
    root = tmp_path_factory.mktemp("cli")
    vgg_path = root / "tiny_vgg.npz"
    vgg._save_npz_atomic(vgg._to_flat_npz(tiny_vgg), vgg_path)
    model = classifier.save_classifier(root / "model.npz", tiny_clf)
    g, frames = sheet_seq
    seq = root / "seq.npz"
    save_sequence(seq, make_sequence(frames, g))
    return {"vgg": vgg_path, "model": model, "seq": seq, "root": root}


def test_cli_classify_exit_codes(cli_files, capsys):
    f = cli_files
    common = ["--model", str(f["model"]), "--vgg", str(f["vgg"]), "--num-frames", "2",
              "--patches-per-frame", "2"]
    assert classify_cli.main(["classify", str(f["seq"]), "--json", *common]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["material"] in MATERIALS and out["num_patches"] == 4
    assert set(out["histogram"]) == set(MATERIALS)
    assert classify_cli.main(["classify", str(f["seq"]), *common]) == 0
    text = capsys.readouterr().out
    assert text.startswith("material: ") and "score" in text
    assert classify_cli.main(["classify", str(f["root"] / "nope.npz"), *common]) == 1
    assert "nope.npz" in capsys.readouterr().err
    bad = ["--model", str(f["root"] / "missing.npz"), "--vgg", str(f["vgg"])]
    assert classify_cli.main(["classify", str(f["seq"]), *bad]) == 1
    assert "no such classifier file" in capsys.readouterr().err
    with pytest.raises(SystemExit) as e:
        classify_cli.main(["classify", str(f["seq"]), "--patches-per-frame", "0"])
    assert e.value.code == 2


def test_cli_train_classifier(cli_files, sheet_seq, tmp_path, capsys):
    data = tmp_path / "seqs"
    g, frames = sheet_seq
    for mat, amp in (("silk_charmeuse", 1.0), ("denim_light", 3.0)):
        seq = make_sequence(frames * np.array([1, 1, amp], np.float32), g,
                            metadata={"material": mat, "garment": "sheet", "motion": "wind"})
        save_sequence(data / "sheet_wind" / f"{mat}_coarse_s0.npz", seq)
    out = tmp_path / "clf.npz"
    args = ["train-classifier", "--data", str(data), "--out", str(out), "--steps", "5",
            "--vgg", str(cli_files["vgg"]), "--feature", "relu2_1:stats", "--num-frames", "2",
            "--patches-per-frame", "2", "--variants", "coarse", "--patch-size", str(SIZE),
            "--texel-size", "0.004"]
    assert classify_cli.main(args) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["patches"] == 8
    assert classifier.load_classifier(out, vgg_params=vgg.load_vgg19(cli_files["vgg"])) \
        .config.feature == "relu2_1:stats"
    feats, labels, entries = classify_train.load_cache(tmp_path / "clf" / "features",
                                                       "relu2_1:stats", split="train")
    assert feats.dtype == np.float16 and feats.shape == (8, 16)
    assert sorted(set(labels.tolist())) == [0, 4] and len(entries) == 2
    (tmp_path / "empty").mkdir()
    assert classify_cli.main(["train-classifier", "--data", str(tmp_path / "empty"), "--out",
                              str(tmp_path / "x.npz")]) == 1


def test_patch_frame_turns_the_mean_normal_to_z():
    rng = np.random.default_rng(4)
    n = rng.normal(size=(3, 8, 8, 3))
    n[..., 2] += 2.0 * np.sign(rng.normal(size=(3, 1, 1)))  # means near +z and -z
    n[2] = (0.0, 0.0, -1.0)  # exactly -z: the half-turn branch
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    m = np.ones((3, 8, 8, 1))
    m[:, :2] = 0.0
    out = np.asarray(jax.jit(classifier.to_patch_frame)(jnp.asarray(n * m, jnp.float32),
                                                        jnp.asarray(m, jnp.float32)))
    mean = (out * m).sum((1, 2))
    np.testing.assert_allclose(mean / np.linalg.norm(mean, axis=-1, keepdims=True),
                               np.tile([0.0, 0.0, 1.0], (3, 1)), atol=1e-5)
    np.testing.assert_allclose(np.linalg.norm(out, axis=-1), m[..., 0], atol=1e-5)
    # Angles between normals are kept (a rotation).
    np.testing.assert_allclose(np.einsum("nhwc,nc->nhw", out, out[:, 4, 4]),
                               np.einsum("nhwc,nc->nhw", n * m, n[:, 4, 4]), atol=1e-5)
