"""A calibrated motion classifier that can abstain (issue 25).

    window features (N, D) --standardize--> multinomial logistic regression --> log p (N, M)
      --mean over windows / temperature T--> softmax: per-sequence probabilities (M,)
      --answer if max p >= threshold and the features look like training data, else abstain

Why this shape: the motion features (`motion`) are a few dozen numbers per window, and there are
only ~50 training sequences (10 garments x 5 fabrics), so a linear model is what the data can
support. Windows of one sequence are strongly correlated, so the mean log-probability over
windows is far too confident if read as a product of independent votes; one temperature, fitted
on cross-validation folds at the sequence level, puts the confidences on the right scale. The
abstain threshold is chosen on the same out-of-fold predictions. A second guard, `novelty`
(mean squared standardized distance of the sequence's mean feature from the training data),
catches inputs unlike any simulation, such as a skinned garment with no dynamics, whose
features a linear model would extrapolate into a confident but meaningless answer.

Everything here is a pure function of NumPy/JAX arrays; the model is a NamedTuple of arrays and
a frozen config, saved as a plain `.npz` (no pickle).
"""

from __future__ import annotations

import dataclasses
import functools
import os
from pathlib import Path
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax

from wrinkle_jax import MATERIALS, modelfile
from wrinkle_jax.classifier.config import ClassifierError
from wrinkle_jax.classifier.motion import FAMILIES, family_slices

MOTION_PATH = Path(__file__).resolve().parents[1] / "assets" / "motion_classifier.npz"
_FORMAT = "wrinkle-jax-motion-classifier/1"
# Physically meaningful groups (issue 25): light silks, heavy wovens, knit.
GROUPS = {"silk_charmeuse": "light_silk", "silk_chiffon": "light_silk",
          "wool_melton": "heavy_woven", "denim_light": "heavy_woven",
          "knit_terry": "knit"}


@dataclasses.dataclass(frozen=True)
class MotionConfig:
    """Static settings of a motion classifier.

    Attributes:
      families: feature families used (subset of `motion.FAMILIES`, in that order).
      window, stride: frames per window and between window starts.
      l2: weight of the L2 penalty on the logistic weights (per standardized feature).
      steps: full-batch optimizer steps.
      materials: output order.
      clip: at prediction, standardized features are clipped to +-clip (0: off) before the
        linear model, so a garment unlike the training ones cannot push a logit past what the
        training range supports (leave-one-garment-out, the pleated skirt's silks were called
        denim at confidence 0.9 without it). The novelty guard reads the unclipped values.
    """

    families: tuple[str, ...] = FAMILIES
    window: int = 32
    stride: int = 16
    l2: float = 1e-2
    steps: int = 300
    materials: tuple[str, ...] = MATERIALS
    clip: float = 0.0

    def __post_init__(self):
        bad = set(self.families) - set(FAMILIES)
        if bad or not self.families:
            raise ValueError(f"families must be a non-empty subset of {FAMILIES}, got "
                             f"{self.families}")

    def columns(self) -> np.ndarray:
        """Indices of the used features in the full `motion.window_features` vector."""
        sl = family_slices()
        return np.concatenate([np.arange(sl[f].start, sl[f].stop) for f in self.families])


class MotionClassifier(NamedTuple):
    """Weights (D, M), bias (M,), mean/std (D,) of the used features, the sequence-level
    temperature, the abstain threshold on max p, the novelty limit, the config, and the
    threshold on the top group's probability (`GROUPS`) for a group-level answer."""

    weights: np.ndarray
    bias: np.ndarray
    mean: np.ndarray
    std: np.ndarray
    temperature: float
    threshold: float
    novelty_limit: float
    config: MotionConfig
    group_threshold: float = 1.0


@functools.partial(jax.jit, static_argnames=("num_classes", "steps"))
def _fit_logistic(x, y, l2, num_classes: int, steps: int):
    """Full-batch L-BFGS on the mean cross-entropy + l2 * |W|^2.

    Module-level jit: every fit with the same data shape reuses one compilation (the
    cross-validation fits hundreds of models of a handful of shapes).
    """

    def loss(p):
        z = x @ p["w"] + p["b"]
        ll = jax.nn.log_softmax(z)[jnp.arange(y.shape[0]), y]
        return -ll.mean() + l2 * jnp.sum(p["w"] ** 2)

    params = {"w": jnp.zeros((x.shape[1], num_classes)), "b": jnp.zeros(num_classes)}
    p = lbfgs_minimize(loss, params, steps)
    return p["w"], p["b"]


