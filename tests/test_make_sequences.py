"""experiments.make_sequences: the self-collision setting per job and the resume guard (a folder
simulated with one setting is never topped up with the other)."""

import dataclasses
import json

import numpy as np
import pytest

from experiments import make_sequences
from wrinkle_jax.sim import scenes


def test_self_collision_per_resolution():
    for res in ("fine", "coarse"):
        assert make_sequences.self_collision_for(res, "on") is scenes.SELF_COLLISION[res]
        assert make_sequences.self_collision_for(res, "off") is None
        assert make_sequences.self_collision_for(res, "off", 80) is None
        on80 = make_sequences.self_collision_for(res, "on", 80)
        assert on80 == scenes.self_collision_config(res, 80) and on80.rebuild_every == 16
    with pytest.raises(ValueError, match="'on' or 'off'"):
        make_sequences.self_collision_for("fine", "yes")


def test_a_scene_may_rebuild_its_fine_candidates_more_often():
    """skirt_walk's and skirt_dance2's fine candidates are rebuilt every 2 substeps (the hem
    outruns the margin at 4); their coarse ones and every other scene's keep the default, and
    the scene JSON of scenes without the setting is what their stored files hold."""
    fine = scenes.SELF_COLLISION["fine"]
    walk = make_sequences.self_collision_for("fine", "on", None, "skirt_walk")
    assert walk == dataclasses.replace(fine, rebuild_every=2, post_passes=3)
    assert scenes.dataset_solver("skirt_walk", "fine") == (20, walk)
    assert make_sequences.self_collision_for("fine", "on", None, "skirt_dance2") == (
        dataclasses.replace(walk, rest_exclusion=0.014))      # and its folds seen (session 37)
    assert make_sequences.self_collision_for("fine", "on", None, "skirt_dance") is fine
    assert scenes.self_collision_config("fine", None, "pleated_skirt_dance2") == (
        dataclasses.replace(fine, post_passes=3))
    coarse = make_sequences.self_collision_for("coarse", "on", 80, "skirt_walk")
    assert coarse == scenes.self_collision_config("coarse", 80)
    # Kept in time at more substeps, as the default is: every 2 of 20 -> every 8 of 80.
    assert scenes.self_collision_config("fine", 80, "skirt_walk").rebuild_every == 8
    # A solver setting (in the files' "self_collision" metadata), not part of the scene's
    # identity: the stored coarse files of these scenes still match.
    walk_scene = scenes.get_scene("skirt_walk")
    plain = dataclasses.replace(walk_scene, fine_self_collision=())
    assert walk_scene.to_json() == plain.to_json()
    bad = dataclasses.replace(walk_scene, fine_self_collision=(("rebuild_evry", 2),))
    with pytest.raises(scenes.SceneError, match="rebuild_evry"):
        scenes.self_collision_config("fine", None, bad)


def test_resume_refuses_another_self_collision_setting(tmp_path):
    (tmp_path / "manifest.json").write_text(json.dumps(
        {"jobs": 1, "version": {"self_collision": "off", "commit": "abc"}, "done": []}))
    with pytest.raises(SystemExit) as e:  # argparse's error: before any simulation
        make_sequences.main(["--out", str(tmp_path), "--tiny", "--only", "apron_dance"])
    assert e.value.code == 2
    assert not (tmp_path / "apron_dance").exists()


def test_git_commit_of_the_checkout_and_of_a_plain_folder(tmp_path):
    from wrinkle_jax.fileio import git_commit

    head = git_commit(make_sequences.ROOT)
    assert head is None or (4 <= len(head) <= 40 and int(head, 16) >= 0)  # None without git
    assert git_commit(tmp_path) is None


def test_coarse_substeps_apply_to_coarse_jobs_only():
    assert make_sequences.substeps_for("coarse", 80) == 80
    assert make_sequences.substeps_for("fine", 80) is None  # the scene's own
    assert make_sequences.substeps_for("coarse", None) is None
    with pytest.raises(ValueError, match=">= 1"):
        make_sequences.substeps_for("coarse", 0)


@pytest.mark.parametrize("stored, given", [(None, []), (None, ["--coarse-substeps", "80"]),
                                           (20, []), (80, ["--coarse-substeps", "40"])])
