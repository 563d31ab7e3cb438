"""Tests for wrinkle_jax.data: patch data set building, splits, determinism, resume, reading."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from wrinkle_jax import data, material_index, primitives
from wrinkle_jax.meshio import make_sequence, save_sequence

CONFIG = data.PatchDataConfig(texel_size=0.004, patch_size=32, crops_per_frame=3,
                              min_coverage=0.3, bake_batch=2, shard_size=5, seed=7)


def _wrinkled_sequence(material, frames=3, **meta):
    g = primitives.grid_sheet(48, 48, size=(0.3, 0.3))
    xy = g.vertices[:, :2]
    out = []
    for t in range(frames):
        z = (0.02 * np.sin(12 * xy[:, 1] + t)  # a large fold
             + 0.0015 * np.sin(140 * xy[:, 0] + 0.5 * t) * np.cos(90 * xy[:, 1]))  # wrinkles
        out.append(np.c_[xy, z])
    return make_sequence(np.asarray(out, np.float32), g, metadata={"material": material, **meta})


@pytest.fixture(scope="module")
def sources(tmp_path_factory):
    d = tmp_path_factory.mktemp("seqs")
    specs = {
        "sheet_wind_silk": dict(material="silk_charmeuse", garment="sheet", motion="wind"),
        "dress_dance_denim": dict(material="denim_light", garment="dress", motion="dance",
                                  split="train"),  # a claim that must be ignored
        "skirt_walk_unseen": dict(material="wool_melton", garment="skirt", motion="walk"),
        # The simulator's layout: garment and motion inside the scene config JSON.
        "sim_skirt_dance": dict(material="knit_terry", scene="skirt_dance", scene_config=json.dumps(
            {"garment": "flared_skirt", "motion": "dance", "test_only": False})),
        "sim_cape": dict(material="knit_terry", scene="cape_x", scene_config=json.dumps(
            {"garment": "cape", "motion": "dance2", "test_only": True})),
    }
    paths = []
    for name, meta in specs.items():
        p = d / f"{name}.npz"
        save_sequence(p, _wrinkled_sequence(**meta))
        paths.append(p)
    return paths


@pytest.fixture(scope="module")
def built(sources, tmp_path_factory):
    root = tmp_path_factory.mktemp("patches")
    return root, data.build_dataset(sources, root, CONFIG)


def test_splits_by_garment_and_motion(built):
    _, entries = built
    split = {e["sequence"]: e["split"] for e in entries}
    assert split == {"sheet_wind_silk": "train", "dress_dance_denim": "heldout",
                     "skirt_walk_unseen": "heldout", "sim_skirt_dance": "train",
                     "sim_cape": "heldout"}
    info = {e["sequence"]: (e["garment"], e["motion"]) for e in entries}
    assert info["sim_skirt_dance"] == ("flared_skirt", "dance")


def test_scene_filter_keeps_only_those_scenes_patches(built):
    root, entries = built
    scene = {e["sequence"]: e["scene"] for e in entries}
    full = data.PatchDataset(root, "train")
    sub = data.PatchDataset(root, "train", scenes=[scene["sim_skirt_dance"]])
    assert [e["sequence"] for e in sub.entries] == ["sim_skirt_dance"]
    assert 0 < len(sub) < len(full)
    # the same patches as in the full split, in the same order
    j = [e["sequence"] for e in full.entries].index("sim_skirt_dance")
    rows = np.flatnonzero(full.sequence_of == j)
    np.testing.assert_array_equal(sub.get(np.arange(len(sub)))["target"],
                                  full.get(rows)["target"])
    assert len(data.PatchDataset(root, "heldout", scenes=[scene["sim_skirt_dance"]])) == 0
    with pytest.raises(ValueError, match="no sequences of scene"):
        data.PatchDataset(root, "train", scenes=["no_such_scene"])


def test_patches_are_valid_pairs(built):
    root, _ = built
    ds = data.PatchDataset(root, "train")
    assert len(ds) == 2 * 3 * CONFIG.crops_per_frame  # two training sequences of 3 frames
    assert ds.patch_size == 32
    b = ds.get(np.arange(len(ds)))
    assert b["input"].shape == (18, 32, 32, 3) and b["mask"].shape == (18, 32, 32, 1)
    assert set(b["material"].tolist()) == {material_index("silk_charmeuse"),
                                           material_index("knit_terry")}
    coverage = b["mask"].mean(axis=(1, 2, 3))
    assert (coverage >= CONFIG.min_coverage).all()
    m = b["mask"][..., 0] > 0
    # Inside the mask both maps are unit normals in RGB form; outside they are zero.
    for key in ("input", "target"):
        n = b[key] * 2 - 1
        np.testing.assert_allclose(np.linalg.norm(n[m], axis=-1), 1.0, atol=2e-3)
        assert not b[key][~m].any()

    def detail(x):  # mean |horizontal difference| inside the mask
        d = np.abs(np.diff(x, axis=2)).sum(-1)
        return d[m[:, :, 1:] & m[:, :, :-1]].mean()

    # The input is the downsampled (coarse-looking) version of the target.
    assert detail(b["input"]) < 0.7 * detail(b["target"])
    big_fold = np.corrcoef(b["input"][m].ravel(), b["target"][m].ravel())[0, 1]
    assert big_fold > 0.9


def test_shards_bound_memory(built):
    _, entries = built
    e = next(e for e in entries if e["sequence"] == "sheet_wind_silk")
    sizes = [len(s["frames"]) for s in e["shards"]]
    # Flushed as soon as a shard reaches shard_size (a frame's crops are never split).
    assert all(s < CONFIG.shard_size + CONFIG.crops_per_frame for s in sizes)
    assert sum(sizes) == 9 and len(sizes) >= 2


def test_deterministic_and_resumable(sources, built, tmp_path):
    root, _ = built
    again = tmp_path / "again"
    data.build_dataset(sources, again, CONFIG)
    for f in sorted((root / "shards").iterdir()):
        assert (again / "shards" / f.name).read_bytes() == f.read_bytes()
    # Resume: only the sequence whose index is missing is rebuilt, identically.
    (again / "index" / "dress_dance_denim.json").unlink()
    rebuilt = []
    data.build_dataset(sources, again, CONFIG, progress=lambda name, e: rebuilt.append(name))
    assert rebuilt == ["dress_dance_denim"]
    for f in sorted((root / "shards").iterdir()):
        assert (again / "shards" / f.name).read_bytes() == f.read_bytes()
    # A different seed gives different crops.
    other = tmp_path / "other"
    data.build_dataset(sources[:1], other, dataclasses.replace(CONFIG, seed=8))
    first = sorted((other / "shards").iterdir())[0]
    assert first.read_bytes() != (root / "shards" / first.name).read_bytes()


def test_bad_metadata(tmp_path):
    seq = _wrinkled_sequence("silk_charmeuse")
    bad = make_sequence(seq.frames, seq.garment, metadata={"material": "velvet"})
    save_sequence(tmp_path / "velvet.npz", bad)
    with pytest.raises(ValueError, match="velvet.*unknown material"):
        data.build_dataset([tmp_path / "velvet.npz"], tmp_path / "out", CONFIG)
    none = make_sequence(seq.frames, seq.garment, metadata={})
    save_sequence(tmp_path / "nomat.npz", none)
    with pytest.raises(ValueError, match="nomat.*no 'material'"):
        data.build_dataset([tmp_path / "nomat.npz"], tmp_path / "out2", CONFIG)


def test_batch_iterator_resumes_exactly(built):
    root, _ = built
    ds = data.PatchDataset(root, "heldout")
    assert len(ds) == 27
    straight = data.BatchIterator(ds, 4, seed=3)
    seen = [next(straight)["input"] for _ in range(7)]  # crosses an epoch boundary
    first = data.BatchIterator(ds, 4, seed=3)
    for _ in range(3):
        next(first)
    resumed = data.BatchIterator(ds, 4, seed=3, state=first.state)
    for k in range(3, 7):
        np.testing.assert_array_equal(next(resumed)["input"], seen[k])
    # Every patch of an epoch appears at most once; epochs are shuffled differently.
    it = data.BatchIterator(ds, 4, seed=3)
    p0 = it._perm(0)
    assert sorted(p0.tolist()) == list(range(27))
    assert not np.array_equal(p0, it._perm(1))
    with pytest.raises(ValueError, match="fewer than one batch"):
        data.BatchIterator(ds, 100)


def _pair(frames=5):
    """A fine and a coarse 'simulation' of one 0.3 m sheet: the coarse one has the large fold
    only, slightly shifted (coarse and fine simulations diverge), the fine one also wrinkles."""
    meta = dict(material="denim_light", scene="sheet_x", scene_config=json.dumps(
        {"garment": "sheet", "motion": "wind", "test_only": False}))
    out = {}
    for res, n, wr in (("fine", 48, 0.0015), ("coarse", 16, 0.0)):
        g = primitives.grid_sheet(n, n, size=(0.3, 0.3))
        xy = g.vertices[:, :2]
        fr = [np.c_[xy, 0.02 * np.sin(12 * xy[:, 1] + t + (0.2 if res == "coarse" else 0))
                    + wr * np.sin(140 * xy[:, 0] + 0.5 * t) * np.cos(90 * xy[:, 1])]
              for t in range(frames)]
        out[res] = make_sequence(np.asarray(fr, np.float32), g, metadata=meta)
    return out["fine"], out["coarse"]


def test_pair_dataset_holds_real_coarse_inputs_and_a_val_split(tmp_path):
    fine, coarse = _pair()
    cfg = dataclasses.replace(CONFIG, augment=False)
    entries = data.build_pair_sequence(fine, coarse, "sheet_x__denim", tmp_path, cfg,
                                       val_fraction=0.4)
    assert [e["split"] for e in entries] == ["train", "val"]
    assert [sorted({f for s in e["shards"] for f in s["frames"]}) for e in entries] == \
        [[0, 1, 2], [3, 4]]  # the val split is the last frames
    tr, val = data.PatchDataset(tmp_path, "train"), data.PatchDataset(tmp_path, "val")
    assert len(tr) == 3 * cfg.crops_per_frame and len(val) == 2 * cfg.crops_per_frame
    assert len(data.PatchDataset(tmp_path, "heldout")) == 0
    b = tr.get(np.arange(len(tr)))
    m = b["mask"][..., 0] > 0
    for key in ("input", "target"):
        np.testing.assert_allclose(np.linalg.norm(b[key][m] * 2 - 1, axis=-1), 1.0, atol=2e-3)
        assert not b[key][~m].any()
    # Input = the coarse simulation baked on the fine grid: same large fold (shifted a little),
    # no wrinkles; the target keeps its own wrinkles.
    d_in = np.abs(np.diff(b["input"], axis=2)).sum(-1)[m[:, :, 1:] & m[:, :, :-1]].mean()
    d_tg = np.abs(np.diff(b["target"], axis=2)).sum(-1)[m[:, :, 1:] & m[:, :, :-1]].mean()
    assert d_in < 0.5 * d_tg
    assert np.corrcoef(b["input"][m][:, 1], b["target"][m][:, 1])[0, 1] > 0.7
    # A held-out garment ignores val_fraction.
    held = dataclasses.replace(fine, metadata={**fine.metadata, "scene_config": json.dumps(
        {"garment": "dress", "motion": "wind", "test_only": True})})
    e = data.build_pair_sequence(held, coarse, "dress_x", tmp_path / "h", cfg, val_fraction=0.4)
    assert [x["split"] for x in e] == ["heldout"]
    # The validation-only garment goes whole to "valgarment", never to train or val.
    vg = dataclasses.replace(fine, metadata={**fine.metadata, "scene_config": json.dumps(
        {"garment": "tabard", "motion": "dance2", "test_only": False, "val_only": True})})
    e = data.build_pair_sequence(vg, coarse, "tabard_x", tmp_path / "v", cfg, val_fraction=0.4)
    assert [x["split"] for x in e] == ["valgarment"]
    assert sorted({f for s in e[0]["shards"] for f in s["frames"]}) == [0, 1, 2, 3, 4]
    assert len(data.PatchDataset(tmp_path / "v", "valgarment")) == 5 * cfg.crops_per_frame
    assert len(data.PatchDataset(tmp_path / "v", "train")) == 0


def test_a_pair_cell_is_stale_when_its_simulations_or_settings_change(tmp_path):
    fine, coarse = _pair(frames=2)
    seqs = tmp_path / "seqs" / "sheet_x"
    seqs.mkdir(parents=True)
    fine_p, coarse_p = seqs / "denim_light_fine_s0.npz", seqs / "denim_light_coarse_s0.npz"
    save_sequence(fine_p, fine)
    save_sequence(coarse_p, coarse)
    cfg = dataclasses.replace(CONFIG, augment=False)
    src = data.pair_sources(fine_p, coarse_p)
    assert src["fine"]["file"] == "sheet_x/denim_light_fine_s0.npz"
    names, root = ["c", "c__val"], tmp_path / "pairs"
    assert data.pair_cell_stale(root, names, src, cfg, 0.5) == "no index entry c"
    data.build_pair_sequence(fine, coarse, "c", root, cfg, val_fraction=0.5)
    assert data.pair_cell_stale(root, names, src, cfg, 0.5) == "c records no sources"
    data.build_pair_sequence(fine, coarse, "c", root, cfg, val_fraction=0.5, sources=src)
    assert data.pair_cell_stale(root, names, src, cfg, 0.5) is None
    assert data.pair_cell_stale(root, names, src, cfg, 0.4) == "c was cut with other settings"
    other = dataclasses.replace(cfg, crops_per_frame=4)
    assert data.pair_cell_stale(root, names, src, other, 0.5) == "c was cut with other settings"
    # The fine simulation written again, with one vertex moved by a micrometre.
    frames = np.array(fine.frames)
    frames[1, 7, 2] += 1e-6
    save_sequence(fine_p, dataclasses.replace(fine, frames=frames))
    new = data.pair_sources(fine_p, coarse_p)
    assert new["coarse"] == src["coarse"] and new["fine"] != src["fine"]
    assert data.pair_cell_stale(root, names, new, cfg, 0.5) == "c was cut from another fine file"
    (root / "index" / "c__val.json").unlink()
    assert data.pair_cell_stale(root, names, src, cfg, 0.5) == "no index entry c__val"


def test_batch_iterator_origins_are_seeded_by_position(built):
    root, _ = built
    ds = data.PatchDataset(root, "heldout")
    a = data.BatchIterator(ds, 4, seed=3, origins=True)
    got = [next(a)["origins"] for _ in range(3)]
    assert got[0].shape == (4, 2) and got[0].dtype == np.int32
    assert not np.array_equal(got[0], got[1])
    b = data.BatchIterator(ds, 4, seed=3, origins=True, state=data.IteratorState(0, 4))
    np.testing.assert_array_equal(next(b)["origins"], got[1])
    assert "origins" not in next(data.BatchIterator(ds, 4, seed=3))


def test_a_damaged_shard_or_index_is_a_value_error_naming_the_file(built, tmp_path):
    import shutil

    root, _ = built
    copy = tmp_path / "copy"
    shutil.copytree(root, copy)
    assert len(data.PatchDataset(copy, "train")) == len(data.PatchDataset(root, "train"))
    train = data.PatchDataset(copy, "train").entries[0]
    shard = copy / "shards" / train["shards"][0]["file"]
    shard.write_bytes(shard.read_bytes()[:200])  # cut short: header only
    with pytest.raises(ValueError, match=f"{shard.name}: unreadable patch shard"):
        data.PatchDataset(copy, "train")
    shutil.rmtree(copy)
    shutil.copytree(root, copy)
    index = copy / "index" / f"{train['sequence']}.json"
    index.write_text(index.read_text()[:40])  # cut short: not JSON
    with pytest.raises(ValueError, match=f"{index.name}: unreadable patch-set index"):
        data.PatchDataset(copy, "train")
    index.write_text('{"split": "train"}')  # JSON, but not an index entry
    with pytest.raises(ValueError, match=f"{index.name}: not a patch-set index"):
        data.PatchDataset(copy, "train")
