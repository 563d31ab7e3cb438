"""UV normal maps: raster plans, jittable baking and sampling, coarse-looking downsampling, and
16-bit PNG IO.

A normal map is float32 `(H, W, 3)` of unit object-space normals in [-1, 1] (zero in the
background) plus a float32 mask `(H, W, 1)` that is 1 on texels whose center lies inside a UV
triangle. Image rows run top to bottom and UV v runs bottom to top, so the picture looks like
the UV layout. A texel has a fixed physical size (`texel_size`, meters): a garment's UV layout
is scaled by its meters-per-UV-unit (`mesh.global_uv_scale`), so every garment is baked at the
same cloth area per pixel.

The split follows the project's convention:
  * `make_plan` (NumPy, once per UV layout) rasterizes the UV triangles: for every covered
    texel, and every texel of a `gutter` band around the mask, the triangle and barycentric
    coordinates to interpolate. Gutter texels use the nearest covered texel's triangle with
    barycentrics clamped to it, so their value continues the garment across UV seams and
    bilinear sampling near a seam never reads background.
  * `bake(plan, vertices)` is pure JAX: jittable, vmappable over frames (`bake_frames`), and
    differentiable with respect to the vertices.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import os
from typing import Any

import cv2
import jax
import jax.numpy as jnp
import numpy as np

from wrinkle_jax.fileio import atomic_write_bytes
from wrinkle_jax.mesh import Garment, GarmentError, face_normals, global_uv_scale, vertex_normals
from wrinkle_jax.numerics import BARY_EPS, UV_AREA_EPS, normalize, safe_div, to_device

DEFAULT_TEXEL_SIZE = 0.002  # meters of cloth per texel (paper: fixed physical pixel size)


class NormalMapError(ValueError):
    """Invalid normal-map input or file (the message names the file and the problem)."""


# --------------------------------------------------------------------------------------------
# Layout and plan
# --------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class UVLayout:
    """Affine map from UV coordinates to continuous pixel coordinates (static, hashable).

    Pixel (col x, row y) continuous coordinates put texel (r, c)'s center at (c + 0.5, r + 0.5):
        x = (u - u_min) * pixels_per_uv + margin
        y = (v_max - v) * pixels_per_uv + margin

    Attributes:
      pixels_per_uv: texels per UV unit.
      u_min, v_max: UV corner mapped to pixel (margin, margin).
      margin: empty texels around the layout (room for the gutter).
      height, width: map size in texels.
      texel_size: meters of cloth per texel.
    """

    pixels_per_uv: float
    u_min: float
    v_max: float
    margin: int
    height: int
    width: int
    texel_size: float

    @property
    def shape(self) -> tuple[int, int]:
        return (self.height, self.width)

    def uv_to_pixel(self, uv):
        """(N, 2) UVs -> (N, 2) continuous (x, y) pixel coordinates (NumPy or JAX)."""
        x = (uv[..., 0] - self.u_min) * self.pixels_per_uv + self.margin
        y = (self.v_max - uv[..., 1]) * self.pixels_per_uv + self.margin
        xp = jnp if isinstance(uv, jax.Array) else np
        return xp.stack([x, y], axis=-1)


def layout_for(garment: Garment, texel_size: float = DEFAULT_TEXEL_SIZE, margin: int = 8,
               meters_per_uv: float | None = None) -> UVLayout:
    """The UV layout that bakes `garment` at `texel_size` meters per texel.

    Args:
      garment: source of the UVs (and of the 3D areas when `meters_per_uv` is None).
      texel_size: meters per texel.
      margin: texels of empty border on every side.
      meters_per_uv: override the scale (e.g. 1.0 for pattern UVs in meters, or to bake a
        coarse and a fine mesh of the same pattern onto identical pixel grids).
    """
    if not texel_size > 0:
        raise NormalMapError(f"texel_size must be positive, got {texel_size}")
    if meters_per_uv is None:
        _check_areas(garment)
    scale = global_uv_scale(garment) if meters_per_uv is None else float(meters_per_uv)
    ppu = scale / texel_size
    uv = np.asarray(garment.uvs, np.float64)[np.unique(np.asarray(garment.uv_faces))]
    u_min, v_min = uv.min(0)
    u_max, v_max = uv.max(0)
    width = int(math.ceil((u_max - u_min) * ppu)) + 2 * margin
    height = int(math.ceil((v_max - v_min) * ppu)) + 2 * margin
    if width * height > 16384 * 16384:
        raise NormalMapError(
            f"a {height}x{width} normal map is too large; increase texel_size ({texel_size} m)"
        )
    return UVLayout(float(ppu), float(u_min), float(v_max), int(margin), height, width,
                    float(texel_size))


def _check_areas(garment: Garment) -> None:
    """Raise GarmentError if the garment has no 3D area or its UV layout has none (the texel
    scale, sqrt(3D area / UV area), needs both), saying which."""
    v = np.asarray(garment.vertices, np.float64)[np.asarray(garment.faces)]
    a3 = np.linalg.norm(np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]), axis=1).sum()
    uv = np.asarray(garment.uvs, np.float64)[np.asarray(garment.uv_faces)]
    e1, e2 = uv[:, 1] - uv[:, 0], uv[:, 2] - uv[:, 0]
    a2 = np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]).sum()
    if not a2 > 0:
        raise GarmentError("the UV layout has zero area (all UVs on one point or line); "
                             "cannot derive a texel size")
    if not a3 > 0:
        raise GarmentError("the garment has zero 3D area (all vertices on one point or "
                             "line); cannot derive a texel size")


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class RasterPlan:
    """Everything `bake` needs, precomputed once per UV layout (a pytree; layout is static).

    Attributes:
      faces: (F, 3) int32 3D triangles (for the vertex normals).
      texel_pixel: (N,) int32 flat pixel index (row * W + col) of each planned texel; the
        covered texels come first (ascending), then the gutter texels.
      texel_tri: (N,) int32 triangle of each planned texel.
      texel_vertex: (N, 3) int32 3D vertex ids of that triangle's corners.
      texel_bary: (N, 3) float32 barycentric weights (sum to 1, all >= 0).
      index_map: (H, W) int32 planned-texel index of every pixel, N for background.
      mask: (H, W, 1) float32, 1 on covered texels.
      layout: UVLayout (static).
    """

    faces: Any
    texel_pixel: Any
    texel_tri: Any
    texel_vertex: Any
    texel_bary: Any
    index_map: Any
    mask: Any
    layout: UVLayout = dataclasses.field(metadata=dict(static=True))

    @property
    def shape(self) -> tuple[int, int]:
        return self.layout.shape

    @property
    def num_covered(self) -> int:
        return int(np.asarray(self.mask).sum())


def _face_affine(tri: np.ndarray):
    """Barycentric coordinates as affine functions of pixel position.

    tri: (F, 3, 2) pixel-space corners. Returns coefficients (F, 3, 3) with
    lambda_k(x, y) = c[:, k, 0] * x + c[:, k, 1] * y + c[:, k, 2], and the signed doubled area.
    Works for either orientation (flipped UV triangles); degenerate ones get zero coefficients.
    """
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    d = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])
    ok = np.abs(d) > UV_AREA_EPS
    inv = np.where(ok, 1.0 / np.where(ok, d, 1.0), 0.0)
    coef = np.empty((len(tri), 3, 3))
    for k, (p, q) in enumerate(((b, c), (c, a), (a, b))):
        # lambda_k = cross(q - p, x - p) / d : the signed area opposite corner k.
        coef[:, k, 0] = -(q[:, 1] - p[:, 1]) * inv
        coef[:, k, 1] = (q[:, 0] - p[:, 0]) * inv
        coef[:, k, 2] = ((q[:, 1] - p[:, 1]) * p[:, 0] - (q[:, 0] - p[:, 0]) * p[:, 1]) * inv
    return coef, d, ok


def _rasterize(tri: np.ndarray, height: int, width: int, chunk: int = 1 << 22):
    """Texel centers inside each triangle, vectorized over triangles in bounded chunks.

    Returns (pixel flat index, triangle id, barycentrics) of every covered texel; a texel
    inside several triangles (shared edges, overlapping UVs) goes to the one it is most inside
    (largest minimum barycentric), deterministically.
    """
    coef, _, ok = _face_affine(tri)
    lo = np.ceil(tri.min(1) - 0.5).astype(np.int64)  # first texel center >= min
    hi = np.floor(tri.max(1) - 0.5).astype(np.int64)
    lo = np.clip(lo, 0, [width - 1, height - 1])
    hi = np.clip(hi, -1, [width - 1, height - 1])
    nx = np.maximum(hi[:, 0] - lo[:, 0] + 1, 0)
    ny = np.maximum(hi[:, 1] - lo[:, 1] + 1, 0)
    count = np.where(ok, nx * ny, 0)
    pix, tid, bary, score = [], [], [], []
    csum = np.cumsum(count)
    start = 0
    while start < len(tri):
        # Take as many triangles as fit in `chunk` candidates (at least one).
        base = csum[start - 1] if start else 0
        stop = max(int(np.searchsorted(csum, base + chunk, side="right")), start + 1)
        f = np.arange(start, stop)
        cnt = count[f]
        total = int(cnt.sum())
        start = stop
        if total == 0:
            continue
        fid = np.repeat(f, cnt)
        local = np.arange(total) - np.repeat(np.cumsum(cnt) - cnt, cnt)
        cx = lo[fid, 0] + local % nx[fid]
        cy = lo[fid, 1] + local // nx[fid]
        px, py = cx + 0.5, cy + 0.5
        lam = coef[fid, :, 0] * px[:, None] + coef[fid, :, 1] * py[:, None] + coef[fid, :, 2]
        inside = (lam >= -BARY_EPS).all(1)
        pix.append(cy[inside] * width + cx[inside])
        tid.append(fid[inside])
        lam = np.clip(lam[inside], 0.0, None)
        bary.append(lam / lam.sum(1, keepdims=True))
        score.append(lam.min(1))
    if not pix:
        return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 3))
    pix, tid = np.concatenate(pix), np.concatenate(tid)
    bary, score = np.concatenate(bary), np.concatenate(score)
    order = np.lexsort((tid, -score, pix))  # per pixel: most-inside first, then lowest id
    pix, tid, bary = pix[order], tid[order], bary[order]
    first = np.r_[True, pix[1:] != pix[:-1]]
    return pix[first], tid[first], bary[first]


def _closest_barycentric(p: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """Barycentric coordinates of the point of each triangle closest to p (2D, vectorized).

    p: (N, 2), tri: (N, 3, 2). Inside points keep their own coordinates; outside ones are
    projected to the nearest edge (clamped to the segment). Degenerate triangles fall back to
    the nearest corner.
    """
    coef, _, ok = _face_affine(tri)
    lam = coef[:, :, 0] * p[:, :1] + coef[:, :, 1] * p[:, 1:2] + coef[:, :, 2]
    inside = ok & (lam >= 0).all(1)
    best = np.full(len(p), np.inf)
    out = np.zeros((len(p), 3))
    for k in range(3):
        i, j = k, (k + 1) % 3
        a, b = tri[:, i], tri[:, j]
        ab = b - a
        t = np.clip(safe_np_div(((p - a) * ab).sum(1), (ab * ab).sum(1)), 0.0, 1.0)
        q = a + t[:, None] * ab
        dist = ((p - q) ** 2).sum(1)
        better = dist < best
        best = np.where(better, dist, best)
        w = np.zeros((len(p), 3))
        w[:, i] = 1.0 - t
        w[:, j] = t
        out = np.where(better[:, None], w, out)
    lam = np.clip(lam, 0.0, None)
    lam = lam / np.maximum(lam.sum(1, keepdims=True), 1e-30)
    return np.where(inside[:, None], lam, out)


def safe_np_div(num: np.ndarray, den: np.ndarray) -> np.ndarray:
    """num / den with 0 where den == 0 (NumPy)."""
    ok = den != 0
    return np.where(ok, num / np.where(ok, den, 1.0), 0.0)


def make_plan(garment: Garment, texel_size: float = DEFAULT_TEXEL_SIZE, gutter: int = 4,
              margin: int | None = None, layout: UVLayout | None = None) -> RasterPlan:
    """Rasterize a garment's UV layout once; the plan is reused for every frame.

    Args:
      garment: topology and UVs (positions are only used for the texel scale).
      texel_size: meters of cloth per texel (ignored when `layout` is given).
      gutter: width in texels of the band around the mask filled by extension across
        seams/borders (0 disables it).
      margin: empty border in texels (default: gutter + 4).
      layout: reuse an existing layout (e.g. bake a coarse and a fine mesh of the same pattern
        onto the same pixels).
    Returns:
      RasterPlan. Degenerate (zero-area) UV triangles cover no texel; flipped ones are
      rasterized like the others.
    """
    if layout is None:
        layout = layout_for(garment, texel_size, gutter + 4 if margin is None else margin)
    h, w = layout.shape
    uv_px = layout.uv_to_pixel(np.asarray(garment.uvs, np.float64))
    uf = np.asarray(garment.uv_faces, np.int64)
    tri = uv_px[uf]
    pix, tid, bary = _rasterize(tri, h, w)
    mask = np.zeros(h * w, np.float32)
    mask[pix] = 1.0
    if gutter > 0 and len(pix):
        g_pix, g_tid, g_bary = _gutter(mask.reshape(h, w), pix, tid, tri, gutter)
        pix = np.r_[pix, g_pix]
        tid = np.r_[tid, g_tid]
        bary = np.r_[bary, g_bary]
    index_map = np.full(h * w, len(pix), np.int32)
    index_map[pix] = np.arange(len(pix), dtype=np.int32)
    faces = np.asarray(garment.faces, np.int32)
    # Device arrays: passing the plan to a jitted bake then copies nothing per call
    # (`to_device`: copies only, no op-by-op compile per array).
    arrays = to_device(dict(
        faces=faces,
        texel_pixel=pix.astype(np.int32),
        texel_tri=tid.astype(np.int32),
        texel_vertex=faces[tid].reshape(-1, 3),
        texel_bary=bary.astype(np.float32).reshape(-1, 3),
        index_map=index_map.reshape(h, w),
        mask=mask.reshape(h, w, 1),
    ))
    return RasterPlan(**arrays, layout=layout)


def _gutter(mask: np.ndarray, pix, tid, tri, gutter: int):
    """Texels within `gutter` of the mask, each assigned the nearest covered texel's triangle
    with barycentrics clamped to that triangle."""
    h, w = mask.shape
    background = (mask == 0).astype(np.uint8)
    dist, labels = cv2.distanceTransformWithLabels(
        background, cv2.DIST_L2, 5, labelType=cv2.DIST_LABEL_PIXEL
    )
    # Every covered (zero) pixel carries its own label; map labels back to covered texels.
    label_owner = np.full(int(labels.max()) + 1, -1, np.int64)
    owner_of_pix = np.full(h * w, -1, np.int64)
    owner_of_pix[pix] = np.arange(len(pix))
    flat_labels = labels.reshape(-1)
    label_owner[flat_labels[pix]] = owner_of_pix[pix]
    band = np.flatnonzero((background.reshape(-1) == 1) & (dist.reshape(-1) <= gutter))
    near = label_owner[flat_labels[band]]
    keep = near >= 0
    band, near = band[keep], near[keep]
    g_tid = tid[near]
    centers = np.stack([band % w + 0.5, band // w + 0.5], 1).astype(np.float64)
    g_bary = _closest_barycentric(centers, tri[g_tid])
    return band, g_tid, g_bary


# --------------------------------------------------------------------------------------------
# Baking and sampling (JAX)
# --------------------------------------------------------------------------------------------


@functools.partial(jax.jit, static_argnames=("smooth",))
def bake(plan: RasterPlan, vertices, smooth: bool = True):
    """Bake one frame to a normal map.

    Args:
      plan: RasterPlan of the garment's UV layout.
      vertices: (V, 3) float32 positions, meters.
      smooth: interpolate area-weighted vertex normals (True) or use flat face normals.
    Returns:
      (H, W, 3) float32 unit normals on covered and gutter texels, zero elsewhere. Jitted
      (`smooth` static: one program per plan shape, also when called eagerly), differentiable
      w.r.t. `vertices`.
    """
    if smooth:
        vn = vertex_normals(vertices, plan.faces)
        n = jnp.einsum("nk,nkc->nc", plan.texel_bary, vn[plan.texel_vertex])
    else:
        n = face_normals(vertices, plan.faces)[plan.texel_tri]
    n = normalize(n)
    n = jnp.concatenate([n, jnp.zeros((1, 3), n.dtype)], axis=0)
    return n[plan.index_map]


@functools.partial(jax.jit, static_argnames=("smooth", "batch_size"))
def bake_frames(plan: RasterPlan, frames, smooth: bool = True, batch_size: int | None = None):
    """Bake a batch of frames (T, V, 3) -> (T, H, W, 3).

    Args:
      batch_size: None vmaps over all T frames at once; an integer bakes `batch_size` frames
        at a time under `lax.map`, which keeps each step's working set in cache (on a CPU this
        is faster per frame for large maps; see benchmarks/bench_normalmap.py) and bounds
        memory.
    """
    if batch_size is None:
        return jax.vmap(lambda v: bake(plan, v, smooth))(frames)
    return jax.lax.map(lambda v: bake(plan, v, smooth), frames, batch_size=batch_size)


@functools.partial(jax.jit, static_argnames=("layout", "renormalize"))
def sample(normal_map, uv, layout: UVLayout, renormalize: bool = True):
    """Bilinearly sample a map at UV positions (jittable, differentiable w.r.t. the map).

    Args:
      normal_map: (H, W, C) float32.
      uv: (N, 2) UV coordinates in the layout's units.
      layout: the UVLayout the map was baked with.
      renormalize: normalize the result to unit length (for normal maps).
    Returns:
      (N, C) float32. Positions outside the map clamp to its border texels.
    """
    h, w = normal_map.shape[:2]
    xy = layout.uv_to_pixel(jnp.asarray(uv)) - 0.5  # texel centers at integer coordinates
    x0 = jnp.floor(xy[:, 0])
    y0 = jnp.floor(xy[:, 1])
    fx = (xy[:, 0] - x0)[:, None]
    fy = (xy[:, 1] - y0)[:, None]
    x0 = x0.astype(jnp.int32)
    y0 = y0.astype(jnp.int32)

    def at(yy, xx):
        return normal_map[jnp.clip(yy, 0, h - 1), jnp.clip(xx, 0, w - 1)]

    out = ((1 - fy) * ((1 - fx) * at(y0, x0) + fx * at(y0, x0 + 1))
           + fy * ((1 - fx) * at(y0 + 1, x0) + fx * at(y0 + 1, x0 + 1)))
    return normalize(out) if renormalize else out


def sample_at_vertices(normal_map, garment: Garment, layout: UVLayout, renormalize: bool = True):
    """Sample a map at every 3D vertex (V, C): seam vertices average their UV copies.

    Each face corner contributes the sample at its own UV, so a vertex on a seam gets the mean
    over the UV copies that touch it (weighted by how many corners use each copy).
    """
    uv_idx = jnp.asarray(garment.uv_faces).reshape(-1)
    v_idx = jnp.asarray(garment.faces).reshape(-1)
    s = sample(normal_map, jnp.asarray(garment.uvs), layout, renormalize=False)[uv_idx]
    nv = garment.num_vertices
    acc = jax.ops.segment_sum(s, v_idx, num_segments=nv)
    cnt = jax.ops.segment_sum(jnp.ones_like(v_idx, s.dtype), v_idx, num_segments=nv)
    out = safe_div(acc, cnt[:, None])
    return normalize(out) if renormalize else out


def downsample_like_coarse(normal_map, mask, factor: float):
    """Make a coarse-looking input from a fine normal map (the paper's training input).

    Normalized convolution: the map is area-downsampled by `factor` with the mask as weights
    (so background never bleeds into the garment), upsampled back with the same weighting,
    renormalized to unit length and cut to the original mask.

    Args:
      normal_map: (H, W, 3) float32; mask: (H, W, 1) float32 in {0, 1}.
      factor: coarse particle distance / texel size, in texels (e.g. 30 mm / 2 mm = 15): the
        coarse mesh cannot hold detail finer than its particle distance. 1 returns the input.
    Returns:
      (H, W, 3) float32, zero outside the mask. Jittable with `factor` static.
    """
    if factor <= 1.0:
        return normal_map * mask
    h, w = normal_map.shape[:2]
    sh, sw = max(1, round(h / factor)), max(1, round(w / factor))
    weighted = normal_map * mask

    def resize(x, hh, ww):
        return jax.image.resize(x, (hh, ww, x.shape[-1]), method="linear", antialias=True)

    small_n = resize(weighted, sh, sw)
    small_m = resize(mask, sh, sw)
    small = safe_div(small_n, small_m)
    big_n = resize(small * (small_m > 0), h, w)
    big_m = resize((small_m > 0).astype(mask.dtype), h, w)
    return normalize(safe_div(big_n, big_m)) * mask


# --------------------------------------------------------------------------------------------
# PNG IO (16-bit)
# --------------------------------------------------------------------------------------------


def to_rgb(normal_map):
    """Unit normals in [-1, 1] -> the RGB image form (n + 1) / 2 in [0, 1]."""
    return (normal_map + 1.0) * 0.5


def from_rgb(rgb):
    """RGB image form in [0, 1] -> normals in [-1, 1] (not renormalized)."""
    return rgb * 2.0 - 1.0


def save_normal_map_png(path: str | os.PathLike, normal_map, mask=None) -> None:
    """Write a normal map as a 16-bit PNG: RGB = (n + 1) / 2, alpha = mask (if given).

    Background texels (zero vectors) are written as mid-grey (0.5, 0.5, 0.5). Written
    atomically.
    """
    n = np.asarray(normal_map, np.float64)
    if n.ndim != 3 or n.shape[2] != 3:
        raise NormalMapError(f"{path}: expected a (H, W, 3) normal map, got shape {n.shape}")
    if not np.isfinite(n).all():
        raise NormalMapError(f"{path}: the normal map has non-finite values")
    rgb = np.clip(np.round(np.clip(to_rgb(n), 0, 1) * 65535.0), 0, 65535).astype(np.uint16)
    img = rgb[..., ::-1]  # OpenCV writes BGR(A)
    if mask is not None:
        m = np.asarray(mask, np.float64).reshape(n.shape[0], n.shape[1], 1)
        alpha = np.round(np.clip(m, 0, 1) * 65535.0).astype(np.uint16)
        img = np.concatenate([img, alpha], axis=2)
    _write_png(path, img)


def load_normal_map_png(path: str | os.PathLike, renormalize: bool = True):
    """Read a PNG written by `save_normal_map_png` (or any 8/16-bit RGB(A) normal map).

    Returns:
      normal_map (H, W, 3) float32 in [-1, 1] (unit length where the mask is set, if
      `renormalize`) and mask (H, W, 1) float32 (from alpha; all ones without alpha).
    """
    img = _read_png(path)
    if img.ndim != 3 or img.shape[2] not in (3, 4):
        raise NormalMapError(f"{path}: expected an RGB or RGBA image, got shape {img.shape}")
    scale = 65535.0 if img.dtype == np.uint16 else 255.0
    x = img.astype(np.float32) / scale
    rgb = x[..., 2::-1] if img.shape[2] == 3 else x[..., [2, 1, 0]]
    mask = (x[..., 3:4] if img.shape[2] == 4 else np.ones_like(x[..., :1]))
    mask = (mask > 0.5).astype(np.float32)
    n = from_rgb(rgb)
    if renormalize:
        n = np.asarray(normalize(jnp.asarray(n))) * mask
    return n.astype(np.float32), mask


def save_mask_png(path: str | os.PathLike, mask) -> None:
    """Write a (H, W[, 1]) mask in [0, 1] as a 16-bit greyscale PNG (atomically)."""
    m = np.asarray(mask, np.float64)
    m = m.reshape(m.shape[0], m.shape[1])
    _write_png(path, np.round(np.clip(m, 0, 1) * 65535.0).astype(np.uint16))


def load_mask_png(path: str | os.PathLike):
    """Read a greyscale mask PNG -> (H, W, 1) float32 in [0, 1]."""
    img = _read_png(path)
    if img.ndim == 3:
        img = img[..., 0]
    scale = 65535.0 if img.dtype == np.uint16 else 255.0
    return (img.astype(np.float32) / scale)[..., None]


def _write_png(path, img: np.ndarray) -> None:
    ok, buf = cv2.imencode(".png", img)
    if not ok:
        raise NormalMapError(f"{path}: PNG encoding failed")
    atomic_write_bytes(path, buf.tobytes())


def _read_png(path) -> np.ndarray:
    try:
        data = np.fromfile(os.fspath(path), np.uint8)
    except OSError as e:
        raise NormalMapError(f"{path}: cannot read ({e.strerror})") from None
    img = cv2.imdecode(data, cv2.IMREAD_UNCHANGED)
    if img is None:
        raise NormalMapError(f"{path}: not a readable PNG image")
    return img