def test_resume_refuses_other_coarse_substeps(tmp_path, stored, given):
    version = {"self_collision": "on", "commit": "abc"}
    if stored is not None:
        version["coarse_substeps"] = stored  # a manifest from before the option has no entry
    done = [{"scene": "dress_dance", "resolution": "coarse", "material": "silk_charmeuse",
             "seed": 1, "frames": 300, "path": "dress_dance/silk_charmeuse_coarse_s1.npz"}]
    (tmp_path / "manifest.json").write_text(json.dumps({"jobs": 1, "version": version,
                                                        "done": done}))
    with pytest.raises(SystemExit) as e:
        make_sequences.main(["--out", str(tmp_path), "--tiny", "--only", "apron_dance", *given])
    assert e.value.code == 2
    assert not (tmp_path / "apron_dance").exists()


def test_a_folder_of_fine_files_takes_any_coarse_substeps(tmp_path, monkeypatch):
    done = [{"scene": "skirt_dance", "resolution": "fine", "material": "silk_charmeuse",
             "seed": 0, "frames": 600, "path": "skirt_dance/silk_charmeuse_fine_s0.npz"}]
    (tmp_path / "manifest.json").write_text(json.dumps(
        {"jobs": 1, "version": {"self_collision": "on", "commit": "abc"}, "done": done}))
    calls = []
    monkeypatch.setattr(make_sequences.scenes, "setup_scene", lambda *a, **k: None)
    monkeypatch.setattr(make_sequences.scenes, "simulate",
                        lambda *a, substeps=None, **k: calls.append(substeps) or 1 / 0)
    assert make_sequences.main(["--out", str(tmp_path), "--tiny", "--only", "apron_dance",
                                "--coarse-substeps", "80"]) == 1  # the fake job fails
    assert calls == [80]


def test_the_coarse_substeps_reach_the_simulation(tmp_path, monkeypatch):
    calls = []

    class Stop(Exception):
        pass

    def fake_simulate(scene, material, resolution, frames, seed, substeps=None, **kw):
        calls.append((resolution, substeps))
        raise Stop  # logged as a failed job; nothing is simulated

    monkeypatch.setattr(make_sequences.scenes, "setup_scene", lambda *a, **k: None)
    monkeypatch.setattr(make_sequences.scenes, "simulate", fake_simulate)
    code = make_sequences.main(["--out", str(tmp_path), "--tiny", "--only", "apron_dance",
                                "--coarse-substeps", "80"])
    assert code == 1 and calls == [("coarse", 80)]  # --tiny: one coarse job per scene
    assert "FAILED" in (tmp_path / "make_sequences.log").read_text()


def test_dataset_solver_is_what_make_sequences_writes_by_default():
    """The evaluations reuse data-set files only if they match `scenes.dataset_solver`, so it
    must name make_sequences' default settings: coarse at its default substeps, fine at the
    scene's own, self-collision on."""
    default = scenes.DATASET_COARSE_SUBSTEPS
    for name in ("dress_dance", "skirt_dance", "skirt_walk"):
        sc = scenes.get_scene(name)
        for res in ("fine", "coarse"):
            substeps = make_sequences.substeps_for(res, default)
            want = (sc.substeps if substeps is None else substeps,
                    make_sequences.self_collision_for(res, "on", substeps, name))
            assert scenes.dataset_solver(name, res) == want
    assert scenes.dataset_solver("dress_dance", "coarse")[0] == 80
    assert scenes.dataset_solver("dress_dance", "coarse")[1].rebuild_every == 16


