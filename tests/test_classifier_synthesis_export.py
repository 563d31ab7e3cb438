"""experiments.classifier_synthesis --stage export: the CV pick saved as a
`synthesis_model.SynthesisClassifier` whose distances equal the study's `Distance`; the held-out
seed / split selection of the inputs."""

import json

import numpy as np

from experiments import classifier_synthesis as cs
from wrinkle_jax import MATERIALS
from wrinkle_jax.classifier import motion, synthesis_model
from wrinkle_jax.sim import scenes

W, D = 3, motion.FEATURE_DIM


def _write_cache(root, pipe, rng):
    """Fake training cache entries of `pipe`: the true fabric's synthesis is nearest."""
    for sc in scenes.TRAINING_SCENES + scenes.VAL_SCENES:
        for y, m in enumerate(MATERIALS):
            x = rng.normal(size=(W, D))
            s = x[None] + rng.normal(size=(len(MATERIALS), W, D))
            s[y] = x + rng.normal(size=(W, D)) * 0.1
            p = root / pipe / "train" / sc / f"{m}.npz"
            p.parent.mkdir(parents=True, exist_ok=True)
            np.savez(p, input=x, skinned=x + 50.0, synth=s, rms=np.ones(5),
                     synth_seconds=np.ones(5), total_seconds=np.array(5.0),
                     config=np.array("{}"))
    # A synthesis being written in another split is skipped, not read.
    tmp = root / pipe / "fresh" / "cape_walk" / "denim_light.tmp.npz"
    tmp.parent.mkdir(parents=True)
    tmp.write_bytes(b"partial")


def test_export_matches_study_distance(tmp_path, monkeypatch):
    rng = np.random.default_rng(0)
    _write_cache(tmp_path, "matched", rng)
    fams = list(motion.FAMILIES)
    monkeypatch.setattr(cs, "candidates", lambda: [
        {"families": fams, "agg": "mean", "l2": None},
        {"families": fams, "agg": "mean", "l2": 0.1}])
    out = tmp_path / "clf.npz"
    assert cs.main(["--stage", "export", "--cache", str(tmp_path), "--model-out", str(out),
                    "--frames", "64", "--settle", "12"]) == 0
    clf = synthesis_model.load(out)
    assert clf.solver == "input" and clf.meta["pipeline"] == "matched"
    assert clf.frames == 64 and clf.settle_frames == 12 and (clf.window, clf.stride) == (32, 16)
    assert clf.meta["training_inputs"] == 50 and "cv" in clf.meta and "date" in clf.meta
    # The study's distance, fitted on all training inputs of the pick, on the same features.
    train = [e for e in cs.load_entries(tmp_path, "matched") if e["split"] == "train"]
    _, _, picks, best = cs.cv_pipelines(tmp_path, quiet=True)
    spec, _, calib = picks["matched"]
    assert clf.families == tuple(spec["families"]) and clf.agg == spec["agg"]
    assert (clf.weights is None) == (spec["l2"] is None)
    assert clf.temperature == calib["T"] and clf.threshold == calib["threshold"]
    assert clf.novelty_limit == calib["novelty_limit"]
    dist = cs.Distance(spec, train)
    ref = dist(train[:7])
    got = np.stack([clf.distances(e["input"], e["synth"]) for e in train[:7]])
    np.testing.assert_allclose(got, ref, rtol=1e-12, atol=1e-12)
    # ... and on the skinned stand-ins, which are novel.
    d = clf.distances(train[0]["skinned"], train[0]["synth"])
    np.testing.assert_allclose(d, dist(train[:1], key="skinned")[0], rtol=1e-12)
    assert synthesis_model.decide(clf, d, W).abstained


def test_export_fixed_solver_for_s80(tmp_path, monkeypatch):
    _write_cache(tmp_path, "s80", np.random.default_rng(1))
    monkeypatch.setattr(cs, "candidates", lambda: [
        {"families": ["kinematic", "stretch"], "agg": "window", "l2": None}])
    out = tmp_path / "clf.npz"
    cs.main(["--stage", "export", "--cache", str(tmp_path), "--model-out", str(out)])
    clf = synthesis_model.load(out)
    assert (clf.solver, clf.substeps) == ("fixed", 80) and clf.weights is None
    assert clf.families == ("kinematic", "stretch")
    json.dumps(clf.meta)


def test_jobs_heldout_seed_and_split(tmp_path):
    train, held = tmp_path / "train", tmp_path / "held"
    for seed in (1, 2):
        p = held / "cape_walk" / f"{MATERIALS[0]}_coarse_s{seed}.npz"
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_bytes(b"")
    train.mkdir()
    j = cs.jobs(train, held, heldout_seed=2, heldout_split="fresh")
    assert [(s, sc, m, f.name) for s, sc, m, f in j] == [
        ("fresh", "cape_walk", MATERIALS[0], f"{MATERIALS[0]}_coarse_s2.npz")]
    assert cs.jobs(train, held)[0][0] == "heldout" and cs.jobs(train, held)[0][3].name.endswith(
        "_s1.npz")


def test_check_inputs_reads_each_named_file_against_its_entry(tmp_path, monkeypatch):
    """Both export checks (the study's and s24c's) run `synthesis_study.check_inputs`: each
    named input's coarse file of the given seed, scored against its own cached entry."""
    from types import SimpleNamespace

    from wrinkle_jax.classifier import synthesis_study

    _write_cache(tmp_path, "s80", np.random.default_rng(2))
    entries = [e for e in cs.load_entries(tmp_path, "s80") if e["split"] == "train"]
    dist = cs.Distance({"families": list(motion.FAMILIES), "agg": "mean", "l2": None}, entries)
    names = ["skirt_dance/denim_light", "sheet_balls_wind/silk_chiffon"]
    for i, name in enumerate(names):
        sc, m = name.split("/")
        p = tmp_path / "data" / sc / f"{m}_coarse_s3.npz"
        p.parent.mkdir(parents=True, exist_ok=True)
        np.savez(p, tag=np.array(i))
    read = []

    def fake_classify(arrays, clf):
        read.append(int(arrays["tag"]))
        return SimpleNamespace(scores={m: 1.0 / len(MATERIALS) for m in MATERIALS}, novelty=7.0,
                               material=MATERIALS[0], confidence=0.2, abstained=True, group=None)

    monkeypatch.setattr(synthesis_model, "classify", fake_classify)
    clf = SimpleNamespace(materials=MATERIALS, temperature=1.0)
    got = list(synthesis_study.check_inputs(clf, dist, entries, names, tmp_path / "data", 3))
    assert [name for name, _, _ in got] == names and read == [0, 1]
    for name, entry, row in got:
        assert f"{entry['scene']}/{entry['material']}" == name
        np.testing.assert_allclose(row["reference_distances"], dist([entry])[0])
        np.testing.assert_allclose(row["classify_distances"], 7.0, rtol=1e-12)
