"""experiments.self_intersections: which files it reads (training and validation scenes at
seed 0, test scenes at seed 1, `--scenes` to measure only some) and what it counts."""

import json

import numpy as np

from experiments import self_intersections
from wrinkle_jax.mesh import Garment
from wrinkle_jax.meshio import make_sequence, save_sequence
from wrinkle_jax.sim import scenes


def _two_triangles(crossing: bool, frames: int = 3):
    """Two separate triangles; the second pierces the first when `crossing` (one pair)."""
    a = [[0, 0, 0], [1, 0, 0], [0, 1, 0]]
    b = [[0.2, 0.2, -0.5], [0.3, 0.2, 0.5], [0.2, 0.3, 0.5]] if crossing else \
        [[0.2, 0.2, 0.5], [0.3, 0.2, 0.6], [0.2, 0.3, 0.6]]
    v = np.asarray(a + b, np.float32)
    faces = np.asarray([[0, 1, 2], [3, 4, 5]], np.int32)
    g = Garment(vertices=v, faces=faces, uvs=v[:, :2].copy(), uv_faces=faces.copy())
    return make_sequence(np.repeat(v[None], frames, 0), g)


def test_reads_the_plan_s_seeds_and_only_the_scenes_asked_for(tmp_path):
    val, test, train = scenes.VAL_SCENES[0], scenes.TEST_SCENES[0], scenes.TRAINING_SCENES[0]
    for name, seed, crossing in ((val, 0, True), (test, 1, False), (train, 0, True)):
        (tmp_path / name).mkdir()
        save_sequence(tmp_path / name / f"silk_charmeuse_fine_s{seed}.npz",
                      _two_triangles(crossing))
    # A test scene's seed-0 file is not what the plan writes: it must not be read.
    save_sequence(tmp_path / test / "silk_charmeuse_fine_s0.npz", _two_triangles(True))
    out = tmp_path / "si.json"
    self_intersections.main(["--sequences", str(tmp_path), "--every", "1", "--out", str(out),
                             "--scenes", val, test])
    got = json.loads(out.read_text())
    rows = got["scenes"]
    assert got["sequences"] == str(tmp_path.resolve())  # which files: outside the project
    assert set(rows) == {val, test}
    assert rows[val]["max_pairs"] == 1 and rows[val]["mean_face_fraction"] == 1.0
    assert rows[test]["max_pairs"] == 0
    # The default covers the training, validation and test scenes (missing files skipped).
    self_intersections.main(["--sequences", str(tmp_path), "--every", "1", "--out", str(out)])
    assert set(json.loads(out.read_text())["scenes"]) == {val, test, train}
