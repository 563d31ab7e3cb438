"""The pipeline's jitted stages (module level, so their compile caches are shared by every
pipeline in the process): bake, tile, merge and lift a chunk of frames, and the U-Net's apply.

Moved out of `wrinkle_jax.pipeline` unchanged; `pipeline` streams frames through them.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp

from wrinkle_jax import enhancer as enhancer_lib
from wrinkle_jax import lift as lift_lib
from wrinkle_jax import normalmap, patches


@functools.partial(jax.jit, static_argnames=("smooth", "padded_shape"))
def _bake_chunk(plan, frames, mask, smooth: bool, padded_shape: tuple[int, int]):
    """(C, V, 3) frames -> coarse maps (C, Hp, Wp, 3) with gutter, and the network input
    (C, Hp, Wp, 3) in the RGB form, zero off the garment (as the training inputs)."""
    maps = normalmap.bake_frames(plan, frames, smooth)
    h, w = maps.shape[1:3]
    maps = jnp.pad(maps, ((0, 0), (0, padded_shape[0] - h), (0, padded_shape[1] - w), (0, 0)))
    return maps, normalmap.to_rgb(maps) * mask


@functools.partial(jax.jit, static_argnames=("size",))
def _extract_chunk(images, origins, size: int):
    """(C, Hp, Wp, 3) -> (C, P, size, size, 3) patches at the same origins in every frame."""
    return jax.vmap(lambda im: patches.extract(im, origins, size))(images)


@functools.partial(jax.jit, static_argnames=("window", "shape"))
def _merge_chunk(outputs, origins, mask, coarse, window: str, shape: tuple[int, int]):
    """Enhanced RGB patches (C, P, S, S, 3) -> N* (C, H, W, 3).

    Patches are merged as normals with `window` weights and renormalized; garment texels
    whose merged vector vanished (a network output of exactly mid-grey) keep the coarse
    normal, and the gutter keeps the coarse map, so the result is unit inside the mask.
    """
    inside = mask > 0

    def one(out, base):
        merged, _ = patches.merge(normalmap.from_rgb(out), origins, base.shape, window=window,
                                  mask=mask, renormalize=True)
        ok = inside & (jnp.sum(merged * merged, -1, keepdims=True) > 0.25)
        return jnp.where(ok, merged, base)

    return jax.vmap(one)(outputs, coarse)[:, : shape[0], : shape[1]]


@functools.partial(jax.jit, static_argnames=("layout", "weights", "solver", "resolve", "phi"))
def _lift_frame(coarse, normal_map, subdivision, fine_garment, topology, body, layout,
                weights, solver, resolve, phi):
    """(Vc, 3) coarse frame + N* (H, W, 3) -> (V', 3) lifted (and de-penetrated) vertices."""
    p = lift_lib.lift_from_normal_map(coarse, subdivision, fine_garment, topology, normal_map,
                                      layout, weights, solver)
    if body is not None:  # the penetration term exists only when a body is given
        p = lift_lib.resolve_penetration(p, topology, body, phi, resolve)
    return p


_APPLY_CACHE: dict = {}


def _network_apply(enh: enhancer_lib.Enhancer):
    """`enhancer.make_apply` shared by every pipeline with the same model (one compile)."""
    key = (enh.config, getattr(enh.model, "conv_impl", None))
    if key not in _APPLY_CACHE:
        _APPLY_CACHE[key] = enhancer_lib.make_apply(enh)
    return _APPLY_CACHE[key]
