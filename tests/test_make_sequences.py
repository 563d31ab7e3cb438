"""experiments.make_sequences: the self-collision setting per job and the resume guard (a folder
simulated with one setting is never topped up with the other)."""

import json

import pytest

from experiments import make_sequences
from wrinkle_jax.sim import scenes


def test_self_collision_per_resolution():
    for res in ("fine", "coarse"):
        assert make_sequences.self_collision_for(res, "on") is scenes.SELF_COLLISION[res]
        assert make_sequences.self_collision_for(res, "off") is None
    with pytest.raises(ValueError, match="'on' or 'off'"):
        make_sequences.self_collision_for("fine", "yes")


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