def test_each_job_checkpoints_under_partial_and_a_rerun_says_it_resumes(tmp_path, monkeypatch):
    calls = []

    def fake_simulate(scene, material, resolution, frames, seed, checkpoint=None,
                      checkpoint_every_s=None, **kw):
        calls.append((checkpoint, checkpoint_every_s))
        raise RuntimeError("killed")

    monkeypatch.setattr(make_sequences.scenes, "setup_scene", lambda *a, **k: None)
    monkeypatch.setattr(make_sequences.scenes, "simulate", fake_simulate)
    args = ["--out", str(tmp_path), "--tiny", "--only", "apron_dance", "--checkpoint-every", "60"]
    assert make_sequences.main(args) == 1
    (path, every), = calls
    job = next(j for j in make_sequences.plan(3, 3) if j["scene"] == "apron_dance")
    job = dict(job, frames=3, resolution="coarse")
    assert path == make_sequences.partial_path(tmp_path, job) and every == 60
    assert path.parent == tmp_path / ".partial" / "apron_dance" and path.suffix == ".partial"
    path.parent.mkdir(parents=True, exist_ok=True)  # (its job's claim made it)
    path.write_bytes(b"")  # a checkpoint left by a killed run
    assert make_sequences.main(args) == 1
    assert "resuming from .partial/apron_dance/" in (tmp_path / "make_sequences.log").read_text()


def test_a_file_written_meanwhile_by_another_run_is_not_simulated_again(tmp_path, monkeypatch):
    """Two runs share the folder (a second one with --only): a job whose file appeared after
    this run started is skipped, not simulated and overwritten."""
    calls = []

    def fake_simulate(scene, material, resolution, frames, seed, **kw):
        calls.append(scene)
        name = ({"apron_dance", "skirt_dance"} - {scene}).pop()
        other = make_sequences.job_path(tmp_path, {"scene": name, "material": material,
                                                   "resolution": resolution, "seed": 0})
        other.parent.mkdir(parents=True, exist_ok=True)
        other.write_bytes(b"written by the other run")
        raise RuntimeError("stop here")

    monkeypatch.setattr(make_sequences.scenes, "setup_scene", lambda *a, **k: None)
    monkeypatch.setattr(make_sequences.scenes, "simulate", fake_simulate)
    args = ["--out", str(tmp_path), "--tiny", "--only", "apron_dance,skirt_dance"]
    assert make_sequences.main(args) == 1
    assert len(calls) == 1  # the first job only; the second's file appeared meanwhile
    assert "written by another run, skipped" in (tmp_path / "make_sequences.log").read_text()


def test_a_job_another_process_is_simulating_is_skipped(tmp_path, monkeypatch):
    """Two runs share the plan: a job whose claim another process holds is not started, and
    the claim is released when a job ends (here: fails), so a rerun takes it."""
    from wrinkle_jax.fileio import claim

    calls = []

    def fake_simulate(scene, material, resolution, frames, seed, checkpoint=None, **kw):
        calls.append(scene)
        assert checkpoint.with_suffix(".lock").exists()  # held while it runs
        raise RuntimeError("stop here")

    monkeypatch.setattr(make_sequences.scenes, "setup_scene", lambda *a, **k: None)
    monkeypatch.setattr(make_sequences.scenes, "simulate", fake_simulate)
    job = next(j for j in make_sequences.plan(3, 3) if j["scene"] == "apron_dance")
    lock = make_sequences.partial_path(tmp_path, dict(job, frames=3, resolution="coarse"))
    args = ["--out", str(tmp_path), "--tiny", "--only", "apron_dance,skirt_dance"]
    with claim(lock.with_suffix(".lock")) as mine:
        assert mine
        assert make_sequences.main(args) == 1
    assert calls == ["skirt_dance"]
    log = (tmp_path / "make_sequences.log").read_text()
    assert "apron_dance silk_charmeuse coarse: running in another process, skipped" in log
    assert make_sequences.main(args) == 1 and calls[1:] == ["skirt_dance", "apron_dance"]
    assert not list((tmp_path / ".partial").rglob("*.lock"))


