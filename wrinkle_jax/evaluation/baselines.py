"""The non-learned baselines: identity, unsharp masking, down/up-sampling.

Patches in the RGB form of normal maps ((n + 1) / 2, in [0, 1]), (N, H, W, 3) float32, with a
(N, H, W, 1) float32 {0, 1} mask. NumPy/OpenCV, masked (background never bleeds into the
garment); outputs are unit normals inside the mask and zero outside.
"""

from __future__ import annotations

import cv2
import numpy as np

__all__ = ["identity", "resample", "unsharp_mask"]


def _normals(rgb):
    return np.asarray(rgb, np.float64) * 2.0 - 1.0


def _to_rgb_masked(n, mask):
    norm = np.linalg.norm(n, axis=-1, keepdims=True)
    unit = np.where(norm > 1e-12, n / np.maximum(norm, 1e-12), 0.0)
    return (((unit + 1.0) * 0.5) * mask).astype(np.float32)


def identity(inp, mask):
    """The input unchanged (improvement score 0 by definition)."""
    return np.asarray(inp, np.float32) * np.asarray(mask, np.float32)


def _masked_blur(n, m, sigma, order: int = 1):
    """Masked Gaussian blur of (H, W, 3) normals with (H, W) weights (OpenCV, float64).

    order 0: normalized convolution (local mean); order 1: the centre value of the weighted
    local least-squares plane (`wrinkle_jax.sharpen.masked_blur` documents why).
    """
    k = int(2 * np.ceil(3 * sigma) + 1)
    if order == 0:
        num = cv2.GaussianBlur(n * m[..., None], (k, k), sigma, borderType=cv2.BORDER_CONSTANT)
        den = cv2.GaussianBlur(m, (k, k), sigma, borderType=cv2.BORDER_CONSTANT)
        return num / np.maximum(den, 1e-8)[..., None]
    g = cv2.getGaussianKernel(k, sigma).ravel()
    d = np.arange(k) - (k - 1) // 2
    g1, g2 = g * d, g * d * d

    def filt(img, ky, kx):  # correlation: sum_de ky[d] kx[e] img[i+d, j+e], zero outside
        return cv2.sepFilter2D(img, cv2.CV_64F, kx, ky, borderType=cv2.BORDER_CONSTANT)

    w = np.maximum(filt(m, g, g), 1e-8)
    nm = n * m[..., None]
    v = filt(nm, g, g) / w[..., None]
    uy, ux = filt(m, g1, g) / w, filt(m, g, g1) / w
    ridge = 1e-3 * sigma**2
    cyy = filt(m, g2, g) / w - uy * uy + ridge
    cxx = filt(m, g, g2) / w - ux * ux + ridge
    cxy = filt(m, g1, g1) / w - uy * ux
    sy = filt(nm, g1, g) / w[..., None] - uy[..., None] * v
    sx = filt(nm, g, g1) / w[..., None] - ux[..., None] * v
    det = (cyy * cxx - cxy * cxy)[..., None]
    by = (cxx[..., None] * sy - cxy[..., None] * sx) / det
    bx = (cyy[..., None] * sx - cxy[..., None] * sy) / det
    return v - by * uy[..., None] - bx * ux[..., None]


def unsharp_mask(inp, mask, sigma: float = 2.0, amount: float = 1.0, order: int = 1):
    """Unsharp masking of the normal field: n + amount (n - blur_sigma(n)), renormalized.

    Args:
      sigma: Gaussian blur radius in texels; amount: sharpening gain (0 = identity);
      order: masked blur order, 1 (local plane: tilted flat panels stay unchanged) or 0
        (normalized convolution, the classic form, which sharpens every mask border).
    """
    inp, mask = np.asarray(inp), np.asarray(mask, np.float32)
    out = np.empty(inp.shape, np.float32)
    for i in range(len(inp)):
        n, m = _normals(inp[i]), mask[i, ..., 0].astype(np.float64)
        out[i] = _to_rgb_masked(n + amount * (n - _masked_blur(n, m, sigma, order)), mask[i])
    return out


def resample(inp, mask, factor: float = 2.0, down=cv2.INTER_AREA, up=cv2.INTER_CUBIC):
    """Down-sample by `factor` and up-sample back (bicubic by default; `up=cv2.INTER_LANCZOS4`
    for Lanczos) -- the image-super-resolution baseline applied to the coarse map, masked."""
    inp, mask = np.asarray(inp), np.asarray(mask, np.float32)
    n_, h, w, _ = inp.shape
    sh, sw = max(1, round(h / factor)), max(1, round(w / factor))
    out = np.empty(inp.shape, np.float32)
    for i in range(n_):
        n, m = _normals(inp[i]), mask[i, ..., 0].astype(np.float64)
        small_n = cv2.resize(n * m[..., None], (sw, sh), interpolation=down)
        small_m = cv2.resize(m, (sw, sh), interpolation=down)
        small = small_n / np.maximum(small_m, 1e-8)[..., None] * (small_m > 1e-8)[..., None]
        big_n = cv2.resize(small, (w, h), interpolation=up)
        big_m = cv2.resize((small_m > 1e-8).astype(np.float64), (w, h), interpolation=up)
        out[i] = _to_rgb_masked(big_n / np.maximum(big_m, 1e-8)[..., None], mask[i])
    return out
