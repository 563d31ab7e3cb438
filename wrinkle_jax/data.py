"""Patch data sets for the enhancer: fine sequences -> (coarse-looking input, fine target) patch
pairs in memory-mappable shards, and a deterministic, resumable batch iterator.

Building (paper Sec. 5, "Dataset"): each fine frame is baked to a normal map at a fixed texel
size; the network input is made from it by `normalmap.downsample_like_coarse` to texels of the
coarse particle distance (factor = coarse PD / texel size; the paper trains on downsampled fine
maps so that input and target are aligned); random crops with at least `min_coverage` garment
texels are cut from the stacked (input, target, mask) map, with the 8 dihedral augmentations.

On disk (`root/`):
    shards/<sequence>_<k>.npy   (n, S, S, 7) uint16: channels 0-2 input and 3-5 target in the
                                RGB form (n + 1) / 2 scaled to 0..65535, channel 6 the mask
    index/<sequence>.json       one per finished sequence: its split, material, scene, garment,
                                motion, and per shard the frame of every patch
A sequence whose index file exists is skipped, so an interrupted build resumes; every file is
written atomically. Memory is bounded by one bake batch plus one shard, however long the
sequences are.

Splits are by garment and by motion: a sequence whose garment is in `heldout_garments`, whose
motion is in `heldout_motions` (the simulator's test scenes: dress, cape, walk), or whose metadata
marks it `test_only` is "heldout"; a validation-only scene (metadata `val_only`: a garment
neither training nor the held-out sets contain, read by checkpoint and recipe choices) is
"valgarment"; everything else is "train". Held-out and validation garments and motions never
reach training.
"""

from __future__ import annotations

import dataclasses
import functools
import io
import json
import os
from collections.abc import Iterable, Sequence
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from wrinkle_jax import MATERIALS, material_index, normalmap, patches
from wrinkle_jax.fileio import NPZ_READ_ERRORS, atomic_write_bytes, atomic_write_text, sha256_file
from wrinkle_jax.meshio import GarmentSequence, load_sequence

CHANNELS = 7  # input RGB, target RGB, mask
_SCALE = 65535.0


@dataclasses.dataclass(frozen=True)
class PatchDataConfig:
    """How patches are cut (static, hashable).

    Attributes:
      texel_size: meters of cloth per texel.
      patch_size: patch side in texels.
      crops_per_frame: random crops per baked frame.
      min_coverage: minimum fraction of garment texels in a crop.
      coarse_pd: particle distance (m) of the coarse simulations the network will see (30 mm in
        the paper); the input is the fine map downsampled to texels of this size, i.e. by
        `downsample_factor` = coarse_pd / texel_size. (Measured on skirt_dance at 2 mm texels:
        a real PD-30 mm map has the first- and second-difference detail of the fine map
        downsampled by 15-20, not by the PD ratio 3, which leaves almost all the detail.)
      frame_stride: use every k-th frame.
      bake_batch: frames baked per jitted call (bounds memory).
      shard_size: patches per shard file.
      augment: random dihedral transforms.
      seed: base seed; each sequence derives its own key from it and its name.
      heldout_garments, heldout_motions: names that never reach the train split.
    """

    texel_size: float = normalmap.DEFAULT_TEXEL_SIZE
    patch_size: int = 128
    crops_per_frame: int = 8
    min_coverage: float = 0.09
    coarse_pd: float = 0.03
    frame_stride: int = 1
    bake_batch: int = 4
    shard_size: int = 512
    augment: bool = True
    seed: int = 0
    heldout_garments: tuple[str, ...] = ("dress", "cape")
    heldout_motions: tuple[str, ...] = ("walk",)

    @property
    def downsample_factor(self) -> float:
        return self.coarse_pd / self.texel_size


