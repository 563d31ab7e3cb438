"""The material-conditioned U-Net that enhances normal-map patches (paper Sec. 4).

Architecture (paper, "Network architecture", and the authors' published network), for
`width` w and 128 x 128 patches:

    input (N,128,128,3) RGB form of a normal map in [0, 1]
      -> [optional ImageNet mean/std normalization of the input, as the authors' code does]
    encoder, 4 x: 3x3 conv (zero padding) -> ReLU -> 2x2 max-pool
      channels w, 2w, 4w, 8w; sizes 128 -> 64 -> 32 -> 16 -> 8
      (the post-ReLU, pre-pool activations are the skips s1..s4)
    decoder, 4 x: 4x4 stride-2 transposed conv -> add skip -> CIN(material) -> ReLU
      channels 8w, 4w, 2w, w (skips s4, s3, s2, s1); sizes 8 -> 16 -> 32 -> 64 -> 128
    3x3 conv to 3 channels  [+ input, with `residual=True`]

With width=64 and 5 materials the network has 8,510,083 parameters.

Conditional instance normalization (Dumoulin et al. 2017): per-material scale and shift
tables gathered by the material id of each sample, so one batch may mix materials; the
normalization layer is injected as `norm` (a `functools.partial`, like BatchNorm in the Flax
ImageNet example). The variance is guarded by `eps`, so constant patches stay finite.

Interop: `from_torch_state_dict` converts the authors' PyTorch state dict (modules
`E1_Conv2d`..`E4_Conv2d`, `D1_Deconv2d`..`D4_Deconv2d`, `D{1..4}_CIN.inns.{k}.weight|bias`,
`out_Conv2d`) into our parameters; `load_torch_checkpoint` reads their `torch.save` file through
the safe, torch-free reader. Their network normalizes its input with the ImageNet statistics
and has no global residual: use `CINUNet(input_norm="imagenet", residual=False)`.
"""

from __future__ import annotations

import functools
import os
from collections.abc import Callable

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)
NUM_LEVELS = 4


class CIN(nn.Module):
    """Conditional instance normalization over (H, W), per sample and channel.

    Attributes:
      num_materials: rows of the scale/shift tables.
      eps: variance guard (PyTorch's InstanceNorm2d default, so converted weights match).
    """

    num_materials: int
    eps: float = 1e-5

    @nn.compact
    def __call__(self, x, material):
        """x: (N, H, W, C) float; material: (N,) int32 ids -> (N, H, W, C)."""
        c = x.shape[-1]
        scale = self.param("scale", nn.initializers.ones, (self.num_materials, c), jnp.float32)
        shift = self.param("shift", nn.initializers.zeros, (self.num_materials, c), jnp.float32)
        x32 = x.astype(jnp.float32)
        mean = jnp.mean(x32, axis=(1, 2), keepdims=True)
        var = jnp.mean(jnp.square(x32 - mean), axis=(1, 2), keepdims=True)  # biased, as torch
        y = (x32 - mean) * jax.lax.rsqrt(var + self.eps)
        gamma = scale[material][:, None, None, :]
        beta = shift[material][:, None, None, :]
        return (y * gamma + beta).astype(x.dtype)


class CINUNet(nn.Module):
    """Material-conditioned U-Net (see the module docstring).

    Attributes:
      num_materials: number of materials the CIN tables hold.
      width: channels of the first level (w); the levels use w, 2w, 4w, 8w.
      residual: return input + network output (a global residual) instead of the output.
      input_norm: "imagenet" (normalize RGB by ImageNet mean/std, as the authors do) or "none".
      norm: the conditional normalization layer factory (called with num_materials).
      dtype: computation dtype of convolutions (parameters stay float32).
    """

    num_materials: int = 5
    width: int = 64
    residual: bool = False
    input_norm: str = "imagenet"
    norm: Callable[..., nn.Module] = CIN
    dtype: jnp.dtype = jnp.float32

    @nn.compact
    def __call__(self, x, material):
        """Enhance patches.

        Args:
          x: (N, H, W, 3) float, RGB form of normal-map patches in [0, 1]; H and W divisible
            by 16 (128 in the paper).
          material: (N,) int material ids (see `wrinkle_jax.MATERIALS`).
        Returns:
          (N, H, W, 3) float32 enhanced patches in the same RGB form (not clipped).
        """
        if x.shape[1] % 16 or x.shape[2] % 16:
            raise ValueError(f"patch size must be divisible by 16, got {x.shape[1:3]}")
        material = jnp.asarray(material, jnp.int32).reshape(x.shape[0])
        h = x.astype(jnp.float32)
        if self.input_norm == "imagenet":
            h = (h - jnp.asarray(IMAGENET_MEAN)) / jnp.asarray(IMAGENET_STD)
        elif self.input_norm != "none":
            raise ValueError(f"unknown input_norm {self.input_norm!r}")
        conv = functools.partial(nn.Conv, kernel_size=(3, 3), padding=((1, 1), (1, 1)),
                                 dtype=self.dtype)
        skips = []
        for level in range(NUM_LEVELS):
            h = nn.relu(conv(self.width * 2**level, name=f"enc{level + 1}")(h))
            skips.append(h)
            h = nn.max_pool(h, (2, 2), strides=(2, 2))
        for level in reversed(range(NUM_LEVELS)):
            # PyTorch ConvTranspose2d(k=4, s=2, p=1) == a conv of the 2x-dilated input with
            # padding k - 1 - p = 2 on each side (kernel stored flipped; see from_torch).
            h = nn.ConvTranspose(self.width * 2**level, (4, 4), strides=(2, 2),
                                 padding=((2, 2), (2, 2)), dtype=self.dtype,
                                 name=f"dec{NUM_LEVELS - level}")(h)
            h = h + skips[level]
            h = self.norm(num_materials=self.num_materials, name=f"cin{NUM_LEVELS - level}")(
                h, material)
            h = nn.relu(h)
        out = conv(3, name="out")(h).astype(jnp.float32)
        return x.astype(jnp.float32) + out if self.residual else out


