"""experiments.make_pair_dataset: a rerun cuts again exactly the cells whose simulations were
written again (or that record none), and `--check` lists them without cutting."""

import json

import numpy as np

from experiments import make_pair_dataset
from wrinkle_jax import primitives
from wrinkle_jax.meshio import make_sequence, save_sequence
from wrinkle_jax.sim import scenes

SMALL = ["--patch-size", "32", "--texel-size", "0.004", "--crops", "2", "--frame-stride", "1",
         "--val-fraction", "0.5"]


def _write(folder, mat, res, phase):
    n = 24 if res == "fine" else 8
    g = primitives.grid_sheet(n, n, size=(0.2, 0.2))
    xy = g.vertices[:, :2]
    frames = np.asarray([np.c_[xy, 0.02 * np.sin(15 * xy[:, 1] + t + phase)] for t in range(2)],
                        np.float32)
    meta = dict(material=mat, scene="sheet_x", scene_config=json.dumps(
        {"garment": "sheet", "motion": "wind", "test_only": False}))
    save_sequence(folder / f"{mat}_{res}_s0.npz", make_sequence(frames, g, metadata=meta))


def test_a_rerun_cuts_again_only_the_cells_whose_simulations_changed(tmp_path, monkeypatch):
    monkeypatch.setattr(scenes, "TRAINING_SCENES", ("sheet_x",))
    monkeypatch.setattr(scenes, "VAL_SCENES", ())
    monkeypatch.setattr(make_pair_dataset, "MATERIALS", ("denim_light", "wool_melton"))
    seqs, out = tmp_path / "seqs", tmp_path / "pairs"
    (seqs / "sheet_x").mkdir(parents=True)
    for mat in ("denim_light", "wool_melton"):
        for res in ("fine", "coarse"):
            _write(seqs / "sheet_x", mat, res, 0.0)
    args = ["--sequences", str(seqs), "--out", str(out), *SMALL]
    log = out / "make_pair_dataset.log"

    def index(name):
        return json.loads((out / "index" / f"{name}.json").read_text())

    assert make_pair_dataset.main(args + ["--check"]) == 1
    assert not (out / "index").exists()  # --check cuts nothing
    assert make_pair_dataset.main(args) == 0
    assert sorted(p.name for p in (out / "index").iterdir()) == [
        "sheet_x__denim_light.json", "sheet_x__denim_light__val.json",
        "sheet_x__wool_melton.json", "sheet_x__wool_melton__val.json"]
    wool = index("sheet_x__wool_melton")
    assert make_pair_dataset.main(args + ["--check"]) == 0

    _write(seqs / "sheet_x", "denim_light", "fine", 0.3)  # simulated again
    lines = len(log.read_text().splitlines())
    assert make_pair_dataset.main(args + ["--check"]) == 1
    new = log.read_text().splitlines()[lines:]
    assert len(new) == 2 and "sheet_x__denim_light: to cut (sheet_x__denim_light was cut " \
        "from another fine file)" in new[0] and "1 cells to cut" in new[1]
    lines = len(log.read_text().splitlines())
    assert make_pair_dataset.main(args) == 0
    cut = log.read_text().splitlines()[lines:]
    assert len(cut) == 1 and "sheet_x__denim_light: {'train': 2, 'val': 2} patches" in cut[0]
    assert index("sheet_x__wool_melton") == wool
    denim = index("sheet_x__denim_light")
    assert denim["sources"]["fine"]["sha256"] == index("sheet_x__denim_light__val")[
        "sources"]["fine"]["sha256"] != wool["sources"]["fine"]["sha256"]
    assert make_pair_dataset.main(args + ["--check"]) == 0
    # A cell whose simulation is gone is kept, and the log says it cannot be checked.
    (seqs / "sheet_x" / "wool_melton_fine_s0.npz").unlink()
    assert make_pair_dataset.main(args) == 1
    assert log.read_text().splitlines()[-1].endswith(
        "missing wool_melton_fine_s0.npz of sheet_x; skipped; its existing cell is kept, "
        "unverified")
    assert index("sheet_x__wool_melton") == wool
    _write(seqs / "sheet_x", "wool_melton", "fine", 0.0)
    # Other settings make every cell stale.
    assert make_pair_dataset.main(args + ["--check", "--crops", "3"]) == 1
