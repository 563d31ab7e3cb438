"""A trained enhancer as one portable file: save, load, and apply to patches.

The shipped default lives at ``wrinkle_jax/assets/enhancer.npz`` and is loaded by
:func:`load_enhancer` with no arguments. The file is a plain ``.npz`` (no pickle):

    params/<module>/<leaf>   float16 (or float32) arrays of the CINUNet parameter pytree
    config.json              uint8 bytes of the JSON :class:`EnhancerConfig`
    meta.json                uint8 bytes of free-form JSON (training data, steps, scores, ...)

Parameters are stored in float16 to keep the package small (the U-Net's weights are far inside
float16's range; the rounding, ~5e-4 relative, is below the bfloat16 rounding of the fast
inference convolutions) and are cast back to float32 on load.

Example:
    >>> import jax, numpy as np
    >>> enh = init_enhancer(jax.random.key(0, impl="rbg"),
    ...                     EnhancerConfig(unet=unet.UNetConfig(width=4)))
    >>> apply = make_apply(enh)
    >>> out = apply(enh.params, np.full((2, 32, 32, 3), 0.5, np.float32), np.array([0, 3]))
    >>> out.shape
    (2, 32, 32, 3)
"""

from __future__ import annotations

import dataclasses
import os
import time
from pathlib import Path
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from wrinkle_jax import MATERIALS, hostcpu, modelfile, normalmap
from wrinkle_jax.nn import torch_interop, unet
from wrinkle_jax.numerics import to_device

__all__ = ["DEFAULT_PATH", "Enhancer", "EnhancerConfig", "EnhancerError", "from_torch_checkpoint",
           "init_enhancer", "load_enhancer", "make_apply", "save_enhancer"]

DEFAULT_PATH = Path(__file__).resolve().parent / "assets" / "enhancer.npz"
_FORMAT = "wrinkle-jax-enhancer/1"
# Loaded models of at least this width run a Winograd form (`inference_conv_impl`).
WINOGRAD_MIN_WIDTH = hostcpu.WINOGRAD_MIN_WIDTH


def inference_conv_impl(config: unet.UNetConfig, environ=None) -> str:
    """The U-Net form a loaded model runs in by default. On a CPU with bfloat16 dot units
    (`hostcpu.native_bf16_dots`; `environ` as there): "winograd_bf16" from width
    `WINOGRAD_MIN_WIDTH` (forward per 16 patches, quiet, session 26: width 32 115.7 -> 103.5 ms,
    width 64 1.25x), else "im2col_bf16": at the shipped width 16 only two small layers qualify,
    the forward gained 0-8 % in repeated runs, and the Winograd program compiles ~0.8 s
    longer. Elsewhere the float32 forms, "winograd_f32" from the same width: emulated
    bfloat16 dots are slower than float32 ones (AVX2-only EPYC, session 46, batch 8, 3
    alternating rounds: width 64 winograd_f32 35-46, winograd_bf16 48-50, im2col_f32 61-72,
    xla 74-79 ms/patch; width 16 im2col_f32 8.6-11.4, winograd_f32 7.6-11.3)."""
    if hostcpu.native_bf16_dots(environ) and config.width >= WINOGRAD_MIN_WIDTH:
        return "winograd_bf16"
    return hostcpu.fast_conv_impl(config.width, environ)


class EnhancerError(ValueError):
    """An enhancer file is missing, unreadable or inconsistent (the message names the file)."""


@dataclasses.dataclass(frozen=True)
class EnhancerConfig:
    """What a model needs at inference.

    Attributes:
      unet: the U-Net's architecture (`nn.unet.UNetConfig`).
      materials: material names in the order of the CIN tables.
      patch_size: patch side in texels the model was trained on.
      texel_size: meters of cloth per texel of the normal maps it was trained on.
      coarse_pd: particle distance (m) of the coarse inputs it was trained for.
    """

    unet: unet.UNetConfig = unet.UNetConfig(width=32)
    materials: tuple[str, ...] = MATERIALS
    patch_size: int = 128
    texel_size: float = normalmap.DEFAULT_TEXEL_SIZE
    coarse_pd: float = 0.03

    def model(self, conv_impl: str | None = None) -> unet.CINUNet:
        """The U-Net in `conv_impl` (None: `inference_conv_impl`)."""
        return self.unet.module(len(self.materials), conv_impl or inference_conv_impl(self.unet))

    def material_id(self, name: str) -> int:
        if name not in self.materials:
            raise ValueError(f"unknown material {name!r}; this model knows "
                             f"{', '.join(self.materials)}")
        return self.materials.index(name)

    def to_json(self) -> dict:
        """Flat: the U-Net's settings among the model's own fields (the model-file format)."""
        own = {f.name: getattr(self, f.name) for f in dataclasses.fields(self) if f.name != "unet"}
        return {**self.unet.to_json(), **own}

    @classmethod
    def from_json(cls, d: dict) -> EnhancerConfig:
        """Read `to_json`'s form, including model files written before `unet` was nested."""
        net, rest = unet.UNetConfig.split_json(d, cls.__dataclass_fields__["unet"].default)
        names = {f.name for f in dataclasses.fields(cls)} - {"unet"}
        unknown = set(rest) - names
        if unknown:
            raise ValueError(f"unknown enhancer config fields {sorted(unknown)}")
        rest["materials"] = tuple(rest["materials"])
        return cls(unet=net, **rest)


