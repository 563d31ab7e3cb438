"""`wrinkle-jax classify` (motion) and `enhance --material auto` on a tiny synthetic model."""

import json

import numpy as np
import pytest

from wrinkle_jax import MATERIALS
from wrinkle_jax.classifier import calibrated as cal
from wrinkle_jax.classifier import motion


def _sequence(path, frames=40, fps=30.0, skinned=False, body=True, n=6):
    """An n x n sheet hanging from a walking body, flapping (or riding rigidly when skinned)."""
    pitch = 0.05
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    uv = np.stack([i.ravel(), j.ravel()], -1) * pitch
    verts = np.stack([uv[:, 0], np.zeros(n * n), 1.0 - uv[:, 1]], -1)
    idx = (i * n + j)[:-1, :-1].ravel()
    faces = np.concatenate([np.stack([idx, idx + n, idx + 1], -1),
                            np.stack([idx + 1, idx + n, idx + n + 1], -1)])
    t = np.arange(frames) / fps
    walk = np.stack([0.8 * t, 0 * t, 0 * t], -1)
    caps = np.zeros((frames, 2, 2, 3))
    caps[:, :, 0] = walk[:, None] + np.array([[0.1, 0.1, 1.0], [0.2, 0.1, 1.0]])
    caps[:, :, 1] = caps[:, :, 0] + np.array([0.0, 0.0, 0.3])
    flap = 0.1 * (1.0 - verts[None, :, 2:]) * np.sin(2 * np.pi * 2.0 * t)[:, None, None]
    x = verts[None] + walk[:, None] + (0.0 if skinned else flap * np.array([0.0, 1.0, 0.3]))
    arrays = {"frames": x.astype(np.float32), "faces": faces.astype(np.int32),
              "uvs": uv.astype(np.float32), "uv_faces": faces.astype(np.int32),
              "fps": np.float64(fps)}
    if body:
        arrays["capsule_ends"] = caps.astype(np.float32)
    np.savez(path, **arrays)
    return path


@pytest.fixture
def model_path(tmp_path):
    """A model fitted to tell the flapping sheet (label 2) from jittered copies (others)."""
    cfg = cal.MotionConfig(window=16, stride=8, families=("kinematic", "spectral"))
    with np.load(_sequence(tmp_path / "train.npz")) as z:
        topo = motion.make_topology(z["faces"], z["uvs"], z["uv_faces"])
        f = motion.sequence_features(z["frames"], motion.body_reference(z["capsule_ends"]),
                                     topo, 30.0, cfg.window, cfg.stride)
    rng = np.random.default_rng(0)
    feats = np.concatenate([f + rng.normal(0, 0.05, f.shape) + (k != 2) * rng.normal(
        0, 1.0, f.shape[1]) for k in range(5)])
    labels = np.repeat(np.arange(5), len(f))
    model = cal.fit(feats, labels, cfg)._replace(threshold=0.5, novelty_limit=10.0)
    return cal.save(tmp_path / "motion.npz", model)


