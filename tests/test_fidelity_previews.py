"""Tests for `wrinkle_jax.compare` and `experiments.fidelity_previews` on a tiny synthetic pair.

A coarse sheet with a smooth bump and a fine sheet with the same bump plus 30 mm wrinkles
(standing upright, so the fitted camera sees their face), a width-4 random enhancer with
32-texel patches; the script's main() runs once for the module with `cell_sequences`
replaced by the synthetic sequences.
"""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from experiments import fidelity_previews
from wrinkle_jax import compare, enhancer, meshio, primitives
from wrinkle_jax.evaluation import suite

SIZE = 0.24  # meters
PANEL = 96
CROP = 32


def _bump(x, y):
    return 0.03 * np.sin(np.pi * x / SIZE) * np.sin(np.pi * y / SIZE)


def _wrinkled(x, y):
    return _bump(x, y) + 0.003 * np.sin(2 * np.pi * (x + 0.5 * y) / 0.03)


# The sheets lie in z = 0; stand them up (a rotation: y -> z, z -> -y) to face the camera.
_UPRIGHT = np.array([[1, 0, 0], [0, 0, -1], [0, 1, 0]], np.float32)


def _sequence(garment, frames: int) -> meshio.GarmentSequence:
    v = np.asarray(garment.vertices, np.float32) @ _UPRIGHT.T
    return meshio.make_sequence(np.stack([v] * frames), garment)


@pytest.fixture(scope="module")
def run(tmp_path_factory, model):
    """main() on one cell (frame 1 of 2) with synthetic sequences and a tiny model."""
    tmp = tmp_path_factory.mktemp("previews")
    coarse = primitives.grid_sheet(8, 8, size=(SIZE, SIZE), height_fn=_bump)
    fine = primitives.grid_sheet(48, 48, size=(SIZE, SIZE), height_fn=_wrinkled)
    paths = {"coarse": tmp / "coarse.npz", "fine": tmp / "fine.npz"}
    meshio.save_sequence(paths["coarse"], _sequence(coarse, 2))
    meshio.save_sequence(paths["fine"], _sequence(fine, 2))
    # The session's tiny enhancer (conftest `model`: width 4, 32-texel patches, 4 mm texels).
    model_path = enhancer.save_enhancer(tmp / "model.npz", model.params, model.config)
    calls = []

    def fake_cell_sequences(cell, frames, **kwargs):
        calls.append((cell.key, frames))
        return {**paths, "coarse_info": {}, "fine_info": {}}

    out = tmp / "out"
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(fidelity_previews.cell_lib, "cell_sequences", fake_cell_sequences)
        index = fidelity_previews.main(
            ["--model", str(model_path), "--frames", "2", "--frame", "1", "--scenes", "dress_dance",
             "--materials", "silk_charmeuse", "--panel", str(PANEL), "--crop", str(CROP),
             "--out", str(out), "--sim-out", str(tmp / "sims")])
    return {"out": out, "index": index, "calls": calls, "model": model_path}


def _read(path) -> np.ndarray:
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    assert img is not None, path
    return img[..., ::-1]


def _panels(image: np.ndarray) -> list[np.ndarray]:
    return [image[:, k * PANEL:(k + 1) * PANEL] for k in range(3)]


def _high_frequency(panel: np.ndarray, garment_only: bool) -> float:
    """Mean |Laplacian| of the grey image below the label, on garment pixels (eroded, so the
    silhouette does not count) when `garment_only`."""
    grey = panel.astype(np.float32).mean(-1)
    lap = np.abs(cv2.Laplacian(grey, cv2.CV_32F))
    keep = np.ones_like(grey, bool)
    if garment_only:
        keep = cv2.erode((grey < 250).astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
    keep[: PANEL // 4] = False  # the label box
    assert keep.sum() > 0.1 * keep.size
    return float(lap[keep].mean())


def test_main_writes_both_rows_at_the_requested_sizes_and_an_index(run):
    out, index = run["out"], run["index"]
    assert run["calls"] == [("dress_dance/silk_charmeuse", 2)]
    stem = "dress_dance__silk_charmeuse"
    for row in ("meshes", "normals"):
        img = _read(out / f"{stem}__{row}.png")
        assert img.shape == (PANEL, 3 * PANEL, 3)
    on_disk = json.loads((out / "index.json").read_text())
    assert on_disk == json.loads(json.dumps(index))
    assert on_disk["frame"] == 1 and on_disk["panel"] == PANEL
    (cell,) = on_disk["cells"]
    assert cell["cell"] == "dress_dance/silk_charmeuse" and cell["frame"] == 1
    for row in ("meshes", "normals"):
        assert cell[row]["size"] == [PANEL, 3 * PANEL]
        assert cell[row]["panel_size"] == [PANEL, PANEL] and len(cell[row]["labels"]) == 3
    assert cell["normals"]["crop_texels"] == CROP
    r, c = cell["normals"]["crop_origin_texels"]
    h, w = cell["normals"]["map_size_texels"]
    assert 0 <= r and 0 <= c and r + CROP <= max(h, CROP) and c + CROP <= max(w, CROP)
    # The model lies outside the project here: its path is absolute; inside, relative.
    assert on_disk["model"] == suite.portable_path(run["model"])
    assert suite.portable_path(suite.ROOT / "wrinkle_jax" / "x.npz") == "wrinkle_jax/x.npz"


@pytest.mark.parametrize("row", ["meshes", "normals"])
def test_panels_differ_and_the_fine_one_has_more_detail(run, row):
    coarse, ours, fine = _panels(_read(run["out"] / f"dress_dance__silk_charmeuse__{row}.png"))
    for a, b in ((coarse, ours), (ours, fine), (coarse, fine)):
        assert np.abs(a.astype(np.float32) - b.astype(np.float32)).mean() > 1.0
    garment_only = row == "meshes"
    hf_coarse = _high_frequency(coarse, garment_only)
    hf_fine = _high_frequency(fine, garment_only)
    assert hf_fine > 2.0 * hf_coarse, (hf_coarse, hf_fine)


def test_crop_origin_prefers_the_fullest_window_near_the_centroid():
    mask = np.zeros((64, 96, 1), np.float32)
    mask[8:56, 10:30] = 1.0   # a narrow panel on the left
    mask[4:60, 40:90] = 1.0   # a wide panel on the right: a 32-window fits inside
    r, c = compare.crop_origin(mask, 32)
    assert mask[r:r + 32, c:c + 32].mean() == 1.0
    assert 40 <= c and c + 32 <= 90
    with pytest.raises(ValueError, match="smaller than the crop"):
        compare.crop_origin(mask[:16], 32)
    assert compare.crop_origin(np.zeros((40, 40, 1), np.float32), 32) == (0, 0)
