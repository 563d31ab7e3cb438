"""Tests for sim.scenes, sim.command and sim.intersect: determinism, metadata and tracks,
the `simulate` command's exit codes, and the self-intersection counter."""

from __future__ import annotations

import argparse
import dataclasses
import json

import numpy as np
import pytest

from wrinkle_jax import meshio
from wrinkle_jax.sim import command, intersect, mannequin, scenes

# A tiny variant of the base scene: PD 60 mm, a short pre-roll.
TINY = dataclasses.replace(scenes.get_scene("sheet_balls_wind"), name="tiny_sheet",
                           preroll_s=0.2, substeps=8)


def test_same_seed_bit_identical_and_different_seed_differs():
    a = scenes.simulate(TINY, "silk_chiffon", 0.06, frames=4, seed=3)
    b = scenes.simulate(TINY, "silk_chiffon", 0.06, frames=4, seed=3)
    c = scenes.simulate(TINY, "silk_chiffon", 0.06, frames=4, seed=4)
    assert a.frames.shape == (4, a.garment.num_vertices, 3)
    np.testing.assert_array_equal(a.frames, b.frames)
    assert not np.array_equal(a.frames, c.frames)


def test_metadata_tracks_and_roundtrip(tmp_path):
    seq = scenes.simulate(TINY, "denim_light", 0.06, frames=3, seed=1)
    meta = seq.metadata
    assert meta["material"] == "denim_light" and meta["material_index"] == 4
    assert meta["pd"] == pytest.approx(0.06)
    assert json.loads(meta["scene_config"])["name"] == "tiny_sheet"
    assert seq.tracks["sphere_centers"].shape == (3, 2, 3)
    assert seq.tracks["pins"].shape[0] == 3
    path = tmp_path / "s.npz"
    scenes.save_simulation(path, seq)
    back = meshio.load_sequence(path)
    np.testing.assert_array_equal(back.frames, seq.frames)
    assert back.metadata["scene"] == "tiny_sheet"
    with np.load(path) as z:
        np.testing.assert_array_equal(z["sphere_centers"], seq.tracks["sphere_centers"])
        # UVs are pattern coordinates in meters.
        assert z["uvs"].max() == pytest.approx(1.0, abs=1e-5)


def test_scene_registry_and_errors():
    assert set(scenes.TRAINING_SCENES) == {
        "sheet_balls_wind", "skirt_dance", "pleated_skirt_dance2", "shawl_dance2", "apron_dance",
        "circle_skirt_dance2", "long_shawl_dance", "skirt_dance2", "apron_dance2"}
    assert {"dress_dance", "cape_walk"} <= set(scenes.TEST_SCENES)
    assert scenes.VAL_SCENES == ("tabard_dance2",)
    held = {scenes.get_scene(n).garment for n in scenes.TEST_SCENES + scenes.VAL_SCENES}
    for name in scenes.TRAINING_SCENES:
        s = scenes.get_scene(name)
        assert s.garment not in held - {"flared_skirt"}  # skirt_walk holds out a motion only
        assert s.motion not in mannequin.TEST_MOTIONS
    for name in scenes.VAL_SCENES:  # the validation garment is neither trained nor held out
        s = scenes.get_scene(name)
        assert s.val_only and not s.test_only and s.motion not in mannequin.TEST_MOTIONS
        assert s.garment not in {scenes.get_scene(n).garment
                                 for n in scenes.TRAINING_SCENES + scenes.TEST_SCENES}
    # Older scenes' JSON is unchanged by the val_only field (stored simulations still match).
    assert "val_only" not in json.loads(scenes.get_scene("dress_dance").to_json())
    assert json.loads(scenes.get_scene("tabard_dance2").to_json())["val_only"] is True
    with pytest.raises(scenes.SceneError, match="unknown scene"):
        scenes.get_scene("ballroom")
    with pytest.raises(ValueError, match="unknown material"):
        scenes.simulate(TINY, "velvet", 0.06, frames=1)
    with pytest.raises(scenes.SceneError, match="resolution"):
        scenes.resolution_pd("ultra")


def test_mannequin_tracks_shapes_and_rest():
    t = np.linspace(-0.5, 2.0, 40)
    for motion in mannequin.MOTIONS:
        ends, radii, frames = mannequin.body_tracks(motion, t, seed=0)
        assert ends.shape == (40, len(mannequin.CAPSULES), 2, 3) and radii.shape == (14,)
        assert np.isfinite(ends).all()
        # Pre-roll (t < 0) is the rest pose for every motion.
        rest, _, _ = mannequin.body_tracks("rest", t[:1])
        np.testing.assert_allclose(ends[0], rest[0], atol=1e-6)
        rot = frames["pelvis"][:, :, :3]
        eye = np.broadcast_to(np.eye(3), rot.shape)
        np.testing.assert_allclose(rot @ rot.transpose(0, 2, 1), eye, atol=1e-6)


