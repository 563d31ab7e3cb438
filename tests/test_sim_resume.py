"""Tests for sim.resume through `scenes.simulate(checkpoint=...)`: a run killed between chunks
resumes bit-identically (with and without self-collision), a checkpoint of other settings is
ignored, and the checkpoint is gone once the simulation completes."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from wrinkle_jax.sim import resume, scenes
from wrinkle_jax.sim.selfcollision import SelfCollisionConfig

TINY = dataclasses.replace(scenes.get_scene("sheet_balls_wind"), name="tiny_sheet",
                           preroll_s=0.2, substeps=8)


class Killed(Exception):
    pass


def _kill_after(frames_done):
    def progress(done, total):
        if done >= frames_done:
            raise Killed
    return progress


@pytest.mark.parametrize("sc", [None, SelfCollisionConfig(thickness=0.004, margin=0.01,
                                                          rebuild_every=2)])
def test_killed_run_resumes_bit_identically(tmp_path, sc):
    kw = dict(frames=6, seed=2, chunk=2, self_collision=sc)
    whole = scenes.simulate(TINY, "silk_chiffon", 0.06, **kw)
    ck = tmp_path / "run.partial"
    with pytest.raises(Killed):  # killed after the third chunk (pre-roll included)
        scenes.simulate(TINY, "silk_chiffon", 0.06, checkpoint=ck, checkpoint_every_s=0,
                        progress=_kill_after(6), **kw)
    key_done = resume.load(ck, _key_of(ck))[0]
    assert key_done == 6
    seen = []
    again = scenes.simulate(TINY, "silk_chiffon", 0.06, checkpoint=ck,
                            progress=lambda d, t: seen.append(d), **kw)
    assert seen[0] == 6  # reported where it resumed, then went on
    np.testing.assert_array_equal(again.frames, whole.frames)
    assert again.metadata["resumed_at_frame"] == 6
    assert whole.metadata["resumed_at_frame"] == 0
    assert again.metadata["self_overflow"] == whole.metadata["self_overflow"]
    assert not ck.exists()


def test_checkpoint_of_other_settings_is_ignored(tmp_path):
    ck = tmp_path / "run.partial"
    with pytest.raises(Killed):
        scenes.simulate(TINY, "silk_chiffon", 0.06, frames=4, seed=2, chunk=2, checkpoint=ck,
                        checkpoint_every_s=0, progress=_kill_after(2))
    assert ck.exists()
    with pytest.warns(UserWarning, match="other settings"):
        other = scenes.simulate(TINY, "denim_light", 0.06, frames=4, seed=2, chunk=2,
                                checkpoint=ck)
    fresh = scenes.simulate(TINY, "denim_light", 0.06, frames=4, seed=2, chunk=2)
    np.testing.assert_array_equal(other.frames, fresh.frames)
    assert other.metadata["resumed_at_frame"] == 0


def test_an_unreadable_checkpoint_is_replaced(tmp_path):
    ck = tmp_path / "run.partial"
    ck.write_bytes(b"PK\x03\x04 truncated")
    with pytest.warns(UserWarning, match="unreadable checkpoint"):
        got = scenes.simulate(TINY, "silk_chiffon", 0.06, frames=2, seed=2, chunk=2,
                              checkpoint=ck)
    fresh = scenes.simulate(TINY, "silk_chiffon", 0.06, frames=2, seed=2, chunk=2)
    np.testing.assert_array_equal(got.frames, fresh.frames)
    assert not ck.exists()


def test_checkpoints_wait_for_their_interval(tmp_path):
    ck = tmp_path / "run.partial"
    with pytest.raises(Killed):  # an hour between checkpoints: none written in 3 chunks
        scenes.simulate(TINY, "silk_chiffon", 0.06, frames=6, seed=2, chunk=2, checkpoint=ck,
                        checkpoint_every_s=3600, progress=_kill_after(6))
    assert not ck.exists()


def _key_of(path):
    with np.load(path) as z:
        return str(z["key"])


def test_a_checkpoint_gets_the_usual_file_mode(tmp_path, monkeypatch):
    import os
    import stat

    from wrinkle_jax import fileio
    from wrinkle_jax.sim.cloth_model import ClothState

    monkeypatch.setattr(fileio, "_UMASK", 0o002)  # 0o664, neither mkstemp's 0o600 nor 0o644
    x = np.zeros((3, 3), np.float32)
    path = tmp_path / "ck.npz"
    resume.save(path, "k", 2, ClothState(x=x, v=x, self_overflow=None), x[None], 1.5)
    assert stat.S_IMODE(os.stat(path).st_mode) == 0o664
    assert resume.load(path, "k")[0] == 2 and os.listdir(tmp_path) == ["ck.npz"]