def lbfgs_minimize(loss, params, steps: int):
    """`steps` full-batch `optax.lbfgs` steps (zoom line search) on `loss(params)` from
    `params` (a pytree); traceable, so callers jit around it. Returns the final params."""
    opt = optax.lbfgs()
    value_and_grad = optax.value_and_grad_from_state(loss)

    def body(carry, _):
        p, s = carry
        v, g = value_and_grad(p, state=s)
        u, s = opt.update(g, s, p, value=v, grad=g, value_fn=loss)
        return (optax.apply_updates(p, u), s), v

    (p, _), _ = jax.lax.scan(body, (params, opt.init(params)), None, length=steps)
    return p


def fit(features, labels, config: MotionConfig = MotionConfig()) -> MotionClassifier:
    """Fit the window-level logistic model (temperature 1, no abstain threshold yet).

    Args:
      features: (N, FEATURE_DIM) full window features (`motion.window_features`).
      labels: (N,) int material indices into `config.materials`.
    """
    x = np.asarray(features, np.float64)[:, config.columns()]
    mean, std = x.mean(0), x.std(0)
    std = np.where(std > 1e-9, std, 1.0)  # a constant feature carries nothing; keep it 0
    z = jnp.asarray((x - mean) / std, jnp.float32)
    w, b = _fit_logistic(z, jnp.asarray(labels, jnp.int32), jnp.float32(config.l2),
                         num_classes=len(config.materials), steps=config.steps)
    return MotionClassifier(np.asarray(w, np.float64), np.asarray(b, np.float64), mean, std,
                            1.0, 0.0, float("inf"), config)


def standardized(model: MotionClassifier, features) -> np.ndarray:
    """(N, D) standardized used features of full window features (N, FEATURE_DIM)."""
    x = np.asarray(features, np.float64)[:, model.config.columns()]
    return (x - model.mean) / model.std


def window_log_probs(model: MotionClassifier, features) -> np.ndarray:
    """(N, M) log-probabilities of each window (before the temperature)."""
    x = standardized(model, features)
    if model.config.clip > 0:
        x = np.clip(x, -model.config.clip, model.config.clip)
    z = x @ model.weights + model.bias
    return np.asarray(jax.nn.log_softmax(jnp.asarray(z)), np.float64)


def sequence_probs(mean_log_probs, temperature: float = 1.0) -> np.ndarray:
    """softmax(mean log p / T): (..., M) per-sequence probabilities."""
    z = np.asarray(mean_log_probs, np.float64) / temperature
    z = z - z.max(axis=-1, keepdims=True)
    e = np.exp(z)
    return e / e.sum(axis=-1, keepdims=True)


def nll(probs, labels) -> float:
    """Mean negative log-likelihood of the true labels; probs (N, M), labels (N,)."""
    p = np.asarray(probs)[np.arange(len(labels)), np.asarray(labels)]
    return float(-np.mean(np.log(np.maximum(p, 1e-12))))


_T_GRID = np.exp(np.linspace(-3.0, 4.0, 141))  # T from 0.05 to 55, 5 % steps


def fit_temperature(mean_log_probs, labels, grid=_T_GRID) -> float:
    """The temperature T minimizing the NLL of softmax(mean log p / T) (grid search in log T).

    Args:
      mean_log_probs: (S, M) out-of-fold mean window log-probabilities per sequence.
      labels: (S,) true material indices.
    """
    losses = [nll(sequence_probs(mean_log_probs, t), labels) for t in grid]
    return float(grid[int(np.argmin(losses))])


def reliability(probs, labels, bins: int = 10):
    """Reliability table of the top-class confidence.

    Returns:
      (counts (B,), mean confidence (B,), accuracy (B,), ece): empty bins have NaN means;
      ECE = sum_b counts_b / N * |acc_b - conf_b|.
    """
    p = np.asarray(probs)
    conf = p.max(axis=1)
    correct = (p.argmax(axis=1) == np.asarray(labels)).astype(np.float64)
    idx = np.clip((conf * bins).astype(np.int64), 0, bins - 1)
    counts = np.bincount(idx, minlength=bins).astype(np.int64)
    with np.errstate(invalid="ignore"):
        mconf = np.bincount(idx, conf, bins) / counts
        macc = np.bincount(idx, correct, bins) / counts
    ece = float(np.nansum(counts / max(len(conf), 1) * np.abs(macc - mconf)))
    return counts, mconf, macc, ece


def choose_threshold(confidence, correct, target: float = 0.9, min_answers: int = 5) -> float:
    """The lowest confidence threshold whose answers (confidence >= threshold) are at least
    `target` accurate, over at least `min_answers` answers; 1.0 (never answer... almost) when
    no threshold reaches the target. Chosen on out-of-fold predictions.
    """
    conf = np.asarray(confidence, np.float64)
    ok = np.asarray(correct, bool)
    for t in np.sort(np.unique(conf)):
        keep = conf >= t
        if keep.sum() >= min_answers and ok[keep].mean() >= target:
            return float(t)
    return 1.0


