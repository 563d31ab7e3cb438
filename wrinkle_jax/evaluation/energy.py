"""Where the fine simulation's wrinkle energy is, and what of the coarse input predicts it.

The detail-only score rewards each patch's own detail statistics, amplitude first (a fine
patch's detail pasted onto another patch of the same fabric scores far below unsharp
masking). These helpers measure how much of that amplitude a method could know:

  * `matched_gain_choice`: among outputs made at several gains, the one whose band energy
    is closest (in log) to a reference level -- with the fine target's level it is an
    oracle that isolates "the right amount of detail per patch";
  * `local_band_energy`: a map of the local mean squared band response of a detail map
    (the same band-pass as `bands.band_rms`, then a masked Gaussian average), so fine and
    coarse energies can be compared texel by texel on one UV grid;
  * `principal_stretches` / `face_values_to_texels`: the coarse mesh's in-plane stretches
    against its rest shape (the UVs are pattern coordinates in meters), on the same grid --
    compression is where a real fabric buckles into wrinkles.

NumPy/OpenCV, float64 inside. Units: texels for radii, meters for positions.
"""

from __future__ import annotations

import cv2
import numpy as np

from wrinkle_jax import detail
from wrinkle_jax.detail import BAND_SIGMAS
from wrinkle_jax.evaluation.bands import band_pass, band_rms
from wrinkle_jax.evaluation.baselines import unsharp_mask
from wrinkle_jax.mesh import Garment

__all__ = ["face_values_to_texels", "gain_sweep", "local_band_energy", "masked_smooth",
           "matched_gain_choice", "principal_stretches"]


def masked_smooth(x, mask, sigma: float) -> np.ndarray:
    """Masked (normalized) Gaussian average of a scalar map: (H, W) values, (H, W) or
    (H, W, 1) mask, radius `sigma` texels -> (H, W) float64 (0 where no mask is near)."""
    x = np.asarray(x, np.float64)
    m = np.asarray(mask, np.float64).reshape(x.shape)
    k = int(2 * np.ceil(3 * sigma) + 1)
    num = cv2.GaussianBlur(x * m, (k, k), sigma, borderType=cv2.BORDER_CONSTANT)
    den = cv2.GaussianBlur(m, (k, k), sigma, borderType=cv2.BORDER_CONSTANT)
    return np.where(den > 1e-8, num / np.maximum(den, 1e-8), 0.0)


def local_band_energy(detail_rgb, mask, band: str = "16_64mm", smooth: float = 16.0):
    """Local mean squared band response of one detail map.

    Args:
      detail_rgb: (H, W, 3) RGB-form detail map (`detail.to_detail_rgb`); mask (H, W, 1).
      band: a `BAND_SIGMAS` key; the band is G_inner(d) - G_outer(d) of the tangential
        components (x, y), masked, as in `bands.band_rms`.
      smooth: radius (texels) of the masked Gaussian average of the squared response.
    Returns:
      (H, W) float64 mean squared band amplitude (dimensionless; its square root is the
      local band RMS).
    """
    x = np.asarray(detail_rgb, np.float64)[..., :2] * 2.0 - 1.0
    m = np.asarray(mask, np.float64)[..., 0]
    resp = band_pass(x, m, *BAND_SIGMAS[band])
    return masked_smooth(np.sum(resp ** 2, -1), m, smooth)


def principal_stretches(vertices, garment: Garment) -> np.ndarray:
    """(F, 2) float64 principal stretches (s_min, s_max) of each face of a deformed mesh
    against its rest shape, the UV triangle (UVs in meters): the singular values of the
    deformation gradient F = [x1 - x0, x2 - x0] [u1 - u0, u2 - u0]^-1 (3 x 2). 1 is
    unstretched; s_min < 1 is compression. `vertices` (V, 3) meters."""
    uv = np.asarray(garment.uvs, np.float64)[np.asarray(garment.uv_faces)]
    x = np.asarray(vertices, np.float64)[np.asarray(garment.faces)]
    dm = np.stack([uv[:, 1] - uv[:, 0], uv[:, 2] - uv[:, 0]], -1)
    ds = np.stack([x[:, 1] - x[:, 0], x[:, 2] - x[:, 0]], -1)
    f = ds @ np.linalg.inv(dm)
    ev = np.linalg.eigvalsh(np.swapaxes(f, 1, 2) @ f)  # ascending
    return np.sqrt(np.maximum(ev, 0.0))


def face_values_to_texels(plan, values, fill: float = 0.0) -> np.ndarray:
    """Per-face values (F,) on a raster plan's covered texels -> (H, W) float64 (`fill`
    elsewhere); `plan` is a `normalmap.RasterPlan` of the same mesh."""
    h, w = plan.shape
    n = plan.num_covered
    out = np.full(h * w, fill, np.float64)
    out[np.asarray(plan.texel_pixel)[:n]] = np.asarray(values, np.float64)[
        np.asarray(plan.texel_tri)[:n]]
    return out.reshape(h, w)


def matched_gain_choice(band_out, level) -> np.ndarray:
    """(N,) int index of the output closest in log band energy to `level`.

    Args:
      band_out: (N, G) band RMS of N patches' outputs at G settings (e.g. unsharp gains).
      level: (N,) the band RMS to match (the fine target's: an oracle; a prediction from
        the input: a method). Zero energies are floored at 1e-9 so they compare in log.
    """
    b = np.log(np.maximum(np.asarray(band_out, np.float64), 1e-9))
    t = np.log(np.maximum(np.asarray(level, np.float64), 1e-9))
    return np.abs(b - t[:, None]).argmin(1)


def gain_sweep(inp, target, mask, sigma: float, gains, detail_sigma: float,
               band: str = "16_64mm") -> dict:
    """The order-1 unsharp mask of patches at several gains, with what matching needs.

    Args:
      inp, target: (N, S, S, 3) RGB-form patches; mask (N, S, S, 1). sigma: the unsharp
        blur radius (texels); gains: G amounts (< 0 smooths); detail_sigma: the detail
        representation's low-pass radius (`detail.on_reference_branch_rgb`, branch from
        the input).
    Returns:
      {"outputs": G arrays (N, S, S, 3), "details": (input, target, *outputs) detail maps,
       "band_out": (N, G) and "band_target": (N,) band RMS of those details in `band`}.
    """
    outs = [np.asarray(unsharp_mask(inp, mask, sigma, g, order=1), np.float32) for g in gains]
    details = tuple(np.asarray(x) for x in detail.on_reference_branch_rgb(
        inp, (target, *outs), mask, detail_sigma))
    return {"outputs": outs, "details": details,
            "band_out": np.stack([band_rms(d, mask)[band] for d in details[2:]], 1),
            "band_target": band_rms(details[1], mask)[band]}