def _parse(argv):
    parser = argparse.ArgumentParser(prog="wrinkle-jax")
    sub = parser.add_subparsers(dest="command", required=True)
    command.add_simulate_parser(sub)
    return parser.parse_args(argv)


def test_command_writes_sequence(tmp_path, capsys, monkeypatch):
    monkeypatch.setitem(scenes.SCENES, "sheet_balls_wind", TINY)
    monkeypatch.setitem(scenes.RESOLUTIONS, "coarse", 0.06)
    out = tmp_path / "o.npz"
    args = _parse(["simulate", "sheet_balls_wind", "--material", "knit_terry",
                   "--resolution", "coarse", "--frames", "2", "--out", str(out)])
    assert args.func(args) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["frames"] == 2 and out.exists()
    assert meshio.load_sequence(out).metadata["material"] == "knit_terry"
    bad = _parse(["simulate", "sheet_balls_wind", "--material", "knit_terry",
                  "--frames", "1", "--out", str(tmp_path / "o.txt")])
    assert bad.func(bad) == 1
    assert "npz" in capsys.readouterr().err


def test_command_bad_usage_exits_2():
    for argv in (["simulate", "nope", "--material", "knit_terry", "--out", "x.npz"],
                 ["simulate", "skirt_dance", "--material", "velvet", "--out", "x.npz"],
                 ["simulate", "skirt_dance", "--material", "knit_terry", "--frames", "0",
                  "--out", "x.npz"]):
        with pytest.raises(SystemExit) as e:
            _parse(argv)
        assert e.value.code == 2


def test_self_intersection_counter():
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0],           # triangle in z = 0
                  [0.2, 0.2, -0.5], [0.3, 0.2, 0.5], [0.2, 0.3, 0.5],  # pierces it
                  [1, 1, 0], [2, 1, 0], [1, 2, 0]], float)   # far away
    f = np.array([[0, 1, 2], [3, 4, 5], [6, 7, 8], [1, 6, 2]])  # the last shares vertices
    pairs = intersect.intersecting_pairs(v, f)
    assert pairs.tolist() == [[0, 1]]
    stats = intersect.self_intersection_stats(np.stack([v, v + 1]), f)
    assert stats["counts"] == [1, 1] and stats["frames_with_intersections"] == 1.0
    assert stats["face_fractions"] == [0.5, 0.5] and stats["max_face_fraction"] == 0.5
    # The worst frame, not the mean: a second frame with the piercing triangle moved away.
    apart = v.copy()
    apart[3:6, 2] += 2.0
    stats = intersect.self_intersection_stats(np.stack([v, apart]), f)
    assert stats["face_fractions"] == [0.5, 0.0]
    assert stats["mean_face_fraction"] == 0.25 and stats["max_face_fraction"] == 0.5
    # A flat sheet does not intersect itself.
    from wrinkle_jax.primitives import grid_sheet

    g = grid_sheet(10, 10)
    assert len(intersect.intersecting_pairs(g.vertices, g.faces)) == 0


def test_self_collision_settings_fit_every_scene():
    # The named per-resolution settings must build a solver for every data-set scene
    # (rebuild_every divides the substeps, else cloth_simulator raises), keep the thickness
    # below half the particle distance (a flat sheet's non-adjacent vertex-triangle distances
    # are >= ~0.8 PD: a thicker layer would push apart the rest shape) and have a margin that
    # covers 2 m/s of relative motion over the substeps between rebuilds.
    from wrinkle_jax.sim import xpbd

    assert set(scenes.SELF_COLLISION) == set(scenes.RESOLUTIONS)
    for res, sc in scenes.SELF_COLLISION.items():
        assert 0 < sc.thickness < 0.5 * scenes.RESOLUTIONS[res]
        for scene in scenes.SCENES.values():
            config = xpbd.SimConfig(substeps=scene.substeps, self_collision=sc)
            xpbd.cloth_simulator(config)  # raises when rebuild_every does not divide
            assert sc.margin >= 2.0 * sc.rebuild_every * config.h


