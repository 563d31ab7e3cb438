"""The pipeline's stages as public, pure functions of one frame (jittable, differentiable).

    coarse (Vc, 3) --bake_stage--> coarse map (Hp, Wp, 3) + network input (Hp, Wp, 3)
      --tile_stage--> patches (P, S, S, 3) --network_stage(params, material)--> (P, S, S, 3)
      --merge_stage--> N* (H, W, 3) --lift_stage (+ body)--> detailed (V', 3)

Each stage takes its per-garment setup (raster plan, padded mask, patch origins, subdivision,
lifting topology: `pipeline.make_pipeline` prepares them once, in NumPy) as explicit
arguments, and its static settings as keyword arguments. `pipeline.frame_fn` composes them into
one differentiable function of (params, coarse vertices, material); `pipeline.iter_enhance`
streams chunks of frames through the jitted, frame-vmapped forms below (module level, so their
compile caches are shared by every pipeline in the process).

Conventions: vertices are meters; normal maps (H, W, 3) unit object-space normals in [-1, 1];
the network works on the RGB form (n + 1) / 2 in [0, 1]; (Hp, Wp) is the map zero-padded at
the bottom/right to at least one patch (`patches.pad_to_patch`); masks are (., ., 1) float32.
Differentiable with respect to the vertices, the network parameters (reverse mode: the U-Net's
fast convolutions and the lift are custom VJPs) and the maps; not with respect to the integer
material id or the origins. The patch merge accumulates in float32 (`patches.merge`) and the
U-Net computes in float32 whatever the input dtype.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from wrinkle_jax import enhancer as enhancer_lib
from wrinkle_jax import lift as lift_lib
from wrinkle_jax import mesh, normalmap, patches
from wrinkle_jax.numerics import normalize

__all__ = ["FrameResult", "bake_stage", "batch_blur_weights", "lift_stage", "merge_stage",
           "network_stage", "tile_stage"]


# --------------------------------------------------------------------------------------------
# Stages (one frame)
# --------------------------------------------------------------------------------------------


def bake_stage(plan: normalmap.RasterPlan, vertices, mask, *, smooth: bool = True,
               padded_shape: tuple[int, int]):
    """Bake one coarse frame: its normal map and the network input.

    Args:
      plan: the raster plan of the garment's UV layout (maps of (H, W) texels).
      vertices: (Vc, 3) float coarse vertices, meters.
      mask: (Hp, Wp, 1) float32 garment texels, zero-padded like the maps.
      smooth: interpolated vertex normals (True) or flat face normals.
      padded_shape: static (Hp, Wp) >= (H, W): the maps are zero-padded at the bottom/right.
    Returns:
      (coarse_map, network_input): (Hp, Wp, 3) unit normals on the garment and its seam
      gutter, zero elsewhere; and (Hp, Wp, 3) its RGB form (n + 1) / 2 times `mask` (zero off
      the garment, as the training inputs).
    """
    coarse = normalmap.bake(plan, vertices, smooth)
    h, w = coarse.shape[:2]
    coarse = jnp.pad(coarse, ((0, padded_shape[0] - h), (0, padded_shape[1] - w), (0, 0)))
    return coarse, normalmap.to_rgb(coarse) * mask


def tile_stage(image, origins, *, size: int):
    """Cut (P, size, size, C) patches at `origins` ((P, 2) int32 row, col) out of an
    (Hp, Wp, C) map (`patches.extract`)."""
    return patches.extract(image, origins, size)


def network_stage(apply, params, tiles, material_id, *, batch_size: int, origins=None,
                  blur_weights=None):
    """Run the U-Net over one frame's patches in fixed-size batches.

    The P patches are zero-padded to whole batches of `batch_size` (each at a fixed position)
    and the batches run one after another (`lax.map`), so the network compiles for one batch
    shape and a patch's result does not depend on the padding.

    Args:
      apply: ``(params, x (B, S, S, 3), material (B,) int32[, origins (B, 2)[, blur_weights]])
        -> (B, S, S, 3)``, e.g. `enhancer.make_apply` (outputs clipped to [0, 1]).
      params: its parameter pytree.
      tiles: (P, S, S, 3) RGB-form patches in [0, 1].
      material_id: int (or int32 scalar array): the material's row in the model's tables.
      batch_size: static patches per network call.
      origins: (P, 2) int32 texel origins of the patches, for models with texel noise; None
        for models without (the argument is then not passed to `apply`).
      blur_weights: None, or `batch_blur_weights` of the patches' masks: the mask-only part
        of the model's blurs, computed once for patches whose masks repeat every frame.
    Returns:
      (P, S, S, 3) enhanced patches, RGB form.
    """
    p = tiles.shape[0]
    b = int(batch_size)
    x = _batches(tiles, b)
    material = jnp.full((b,), material_id, jnp.int32)
    o = None if origins is None else _batches(jnp.asarray(origins, jnp.int32), b)
    if o is None and blur_weights is None:
        out = jax.lax.map(lambda xb: apply(params, xb, material), x)
    else:
        out = jax.lax.map(lambda a: apply(params, a[0], material, a[1], a[2]),
                          (x, o, blur_weights))
    return out.reshape(-1, *tiles.shape[1:])[:p]


def _batches(a, b: int):
    """(P, ...) -> (ceil(P / b), b, ...): zero-padded to whole batches of `b`, each row of `a`
    at a fixed position (`network_stage`'s batching)."""
    nb = -(-a.shape[0] // b)
    a = jnp.pad(a, ((0, nb * b - a.shape[0]),) + ((0, 0),) * (a.ndim - 1))
    return a.reshape(nb, b, *a.shape[1:])


@functools.partial(jax.jit, static_argnames=("unet_config", "size", "batch_size"))
def batch_blur_weights(unet_config, mask, origins, *, size: int, batch_size: int):
    """`network_stage`'s `blur_weights` for the patches at `origins`: the model's
    `UNetConfig.blur_weights` of each batch of their masks, stacked along a leading
    batch-index axis.

    Args:
      unet_config: the model's `nn.unet.UNetConfig` (static: one compile per config).
      mask: (Hp, Wp, 1) the padded map's garment mask (nonzero inside the garment).
      origins: (P, 2) int patch origins, as the network's input patches are cut (`tile_stage`;
        P may be a multiple of a frame's patches, for several frames per call).
      size: the patch size S; batch_size: the `network_stage` batch size B.
    Returns:
      a dict of (P / B rounded up, K, S, B, S) planes; {} for models without blurs.
    """
    m = (tile_stage(jnp.asarray(mask), origins, size=size) > 0).astype(jnp.float32)
    # ^ as `sharpen.mask_from_rgb` of the baked patches
    return jax.vmap(unet_config.blur_weights)(_batches(m, int(batch_size)))


def merge_stage(outputs, origins, mask, coarse_map, *, window: str = "hann",
                shape: tuple[int, int]):
    """Merge enhanced patches into the enhanced map N*.

    Patches are merged as normals with `window` weights (`patches.merge`) and renormalized;
    garment texels whose merged vector vanished (a network output of exactly mid-grey) keep
    the coarse normal, and the gutter keeps the coarse map, so N* is unit inside the mask.

    Args:
      outputs: (P, S, S, 3) enhanced patches, RGB form.
      origins: (P, 2) int32 their origins in the padded map.
      mask: (Hp, Wp, 1) float32 garment texels (padded).
      coarse_map: (Hp, Wp, 3) the frame's coarse map (`bake_stage`).
      window: "hann" or "uniform" merge weights.
      shape: static (H, W): the map's size before padding.
    Returns:
      (H, W, 3) N*: unit normals on the garment, coarse normals in the gutter, zero elsewhere.
    """
    merged, _ = patches.merge(normalmap.from_rgb(outputs), origins, coarse_map.shape,
                              window=window, mask=mask, renormalize=True)
    ok = (mask > 0) & (jnp.sum(merged * merged, -1, keepdims=True) > 0.25)
    return jnp.where(ok, merged, coarse_map)[: shape[0], : shape[1]]


def lift_stage(coarse_vertices, normal_map, subdivision, fine_garment,
               topology: lift_lib.LiftTopology, body=None,
               resolve_coarse: lift_lib.ResolveCoarse | None = None, *,
               layout: normalmap.UVLayout,
               weights: lift_lib.LiftWeights = lift_lib.LiftWeights(),  # noqa: B008
               solver: lift_lib.SolverConfig = lift_lib.SolverConfig(),  # noqa: B008
               resolve: lift_lib.ResolveConfig = lift_lib.ResolveConfig(),  # noqa: B008
               phi: float = 5e3):
    """Lift one frame: upsample the coarse frame, follow N*, push out of the body.

    Args:
      coarse_vertices: (Vc, 3) meters.
      normal_map: (H, W, 3) the enhanced map N* on `layout`.
      subdivision, fine_garment: from `lift.upsample` (the lifted mesh's topology and UVs).
      topology: `lift.lift_topology` of the fine mesh.
      body: None, or a `bodies` body (meters) the result is pushed out of; the penetration
        term exists only then, and is not differentiable in reverse mode.
      resolve_coarse: None, or `lift.resolve_coarse(subdivision, topology, phi, resolve)`
        (the push-out's coarse-grid preconditioner; used only with a body).
      layout, weights, solver, resolve, phi: static settings (see `lift.lift_from_normal_map`
        and `lift.resolve_penetration`).
    Returns:
      (V', 3) lifted vertices, meters; differentiable (without a body) with respect to the
      coarse vertices and the map, by the implicit function theorem (exact at a converged
      solve: tighten `solver` when gradients must be accurate).
    """
    p = lift_lib.lift_from_normal_map(coarse_vertices, subdivision, fine_garment, topology,
                                      normal_map, layout, weights, solver)
    if body is not None:  # the penetration term exists only when a body is given
        p = lift_lib.resolve_penetration(p, topology, body, phi, resolve, resolve_coarse)
    return p


# --------------------------------------------------------------------------------------------
# The composed frame (`pipeline.frame_fn` binds its setup)
# --------------------------------------------------------------------------------------------


class FrameResult(NamedTuple):
    """What a `frame_fn` function returns (a pytree).

    Attributes:
      normal_map: (H, W, 3) the enhanced map N* (unit normals on the garment, the coarse
        normals in the seam gutter, zero elsewhere).
      mask: (H, W, 1) float32 garment texels (a constant of the UV layout).
      detailed: (V', 3) lifted vertices, meters (topology `Pipeline.fine_garment`), or None
        when the pipeline does not lift.
    """

    normal_map: Any
    mask: Any
    detailed: Any


@dataclasses.dataclass(frozen=True)
class _FrameStatic:
    """The static (hashable) settings of `_frame`: the stages' keyword arguments."""

    apply: Callable
    smooth: bool
    padded_shape: tuple[int, int]
    shape: tuple[int, int]
    size: int
    batch_size: int
    window: str
    noise: bool
    lift: tuple | None  # lift_stage's static keywords as sorted (name, value) items, or None

    def lift_kwargs(self) -> dict:
        return dict(self.lift)


@functools.partial(jax.jit, static_argnames=("static",))
def _frame(setup: dict, params, coarse_vertices, material_id, static: _FrameStatic):
    """bake -> tile -> network -> merge (-> lift) of one frame; `setup` holds the arrays (plan,
    padded_mask, blur_weights, origins, mask, subdivision, fine_garment, topology, body,
    resolve_coarse)."""
    coarse_map, rgb = bake_stage(setup["plan"], coarse_vertices, setup["padded_mask"],
                                 smooth=static.smooth, padded_shape=static.padded_shape)
    tiles = tile_stage(rgb, setup["origins"], size=static.size)
    out = network_stage(static.apply, params, tiles, material_id, batch_size=static.batch_size,
                        origins=setup["origins"] if static.noise else None,
                        blur_weights=setup["blur_weights"])
    normal_map = merge_stage(out, setup["origins"], setup["padded_mask"], coarse_map,
                             window=static.window, shape=static.shape)
    detailed = None
    if static.lift is not None:
        detailed = lift_stage(coarse_vertices, normal_map, setup["subdivision"],
                              setup["fine_garment"], setup["topology"], setup["body"],
                              setup["resolve_coarse"], **static.lift_kwargs())
    return FrameResult(normal_map, setup["mask"], detailed)


# --------------------------------------------------------------------------------------------
# Jitted forms used by the streaming pipeline (a chunk of C frames at a time)
# --------------------------------------------------------------------------------------------


@functools.partial(jax.jit, static_argnames=("smooth", "padded_shape"))
def _bake_chunk(plan, frames, mask, smooth: bool, padded_shape: tuple[int, int]):
    """`bake_stage` over a chunk: (C, Vc, 3) -> (C, Hp, Wp, 3) twice."""
    return jax.vmap(lambda v: bake_stage(plan, v, mask, smooth=smooth,
                                         padded_shape=padded_shape))(frames)


@functools.partial(jax.jit, static_argnames=("size",))
def _extract_chunk(images, origins, size: int):
    """`tile_stage` over a chunk: (C, Hp, Wp, 3) -> (C, P, size, size, 3)."""
    return jax.vmap(lambda im: tile_stage(im, origins, size=size))(images)


# One frame's patches per call (a frame's batches never mix with another frame's).
_network_frame = jax.jit(network_stage, static_argnames=("apply", "batch_size"))


@functools.partial(jax.jit, static_argnames=("window", "shape"))
def _merge_chunk(outputs, origins, mask, coarse, window: str, shape: tuple[int, int]):
    """`merge_stage` over a chunk: (C, P, S, S, 3) -> N* (C, H, W, 3)."""
    return jax.vmap(lambda out, base: merge_stage(out, origins, mask, base, window=window,
                                                  shape=shape))(outputs, coarse)


_lift_frame = jax.jit(lift_stage, static_argnames=("layout", "weights", "solver", "resolve",
                                                   "phi"))


# --------------------------------------------------------------------------------------------
# Warm-started lifting of a stream of frames
# --------------------------------------------------------------------------------------------


def local_frames(vertices, topology: lift_lib.LiftTopology):
    """(V, 3, 3) orthonormal frames, rows (tangent, bitangent, normal), at every vertex.

    The normal is the area-weighted vertex normal; the tangent is the edge to the first
    one-ring neighbour projected onto the tangent plane, so the frame turns with the surface
    and is a function of the mesh alone (a vertex without neighbours gets a zero tangent
    plane: its offsets keep only their normal part).
    """
    n = mesh.vertex_normals(vertices, topology.faces)
    e = vertices[topology.neighbors[:, 0]] - vertices
    t = normalize(e - jnp.sum(e * n, -1, keepdims=True) * n)
    return jnp.stack([t, jnp.cross(n, t), n], -2)


def to_local(offsets, frames):
    """(V, 3) world offsets -> (V, 3) components in `frames` ((V, 3, 3), `local_frames`)."""
    return jnp.einsum("vij,vj->vi", frames, offsets)


def from_local(local, frames):
    """Inverse of `to_local`: (V, 3) frame components -> (V, 3) world offsets."""
    return jnp.einsum("vij,vi->vj", frames, local)


def _lift_warm(coarse_vertices, normal_map, local, subdivision, fine_garment, topology,
               body=None, resolve_coarse=None, *, layout, weights, solver, resolve, phi):
    """`lift_stage` started from the previous frame's solution, carried in local coordinates.

    The lifted detail of consecutive frames is nearly the same *relative to the coarse
    surface*, not in world space (the garment moves), so the carried state is the previous
    frame's offsets p - p0 expressed in p0's `local_frames`; this frame starts at
    p0 + those offsets in its own frames (`lift.lift` falls back to p0 when that guess has the
    higher energy). Zero offsets are a cold start.

    Args:
      local: (V', 3) the previous frame's offsets in its local frames, meters (zeros: none).
      the rest: as `lift_stage`.
    Returns:
      (detailed (V', 3) meters, this frame's local offsets (V', 3) meters, LiftInfo); the
      offsets are those of the lift itself, before any body push-out.
    """
    p0 = subdivision.apply(coarse_vertices)
    n = lift_lib.sample_target_normals(normal_map, fine_garment, layout)
    frames = local_frames(p0, topology)  # this frame's: they place the start and carry p - p0
    p, info = lift_lib.lift_with_info(p0, topology, n, weights, solver,
                                      start=p0 + from_local(local, frames))
    carried = to_local(p - p0, frames)
    if body is not None:
        p = lift_lib.resolve_penetration(p, topology, body, phi, resolve, resolve_coarse)
    return p, carried, info


_lift_frame_warm = jax.jit(_lift_warm, static_argnames=("layout", "weights", "solver",
                                                        "resolve", "phi"))

_APPLY_CACHE: dict = {}


def _network_apply(enh: enhancer_lib.Enhancer):
    """`enhancer.make_apply` shared by every pipeline with the same model (one compile)."""
    key = (enh.config, type(enh.model), getattr(enh.model, "conv_impl", None))
    if key not in _APPLY_CACHE:
        _APPLY_CACHE[key] = enhancer_lib.make_apply(enh)
    return _APPLY_CACHE[key]
