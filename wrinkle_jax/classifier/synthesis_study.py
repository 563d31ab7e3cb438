"""The analysis-by-synthesis study's cache entries and fitted distance (issue 25), shared by
`experiments/classifier_synthesis.py` (the study) and `experiments/classifier_s24c.py` (the
shipped classifier's check).

Cache layout: `<cache>/<variant>/<split>/<scene>/<material>.npz`, each holding the input's
window features (`input` (W, D)), its skinned stand-in's (`skinned`), the five syntheses'
(`synth` (M, W, D)), their position RMS to the input (`rms` (M,) m) and seconds.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from wrinkle_jax import MATERIALS
from wrinkle_jax.classifier import synthesis as syn


def load_npz(path: str | Path) -> dict:
    """All arrays of an `.npz` file, loaded."""
    with np.load(path) as z:
        return {k: z[k] for k in z.files}


def load_entries(cache: str | Path, variant: str) -> list[dict]:
    """Every cached input of `variant`: dicts with split, scene, material, label (index in
    `MATERIALS`) and the file's arrays; files being written (`.tmp.npz`) are skipped."""
    out = []
    for p in sorted((Path(cache) / variant).glob("*/*/*.npz")):
        if p.name.endswith(".tmp.npz"):
            continue
        out.append({"split": p.parent.parent.name, "scene": p.parent.name,
                    "material": p.stem, "label": MATERIALS.index(p.stem), **load_npz(p)})
    return out


def entry_differences(entry: dict, key: str = "input") -> np.ndarray:
    """(M, W, D) input (or `key`, e.g. "skinned") minus synthesis features of a cache entry."""
    return syn.differences(entry[key], entry["synth"])


class Distance:
    """A distance fitted on training entries: per-feature scale (D,) of the chosen families'
    columns and, when spec["l2"] is not None, conditional-logit weights (D,); otherwise the
    mean over features.

    Args:
      spec: {"families", "agg", "l2"}. fit_on: training cache entries.
    """

    def __init__(self, spec: dict, fit_on: list[dict]):
        self.spec, self.mask = spec, syn.feature_mask(spec["families"])
        self.scale = syn.difference_scale([entry_differences(e)[..., self.mask]
                                           for e in fit_on])
        self.w = None
        if spec["l2"] is not None:
            q = np.stack([self.q(e) for e in fit_on])
            self.w = syn.fit_weights(q, np.array([e["label"] for e in fit_on]), spec["l2"])

    def q(self, e, key="input"):
        """(M, D) `synthesis.mean_squares` of one entry."""
        return syn.mean_squares(entry_differences(e, key)[..., self.mask], self.scale,
                                self.spec["agg"])

    def __call__(self, entries, key="input") -> np.ndarray:
        """(len(entries), M) distances (`synthesis.distances`)."""
        return np.stack([syn.distances(entry_differences(e, key)[..., self.mask], self.scale,
                                       self.w, self.spec["agg"]) for e in entries])


def check_classify(clf, arrays: dict, dist: Distance, entry: dict) -> tuple[dict, object]:
    """Run `synthesis_model.classify(arrays, clf)` on an input file's arrays and compare the
    distances its answer implies (nearest distance + T x log-probability ratios) with the
    study's `dist` on the cached `entry` of the same input.

    Returns:
      (row, result): row = {seconds, classify_distances, reference_distances, max_abs_diff,
      max_rel_diff, classify: {material, confidence, abstained, group}, cache_config}; result
      the `MotionClassification`.
    """
    from wrinkle_jax.classifier import synthesis_model

    t0 = time.perf_counter()
    r = synthesis_model.classify(arrays, clf)
    secs = time.perf_counter() - t0
    p = np.array([r.scores[k] for k in clf.materials])
    energy = -clf.temperature * np.log(np.maximum(p, 1e-300))
    got = r.novelty + energy - energy.min()
    ref = dist([entry])[0]
    row = {"seconds": secs, "classify_distances": got.tolist(),
           "reference_distances": ref.tolist(), "max_abs_diff": float(np.abs(got - ref).max()),
           "max_rel_diff": float((np.abs(got - ref) / np.maximum(np.abs(ref), 1e-12)).max()),
           "classify": {"material": r.material, "confidence": r.confidence,
                        "abstained": r.abstained, "group": r.group},
           "cache_config": str(entry["config"]) if "config" in entry else None}
    return row, r


def check_inputs(clf, dist: Distance, entries: list[dict], names, data: str | Path, seed: int):
    """`check_classify` on the inputs named "scene/material" in `names`: each one's coarse
    file `<data>/<scene>/<material>_coarse_s<seed>.npz` against its cached entry among
    `entries`.

    Yields:
      (name, entry, row) per input, in order (one input costs a re-simulation, so callers
      can report each as it is done).
    """
    for name in names:
        sc, m = name.split("/")
        entry = next(e for e in entries if (e["scene"], e["material"]) == (sc, m))
        arrays = load_npz(Path(data) / sc / f"{m}_coarse_s{seed}.npz")
        row, _ = check_classify(clf, arrays, dist, entry)
        yield name, entry, row