def sequence_info(seq: GarmentSequence, name: str) -> dict:
    """Material, scene, garment and motion of a sequence, from its metadata.

    Raises:
      ValueError: naming the sequence, if the material is missing or unknown.
    """
    meta = seq.metadata
    material = meta.get("material")
    if material is None:
        raise ValueError(f"{name}: sequence metadata has no 'material'")
    try:
        material_index(material)
    except ValueError as e:
        raise ValueError(f"{name}: {e}") from None
    scene = meta.get("scene", name)
    # Simulated sequences keep garment and motion inside their scene config (JSON string).
    scene_cfg = meta.get("scene_config", {})
    if isinstance(scene_cfg, str):
        try:
            scene_cfg = json.loads(scene_cfg)
        except json.JSONDecodeError:
            raise ValueError(f"{name}: metadata 'scene_config' is not valid JSON") from None
    garment = meta.get("garment", scene_cfg.get("garment", scene))
    motion = meta.get("motion", scene_cfg.get("motion", scene))
    test_only = bool(meta.get("test_only", scene_cfg.get("test_only", False)))
    info = {"material": material, "scene": scene, "garment": garment,
            "motion": str(motion), "test_only": test_only}
    if meta.get("val_only", scene_cfg.get("val_only", False)):
        info["val_only"] = True
    return info


def split_of(info: dict, config: PatchDataConfig) -> str:
    """'heldout' if the garment or the motion is held out or the sequence is marked test-only,
    'valgarment' if it is marked validation-only, else 'train'."""
    if (info["garment"] in config.heldout_garments or info["motion"] in config.heldout_motions
            or info.get("test_only", False)):
        return "heldout"
    if info.get("val_only", False):
        return "valgarment"
    return "train"


def _to_uint16(rgb: np.ndarray) -> np.ndarray:
    return np.round(np.clip(rgb, 0.0, 1.0) * _SCALE).astype(np.uint16)


def _seed_for(name: str, seed: int) -> int:
    # A stable per-sequence seed (Python's hash() is salted per process).
    h = 2166136261
    for ch in f"{seed}:{name}".encode():
        h = ((h ^ ch) * 16777619) & 0xFFFFFFFF
    return h


@functools.lru_cache(maxsize=8)
def _make_crop_fn(config: PatchDataConfig):
    """Jitted (key, fine map, mask) -> (n, S, S, 7) float32 crops in the RGB form.

    Cached per config, so every sequence reuses the compiled function.
    """
    factor = float(config.downsample_factor)

    def crops(key, fine, mask):
        coarse = normalmap.downsample_like_coarse(fine, mask, factor)
        stacked = jnp.concatenate([normalmap.to_rgb(coarse) * mask,
                                   normalmap.to_rgb(fine) * mask, mask], axis=-1)
        out, _, _ = patches.random_crops(key, stacked, mask, config.crops_per_frame,
                                         config.patch_size, config.min_coverage,
                                         augment=config.augment)
        return out

    return jax.jit(crops)


class _ShardWriter:
    """Buffers a sequence's crops and writes them as shards of >= `shard_size` patches
    (a frame's crops are never split), atomically; `shards` lists the written files."""

    def __init__(self, shard_dir: Path, name: str, shard_size: int):
        self.shard_dir, self.name, self.shard_size = shard_dir, name, shard_size
        self.shards: list[dict] = []
        self._buf: list[np.ndarray] = []
        self._frames: list[int] = []

    def add(self, crops: np.ndarray, frame: int) -> None:
        self._buf.append(crops)
        self._frames.extend([int(frame)] * len(crops))
        if sum(len(b) for b in self._buf) >= self.shard_size:
            self.flush()

    def flush(self) -> None:
        if not self._buf:
            return
        out = io.BytesIO()
        np.save(out, np.concatenate(self._buf))
        path = self.shard_dir / f"{self.name}_{len(self.shards):05d}.npy"
        atomic_write_bytes(path, out.getvalue())
        self.shards.append({"file": path.name, "frames": list(self._frames)})
        self._buf.clear()
        self._frames.clear()