def count_params(params) -> int:
    """Total number of scalars in a parameter pytree."""
    return int(sum(np.prod(p.shape) for p in jax.tree_util.tree_leaves(params)))


def init_params(model: CINUNet, key, patch_size: int = 128):
    """Initialize parameters for (N, patch_size, patch_size, 3) inputs (jitted).

    Note: with jaxlib 0.10 on CPU, compiling many threefry draws is slow (about 10 s for this
    network); a key made with `jax.random.key(seed, impl="rbg")` compiles about 8x faster.
    """
    x = jnp.zeros((1, patch_size, patch_size, 3), jnp.float32)
    init = jax.jit(lambda k: model.init(k, x, jnp.zeros((1,), jnp.int32))["params"])
    return init(key)


# --------------------------------------------------------------------------------------------
# PyTorch interop
# --------------------------------------------------------------------------------------------


class StateDictError(ValueError):
    """A state dict does not match the authors' U-Net layout (names the missing/odd key)."""


def _get(sd: dict, key: str, shape_len: int) -> np.ndarray:
    if key not in sd:
        raise StateDictError(f"state dict has no {key!r}")
    a = np.asarray(sd[key], np.float32)
    if a.ndim != shape_len:
        raise StateDictError(f"{key}: expected {shape_len} dimensions, got shape {a.shape}")
    return a


def from_torch_state_dict(state_dict: dict) -> tuple[dict, dict]:
    """Convert the authors' PyTorch U-Net state dict to our parameters.

    Layouts: PyTorch convs are OIHW -> HWIO; transposed convs are (in, out, kH, kW) -> HWIO
    with the kernel flipped spatially (PyTorch's transposed conv correlates the dilated input
    with the flipped kernel); CIN tables stack `D{l}_CIN.inns.{k}` over materials k.

    Returns:
      (params, config): params for `CINUNet`, and the constructor arguments that reproduce the
      authors' forward pass (width and material count read from the weights,
      input_norm="imagenet", residual=False).
    """
    sd = {k.removeprefix("module."): v for k, v in state_dict.items()}
    params: dict = {}
    w1 = _get(sd, "E1_Conv2d.weight", 4)
    width = int(w1.shape[0])
    for level in range(1, NUM_LEVELS + 1):
        w = _get(sd, f"E{level}_Conv2d.weight", 4)
        params[f"enc{level}"] = {"kernel": w.transpose(2, 3, 1, 0),
                                 "bias": _get(sd, f"E{level}_Conv2d.bias", 1)}
        d = _get(sd, f"D{level}_Deconv2d.weight", 4)
        params[f"dec{level}"] = {"kernel": d[:, :, ::-1, ::-1].transpose(2, 3, 0, 1),
                                 "bias": _get(sd, f"D{level}_Deconv2d.bias", 1)}
        ks = sorted({int(k.split(".")[2]) for k in sd if k.startswith(f"D{level}_CIN.inns.")})
        if not ks or ks != list(range(len(ks))):
            raise StateDictError(f"D{level}_CIN.inns.* must hold materials 0..K-1, got {ks}")
        params[f"cin{level}"] = {
            "scale": np.stack([_get(sd, f"D{level}_CIN.inns.{k}.weight", 1) for k in ks]),
            "shift": np.stack([_get(sd, f"D{level}_CIN.inns.{k}.bias", 1) for k in ks]),
        }
    params["out"] = {"kernel": _get(sd, "out_Conv2d.weight", 4).transpose(2, 3, 1, 0),
                     "bias": _get(sd, "out_Conv2d.bias", 1)}
    num_materials = params["cin1"]["scale"].shape[0]
    params = jax.tree_util.tree_map(lambda a: jnp.asarray(np.ascontiguousarray(a)), params)
    config = dict(num_materials=int(num_materials), width=width, input_norm="imagenet",
                  residual=False)
    return params, config


def load_torch_checkpoint(path: str | os.PathLike) -> tuple[CINUNet, dict]:
    """Load the authors' `torch.save` checkpoint (a dict whose 'model' entry is the U-Net's
    state dict) without PyTorch, through the allow-listed reader.

    Returns:
      (model, params) ready for `model.apply({"params": params}, x, material)`.
    """
    from wrinkle_jax.io import torch_pickle

    flat = torch_pickle.load(path)
    sd = {k.removeprefix("model."): v for k, v in flat.items() if k.startswith("model.")}
    if not sd:  # a bare state dict
        sd = flat
    try:
        params, config = from_torch_state_dict(sd)
    except StateDictError as e:
        raise StateDictError(f"{path}: {e}") from None
    return CINUNet(**config), params
