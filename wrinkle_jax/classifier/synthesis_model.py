"""A saved analysis-by-synthesis classifier (`synthesis`) and its answer for one input.

    clf = synthesis_model.load(path)                       # written by `save`
    result = synthesis_model.classify(arrays, clf)         # a `calibrated.MotionClassification`

`classify` re-simulates the input garment once per fabric on the input's own pin and body
tracks (`synthesis.synthesize`), computes the window features of the input and of every
synthesis (`synthesis.window_features`), and scores the fabrics by the fitted distance of
their differences, exactly as `experiments/classifier_synthesis.py` does in its study:
q = `synthesis.mean_squares` over the chosen families' columns, d = q . w (or the mean of q
when no weights were fitted), p = softmax(-d / T). It answers when max p reaches the
threshold and the nearest synthesis lies within the novelty limit (else nothing in the library
reproduces the input: a skinned garment, another simulator); the group answer (light silks /
heavy wovens / knit) has its own threshold.

Solver of the syntheses (`SynthesisClassifier.solver`): "input" re-simulates with the input's
own settings as its metadata records them (substeps, stretch sweeps, self-collision;
`synthesis.config_from_metadata`), falling back to `substeps` without self-collision when the
file records none; "fixed" always uses `substeps` without self-collision. The distance only
means something when the synthesis strains like the input (experiments/results/classifier).

Cost: 5 fabrics x (settle + frames) simulated frames per call: ~16 s per coarse sequence at 80
substeps without self-collision, ~60-90 s with it, on two shared cores.

File (`.npz`, no pickle): "head" (JSON: format, materials, families, agg, solver, substeps,
frames, settle_frames, window, stride, temperature, threshold, group_threshold,
novelty_limit, meta), "scale" (D,) and optionally "weights" (D,) float64, D = the chosen
families' feature columns.
"""

from __future__ import annotations

import dataclasses
import json
import os
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from wrinkle_jax import MATERIALS, modelfile
from wrinkle_jax.classifier import calibrated, drape, motion
from wrinkle_jax.classifier import synthesis as syn
from wrinkle_jax.classifier.config import ClassifierError
from wrinkle_jax.fileio import NPZ_READ_ERRORS

FORMAT = "wrinkle-jax-synthesis-classifier/1"
# The shipped classifier, when one ships (only once issue 25's targets hold on held-out data):
# `wrinkle-jax classify` and `enhance --material auto` then use it instead of the motion one.
SYNTHESIS_PATH = Path(__file__).resolve().parents[1] / "assets" / "synthesis_classifier.npz"
SOLVERS = ("input", "fixed")


@dataclasses.dataclass(frozen=True, eq=False)
class SynthesisClassifier:
    """A fitted synthesis distance and its calibration.

    Attributes:
      materials: fabric names, the synthesis library's order (names in `wrinkle_jax.MATERIALS`).
      families: feature families compared (`motion.FAMILIES` names).
      agg: "window" or "mean" (`synthesis.mean_squares`).
      scale: (D,) per-feature scale of the differences, D = the families' columns.
      weights: (D,) non-negative weights of the distance, or None (the mean over features).
      temperature: T of p = softmax(-d / T).
      threshold: answer when max p >= this. group_threshold: the same for the group answer.
      novelty_limit: abstain when the nearest synthesis' distance exceeds this.
      solver: "input" or "fixed" (see the module docstring). substeps: the fixed solver's
        substeps per frame (and the fallback of "input").
      frames, settle_frames: synthesized frames and the settle before them.
      window, stride: the feature windows (frames).
      meta: provenance (free-form JSON).
    """

    materials: tuple
    families: tuple
    agg: str
    scale: np.ndarray
    weights: np.ndarray | None
    temperature: float
    threshold: float
    group_threshold: float
    novelty_limit: float
    solver: str = "input"
    substeps: int = 80
    frames: int = 64
    settle_frames: int = 12
    window: int = 32
    stride: int = 16
    meta: dict = dataclasses.field(default_factory=dict)

    def __post_init__(self):
        if self.solver not in SOLVERS:
            raise ClassifierError(f"solver must be one of {SOLVERS}, got {self.solver!r}")
        if self.agg not in ("window", "mean"):
            raise ClassifierError(f"agg must be 'window' or 'mean', got {self.agg!r}")
        d = int(syn.feature_mask(self.families).sum())
        if np.shape(self.scale) != (d,) or (self.weights is not None
                                            and np.shape(self.weights) != (d,)):
            raise ClassifierError(f"scale {np.shape(self.scale)} / weights "
                                  f"{np.shape(self.weights)} do not match the {d} columns of "
                                  f"the families {self.families}")

    def synthesis_config(self, metadata: Mapping) -> syn.SynthesisConfig:
        """The `SynthesisConfig` the syntheses of an input with `metadata` run with."""
        if self.solver == "input" and "substeps" in metadata:
            return syn.config_from_metadata(metadata, frames=self.frames,
                                            settle_frames=self.settle_frames)
        return syn.SynthesisConfig(frames=self.frames, settle_frames=self.settle_frames,
                                   substeps=self.substeps)

    def distances(self, input_features, synth_features) -> np.ndarray:
        """(M,) distances of the input's window features (W, FEATURE_DIM) to each fabric's
        synthesis' (M, W, FEATURE_DIM)."""
        mask = syn.feature_mask(self.families)
        return syn.distances(syn.differences(input_features, synth_features)[..., mask],
                             self.scale, self.weights, self.agg)


