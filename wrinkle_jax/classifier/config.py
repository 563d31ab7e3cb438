"""The classifier's static configuration, its feature specs and errors."""

from __future__ import annotations

import dataclasses

from wrinkle_jax import MATERIALS
from wrinkle_jax.nn import vgg

REDUCTIONS = ("grid4", "stats")
GRID = 4  # cells per side of the "grid4" reduction


class ClassifierError(ValueError):
    """A classifier file is missing, unreadable or inconsistent, or a sequence cannot be
    classified (the message names the file or the problem)."""


@dataclasses.dataclass(frozen=True)
class ClassifierConfig:
    """What a classifier needs at inference (static, hashable).

    Attributes:
      feature: ``"<vgg layer>:<grid4|stats>"`` (see the module docstring).
      hidden: widths of the three hidden Dense layers.
      dropout: dropout rate after each hidden layer (training only).
      materials: material names in output order.
      patch_size: patch side in texels.
      texel_size: meters of cloth per texel of the baked coarse maps.
      min_coverage: minimum fraction of garment texels in a sampled patch.
      downsample_factor: coarse PD / fine PD used to make coarse-looking maps from fine
        simulations for training (`normalmap.downsample_like_coarse`).
      normal_frame: "object" (normals as baked) or "patch" (each patch rotated so its mean
        normal is +z, see `to_patch_frame`).
    """

    feature: str = "relu4_1:stats"
    hidden: tuple[int, ...] = (256, 128, 64)
    dropout: float = 0.3
    materials: tuple[str, ...] = MATERIALS
    patch_size: int = 128
    texel_size: float = 0.004
    min_coverage: float = 0.09
    downsample_factor: float = 3.0
    normal_frame: str = "object"

    def __post_init__(self):
        _parse_feature(self.feature)  # raises on a malformed spec
        if len(self.hidden) != 3:
            raise ValueError(f"hidden must give 3 widths (4 Dense layers), got {self.hidden}")
        if not 0.0 <= self.dropout < 1.0:
            raise ValueError(f"dropout must be in [0, 1), got {self.dropout}")
        if self.normal_frame not in ("object", "patch"):
            raise ValueError(f"normal_frame must be 'object' or 'patch', got "
                             f"{self.normal_frame!r}")

    def to_json(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_json(cls, d: dict) -> ClassifierConfig:
        d = dict(d)
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = set(d) - names
        if unknown:
            raise ValueError(f"unknown classifier config fields {sorted(unknown)}")
        for k in ("hidden", "materials"):
            if k in d:
                d[k] = tuple(d[k])
        return cls(**d)


def _parse_feature(feature: str) -> tuple[str, str]:
    layer, sep, reduce = feature.partition(":")
    if not sep or reduce not in REDUCTIONS:
        raise ValueError(f"feature must look like '<vgg layer>:<{'|'.join(REDUCTIONS)}>', "
                         f"got {feature!r}")
    vgg.layer_level(layer)  # validates the layer name
    return layer, reduce


def _layer_channels(vgg_params, layer: str) -> int:
    """Output channels of a VGG layer, read from the parameters (tiny test VGGs differ)."""
    level = vgg.layer_level(layer)
    if layer.startswith("pool"):
        conv = [n for n in vgg.CONV_NAMES if int(n[4]) == level][-1]
    else:
        conv = "conv" + layer[4:]
    if conv not in vgg_params:
        raise ClassifierError(f"VGG parameters have no {conv!r} (needed for feature {layer!r})")
    return int(vgg_params[conv]["kernel"].shape[-1])


def feature_dim(vgg_params, feature: str, patch_size: int = 128) -> int:
    """Length D of the feature vector of one patch."""
    layer, reduce = _parse_feature(feature)
    c = _layer_channels(vgg_params, layer)
    if reduce == "stats":
        return 2 * c
    side = patch_size // 2 ** vgg.layer_level(layer)
    if side < GRID or side % GRID:
        raise ValueError(f"{layer} of a {patch_size}-texel patch is {side}x{side}, not "
                         f"divisible into a {GRID}x{GRID} grid")
    return GRID * GRID * c
