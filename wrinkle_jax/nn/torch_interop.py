"""Conversion of the authors' PyTorch U-Net weights to ours (`unet.CINUNet`).

`from_torch_state_dict` converts the authors' PyTorch state dict (modules
`E1_Conv2d`..`E4_Conv2d`, `D1_Deconv2d`..`D4_Deconv2d`, `D{1..4}_CIN.inns.{k}.weight|bias`,
`out_Conv2d`) into our parameters; `load_torch_checkpoint` reads their `torch.save` file through
the safe, torch-free reader. Their network normalizes its input with the ImageNet statistics
and has no global residual, and its output is in the same ImageNet-normalized units as its
input (nothing in it undoes the input normalization): `from_torch_state_dict`'s config sets
`input_norm="imagenet", residual=False, output_norm="imagenet"`, so the converted network
outputs the RGB form in [0, 1] like ours (`enhancer.from_torch_checkpoint` makes a
pipeline-ready model of it).
"""

from __future__ import annotations

import os

import jax
import numpy as np

from wrinkle_jax.nn.unet import NUM_LEVELS, CINUNet, UNetConfig
from wrinkle_jax.numerics import to_device


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
      (params, kwargs): params for `CINUNet`, and the constructor arguments that reproduce the
      authors' forward pass, ``CINUNet(**kwargs)``: `num_materials` and a `config` (UNetConfig)
      with the width read from the weights, input_norm="imagenet", residual=False, and
      output_norm="imagenet" (its ImageNet-normalized output de-normalized to the RGB form).
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
    # One host-to-device copy per leaf, no one-op compile per leaf shape (`to_device`).
    params = to_device(jax.tree_util.tree_map(np.ascontiguousarray, params))
    config = UNetConfig(width=width, input_norm="imagenet", residual=False,
                        output_norm="imagenet")
    return params, dict(num_materials=int(num_materials), config=config)


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