def novelty(model: MotionClassifier, features) -> float:
    """Mean squared standardized value of the sequence's mean used feature (training ~ small).

    A skinned garment (no dynamics) has near-zero deformation speed and spectra unlike any
    simulation, so its standardized mean lies far outside the training cloud.
    """
    z = standardized(model, features).mean(axis=0)
    return float(np.mean(z ** 2))


def group_scores(scores: dict) -> dict:
    """Material name -> p summed into `GROUPS` (light_silk, heavy_woven, knit) -> p."""
    out = {}
    for m, p in scores.items():
        out[GROUPS[m]] = out.get(GROUPS[m], 0.0) + float(p)
    return out


class MotionClassification(NamedTuple):
    """material (None when abstained), scores (name -> p), confidence = max p, abstained,
    reason (why it abstained, '' when it answered), novelty, num_windows, and the group-level
    answer: group (None when that abstains too), group_scores, group_confidence."""

    material: str | None
    scores: dict
    confidence: float
    abstained: bool
    reason: str
    novelty: float
    num_windows: int
    group: str | None = None
    group_scores: dict | None = None
    group_confidence: float = 0.0

    def to_json(self) -> dict:
        return dict(self._asdict())


def classify_features(model: MotionClassifier, features) -> MotionClassification:
    """Vote over the windows of one sequence and decide whether to answer.

    Args:
      features: (N, FEATURE_DIM) window features of one sequence, N >= 1.
    """
    f = np.asarray(features)
    if f.ndim != 2 or len(f) == 0 or not np.all(np.isfinite(f)):
        raise ClassifierError(f"need (N >= 1, D) finite window features, got shape {f.shape}")
    probs = sequence_probs(window_log_probs(model, f).mean(axis=0), model.temperature)
    names = model.config.materials
    scores = {m: float(p) for m, p in zip(names, probs, strict=True)}
    groups = group_scores(scores)
    top_group = max(groups, key=groups.get)
    conf = float(probs.max())
    nov = novelty(model, f)
    reason = ""
    if nov > model.novelty_limit:
        reason = (f"the motion is unlike every training simulation (novelty {nov:.3g} > "
                  f"{model.novelty_limit:.3g}; e.g. a skinned garment without dynamics)")
    elif conf < model.threshold:
        reason = f"low confidence ({conf:.2f} < threshold {model.threshold:.2f})"
    group_ok = nov <= model.novelty_limit and groups[top_group] >= model.group_threshold
    return MotionClassification(
        material=None if reason else names[int(probs.argmax())],
        scores=scores, confidence=conf, abstained=bool(reason), reason=reason, novelty=nov,
        num_windows=int(len(f)), group=top_group if group_ok else None, group_scores=groups,
        group_confidence=float(groups[top_group]))


def save(path: str | os.PathLike, model: MotionClassifier, meta: dict | None = None) -> Path:
    """Write the model as a plain `.npz` (float32 arrays, JSON config), atomically."""
    head = {"config": dataclasses.asdict(model.config), "temperature": model.temperature,
            "threshold": model.threshold, "novelty_limit": model.novelty_limit,
            "group_threshold": model.group_threshold, "meta": meta or {}}
    arrays = {k: np.asarray(getattr(model, k), np.float32)
              for k in ("weights", "bias", "mean", "std")}
    return modelfile.write_headed(path, _FORMAT, {**arrays, modelfile.HEAD: head})


def load(path: str | os.PathLike | None = None) -> MotionClassifier:
    """Read a model written by `save` (default: the shipped `MOTION_PATH`).

    Raises:
      ClassifierError: naming the file when it is missing or not a motion classifier.
    """
    path = Path(MOTION_PATH if path is None else path)
    model = modelfile.read_headed(path, _FORMAT, "motion classifier", ClassifierError, _decode)
    d, m = len(model.config.columns()), len(model.config.materials)
    if model.weights.shape != (d, m) or model.bias.shape != (m,):
        raise ClassifierError(f"{path}: weights {model.weights.shape} do not match the "
                              f"config ({d} features, {m} materials)")
    return model


def _decode(head: dict, arrays: dict) -> MotionClassifier:
    cfg = head["config"]
    config = MotionConfig(**{**cfg, "families": tuple(cfg["families"]),
                             "materials": tuple(cfg["materials"])})
    weights, bias, mean, std = (np.asarray(arrays[k], np.float64)
                                for k in ("weights", "bias", "mean", "std"))
    return MotionClassifier(weights, bias, mean, std, float(head["temperature"]),
                            float(head["threshold"]), float(head["novelty_limit"]), config,
                            float(head.get("group_threshold", 1.0)))