def from_study(spec: Mapping, scale, weights, calibration: Mapping, *, solver: str,
               substeps: int, frames: int = 64, settle_frames: int = 12, window: int = 32,
               stride: int = 16, materials=None, meta: Mapping | None = None
               ) -> SynthesisClassifier:
    """A classifier from a study's choice (experiments/classifier_synthesis.py): `spec`
    {"families", "agg", "l2"}, the fitted distance's `scale` and `weights` (None: uniform),
    `calibration` {"T", "threshold", "group_threshold", "novelty_limit"}; the synthesis
    `solver` ("input" / "fixed") and `substeps`, frames/settle/windows as the study used."""
    return SynthesisClassifier(
        materials=tuple(materials or MATERIALS), families=tuple(spec["families"]),
        agg=str(spec["agg"]), scale=np.asarray(scale, np.float64),
        weights=None if weights is None else np.asarray(weights, np.float64),
        temperature=float(calibration["T"]), threshold=float(calibration["threshold"]),
        group_threshold=float(calibration["group_threshold"]),
        novelty_limit=float(calibration["novelty_limit"]), solver=solver,
        substeps=int(substeps), frames=int(frames), settle_frames=int(settle_frames),
        window=int(window), stride=int(stride), meta=dict(meta or {}))


def decide(clf: SynthesisClassifier, dist, num_windows: int) -> calibrated.MotionClassification:
    """The calibrated answer for distances `dist` (M,) to the fabrics' syntheses."""
    d = np.asarray(dist, np.float64)
    probs = syn.scores_to_probs(d, clf.temperature)
    scores = {m: float(p) for m, p in zip(clf.materials, probs, strict=True)}
    groups = calibrated.group_scores(scores)
    top_group = max(groups, key=groups.get)
    conf, nearest = float(probs.max()), float(d.min())
    reason = ""
    if not np.isfinite(nearest) or nearest > clf.novelty_limit:
        reason = (f"no fabric's re-simulation reproduces the input (nearest synthesis "
                  f"{nearest:.3g} > limit {clf.novelty_limit:.3g}; e.g. a skinned garment or "
                  f"another simulator)")
    elif conf < clf.threshold:
        reason = f"low confidence ({conf:.2f} < threshold {clf.threshold:.2f})"
    group_ok = not reason.startswith("no fabric") and groups[top_group] >= clf.group_threshold
    return calibrated.MotionClassification(
        material=None if reason else clf.materials[int(probs.argmax())], scores=scores,
        confidence=conf, abstained=bool(reason), reason=reason, novelty=nearest,
        num_windows=int(num_windows), group=top_group if group_ok else None,
        group_scores=groups, group_confidence=float(groups[top_group]))


