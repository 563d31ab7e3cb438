"""Differentiable masked unsharp masking of normal maps (JAX).

The same operation as the OpenCV baseline `wrinkle_jax.evaluation.unsharp_mask` (which the
tests compare against), written in JAX so that it can sit inside a network: the enhancer's
residual base (`nn.unet.UNetConfig(residual_base="unsharp")`) starts from the best non-learned
sharpening and learns a correction on top of it, with a learnable per-material gain.

    n' = normalize(n + amount * (n - blur_sigma(n)))

where `blur_sigma` is a masked Gaussian blur, so background texels never bleed into the
garment, and texels outside the mask are returned as 0 (the RGB form's background). Two orders:

- order 0, normalized convolution: blur(mask * n) / blur(mask), a Gaussian-weighted local mean.
  Near the mask's border the window is one-sided, so on a tilted but otherwise flat field the
  local mean lags the centre texel and `n - blur` is a spurious ramp along every border. Patches
  whose target is nearly flat are then made many times worse (held-out dress patches with a
  style-loss ratio of 4-8 under sigma 8; experiments/results/recipe/).
- order 1 (default), first-order normalized convolution: a Gaussian- and mask-weighted local
  linear fit evaluated at the centre texel. Linear fields are fixed points up to the border,
  so the unsharp mask only amplifies curvature (folds), never the tilt of a flat panel.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from wrinkle_jax.numerics import dot3

__all__ = ["blur_weights", "gaussian_kernel", "mask_from_rgb", "masked_blur", "unsharp_rgb"]


def gaussian_kernel(sigma: float) -> np.ndarray:
    """Normalized 1D Gaussian taps, length 2 ceil(3 sigma) + 1 (OpenCV's for this size)."""
    k = int(2 * np.ceil(3 * sigma) + 1)
    x = np.arange(k, dtype=np.float64) - (k - 1) / 2
    g = np.exp(-0.5 * (x / sigma) ** 2)
    return (g / g.sum()).astype(np.float32)


def mask_from_rgb(x, threshold: float = 1e-3):
    """(..., 3) RGB-form normals -> (..., 1) float mask: 1 where the texel holds a normal.

    A unit normal's RGB form has a channel >= (1 - 1/sqrt(3)) / 2 ~ 0.21, and the background
    is 0, so a small threshold separates them exactly.
    """
    return (jnp.max(x, axis=-1, keepdims=True) > threshold).astype(jnp.float32)


def _band_matrix(n: int, taps: np.ndarray) -> np.ndarray:
    """(n, n) matrix B with (B @ v)[i] = sum_k taps[k] v[i + k - r], zero outside [0, n)."""
    r = (len(taps) - 1) // 2
    i = np.arange(n)
    d = i[None, :] - i[:, None] + r  # tap index of column j for row i
    ok = (d >= 0) & (d < len(taps))
    return np.where(ok, taps[np.clip(d, 0, len(taps) - 1)], 0.0).astype(np.float32)


def _bands(n: int, *taps: np.ndarray):
    """The (n, n) band matrices of several tap vectors stacked along rows: (K n, n)."""
    return jnp.asarray(np.concatenate([_band_matrix(n, t) for t in taps], axis=0))


def _rows(planes, *taps):
    """Zero-padded correlation along the rows of (H, P, N, W) planes with each of K tap
    vectors: (K, H, P, N, W). One dense banded matmul (K H x H) @ (H, P N W): XLA:CPU runs a
    depthwise 49-tap convolution ~10x slower than the equivalent matmuls at patch sizes."""
    h = planes.shape[0]
    out = jnp.einsum("ij,j...->i...", _bands(h, *taps), planes)
    return out.reshape(len(taps), *planes.shape)


def _cols(planes, *taps):
    """The same along the last (column) axis of (..., W) planes: (..., K, W), one matmul
    (... , W) @ (W, K W)."""
    w = planes.shape[-1]
    out = jnp.einsum("...w,vw->...v", planes, _bands(w, *taps))
    return out.reshape(*planes.shape[:-1], len(taps), w)


# Ridge on the local slope, relative to the window's offset variance (~sigma^2 inside the
# garment): where the masked window is a thin strip the slope across it is undetermined and the
# fit falls back to the local mean; inside the garment it shrinks slopes by ~0.1 %.
_SLOPE_RIDGE = 1e-3


@functools.partial(jax.jit, static_argnames=("sigma", "order"))
def blur_weights(mask, sigma: float, order: int = 1):
    """The mask's part of `masked_blur`: per-texel weights of the values' Gaussian moments.

    The order-1 blur is linear in the values: with m0, my, mx the Gaussian moments of the
    masked values (sums of g(dy) g(dx) mask v, times 1, dy, dx) it is a0 m0 + ay my + ax mx,
    where a0, ay, ax depend on the mask alone (its weight, centroid and offset covariance).
    Several fields blurred on one mask, or one patch layout blurred every frame (the pipeline's
    patches sit at fixed texels, so their masks never change), share these weights; computing
    them once saves the mask's 9 of the 5 C + 9 passes (order 1, C value channels).

    Args:
      mask: (N, H, W, 1) weights in [0, 1]; sigma: radius in texels; order: 0 or 1.
    Returns:
      (K, H, N, W) planes (the mask's float dtype) in `masked_blur`'s layout: K = 3 (a0,
      ay, ax) for order 1, K = 1 (a0 = 1 / the mask's blur) for order 0.
    """
    if order not in (0, 1):
        raise ValueError(f"masked_blur order must be 0 or 1, got {order!r}")
    g = gaussian_kernel(sigma)
    mk = jnp.transpose(jnp.asarray(mask)[..., 0], (1, 0, 2))  # (H, N, W)
    if order == 0:
        m0 = _cols(_rows(mk, g)[0], g)[..., 0, :]
        return (1.0 / jnp.maximum(m0, 1e-8))[None]
    d = np.arange(len(g), dtype=np.float32) - (len(g) - 1) // 2  # offset q - p (texels)
    g1, g2 = g * d, g * d * d
    rows = _rows(mk, g, g1, g2)                      # (3, H, N, W): taps g, g1, g2 along H
    both = _cols(rows[0], g, g1, g2)                 # (H, N, 3, W): then g, g1, g2 along W
    m0, mx, mxx = both[..., 0, :], both[..., 1, :], both[..., 2, :]
    dy = _cols(rows[1], g, g1)
    my, mxy = dy[..., 0, :], dy[..., 1, :]
    myy = _cols(rows[2], g)[..., 0, :]
    # Weighted means and (co)variances of the window's offsets; the least-squares plane through
    # the weighted mean, evaluated at offset 0, is v - p sy - q sx with v, sy, sx the values'
    # weighted mean and covariances with the offsets, which regroups into the three weights.
    w = jnp.maximum(m0, 1e-8)
    uy, ux = my / w, mx / w
    cyy = myy / w - uy * uy + _SLOPE_RIDGE * sigma**2
    cxx = mxx / w - ux * ux + _SLOPE_RIDGE * sigma**2
    cxy = mxy / w - uy * ux
    det = cyy * cxx - cxy * cxy
    p = (uy * cxx - ux * cxy) / det
    q = (ux * cyy - uy * cxy) / det
    s = (mk > 0) / w
    return jnp.stack([s * (1.0 + p * uy + q * ux), -s * p, -s * q])


@functools.partial(jax.jit, static_argnames=("sigma", "order"))
def masked_blur(n, mask, sigma: float, order: int = 1, weights=None):
    """Masked Gaussian blur: normalized convolution of order 0 (local mean) or 1 (local plane).

    Args:
      n: (N, H, W, C) values; mask: (N, H, W, 1) weights in [0, 1]; sigma: radius in texels;
      order: 0 for blur(mask * n) / blur(mask); 1 for the value at the centre of the weighted
        least-squares plane through the window (weights Gaussian * mask), which leaves linear
        fields unchanged up to the mask's border.
      weights: None, or ``blur_weights(mask, sigma, order)`` computed once for this mask
        (then `mask` only masks the values).
    Returns:
      (N, H, W, C) blurred values (order 0: 0 where no masked texel is in reach; order 1: 0
      outside the mask).

    Several fields on the same mask and sigma (e.g. a network's input and its residual) should
    be blurred in one call, stacked along C, or share `weights`.

    The Gaussian moments are separable sums of dense banded matmuls on the planes laid out as
    (H, C, N, W), where both the row and the column pass are plain matrix products (no
    transposes between them), and each row pass is shared by the column passes that need it:
    order 1 costs 2 C row and 3 C column passes on the values (one pass: one plane's (H, H)
    matmul), plus the mask's 3 + 6 in `blur_weights` when `weights` is None.
    """
    if order not in (0, 1):
        raise ValueError(f"masked_blur order must be 0 or 1, got {order!r}")
    if weights is None:
        weights = blur_weights(mask, sigma, order)
    elif weights.shape[0] != (3 if order == 1 else 1):
        raise ValueError(f"weights of {weights.shape[0]} planes do not fit order {order!r} "
                         "(blur_weights gives 3 for order 1, 1 for order 0)")
    g = gaussian_kernel(sigma)
    planes = jnp.transpose(n * mask, (1, 3, 0, 2))   # (H, C, N, W)
    a = weights[:, :, None]                          # (K, H, 1, N, W), over the C planes
    if order == 0:
        out = _cols(_rows(planes, g)[0], g)[..., 0, :] * a[0]
        return jnp.transpose(out, (2, 0, 3, 1))
    d = np.arange(len(g), dtype=np.float32) - (len(g) - 1) // 2
    rows = _rows(planes, g, g * d)                   # (2, H, C, N, W)
    both = _cols(rows[0], g, g * d)                  # (H, C, N, 2, W)
    my = _cols(rows[1], g)[..., 0, :]
    out = a[0] * both[..., 0, :] + a[1] * my + a[2] * both[..., 1, :]
    return jnp.transpose(out, (2, 0, 3, 1))


@functools.partial(jax.jit, static_argnames=("sigma", "order"))
def masked_blur_reference(n, mask, sigma: float, order: int = 1):
    """`masked_blur` as first written, the direct formula: every moment its own separable
    filter, two (H x H) banded matmuls on NHWC. Same result to float32 rounding, slower;
    kept as the reference that tests and `benchmarks/bench_blur.py` compare against."""
    g = gaussian_kernel(sigma)

    def sep(x, th, tw):
        bh = jnp.asarray(_band_matrix(x.shape[1], th))
        bw = jnp.asarray(_band_matrix(x.shape[2], tw))
        return jnp.einsum("kw,nhwc->nhkc", bw, jnp.einsum("ij,njwc->niwc", bh, x))

    both = jnp.concatenate([n * mask, mask], axis=-1)
    if order == 0:
        m = sep(both, g, g)
        return m[..., :-1] / jnp.maximum(m[..., -1:], 1e-8)
    d = np.arange(len(g), dtype=np.float32) - (len(g) - 1) // 2
    g1, g2 = g * d, g * d * d
    m0, my, mx = (sep(both, a, b) for a, b in ((g, g), (g1, g), (g, g1)))
    myy, mxx, mxy = sep(mask, g2, g), sep(mask, g, g2), sep(mask, g1, g1)
    w = jnp.maximum(m0[..., -1:], 1e-8)
    uy, ux, v = my[..., -1:] / w, mx[..., -1:] / w, m0[..., :-1] / w
    ridge = _SLOPE_RIDGE * sigma**2
    cyy, cxx = myy / w - uy * uy + ridge, mxx / w - ux * ux + ridge
    cxy = mxy / w - uy * ux
    sy, sx = my[..., :-1] / w - uy * v, mx[..., :-1] / w - ux * v
    det = cyy * cxx - cxy * cxy
    by, bx = (cxx * sy - cxy * sx) / det, (cyy * sx - cxy * sy) / det
    return (v - by * uy - bx * ux) * (mask > 0)


@functools.partial(jax.jit, static_argnames=("sigma", "order"))
def unsharp_rgb(x, sigma: float, amount, mask=None, order: int = 1, blurred=None):
    """Unsharp-mask RGB-form normal-map patches.

    Args:
      x: (N, H, W, 3) RGB form ((n + 1) / 2) of normal maps, 0 outside the garment.
      sigma: blur radius in texels.
      amount: scalar or (N,) per-patch sharpening gain (0 = identity inside the mask).
      mask: (N, H, W, 1) garment mask; None to infer it from `x` (`mask_from_rgb`).
      order: `masked_blur` order (1: flat tilted panels stay unchanged; 0: the OpenCV
        normalized-convolution form of `evaluation.unsharp_mask(order=0)`).
      blurred: None, or the (N, H, W, 3) ``masked_blur(x * 2 - 1, mask, sigma, order)`` when
        the caller has it already (blurred together with other fields on the same mask).
    Returns:
      (N, H, W, 3) float32 RGB form of unit normals inside the mask, 0 outside.
    """
    x = jnp.asarray(x, jnp.float32)
    mask = mask_from_rgb(x) if mask is None else jnp.asarray(mask, jnp.float32)
    n = x * 2.0 - 1.0
    a = jnp.asarray(amount, jnp.float32)
    a = a.reshape((-1, 1, 1, 1)) if a.ndim == 1 else a
    low = masked_blur(n, mask, sigma, order) if blurred is None else blurred
    s = n + a * (n - low)
    # Guarded normalization: s is never ~0 inside the mask for moderate gains, and the
    # guard keeps the gradient finite on the background.
    # dot3: the 3-channel sum as multiply-adds (the reduction ran as a slow library fusion:
    # 5 % of the shipped network's thread time, session 44).
    norm = jnp.sqrt(dot3(s, s)[..., None] + 1e-12)
    return ((s / norm + 1.0) * 0.5) * mask
