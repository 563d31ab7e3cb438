"""Normal-map features of a coarse garment sequence, per time window: the ``drape`` family.

The paper classifies the material from normal-map patches (Sec. 4.2). On our coarse
simulations (PD 30 mm) nothing below ~60 mm exists in the map, so instead of a VGG pass over
128-texel patches this family measures what a coarse normal map can hold, at the 3-15 cm
scale where drape differs between fabrics, from the baked map (`normalmap.bake`) of every
`frame_step`-th frame:

  * band energy: the mean squared difference-of-Gaussians of the normal field at three
    octaves (Gaussian sigma 20-40, 40-80, 80-160 mm of cloth; log), i.e. how much the surface
    turns at each fold size;
  * band rate: how fast each band changes over time (log RMS change per second);
  * fold wavelength: 2 pi sqrt(E|B|^2 / E|grad B|^2) of the band-passed field B (20-160 mm),
    the dominant fold spacing (log meters);
  * hang: mean |n_z| (z up), how far the cloth tilts from hanging straight down.

Smoothing uses normalized convolution on the garment's mask (the UV layout's empty space and
seams do not pull the normals towards zero); statistics are means over texels whose
neighbourhood at the largest scale is at least half garment. Every statistic is a function of
distances between normals and of their vertical component, so it is invariant to a
translation of the garment and a rotation about the vertical (tests/test_classifier_drape.py).
The per-frame work is NumPy/OpenCV; baking is the library's jitted `normalmap.bake_frames`.
"""

from __future__ import annotations

import cv2
import numpy as np

# Gaussian sigmas (meters of cloth) bounding the three bands, finest first.
SIGMAS_M = (0.02, 0.04, 0.08, 0.16)
TEXEL_M = 0.01       # bake resolution: a 30 mm coarse mesh holds nothing finer than ~60 mm
FRAME_STEP = 4       # frames between baked frames (window 32 -> 8 baked frames)
DIM = 8              # 3 band energies, 3 band rates, fold wavelength, hang
_FLOOR = 1e-8


def _blur(img, sigma_px: float):
    """Gaussian blur of (H, W) or (H, W, C) float64, zero outside the image."""
    k = int(2 * np.ceil(3 * sigma_px) + 1)
    return cv2.GaussianBlur(np.ascontiguousarray(img), (k, k), sigma_px,
                            borderType=cv2.BORDER_CONSTANT)


def smooth_normals(normals, mask, sigma_px: float):
    """Normalized convolution of a normal field on a mask: G*(n m) / G*m, (H, W, 3).

    Texels where G*m is ~0 (far from the garment) get 0. `normals` (H, W, 3), `mask` (H, W)."""
    m = np.asarray(mask, np.float64)
    num = _blur(np.asarray(normals, np.float64) * m[..., None], sigma_px)
    den = _blur(m, sigma_px)
    return num / np.maximum(den, 1e-6)[..., None] * (den > 1e-6)[..., None]


def frame_bands(normals, mask, texel: float = TEXEL_M, sigmas=SIGMAS_M):
    """Band-passed normal fields of one baked frame.

    Args:
      normals: (H, W, 3) unit normals (zero off the garment), object space, z up.
      mask: (H, W) 1 on garment texels.
      texel: meters of cloth per texel.
      sigmas: increasing Gaussian sigmas (meters); band i is smooth(sigma_i) - smooth(sigma_i+1).
    Returns:
      (bands (B, H, W, 3), support (H, W) bool: garment texels whose neighbourhood at the
      largest sigma is at least half garment, smooth at the finest sigma (H, W, 3)).
    """
    m = np.asarray(mask, np.float64)
    sm = [smooth_normals(normals, m, s / texel) for s in sigmas]
    support = (m > 0.5) & (_blur(m, sigmas[-1] / texel) >= 0.5)
    bands = np.stack([a - b for a, b in zip(sm[:-1], sm[1:], strict=True)])
    return bands, support, sm[0]


def _mean_sq(field, support) -> float:
    """Mean over support texels of the squared norm of a (..., H, W, 3) field's last axis."""
    return float((field ** 2).sum(-1)[..., support].mean()) if support.any() else 0.0


def fold_wavelength(band, support, texel: float) -> float:
    """Dominant spacing (meters) of a band-passed field: 2 pi sqrt(E|B|^2 / E|grad B|^2).

    For B = a sin(2 pi x / L) this is L (the mean squares of a sine and of its derivative
    differ by (2 pi / L)^2). Gradients by central differences (per texel -> per meter)."""
    gy, gx = np.gradient(np.asarray(band, np.float64), axis=(0, 1))
    g2 = _mean_sq(gx, support) + _mean_sq(gy, support)
    e = _mean_sq(band, support)
    return float(2 * np.pi * texel * np.sqrt(e / max(g2, _FLOOR)))