def _abstain(clf: SynthesisClassifier, reason: str) -> calibrated.MotionClassification:
    n = len(clf.materials)
    scores = {m: 1.0 / n for m in clf.materials}
    groups = calibrated.group_scores(scores)
    return calibrated.MotionClassification(None, scores, 1.0 / n, True, reason, float("nan"),
                                           0, None, groups, max(groups.values()))


def classify(arrays: Mapping, clf: SynthesisClassifier) -> calibrated.MotionClassification:
    """Classify one simulated sequence (a dict of its `.npz` arrays: frames (T, V, 3) m,
    faces, uvs in meters, uv_faces, pins (T, P, 3), pin_vertices, capsule_ends (T, C, 2, 3),
    capsule_radii, fps, metadata). An input that cannot be re-simulated (no pin track, UVs
    not in meters, fewer than `clf.frames` frames) gets an abstention saying why.

    `novelty` in the result is the nearest synthesis' distance (limit: `clf.novelty_limit`).
    """
    why = syn.check_input(arrays)
    n = int(np.shape(arrays["frames"])[0]) if "frames" in arrays else 0
    if not why and n < clf.frames:
        why = f"{n} frames, fewer than the {clf.frames} the classifier compares"
    if not why and motion.reference_track(arrays) is None:
        why = "no body track (capsule_ends or pins)"
    if why:
        return _abstain(clf, why)
    meta = arrays.get("metadata")
    meta = {} if meta is None else (meta if isinstance(meta, Mapping) else json.loads(str(meta)))
    cfg = clf.synthesis_config(meta)
    plan = None
    if "drape" in clf.families:
        plan = drape.make_plan(arrays["faces"], arrays["uvs"], arrays["uv_faces"],
                               np.asarray(arrays["frames"][0]))
    model = syn.build_model(arrays)
    feats = [syn.window_features(arrays, syn.synthesize(arrays, m, cfg, model), clf.window,
                                 clf.stride, drape_plan=plan) for m in clf.materials]
    inp = syn.window_features(arrays, np.asarray(arrays["frames"][:clf.frames]), clf.window,
                              clf.stride, drape_plan=plan)
    return decide(clf, clf.distances(inp, np.stack(feats)), len(inp))


def save(path: str | os.PathLike, clf: SynthesisClassifier) -> Path:
    """Write `clf` as a plain `.npz` (atomically)."""
    head = {f.name: getattr(clf, f.name) for f in dataclasses.fields(clf)
            if f.name not in ("scale", "weights")}
    head["materials"], head["families"] = list(clf.materials), list(clf.families)
    arrays = {"scale": np.asarray(clf.scale, np.float64), modelfile.HEAD: head}
    if clf.weights is not None:
        arrays["weights"] = np.asarray(clf.weights, np.float64)
    return modelfile.write_headed(path, FORMAT, arrays)


def is_synthesis_file(path: str | os.PathLike) -> bool:
    """True when `path` is a readable `.npz` written by `save`."""
    try:
        with np.load(path, allow_pickle=False) as z:
            return is_synthesis_head(z[modelfile.HEAD]) if modelfile.HEAD in z.files else False
    except NPZ_READ_ERRORS:
        return False


def is_synthesis_head(head: np.ndarray) -> bool:
    """True when a file's head array (`modelfile.HEAD`) names this format."""
    return modelfile.head_format(head) == FORMAT


def shipped() -> bool:
    """True when a synthesis classifier ships (`SYNTHESIS_PATH` exists)."""
    return SYNTHESIS_PATH.is_file()


def load(path: str | os.PathLike | None = None) -> SynthesisClassifier:
    """Read a classifier written by `save` (default: the shipped `SYNTHESIS_PATH`).

    Raises:
      ClassifierError: naming the file when it is missing or not a synthesis classifier.
    """
    path = SYNTHESIS_PATH if path is None else path
    return modelfile.read_headed(path, FORMAT, "synthesis classifier", ClassifierError, _build)


def _build(head: dict, arrays: dict) -> SynthesisClassifier:
    head["materials"], head["families"] = tuple(head["materials"]), tuple(head["families"])
    weights = np.asarray(arrays["weights"], np.float64) if "weights" in arrays else None
    return SynthesisClassifier(scale=np.asarray(arrays["scale"], np.float64), weights=weights,
                               **head)
