"""Masked Gram-matrix style loss and masked content loss on VGG19 features (paper Sec. 4.1).

Contract:
  Every loss takes feature dicts from :func:`wrinkle_jax.nn.vgg.features` (``layer name ->
  (N, h, w, C)``) and the full-resolution UV mask ``(N, H, W, 1)`` in [0, 1] (1 = garment,
  0 = background), and returns **per-sample** ``(N,)`` float32 values; reduction is left to the
  caller (optax style). :func:`enhancer_loss` is the exception: it is the training objective and
  returns the batch mean plus the per-sample parts.

Mask per layer: the mask is average-pooled 2x2 at each VGG pooling stage
(:func:`mask_pyramid`), so ``relu1_*`` see the full-resolution mask, ``relu2_*`` the mask at
/2, and so on. Pooled masks are fractional along the garment boundary.

Normalization (what the numbers mean):
  * ``gram(F, B) = (B o F)^T (B o F)``, a (C, C) sum over pixels (paper's G_l^M), i.e.
    ``sum_p B(p)^2 f_p f_p^T``; ``normalize=True`` divides by ``R = sum_p B(p)``.
  * ``R_l = sum_p B_l(p)``, the valid-pixel count of the downsampled mask (fractional pixels
    count fractionally; for a binary mask at full resolution it is the exact count).
  * style, per layer: ``||G_l(out) - G_l(target)||_F^2 / (4 R_l^2)`` exactly as in the paper,
    computed as ``||G_l(out)/R_l - G_l(target)/R_l||_F^2 / 4``. This is independent of patch
    size and mask area; it is NOT divided by the channel count: a layer's term is a sum over
    its C_l^2 Gram entries. ``normalize_channels=True`` also divides by C_l^2, i.e. Gatys et
    al.'s ``1 / (4 N_l^2 M_l^2)`` with M_l -> R_l, so that every layer's term is a *mean*
    squared Gram-entry difference and equal layer weights mean equal per-entry emphasis.
    With the Gatys-normalised weights every filter's mean activation is ~1, so Gram entries
    are O(1) at every depth either way.
  * content: masked mean squared error over valid pixels and channels,
    ``sum_p B(p) ||f_out(p) - f_in(p)||^2 / (C R)``. The paper writes an unnormalized
    ``sum [F* - F]^2 / 2``; the mean makes ``w_c`` independent of patch and mask size.

Every normalization is guarded (``numerics.safe_div``): an empty mask gives a loss of exactly 0
with finite (zero) gradients.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from wrinkle_jax import detail
from wrinkle_jax.nn import vgg
from wrinkle_jax.numerics import safe_div

__all__ = [
    "DEFAULT_CONTENT_LAYER",
    "DEFAULT_STYLE_LAYERS",
    "band_loss",
    "content_loss",
    "enhancer_loss",
    "gram",
    "mask_pyramid",
    "style_loss",
    "valid_count",
]

DEFAULT_STYLE_LAYERS = vgg.DEFAULT_LAYERS
DEFAULT_CONTENT_LAYER = "relu2_1"


def mask_pyramid(mask, num_levels):
    """The UV mask at each VGG resolution.

    Args:
      mask: (N, H, W, 1) float in [0, 1].
      num_levels: how many levels (1..5); level l matches layers with ``layer_level == l``.

    Returns:
      list of `num_levels` float32 arrays, level l of shape (N, H // 2**l, W // 2**l, 1); level 0
      is `mask` itself and each next level is the 2x2 average pool of the previous one.
    """
    if mask.ndim != 4 or mask.shape[-1] != 1:
        raise ValueError(f"mask must be (N, H, W, 1), got shape {mask.shape}")
    levels = [mask.astype(jnp.float32)]
    for _ in range(num_levels - 1):
        levels.append(vgg.pool2x2(levels[-1], "avg"))
    return levels


def valid_count(mask):
    """R = sum of mask values per sample. mask (N, h, w, 1) -> (N,) float32."""
    return jnp.sum(mask, axis=(1, 2, 3))


def _mask_for(features, mask):
    """Broadcast a (1 or N, h, w, 1) mask to a (N, h, w, C) feature map's batch, checking sizes."""
    n, h, w, _ = features.shape
    if mask.shape[1:] != (h, w, 1) or mask.shape[0] not in (1, n):
        raise ValueError(
            f"mask of shape {mask.shape} does not match features of shape {features.shape}"
        )
    return jnp.broadcast_to(mask, (n, h, w, 1))


def gram(features, mask, normalize=False):
    """Masked Gram matrix ``(B o F)^T (B o F)``.

    Args:
      features: (N, h, w, C) float.
      mask: (N or 1, h, w, 1) float in [0, 1] at the features' resolution.
      normalize: divide by the valid-pixel count R = sum(mask) (0 where R = 0).

    Returns:
      (N, C, C) float32, symmetric positive semi-definite.
    """
    mask = _mask_for(features, mask)
    masked = features.astype(jnp.float32) * mask
    g = jnp.einsum("nhwc,nhwd->ncd", masked, masked)
    if normalize:
        g = safe_div(g, valid_count(mask)[:, None, None])
    return g


def _weights(layers, layer_weights):
    if layer_weights is None:
        return [1.0] * len(layers)
    if isinstance(layer_weights, dict):
        return [layer_weights[name] for name in layers]
    if len(layer_weights) != len(layers):
        raise ValueError(f"{len(layer_weights)} layer weights for {len(layers)} layers")
    return list(layer_weights)


def style_loss(out_feats, target_feats, mask, layers=DEFAULT_STYLE_LAYERS, layer_weights=None,
               normalize_channels=False):
    """Masked Gram style loss, paper Sec. 4.1: ``sum_l w_l ||G_l(out) - G_l(tgt)||^2 / (4 R_l^2)``.

    Args:
      out_feats, target_feats: dicts layer -> (N, h_l, w_l, C_l) features (``vgg.features``).
      mask: (N or 1, H, W, 1) full-resolution mask in [0, 1].
      layers: layer names to use (each must be in both dicts).
      layer_weights: None (all 1), a sequence aligned with `layers`, or a dict name -> weight.
      normalize_channels: also divide each layer's term by C_l^2 (see module docstring).

    Returns:
      (N,) float32 per-sample loss; 0 for an empty mask.
    """
    layers = (layers,) if isinstance(layers, str) else tuple(layers)
    weights = _weights(layers, layer_weights)
    masks = mask_pyramid(mask, max(vgg.layer_level(name) for name in layers) + 1)
    total = 0.0
    for name, weight in zip(layers, weights, strict=True):
        m = masks[vgg.layer_level(name)]
        out, tgt = out_feats[name], target_feats[name]
        if out.shape[1:] != tgt.shape[1:]:
            raise ValueError(f"{name}: output {out.shape} and target {tgt.shape} differ")
        # Normalize before subtracting: ||dG||^2 / (4 R^2) = ||dG / R||^2 / 4, better in float32.
        diff = gram(out, m, normalize=True) - gram(tgt, m, normalize=True)
        term = jnp.sum(diff * diff, axis=(1, 2)) / 4.0
        if normalize_channels:
            term = term / out.shape[-1] ** 2
        total = total + weight * term
    return total


def content_loss(out_feats, inp_feats, mask, layer=DEFAULT_CONTENT_LAYER):
    """Masked mean squared feature error at one layer.

    Args:
      out_feats, inp_feats: dicts layer -> (N, h, w, C) features.
      mask: (N or 1, H, W, 1) full-resolution mask in [0, 1].
      layer: the content layer name.

    Returns:
      (N,) float32: ``sum_p B(p) ||f_out(p) - f_in(p)||^2 / (C R)``; 0 for an empty mask.
    """
    m = mask_pyramid(mask, vgg.layer_level(layer) + 1)[-1]
    out, inp = out_feats[layer], inp_feats[layer]
    m = _mask_for(out, m)
    sq = jnp.sum(jnp.square(out.astype(jnp.float32) - inp.astype(jnp.float32)), axis=-1,
                 keepdims=True)
    return safe_div(jnp.sum(m * sq, axis=(1, 2, 3)), valid_count(m) * out.shape[-1])


def enhancer_loss(vgg_params, out_images, inp_images, target_images, mask,
                  style_layers=DEFAULT_STYLE_LAYERS, content_layer=DEFAULT_CONTENT_LAYER,
                  w_c=1.0, w_s=1e4, layer_weights=None, pool="avg", normalize_channels=False,
                  conv_impl="xla", relative_floor=None, relative_log=False,
                  out_features=None):
    """Training objective of the enhancer: ``w_c content(out, inp) + w_s style(out, target)``.

    With `relative_floor` set, the style term of each patch is divided by the input's own style
    loss: ``style(out, tgt) / (style(inp, tgt) + relative_floor)`` -- the quantity the paper's
    improvement score measures per patch. The absolute form lets a patch that is already right
    (tiny input loss) take on detail it does not need, which costs little in the batch mean
    but ruins that patch's score; the relative form weighs every patch's improvement equally.
    With `relative_log` as well, the style term is the log of that ratio,
    ``log(style(out, tgt) + floor) - log(style(inp, tgt) + floor)``: the evaluation reads the
    per-patch MEDIAN of ``1 - style(out)/style(inp)``, and a batch mean of plain ratios is led
    by the few patches whose output got much worse (the ratio is unbounded above, bounded
    below by 0), which makes the network timid everywhere; on the log scale halving a patch's
    loss and doubling another's cancel, so the mean follows the typical patch.

    VGG runs once per image set and only as deep as needed: the output to the deepest of the
    style and content layers, the input to the content layer, the target to the deepest style
    layer. Input and target are treated as constants (``stop_gradient``).

    Args:
      vgg_params: params from ``vgg.load_vgg19``.
      out_images: (N, H, W, 3) enhancer output, RGB form of normal maps in [0, 1].
      inp_images: (N, H, W, 3) coarse input patches.
      target_images: (N, H, W, 3) detailed (material-specific) target patches.
      mask: (N or 1, H, W, 1) UV mask in [0, 1].
      style_layers, content_layer, layer_weights, pool, normalize_channels, conv_impl: see
        :func:`style_loss`, :func:`content_loss`, ``vgg.features`` (all static under jit).
      w_c, w_s: content and style weights (paper: 1 and 1e4).
      relative_floor: None (the paper's absolute style loss) or a float > 0 (see above; the
        input's features then run to the deepest style layer too).
      relative_log: with `relative_floor`, the log-ratio form (see above; zero when the output
        equals the input).
      out_features: the output's VGG features if the caller already has them (layer -> (N,
        h, w, C), at least the style and content layers, same `pool` and `conv_impl`).

    Returns:
      (total, parts): total is the batch mean of the per-sample objective (scalar float32);
      parts = {"content": (N,), "style": (N,), "total": (N,)}.
    """
    style_layers = (style_layers,) if isinstance(style_layers, str) else tuple(style_layers)
    out_layers = tuple(sorted(set(style_layers) | {content_layer}))
    out_f = (vgg.features(vgg_params, out_images, layers=out_layers, pool=pool,
                          conv_impl=conv_impl) if out_features is None else out_features)
    inp_layers = out_layers if relative_floor is not None else (content_layer,)
    inp_f = vgg.features(vgg_params, jax.lax.stop_gradient(inp_images), layers=inp_layers,
                         pool=pool, conv_impl=conv_impl)
    tgt_f = vgg.features(vgg_params, jax.lax.stop_gradient(target_images), layers=style_layers,
                         pool=pool, conv_impl=conv_impl)
    content = content_loss(out_f, inp_f, mask, content_layer)
    style = style_loss(out_f, tgt_f, mask, style_layers, layer_weights, normalize_channels)
    if relative_floor is not None:
        style_in = style_loss(inp_f, tgt_f, mask, style_layers, layer_weights,
                              normalize_channels)
        style_in = jax.lax.stop_gradient(style_in) + relative_floor
        style = (jnp.log(style + relative_floor) - jnp.log(style_in) if relative_log
                 else style / style_in)
    per_sample = w_c * content + w_s * style
    return jnp.mean(per_sample), {"content": content, "style": style, "total": per_sample}


def band_loss(out_detail, target_detail, mask, bands=detail.BAND_SIGMAS, eps: float = 1e-6):
    """Per-patch band-energy mismatch of two detail maps: the sum over bands of
    ``(log rms_out - log rms_target)^2`` (`detail.band_rms`; e.g. the < 16 mm and 16-64 mm
    bands).

    The Gram style loss weighs the texel-scale band weakly, so a network trained on it alone
    puts 1.5-2.5x the fine simulation's energy below 16 mm (creases and a 2-texel checkerboard
    the fine cloth does not have). Band energy is a statistic of the texture, not of its
    placement, so this needs no pixel alignment of output and target; on the log scale a
    doubling and a halving cost the same.

    Args:
      out_detail, target_detail: (N, H, W, 3) RGB-form detail maps (`detail.to_detail_rgb`).
      mask: (N, H, W, 1) in {0, 1}.
      eps: floor of the mean squares (a flat target band then pulls the output's towards
        sqrt(eps), not to -inf; default 1e-6, i.e. RMS 1e-3, about 1/10 of the fine
        simulation's < 16 mm level).
    Returns:
      (N,) float32; 0 where the mask has no interior texels.
    """
    total = 0.0
    for rms_out, rms_tgt in detail.band_rms_pair(out_detail, target_detail, mask, bands,
                                                 eps).values():
        ok = rms_out > 0
        diff = jnp.log(jnp.where(ok, rms_out, 1.0)) - jnp.log(jnp.where(ok, rms_tgt, 1.0))
        total = total + jnp.square(diff)
    return total