class Enhancer(NamedTuple):
    """A ready-to-apply model: `model.apply({"params": params}, x, material_ids)`."""

    model: unet.CINUNet
    params: Any
    config: EnhancerConfig
    meta: dict


def init_enhancer(key, config: EnhancerConfig = EnhancerConfig(), conv_impl: str = "auto",
                  meta: dict | None = None) -> Enhancer:
    """An untrained enhancer (random parameters) -- for tests and as a training start."""
    model = config.model(conv_impl)
    params = unet.init_params(model, key, config.patch_size)
    return Enhancer(model, params, config, dict(meta or {}))


def with_unet(enh: Enhancer, **changes) -> Enhancer:
    """`enh` with U-Net settings changed that keep its parameters valid (e.g.
    ``residual_gain=0.5``: the same network adding half its residual); same conv form."""
    config = dataclasses.replace(enh.config,
                                 unet=dataclasses.replace(enh.config.unet, **changes))
    return Enhancer(config.model(enh.model.conv_impl), enh.params, config, enh.meta)


def save_enhancer(path: str | os.PathLike, params, config: EnhancerConfig,
                  meta: dict | None = None, dtype=np.float16) -> Path:
    """Write `params` (a CINUNet pytree), `config` and `meta` to `path` atomically.

    Raises:
      EnhancerError: if a parameter does not fit `dtype` (non-finite after the cast).
    """
    path = Path(path)
    arrays = modelfile.cast_params(params, dtype, path, EnhancerError)
    return modelfile.write(path, arrays, config.to_json(), meta or {}, _FORMAT)


def load_enhancer(path: str | os.PathLike | None = None,
                  conv_impl: str | None = None) -> Enhancer:
    """Load an enhancer file (default: the shipped model).

    Args:
      path: an ``.npz`` written by :func:`save_enhancer`; None for ``DEFAULT_PATH``.
      conv_impl: the U-Net's convolution form: None picks by the CPU and the width
        (`inference_conv_impl`); "winograd_bf16" (fastest from width 32 on CPUs with bfloat16
        dot units) or "im2col_bf16"; "im2col_f32" or "xla" exact; "auto" as in `nn.unet`.
        The parameters are the same for all forms.

    Raises:
      EnhancerError: naming the file, if it is missing, not an enhancer file, or its
        parameters do not match its config.
    """
    path = Path(DEFAULT_PATH if path is None else path)
    if not path.is_file():
        hint = (" (the shipped model is built by `python -m experiments.train_default`)"
                if path == DEFAULT_PATH else "")
        raise EnhancerError(f"{path}: no such enhancer file{hint}")
    files, config, meta = modelfile.read(path, "enhancer", _FORMAT, EnhancerError)
    try:
        config = EnhancerConfig.from_json(config)
    except (TypeError, ValueError, KeyError) as e:
        raise EnhancerError(f"{path}: not a readable enhancer file ({e})") from None
    flat = modelfile.float32_params(files)
    params = to_device(modelfile.unflatten(flat))  # one copy, no per-leaf compile
    model = config.model(conv_impl)
    want = jax.eval_shape(lambda: unet.init_params(model, jax.random.key(0, impl="rbg"),
                                                   config.patch_size))
    want_shapes = modelfile.flatten(want, lambda s: tuple(s.shape))
    got_shapes = {k: v.shape for k, v in flat.items()}
    if want_shapes != got_shapes:
        missing = sorted(set(want_shapes) - set(got_shapes))[:3]
        wrong = sorted(k for k in set(want_shapes) & set(got_shapes)
                       if want_shapes[k] != got_shapes[k])[:3]
        raise EnhancerError(f"{path}: parameters do not match the config (width "
                            f"{config.unet.width}); missing {missing}, wrong shape {wrong}")
    return Enhancer(model, params, config, meta)


