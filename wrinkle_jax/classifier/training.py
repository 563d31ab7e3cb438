"""Training data for the material classifier: sequences -> cached VGG features of patches.

The VGG19 is frozen, so its features are computed once per patch and cached; only the
four-layer MLP is trained on them (`wrinkle_jax.classifier.train_classifier`), which takes
seconds instead of hours on a CPU.

On disk (`root/`), one folder per sequence variant::

    <name>/meta.json              material, scene, garment, motion, resolution, variant
                                  ("coarse" or "fine_ds": fine maps made coarse-looking with
                                  `normalmap.downsample_like_coarse`), split, frame of every
                                  patch, the texel size and patch size
    <name>/<feature>.npy          (N, D) float16 raw features per spec (":" written as "-")

A folder whose meta.json exists is skipped, so an interrupted build resumes; files are
written atomically, meta.json last. Splits follow `wrinkle_jax.data.split_of`: held-out
garments and motions (the simulator's test scenes) are "heldout" and never reach training.
"""

from __future__ import annotations

import dataclasses
import io
import json
import math
import os
import time
from collections.abc import Iterable
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from wrinkle_jax import classifier as clf_mod
from wrinkle_jax import data, material_index, normalmap
from wrinkle_jax.fileio import atomic_write_bytes, atomic_write_text
from wrinkle_jax.meshio import load_sequence

# Candidate features measured by experiments/classifier_report.py (one VGG pass gives all).
CANDIDATE_FEATURES = ("relu3_1:stats", "relu3_1:grid4", "relu4_1:stats", "relu4_1:grid4",
                      "relu5_4:stats", "relu5_4:grid4")


@dataclasses.dataclass(frozen=True)
class FeatureCacheConfig:
    """How patches are sampled for the feature cache (static, hashable).

    Attributes:
      classifier: texel size, patch size, coverage and downsampling factor (the feature
        field is ignored here; `features` lists what is cached).
      features: feature specs computed in the same VGG pass.
      patches_per_frame: crops per sampled frame.
      num_frames: frames sampled evenly over each sequence.
      augment: dihedral augmentation of training crops (held-out crops are never augmented).
      batch_size: patches per VGG call.
      seed: base seed; each sequence derives its key from it and its name.
    """

    classifier: clf_mod.ClassifierConfig = clf_mod.ClassifierConfig()
    features: tuple[str, ...] = CANDIDATE_FEATURES
    patches_per_frame: int = 4
    num_frames: int = 60
    augment: bool = True
    batch_size: int = 16
    seed: int = 0


def _feature_file(spec: str) -> str:
    return spec.replace(":", "-") + ".npy"


def _save_npy(path: Path, arr: np.ndarray) -> None:
    buf = io.BytesIO()
    np.save(buf, arr)
    atomic_write_bytes(path, buf.getvalue())


def sequence_variants(path: str | os.PathLike, fine_ds: bool = True) -> list[tuple[str, bool]]:
    """(variant, downsample) pairs to extract from a sequence file: coarse sims as they are,
    fine sims downsampled to look coarse (if `fine_ds`)."""
    name = Path(path).stem
    if "_coarse_" in name:
        return [("coarse", False)]
    if "_fine_" in name and fine_ds:
        return [("fine_ds", True)]
    return []


def cache_sequence(path: str | os.PathLike, root: str | os.PathLike, vgg_params,
                   config: FeatureCacheConfig, variant: str = "coarse", downsample: bool = False,
                   conv_impl: str = "auto", splits: tuple[str, ...] | None = None
                   ) -> dict | None:
    """Extract and cache the features of one sequence variant; returns its meta entry.

    With `splits`, a sequence of another split is skipped (None is returned).
    """
    path = Path(path)
    root = Path(root)
    name = f"{path.parent.name}__{path.stem}__{variant}"
    out = root / name
    if (out / "meta.json").exists():
        entry = json.loads((out / "meta.json").read_text())
        return None if splits is not None and entry["split"] not in splits else entry
    t0 = time.perf_counter()
    seq = load_sequence(path)
    info = data.sequence_info(seq, name)
    split = data.split_of(info, data.PatchDataConfig())
    if splits is not None and split not in splits:
        return None
    ccfg = config.classifier
    plan = normalmap.make_plan(seq.garment, texel_size=ccfg.texel_size)
    key = jax.random.key(data._seed_for(name, config.seed), impl="rbg")
    augment = config.augment and split == "train"
    rgb, mask, fids = clf_mod.sample_patches(plan, seq.frames, key, ccfg, config.patches_per_frame,
                                             config.num_frames, downsample=downsample,
                                             augment=augment, source=str(path))
    sample_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    feats = _extract(vgg_params, rgb, mask, config.features, config.batch_size, conv_impl)
    vgg_s = time.perf_counter() - t0
    out.mkdir(parents=True, exist_ok=True)
    for spec, arr in feats.items():
        _save_npy(out / _feature_file(spec), arr.astype(np.float16))
    entry = {"name": name, "source": str(path), "variant": variant, "split": split, **info,
             "material_id": material_index(info["material"]),
             "resolution": seq.metadata.get("resolution"),
             "frames": [int(f) for f in fids], "num_patches": int(len(fids)),
             "texel_size": ccfg.texel_size, "patch_size": ccfg.patch_size,
             "min_coverage": ccfg.min_coverage, "augment": augment,
             "mask_fraction": [float(m) for m in mask.mean(axis=(1, 2, 3))],
             "features": list(feats), "sample_s": sample_s, "vgg_s": vgg_s}
    atomic_write_text(out / "meta.json", json.dumps(entry))
    return entry


