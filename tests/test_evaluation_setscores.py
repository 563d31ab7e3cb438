"""wrinkle_jax.evaluation.setscores: Table 2's cell records, their files, means and table
(pure NumPy; the VGG features and `experiments.table2.main` are tested in
test_eval_experiments.py)."""

import json

import numpy as np
import pytest

from wrinkle_jax import evaluation
from wrinkle_jax.evaluation import cells as cell_lib
from wrinkle_jax.evaluation import patchscores, setscores
from wrinkle_jax.evaluation import sets as set_lib


def test_set_c_frames_are_between_table1_frames_never_on_them():
    a = patchscores.Sampling().frame_indices
    c = setscores.c_frame_indices(a, 200, 10)
    assert c == list(range(5, 200, 10)) and not set(a) & set(c)
    assert setscores.c_frame_indices([0, 3, 6], 7, 3) == [1, 4, 5]  # past the end: the one before
    with pytest.raises(ValueError, match=">= 2"):
        setscores.c_frame_indices([0, 1], 2, 1)
    with pytest.raises(ValueError, match="within 1 frames"):
        setscores.c_frame_indices([0], 1, 2)


def _three_sets(n=20, seed=0):
    """6-D Gaussian clouds (std 0.3): c at the origin, b 0.5 from it, a 3.0 from it."""
    rng = np.random.default_rng(seed)
    sets = []
    for offset in (3.0, 0.5, 0.0):  # a, b, c
        p = rng.normal(0.0, 0.3, (n, 6))
        p[:, 0] += offset
        sets.append(p)
    return sets


def test_cell_comparison_finds_b_nearer_to_c_than_a_and_a_swap_reverses_it():
    a, b, c = _three_sets()
    ac = np.concatenate([a, c])
    res = {"frame": np.zeros(len(a), np.int32), "origin": np.zeros((len(a), 2), np.int32),
           "frame_c": np.ones(len(c), np.int32), "origin_c": np.zeros((len(c), 2), np.int32),
           "scales": {}, "n_candidates": 1, "timings": {},
           "d2_ref": evaluation.sq_dists(ac),
           "d2_method": {"near": np.concatenate([evaluation.sq_dists(b, ac),
                                                 evaluation.sq_dists(b)], 1),
                         "same": np.concatenate([evaluation.sq_dists(a, ac),
                                                 evaluation.sq_dists(a)], 1)}}
    d2, labels = set_lib.union_sq_dists(res["d2_ref"], res["d2_method"]["near"], len(a))
    np.testing.assert_allclose(d2, evaluation.sq_dists(np.concatenate([a, b, c])), atol=1e-12)
    rec = setscores.cell_record(res)
    near, same = rec["methods"]["near"], rec["methods"]["same"]
    for space in setscores.SPACES:
        s = near[space]
        assert s["c2"] < s["c1"] and s["dr_signed"] > 0 and s["dr"] == s["dr_signed"]
        assert same[space]["dr_signed"] == pytest.approx(0.0, abs=1e-6)
    assert near["full"]["c1"] == pytest.approx(evaluation.chamfer_distance(a, c), rel=1e-9)
    assert near["full"]["c2"] == pytest.approx(evaluation.chamfer_distance(b, c), rel=1e-9)
    emb = near["embedding"]
    assert emb.shape == (60, 2) and emb.dtype == np.float32
    assert np.sqrt(((emb - emb.mean(0)) ** 2).sum(1).mean()) == pytest.approx(1.0, rel=1e-5)
    # Swapping the roles of a and b must flip the verdict.
    swapped = set_lib.compare_sets(d2, np.choose(labels, [set_lib.SET_B, set_lib.SET_A,
                                                         set_lib.SET_C]))
    for space in setscores.SPACES:
        assert swapped[space]["c2"] > swapped[space]["c1"]
        assert swapped[space]["dr_signed"] < 0 < swapped[space]["dr"]
    # The order of the rows does not matter.
    perm = np.random.default_rng(3).permutation(len(labels))
    shuffled = set_lib.compare_sets(d2[np.ix_(perm, perm)], labels[perm])
    for space in setscores.SPACES:
        for k in ("c1", "c2"):
            assert shuffled[space][k] == pytest.approx(near[space][k], rel=1e-5)


