"""Tests for the evaluation scripts (`.table1`, `.table2`, `.temporal`, `.stride`, `.report`,
`.timing`) on tiny analytic sheets, a tiny VGG and a tiny random enhancer (no simulation, no real
VGG).

Every garment here is a flat-UV grid sheet (UVs = rest (x, y) in meters), displaced by known
height fields, so normals and UV positions are known in closed form.
"""

from __future__ import annotations

import dataclasses
import json
import time
from types import SimpleNamespace

import jax
import numpy as np
import pytest

from experiments import report, stride, table1, table2, temporal, timing
from wrinkle_jax import (
    MATERIALS,
    enhancer,
    evaluation,
    material_index,
    meshio,
    normalmap,
    patches,
    primitives,
)
from wrinkle_jax.evaluation import cells as cell_lib
from wrinkle_jax.evaluation import gram, patchscores, patchsets, suite
from wrinkle_jax.evaluation import methods as method_lib
from wrinkle_jax.evaluation import seams as seam_lib
from wrinkle_jax.evaluation import sets as set_lib
from wrinkle_jax.evaluation import temporal as temporal_lib
from wrinkle_jax.nn import vgg
from wrinkle_jax.sim import scenes

SIZE = (0.3, 0.2)  # sheet, meters
TEXEL = 0.004
PATCH = 32
FOLD = 0.3  # wavelength of the fold, meters


@pytest.fixture(scope="module")
def tiny_vgg():
    return vgg.init_vgg19(jax.random.key(0, impl="rbg"), widths=(4, 8, 8, 8, 8), num_convs=16,
                          spec=vgg.VGGSpec("custom", "REFLECT"))


@pytest.fixture(scope="module")
def model():
    config = enhancer.EnhancerConfig(width=4, patch_size=PATCH, texel_size=TEXEL, residual=True)
    return enhancer.init_enhancer(jax.random.key(0, impl="rbg"), config)


def _height(x, y, t, ripple):
    """Travelling fold (2 cm amplitude, 30 cm wavelength) plus optional fine ripples (m)."""
    return (0.02 * np.sin(2 * np.pi * x / FOLD + 0.5 * t)
            + ripple * np.sin(2 * np.pi * y / 0.02))


def _sheet_sequence(nx, ny, frames, ripple=0.0, metadata=None):
    g = primitives.grid_sheet(nx, ny, size=SIZE)
    v = np.asarray(g.vertices)
    out = np.stack([np.c_[v[:, :2], _height(v[:, 0], v[:, 1], t, ripple)]
                    for t in range(frames)]).astype(np.float32)
    return meshio.make_sequence(out, g, metadata=metadata)


def _pair(frames=3):
    """(fine 5 mm grid with ripples, coarse 30 mm grid) of the same sheet and fold."""
    return (_sheet_sequence(60, 40, frames, ripple=0.002), _sheet_sequence(10, 7, frames))