def build_sequence(seq: GarmentSequence, name: str, root: Path, config: PatchDataConfig) -> dict:
    """Cut one sequence into shards under `root`; returns (and writes) its index entry."""
    info = sequence_info(seq, name)
    split = split_of(info, config)
    plan = normalmap.make_plan(seq.garment, texel_size=config.texel_size)
    h, w = plan.shape
    size = config.patch_size
    mask = plan.mask
    if h < size or w < size:
        mask = jnp.asarray(patches.pad_to_patch(np.asarray(mask), size)[0])
    counts = np.asarray(patches.crop_mask_counts(mask, size))
    if counts.max() < config.min_coverage * size * size:
        raise ValueError(f"{name}: no {size}x{size} patch reaches {config.min_coverage:.0%} "
                         f"garment coverage at texel size {config.texel_size} m")
    bake = jax.jit(functools.partial(normalmap.bake_frames, batch_size=2))
    crop = _make_crop_fn(config)
    key = jax.random.key(_seed_for(name, config.seed))
    frames = np.arange(0, len(seq), config.frame_stride)
    shard_dir = root / "shards"
    shard_dir.mkdir(parents=True, exist_ok=True)
    writer = _ShardWriter(shard_dir, name, config.shard_size)

    for start in range(0, len(frames), config.bake_batch):
        idx = frames[start:start + config.bake_batch]
        padded = np.resize(idx, config.bake_batch)  # fixed batch shape: compile once
        maps = bake(plan, jnp.asarray(seq.frames[padded]))
        for j, t in enumerate(idx):
            fine = maps[j]
            if fine.shape[:2] != mask.shape[:2]:
                fine = jnp.asarray(patches.pad_to_patch(np.asarray(fine), size)[0])
            key, sub = jax.random.split(key)
            writer.add(_to_uint16(np.asarray(crop(sub, fine, mask))), t)
    writer.flush()
    entry = {"sequence": name, "split": split, **info,
             "material_id": material_index(info["material"]),
             "patch_size": size, "texel_size": config.texel_size,
             "config": dataclasses.asdict(config), "shards": writer.shards}
    (root / "index").mkdir(parents=True, exist_ok=True)
    atomic_write_text(root / "index" / f"{name}.json", json.dumps(entry))
    return entry


def build_dataset(sources: Iterable[str | os.PathLike], root: str | os.PathLike,
                  config: PatchDataConfig = PatchDataConfig(), progress=None) -> list[dict]:
    """Build (or resume building) a patch data set from sequence files.

    Args:
      sources: `.npz` sequences (or OBJ folders) of FINE simulations with metadata `material`
        and, ideally, `scene`, `garment`, `motion`.
      root: output folder.
      config: PatchDataConfig.
      progress: optional callable(name, entry) called after each sequence.
    Returns:
      the index entries of all sequences (finished before or now).
    """
    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    entries = []
    for src in sources:
        src = Path(src)
        name = src.stem if src.suffix else src.name
        done = root / "index" / f"{name}.json"
        if done.exists():
            entries.append(json.loads(done.read_text()))
            continue
        entry = build_sequence(load_sequence(src), name, root, config)
        entries.append(entry)
        if progress is not None:
            progress(name, entry)
    return entries


@functools.lru_cache(maxsize=8)
def _make_pair_crop_fn(config: PatchDataConfig):
    """Jitted (key, (H, W, 7) stacked coarse RGB | fine RGB | mask) -> (n, S, S, 7) crops."""

    def crops(key, stacked):
        out, _, _ = patches.random_crops(key, stacked, stacked[..., 6:7],
                                         config.crops_per_frame, config.patch_size,
                                         config.min_coverage, augment=config.augment)
        return out

    return jax.jit(crops)