def test_status_counts_files_checkpoints_and_hours_left_at_the_written_rates(tmp_path):
    """--status: a written file's rate (its metadata) prices the rest of its scene; a scene
    with no file is priced by EST_MS times the written files' ratio to EST_MS; a checkpoint
    counts its frames as done; a damaged file counts as not written."""
    import json

    jobs = [j for j in make_sequences.plan(600, 300)
            if j["scene"] in ("apron_dance", "shawl_dance2")]
    apron = [j for j in jobs if j["scene"] == "apron_dance"]
    est = make_sequences.EST_MS["apron_dance"][0]
    for job, ms in zip(apron[:2], (3 * est, 4 * est), strict=True):
        path = make_sequences.job_path(tmp_path, job)
        path.parent.mkdir(parents=True, exist_ok=True)
        np.savez(path, metadata=np.str_(json.dumps({"ms_per_frame": ms})))
    partial = make_sequences.partial_path(tmp_path, apron[2])
    partial.parent.mkdir(parents=True, exist_ok=True)
    with open(partial, "wb") as fh:  # (np.savez would append .npz to the name)
        np.savez(fh, done=np.int64(100))
    make_sequences.job_path(tmp_path, apron[3]).write_bytes(b"cut short")
    rows = make_sequences.job_status(tmp_path, jobs)
    by = {(r["scene"], r["material"]): r for r in rows}
    total = 600 + int(round(scenes.get_scene("apron_dance").preroll_s * 30)) - 1
    first, third, fourth = (by[("apron_dance", j["material"])] for j in apron[:3:2] + [apron[3]])
    assert first["state"] == "done" and first["frames_left"] == 0
    assert first["ms_per_frame"] == 3 * est and first["source"] == "file"
    assert third["state"] == "partial" and third["frames_left"] == total - 100
    assert third["ms_per_frame"] == 3 * est and third["source"] == "scene"  # the fastest
    assert fourth["state"] == "todo" and fourth["frames_left"] == total
    shawl = by[("shawl_dance2", "silk_charmeuse")]
    assert shawl["ms_per_frame"] == pytest.approx(3 * make_sequences.EST_MS["shawl_dance2"][0])
    assert shawl["source"] == "estimate x 3.0"
    text = make_sequences.status_text(rows)
    hours = ((total - 100) + 2 * total) * 3 * est / 3.6e6 + 5 * (
        total * 3 * make_sequences.EST_MS["shawl_dance2"][0]) / 3.6e6
    assert "| apron_dance | fine | 2 | 1 | 2 |" in text
    assert f"2 of 10 files written; {hours:.1f} hours of simulation left" in text


@pytest.mark.parametrize("module, args, lock", [
    ("make_coarse_training_sequences", ["--scenes", "apron_dance"],
     "apron_dance/{}_coarse_s0.npz.lock"),
    ("classifier_sequences", ["--cells", "dress_dance"], "dress_dance/{}_coarse_s1.npz.lock"),
])
def test_coarse_runs_skip_a_file_another_run_is_simulating(tmp_path, monkeypatch, module, args,
                                                           lock):
    """The coarse training and classifier sequence runs claim each file, as make_sequences
    does: a file whose claim another process holds is not simulated."""
    import importlib

    from wrinkle_jax import MATERIALS
    from wrinkle_jax.fileio import claim

    runs = importlib.import_module(f"experiments.{module}")
    calls = []

    def fake_simulate(scene, material, *a, **k):
        calls.append(material)
        raise RuntimeError("stop here")

    monkeypatch.setattr(runs.scenes, "setup_scene",
                        lambda name, *a, **k: dataclasses.make_dataclass("S", ["scene"])(name))
    monkeypatch.setattr(runs.scenes, "simulate", fake_simulate)
    lock = tmp_path / ".partial" / lock.format(MATERIALS[0])
    with claim(lock) as mine, pytest.raises(RuntimeError, match="stop here"):
        assert mine
        runs.main(["--out", str(tmp_path), "--frames", "3", *args])
    assert calls == [MATERIALS[1]]  # the first fabric's file is another run's
    assert not lock.exists()


def test_the_plan_seeds_are_the_data_sets():
    """Every job's seed is `scenes.dataset_seed`: the test scenes' unseen performance (the
    evaluation's TEST_SEED), 0 for the training and validation scenes."""
    from wrinkle_jax.evaluation import cells

    jobs = make_sequences.plan(3, 3, 3)
    assert {(j["scene"], j["seed"]) for j in jobs} == (
        {(n, 0) for n in scenes.TRAINING_SCENES + scenes.VAL_SCENES}
        | {(n, cells.TEST_SEED) for n in scenes.TEST_SCENES})
    assert cells.TEST_SEED == 1 and scenes.dataset_seed("skirt_walk") == 1

