"""The improvement score of enhanced patches against ground truth (paper Sec. 5/6).

All functions take patches in the RGB form of normal maps ((n + 1) / 2, in [0, 1]) with a UV
mask, as stored by `wrinkle_jax.data`:

    inp, out, target: (N, H, W, 3) float32;  mask: (N, H, W, 1) float32 in {0, 1}.

:func:`improvement_score` is the paper's quantitative score for batches of patches, per patch:

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

`score_patches` is the same score on a FIXED set of VGG layers (`EVAL_LAYERS`, independent of
the layers a model was trained with, so that models trained with different losses are compared
on one yardstick), batched, plus its signed form. With `detail_sigma` set, the same score is
taken on the detail representation (`wrinkle_jax.detail`: each map's own large scale rotated
to +z, the branch chosen from the input), the project's primary, detail-only score: it ignores
where coarse and fine simulations diverge at large scale.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from wrinkle_jax import detail
from wrinkle_jax.nn import losses, vgg

__all__ = ["EVAL_LAYERS", "ImprovementScore", "detail_triplet", "improvement_score",
           "improvement_score_from_losses", "score_patches", "scores_from_losses"]

EVAL_LAYERS = vgg.DEFAULT_LAYERS  # relu1_2, relu2_1, relu3_1, relu4_1, relu5_1 (Gatys)


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


_SCORE_CACHE: dict = {}


def _score_fn(layers, pool):
    key = (layers, pool)
    if key not in _SCORE_CACHE:
        def fn(vgg_params, inp, out, target, mask):
            n = inp.shape[0]
            feats = vgg.features(vgg_params, jnp.concatenate([inp, out, target]),
                                 layers=layers, pool=pool)
            f_in, f_out, f_tgt = ({k: v[i * n:(i + 1) * n] for k, v in feats.items()}
                                  for i in range(3))
            return (losses.style_loss(f_in, f_tgt, mask, layers),
                    losses.style_loss(f_out, f_tgt, mask, layers))
        _SCORE_CACHE[key] = jax.jit(fn)
    return _SCORE_CACHE[key]


@functools.partial(jax.jit, static_argnames="sigma")
def _detail_triplet(inp, out, target, mask, sigma):
    return detail.on_reference_branch_rgb(inp, (out, target), mask, sigma)


def detail_triplet(inp, out, target, mask, sigma: float = detail.DEFAULT_SIGMA):
    """Detail maps (RGB form) of input, output and target patches, all on the INPUT's branch
    (`wrinkle_jax.detail`), each with its own large scale removed. (N, S, S, 3) float32 each."""
    got = _detail_triplet(*(jnp.asarray(np.asarray(a), jnp.float32)
                            for a in (inp, out, target, mask)), float(sigma))
    return tuple(np.asarray(g) for g in got)


def score_patches(vgg_params, inp, out, target, mask, layers=EVAL_LAYERS, pool="avg",
                  batch_size: int = 16, detail_sigma: float | None = None
                  ) -> dict[str, np.ndarray]:
    """Per-patch style losses and improvement scores (float32 XLA convolutions: exact).

    Args:
      detail_sigma: None for the paper's object-space score; a low-pass radius in texels
        (e.g. `detail.DEFAULT_SIGMA`) for the detail-only score (`detail_triplet`).
    Returns:
      dict of (N,) arrays: loss_input, loss_output, improvement (the paper's |.| form, %),
      improvement_signed (%), valid (bool: the input's loss is not ~0).
    """
    fn = _score_fn(tuple(layers), pool)
    n = len(inp)
    if detail_sigma is not None:
        inp, out, target = detail_triplet(inp, out, target, mask, detail_sigma)
    parts = []
    for s in range(0, n, batch_size):
        sl = slice(s, min(s + batch_size, n))
        idx = np.resize(np.arange(sl.start, sl.stop), batch_size)  # fixed shape: one compile
        got = fn(vgg_params, *(jnp.asarray(np.asarray(a)[idx], jnp.float32)
                               for a in (inp, out, target, mask)))
        parts.append([np.asarray(g)[:sl.stop - sl.start] for g in got])
    return scores_from_losses(np.concatenate([p[0] for p in parts]),
                              np.concatenate([p[1] for p in parts]))


def scores_from_losses(loss_input, loss_output) -> dict[str, np.ndarray]:
    """Improvement scores of a set of patches from their (N,) input and output style losses.

    eps = 1e-6 of the set's largest input loss (only an exact match of input and target makes a
    patch's score undefined). Returns dict of (N,) arrays: loss_input, loss_output, improvement
    (paper |.| form, %), improvement_signed (%), valid (bool).
    """
    loss_input = np.asarray(loss_input, np.float32)
    loss_output = np.asarray(loss_output, np.float32)
    eps = 1e-6 * max(float(loss_input.max(initial=0.0)), 1e-30)
    sc = improvement_score_from_losses(jnp.asarray(loss_input), jnp.asarray(loss_output),
                                       eps=eps)
    return {"loss_input": loss_input, "loss_output": loss_output,
            "improvement": np.asarray(sc.score), "improvement_signed": np.asarray(sc.signed_score),
            "valid": np.asarray(sc.valid)}