def build_pair_sequence(fine: GarmentSequence, coarse: GarmentSequence, name: str, root: Path,
                        config: PatchDataConfig, val_fraction: float = 0.0,
                        sources: dict | None = None) -> list[dict]:
    """Cut REAL coarse-input / fine-target pairs of one simulated frame range into shards.

    Unlike `build_sequence` (input = the fine map downsampled, pixel-aligned with its target),
    the input here is the coarse simulation of the same scene, material, seed and frame, baked
    on the fine map's grid (`patchsets.aligned_pair`), so the network sees what users give it.
    Input and target then agree only up to the simulations' divergence; losses meant for such
    pairs compare statistics (Gram matrices of detail maps), not pixels. The mask is where both
    meshes cover the texel. The shard format and index are `build_sequence`'s (7 channels), so
    `PatchDataset` reads both kinds.

    Args:
      fine, coarse: sequences of the same pattern and motion (frames (T, V, 3) meters; the
        shorter length is used).
      name: sequence name in the data set.
      root: data set folder.
      config: PatchDataConfig (its `coarse_pd` is unused: the input is not synthesized).
      val_fraction: the last fraction of the frames of a TRAIN-split sequence goes to a "val"
        split entry (`<name>__val`): data from training scenes set aside for recipe choices,
        so that held-out scenes never influence them. Held-out sequences ignore it.
      sources: recorded in each entry as "sources" (`pair_sources` of the two files), with
        `val_fraction`, so that `pair_cell_stale` can tell a cell cut from files that were
        simulated again, or with other settings.
    Returns:
      the index entries written (one, or two with a val part).
    """
    from wrinkle_jax.evaluation import patchsets

    info = sequence_info(fine, name)
    split = split_of(info, config)
    size = config.patch_size
    pair = patchsets.aligned_pair(fine.garment, coarse.garment, config.texel_size)
    mask = np.asarray(patches.pad_to_patch(pair.mask, size)[0])
    counts = np.asarray(patches.crop_mask_counts(jnp.asarray(mask), size))
    if counts.max() < config.min_coverage * size * size:
        raise ValueError(f"{name}: no {size}x{size} patch reaches {config.min_coverage:.0%} "
                         f"coverage by both meshes at texel size {config.texel_size} m")
    crop = _make_pair_crop_fn(config)
    key = jax.random.key(_seed_for(name, config.seed))
    frames = np.arange(0, min(len(fine), len(coarse)), config.frame_stride)
    n_val = int(round(len(frames) * val_fraction)) if split == "train" else 0
    parts = [(name, split, frames[:len(frames) - n_val])]
    if n_val:
        parts.append((f"{name}__val", "val", frames[len(frames) - n_val:]))
    shard_dir = root / "shards"
    shard_dir.mkdir(parents=True, exist_ok=True)
    entries = []
    for part_name, part_split, part_frames in parts:
        writer = _ShardWriter(shard_dir, part_name, config.shard_size)
        for t in part_frames:
            f_map = patches.pad_to_patch(patchsets.bake_map(pair.fine, fine.frames[t]), size)[0]
            c_map = patches.pad_to_patch(patchsets.bake_map(pair.coarse, coarse.frames[t]),
                                         size)[0]
            stacked = np.concatenate([np.asarray(normalmap.to_rgb(c_map)) * mask,
                                      np.asarray(normalmap.to_rgb(f_map)) * mask, mask], -1)
            key, sub = jax.random.split(key)
            writer.add(_to_uint16(np.asarray(crop(sub, jnp.asarray(stacked, jnp.float32)))), t)
        writer.flush()
        entry = {"sequence": part_name, "split": part_split, **info,
                 "material_id": material_index(info["material"]), "input": "coarse_sim",
                 "patch_size": size, "texel_size": config.texel_size,
                 "config": dataclasses.asdict(config), "shards": writer.shards}
        if sources is not None:
            entry.update(sources=sources, val_fraction=val_fraction)
        (root / "index").mkdir(parents=True, exist_ok=True)
        atomic_write_text(root / "index" / f"{part_name}.json", json.dumps(entry))
        entries.append(entry)
    return entries