def from_torch_checkpoint(path: str | os.PathLike, materials: tuple[str, ...] | None = None, *,
                          patch_size: int = 128,
                          texel_size: float = normalmap.DEFAULT_TEXEL_SIZE,
                          conv_impl: str | None = None) -> Enhancer:
    """The authors' PyTorch U-Net checkpoint as a pipeline-ready enhancer (no torch needed).

    The weights are converted by `torch_interop.load_torch_checkpoint` (the allow-listed
    reader). Their network takes ImageNet-normalized RGB and outputs ImageNet-normalized RGB;
    the config records both (`UNetConfig(input_norm="imagenet", output_norm="imagenet",
    residual=False)`), so the model normalizes its input and de-normalizes its output to the RGB
    form in [0, 1] inside its own forward pass -- exactly once, wherever it is applied
    (`make_apply`, the pipeline, a model file written by `save_enhancer` and read back).

    Args:
      path: the `torch.save` file (a dict with a "model" state dict, or a bare state dict).
      materials: names of the checkpoint's CIN rows, in order; None means `MATERIALS` and
        needs a checkpoint with exactly that many rows.
      patch_size: patch side (texels) to tile with; any multiple of 16 runs.
      texel_size: meters of cloth per texel of the maps it is given (the checkpoint does not
        record the scale it was trained at; the default is this package's).
      conv_impl: the convolution form (see `load_enhancer`).
    Raises:
      torch_interop.StateDictError: naming the file, if the weights are not the authors' U-Net.
      EnhancerError: the number of materials does not match the checkpoint's CIN tables.
      io.torch_pickle.CheckpointError: the file is not a readable PyTorch checkpoint
        (`UnsafeCheckpointError`, a subclass: it names a global outside the allow-list).
    """
    net, params = torch_interop.load_torch_checkpoint(path)
    if materials is None:
        materials = MATERIALS
        if net.num_materials != len(MATERIALS):
            raise EnhancerError(f"{path}: the checkpoint has {net.num_materials} materials, "
                                f"this package {len(MATERIALS)}; pass their names as "
                                "`materials`")
    materials = tuple(materials)
    if len(materials) != net.num_materials:
        raise EnhancerError(f"{path}: {len(materials)} material names for a checkpoint with "
                            f"{net.num_materials} materials")
    config = EnhancerConfig(unet=net.config, materials=materials, patch_size=int(patch_size),
                            texel_size=float(texel_size))
    meta = {"source": f"converted from the PyTorch checkpoint {Path(path).name}"}
    return Enhancer(config.model(conv_impl), params, config, meta)


def make_apply(enhancer: Enhancer, clip: bool = True):
    """Jitted ``(params, x (N, H, W, 3) RGB-form patches, material (N,) int[, origins (N, 2)
    int[, blur_weights]]) -> (N, H, W, 3)``; `origins` (the patches' texel positions in their
    UV layout) feed the texel noise of models that have it, and are ignored otherwise;
    `blur_weights` (``enhancer.config.unet.blur_weights(mask)``, optional) are the mask-only
    part of the model's blurs, for patches whose masks repeat (the pipeline's).

    With `clip`, outputs are clipped to [0, 1] (the RGB form of unit normals); the parameters
    are an argument (not a closed-over constant), so one compile serves any weights of the same
    shapes and gradients flow to them.
    """
    model = enhancer.model

    @jax.jit
    def apply(params, x, material, origins=None, blur_weights=None):
        # Passed only when given: other modules (a user's, a test's) need not take them.
        extra = () if blur_weights is None else (blur_weights,)
        out = model.apply({"params": params}, x, material, origins, *extra)
        return jnp.clip(out, 0.0, 1.0) if clip else out

    return apply


def enhance_patches(apply, params, inputs, materials, mask, batch_size: int = 16,
                    timings: dict | None = None, origins=None) -> np.ndarray:
    """Run a model over patches in fixed-shape batches; unit normals inside the mask.

    Args:
      apply: jitted ``(params, x (B, S, S, 3), material (B,)) -> (B, S, S, 3)`` RGB-form
        outputs, e.g. `make_apply(enhancer)`; every call has batch `batch_size` (the last
        batch repeats patches), so it compiles once.
      params: its parameters.
      inputs: (N, S, S, 3) RGB-form patches in [0, 1].
      materials: an int, or (N,) ints: material ids of the model.
      mask: (N, S, S, 1) garment mask (1 inside).
      batch_size: patches per call.
      timings: accumulates "network_s" (seconds in the network) and "network_patches".
      origins: optional (N, 2) int texel positions of the patches (for texel-noise models).
    Returns:
      (N, S, S, 3) float32 RGB form: the output renormalized to unit normals inside the mask
      (as the pipeline's merge does), 0 outside.
    """
    inputs = np.asarray(inputs, np.float32)
    n = len(inputs)
    mats = np.broadcast_to(np.asarray(materials, np.int32), (n,))
    outs = []
    t0 = time.perf_counter()
    for s in range(0, n, batch_size):
        idx = np.resize(np.arange(s, min(s + batch_size, n)), batch_size)
        if origins is None:
            o = apply(params, jnp.asarray(inputs[idx]), jnp.asarray(mats[idx]))
        else:
            o = apply(params, jnp.asarray(inputs[idx]), jnp.asarray(mats[idx]),
                      jnp.asarray(np.asarray(origins, np.int32)[idx]))
        outs.append(np.asarray(o)[:min(batch_size, n - s)])
    if timings is not None:
        timings["network_s"] = timings.get("network_s", 0.0) + time.perf_counter() - t0
        timings["network_patches"] = timings.get("network_patches", 0) + n
    if not outs:
        return np.zeros_like(inputs)
    nrm = np.concatenate(outs) * 2.0 - 1.0
    nrm = nrm / np.maximum(np.linalg.norm(nrm, axis=-1, keepdims=True), 1e-8)
    return ((nrm + 1.0) * 0.5 * np.asarray(mask, np.float32)).astype(np.float32)
