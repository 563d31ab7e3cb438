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
"""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp

from wrinkle_jax.nn import losses, vgg

__all__ = ["ImprovementScore", "improvement_score", "improvement_score_from_losses"]


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