# One jitted function for every sequence (a jit made per call would recompile each time).
_features_jit = jax.jit(clf_mod.patch_features, static_argnames=("features", "conv_impl"))


def _extract(vgg_params, rgb, mask, features, batch_size, conv_impl):
    fn = _features_jit
    n = len(rgb)
    parts: dict[str, list] = {f: [] for f in features}
    for start in range(0, n, batch_size):
        idx = np.resize(np.arange(start, min(start + batch_size, n)), batch_size)
        got = fn(vgg_params, jnp.asarray(rgb[idx]), jnp.asarray(mask[idx]),
                 features=tuple(features), conv_impl=conv_impl)
        for f in features:
            parts[f].append(np.asarray(got[f])[: min(batch_size, n - start)])
    return {f: np.concatenate(v) for f, v in parts.items()}


def build_feature_cache(sources: Iterable[str | os.PathLike], root: str | os.PathLike,
                        vgg_params, config: FeatureCacheConfig = FeatureCacheConfig(),
                        fine_ds: bool = True, splits: tuple[str, ...] | None = None,
                        progress=None) -> list[dict]:
    """Cache features for every sequence file (coarse sims, and fine sims downsampled).

    `splits` restricts caching to sequences of those splits (e.g. ("train",)).
    """
    entries = []
    for src in sources:
        for variant, downsample in sequence_variants(src, fine_ds):
            entry = cache_sequence(src, root, vgg_params, config, variant, downsample,
                                   splits=splits)
            if entry is None:
                continue
            entries.append(entry)
            if progress is not None:
                progress(entry)
    return entries


def load_cache(root: str | os.PathLike, feature: str, split: str | None = None,
               variants: tuple[str, ...] | None = None) -> tuple[np.ndarray, np.ndarray, list]:
    """Cached features of all matching sequences.

    Returns:
      (features (N, D) float16, labels (N,) int32, entries): `entries` are the meta dicts,
      each with an added "rows" slice [start, stop) into the arrays.
    """
    root = Path(root)
    feats, labels, entries = [], [], []
    start = 0
    for meta_path in sorted(root.glob("*/meta.json")):
        entry = json.loads(meta_path.read_text())
        if split is not None and entry["split"] != split:
            continue
        if variants is not None and entry["variant"] not in variants:
            continue
        f = np.load(meta_path.parent / _feature_file(feature))
        feats.append(f)
        labels.append(np.full(len(f), entry["material_id"], np.int32))
        entry["rows"] = [start, start + len(f)]
        start += len(f)
        entries.append(entry)
    if not feats:
        raise FileNotFoundError(f"{root}: no cached sequences match split={split} "
                                f"variants={variants}")
    return np.concatenate(feats), np.concatenate(labels), entries


def accuracy_by_patches(probs_per_sequence, labels, counts, key, trials: int = 50,
                        bins: int = 10, method: str = "histogram") -> dict[int, float]:
    """Per-sequence accuracy when voting with k random patches of each sequence.

    Args:
      probs_per_sequence: list of (N_s, M) per-patch probabilities.
      labels: (S,) true material indices.
      counts: numbers of patches k to try (each <= min N_s).
      key: PRNG key for the subsets (NumPy generator seeded from it).
      trials: random subsets per sequence and k.
    Returns:
      dict k -> mean accuracy over sequences and trials.
    """
    rng = np.random.default_rng(np.asarray(jax.random.key_data(key)).ravel().tolist())
    out = {}
    for k in counts:
        hits = []
        for probs, y in zip(probs_per_sequence, labels, strict=True):
            for _ in range(trials):
                sub = probs[rng.choice(len(probs), size=min(k, len(probs)), replace=False)]
                scores, _, _ = clf_mod.vote(sub, bins, method)
                hits.append(int(np.argmax(scores)) == int(y))
        out[int(k)] = float(np.mean(hits)) if hits else math.nan
    return out