def _rgb_patches(n=3, size=PATCH, seed=0, detail=0.3):
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:size, 0:size] / size
    out = []
    for _ in range(n):
        a, b = rng.uniform(1, 3, 2)
        gx = 0.5 * np.sin(2 * np.pi * a * x) + detail * np.sin(2 * np.pi * 7 * y + rng.uniform())
        gy = 0.5 * np.cos(2 * np.pi * b * y)
        nrm = np.stack([-gx, -gy, np.ones_like(gx)], -1)
        out.append((nrm / np.linalg.norm(nrm, axis=-1, keepdims=True) + 1) / 2)
    mask = np.zeros((n, size, size, 1), np.float32)
    mask[:, :, : size * 3 // 4] = 1
    return np.asarray(out, np.float32) * mask, mask


# --------------------------------------------------------------------------------------------
# Scoring with shared Gram matrices
# --------------------------------------------------------------------------------------------


def test_method_losses_equal_score_patches_and_share_the_input_and_target_passes(tiny_vgg):
    inp, mask = _rgb_patches(5, detail=0.0)
    target, _ = _rgb_patches(5, seed=1, detail=0.4)
    noisy = np.clip(inp + 0.2 * np.random.default_rng(2).standard_normal(inp.shape), 0, 1)
    outputs = {"identity": evaluation.identity(inp, mask),
               "noisy": (noisy * mask).astype(np.float32),
               "unsharp": evaluation.unsharp_mask(inp, mask, 2.0, 1.0),
               "oracle": target}
    counter = {}
    got = gram.method_losses(tiny_vgg, inp, target, mask, outputs, batch_size=2, counter=counter)
    # 3 batches (2 + 2 + 1 padded): target and input once each, identity reuses the input.
    assert counter["vgg_passes"] == 3 * (2 + 3)
    for name, out in outputs.items():
        ref = evaluation.score_patches(tiny_vgg, inp, out, target, mask, batch_size=2)
        sc = evaluation.scores_from_losses(got["input"], got[name])
        np.testing.assert_allclose(sc["loss_input"], ref["loss_input"], rtol=1e-5)
        np.testing.assert_allclose(sc["loss_output"], ref["loss_output"], rtol=1e-5, atol=1e-12)
        np.testing.assert_allclose(sc["improvement_signed"], ref["improvement_signed"],
                                   rtol=1e-4, atol=1e-3)
        np.testing.assert_array_equal(sc["valid"], ref["valid"])
    ident = evaluation.scores_from_losses(got["input"], got["identity"])
    oracle = evaluation.scores_from_losses(got["input"], got["oracle"])
    assert ident["valid"].all()
    np.testing.assert_array_equal(ident["improvement"], 0.0)
    np.testing.assert_allclose(oracle["improvement_signed"], 100.0, atol=1e-3)


def test_unsharp_setting_reads_the_sweep_best_or_falls_back(tmp_path):
    p = tmp_path / "results.json"
    p.write_text(json.dumps({"unsharp_sweep": {"sigma=2,amount=1": 3.0,
                                               "sigma=12,amount=1.5": 7.5,
                                               "sigma=8,amount=4": -60.0}}))
    # Keys without "order=" predate the order-1 blur: they are order 0.
    assert method_lib.unsharp_setting(p, order=0)[:2] == (12.0, 1.5)
    assert method_lib.unsharp_setting(p, order=1)[:2] == method_lib.DEFAULT_UNSHARP
    p.write_text(json.dumps({"unsharp_sweep": {"order=0,sigma=8,amount=1.5": 9.0,
                                               "order=1,sigma=12,amount=1": 8.0,
                                               "order=1,sigma=16,amount=2": 5.0}}))
    assert method_lib.unsharp_setting(p, order=0)[:2] == (8.0, 1.5)
    assert method_lib.unsharp_setting(p, order=1)[:2] == (12.0, 1.0)
    assert method_lib.unsharp_setting(tmp_path / "missing.json")[:2] == method_lib.DEFAULT_UNSHARP
    names = list(method_lib.baseline_methods({0: (8.0, 1.5), 1: (12.0, 1.0)}))
    assert names[1:3] == ["unsharp order 0 (sigma=8,amount=1.5)",
                          "unsharp order 1 (sigma=12,amount=1)"]


# --------------------------------------------------------------------------------------------
# Alignment
# --------------------------------------------------------------------------------------------


def _analytic_normals(layout, t=0):
    """Normals of the fold (no ripple) at every texel center of `layout`: (H, W, 3)."""
    h, w = layout.shape
    col, row = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    u = (col - layout.margin) / layout.pixels_per_uv + layout.u_min
    dzdx = 0.02 * 2 * np.pi / FOLD * np.cos(2 * np.pi * u / FOLD + 0.5 * t)
    n = np.stack([-dzdx, np.zeros_like(dzdx), np.ones_like(dzdx)], -1)
    return n / np.linalg.norm(n, axis=-1, keepdims=True)


def test_coarse_and_fine_maps_share_one_grid_and_their_patches_align_in_uv():
    fine, coarse = _sheet_sequence(60, 40, 1), _sheet_sequence(10, 7, 1)
    # Stretch the coarse rest mesh by 1 %: its own layout_for scale would differ.
    coarse = dataclasses.replace(coarse, garment=coarse.garment.replace(
        vertices=np.asarray(coarse.garment.vertices) * 1.01))
    pair = patchsets.aligned_pair(fine.garment, coarse.garment, TEXEL)
    assert pair.fine.layout == pair.coarse.layout == pair.layout
    assert pair.layout.pixels_per_uv == pytest.approx(1.0 / TEXEL)  # the fine (reference) scale
    fm, cm = np.asarray(pair.fine.mask), np.asarray(pair.coarse.mask)
    assert (pair.mask <= fm).all() and (pair.mask <= cm).all() and pair.mask.sum() > 0.9 * fm.sum()
    truth = _analytic_normals(pair.layout)
    inside = pair.mask[..., 0] > 0
    for plan, tol in ((pair.fine, 0.5), (pair.coarse, 4.0)):
        baked = patchsets.bake_map(plan, fine.frames[0] if plan is pair.fine else coarse.frames[0])
        assert evaluation.mean_angular_change(baked, truth, pair.mask) < tol
    # The coarse mesh's own layout (scale from its stretched 3D areas) drifts off the grid.
    own = normalmap.make_plan(coarse.garment, texel_size=TEXEL)
    assert own.layout.pixels_per_uv != pytest.approx(pair.layout.pixels_per_uv)
    # Patches cut at the same origins show the same cloth: input and target agree everywhere
    # on the fold (the fine map's ripples tilt normals by < 33 degrees).
    size = PATCH
    mask = np.asarray(patches.pad_to_patch(pair.mask, size)[0])
    origins, cov = patchsets.candidate_origins(mask, size, size // 2, 0.5)
    ps = patchsets.aligned_patches(pair, fine.frames[0], coarse.frames[0], origins, size, 0)
    assert ps.input.shape == ps.target.shape == (len(origins), size, size, 3)
    truth_p = patchsets.cut(np.asarray(patches.pad_to_patch(truth, size)[0]), origins, size)
    for k in range(len(origins)):
        assert evaluation.mean_angular_change(ps.input[k] * 2 - 1, truth_p[k], ps.mask[k]) < 4.0
        # The fine map resolves the fold: a patch one texel off would be > 1 degree away.
        assert evaluation.mean_angular_change(ps.target[k] * 2 - 1, truth_p[k], ps.mask[k]) < 0.5
    fine_rgb = np.asarray(patches.pad_to_patch(
        normalmap.to_rgb(patchsets.bake_map(pair.fine, fine.frames[0])), size)[0]) * mask
    np.testing.assert_array_equal(ps.target, np.asarray(patches.extract(fine_rgb, origins, size)))
    np.testing.assert_array_equal(ps.mask, patchsets.cut(mask, origins, size))
    assert inside.any() and not ps.input[ps.mask[..., 0] == 0].any()


def test_candidate_origins_are_exactly_the_grid_patches_with_enough_coverage():
    mask = np.zeros((100, 130, 1), np.float32)
    mask[10:70, 20:110] = 1
    origins, cov = patchsets.candidate_origins(mask, 32, 16, 0.5)
    all_origins = patches.tile(mask, 32, 16)
    brute = np.array([mask[r:r + 32, c:c + 32].mean() for r, c in all_origins])
    np.testing.assert_array_equal(origins, all_origins[brute >= 0.5])
    np.testing.assert_allclose(cov, brute[brute >= 0.5], rtol=1e-6)
    chosen = patchsets.choose_origins(origins, 3, (1, 2))
    assert len(chosen) == 3 and {tuple(o) for o in chosen} <= {tuple(o) for o in origins}
    np.testing.assert_array_equal(chosen, patchsets.choose_origins(origins, 3, (1, 2)))  # seeded


# --------------------------------------------------------------------------------------------
# Table 1
# --------------------------------------------------------------------------------------------


SAMPLING = patchscores.Sampling(frames=3, frame_stride=2, patches_per_frame=2, patch_size=PATCH,
                           texel_size=TEXEL, min_coverage=0.5, score_batch=2)


def test_evaluate_cell_identity_scores_zero_and_the_target_scores_100(tiny_vgg, model):
    fine, coarse = _pair()
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


def test_model_method_outputs_unit_normals_inside_the_mask_only(model):
    fine, coarse = _pair(1)
    pair = patchsets.aligned_pair(fine.garment, coarse.garment, TEXEL)
    mask = np.asarray(patches.pad_to_patch(pair.mask, PATCH)[0])
    origins, _ = patchsets.candidate_origins(mask, PATCH, PATCH // 2, 0.1)
    ps = patchsets.aligned_patches(pair, fine.frames[0], coarse.frames[0], origins[:3], PATCH, 4)
    timings = {}
    out = method_lib.enhancer_method(model, batch_size=2, timings=timings)(ps)
    inside = ps.mask[..., 0] > 0
    np.testing.assert_allclose(np.linalg.norm(out[inside] * 2 - 1, axis=-1), 1.0, atol=1e-5)
    assert not out[~inside].any()
    assert timings["network_patches"] == 3 and timings["compile_s"] > 0


def test_run_cells_reuses_by_source_adds_missing_methods_and_upgrades_legacy_files(tmp_path):
    cells = cell_lib.table_cells(["dress"], ["silk_charmeuse"], ["dance", "walk"])
    a, b = cells
    store = {  # a: legacy file with m1 only; b: current file with m1 from another source
        a.key: {"loss": {"m1": 1}, "sources": {"m1": "m1"}, "legacy": True, "timings": {}},
        b.key: {"loss": {"m1": 1, "m2": 2}, "sources": {"m1": "old", "m2": "m2"},
                "legacy": False, "timings": {"cell_s": 5.0}}}
    saved, evaluated = {}, []

    def evaluate(cell, names, progress):
        evaluated.append((cell.key, list(names)))
        if progress is not None:
            progress(1, "step")
        return {"loss": {n: 10 for n in names}, "timings": {}}

    def merge(old, new, order):
        if new.get("bad"):
            raise ValueError
        return {**old, "loss": {**old["loss"], **new["loss"]}, "timings": dict(old["timings"])}

    common = dict(path_of=lambda c: tmp_path / c.key.replace("/", "_"),
                  fingerprint_of=lambda c: {}, load=lambda p, f: next(
                      v for k, v in store.items() if k.replace("/", "_") == p.name),
                  save=lambda p, r, f, src: saved.__setitem__(p.name, (r, src)),
                  evaluate=evaluate, merge=merge, field="loss", units=lambda n: 1, unit="x",
                  log=lambda m: None)
    got = cell_lib.run_cells(cells, {"m1": None}, None, **common)
    assert evaluated == [(b.key, ["m1"])]  # b's m1 came from another source
    assert got[a.key]["loss"] == {"m1": 1} and got[b.key]["loss"] == {"m1": 10}
    name_a = a.key.replace("/", "_")
    assert saved[name_a][1] == {"m1": "m1"}  # the legacy file was rewritten with its sources
    evaluated.clear()
    got = cell_lib.run_cells(cells, {"m1": None, "m3": None}, {"m1": "m1", "m3": "s3"}, **common)
    assert (a.key, ["m3"]) in evaluated and got[a.key]["loss"] == {"m1": 1, "m3": 10}
    assert saved[name_a][1] == {"m1": "m1", "m3": "s3"}
    evaluated.clear()
    cell_lib.run_cells(cells, {"m1": None}, None, **common, fresh=True)
    assert evaluated == [(a.key, ["m1"]), (b.key, ["m1"])]
    # Patches that no longer match the stored ones: every method is evaluated again.
    evaluated.clear()

    def refuse(old, new, order):
        raise ValueError("different patches")

    cell_lib.run_cells(cells[:1], {"m1": None, "m4": None}, None, **{**common, "merge": refuse})
    assert evaluated == [(a.key, ["m4"]), (a.key, ["m1", "m4"])]


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


def test_wrong_material_swaps_the_table_materials_and_the_method_tells_the_model_so(model):
    silk, denim = material_index("silk_charmeuse"), material_index("denim_light")
    assert method_lib.wrong_material(silk) == denim and method_lib.wrong_material(denim) == silk
    assert method_lib.wrong_material(material_index("wool_melton")) == silk
    with pytest.raises(ValueError):
        method_lib.wrong_material(silk, materials=("silk_charmeuse",))
    # Give every material its own CIN parameters, so the material id changes the output.
    key = jax.random.key(3, impl="rbg")
    leaves, tree = jax.tree_util.tree_flatten(model.params)
    keys = jax.random.split(key, len(leaves))
    params = jax.tree_util.tree_unflatten(tree, [
        x + 0.3 * jax.random.normal(k, x.shape) for x, k in zip(leaves, keys, strict=True)])
    noisy = model._replace(params=params)
    fine, coarse = _pair(1)
    pair = patchsets.aligned_pair(fine.garment, coarse.garment, TEXEL)
    mask = np.asarray(patches.pad_to_patch(pair.mask, PATCH)[0])
    origins, _ = patchsets.candidate_origins(mask, PATCH, PATCH // 2, 0.1)
    ps = patchsets.aligned_patches(pair, fine.frames[0], coarse.frames[0], origins[:2], PATCH, silk)
    wrong = method_lib.enhancer_method(noisy, batch_size=2,
                                       material_of=method_lib.wrong_material)(ps)
    right = method_lib.enhancer_method(noisy, batch_size=2)
    np.testing.assert_allclose(wrong, right(dataclasses.replace(ps, material_id=denim)),
                               atol=1e-6)
    assert np.abs(wrong - right(ps)).max() > 1e-3


def _spy_on_evaluate_cell(monkeypatch, module) -> list:
    """Record the method names of every `module.evaluate_cell` call (still evaluating)."""
    calls = []
    real = module.evaluate_cell

    def spy(fine, coarse, material, methods, *a, **k):
        calls.append(list(methods))
        return real(fine, coarse, material, methods, *a, **k)

    monkeypatch.setattr(module, "evaluate_cell", spy)
    return calls


def _write_cell_files(root, garment, motion, material, frames=3):
    """Tiny fine/coarse sheet files that `evaluation.cells.cell_sequences` accepts for a cell."""
    sc = cell_lib.scene_for(garment, motion)
    meta = {"scene_config": sc.to_json(), "material": material, "seed": cell_lib.TEST_SEED}
    fine, coarse = _pair(frames)
    for res, seq in (("fine", fine), ("coarse", coarse)):
        seq = meshio.make_sequence(seq.frames, seq.garment, metadata=meta)
        path = cell_lib.sequence_file(root, sc.name, material, res, cell_lib.TEST_SEED)
        meshio.save_sequence(path, seq)


def test_table1_main_writes_results_and_resumes_from_stored_cells(tmp_path, monkeypatch,
                                                                  tiny_vgg, model):
    seqs = tmp_path / "seqs"
    _write_cell_files(seqs, "dress", "dance", "silk_charmeuse")
    _write_cell_files(seqs, "dress", "walk", "silk_charmeuse")
    model_path = tmp_path / "tiny.npz"
    enhancer.save_enhancer(model_path, model.params, model.config)
    monkeypatch.setattr(table1.vgg, "load_vgg19", lambda *a, **k: tiny_vgg)
    out = tmp_path / "out"
    argv = ["--model", str(model_path), "--garments", "dress", "--motions", "dance,walk",
            "--materials", "silk_charmeuse", "--frames", "3", "--frame-stride", "2",
            "--patches-per-frame", "2", "--sequences", str(seqs),
            "--sim-out", str(tmp_path / "sim"), "--out", str(out)]
    assert table1.main(argv) == 0
    assert not (tmp_path / "sim").exists()  # everything reused, nothing simulated
    res = json.loads((out / "results.json").read_text())
    for key in ("model", "methods", "unsharp", "sampling", "cells", "by_kind", "all", "timings",
                "machine"):
        assert key in res
    assert set(res["machine"]) >= {"platform", "cpu_count", "jax"}
    assert res["methods"][0] == "identity" and res["methods"][-2:] == [patchscores.MODEL,
                                                                          patchscores.WRONG]
    assert set(res["cells"]) == {"dress_dance/silk_charmeuse", "dress_walk/silk_charmeuse"}
    cell = res["cells"]["dress_walk/silk_charmeuse"]
    assert cell["scene"] == "dress_walk" and cell["kind"] == "unseen garment"
    assert cell["n_patches"] == 4 and cell["frames_scored"] == [0, 2]
    assert cell["methods"]["identity"]["improvement_mean"] == 0.0
    for name in res["methods"]:
        assert res["all"][name]["n"] == 8
        assert {"improvement_mean", "improvement_std", "signed_mean", "signed_std"} <= set(
            res["all"][name])
    table = (out / "table.md").read_text()
    assert "| silk_charmeuse | walk (unseen) |" in table and "dress (unseen)" in table
    with np.load(out / "scores.npz") as z:
        assert z["dress_walk__silk_charmeuse/identity/improvement_signed"].shape == (4,)
    # A rerun with the same settings reuses the stored cells; other settings rescore.
    monkeypatch.setattr(patchscores, "evaluate_cell", lambda *a, **k: pytest.fail("rescored"))
    assert table1.main(argv) == 0
    assert json.loads((out / "results.json").read_text())["all"] == res["all"]
    with pytest.raises(pytest.fail.Exception):
        table1.main(argv + ["--seed", "3"])
    # An extra model is scored alone on the stored patches; the other methods are reused.
    monkeypatch.undo()
    monkeypatch.setattr(table1.vgg, "load_vgg19", lambda *a, **k: tiny_vgg)
    calls = _spy_on_evaluate_cell(monkeypatch, patchscores)
    other = tmp_path / "other.npz"
    params = jax.tree.map(lambda x: x * 0.5, model.params)
    enhancer.save_enhancer(other, params, model.config)
    assert table1.main(argv + ["--extra", f"half={other}"]) == 0
    assert calls == [["half"], ["half"]]
    res2 = json.loads((out / "results.json").read_text())
    assert res2["methods"][-1] == "half" and res2["method_sources"]["half"].startswith("model ")
    for name in res["methods"]:
        assert res2["all"][name] == res["all"][name]
    # ... and a later run without it still reuses the stored cells.
    calls.clear()
    assert table1.main(argv) == 0 and calls == []
    with pytest.raises(SystemExit):
        table1.main(argv + ["--extra", "no-path"])


def test_scene_for_reuses_existing_scenes_and_derives_new_ones():
    assert cell_lib.scene_for("dress", "dance") is scenes.SCENES["dress_dance"]
    assert cell_lib.scene_for("flared_skirt", "walk") is scenes.SCENES["skirt_walk"]
    cape = cell_lib.scene_for("cape", "dance")
    base = scenes.SCENES["cape_walk"]
    assert cape.name == "cape_dance" and cape.motion == "dance"
    assert (cape.pins, cape.attach_to, cape.preroll_s) == (base.pins, base.attach_to, 2.0)
    kinds = {c.key: c.kind for c in cell_lib.table_cells()}
    assert len(kinds) == 12
    assert kinds["skirt_dance/denim_light"] == "seen garment, seen motion"
    assert kinds["skirt_walk/denim_light"] == "seen garment, unseen motion"
    assert kinds["cape_dance/silk_charmeuse"] == "unseen garment"


# --------------------------------------------------------------------------------------------
# Temporal coherence
# --------------------------------------------------------------------------------------------


def _rotating_sheet(frames, degrees_per_frame, nx=12, ny=8):
    """A flat sheet turning rigidly about the x axis: every normal turns by the same angle."""
    g = primitives.grid_sheet(nx, ny, size=SIZE)
    v = np.asarray(g.vertices)
    out = []
    for t in range(frames):
        a = np.radians(degrees_per_frame * t)
        rot = np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])
        out.append(v @ rot.T)
    return meshio.make_sequence(np.asarray(out, np.float32), g)


def test_flicker_of_a_rigid_rotation_is_its_angle_and_of_a_static_map_zero():
    seq = _rotating_sheet(4, 3.0)
    plan = normalmap.make_plan(seq.garment, texel_size=TEXEL)
    maps = np.stack([patchsets.bake_map(plan, f) for f in seq.frames])
    np.testing.assert_allclose(evaluation.flicker_series(maps, plan.mask), 3.0, atol=1e-3)
    np.testing.assert_allclose(evaluation.flicker_series(maps[[1, 1, 1]], plan.mask), 0.0,
                               atol=1e-4)
    assert evaluation.mean_angular_change(maps[0], maps[1], np.zeros_like(plan.mask)) == 0.0


def test_sequence_flicker_static_is_zero_and_rotation_moves_coarse_and_fine(model):
    static = _sheet_sequence(10, 7, 1)
    static = meshio.make_sequence(np.repeat(static.frames, 3, 0), static.garment)
    res = temporal_lib.sequence_flicker(static, static, model, "wool_melton", [0, 1, 2],
                                    batch_size=4)
    for k in temporal_lib.SERIES:
        np.testing.assert_allclose(res[k], 0.0, atol=1e-3)
    assert res["patches_per_frame"] > 0 and res["timings"]["network"] > 0
    coarse, fine = _rotating_sheet(3, 2.0), _rotating_sheet(3, 2.0, nx=40, ny=30)
    res = temporal_lib.sequence_flicker(coarse, fine, model, "wool_melton", [0, 1, 2], batch_size=4)
    np.testing.assert_allclose(res["coarse"], 2.0, atol=1e-3)
    np.testing.assert_allclose(res["fine"], 2.0, atol=1e-3)
    assert res["output"].shape == (2,) and np.isfinite(res["output"]).all()
    s = temporal.summarize(res)
    assert s["output_over_fine"] == pytest.approx(res["output"].mean() / 2.0, rel=1e-3)
    with pytest.raises(ValueError, match="consecutive"):
        temporal_lib.sequence_flicker(coarse, fine, model, "wool_melton", [0, 2])


def test_temporal_main_writes_results_and_plot(tmp_path, model):
    seqs = tmp_path / "seqs"
    _write_cell_files(seqs, "cape", "dance", "denim_light", frames=3)
    model_path = tmp_path / "tiny.npz"
    enhancer.save_enhancer(model_path, model.params, model.config)
    out = tmp_path / "out"
    assert temporal.main(["--model", str(model_path), "--garments", "cape", "--motions",
                          "dance", "--materials", "denim_light", "--frames", "3",
                          "--table-frames", "3", "--sequences", str(seqs),
                          "--sim-out", str(tmp_path / "sim"), "--out", str(out),
                          "--batch-size", "4"]) == 0
    res = json.loads((out / "results.json").read_text())
    seq = res["sequences"]["cape_dance/denim_light"]
    assert res["frames"] == [0, 1, 2] and set(seq["series"]) == {"coarse", "output", "fine"}
    assert all(len(v) == 2 for v in seq["series"].values())
    assert seq["summary"]["fine"]["mean"] > 0  # the fold travels
    assert {"platform", "cpu_count", "jax"} <= set(res["machine"])
    assert (out / "flicker.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


# --------------------------------------------------------------------------------------------
# Timing
# --------------------------------------------------------------------------------------------


def test_time_pipeline_reports_every_stage_per_frame_and_compile_separately(model):
    seq = _sheet_sequence(10, 7, 3)
    info = timing.time_pipeline(seq, model, "silk_chiffon", body=None, lift=True, batch_size=4,
                                chunk_size=2)
    assert info["frames"] == 3 and info["warmup_frames"] == 2
    assert set(info["ms_per_frame"]) == set(timing.STAGES)
    for stage in ("bake", "network", "merge", "lift"):
        assert info["ms_per_frame"][stage] > 0
    assert info["ms_per_frame_total"] == pytest.approx(sum(info["ms_per_frame"].values()))
    assert info["compile_s"] > 0 and info["detailed_vertices"] > seq.garment.num_vertices


def test_time_simulation_counts_simulated_frames_and_separates_the_first_call(monkeypatch):
    calls = []

    def fake_simulate(config, material, resolution, frames, seed, setup=None, progress=None):
        calls.append(frames)
        pre = 5
        total = pre + frames - 1
        if frames == 1:
            time.sleep(0.2)  # the first call compiles
            return SimpleNamespace(metadata={"preroll_frames": pre})
        done = 0
        for n in (30, 30, total - 60):  # chunks of simulated frames, 1 ms each
            time.sleep(0.001 * n)
            done += n
            progress(done, total)
        return SimpleNamespace(metadata={"preroll_frames": pre},
                               garment=SimpleNamespace(num_vertices=123))

    monkeypatch.setattr(timing.scenes, "simulate", fake_simulate)
    monkeypatch.setattr(timing.scenes, "setup_scene", lambda *a, **k: None)
    _, info = timing.time_simulation(scenes.SCENES["dress_dance"], "silk_charmeuse",
                                     "coarse", frames=70)
    assert calls == [1, 70]
    assert info["simulated_frames"] == 5 + 70 - 1 and len(info["chunk_ms_per_frame"]) == 3
    assert info["ms_per_frame"] == pytest.approx(1e3 * info["wall_s"] / 74)
    assert 0.15 < info["compile_s"] <= info["first_call_s"]
    assert info["vertices"] == 123


def test_timing_ratios_body_and_plot(tmp_path):
    r = timing.ratios(10.0, 200.0, {"bake": 5.0, "tile": 0.0, "network": 60.0, "merge": 5.0,
                                    "lift": 20.0})
    assert r["ours_ms_per_frame"] == 100.0 and r["speedup"] == 2.0
    assert r["speedup_no_lift"] == 2.5
    ends = np.zeros((2, 1, 2, 3), np.float32)
    ends[:, 0, 1, 2] = 1.0  # a vertical capsule from the origin to z = 1 m
    body = timing.capsule_body_fn({"capsule_ends": ends,
                                   "capsule_radii": np.array([0.1], np.float32)})(1)
    from wrinkle_jax import bodies

    q = bodies.query(body, np.array([[0.0, 0.0, 0.5], [0.5, 0.0, 0.5]], np.float32))
    np.testing.assert_allclose(np.asarray(q.distance), [-0.1, 0.4], atol=1e-5)
    assert timing.capsule_body_fn({}) is None
    results = {"scene": "s", "material": "m", "frames": 3,
               "coarse_sim": {"ms_per_frame": 10.0}, "fine_sim": {"ms_per_frame": 200.0},
               "pipeline": {"ms_per_frame": {k: 10.0 for k in timing.STAGES}}, "ratio": r}
    timing.plot(tmp_path / "t.png", results)
    assert (tmp_path / "t.png").read_bytes()[:4] == b"\x89PNG"


# --------------------------------------------------------------------------------------------
# Table 2
# --------------------------------------------------------------------------------------------


def test_chamfer_scores_hold_both_distances_and_both_ratios():
    assert set_lib.chamfer_scores(2.0, 3.0) == {"c1": 2.0, "c2": 3.0, "dr": 50.0,
                                               "dr_signed": -50.0}


def test_gram_features_are_upper_triangles_with_layers_scaled_to_unit_median_norm():
    rng = np.random.default_rng(1)

    def sym(n, c, scale):
        m = rng.normal(size=(n, c, c)) * scale
        return m + m.transpose(0, 2, 1)

    grams = {"small": sym(3, 2, 1.0), "big": sym(3, 4, 1000.0)}
    flat = set_lib.upper_triangle(grams)
    assert list(flat) == ["small", "big"]
    assert flat["small"].shape == (3, 3) and flat["big"].shape == (3, 10)
    assert flat["big"].dtype == np.float32
    g = grams["small"][1]
    np.testing.assert_allclose(flat["small"][1], [g[0, 0], g[0, 1], g[1, 1]], rtol=1e-6)
    scales = set_lib.layer_scales(flat)
    assert scales["big"] == pytest.approx(np.median(np.linalg.norm(flat["big"], axis=1)))
    feats = set_lib.scaled_features(flat, scales)
    assert feats.shape == (3, 13)
    for block in (feats[:, :3], feats[:, 3:]):
        assert np.median(np.linalg.norm(block, axis=1)) == pytest.approx(1.0)
    # A layer's overall magnitude is scaled away.
    louder = dict(flat, big=flat["big"] * 1e3)
    np.testing.assert_allclose(set_lib.scaled_features(louder, set_lib.layer_scales(louder)), feats,
                               rtol=1e-5)
    # Layer-by-layer distances equal the distances of the concatenated features.
    np.testing.assert_allclose(set_lib.scaled_sq_dists(flat, None, scales),
                               evaluation.sq_dists(feats), rtol=1e-9, atol=1e-12)
    other = set_lib.upper_triangle({"small": sym(2, 2, 1.0), "big": sym(2, 4, 1000.0)})
    np.testing.assert_allclose(set_lib.scaled_sq_dists(other, flat, scales),
                               evaluation.sq_dists(set_lib.scaled_features(other, scales), feats),
                               rtol=1e-9)
    assert set_lib.layer_scales({"zero": np.zeros((2, 3), np.float32)}) == {"zero": 1.0}
    with pytest.raises(ValueError, match="Gram"):
        set_lib.upper_triangle({"x": np.zeros((2, 3, 4))})


def test_set_c_frames_are_between_table1_frames_never_on_them():
    a = patchscores.Sampling().frame_indices
    c = table2.c_frame_indices(a, 200, 10)
    assert c == list(range(5, 200, 10)) and not set(a) & set(c)
    assert table2.c_frame_indices([0, 3, 6], 7, 3) == [1, 4, 5]  # past the end: the one before
    with pytest.raises(ValueError, match=">= 2"):
        table2.c_frame_indices([0, 1], 2, 1)
    with pytest.raises(ValueError, match="within 1 frames"):
        table2.c_frame_indices([0], 1, 2)


def test_embedding_from_the_distance_matrix_equals_the_embedding_of_the_points():
    x = np.random.default_rng(2).normal(size=(30, 50))
    d2 = evaluation.sq_dists(x)
    pts = set_lib.points_from_sq_dists(d2)
    np.testing.assert_allclose(evaluation.sq_dists(pts), d2, atol=1e-9)
    # Eigenvectors are defined up to sign.
    np.testing.assert_allclose(np.abs(evaluation.spectral_embedding(pts)),
                               np.abs(evaluation.spectral_embedding(x)), atol=1e-9)


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
    rec = table2.cell_record(res)
    near, same = rec["methods"]["near"], rec["methods"]["same"]
    for space in table2.SPACES:
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
    for space in table2.SPACES:
        assert swapped[space]["c2"] > swapped[space]["c1"]
        assert swapped[space]["dr_signed"] < 0 < swapped[space]["dr"]
    # The order of the rows does not matter.
    perm = np.random.default_rng(3).permutation(len(labels))
    shuffled = set_lib.compare_sets(d2[np.ix_(perm, perm)], labels[perm])
    for space in table2.SPACES:
        for k in ("c1", "c2"):
            assert shuffled[space][k] == pytest.approx(near[space][k], rel=1e-5)


def test_table2_main_uses_table1_patches_writes_results_and_resumes(tmp_path, monkeypatch,
                                                                      tiny_vgg, model):
    seqs = tmp_path / "seqs"
    _write_cell_files(seqs, "dress", "dance", "silk_charmeuse", frames=4)
    model_path = tmp_path / "tiny.npz"
    enhancer.save_enhancer(model_path, model.params, model.config)
    monkeypatch.setattr(table2.vgg, "load_vgg19", lambda *a, **k: tiny_vgg)
    out = tmp_path / "out"
    argv = ["--model", str(model_path), "--garments", "dress", "--motions", "dance",
            "--materials", "silk_charmeuse", "--frames", "4", "--frame-stride", "2",
            "--patches-per-frame", "3", "--sequences", str(seqs),
            "--sim-out", str(tmp_path / "sim"), "--out", str(out)]
    assert table2.main(argv) == 0
    assert not (tmp_path / "sim").exists()  # Table 1's sequences reused, nothing simulated
    res = json.loads((out / "results.json").read_text())
    assert res["methods"][0] == "identity" and res["methods"][-1] == table2.MODEL
    assert {"platform", "cpu_count", "jax"} <= set(res["machine"])
    cell = res["cells"]["dress_dance/silk_charmeuse"]
    assert cell["frames_a"] == [0, 2] and cell["frames_c"] == [1, 3]
    assert cell["group"] == "unseen garment" and cell["n_a"] == cell["n_c"] > 0
    ident, ours = cell["methods"]["identity"], cell["methods"][table2.MODEL]
    for space in table2.SPACES:
        assert ident[space]["dr_signed"] == pytest.approx(0.0, abs=1e-6)
        assert all(np.isfinite(ours[space][k]) for k in ("c1", "c2", "dr", "dr_signed"))
    assert ident["full"]["c1"] == ours["full"]["c1"]  # one feature space for every method
    assert set(res["by_group"]) == {"unseen garment"}
    assert res["all"][table2.MODEL]["full"]["n_cells"] == 1
    table = (out / "table.md").read_text()
    assert "| silk_charmeuse | dance (seen) |" in table and "dress (unseen)" in table
    assert (out / "embeddings.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # Set a is Table 1's patches: same frames and origins.
    c = cell_lib.Cell("dress", "dance", "silk_charmeuse")
    fine, coarse = (cell_lib.load_first_frames(
        cell_lib.sequence_file(seqs, "dress_dance", c.material, r, cell_lib.TEST_SEED), 4)
        for r in ("fine", "coarse"))
    sampling = patchscores.Sampling(frames=4, frame_stride=2, patches_per_frame=3, patch_size=PATCH,
                               texel_size=TEXEL, score_batch=3)
    t1 = patchscores.evaluate_cell(fine, coarse, c.material, {}, tiny_vgg, sampling,
                              c.patch_seed)
    with np.load(out / "cells" / "dress_dance__silk_charmeuse.npz") as z:
        np.testing.assert_array_equal(z["frame"], t1["frame"])
        np.testing.assert_array_equal(z["origin"], t1["origin"])
    # A rerun with the same settings reuses the stored cell; other settings recompute.
    monkeypatch.setattr(table2, "evaluate_cell", lambda *a, **k: pytest.fail("recomputed"))
    assert table2.main(argv) == 0
    assert json.loads((out / "results.json").read_text())["all"] == res["all"]
    with pytest.raises(pytest.fail.Exception):
        table2.main(argv + ["--seed", "3"])
    # An extra model is computed alone on the stored sets; the others keep their numbers.
    monkeypatch.undo()
    monkeypatch.setattr(table2.vgg, "load_vgg19", lambda *a, **k: tiny_vgg)
    calls = _spy_on_evaluate_cell(monkeypatch, table2)
    other = tmp_path / "other.npz"
    enhancer.save_enhancer(other, jax.tree.map(lambda x: x * 0.5, model.params), model.config)
    assert table2.main(argv + ["--extra", f"half={other}"]) == 0
    assert calls == [["half"]]
    res2 = json.loads((out / "results.json").read_text())
    assert res2["methods"][-1] == "half"
    half = res2["cells"]["dress_dance/silk_charmeuse"]["methods"]["half"]
    assert half["full"]["c1"] == pytest.approx(ours["full"]["c1"], rel=1e-5)
    for name in res["methods"]:
        assert res2["all"][name] == res["all"][name]
    calls.clear()
    assert table2.main(argv) == 0 and calls == []


def test_merge_records_checks_the_sets_and_orders_the_methods():
    rec = {"frame": np.array([0]), "origin": np.array([[0, 0]]), "frame_c": np.array([1]),
           "origin_c": np.array([[4, 4]]), "scales": {"relu1_2": 2.0},
           "methods": {"a": {"x": 1}}, "timings": {"methods_s": {"a": 1.0}, "vgg_passes": 2}}
    new = {**rec, "methods": {"b": {"x": 2}},
           "timings": {"methods_s": {"b": 0.5}, "vgg_passes": 3}}
    got = table2.merge_records(rec, new, ["b", "a"])
    assert list(got["methods"]) == ["b", "a"] and got["timings"]["vgg_passes"] == 5
    with pytest.raises(ValueError):
        table2.merge_records(rec, {**new, "scales": {"relu1_2": 2.1}}, ["a", "b"])
    with pytest.raises(ValueError):
        table2.merge_records(rec, {**new, "frame_c": np.array([3])}, ["a", "b"])


# --------------------------------------------------------------------------------------------
# Stride ablation
# --------------------------------------------------------------------------------------------


def test_border_pairs_mark_the_neighbour_pairs_across_tile_starts_and_ends():
    origins = np.array([[0, 0], [16, 0], [28, 0]])  # rows 0, 16 and the clamped last row
    got = seam_lib.border_pairs(origins, 32, 60, axis=0)
    # tiles start at 16, 28 and end after 31, 47, 59 (the last, at the map's edge, has no pair)
    assert np.flatnonzero(got).tolist() == [15, 27, 31, 47]
    assert np.flatnonzero(seam_lib.border_pairs(origins, 32, 60, axis=1)).tolist() == [31]


def test_seam_ratio_is_one_for_uniform_bending_and_sees_a_kink_at_a_tile_border():
    h = w = 64
    y, x = np.mgrid[0:h, 0:w].astype(np.float64)
    ang = np.radians(0.5) * (x + y)  # the normal turns 0.5 degrees per texel along x and y
    nrm = np.stack([np.sin(ang), np.zeros_like(ang), np.cos(ang)], -1)
    mask = np.ones((h, w), bool)
    origins = np.array([[r, c] for r in (0, 16, 32) for c in (0, 16, 32)])
    assert seam_lib.seam_ratio(seam_lib.seam_sums(nrm, mask, origins, 32)) == pytest.approx(1.0)
    kinked = nrm.copy()
    kinked[:, 16:] = nrm[:, 16:] @ np.array([[np.cos(0.1), 0, -np.sin(0.1)], [0, 1, 0],
                                              [np.sin(0.1), 0, np.cos(0.1)]]).T
    assert seam_lib.seam_ratio(seam_lib.seam_sums(kinked, mask, origins, 32)) > 1.5
    off_border = nrm.copy()
    off_border[:, 20:] = kinked[:, 16:60]  # the same kink between tiles' borders
    assert seam_lib.seam_ratio(seam_lib.seam_sums(off_border, mask, origins, 32)) < 1.0
    assert np.isnan(seam_lib.seam_ratio(np.zeros(4)))


def test_stride_identity_network_scores_zero_and_leaves_the_coarse_seams(tiny_vgg, model):
    params = {**model.params, "out": jax.tree.map(jax.numpy.zeros_like, model.params["out"])}
    ident = model._replace(params=params)
    fine, coarse = _pair(3)
    sampling = patchscores.Sampling(frames=3, frame_stride=1, patches_per_frame=2, patch_size=PATCH,
                               texel_size=TEXEL, min_coverage=0.3, score_batch=2)
    res = stride.evaluate_cell(fine, coarse, "denim_light", ident, [8, 16, 24], tiny_vgg,
                               sampling, [0, 2], batch_size=2)
    for name in (stride.PATCH, 8, 16, 24):
        sc = evaluation.scores_from_losses(res["loss_input"], res["loss"][name])
        np.testing.assert_allclose(sc["improvement_signed"][sc["valid"]], 0.0, atol=1e-3)
    for s in (8, 16, 24):
        assert seam_lib.seam_ratio(res["seams"][s]) == pytest.approx(
            seam_lib.seam_ratio(res["seams_coarse"][s]), rel=1e-3)
    counts = [res["patches_per_frame"][s] for s in (8, 16, 24)]
    assert counts[0] > counts[1] > counts[2]
    pooled = stride.summarize({"a": res}, [8, 16, 24])
    assert pooled["8"]["patches_per_frame"] == counts[0]
    assert pooled["8"]["ms_tile_network_merge"] > 0
    assert pooled[stride.PATCH]["score"]["n"] == 4


def test_stride_main_writes_results_table_and_plot(tmp_path, monkeypatch, tiny_vgg, model):
    seqs = tmp_path / "seqs"
    _write_cell_files(seqs, "dress", "walk", "silk_charmeuse", frames=3)
    model_path = tmp_path / "tiny.npz"
    enhancer.save_enhancer(model_path, model.params, model.config)
    monkeypatch.setattr(stride.vgg, "load_vgg19", lambda *a, **k: tiny_vgg)
    out = tmp_path / "out"
    argv = ["--model", str(model_path), "--garments", "dress", "--motions", "walk",
            "--materials", "silk_charmeuse", "--frames", "3", "--frame-stride", "1",
            "--frame-every", "2", "--patches-per-frame", "2", "--strides", "16,24",
            "--sequences", str(seqs), "--sim-out", str(tmp_path / "sim"), "--out", str(out)]
    assert stride.main(argv) == 0
    res = json.loads((out / "results.json").read_text())
    assert res["frames"] == [0, 2] and set(res["pooled"]) == {"patch", "16", "24"}
    assert res["pooled"]["16"]["patches_per_frame"] > res["pooled"]["24"]["patches_per_frame"]
    assert (out / "pareto.png").stat().st_size > 0
    assert "| 24 |" in (out / "table.md").read_text()
    with pytest.raises(SystemExit):
        stride.main(argv + ["--strides", "64"])  # larger than the tiny model's 32-texel patch


# --------------------------------------------------------------------------------------------
# Report
# --------------------------------------------------------------------------------------------


def test_report_demote_and_drop():
    text = "# A\n## B\ntext # not a heading"
    assert report.demote(text, 1) == "## A\n### B\ntext # not a heading"
    right, wrong = {"signed_mean": 40.0}, {"signed_mean": 38.0}
    assert report._drop(right, wrong, "signed_mean") == pytest.approx(5.0)
    assert report._drop({"signed_mean": 0.0}, wrong, "signed_mean") is None


def test_report_assembles_stored_results_and_names_what_is_missing(tmp_path, monkeypatch,
                                                                   tiny_vgg, model):
    seqs = tmp_path / "seqs"
    _write_cell_files(seqs, "dress", "walk", "silk_charmeuse")
    _write_cell_files(seqs, "dress", "walk", "denim_light")
    model_path = tmp_path / "tiny.npz"
    enhancer.save_enhancer(model_path, model.params, model.config)
    monkeypatch.setattr(table1.vgg, "load_vgg19", lambda *a, **k: tiny_vgg)
    results = tmp_path / "results"
    assert table1.main(["--model", str(model_path), "--garments", "dress", "--motions", "walk",
                        "--frames", "3", "--frame-stride", "2", "--patches-per-frame", "2",
                        "--sequences", str(seqs), "--sim-out", str(tmp_path / "sim"),
                        "--out", str(results / "table1")]) == 0
    (results / "timing").mkdir()
    (results / "timing" / "results.json").write_text(
        (suite.RESULTS / "timing" / "results.json").read_text())  # the committed timing run
    out = tmp_path / "REPORT.md"
    assert report.main(["--results", str(results), "--out", str(out)]) == 0
    text = out.read_text()
    t1 = json.loads((results / "table1" / "results.json").read_text())
    unseen = t1["by_kind"]["unseen garment"]
    assert f"model signed mean {unseen['model']['signed_mean']:+.1f}" in text
    assert "| silk_charmeuse | walk (unseen) |" in text  # Table 1's own layout, embedded
    assert "### Wrong material at inference" in text and "| denim_light |" in text
    assert "0.09x the fine simulation's speed" in text  # the timing run's ratio
    for missing in ("Table 2", "the stride ablation", "the flicker study",
                    "the PatchGAN baseline"):
        assert f"**Not run yet**: {missing}." in text
    assert "- table2: `python -m experiments.table2`" in text
    assert "- patchgan: `python -m experiments.patchgan`" in text
    # The sheet-only ablation reads model-card-format results (here the committed card's).
    for name in ("model_card", "sheet_only"):
        (results / name).mkdir()
        (results / name / "results.json").write_text(
            (suite.RESULTS / "model_card" / "results.json").read_text())
    assert report.main(["--results", str(results), "--out", str(out)]) == 0
    text = out.read_text()
    card = json.loads((suite.RESULTS / "model_card" / "results.json").read_text())
    unseen = card["methods"]["model"]["heldout"]["by_kind"]["unseen garment"]["signed_mean"]
    assert f"| sheet only | {unseen:+.1f} |" in text
    # ... and the headline compares it, and the model with its best baseline, in one line each
    assert (f"Sheet-only training (paper Fig. 8), model card's unseen-garment patches: "
            f"{unseen:+.1f} against {unseen:+.1f}") in text
    held = {m: d["heldout"]["all"]["signed_mean"] for m, d in card["methods"].items()}
    best = max((m for m in held if m not in ("model", "identity")), key=held.get)
    assert f"best baseline {best} {held[best]:+.1f}" in text
    assert text.count("- patchgan: `python -m experiments.patchgan`") == 1  # read once
    assert report.main(["--results", str(results), "--out", str(out), "--strict"]) == 1


def test_make_sequences_only_selects_the_named_scenes_in_plan_order():
    from experiments import make_sequences

    jobs = make_sequences.plan(6, 3)
    assert make_sequences.select(jobs, None) == jobs
    got = make_sequences.select(jobs, "cape_walk,sheet_balls_wind")
    assert {j["scene"] for j in got} == {"cape_walk", "sheet_balls_wind"}
    assert got == [j for j in jobs if j["scene"] in ("cape_walk", "sheet_balls_wind")]
    # the sheet trains (fine only, seed 0); the cape is test-only (fine and coarse, seed 1)
    n = len(MATERIALS)
    assert len(got) == n + 2 * n
    assert all(j["seed"] == (0 if j["scene"] == "sheet_balls_wind" else 1) for j in got)
    with pytest.raises(ValueError, match="unknown scenes"):
        make_sequences.select(jobs, "sheet_balls_wind,no_such_scene")


def test_recipe_flag_defaults_are_the_shipped_recipe_and_the_width_study_changes_width_only():
    import argparse

    from experiments import short_runs, train_default

    ap = argparse.ArgumentParser()
    train_default.add_recipe_args(ap)
    cfg = train_default.config_from_args(ap.parse_args([]))
    shipped = enhancer.load_enhancer().meta["train_config"]
    got = cfg.to_json()
    differ = {k for k in shipped if k in got and list(np.atleast_1d(got[k]))
              != list(np.atleast_1d(shipped[k]))}
    assert differ == set()
    studies = short_runs.variants("width", cfg, (8, 32))
    assert list(studies) == ["w8", "w32"]
    for name, c in studies.items():
        assert c.width == int(name[1:])
        assert dataclasses.replace(c, width=cfg.width) == cfg
    res = short_runs.variants("residual", cfg)
    assert not res["plain"].residual and res["residual"].residual


def _fake_fidelity_cell(name, kind, seed):
    rng = np.random.default_rng(seed)
    n = 40
    li = rng.uniform(1, 2, n)

    def method(frac):  # output loss = frac * input loss (score = 100 (1 - frac))
        return {"detail": (li * frac).tolist(), "object": (li * (frac + 0.5)).tolist(),
                "lt16mm": [0.01] * n, "16_64mm": [0.05] * n, "checker": [0.001] * n}

    bands = {"lt16mm": [0.02] * n, "16_64mm": [0.06] * n, "checker": [0.001] * n}
    return {"cell": name, "kind": kind, "loss_input": {"detail": li.tolist(),
                                                       "object": li.tolist()},
            "bands": {"input": bands, "target": bands},
            "methods": {"identity": method(1.0), "unsharp": method(0.6),
                        "new": method(0.3)}}


def test_fidelity_summary_and_report_section():
    from experiments import fidelity

    cells = [_fake_fidelity_cell("dress_dance/silk_charmeuse", "unseen garment", 0),
             _fake_fidelity_cell("cape_walk/silk_charmeuse", "unseen garment", 1)]
    got = fidelity.summarize(cells)["unseen garment"]
    m = got["methods"]
    assert m["identity"]["detail"]["signed_median"] == pytest.approx(0.0, abs=1e-4)
    assert m["unsharp"]["detail"]["signed_median"] == pytest.approx(40.0, abs=1e-3)
    assert m["new"]["detail"]["signed_median"] == pytest.approx(70.0, abs=1e-3)
    vs = m["new"]["detail"]["vs_unsharp"]
    assert vs["n"] == 80 and vs["median_diff"] == pytest.approx(30.0, abs=1e-3)
    assert vs["median_diff_ci"][0] == pytest.approx(30.0, abs=1e-3)
    assert m["new"]["object"]["signed_median"] == pytest.approx(20.0, abs=1e-3)
    assert m["new"]["band_ratio_to_fine"]["16_64mm"] == pytest.approx(0.05 / 0.06)
    assert set(m["new"]["detail"]["cell_medians"]) == {c["cell"] for c in cells}
    rep = report.Report(suite.RESULTS)
    report.fidelity_section(rep, {"unseen garment": got})
    text = "\n".join(rep.lines)
    assert "| new | +70.0 (+70.0) | +30.0 [+30.0, +30.0] |  | +20.0 (+20.0) |" in text
    rows = report.fidelity_headline({"unseen garment": got})
    assert len(rows) == 1 and "**+70.0**" in rows[0] and "median +40.0" in rows[0]
