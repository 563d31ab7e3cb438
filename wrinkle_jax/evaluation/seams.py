"""Seams of merged patch grids: how much sharper normals turn across tile borders.

A merged map N* whose tiles disagree shows creases along the tile borders. The measure: the
mean angle between neighbouring texels' normals on pairs that cross a tile border (a tile
starts or ends between them), over the mean angle on all other pairs; 1 for a seamless map.
Normals (H, W, 3) unit vectors, masks (H, W) bool, origins (P, 2) int (row, col), texels.
"""

from __future__ import annotations

import numpy as np

from wrinkle_jax.evaluation.flicker import normal_angles

__all__ = ["border_pairs", "neighbour_angles", "seam_ratio", "seam_sums"]


def neighbour_angles(normals: np.ndarray, mask: np.ndarray, axis: int):
    """Angles (degrees) between unit normals of neighbouring texels along `axis`.

    Args:
      normals: (H, W, 3) unit normals; mask: (H, W) bool garment texels.
      axis: 0 (texel (r, c) vs (r + 1, c)) or 1 ((r, c) vs (r, c + 1)).
    Returns:
      (angles, valid), both shaped like the map shortened by one along `axis`; valid where
      both texels are garment.
    """
    a = np.take(normals, np.arange(normals.shape[axis] - 1), axis=axis)
    b = np.take(normals, np.arange(1, normals.shape[axis]), axis=axis)
    ma = np.take(mask, np.arange(mask.shape[axis] - 1), axis=axis)
    mb = np.take(mask, np.arange(1, mask.shape[axis]), axis=axis)
    return normal_angles(a, b), ma & mb


def border_pairs(origins: np.ndarray, size: int, length: int, axis: int) -> np.ndarray:
    """(length - 1,) bool: neighbour pair (x - 1, x) crosses a tile border along `axis`, i.e. a
    tile starts at x or ends at x - 1 (origins (P, 2) (row, col))."""
    starts = np.asarray(origins)[:, axis]
    edges = np.concatenate([starts, starts + size])  # x where a tile starts or one ends
    out = np.zeros(length - 1, bool)
    edges = edges[(edges >= 1) & (edges <= length - 1)]
    out[edges - 1] = True
    return out


def seam_sums(normals: np.ndarray, mask: np.ndarray, origins: np.ndarray, size: int
              ) -> np.ndarray:
    """[sum of border angles, border pairs, sum of other angles, other pairs] over both axes
    (add over frames, then `seam_ratio`)."""
    out = np.zeros(4)
    for axis in (0, 1):
        ang, valid = neighbour_angles(normals, mask, axis)
        border = border_pairs(origins, size, normals.shape[axis], axis)
        border = border[:, None] if axis == 0 else border[None, :]
        on, off = valid & border, valid & ~border
        out += [ang[on].sum(), on.sum(), ang[off].sum(), off.sum()]
    return out


def seam_ratio(sums: np.ndarray) -> float:
    """Mean border angle / mean other angle (nan without border or other pairs)."""
    s_on, n_on, s_off, n_off = sums
    if n_on == 0 or n_off == 0 or s_off == 0:
        return float("nan")
    return float((s_on / n_on) / (s_off / n_off))
