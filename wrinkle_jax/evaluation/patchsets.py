"""Coarse and fine simulations of one pattern on ONE pixel grid, and aligned patch sets.

A coarse (PD 30 mm) and a fine (PD 10 mm) simulation of the same sewing pattern have UVs in the
same units but slightly different outlines; baking each with its own layout would drift by a few
texels across a garment. `shared_layout` puts both on one grid, so a patch origin means the same
cloth in both maps: the evaluation tables score patches cut at the same origins, and
`wrinkle_jax.data` builds coarse-input/fine-target training pairs the same way.

Conventions: normal maps are float32 (H, W, 3) unit vectors in [-1, 1]; patches are in the RGB
form (n + 1) / 2 in [0, 1], NHWC, with a (K, S, S, 1) float32 {0, 1} mask; vertices are meters.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterable

import numpy as np

from wrinkle_jax import data, normalmap, patches
from wrinkle_jax.mesh import Garment, global_uv_scale
from wrinkle_jax.numerics import to_device

__all__ = ["AlignedPair", "PatchSet", "aligned_pair", "aligned_patches", "bake_map",
           "candidate_origins", "choose_origins", "cut", "shared_layout", "take"]


# --------------------------------------------------------------------------------------------


def shared_layout(reference: Garment, other: Garment, texel_size: float,
                  margin: int = 8) -> normalmap.UVLayout:
    """One UV layout for two meshes of the same pattern (UVs in the same units).

    The scale is `reference`'s meters per UV unit (`mesh.global_uv_scale`, the scale the
    library bakes `reference` at); the UV bounds are the union of both meshes' (their outlines
    differ by the coarse mesh's coarser polyline). Texel (r, c) then covers the same UV square,
    i.e. the same cloth, in both maps. (Baking each mesh with its own `layout_for` would not:
    their scales differ by ~1e-3, a drift of ~2 texels across a 2 m skirt.)
    """
    ppu = global_uv_scale(reference) / float(texel_size)

    def used(g):
        return np.asarray(g.uvs, np.float64)[np.unique(np.asarray(g.uv_faces))]

    uv = np.concatenate([used(reference), used(other)])
    u_min, v_min = uv.min(0)
    u_max, v_max = uv.max(0)
    width = int(math.ceil((u_max - u_min) * ppu)) + 2 * margin
    height = int(math.ceil((v_max - v_min) * ppu)) + 2 * margin
    return normalmap.UVLayout(float(ppu), float(u_min), float(v_max), int(margin), height, width,
                              float(texel_size))


@dataclasses.dataclass(frozen=True, eq=False)
class AlignedPair:
    """Raster plans of a fine and a coarse mesh on one layout.

    Attributes:
      fine, coarse: `normalmap.RasterPlan`s sharing `layout`.
      mask: (H, W, 1) float32, 1 where BOTH meshes cover the texel (the scored texels).
    """

    fine: normalmap.RasterPlan
    coarse: normalmap.RasterPlan
    mask: np.ndarray

    @property
    def layout(self) -> normalmap.UVLayout:
        return self.fine.layout


def aligned_pair(fine: Garment, coarse: Garment, texel_size: float) -> AlignedPair:
    """Plans of `fine` and `coarse` on `shared_layout(fine, coarse, texel_size)`."""
    layout = shared_layout(fine, coarse, texel_size)
    pf = normalmap.make_plan(fine, layout=layout)
    pc = normalmap.make_plan(coarse, layout=layout)
    mask = (np.asarray(pf.mask) * np.asarray(pc.mask)).astype(np.float32)
    return AlignedPair(pf, pc, mask)


def bake_map(plan: normalmap.RasterPlan, vertices) -> np.ndarray:
    """One frame (V, 3) meters -> (H, W, 3) float32 normal map (jitted bake, NumPy out)."""
    return np.asarray(normalmap.bake(plan, to_device(vertices, np.float32)))


def candidate_origins(mask: np.ndarray, size: int, stride: int, min_coverage: float
                      ) -> tuple[np.ndarray, np.ndarray]:
    """Grid patch origins whose patch has at least `min_coverage` of mask texels.

    Args:
      mask: (H, W, 1) float32 {0, 1} with H, W >= size (pad first).
      size, stride: patch side and grid step, texels.
      min_coverage: minimum fraction of mask texels in a patch, in [0, 1].
    Returns:
      origins (K, 2) int32 (row, col), row-major; coverage (K,) float32 fractions.
    """
    origins = patches.tile(mask, size=size, stride=stride)
    m = np.asarray(mask[..., 0] > 0, np.int64)
    sat = np.zeros((m.shape[0] + 1, m.shape[1] + 1), np.int64)
    sat[1:, 1:] = m.cumsum(0).cumsum(1)
    r, c = origins[:, 0].astype(np.int64), origins[:, 1].astype(np.int64)
    count = sat[r + size, c + size] - sat[r, c + size] - sat[r + size, c] + sat[r, c]
    cov = (count / float(size * size)).astype(np.float32)
    keep = cov >= min_coverage
    return origins[keep].astype(np.int32).reshape(-1, 2), cov[keep]


def choose_origins(origins: np.ndarray, count: int, seed: Iterable[int]) -> np.ndarray:
    """`count` of `origins` without replacement (all if fewer), seeded, in row-major order."""
    if len(origins) <= count:
        return origins
    rng = np.random.default_rng(list(seed))
    return origins[np.sort(rng.choice(len(origins), count, replace=False))]


def cut(image: np.ndarray, origins: np.ndarray, size: int) -> np.ndarray:
    """(H, W, C) -> (K, size, size, C) float32 patches at `origins` (NumPy)."""
    rows = origins[:, 0, None, None] + np.arange(size)[None, :, None]
    cols = origins[:, 1, None, None] + np.arange(size)[None, None, :]
    return np.asarray(image, np.float32)[rows, cols]


@dataclasses.dataclass(frozen=True)
class PatchSet:
    """Aligned patches of one frame.

    Attributes:
      input: (K, S, S, 3) coarse map, RGB form, zero off the mask.
      target: (K, S, S, 3) fine map, RGB form, zero off the mask.
      mask: (K, S, S, 1) float32, texels covered by both meshes.
      origins: (K, 2) int32 (row, col) in the shared layout.
      material_id: index into `wrinkle_jax.MATERIALS`.
    """

    input: np.ndarray
    target: np.ndarray
    mask: np.ndarray
    origins: np.ndarray
    material_id: int


def aligned_patches(pair: AlignedPair, fine_vertices, coarse_vertices, origins: np.ndarray,
                    size: int, material_id: int) -> PatchSet:
    """Bake one fine and one coarse frame on the shared grid and cut the same patches."""
    mask = np.asarray(patches.pad_to_patch(pair.mask, size)[0])
    fine = normalmap.to_rgb(patches.pad_to_patch(bake_map(pair.fine, fine_vertices), size)[0])
    coarse = normalmap.to_rgb(
        patches.pad_to_patch(bake_map(pair.coarse, coarse_vertices), size)[0])
    m = cut(mask, origins, size)
    return PatchSet(cut(coarse, origins, size) * m, cut(fine, origins, size) * m, m,
                    np.asarray(origins, np.int32), int(material_id))


def take(ds: data.PatchDataset, n: int) -> dict:
    """`n` patches of a data set spread evenly over it (all if fewer), as `ds.get`'s batch
    dict plus "scene": (n,) the scene name of every patch."""
    idx = np.unique(np.linspace(0, len(ds) - 1, min(n, len(ds))).round().astype(int))
    b = ds.get(idx)
    b["scene"] = np.array([ds.entries[j]["scene"] for j in ds.sequence_of[idx]])
    return b
