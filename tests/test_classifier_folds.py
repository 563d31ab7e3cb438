"""Cross-validation folds of the motion classifier study leave out one GARMENT (all its
scenes) at a time; the garment of a scene comes from the scene definitions."""

import doctest

import numpy as np
import pytest

from experiments import classifier_motion
from wrinkle_jax.classifier import calibrated as cal
from wrinkle_jax.classifier import folds
from wrinkle_jax.classifier.motion import FEATURE_DIM
from wrinkle_jax.sim import scenes

STUDY_SCENES = scenes.TRAINING_SCENES + scenes.VAL_SCENES  # what the study trains on


def _fake_scene(name, garment):
    return scenes.SceneConfig(name, garment, "dance", "waist", "pelvis")


def test_grouping_follows_scene_definitions_not_names():
    # Names that mislead: a name-based grouping would pair a_dance with a_dance2.
    table = {s.name: s for s in (_fake_scene("a_dance", "x"), _fake_scene("b_walk", "x"),
                                 _fake_scene("a_dance2", "y"))}
    assert folds.garment_groups(["a_dance", "a_dance2", "b_walk"], table) == {
        "x": ("a_dance", "b_walk"), "y": ("a_dance2",)}
    fs = folds.leave_one_garment_out(["a_dance", "a_dance2", "b_walk"], table)
    assert fs == [folds.Fold("x", ("a_dance2",), ("a_dance", "b_walk")),
                  folds.Fold("y", ("a_dance", "b_walk"), ("a_dance2",))]
    with pytest.raises(scenes.SceneError, match="unknown scene 'c_run'"):
        folds.scene_garments(["a_dance", "c_run"], table)


def test_study_scenes_group_by_garment():
    g = folds.garment_groups(STUDY_SCENES)
    assert g["flared_skirt"] == ("skirt_dance", "skirt_dance2")
    assert g["apron"] == ("apron_dance", "apron_dance2")
    # shawl and long_shawl are different garments in the catalogue, so different folds.
    assert g["shawl"] == ("shawl_dance2",) and g["long_shawl"] == ("long_shawl_dance",)
    assert len(g) == 8 and sorted(sum(g.values(), ())) == sorted(STUDY_SCENES)
    assert doctest.testmod(folds, raise_on_error=False).failed == 0


def test_no_fold_has_a_garment_on_both_sides():
    garment = folds.scene_garments(STUDY_SCENES)
    fs = folds.leave_one_garment_out(STUDY_SCENES)
    assert sorted(s for f in fs for s in f.validate) == sorted(STUDY_SCENES)  # each once
    for f in fs:
        assert {garment[s] for s in f.validate} == {f.group}
        assert f.group not in {garment[s] for s in f.train}
        assert sorted(f.train + f.validate) == sorted(STUDY_SCENES)
    # The old protocol leaks: leaving out skirt_dance keeps skirt_dance2 in training.
    old = {f.group: f for f in folds.leave_one_scene_out(STUDY_SCENES)}
    assert len(old) == len(STUDY_SCENES) and "skirt_dance2" in old["skirt_dance"].train


def test_study_cross_validation_fits_without_the_validated_garment(monkeypatch):
    """The study's cross_validate, with the model replaced by a recorder: every fit sees no
    scene of the garment it is then asked to predict."""
    idx = {s: i for i, s in enumerate(STUDY_SCENES)}
    train = [{"scene": s, "material": "silk_chiffon", "label": 3,
              "features": np.full((2, FEATURE_DIM), float(idx[s]))} for s in STUDY_SCENES]
    fitted, predicted = [], []

    def fake_fit(x, y, config):
        fitted.append({STUDY_SCENES[int(v)] for v in np.unique(x[:, 0])})
        return len(fitted) - 1

    def fake_log_probs(model, f):
        predicted.append((model, STUDY_SCENES[int(f[0, 0])]))
        return np.log(np.full((len(f), 5), 0.2))

    monkeypatch.setattr(cal, "fit", fake_fit)
    monkeypatch.setattr(cal, "window_log_probs", fake_log_probs)
    monkeypatch.setattr(cal, "novelty", lambda model, f: 0.0)
    cv = classifier_motion.cross_validate(train, cal.MotionConfig())
    garment = folds.scene_garments(STUDY_SCENES)
    assert len(fitted) == 8 and len(cv["labels"]) == len(STUDY_SCENES)
    assert sorted(s for _, s in predicted) == sorted(STUDY_SCENES)
    for model, scene in predicted:
        assert garment[scene] not in {garment[s] for s in fitted[model]}
        assert fitted[model] == {s for s in STUDY_SCENES if garment[s] != garment[scene]}
    assert len(classifier_motion.make_folds(train, "scene")) == len(STUDY_SCENES)
    with pytest.raises(ValueError, match="garment"):
        classifier_motion.make_folds(train, "material")


