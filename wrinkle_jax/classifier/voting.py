"""Temporal voting: per-patch probabilities of a sequence -> one material (paper Fig. 6)."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from wrinkle_jax.classifier.config import ClassifierError
from wrinkle_jax.classifier.model import Classifier


class Classification(NamedTuple):
    """Result of classifying a set of patches or a sequence.

    Attributes:
      material: the winning material name.
      scores: material -> vote share (floats summing to 1).
      num_patches: number of patches that voted.
      histogram: (M, B) int counts: for material m, how many patches have p_m in bin b
        (the paper's Fig. 6).
      bin_edges: (B + 1,) float bin edges in [0, 1].
      patch_probs: (N, M) per-patch probabilities.
      frame_ids: (N,) frame of each patch (empty for bare patches).
    """

    material: str
    scores: dict
    num_patches: int
    histogram: np.ndarray
    bin_edges: np.ndarray
    patch_probs: np.ndarray
    frame_ids: np.ndarray

    def to_json(self) -> dict:
        return {"material": self.material, "scores": self.scores,
                "num_patches": self.num_patches,
                "histogram": {m: [int(c) for c in row] for m, row in
                              zip(self.scores, self.histogram, strict=True)},
                "bin_edges": [float(e) for e in self.bin_edges]}


def vote(probs, bins: int = 10, method: str = "histogram"):
    """Votes over per-patch probabilities (paper Fig. 6).

    For each material m the patches are histogrammed by p_m into `bins` equal bins of [0, 1].
    ``method="histogram"``: the score of m is the histogram's centroid (sum of bin centers
    weighted by counts, / N), i.e. how far the mass of m's histogram sits towards 1; scores
    are normalized to sum 1. ``method="majority"``: the share of patches whose most likely
    material is m. Ties go to the lower material index.

    Args:
      probs: (N, M) probabilities, N >= 1.
      bins: number of histogram bins B.
      method: "histogram" or "majority".
    Returns:
      (scores (M,) float64 summing to 1, histogram (M, B) int64, edges (B + 1,)).
    """
    p = np.asarray(probs, np.float64)
    if p.ndim != 2 or len(p) == 0:
        raise ClassifierError(f"vote needs (N, M) probabilities with N >= 1, got {p.shape}")
    edges = np.linspace(0.0, 1.0, bins + 1)
    # Bin index with 1.0 falling into the last bin.
    idx = np.clip((p * bins).astype(np.int64), 0, bins - 1)
    hist = np.stack([np.bincount(idx[:, m], minlength=bins) for m in range(p.shape[1])])
    if method == "histogram":
        centers = 0.5 * (edges[:-1] + edges[1:])
        raw = hist @ centers / len(p)
    elif method == "majority":
        raw = np.bincount(np.argmax(p, axis=1), minlength=p.shape[1]).astype(np.float64)
    else:
        raise ValueError(f"unknown vote method {method!r}; expected 'histogram' or 'majority'")
    total = raw.sum()
    scores = raw / total if total > 0 else np.full(p.shape[1], 1.0 / p.shape[1])
    return scores, hist, edges


def classify_patches(classifier: Classifier, probs, frame_ids=None, bins: int = 10,
                     method: str = "histogram") -> Classification:
    """Vote over already computed per-patch probabilities (N, M) -> Classification."""
    scores, hist, edges = vote(probs, bins, method)
    names = classifier.config.materials
    return Classification(
        material=names[int(np.argmax(scores))],
        scores={m: float(s) for m, s in zip(names, scores, strict=True)},
        num_patches=int(len(probs)), histogram=hist, bin_edges=edges,
        patch_probs=np.asarray(probs, np.float32),
        frame_ids=np.asarray([] if frame_ids is None else frame_ids, np.int64))
