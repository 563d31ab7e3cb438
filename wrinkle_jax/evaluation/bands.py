"""Band energies of detail maps and the 2-texel checkerboard (transposed-conv) artefact.

NumPy/OpenCV, float64 inside; patches (N, S, S, 3) RGB form with a (N, S, S, 1) mask.
"""

from __future__ import annotations

import cv2
import numpy as np

from wrinkle_jax.detail import BAND_SIGMAS

__all__ = ["BAND_SIGMAS", "band_pass", "band_rms", "checker_rms"]


def _masked_gauss(x, m, sigma):
    if sigma <= 0:
        return x
    k = int(2 * np.ceil(3 * sigma) + 1)
    num = cv2.GaussianBlur(x * m[..., None], (k, k), sigma, borderType=cv2.BORDER_CONSTANT)
    den = cv2.GaussianBlur(m, (k, k), sigma, borderType=cv2.BORDER_CONSTANT)
    return num / np.maximum(den, 1e-8)[..., None]


def band_pass(x, m, inner: float, outer: float) -> np.ndarray:
    """G_inner(x) - G_outer(x) of one map (H, W, C) under its mask (H, W): masked normalized
    Gaussians of radii `inner` and `outer` texels (inner 0 = x itself). float64."""
    return _masked_gauss(x, m, inner) - _masked_gauss(x, m, outer)


def band_rms(detail_rgb, mask, bands=BAND_SIGMAS) -> dict[str, np.ndarray]:
    """Per-patch RMS of the tangential detail (x, y of the detail normals) in each band
    (the NumPy reference of the jittable `detail.band_rms`).

    Args:
      detail_rgb: (N, S, S, 3) RGB-form detail maps (`detail_triplet`); mask (N, S, S, 1).
      bands: name -> (inner, outer) Gaussian radii in texels; the band is
        G_inner(d) - G_outer(d) (masked normalized convolution; inner 0 = d itself).
    Returns:
      name -> (N,) float32 RMS over texels at least 6 texels inside the mask (band-passes
      are unreliable at the border).
    """
    x = np.asarray(detail_rgb, np.float64)[..., :2] * 2.0 - 1.0
    m = np.asarray(mask, np.float64)[..., 0]
    out = {k: np.zeros(len(x), np.float32) for k in bands}
    for i in range(len(x)):
        inner = cv2.erode(m[i], np.ones((13, 13), np.uint8)) > 0
        for name, (a, b) in bands.items():
            band = band_pass(x[i], m[i], a, b)
            out[name][i] = np.sqrt(np.mean(np.sum(band[inner] ** 2, -1))) if inner.any() else 0
    return out


def checker_rms(rgb, mask) -> np.ndarray:
    """(N,) RMS of the 2-texel checkerboard component (the Nyquist frequency of the texel grid,
    the transposed-conv artefact) of the normals' x, y: the 2x2 kernel [[1, -1], [-1, 1]] / 4
    over 2x2 blocks fully inside the mask."""
    x = np.asarray(rgb, np.float64)[..., :2] * 2.0 - 1.0
    m = np.asarray(mask, np.float64)[..., 0]
    c = (x[:, :-1, :-1] - x[:, 1:, :-1] - x[:, :-1, 1:] + x[:, 1:, 1:]) / 4.0
    ok = (m[:, :-1, :-1] * m[:, 1:, :-1] * m[:, :-1, 1:] * m[:, 1:, 1:]) > 0
    sq = np.sum(c * c, -1) * ok
    return np.sqrt(sq.sum((1, 2)) / np.maximum(ok.sum((1, 2)), 1)).astype(np.float32)