def test_self_collision_config_keeps_the_rebuild_interval_in_time():
    # More substeps must not rebuild candidates more often in time than the tuned settings (the
    # build dominates the cost), nor less often than the margin covers (2 m/s between rebuilds),
    # and rebuild_every must divide the substeps (else the solver cannot be built).
    from wrinkle_jax.sim import xpbd

    for res, base in scenes.SELF_COLLISION.items():
        assert scenes.self_collision_config(res) is base
        assert scenes.self_collision_config(res, scenes.SELF_COLLISION_SUBSTEPS) is base
        assert scenes.self_collision_config(res, 80).rebuild_every == 16
        for n in (5, 7, 33, 40, 80, 90):
            sc = scenes.self_collision_config(res, n)
            assert dataclasses.replace(sc, rebuild_every=base.rebuild_every) == base
            assert n % sc.rebuild_every == 0
            assert sc.rebuild_every / n <= base.rebuild_every / scenes.SELF_COLLISION_SUBSTEPS
            config = xpbd.SimConfig(substeps=n, self_collision=sc)
            xpbd.cloth_simulator(config)
            assert sc.margin >= 2.0 * sc.rebuild_every * config.h
    with pytest.raises(scenes.SceneError, match="resolution"):
        scenes.self_collision_config("medium", 80)
    with pytest.raises(scenes.SceneError, match=">= 1"):
        scenes.self_collision_config("coarse", 0)


def test_resimulate_continues_a_stored_run_with_its_or_other_settings(tmp_path, monkeypatch):
    # Thick enough to act on this tiny sheet: with the data set's 9 mm layer its frames are the
    # same with self-collision off, and the test could not tell whether it ran.
    cfg = dataclasses.replace(scenes.self_collision_config("coarse"), thickness=0.025,
                              rest_exclusion=0.05)
    # Chunks of 3 frames, as the continuation below runs: one solver program for both.
    seq = scenes.simulate(TINY, "silk_chiffon", 0.06, frames=6, seed=3, self_collision=cfg,
                          chunk=3)
    path = tmp_path / "s.npz"
    scenes.save_simulation(path, seq)
    back = meshio.load_sequence(path)  # the settings come back through the JSON metadata
    seen = []
    real = scenes.xpbd.simulate_frames
    monkeypatch.setattr(scenes.xpbd, "simulate_frames",
                        lambda config, *a, **k: seen.append(config) or real(config, *a, **k))
    xs = scenes.resimulate(back, 2, 5, scene=TINY)
    # By default the file's settings, read back from its metadata.
    assert seen[0].self_collision == cfg and seen[0].substeps == TINY.substeps
    assert xs.shape == (3,) + back.frames.shape[1:]
    # The velocity is a finite difference of the stored frames, so the continuation is close
    # to the stored run, not equal: the first frame is nearer its stored self than its start.
    err = np.abs(xs[0] - back.frames[3]).max()
    assert 0 < err < 0.25 * np.abs(back.frames[3] - back.frames[2]).max()
    np.testing.assert_array_equal(xs, scenes.resimulate(back, 2, 5, self_collision=cfg,
                                                        substeps=TINY.substeps, scene=TINY))
    # Other settings reach the solver's config (read there, not run: each would compile
    # another solver, ~6 s of the suite).
    def stop(config, *a, **k):
        seen.append(config)
        raise InterruptedError

    monkeypatch.setattr(scenes.xpbd, "simulate_frames", stop)
    for other in ({"substeps": 4}, {"self_collision": None}):
        with pytest.raises(InterruptedError):
            scenes.resimulate(back, 2, 5, scene=TINY, **other)
        want = {"substeps": TINY.substeps, "self_collision": cfg} | other
        assert (seen[-1].substeps, seen[-1].self_collision) == (want["substeps"],
                                                                 want["self_collision"])
    monkeypatch.setattr(scenes.xpbd, "simulate_frames", real)
    # The final state comes with the same frames on request (its dropped-candidate counts).
    again, final = scenes.resimulate(back, 2, 5, scene=TINY, return_state=True)
    np.testing.assert_array_equal(again, xs)
    np.testing.assert_array_equal(np.asarray(final.x), xs[-1])
    assert np.asarray(final.self_overflow).shape == (3,)
    with pytest.raises(scenes.SceneError, match="start"):
        scenes.resimulate(back, 0, 3, scene=TINY)
    with pytest.raises(scenes.SceneError, match="start"):
        scenes.resimulate(back, 2, 6, scene=TINY)  # frame 6 was never stored
    with pytest.raises(scenes.SceneError, match="differs"):
        scenes.resimulate(back, 2, 5, scene=dataclasses.replace(TINY, substeps=9))
