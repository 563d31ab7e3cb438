"""experiments.classifier_synthesis report helpers: a variant's held-out syntheses scored by a
fixed (base) classifier, per garment, and session 24's decision rule."""

import numpy as np

from experiments import classifier_synthesis as cs
from wrinkle_jax import MATERIALS
from wrinkle_jax.classifier import motion

W, D = 3, motion.FEATURE_DIM


def _entry(rng, scene, label, fabric_of_nearest=None):
    """A fake cache entry: the synthesis of `fabric_of_nearest` (default: the true fabric)
    reproduces the input up to small noise, the others are far."""
    x = rng.normal(size=(W, D))
    s = x[None] + rng.normal(size=(len(MATERIALS), W, D)) * 3.0
    k = label if fabric_of_nearest is None else fabric_of_nearest
    s[k] = x + rng.normal(size=(W, D)) * 0.01
    return {"split": "heldout", "scene": scene, "material": MATERIALS[label], "label": label,
            "input": x, "synth": s}


def test_score_variant_per_garment_and_unseen():
    rng = np.random.default_rng(0)
    train = [_entry(rng, f"train{i}", y) for i in range(4) for y in range(5)]
    dist = cs.Distance({"families": list(motion.FAMILIES), "agg": "mean", "l2": None}, train)
    calib = {"T": 0.1, "threshold": 0.5, "group_threshold": 0.5, "novelty_limit": 1e9}
    good = [_entry(rng, sc, y) for sc in ("dress_walk", "skirt_walk") for y in range(5)]
    # A variant whose cape syntheses are nearest for the NEXT fabric: all wrong there.
    bad = [_entry(rng, "cape_walk", y, (y + 1) % 5) for y in range(5)]
    r = cs.score_variant(dist, calib, good + bad)
    g = r["per_garment"]
    assert set(g) == {"dress_walk", "skirt_walk", "cape_walk"}
    assert g["dress_walk"] == {"n": 5, "right": 5, "answered": 5, "right_where_answers": 5}
    assert g["skirt_walk"]["right"] == 5 and g["cape_walk"]["right"] == 0
    assert g["cape_walk"]["answered"] == 5 and g["cape_walk"]["right_where_answers"] == 0
    assert r["all"]["n"] == 15 and abs(r["all"]["seq_acc"] - 10 / 15) < 1e-12
    # skirt_walk is a training garment: the unseen subset is the dress and the cape only.
    assert r["unseen_garments"]["n"] == 10 and abs(r["unseen_garments"]["seq_acc"] - 0.5) < 1e-12
    conf = np.array(r["all"]["confusion"])
    assert conf.trace() == 10 and conf.sum() == 15
    # The same numbers as scoring the entries directly with the fixed classifier.
    ref = cs.summarize(dist(good + bad), np.array([e["label"] for e in good + bad]), calib)
    assert ref["coverage"] == r["all"]["coverage"] and ref["nll"] == r["all"]["nll"]
    assert "skinned" not in r
    # Skinned stand-ins far from every synthesis: novel, so no answer.
    for e in good:
        e["skinned"] = e["input"] + 100.0
    s = cs.score_variant(dist, calib | {"novelty_limit": 50.0}, good)["skinned"]
    assert s["n"] == 10 and s["answered"] == 0 and s["min_distance_range"][0] > 50.0


def test_rule_s24():
    base = {"seq_acc": 0.8, "answered": 10}
    assert cs.rule_s24(base, {"seq_acc": 0.8, "answered": 9})["variant_picked"]
    assert cs.rule_s24(base, {"seq_acc": 0.9, "answered": 11})["variant_picked"]
    r = cs.rule_s24(base, {"seq_acc": 0.9, "answered": 8})
    assert r["accuracy_not_lower"] and not r["coverage_within_one"] and not r["variant_picked"]
    r = cs.rule_s24(base, {"seq_acc": 0.7, "answered": 10})
    assert not r["accuracy_not_lower"] and not r["variant_picked"]