def pair_sources(fine_path: str | os.PathLike, coarse_path: str | os.PathLike) -> dict:
    """What a pair cell records of the two simulation files it is cut from: each file's
    "<scene folder>/<name>" and the SHA-256 of its bytes."""
    return {res: {"file": f"{Path(p).parent.name}/{Path(p).name}", "sha256": sha256_file(p)}
            for res, p in (("fine", fine_path), ("coarse", coarse_path))}


def pair_cell_stale(root: str | os.PathLike, names: Sequence[str], sources: dict,
                    config: PatchDataConfig, val_fraction: float = 0.0) -> str | None:
    """Why the pair cell whose index entries are `names` (e.g. `<cell>` and `<cell>__val`) under
    `root` must be cut again, or None when every entry exists and was cut from `sources`
    (`pair_sources`) with `config` and `val_fraction`.

    A cell without a record of its sources (written before they were recorded) is stale too:
    nothing says which simulation it was cut from.
    """
    want = json.loads(json.dumps(dataclasses.asdict(config)))  # as stored: tuples -> lists
    for n in names:
        p = Path(root) / "index" / f"{n}.json"
        if not p.exists():
            return f"no index entry {n}"
        entry = json.loads(p.read_text())
        recorded = entry.get("sources")
        if recorded is None:
            return f"{n} records no sources"
        for res in sorted(set(sources) | set(recorded)):
            if recorded.get(res) != sources.get(res):
                return f"{n} was cut from another {res} file"
        if (entry.get("config") != want
                or entry.get("val_fraction") != val_fraction):
            return f"{n} was cut with other settings"
    return None


# --------------------------------------------------------------------------------------------
# Reading
# --------------------------------------------------------------------------------------------


_INDEX_KEYS = {"split", "scene", "shards", "material_id"}  # what PatchDataset reads


def _read_index(path: Path) -> dict:
    """One sequence's index entry (JSON written by `build_dataset`).

    Raises:
      ValueError: naming the file, if it is not readable JSON with the entry's keys.
    """
    try:
        entry = json.loads(path.read_text())
    except (OSError, ValueError) as e:  # ValueError: bad JSON or UTF-8
        raise ValueError(f"{path}: unreadable patch-set index ({type(e).__name__}: {e})") from None
    missing = (sorted(_INDEX_KEYS - set(entry)) if isinstance(entry, dict)
               else sorted(_INDEX_KEYS))
    if missing:
        raise ValueError(f"{path}: not a patch-set index (no {', '.join(missing)})")
    return entry


