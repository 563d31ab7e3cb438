"""Side-by-side fidelity previews: coarse simulation | ours | fine simulation, for a person.

Two rows of three panels for one frame of a coarse and a fine simulation of the same pattern:

    meshes   coarse mesh | lifted mesh of the enhanced map (ours) | fine mesh
             (one camera, fitted to the coarse frame; Lambert shading, `render.render_mesh`)
    normals  coarse map | enhanced map | fine map, the same crop of texels in all three,
             upscaled nearest-neighbour so single texels stay visible

All three maps live on ONE pixel grid: the coarse and the fine mesh are baked on
`patchsets.shared_layout` (`patchsets.aligned_pair`), and the pipeline is built on that same layout
(`pipeline.make_pipeline(layout=...)`), so its enhanced map N* is already on the grid; a texel
(r, c) is the same cloth in every map and the crop needs no resampling.

Conventions: vertices are meters; normal maps are float32 (H, W, 3) unit vectors in [-1, 1]
with a (H, W, 1) float32 mask; panels are uint8 RGB (H, W, 3).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import cv2
import numpy as np

from wrinkle_jax import enhancer as enhancer_lib
from wrinkle_jax import normalmap, patches, render
from wrinkle_jax import pipeline as pipeline_lib
from wrinkle_jax.evaluation import patchsets
from wrinkle_jax.mesh import Garment

__all__ = ["FidelityPreviews", "MESH_LABELS", "MAP_LABELS", "crop_origin", "fidelity_previews",
           "map_row", "mesh_row"]

MESH_LABELS = ("coarse simulation", "ours (enhanced + lifted)", "fine simulation")
MAP_LABELS = ("coarse map", "enhanced map (ours)", "fine map")


def crop_origin(mask, size: int, stride: int | None = None) -> tuple[int, int]:
    """The (row, col) of a `size` x `size` window of `mask` for a preview crop.

    The window of most garment texels on a grid of step `stride` (default size // 8); among
    windows within 2 % of the best coverage, the one whose center is nearest the mask's
    centroid (so the crop sits on the garment's middle, not on an edge or a hole).

    Args:
      mask: (H, W) or (H, W, 1) {0, 1}; pad to >= size first (`patches.pad_to_patch`).
      size: window side, texels. stride: grid step, texels.
    Returns:
      (row, col) ints with row + size <= H and col + size <= W.
    """
    m = np.asarray(mask, np.float32).reshape(np.shape(mask)[0], np.shape(mask)[1], 1)
    if m.shape[0] < size or m.shape[1] < size:
        raise ValueError(f"mask {m.shape[:2]} is smaller than the crop {size}; pad it first")
    step = max(1, size // 8) if stride is None else int(stride)
    origins, cov = patchsets.candidate_origins(m, size, step, 0.0)
    if not len(origins):  # an empty mask: tile() keeps only windows touching it
        return 0, 0
    rows, cols = np.nonzero(m[..., 0] > 0)
    centroid = np.array([rows.mean(), cols.mean()])
    near_best = cov >= cov.max() - 0.02
    dist = np.linalg.norm(origins + size / 2.0 - centroid, axis=1)
    k = np.flatnonzero(near_best)[np.argmin(dist[near_best])]
    return int(origins[k, 0]), int(origins[k, 1])


def map_row(maps: Sequence[np.ndarray], mask, origin: tuple[int, int], crop: int,
            panel: int, labels: Sequence[str]) -> np.ndarray:
    """Normal-map panels side by side: the same `crop` x `crop` texels of every map.

    Args:
      maps: (H, W, 3) normals in [-1, 1] on one grid. mask: (H, W, 1) texels shown (others
        mid-grey). origin: (row, col) of the crop (maps are zero-padded bottom/right to >=
        crop). crop: texels. panel: output pixels per side (nearest-neighbour upscale).
      labels: one caption per map.
    Returns:
      (panel, len(maps) * panel, 3) uint8 RGB.
    """
    r, c = origin
    m = np.asarray(patches.pad_to_patch(np.asarray(mask, np.float32), crop)[0])
    m = m[r:r + crop, c:c + crop]
    out = []
    for nmap, text in zip(maps, labels, strict=True):
        x = np.asarray(patches.pad_to_patch(np.asarray(nmap, np.float32), crop)[0])
        img = render.normal_map_image(normalmap.to_rgb(x[r:r + crop, c:c + crop]), m)
        img = cv2.resize(img, (panel, panel), interpolation=cv2.INTER_NEAREST)
        out.append(render._label(img, text))
    return np.concatenate(out, axis=1)


def mesh_row(meshes: Sequence[tuple[np.ndarray, np.ndarray]], camera: render.Camera,
             panel: int, labels: Sequence[str], supersample: int = 2) -> np.ndarray:
    """Shaded meshes side by side under one camera and light.

    Args:
      meshes: (vertices (V, 3) meters, faces (F, 3) int) per panel. camera: shared camera.
      panel: pixels per side. labels: one caption per mesh. supersample: as in `render_mesh`.
    Returns:
      (panel, len(meshes) * panel, 3) uint8 RGB.
    """
    out = []
    for (v, f), text in zip(meshes, labels, strict=True):
        img = render.to_uint8(render.render_mesh(np.asarray(v), np.asarray(f), camera, panel,
                                                 supersample=supersample))
        out.append(render._label(img, text))
    return np.concatenate(out, axis=1)


@dataclasses.dataclass(frozen=True)
class FidelityPreviews:
    """What `fidelity_previews` returns.

    Attributes:
      meshes: (panel, 3 * panel, 3) uint8: coarse | ours | fine shaded meshes.
      normals: (panel, 3 * panel, 3) uint8: coarse | enhanced | fine map crops.
      crop_origin: (row, col) of the crop on the shared grid (texels). crop: its side, texels.
      texel_size: meters per texel. layout: the shared `normalmap.UVLayout`.
      maps: {"coarse", "enhanced", "fine"} (H, W, 3) full maps on the layout; mask (H, W, 1)
        the texels both meshes cover.
      vertex_counts: {"coarse", "ours", "fine"} vertices of each rendered mesh.
    """

    meshes: np.ndarray
    normals: np.ndarray
    crop_origin: tuple[int, int]
    crop: int
    texel_size: float
    layout: normalmap.UVLayout
    maps: dict
    mask: np.ndarray
    vertex_counts: dict


def fidelity_previews(coarse: Garment, coarse_vertices, fine: Garment, fine_vertices,
                      enhancer: enhancer_lib.Enhancer, material: str, *, panel: int = 512,
                      crop: int = 256, supersample: int = 2,
                      config: pipeline_lib.PipelineConfig | None = None,
                      mesh_labels: Sequence[str] = MESH_LABELS,
                      map_labels: Sequence[str] = MAP_LABELS) -> FidelityPreviews:
    """The two preview rows of one frame of a coarse and a fine simulation.

    The enhanced map and the lifted mesh come from the pipeline (`pipeline.make_pipeline` on
    the shared layout, `pipeline.iter_enhance` of this one frame, no body).

    Args:
      coarse, fine: garments of the same pattern (UVs in the same units). coarse_vertices:
        (Vc, 3), fine_vertices: (Vf, 3) the frame, meters.
      enhancer: the model. material: one of its material names.
      panel: pixels per panel side. crop: texels per side of the normal-map crop.
      supersample: mesh antialiasing. config: PipelineConfig (default: the pipeline's, with
        lifting on).
      mesh_labels, map_labels: captions of the three panels of each row.
    Returns:
      FidelityPreviews.
    Raises:
      pipeline.PipelineError: unknown material or a garment without texels.
    """
    config = pipeline_lib.PipelineConfig() if config is None else config
    if not config.lift:
        config = dataclasses.replace(config, lift=True)
    material_id = enhancer.config.material_id(
        pipeline_lib.resolve_material(material, enhancer.config.materials)[0])
    cv = np.asarray(coarse_vertices, np.float32)
    fv = np.asarray(fine_vertices, np.float32)
    pair = patchsets.aligned_pair(fine, coarse, enhancer.config.texel_size)
    pipe = pipeline_lib.make_pipeline(coarse, enhancer, config, layout=pair.layout)
    (frame,) = pipeline_lib.iter_enhance(pipe, cv[None], material_id, indices=[0])
    maps = {"coarse": patchsets.bake_map(pair.coarse, cv), "enhanced": frame.normal_map,
            "fine": patchsets.bake_map(pair.fine, fv)}
    mask = np.asarray(pair.mask, np.float32)
    origin = crop_origin(patches.pad_to_patch(mask, crop)[0], crop)
    normals = map_row([maps["coarse"], maps["enhanced"], maps["fine"]], mask, origin, crop,
                      panel, map_labels)
    camera = render.fit_camera(cv)
    ours_faces = np.asarray(pipe.fine_garment.faces)
    meshes = mesh_row([(cv, coarse.faces), (frame.detailed, ours_faces), (fv, fine.faces)],
                      camera, panel, mesh_labels, supersample)
    return FidelityPreviews(meshes, normals, origin, int(crop), float(enhancer.config.texel_size),
                            pair.layout, maps, mask,
                            {"coarse": int(len(cv)), "ours": int(len(frame.detailed)),
                             "fine": int(len(fv))})
