"""The "headed" `.npz` layout of the calibrated classifiers (`modelfile.write_headed` /
`read_headed`): files written before the shared helper stay readable and are rewritten member
for member, and bad files get an error naming them."""

from __future__ import annotations

import dataclasses
import json
import zipfile
from pathlib import Path

import numpy as np
import pytest

from wrinkle_jax.classifier import calibrated as cal
from wrinkle_jax.classifier import synthesis_model as sm
from wrinkle_jax.classifier.config import ClassifierError

ROOT = Path(__file__).resolve().parents[1]


def _members(path) -> list:
    """(name, compression, bytes) of every zip member, in order (timestamps left out)."""
    with zipfile.ZipFile(path) as z:
        return [(i.filename, i.compress_type, z.read(i)) for i in z.infolist()]


@pytest.mark.parametrize("path", [
    sm.SYNTHESIS_PATH, ROOT / "experiments/results/classifier/synthesis_classifier_s24c.npz"])
def test_committed_synthesis_classifiers_load_and_save_back_member_for_member(path, tmp_path):
    clf = sm.load(path)
    assert clf.weights is not None and clf.scale.dtype == np.float64
    assert _members(sm.save(tmp_path / "again.npz", clf)) == _members(path)
    assert sm.is_synthesis_file(path)


def _motion_model() -> cal.MotionClassifier:
    config = cal.MotionConfig(families=("kinematic", "lag"), clip=3.0)
    d, m = len(config.columns()), len(config.materials)
    rng = np.random.default_rng(0)
    return cal.MotionClassifier(rng.normal(size=(d, m)), rng.normal(size=m),
                                rng.normal(size=d), rng.uniform(0.5, 2.0, d), 1.7, 0.6, 4.5,
                                config, 0.8)


def test_motion_classifier_file_keeps_its_layout(tmp_path):
    model = _motion_model()
    path = cal.save(tmp_path / "m.npz", model, meta={"seed": 1})
    # the layout as the first writer wrote it: float32 arrays, then the JSON head
    head = {"format": "wrinkle-jax-motion-classifier/1",
            "config": dataclasses.asdict(model.config), "temperature": 1.7, "threshold": 0.6,
            "novelty_limit": 4.5, "group_threshold": 0.8, "meta": {"seed": 1}}
    ref = tmp_path / "ref.npz"
    np.savez(ref, weights=model.weights.astype(np.float32),
             bias=model.bias.astype(np.float32), mean=model.mean.astype(np.float32),
             std=model.std.astype(np.float32),
             head=np.frombuffer(json.dumps(head).encode(), np.uint8))
    assert _members(path) == _members(ref)
    back = cal.load(ref)
    assert back.config == model.config and back.group_threshold == 0.8
    np.testing.assert_array_equal(back.weights, model.weights.astype(np.float32))


def test_bad_headed_files_name_the_file(tmp_path):
    good = cal.save(tmp_path / "good.npz", _motion_model())
    with pytest.raises(ClassifierError, match="missing.npz: no such motion classifier file"):
        cal.load(tmp_path / "missing.npz")
    with pytest.raises(ClassifierError, match="no such synthesis classifier file"):
        sm.load(tmp_path / "missing.npz")
    truncated = tmp_path / "truncated.npz"
    truncated.write_bytes(good.read_bytes()[:200])
    empty = tmp_path / "empty.npz"
    empty.write_bytes(b"")
    other = tmp_path / "other.npz"
    np.savez(other, head=np.frombuffer(b'{"format": "other/1"}', np.uint8), scale=np.ones(2))
    listed = tmp_path / "listed.npz"
    np.savez(listed, head=np.frombuffer(b'["format"]', np.uint8))
    for bad in (truncated, empty, other, listed):
        with pytest.raises(ClassifierError, match=f"{bad.name}: not a readable motion"):
            cal.load(bad)
        with pytest.raises(ClassifierError, match=f"{bad.name}: not a readable synthesis"):
            sm.load(bad)
        assert not sm.is_synthesis_file(bad)
    with pytest.raises(ClassifierError, match="expected 'wrinkle-jax-synthesis"):
        sm.load(good)
    # a head the classifier refuses (a field it does not have) is unreadable, not a crash
    clf = sm.load(sm.SYNTHESIS_PATH)
    with np.load(sm.save(tmp_path / "s.npz", clf)) as z:
        arrays = {k: z[k] for k in z.files}
    head = json.loads(bytes(arrays["head"]).decode())
    arrays["head"] = np.frombuffer(json.dumps({**head, "colour": 1}).encode(), np.uint8)
    np.savez(tmp_path / "extra.npz", **arrays)
    with pytest.raises(ClassifierError, match="extra.npz: not a readable synthesis"):
        sm.load(tmp_path / "extra.npz")