class PatchDataset:
    """Memory-mapped patches of one split.

    Attributes:
      root: data set folder. split: "train" or "heldout".
      scenes: None (every scene) or the scene names kept (e.g. the sheet-only ablation).
      entries: index entries of the sequences in this split (and scenes).
      materials: (N,) int32 material id of every patch.
      frames: (N,) int32 source frame of every patch.
      sequence_of: (N,) int32 index into `entries` of every patch's sequence.
    """

    def __init__(self, root: str | os.PathLike, split: str = "train",
                 scenes: Sequence[str] | None = None):
        self.root = Path(root)
        self.split = split
        self.scenes = None if scenes is None else tuple(scenes)
        index_dir = self.root / "index"
        if not index_dir.is_dir():
            raise FileNotFoundError(f"{self.root}: not a patch data set (no index/ folder)")
        entries = [_read_index(p) for p in sorted(index_dir.glob("*.json"))]
        if self.scenes is not None:
            known = {e["scene"] for e in entries}
            unknown = sorted(set(self.scenes) - known)
            if unknown:
                raise ValueError(f"{self.root}: no sequences of scene(s) {', '.join(unknown)} "
                                 f"(it has {', '.join(sorted(known))})")
        self.entries = [e for e in entries if e["split"] == split
                        and (self.scenes is None or e["scene"] in self.scenes)]
        self._shards, shard_ids, rows, mats, frames, seqs = [], [], [], [], [], []
        for j, e in enumerate(self.entries):
            for s in e["shards"]:
                path = self.root / "shards" / s["file"]
                try:
                    arr = np.load(path, mmap_mode="r")
                except NPZ_READ_ERRORS as err:
                    raise ValueError(f"{path}: unreadable patch shard "
                                     f"({type(err).__name__}: {err})") from None
                if arr.ndim != 4 or arr.shape[-1] != CHANNELS:
                    raise ValueError(f"{path}: expected (n, S, S, {CHANNELS}) patches")
                k = len(self._shards)
                self._shards.append(arr)
                shard_ids.append(np.full(len(arr), k, np.int32))
                rows.append(np.arange(len(arr), dtype=np.int32))
                mats.append(np.full(len(arr), e["material_id"], np.int32))
                frames.append(np.asarray(s["frames"], np.int32))
                seqs.append(np.full(len(arr), j, np.int32))
        def cat(xs):
            return np.concatenate(xs) if xs else np.zeros(0, np.int32)

        self._shard_of, self._row_of = cat(shard_ids), cat(rows)
        self.materials, self.frames, self.sequence_of = cat(mats), cat(frames), cat(seqs)

    def __len__(self) -> int:
        return int(len(self.materials))

    @property
    def patch_size(self) -> int:
        return int(self._shards[0].shape[1]) if self._shards else 0

    def get(self, indices) -> dict:
        """Patches by global index -> dict of float32 arrays.

        Returns:
          {"input": (B,S,S,3), "target": (B,S,S,3), "mask": (B,S,S,1)} in the RGB form /
          [0, 1], and "material": (B,) int32.
        """
        indices = np.asarray(indices)
        out = np.stack([self._shards[self._shard_of[i]][self._row_of[i]] for i in indices])
        x = out.astype(np.float32) / _SCALE
        return {"input": x[..., 0:3], "target": x[..., 3:6], "mask": x[..., 6:7],
                "material": self.materials[indices]}

    def material_counts(self) -> dict[str, int]:
        return {MATERIALS[k]: int((self.materials == k).sum()) for k in range(len(MATERIALS))}


@dataclasses.dataclass(frozen=True)
class IteratorState:
    """Position of a `BatchIterator` (saved in checkpoints for an exact resume)."""

    epoch: int = 0
    cursor: int = 0


class BatchIterator:
    """Deterministic shuffled batches: epoch e visits a permutation seeded by (seed, e).

    The state is two integers, so a resumed run draws exactly the batches the uninterrupted
    run would have drawn. With `origins`, each batch also holds "origins" (B, 2) int32: random
    positions of the patches in a texel-noise field (`nn.unet.texel_noise`), seeded by the
    position in the data, so a noise-driven model sees fresh noise every step.
    """

    def __init__(self, dataset: PatchDataset, batch_size: int, seed: int = 0,
                 state: IteratorState = IteratorState(), origins: bool = False):
        if len(dataset) < batch_size:
            raise ValueError(f"{len(dataset)} patches are fewer than one batch of {batch_size}")
        self.dataset, self.batch_size, self.seed, self.state = dataset, batch_size, seed, state
        self.origins = origins

    def _perm(self, epoch: int) -> np.ndarray:
        return np.random.default_rng([self.seed, epoch]).permutation(len(self.dataset))

    def __iter__(self):
        return self

    def __next__(self) -> dict:
        epoch, cursor = self.state.epoch, self.state.cursor
        if cursor + self.batch_size > len(self.dataset):  # drop the ragged tail of an epoch
            epoch, cursor = epoch + 1, 0
        idx = self._perm(epoch)[cursor:cursor + self.batch_size]
        self.state = IteratorState(epoch, cursor + self.batch_size)
        batch = self.dataset.get(idx)
        if self.origins:
            rng = np.random.default_rng([self.seed, epoch, cursor, 1])
            batch["origins"] = rng.integers(0, 2**20, (len(idx), 2)).astype(np.int32)
        return batch
