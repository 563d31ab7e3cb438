"""Evaluation metrics.

Contract:
  :func:`improvement_score` is the paper's quantitative score (Sec. 5, "Quantitative
  evaluation") for batches of patches, per patch:

      score = 100 * | (L(N) - L(N*)) / (L(N) - L(N_hat)) |

  with N the coarse input, N* the output, N_hat the ground truth and L(X) the masked style loss
  of X against N_hat (``nn.losses.style_loss``). Since L(N_hat) = 0 this is
  ``100 |L(N) - L(N*)| / L(N)``: 100 when the output matches the target's style, 0 when it is
  no better than the input.

  Quirk of the paper's absolute value, kept for fidelity: the score measures how far L moved, not
  in which direction. An output *worse* than its input (L(N*) > L(N)) also scores > 0, and
  above 100 once L(N*) > 2 L(N). ``signed_score = 100 (L(N) - L(N*)) / L(N)`` (<= 100, negative
  when the output is worse) is returned alongside to tell these cases apart.

  Degenerate denominator: when ``|L(N) - L(N_hat)| <= eps`` the input already matches the
  target and the ratio is undefined. Then ``valid`` is False and both scores are 100 if the
  output also matches (``|L(N*) - L(N_hat)| <= eps``) and 0 otherwise -- never NaN. Average
  scores over ``valid`` patches only when reporting.

  Sets of patches without correspondence (paper Table 2): :func:`chamfer_distance` of feature
  point sets, :func:`decrease_ratio` DR = 100 |C1 - C2| / C1 (and its signed form), and the
  Laplacian-eigenmap :func:`spectral_embedding` the paper plots them in.

  Temporal coherence: :func:`normal_angles` (degrees, accurate for small angles),
  :func:`mean_angular_change` of two normal maps over a mask and :func:`flicker_series` of a
  sequence of maps. These set and temporal metrics are NumPy (float64), for reporting.
"""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
import numpy as np

from wrinkle_jax.nn import losses, vgg

__all__ = ["ImprovementScore", "chamfer_distance", "chamfer_from_sq_dists", "decrease_ratio",
           "flicker_series", "improvement_score", "improvement_score_from_losses",
           "mean_angular_change", "normal_angles", "spectral_embedding", "sq_dists"]


class ImprovementScore(NamedTuple):
    """Per-patch improvement scores; every field is (N,)."""

    score: jnp.ndarray  # float32, the paper's 100 |.| score
    signed_score: jnp.ndarray  # float32, 100 (L(N) - L(N*)) / (L(N) - L(N_hat))
    valid: jnp.ndarray  # bool, False where the denominator is <= eps
    loss_input: jnp.ndarray  # float32, L(N)
    loss_output: jnp.ndarray  # float32, L(N*)


def improvement_score_from_losses(loss_input, loss_output, loss_target=0.0, eps=1e-6):
    """The improvement score from precomputed style losses (see module docstring).

    Args:
      loss_input: (N,) L(N), style loss of the input against the ground truth.
      loss_output: (N,) L(N*), style loss of the output against the ground truth.
      loss_target: (N,) or scalar L(N_hat) (0 when the ground truth is the style reference).
      eps: denominators with magnitude <= eps are treated as zero (same units as the losses).

    Returns:
      ImprovementScore.
    """
    loss_input = jnp.asarray(loss_input, jnp.float32)
    loss_output = jnp.asarray(loss_output, jnp.float32)
    den = loss_input - loss_target
    valid = jnp.abs(den) > eps
    signed = 100.0 * (loss_input - loss_output) / jnp.where(valid, den, 1.0)
    fallback = jnp.where(jnp.abs(loss_output - loss_target) <= eps, 100.0, 0.0)
    return ImprovementScore(
        score=jnp.where(valid, jnp.abs(signed), fallback),
        signed_score=jnp.where(valid, signed, fallback),
        valid=valid,
        loss_input=loss_input,
        loss_output=loss_output,
    )


def improvement_score(inp, out, target, mask, vgg_params, layers=losses.DEFAULT_STYLE_LAYERS,
                      layer_weights=None, pool="avg", eps=1e-6):
    """Paper's improvement score of output patches over input patches, per patch.

    Args:
      inp: (N, H, W, 3) coarse input patches N, RGB form of normal maps in [0, 1].
      out: (N, H, W, 3) enhanced output patches N*.
      target: (N, H, W, 3) ground-truth patches N_hat.
      mask: (N or 1, H, W, 1) UV mask in [0, 1].
      vgg_params: params from ``vgg.load_vgg19``.
      layers, layer_weights, pool: style-loss configuration (static under jit).
      eps: threshold on |L(N)| below which the patch is flagged invalid (see module docstring).

    Returns:
      ImprovementScore with (N,) fields.

    Example:
      >>> s = improvement_score(inp, out, gt, mask, load_vgg19())  # doctest: +SKIP
      >>> float(s.score[s.valid].mean())                          # doctest: +SKIP
    """
    n = inp.shape[0]
    if out.shape != inp.shape or target.shape != inp.shape:
        raise ValueError(f"inp {inp.shape}, out {out.shape}, target {target.shape} must match")
    layers = (layers,) if isinstance(layers, str) else tuple(layers)
    # One VGG pass over all three sets.
    feats = vgg.features(vgg_params, jnp.concatenate([inp, out, target]), layers=layers,
                         pool=pool)
    f_inp = {k: v[:n] for k, v in feats.items()}
    f_out = {k: v[n:2 * n] for k, v in feats.items()}
    f_tgt = {k: v[2 * n:] for k, v in feats.items()}
    loss_in = losses.style_loss(f_inp, f_tgt, mask, layers, layer_weights)
    loss_out = losses.style_loss(f_out, f_tgt, mask, layers, layer_weights)
    return improvement_score_from_losses(loss_in, loss_out, 0.0, eps)