def test_classify_json_answers_and_abstains(tmp_path, model_path, capsys):
    from wrinkle_jax import cli

    seq = _sequence(tmp_path / "seq.npz")
    assert cli.main(["classify", str(seq), "--json", "--model", str(model_path)]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["material"] == MATERIALS[2] and not out["abstained"]
    assert set(out["scores"]) == set(MATERIALS)
    assert sum(out["scores"].values()) == pytest.approx(1.0)
    # A skinned copy (no dynamics) is unlike the training data: it abstains.
    lbs = _sequence(tmp_path / "lbs.npz", skinned=True)
    assert cli.main(["classify", str(lbs), "--json", "--model", str(model_path)]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["abstained"] and out["material"] is None and out["reason"]
    # No body track: abstains and says why.
    nobody = _sequence(tmp_path / "nobody.npz", body=False)
    assert cli.main(["classify", str(nobody), "--model", str(model_path)]) == 0
    assert "no body track" in capsys.readouterr().out


def test_classify_missing_model_is_an_error(tmp_path, capsys):
    from wrinkle_jax import cli

    seq = _sequence(tmp_path / "seq.npz")
    assert cli.main(["classify", str(seq), "--model", str(tmp_path / "none.npz")]) == 1
    assert "no such motion classifier" in capsys.readouterr().err


def test_material_auto_uses_answer_or_names_the_flag(tmp_path, model_path, monkeypatch):
    from wrinkle_jax import cli_pipeline, validate
    from wrinkle_jax.classifier import synthesis_model

    monkeypatch.setattr(cal, "MOTION_PATH", model_path)
    # no synthesis classifier ships here: the motion classifier answers
    monkeypatch.setattr(synthesis_model, "SYNTHESIS_PATH", tmp_path / "none.npz")
    name, result, kind = cli_pipeline._classify_auto(_sequence(tmp_path / "seq.npz"), MATERIALS)
    assert name == MATERIALS[2] and result.confidence >= 0.5 and kind == "motion"
    with pytest.raises(validate.UsageError, match="abstained.*--material NAME"):
        cli_pipeline._classify_auto(_sequence(tmp_path / "lbs.npz", skinned=True), MATERIALS)


def test_classify_bakes_the_drape_family_when_the_model_uses_it(tmp_path, capsys):
    """A model of the normal-map family alone: classify must bake the input's normal maps
    (drape.make_plan); the family's zeros (no plan) would be far from the training data."""
    from wrinkle_jax import cli
    from wrinkle_jax.classifier import drape

    cfg = cal.MotionConfig(window=16, stride=8, families=("drape",))
    seq = _sequence(tmp_path / "big.npz", n=14)
    with np.load(seq) as z:
        arrays = dict(z)
    t = np.arange(len(arrays["frames"]))[:, None] / 30.0
    arrays["frames"][..., 1] += 0.03 * np.sin(2 * np.pi * arrays["uvs"][None, :, 0] / 0.2
                                              + 3.0 * t)          # a travelling 20 cm fold
    np.savez(seq, **arrays)
    with np.load(seq) as z:
        topo = motion.make_topology(z["faces"], z["uvs"], z["uv_faces"])
        plan = drape.make_plan(z["faces"], z["uvs"], z["uv_faces"], z["frames"][0])
        f = motion.sequence_features(z["frames"], motion.body_reference(z["capsule_ends"]),
                                     topo, 30.0, cfg.window, cfg.stride, drape_plan=plan)
    sl = motion.family_slices()["drape"]
    assert np.all(f[:, sl] != 0.0) and np.all(f[:, sl][:, :3] > -10)  # real band energies
    rng = np.random.default_rng(0)
    feats = np.concatenate([f + rng.normal(0, 0.05, f.shape) + (k != 2) * rng.normal(
        0, 1.0, f.shape[1]) for k in range(5)])
    model = cal.fit(feats, np.repeat(np.arange(5), len(f)), cfg)._replace(
        threshold=0.5, novelty_limit=10.0)
    path = cal.save(tmp_path / "drape_model.npz", model)
    assert cli.main(["classify", str(seq), "--json", "--model", str(path)]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["material"] == MATERIALS[2] and not out["abstained"]


def test_kind_of_a_model_file_reads_it_once(tmp_path, monkeypatch):
    import argparse

    from wrinkle_jax.classifier import cli as ccli
    from wrinkle_jax.classifier import synthesis_model as sm

    cfg = cal.MotionConfig(families=("kinematic",))
    d = len(cfg.columns())
    motion_file = cal.save(tmp_path / "m.npz", cal.MotionClassifier(
        np.zeros((d, 5)), np.zeros(5), np.zeros(d), np.ones(d), 1.0, 0.5, 1.0, cfg))
    patches_file = tmp_path / "p.npz"
    np.savez(patches_file, **{"config.json": np.zeros(2, np.uint8)})
    text = tmp_path / "t.npz"
    text.write_text("not a model")
    truncated = tmp_path / "cut.npz"
    truncated.write_bytes(motion_file.read_bytes()[:100])
    loads = []
    real_load = np.load
    monkeypatch.setattr(np, "load", lambda *a, **k: loads.append(a[0]) or real_load(*a, **k))

    def kind(model, kind=None, vgg=None):
        loads.clear()
        out = ccli._kind(argparse.Namespace(kind=kind, vgg=vgg, model=model and str(model)))
        assert len(loads) <= 1, loads
        return out

    assert kind(sm.SYNTHESIS_PATH) == "synthesis"
    assert kind(motion_file) == "motion" and kind(patches_file) == "patches"
    assert kind(text) == "motion" and kind(truncated) == "motion"  # the loader reports it
    assert kind(tmp_path / "missing.npz") == "motion"
    assert kind(motion_file, kind="synthesis") == "synthesis" and kind(None, vgg="v") == "patches"


def test_a_damaged_compressed_sequence_is_a_classifier_error(tmp_path, model_path):
    """Sequences are written compressed (meshio): a damaged member is reported naming the
    file, not as a zlib.error from inside NumPy."""
    from test_fileio import _deflate_start  # tests/ is on sys.path

    from wrinkle_jax.classifier import cli as classifier_cli
    from wrinkle_jax.classifier.config import ClassifierError

    plain = _sequence(tmp_path / "plain.npz")
    with np.load(plain) as z:
        arrays = {k: z[k] for k in z.files}
    path = tmp_path / "seq.npz"
    np.savez_compressed(path, **arrays)
    assert classifier_cli.classify_motion_input(path, model_path).material == MATERIALS[2]
    data = bytearray(path.read_bytes())
    data[_deflate_start(bytes(data), "frames.npy")] = 0xFF
    path.write_bytes(bytes(data))
    with pytest.raises(ClassifierError, match="seq.npz: cannot read the sequence"):
        classifier_cli.classify_motion_input(path, model_path)


def test_sequence_read_errors_are_reported_and_errors_of_our_own_code_are_not(
        tmp_path, model_path, monkeypatch):
    """Only reading the file is under the damaged-file errors: a sequence without frames is
    unreadable, one whose faces do not fit is malformed, and a bug in the feature code
    propagates instead of being reported as an unreadable sequence."""
    from wrinkle_jax.classifier import cli as classifier_cli
    from wrinkle_jax.classifier import motion
    from wrinkle_jax.classifier.config import ClassifierError

    path = _sequence(tmp_path / "seq.npz")
    with np.load(path) as z:
        arrays = {k: z[k] for k in z.files}
    np.savez(tmp_path / "noframes.npz", **{k: v for k, v in arrays.items() if k != "frames"})
    with pytest.raises(ClassifierError, match="noframes.npz: cannot read the sequence"):
        classifier_cli.classify_motion_input(tmp_path / "noframes.npz", model_path)
    np.savez(tmp_path / "nofaces.npz", **{k: v for k, v in arrays.items() if k != "faces"})
    with pytest.raises(ClassifierError, match="nofaces.npz: malformed sequence"):
        classifier_cli.classify_motion_input(tmp_path / "nofaces.npz", model_path)

    def broken(*a, **k):
        raise RuntimeError("bug in make_topology")

    monkeypatch.setattr(motion, "make_topology", broken)
    with pytest.raises(RuntimeError, match="bug in make_topology"):
        classifier_cli.classify_motion_input(path, model_path)
