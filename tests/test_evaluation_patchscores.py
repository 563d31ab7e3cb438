"""Tests for scoring methods on a cell's aligned patches and the cell files
(`wrinkle_jax.evaluation.patchscores`)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from evaluation_fixtures import (  # tests/ is on sys.path
    PATCH,
    TEXEL,
    sheet_pair,
)

from wrinkle_jax import evaluation
from wrinkle_jax.evaluation import methods as method_lib
from wrinkle_jax.evaluation import patchscores, suite

SAMPLING = patchscores.Sampling(frames=3, frame_stride=2, patches_per_frame=2, patch_size=PATCH,
                           texel_size=TEXEL, min_coverage=0.5, score_batch=2)


def test_evaluate_cell_identity_scores_zero_and_the_target_scores_100(tiny_vgg, model):
    fine, coarse = sheet_pair()
    methods = {"identity": lambda p: evaluation.identity(p.input, p.mask),
               "oracle": lambda p: p.target,
               patchscores.MODEL: method_lib.enhancer_method(model, batch_size=2)}
    res = patchscores.evaluate_cell(fine, coarse, "denim_light", methods, tiny_vgg, SAMPLING)
    np.testing.assert_array_equal(res["frame"], [0, 0, 2, 2])
    assert res["origin"].shape == (4, 2) and (res["coverage"] >= 0.5).all()
    assert res["timings"]["vgg_passes"] == 2 * (2 + 2)  # 2 frames x (input, target, 2 outputs)
    sc = patchscores.cell_scores(res)
    assert sc["identity"]["valid"].all()
    np.testing.assert_array_equal(sc["identity"]["improvement"], 0.0)
    np.testing.assert_allclose(sc["oracle"]["improvement_signed"], 100.0, atol=1e-3)
    assert np.isfinite(sc[patchscores.MODEL]["improvement_signed"]).all()
    assert np.abs(sc[patchscores.MODEL]["improvement_signed"]).max() > 0  # the random net acts
    s = patchscores.summary(sc["oracle"])
    assert s["n"] == 4 and s["signed_mean"] == pytest.approx(100.0, abs=1e-3)


def test_legacy_cell_sources_trust_an_unchanged_model_file_only(tmp_path):
    f = tmp_path / "m.npz"
    f.write_bytes(b"weights")
    fp = {"model": str(f), "model_mtime": f.stat().st_mtime}
    src = patchscores.legacy_sources(fp, ["identity", patchscores.MODEL, patchscores.WRONG])
    digest = suite.file_digest(f)
    assert digest.startswith("sha256:") and len(digest) == 7 + 16
    assert src == {"identity": "identity", patchscores.MODEL: f"model {digest}",
                   patchscores.WRONG: f"model {digest} wrong material"}
    stale = patchscores.legacy_sources({**fp, "model_mtime": 1.0}, [patchscores.MODEL])
    assert stale[patchscores.MODEL] == "unknown model"
    assert suite.portable_path(suite.ROOT / "data" / "x.npz") == "data/x.npz"
    assert suite.portable_path(tmp_path / "y") == str((tmp_path / "y").resolve())


def test_file_digest_is_hashed_once_per_file_version(tmp_path, monkeypatch):
    import os

    calls = []
    real = suite.sha256_file
    monkeypatch.setattr(suite, "sha256_file", lambda p: calls.append(p) or real(p))
    f = tmp_path / "seq.npz"
    f.write_bytes(b"aaaa")
    os.utime(f, ns=(10**18, 10**18))
    first = suite.file_digest(f)
    assert suite.file_digest(str(f)) == first and len(calls) == 1
    f.write_bytes(b"bbbb")  # same size: only the mtime tells the new version
    os.utime(f, ns=(10**18 + 1, 10**18 + 1))
    assert suite.file_digest(f) != first and len(calls) == 2


def test_merge_cell_adds_methods_on_the_same_patches_only():
    base = {"frame": np.array([0, 0]), "origin": np.array([[0, 0], [4, 4]]),
            "loss_input": np.array([1.0, 2.0]), "loss": {"a": np.array([0.5, 0.5])},
            "timings": {"methods_s": {"a": 1.0}, "score_s": 2.0, "vgg_passes": 3}}
    new = {**base, "loss": {"b": np.array([0.1, 0.2])},
           "timings": {"methods_s": {"b": 0.5}, "score_s": 1.0, "vgg_passes": 2}}
    got = patchscores.merge_cell(base, new, ["b", "a"])
    assert list(got["loss"]) == ["b", "a"] and got["timings"]["vgg_passes"] == 5
    with pytest.raises(ValueError):
        patchscores.merge_cell(base, {**new, "loss_input": np.array([1.0, 2.5])}, ["a", "b"])
    with pytest.raises(ValueError):
        patchscores.merge_cell(base, {**new, "origin": np.array([[0, 0], [4, 8]])}, ["a", "b"])


def test_cell_files_round_trip_and_only_unreadable_or_foreign_files_are_recomputed(
        tmp_path, monkeypatch):
    res = {"frame": np.array([0, 2]), "origin": np.array([[0, 0], [8, 4]]),
           "coverage": np.array([1.0, 0.75]), "loss_input": np.array([1.0, 2.0]),
           "loss": {"identity": np.array([1.0, 2.0]), "model": np.array([0.5, 1.5])},
           "n_candidates": 7, "timings": {"score_s": 0.25}}
    fp = {"sampling": {"frames": 3}, "sequences": ["a"], "metric": "v1"}
    path = tmp_path / "cell.npz"
    patchscores.save_cell(path, res, fp, {"identity": "identity", "model": "m1"})
    got = patchscores.load_cell(path, fp)
    np.testing.assert_array_equal(got["loss"]["model"], [0.5, 1.5])
    assert got["n_candidates"] == 7 and got["sources"]["model"] == "m1" and not got["legacy"]
    assert patchscores.load_cell(path, {**fp, "metric": "v2"}) is not None  # same patches
    assert patchscores.load_cell(path, {**fp, "sequences": ["b"]}) is None  # other patches
    assert patchscores.load_cell(tmp_path / "missing.npz", fp) is None
    whole = path.read_bytes()
    path.write_bytes(whole[: len(whole) // 2])  # cut short: recomputed
    assert patchscores.load_cell(path, fp) is None
    np.savez(path, meta=np.str_("{}"))  # another layout: recomputed
    assert patchscores.load_cell(path, fp) is None
    path.write_bytes(whole)

    def broken(*a, **k):  # an error in our own code is not an unreadable file
        raise RuntimeError("bug")

    monkeypatch.setattr(patchscores, "cell_part", broken)
    with pytest.raises(RuntimeError, match="bug"):
        patchscores.load_cell(path, fp)


def test_a_cell_of_a_sequence_simulated_again_is_scored_again(tmp_path):
    """Cells name their simulations by digest; a cell stored before digests were recorded is
    reused (and marked for rewriting) only while it is newer than both sequence files."""
    import os

    res = {"frame": np.array([0]), "origin": np.array([[0, 0]]), "coverage": np.array([1.0]),
           "loss_input": np.array([1.0]), "loss": {"identity": np.array([1.0])},
           "n_candidates": 1, "timings": {}}
    seqs = {r: tmp_path / f"{r}.npz" for r in ("fine", "coarse")}
    for r, p in seqs.items():
        p.write_bytes(r.encode())
        os.utime(p, (1e9, 1e9))
    old = {"sampling": {"frames": 3}, "sequences": {r: str(p) for r, p in seqs.items()}}
    new = {**old, "simulations": {r: suite.file_digest(p) for r, p in seqs.items()}}
    path = tmp_path / "cell.npz"
    patchscores.save_cell(path, res, old, {"identity": "identity"})
    got = patchscores.load_cell(path, new)
    assert got is not None and got["legacy"] and got["sources"] == {"identity": "identity"}
    assert patchscores.load_cell(path, {**new, "sampling": {"frames": 4}}) is None
    seqs["fine"].write_bytes(b"simulated again")  # newer than the cell now
    again = {**old, "simulations": {r: suite.file_digest(p) for r, p in seqs.items()}}
    assert patchscores.load_cell(path, again) is None
    # Stored with digests: reused exactly while the digests agree.
    patchscores.save_cell(path, res, new, {"identity": "identity"})
    assert not patchscores.load_cell(path, new)["legacy"]
    assert patchscores.load_cell(path, again) is None


def test_paired_against_pairs_patches_valid_for_both():
    a = {"improvement_signed": np.array([5.0, 7.0, 1.0, 100.0]),
         "valid": np.array([True, True, True, False])}
    b = {"improvement_signed": np.array([4.0, 3.0, 2.0, 0.0]),
         "valid": np.array([True, True, True, True])}
    out = patchscores.paired_against({"m": a, "u": b}, ["m", "missing"], ["u", "absent"])
    assert list(out) == ["m"] and list(out["m"]) == ["u"]
    d = out["m"]["u"]
    assert d["n"] == 3 and d["median_diff"] == 1.0 and np.isclose(d["mean_diff"], 4.0 / 3)
    lo, hi = d["median_diff_ci"]
    assert -1.0 <= lo <= 1.0 <= hi <= 4.0


def _cell(path, sims):
    fingerprint = {"sampling": {}} if sims is None else {"sampling": {}, "simulations": sims}
    np.savez(path, meta=np.str_(json.dumps({"fingerprint": fingerprint})))


def test_same_simulations_sorts_cells_by_their_recorded_digests(tmp_path):
    a, b = tmp_path / "t1", tmp_path / "t2"
    a.mkdir()
    b.mkdir()
    one, two = {"fine": "sha256:1", "coarse": "sha256:2"}, {"fine": "sha256:1", "coarse": "x"}
    for name, ref, got in (("same", one, one), ("diff", one, two), ("old", one, None),
                           ("refold", None, one)):
        _cell(a / f"{name}.npz", ref)
        _cell(b / f"{name}.npz", got)
    _cell(b / "extra.npz", one)
    (b / "broken.npz").write_bytes(b"not a zip")
    assert patchscores.same_simulations(a, b) == {
        "same": ["same"], "different": ["diff"], "unrecorded": ["old", "refold"],
        "unmatched": ["broken", "extra"]}
    assert patchscores.cell_simulations(b)["broken"] is None