# --------------------------------------------------------------------------------------------
# Sets of patches without correspondence (paper Table 2)
# --------------------------------------------------------------------------------------------


def _sq_norms(x) -> np.ndarray:
    """(N, D) -> (N,) float64 squared row norms."""
    x = np.asarray(x)
    return np.einsum("ij,ij->i", x, x, dtype=np.float64)


def sq_dists(x, y=None) -> np.ndarray:
    """Pairwise squared Euclidean distances of (n, d) and (m, d) points: (n, m) float64, as
    |x|^2 + |y|^2 - 2 x.y in float64, clipped at 0 (y None: x with itself, zero diagonal)."""
    x64 = np.asarray(x, np.float64)
    y64 = x64 if y is None else np.asarray(y, np.float64)
    d2 = _sq_norms(x64)[:, None] + _sq_norms(y64)[None, :] - 2.0 * (x64 @ y64.T)
    d2 = np.maximum(d2, 0.0)
    if y is None:
        np.fill_diagonal(d2, 0.0)
    return d2


def chamfer_from_sq_dists(d2) -> float:
    """Symmetric Chamfer distance from the (n, m) squared distances between two point sets:
    (mean_i min_j d_ij + mean_j min_i d_ij) / 2 with d = sqrt(d2); NaN if a set is empty."""
    d2 = np.asarray(d2, np.float64)
    if d2.ndim != 2:
        raise ValueError(f"expected an (n, m) matrix, got shape {d2.shape}")
    if 0 in d2.shape:
        return float("nan")
    d = np.sqrt(np.maximum(d2, 0.0))
    return 0.5 * float(d.min(axis=1).mean() + d.min(axis=0).mean())


def chamfer_distance(x, y) -> float:
    """Symmetric Chamfer distance of (n, d) and (m, d) point sets: the mean distance from a point
    to the nearest point of the other set, averaged over both directions (not squared).

    >>> chamfer_distance([[0.0, 0.0]], [[3.0, 4.0], [0.0, 1.0]])  # (1 + (5 + 1) / 2) / 2
    2.0
    """
    x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
    if x.ndim != 2 or y.ndim != 2 or x.shape[1] != y.shape[1]:
        raise ValueError(f"expected (n, d) and (m, d) points, got {x.shape} and {y.shape}")
    if not len(x) or not len(y):
        return float("nan")
    if len(x) * len(y) * x.shape[1] <= 2**25:
        # Exact differences (not the |x|^2 + |y|^2 - 2 x.y expansion): no cancellation.
        return chamfer_from_sq_dists(((x[:, None, :] - y[None, :, :]) ** 2).sum(-1))
    return chamfer_from_sq_dists(sq_dists(x, y))


def decrease_ratio(c1: float, c2: float, signed: bool = False) -> float:
    """The paper's DR = 100 |C1 - C2| / C1, or signed 100 (C1 - C2) / C1 (> 0 when C2 < C1);
    NaN unless C1 is positive and finite."""
    c1, c2 = float(c1), float(c2)
    if not (np.isfinite(c1) and c1 > 0.0):
        return float("nan")
    dr = 100.0 * (c1 - c2) / c1
    return dr if signed else abs(dr)


def spectral_embedding(x, dim: int = 2) -> np.ndarray:
    """(n, d) points -> (n, dim) Laplacian-eigenmap coordinates (float64): Gaussian affinity
    with the median squared distance as bandwidth, symmetric normalized Laplacian, the `dim`
    eigenvectors after the trivial one, divided by sqrt(degree)."""
    x = np.asarray(x, np.float64)
    d2 = sq_dists(x)
    sigma2 = np.median(d2[np.triu_indices(len(x), 1)])
    w = np.exp(-d2 / max(sigma2, 1e-30))
    deg = w.sum(1)
    lap_sym = w / np.sqrt(deg[:, None] * deg[None, :])
    _, vecs = np.linalg.eigh(lap_sym)
    # The largest eigenvalue of D^-1/2 W D^-1/2 is the trivial one; take the next `dim`.
    return vecs[:, -1 - dim:-1][:, ::-1] / np.sqrt(deg)[:, None]


# --------------------------------------------------------------------------------------------
# Temporal coherence
# --------------------------------------------------------------------------------------------


def normal_angles(a, b) -> np.ndarray:
    """Angles in degrees between normals a and b (..., 3) (any length; zero vectors give 0),
    as atan2(|a x b|, a . b) in float64: accurate for the small angles between neighbouring
    texels or frames, where arccos of a rounded dot product is not."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    return np.degrees(np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1), np.sum(a * b, -1)))


def mean_angular_change(a, b, mask) -> float:
    """Mean angle in degrees between two normal maps over the mask texels.

    a, b: (H, W, 3) normals (not necessarily unit; zero vectors count as 0 degrees);
    mask: (H, W, 1) or (H, W), > 0 on the texels to average. 0.0 for an empty mask.
    """
    m = np.asarray(mask).reshape(np.asarray(a).shape[:2]) > 0
    if not m.any():
        return 0.0
    return float(normal_angles(np.asarray(a)[m], np.asarray(b)[m]).mean())


def flicker_series(maps, mask) -> np.ndarray:
    """(T, H, W, 3) normal maps -> (T - 1,) float64 mean angular change (degrees) per pair."""
    return np.array([mean_angular_change(maps[t], maps[t + 1], mask)
                     for t in range(len(maps) - 1)])
