"""Temporal coherence: angles between normals and frame-to-frame flicker of normal maps.

:func:`normal_angles` (degrees, accurate for small angles), :func:`mean_angular_change` of two
normal maps over a mask and :func:`flicker_series` of a sequence of maps. NumPy (float64).
"""

from __future__ import annotations

import numpy as np

__all__ = ["flicker_series", "mean_angular_change", "normal_angles"]


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