def test_best_per_set_uses_the_study_rule():
    rows = [{"families": ["a"], "l2": 1, "clip": 0, "cv_seq_acc": 0.5, "cv_nll": 1.0},
            {"families": ["a"], "l2": 2, "clip": 0, "cv_seq_acc": 0.5, "cv_nll": 0.9},
            {"families": ["a"], "l2": 3, "clip": 2, "cv_seq_acc": 0.4, "cv_nll": 0.1},
            {"families": ["b"], "l2": 1, "clip": 3, "cv_seq_acc": 0.3, "cv_nll": 2.0}]
    best = classifier_motion.best_per_set(rows)
    assert [(r["families"], r["l2"]) for r in best] == [(["a"], 2), (["b"], 1)]


def test_per_fold_accuracy_groups_sequences_by_left_out_garment():
    fs = folds.leave_one_garment_out(["skirt_dance", "skirt_dance2", "apron_dance"])
    lp = np.log(np.array([[0.9, 0.1], [0.2, 0.8], [0.6, 0.4], [0.3, 0.7]]))
    cv = {"mean_lp": lp, "labels": np.array([0, 0, 0, 1]),
          "names": ["skirt_dance/a", "skirt_dance2/a", "apron_dance/a", "skirt_dance/b"]}
    assert classifier_motion.per_fold_accuracy(cv, fs) == {"flared_skirt": 2 / 3, "apron": 1.0}


def test_classifier_report_cv_leaves_out_every_scene_of_a_garment():
    """The patch-classifier study's CV (`classifier_report.cv_splits`) validates each garment
    on all its scenes, with no scene of it in training; each validated scene is seen as the
    test sees it (its coarse simulation when cached, else its downsampled fine maps), and
    training takes only the candidate's variants. `by="scene"` gives the older folds."""
    from experiments import classifier_report

    entries = [{"scene": s, "variant": v, "id": f"{s}/{v}"}
               for s in ("skirt_dance", "skirt_dance2", "apron_dance", "sheet_balls_wind")
               for v in ("coarse", "fine_ds") if not (s == "skirt_dance2" and v == "coarse")]
    splits = classifier_report.cv_splits(entries, ("coarse",))
    garments = folds.scene_garments(e["scene"] for e in entries)
    assert sorted(g for g, _, _ in splits) == sorted(set(garments.values()))
    for group, tr, va in splits:
        held = {e["scene"] for e in va}
        assert held == {s for s, g in garments.items() if g == group}
        assert not held & {e["scene"] for e in tr}
        assert {e["variant"] for e in tr} == {"coarse"}
        for e in va:  # skirt_dance2 has no coarse simulation cached
            assert e["variant"] == ("fine_ds" if e["scene"] == "skirt_dance2" else "coarse")
    skirt = next(s for s in splits if s[0] == garments["skirt_dance"])
    assert {e["id"] for e in skirt[2]} == {"skirt_dance/coarse", "skirt_dance2/fine_ds"}
    by_scene = classifier_report.cv_splits(entries, ("coarse", "fine_ds"), by="scene")
    assert [g for g, _, _ in by_scene] == sorted({e["scene"] for e in entries})
    assert any("skirt_dance2" in {e["scene"] for e in tr} for g, tr, _ in by_scene
               if g == "skirt_dance")  # a scene fold keeps the garment in training
    with pytest.raises(ValueError, match="garment"):
        classifier_report.cv_splits(entries, ("coarse",), by="sequence")