def test_merge_records_checks_the_sets_and_orders_the_methods():
    rec = {"frame": np.array([0]), "origin": np.array([[0, 0]]), "frame_c": np.array([1]),
           "origin_c": np.array([[4, 4]]), "scales": {"relu1_2": 2.0},
           "methods": {"a": {"x": 1}}, "timings": {"methods_s": {"a": 1.0}, "vgg_passes": 2}}
    new = {**rec, "methods": {"b": {"x": 2}},
           "timings": {"methods_s": {"b": 0.5}, "vgg_passes": 3}}
    got = setscores.merge_records(rec, new, ["b", "a"])
    assert list(got["methods"]) == ["b", "a"] and got["timings"]["vgg_passes"] == 5
    with pytest.raises(ValueError):
        setscores.merge_records(rec, {**new, "scales": {"relu1_2": 2.1}}, ["a", "b"])
    with pytest.raises(ValueError):
        setscores.merge_records(rec, {**new, "frame_c": np.array([3])}, ["a", "b"])


def _record(dr_model, n_a=3, n_c=2):
    def m(dr):
        s = {"c1": 2.0, "c2": 2.0 * (1 - dr / 100), "dr": abs(dr), "dr_signed": dr}
        return {"embedded": dict(s), "full": dict(s),
                "embedding": np.zeros((2 * n_a + n_c, 2), np.float32)}

    return {"frame": np.zeros(n_a, np.int32), "origin": np.zeros((n_a, 2), np.int32),
            "frame_c": np.ones(n_c, np.int32), "origin_c": np.zeros((n_c, 2), np.int32),
            "scales": {"relu1_2": 1.5}, "n_candidates": 4, "timings": {"compare_s": 0.1},
            "methods": {"identity": m(0.0), patchscores.MODEL: m(dr_model)}}


def _raise_runtime_error(*args, **kwargs):
    raise RuntimeError("bug")


def test_means_skip_nan_cells_and_the_table_and_cell_files_keep_the_numbers(tmp_path):
    recs = [_record(10.0), _record(30.0), _record(float("nan"))]
    means = setscores.mean_scores(recs)
    model = means[patchscores.MODEL]["embedded"]
    assert model["dr_signed"] == pytest.approx(20.0) and model["n_cells"] == 2
    assert means["identity"]["full"]["n_cells"] == 3
    seen, unseen = cell_lib.Cell("flared_skirt", "dance", "silk_charmeuse"), cell_lib.Cell(
        "dress", "walk", "silk_charmeuse")
    assert [setscores.group_of(c) for c in (seen, unseen)] == list(setscores.GROUPS)
    results = {"model": "m.npz", "sampling_text": "S.", "methods": ["identity", "model"],
               "config": {"garments": ["dress"], "materials": ["silk_charmeuse"],
                          "motions": ["walk"]},
               "cells": {unseen.key: {"kind": "unseen garment",
                                      "methods": {k: {s: v[s] for s in setscores.SPACES}
                                                  for k, v in recs[2]["methods"].items()}}},
               "by_group": {"unseen garment": means}, "all": means}
    text = setscores.table_markdown(results)
    assert "| silk_charmeuse | walk (unseen) | - |" in text  # a NaN cell prints "-"
    assert "| mean, all | 2 cells | 2.000 / 2.000 / +0.0 | 2.000 / 1.600 / +20.0 |" in text
    path = setscores.cell_path(tmp_path, unseen)
    fp = {"sampling": {"frames": 4}, "sequences": ["a"], "metric": "v1", "model": "x"}
    setscores.save_cell(path, recs[0], fp, {"identity": "identity", "model": "m1"})
    got = setscores.load_cell(path, {**fp, "model": "y"})  # not a set-defining key
    assert got["sources"] == {"identity": "identity", "model": "m1"} and not got["legacy"]
    assert got["methods"]["model"]["full"] == recs[0]["methods"]["model"]["full"]
    assert np.array_equal(got["frame_c"], recs[0]["frame_c"]) and got["scales"] == {
        "relu1_2": 1.5}
    assert setscores.load_cell(path, {**fp, "metric": "v2"}) is None
    assert json.loads(json.dumps(got["timings"])) == {"compare_s": 0.1}
    whole = path.read_bytes()
    path.write_bytes(whole[:-40])  # a damaged file is recomputed
    assert setscores.load_cell(path, fp) is None
    path.write_bytes(whole)
    with pytest.MonkeyPatch.context() as mp:  # an error in our own code is not a damaged file
        mp.setattr(patchscores, "cell_part", _raise_runtime_error)
        with pytest.raises(RuntimeError, match="bug"):
            setscores.load_cell(path, fp)
