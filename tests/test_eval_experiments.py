"""Tests for the evaluation scripts (`.table1`, `.table2`, `.temporal`, `.stride`, `.report`,
`.timing`, `.fidelity`) on tiny analytic sheets, a tiny VGG and a tiny random enhancer (no
simulation, no real VGG). The library they use is tested in tests/test_evaluation_*.py.

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
from evaluation_fixtures import (  # tests/ is on sys.path
    PATCH,
    TEXEL,
    sheet_pair,
    sheet_sequence,
    write_cell_files,
)

from experiments import report, stride, table1, table2, temporal, timing
from wrinkle_jax import MATERIALS, enhancer, evaluation
from wrinkle_jax.evaluation import cells as cell_lib
from wrinkle_jax.evaluation import headlines, patchscores, setscores, suite
from wrinkle_jax.evaluation import seams as seam_lib
from wrinkle_jax.sim import scenes

# --------------------------------------------------------------------------------------------
# Table 1
# --------------------------------------------------------------------------------------------


def _spy_on_evaluate_cell(monkeypatch, module) -> list:
    """Record the method names of every `module.evaluate_cell` call (still evaluating)."""
    calls = []
    real = module.evaluate_cell

    def spy(fine, coarse, material, methods, *a, **k):
        calls.append(list(methods))
        return real(fine, coarse, material, methods, *a, **k)

    monkeypatch.setattr(module, "evaluate_cell", spy)
    return calls


def test_table1_main_writes_results_and_resumes_from_stored_cells(tmp_path, monkeypatch,
                                                                  tiny_vgg, model):
    seqs = tmp_path / "seqs"
    write_cell_files(seqs, "dress", "dance", "silk_charmeuse")
    write_cell_files(seqs, "dress", "walk", "silk_charmeuse")
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


# --------------------------------------------------------------------------------------------
# Temporal coherence
# --------------------------------------------------------------------------------------------


def test_temporal_main_writes_results_and_plot(tmp_path, model):
    seqs = tmp_path / "seqs"
    write_cell_files(seqs, "cape", "dance", "denim_light", frames=3)
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
    seq = sheet_sequence(10, 7, 3)
    info = timing.time_pipeline(seq, model, "silk_chiffon", body=None, lift=True, batch_size=4,
                                chunk_size=2)
    assert info["frames"] == 3 and info["warmup_frames"] == 2
    assert set(info["ms_per_frame"]) == set(timing.STAGES)
    for stage in ("bake", "network", "merge", "lift"):
        assert info["ms_per_frame"][stage] > 0
    assert info["ms_per_frame_total"] == pytest.approx(sum(info["ms_per_frame"].values()))
    assert info["compile_s"] > 0 and info["detailed_vertices"] > seq.garment.num_vertices
    # As the CLI: the lift overlaps the next chunk; the wall time covers every stage's work
    # at least once and at most their sum (plus the loop's own overhead).
    assert info["overlap_lift"]
    per = info["ms_per_frame"]
    assert max(per.values()) < info["wall_ms_per_frame"] < 2 * info["ms_per_frame_total"]


def test_time_simulation_counts_simulated_frames_and_separates_the_first_call(monkeypatch):
    calls, solvers = [], []

    def fake_simulate(config, material, resolution, frames, seed, setup=None, progress=None,
                      **solver):
        calls.append(frames)
        solvers.append(solver)
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
    # The legacy recipe passes no solver settings: the scene's substeps, no self-collision.
    assert solvers == [{}, {}] and info["recipe"] == "legacy"
    assert info["substeps"] == scenes.SCENES["dress_dance"].substeps
    assert info["self_collision"] is False
    # The data set's recipe passes scenes.dataset_solver's settings to both calls; without
    # the warm-up only the timed call runs and no compile time is claimed.
    calls.clear()
    solvers.clear()
    _, info = timing.time_simulation(scenes.SCENES["dress_dance"], "silk_charmeuse",
                                     "coarse", frames=70, recipe="dataset", warm_up=False)
    substeps, sc = scenes.dataset_solver("dress_dance", "coarse")
    assert calls == [70] and solvers == [{"substeps": substeps, "self_collision": sc}]
    assert info["substeps"] == substeps == scenes.DATASET_COARSE_SUBSTEPS
    assert info["self_collision"] is True
    assert info["first_call_s"] is None and info["compile_s"] is None
    with pytest.raises(ValueError, match="recipe"):
        timing.solver_settings(scenes.SCENES["dress_dance"], "fine", "fast")


def test_dataset_recipe_is_timed_in_a_child_with_xla_defaults(monkeypatch, tmp_path):
    from wrinkle_jax import cli, runtime

    env = timing.child_env({"XLA_FLAGS": f"--xla_foo=1 {cli.FAST_COMPILE_FLAG}", "HOME": "/h"})
    assert env["XLA_FLAGS"] == "--xla_foo=1" and env["HOME"] == "/h"
    assert env["WRINKLE_JAX_XLA_DEFAULTS"] == "1" and env[runtime.MALLOC_ENV] == "default"
    # The child's own start-up then makes neither setting.
    assert not cli.use_fast_compile(dict(env), backend_started=False)
    assert not runtime.use_retained_memory(env)
    assert "XLA_FLAGS" not in timing.child_env({"XLA_FLAGS": cli.FAST_COMPILE_FLAG})
    assert timing.CHILD_RECIPES == ("dataset",)
    # The child mode: one warmed-up simulation of the given recipe and resolution, its info
    # in child.json (fake solver: the scene's pre-roll of 3 frames, 1 ms per frame).
    calls = []

    def fake_simulate(config, material, resolution, frames, seed, setup=None, progress=None,
                      **solver):
        calls.append((resolution, frames, solver))
        if progress is not None:
            time.sleep(0.001 * (frames + 2))
            progress(frames + 2, frames + 2)
        return SimpleNamespace(metadata={"preroll_frames": 3},
                               garment=SimpleNamespace(num_vertices=7))

    monkeypatch.setattr(timing.scenes, "simulate", fake_simulate)
    monkeypatch.setattr(timing.scenes, "setup_scene", lambda *a, **k: None)
    assert timing.main(["--frames", "4", "--child", "dataset:fine", "--out", str(tmp_path)]) == 0
    info = json.loads((tmp_path / "child.json").read_text())
    substeps, sc = scenes.dataset_solver("dress_dance", "fine")
    assert [c[:2] for c in calls] == [("fine", 1), ("fine", 4)]
    assert calls[1][2] == {"substeps": substeps, "self_collision": sc}
    assert info["recipe"] == "dataset" and info["simulated_frames"] == 6
    assert not (tmp_path / "results.json").exists()


def test_timing_recipes_parse_and_rounds_summarize_by_median():
    assert timing.parse_recipes("dataset, legacy") == ("dataset", "legacy")
    for bad in ("", "legacy,legacy", "legacy,fast"):
        with pytest.raises(ValueError):
            timing.parse_recipes(bad)
    stages = {k: 0.0 for k in timing.STAGES}

    def round_(coarse, fine, network):
        ms = {**stages, "network": network}
        return {"pipeline": {"ms_per_frame": ms, "wall_ms_per_frame": network},
                "pipeline_no_lift": {"wall_ms_per_frame": network / 2},
                "recipes": {"legacy": {"coarse_sim": {"ms_per_frame": coarse},
                                       "fine_sim": {"ms_per_frame": fine},
                                       "ratio": timing.ratios(coarse, fine, ms)}}}

    # Three rounds, one of them slow throughout: the medians ignore it.
    s = timing.summarize([round_(10, 200, 90), round_(40, 900, 400), round_(12, 180, 88)],
                         ("legacy",))
    assert s["pipeline_ms_per_frame"]["network"] == 90.0
    r = s["recipes"]["legacy"]
    assert r["coarse_ms_per_frame"] == 12.0 and r["fine_ms_per_frame"] == 200.0
    assert r["ratio"]["speedup"] == pytest.approx(200.0 / 102.0)
    assert r["ratio"]["speedup_no_lift"] == pytest.approx(200.0 / 57.0)
    assert s["pipeline_wall_ms_per_frame"] == 90.0
    assert r["speedup_per_round"] == pytest.approx([2.0, 900.0 / 440.0, 1.8])


def test_timing_ratios_body_and_plot(tmp_path):
    r = timing.ratios(10.0, 200.0, {"bake": 5.0, "tile": 0.0, "network": 60.0, "merge": 5.0,
                                    "lift": 20.0})
    assert r["ours_ms_per_frame"] == 100.0 and r["speedup"] == 2.0
    assert r["speedup_no_lift"] == 2.5
    # Wall times (the lift overlapping; a run without it) replace the stages' sums.
    r = timing.ratios(10.0, 200.0, {"network": 60.0, "lift": 50.0}, 70.0, 40.0)
    assert r["ours_ms_per_frame"] == 80.0 and r["ours_no_lift_ms_per_frame"] == 50.0
    assert r["speedup"] == 2.5 and r["speedup_no_lift"] == 4.0
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
    results["summary"] = {"recipes": {
        name: {"coarse_ms_per_frame": c, "fine_ms_per_frame": f,
               "ratio": timing.ratios(c, f, results["pipeline"]["ms_per_frame"])}
        for name, c, f in (("legacy", 10.0, 200.0), ("dataset", 90.0, 800.0))}}
    timing.plot(tmp_path / "t2.png", results)
    assert (tmp_path / "t2.png").read_bytes()[:4] == b"\x89PNG"


# --------------------------------------------------------------------------------------------
# Table 2
# --------------------------------------------------------------------------------------------


def test_table2_detail_features_remove_the_large_scale_and_pair_outputs_with_their_input():
    rng = np.random.default_rng(0)
    mask = np.ones((2, 24, 24, 1), np.float32)
    mask[1, :, :6] = 0.0
    tilt = np.array([0.5, -0.3, 0.8]) / np.linalg.norm([0.5, -0.3, 0.8])
    flat = np.broadcast_to((tilt + 1.0) / 2.0, (2, 24, 24, 3)).astype(np.float32) * mask
    bumpy = flat + mask * rng.normal(0.0, 0.03, flat.shape).astype(np.float32)
    a_o, c_o, b_o = table2.to_feature_space("object", bumpy, mask, flat, mask)
    assert a_o is bumpy and c_o is flat and b_o(flat) is flat
    a_d, c_d, b_fn = table2.to_feature_space("detail", bumpy, mask, flat, mask)
    # A tilted plane has no detail: its detail map is +z (RGB 0.5, 0.5, 1) inside the mask.
    inside = mask[..., 0] > 0
    np.testing.assert_allclose(c_d[inside], np.broadcast_to([0.5, 0.5, 1.0], c_d[inside].shape),
                               atol=1e-5)
    assert np.all(c_d[~inside] == 0)
    # The bumps survive, the tilt does not: mean detail near +z, spread kept.
    n = a_d[inside] * 2.0 - 1.0
    assert abs(n[:, 2].mean() - 1.0) < 5e-3 and n[:, :2].std() > 0.02
    # An output equal to the input maps to the input's own detail (same branch).
    np.testing.assert_allclose(b_fn(bumpy), a_d, atol=1e-6)
    with pytest.raises(ValueError, match="unknown feature space"):
        table2.to_feature_space("tangent", bumpy, mask, flat, mask)


def test_table2_main_uses_table1_patches_writes_results_and_resumes(tmp_path, monkeypatch,
                                                                      tiny_vgg, model):
    seqs = tmp_path / "seqs"
    write_cell_files(seqs, "dress", "dance", "silk_charmeuse", frames=4)
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
    for space in setscores.SPACES:
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


# --------------------------------------------------------------------------------------------
# Stride ablation
# --------------------------------------------------------------------------------------------


def test_stride_identity_network_scores_zero_and_leaves_the_coarse_seams(tiny_vgg, model):
    params = {**model.params, "out": jax.tree.map(jax.numpy.zeros_like, model.params["out"])}
    ident = model._replace(params=params)
    fine, coarse = sheet_pair(3)
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
    write_cell_files(seqs, "dress", "walk", "silk_charmeuse", frames=3)
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


def test_report_assembles_stored_results_and_names_what_is_missing(tmp_path, monkeypatch,
                                                                   tiny_vgg, model):
    seqs = tmp_path / "seqs"
    write_cell_files(seqs, "dress", "walk", "silk_charmeuse")
    write_cell_files(seqs, "dress", "walk", "denim_light")
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
    # The robust row leads: the median, and paired differences against each unsharp mask.
    pair = t1["paired_vs_unsharp"]["unseen garment"]["model"]
    assert sorted(pair) == sorted(m for m in unseen if m.startswith("unsharp"))
    assert f"model signed median {unseen['model']['signed_median']:+.1f}; paired" in text
    assert text.index("model signed median") < text.index("model signed mean")
    assert "| silk_charmeuse | walk (unseen) |" in text  # Table 1's own layout, embedded
    assert "### Wrong material at inference" in text and "| denim_light |" in text
    timing_run = json.loads((results / "timing" / "results.json").read_text())
    speedup = timing_run["ratio"]["speedup"]
    assert f"{speedup:.2f}x the fine simulation's speed" in text  # the timing run's ratio
    for name, r in report.timing_ratios(timing_run):  # every solver recipe, table and headline
        assert text.count(f"{r['speedup']:.2f}x the fine simulation's speed") >= 2, name
    if "context" in timing_run:  # the run's own caveats travel with its numbers
        assert timing_run["context"] in text
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


def test_report_table2_section_says_when_its_cells_lag_table1s_simulations(tmp_path):
    def cell(folder, name, sims):
        (tmp_path / folder / "cells").mkdir(parents=True, exist_ok=True)
        meta = {"fingerprint": {} if sims is None else {"simulations": sims}}
        np.savez(tmp_path / folder / "cells" / f"{name}.npz", meta=np.str_(json.dumps(meta)))

    now, old = {"fine": "a", "coarse": "b"}, {"fine": "c", "coarse": "b"}
    cell("table1", "x", now)
    cell("table1", "y", now)
    cell("table2", "x", now)
    rep = report.Report(tmp_path)
    report.table2_section(rep, {"cells": {}})
    assert not any("Not known" in line for line in rep.lines)
    cell("table2", "y", old)
    cell("table2", "z", None)
    cell("table1", "z", now)
    rep = report.Report(tmp_path)
    report.table2_section(rep, {"cells": {}})
    assert ("**Not known to be on Table 1's simulations:** 2 of 3 cells: 1 were scored on "
            "other simulation files than Table 1's cell of the same name, 1 record no digests "
            "(scored before they were kept); rerun `python -m experiments.table2`.") in rep.lines


def test_report_reference_section_reads_both_runs_and_says_what_is_missing():
    unet_run = json.loads((suite.RESULTS / "timing" / "reference_unet.json").read_text())
    train_run = json.loads((suite.RESULTS / "timing" / "reference_train.json").read_text())
    rep = report.Report(suite.RESULTS)
    report.reference_section(rep, unet_run, train_run)
    text = "\n".join(rep.lines)
    for form in ("im2col_bf16", "winograd_bf16"):
        infer = unet_run["unet"]["speedup_vs_authors_wall"][f"ours_{form}"]
        step = train_run["train"]["speedup_vs_authors_wall"][f"ours_{form}"]
        err = unet_run["unet"]["agreement_vs_authors"][form]["rel_rms"]
        assert f"| {form} | {infer:.2f}x | {err:.2%} | {step:.2f}x |" in text
    assert "| xla | " in text and "| - | - |" in text  # timed for inference only
    rep = report.Report(suite.RESULTS)
    report.reference_section(rep, None, None)
    assert "**Not run yet**" in "\n".join(rep.lines)


def test_report_ceiling_section_gives_each_form_its_ceilings():
    run = json.loads((suite.RESULTS / "timing" / "ceiling.json").read_text())
    rep = report.Report(suite.RESULTS)
    report.ceiling_section(rep, run)
    text = "\n".join(rep.lines)
    for part, target in (("infer", 3), ("train", 4)):
        for form, r in run[part]["forms"].items():
            assert (f"| {form} | {r['program_ms']:,.1f} | {r['dots_ms']:,.1f} "
                    f"({r['dots_share']:.0%}) | {r['dots_gflops_per_s']:.0f} "
                    f"| {r['stored_speedup_vs_authors']:.2f}x "
                    f"| {r['ceiling_speedup_vs_authors_dots']:.2f}x / "
                    f"{r['ceiling_speedup_vs_authors_peak']:.2f}x | {target}x |") in text
            # the ceiling is the stored ratio times the program's time over its dots'
            assert r["ceiling_speedup_vs_authors_dots"] == pytest.approx(
                r["stored_speedup_vs_authors"] * r["ceiling_gain_dots"], abs=0.006)
    for form, r in run["shipped"]["forms"].items():  # no side-by-side run: no ceiling vs theirs
        assert (f"| shipped model (pipeline batch {run['shipped']['batch']}) | {form} "
                f"| {r['program_ms']:,.1f} | {r['dots_ms']:,.1f} ({r['dots_share']:.0%}) "
                f"| {r['dots_gflops_per_s']:.0f} | - | - | - |") in text
    rep = report.Report(suite.RESULTS)
    report.ceiling_section(rep, None)
    assert "**Not run yet**" in "\n".join(rep.lines)


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

    from experiments import short_runs
    from wrinkle_jax import recipe

    ap = argparse.ArgumentParser()
    recipe.add_recipe_args(ap)
    cfg = recipe.config_from_args(ap.parse_args([]))
    shipped = enhancer.load_enhancer().meta["train_config"]
    got = cfg.to_json()
    differ = {k for k in shipped if k in got and list(np.atleast_1d(got[k]))
              != list(np.atleast_1d(shipped[k]))}
    # The convolution form is the host's ("auto"; the shipped model trained in im2col_bf16).
    assert differ == {"conv_impl"} and got["conv_impl"] == "auto"
    studies = short_runs.variants("width", cfg, (8, 32))
    assert list(studies) == ["w8", "w32"]
    for name, c in studies.items():
        assert c.unet.width == int(name[1:])
        assert dataclasses.replace(c, unet=dataclasses.replace(c.unet, width=cfg.unet.width)) == cfg
    res = short_runs.variants("residual", cfg)
    assert not res["plain"].unet.residual and res["residual"].unet.residual


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
    # Columns: vs the val-swept unsharp, vs the card's, vs the per-material gains (absent here).
    assert "| new | +70.0 (+70.0) | +30.0 [+30.0, +30.0] |  |  | +20.0 (+20.0) |" in text
    rows = headlines.fidelity_headline({"unseen garment": got})
    assert len(rows) == 1 and "**+70.0**" in rows[0] and "median +40.0" in rows[0]