def frame_stats(maps, mask, texel: float = TEXEL_M, dt: float = 1.0) -> np.ndarray:
    """Per-frame drape statistics of a stack of baked frames.

    Args:
      maps: (K, H, W, 3) baked normal maps of frames `dt` seconds apart.
      mask: (H, W) or (H, W, 1) garment mask.
      dt: seconds between consecutive maps (band rates are per second).
    Returns:
      (K, DIM) float64: [log band energy x 3, log band rate x 3 (of the change to the next
      map; the last row repeats the previous one), log fold wavelength (m), mean |n_z|].
    """
    maps = np.asarray(maps, np.float64)
    m = np.asarray(mask, np.float64).reshape(maps.shape[1:3])
    out = np.zeros((len(maps), DIM))
    prev = None
    for k, n in enumerate(maps):
        bands, support, fine = frame_bands(n, m, texel)
        energy = [_mean_sq(b, support) for b in bands]
        out[k, :3] = np.log(np.asarray(energy) + _FLOOR)
        total = bands.sum(axis=0)                       # smooth(finest) - smooth(coarsest)
        out[k, 6] = np.log(fold_wavelength(total, support, texel) + _FLOOR)
        nz = np.abs(fine[..., 2])[support]
        out[k, 7] = float(nz.mean()) if nz.size else 0.0
        if prev is not None:
            out[k - 1, 3:6] = [0.5 * np.log(_mean_sq(b - p, support) / dt ** 2 + _FLOOR)
                               for b, p in zip(bands, prev, strict=True)]
        prev = bands
    if len(maps) > 1:
        out[-1, 3:6] = out[-2, 3:6]
    return out


def window_features(stats, starts, window: int, frame_step: int = FRAME_STEP) -> np.ndarray:
    """Mean of the per-frame statistics of the baked frames inside each window.

    Args:
      stats: (K, DIM) `frame_stats` of frames 0, frame_step, 2 frame_step, ...
      starts: (N,) window start frames; window n covers frames [s, s + window).
    Returns:
      (N, DIM): statistics averaged over the window's baked frames; band rates over the
      pairs whose both frames lie in the window.
    """
    stats = np.asarray(stats, np.float64)
    out = np.zeros((len(starts), DIM))
    for i, s in enumerate(np.asarray(starts)):
        first = -(-int(s) // frame_step)
        last = (int(s) + window - 1) // frame_step           # inclusive
        rows = stats[first:last + 1]
        if len(rows) == 0:
            raise ValueError(f"window at frame {s} holds no baked frame (step {frame_step})")
        out[i] = rows.mean(axis=0)
        if len(rows) > 1:
            out[i, 3:6] = rows[:-1, 3:6].mean(axis=0)
    return out


def make_plan(faces, uvs, uv_faces, vertices, texel: float = TEXEL_M):
    """The raster plan of a garment's UV layout at `texel` meters (`normalmap.make_plan`)."""
    from wrinkle_jax import mesh, normalmap

    g = mesh.make_garment(vertices, faces, uvs, uv_faces)
    return normalmap.make_plan(g, texel_size=texel, gutter=2)


def bake_every(plan, frames, frame_step: int = FRAME_STEP, batch: int = 32) -> np.ndarray:
    """Normal maps (K, H, W, 3) of frames 0, frame_step, ... of a (T, V, 3) sequence, baked with
    `plan` by the (jitted) `normalmap.bake_frames` in batches of `batch` frames (the last one
    padded, so a garment compiles once)."""
    from wrinkle_jax import normalmap
    from wrinkle_jax.numerics import to_device

    sel = np.asarray(frames, np.float32)[::frame_step]
    pad = -len(sel) % batch
    sel = np.concatenate([sel, np.repeat(sel[-1:], pad, axis=0)])
    return np.concatenate([np.asarray(normalmap.bake_frames(plan, to_device(sel[i:i + batch])))
                           for i in range(0, len(sel), batch)])[:len(sel) - pad]


def sequence_stats(plan, frames, fps: float, frame_step: int = FRAME_STEP) -> np.ndarray:
    """`frame_stats` of frames 0, frame_step, ... of a (T, V, 3) sequence baked with `plan`
    (`bake_every`), frame_step / fps seconds apart."""
    return frame_stats(bake_every(plan, frames, frame_step), np.asarray(plan.mask),
                       plan.layout.texel_size, frame_step / fps)
