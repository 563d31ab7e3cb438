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
    3x3 conv to 3 channels  [-> output_norm="imagenet": de-normalized, out * std + mean]
                            [+ base, with `residual=True`: the input itself, or with
                             residual_base="unsharp" the unsharp-masked input with a learnable
                             per-material gain (`wrinkle_jax.sharpen`)]

With width=64 and 5 materials the network has 8,510,083 parameters.

Settings: `UNetConfig` holds the architecture (width, residual base, detail space, noise, ...)
as one frozen, serializable config that the training, model-file and PatchGAN configs nest;
`CINUNet` takes it as its `config` attribute (the module repeats none of its fields), and
`UNetConfig.module(num_materials, conv_impl)` builds the `CINUNet`. `RECIPE_UNET` is the
shipped model's.

Conditional instance normalization (Dumoulin et al. 2017): per-material scale and shift
tables gathered by the material id of each sample, so one batch may mix materials; the
normalization layer is injected as `norm` (a `functools.partial`, like BatchNorm in the Flax
ImageNet example). The variance is guarded by `eps`, so constant patches stay finite.

Convolution forms (`conv_impl`): "xla" (default) uses `flax.linen.Conv`/`ConvTranspose`, i.e.
XLA's convolutions. "im2col_bf16" runs the convs, transposed convs and CIN through
`wrinkle_jax.nn.fastconv`: patch extraction by slicing plus one bfloat16 dot with float32
accumulation per layer, the transposed convs as four sub-pixel phases, CIN in one fused pass,
2x2 max-pool as a reshape; the first conv (the raw image: bfloat16 would round its fine detail
to 8 bits) and the last conv (2% of the FLOPs together) stay float32. On AVX512-BF16 CPUs it
infers 1.4-2.7x faster than "xla", and a training step (with the fast VGG loss) is 2-8x faster
(8x at width 64: XLA:CPU's own transposed-conv gradients are pathologically slow), with ~4e-3
relative output error (see `benchmarks/bench_unet.py`). "im2col_f32" is the same index
arithmetic with float32 dots: exact to float32 rounding, and (since it avoids XLA's
transposed-conv gradient) a training step ~5x faster than "xla" without any bfloat16.
"winograd_bf16" is "im2col_bf16" with the layers that have enough channels and texels
(`winograd.use_winograd`) computed by Winograd F(2x2, 3x3) / F(3x3, 2x2) transforms: 2.25x
fewer products there (input gradients too), ~1.5x the per-layer bfloat16 error;
"winograd_f32" the same in float32 (Winograd's rounding only, ~1e-6). "auto" is
the host's fast form for the width (`hostcpu.fast_conv_impl`): "im2col_bf16" where the CPU
has bfloat16 dot units, else "im2col_f32", or "winograd_f32" from width 32 (emulated bfloat16
dots make the bfloat16 forms slower there than float32). All forms have the same parameters
(names, shapes, init), so converted weights and checkpoints work with any of them.

Detail space and texel noise (the session-6 recipe, `experiments/results/fidelity/`): with
`detail_sigma` > 0 the network sees and writes the *detail representation* of its input
(`wrinkle_jax.detail`: the input's own large scale rotated to +z) and its output is rotated back
onto the input's large scale, so it works on detail relative to the coarse simulation's shape;
with `residual_highpass` above `detail_sigma` its residual cannot tilt that shape either.
With `noise_channels` k > 0, k channels of fixed per-texel noise
(`texel_noise`, a hash of the texel's absolute position in the UV layout, given by the patch
`origins`) join the input: a source for wrinkle texture the coarse input lacks that is the same
at the same cloth texel in every frame and in overlapping patches, so frames stay coherent.

Interop with the authors' PyTorch weights: `wrinkle_jax.nn.torch_interop`.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from wrinkle_jax import detail, hostcpu, sharpen
from wrinkle_jax.nn import fastconv, winograd

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)
NUM_LEVELS = 4
CONV_IMPLS = {"xla": None, "im2col_f32": jnp.float32, "im2col_bf16": jnp.bfloat16,
              "winograd_bf16": jnp.bfloat16, "winograd_f32": jnp.float32}
# What a config or a command line may name: a form, or "auto" (resolved when a module is built).
CONV_IMPL_CHOICES = (hostcpu.AUTO, *CONV_IMPLS)


class CIN(nn.Module):
    """Conditional instance normalization over (H, W), per sample and channel.

    Attributes:
      num_materials: rows of the scale/shift tables.
      eps: variance guard (PyTorch's InstanceNorm2d default, so converted weights match).
      fused: compute the statistics in one pass and fold scale/shift into one multiply-add
        (`fastconv.instance_norm`); same parameters and, to float32 rounding, same result.
    """

    num_materials: int
    eps: float = 1e-5
    fused: bool = False

    @nn.compact
    def __call__(self, x, material):
        """x: (N, H, W, C) float; material: (N,) int32 ids -> (N, H, W, C)."""
        c = x.shape[-1]
        scale = self.param("scale", nn.initializers.ones, (self.num_materials, c), jnp.float32)
        shift = self.param("shift", nn.initializers.zeros, (self.num_materials, c), jnp.float32)
        if self.fused:
            return fastconv.instance_norm(x, scale[material], shift[material], self.eps,
                                          out_dtype=x.dtype)
        x32 = x.astype(jnp.float32)
        mean = jnp.mean(x32, axis=(1, 2), keepdims=True)
        var = jnp.mean(jnp.square(x32 - mean), axis=(1, 2), keepdims=True)  # biased, as torch
        y = (x32 - mean) * jax.lax.rsqrt(var + self.eps)
        gamma = scale[material][:, None, None, :]
        beta = shift[material][:, None, None, :]
        return (y * gamma + beta).astype(x.dtype)


@dataclasses.dataclass(frozen=True)
class UNetConfig:
    """The U-Net's architecture settings: what `CINUNet` computes and which parameters it has,
    apart from the number of materials (the model's material list sets it) and the convolution
    form (same parameters for every form). Static, hashable; `CINUNet` takes one as its
    `config`, and one is nested in every config that builds a U-Net (`train.TrainConfig`,
    `enhancer.EnhancerConfig`, `nn.patchgan.GANConfig`). `RECIPE_UNET` is the shipped model's.
    On disk the settings are stored flat, among the outer config's own fields (`split_json`),
    so every file written before this class existed still reads.

    Attributes:
      width: channels of the first level (w); the levels use w, 2w, 4w, 8w.
      residual: return base + network output (a global residual) instead of the output.
      input_norm: "imagenet" (normalize RGB by ImageNet mean/std, as the authors do) or "none".
      output_norm: "none", or "imagenet": the output conv computes ImageNet-normalized RGB (the
        authors' network) and is de-normalized (out * std + mean) to the RGB form before
        anything else uses it, so the module always returns the RGB form.
      residual_base: "input" (base = the input) or "unsharp" (base = the unsharp-masked input,
        `sharpen.unsharp_rgb` with `unsharp_sigma` texels and a per-material gain, parameter
        ``unsharp_amount`` (num_materials,), initialized to `unsharp_amount`). With a
        zero-initialized output conv the untrained network then IS the best non-learned
        baseline, and training learns what sharpening misses.
      unsharp_sigma: radius (texels) of the unsharp base's masked blur.
      unsharp_amount: initial value of the learned per-material unsharp gain.
      residual_highpass: 0, or a Gaussian radius in texels: the network's residual is
        high-passed (minus its masked blur, `sharpen.masked_blur`) so it can add detail but not
        shift the patch's low-frequency orientation -- which the style loss's early layers
        (relu1_2, relu2_1) punish hard on patches already close to their target.
      blur_order: order of the masked blur of the unsharp base and of the high-pass
        (`sharpen.masked_blur`): 1 (local plane; flat tilted panels pass unchanged) or 0 (local
        mean, which turns every mask border into a spurious ramp; models trained before
        session 4 use it).
      detail_sigma: 0, or the low-pass radius (texels) of the detail representation the network
        works in (see the module docstring); the output is then unit normals on the input's
        large scale, 0 outside the mask.
      noise_channels: number of fixed per-texel noise channels appended to the input
        (`texel_noise`; needs the patches' `origins` for UV-coherent noise).
      noise_scale: lattice spacing of that noise in texels (1: white per-texel noise; s > 1:
        value noise on an s-texel lattice, bilinearly interpolated, so its energy sits at
        wavelengths >= 2s texels instead of at the texel scale).
      residual_gain: the residual's scale at the output (base + gain * residual; 1 in
        training): an inference-time amplitude knob chosen on validation data, since a
        network trained on some garments may over-add detail on others. Files without it
        read 1.
      upsample: the decoder's 2x up-sampling: "transpose" (4x4 stride-2 transposed conv, the
        authors' layers), or a fixed resize then a 3x3 conv (Odena et al. 2016), "nearest" or
        "bilinear" (`upsample2`): every output texel sees the same kernel, so no learned
        2-texel checkerboard; bilinear also avoids nearest's 2x2 block edges (untrained
        width-8 networks: checkerboard/output RMS 1.2-1.3 transposed, 0.25-0.31 nearest). The
        resize forms' decoder kernels are 3x3, so their parameters differ from "transpose".
    """

    width: int = 64
    residual: bool = False
    input_norm: str = "imagenet"
    output_norm: str = "none"
    residual_base: str = "input"
    unsharp_sigma: float = 8.0
    unsharp_amount: float = 1.0
    residual_highpass: float = 0.0
    blur_order: int = 1
    detail_sigma: float = 0.0
    noise_channels: int = 0
    noise_scale: int = 1
    upsample: str = "transpose"
    residual_gain: float = 1.0

    def module(self, num_materials: int, conv_impl: str = "xla") -> CINUNet:
        """The `CINUNet` with these settings for `num_materials` materials, in `conv_impl`
        ("auto": this host's fast form, so the module holds the form it runs)."""
        return CINUNet(config=self, num_materials=num_materials,
                       conv_impl=hostcpu.resolve_conv_impl(conv_impl, self.width))

    def shares_blur(self) -> bool:
        """Whether the unsharp base and the high-pass blur on one radius (one blur serves both)."""
        return self.residual_base == "unsharp" and 0 < self.residual_highpass == self.unsharp_sigma

    def blur_weights(self, mask) -> dict:
        """The mask-only part of the model's masked blurs, for masks known before the values.

        The pipeline's patches sit at fixed texels of the garment's layout, so their masks are
        the same every frame: it computes these once per garment and passes them to
        `CINUNet.__call__`, which then skips the mask's passes (about a third of each blur).

        Args:
          mask: (N, H, W, 1) float, 1 inside the garment and 0 outside: the
            `sharpen.mask_from_rgb` of the patches these weights will serve.
        Returns:
          {"detail": w, "highpass": w, "unsharp": w}, the entries for the blurs this config
          runs (`sharpen.blur_weights` planes); {} when it runs none.
        """
        out = {}
        if self.detail_sigma > 0:
            out["detail"] = sharpen.blur_weights(mask, float(self.detail_sigma), 1)
        if not self.residual:
            return out
        if self.residual_highpass > 0:
            out["highpass"] = sharpen.blur_weights(mask, float(self.residual_highpass),
                                                   self.blur_order)
        if self.residual_base == "unsharp" and not self.shares_blur():
            out["unsharp"] = sharpen.blur_weights(mask, float(self.unsharp_sigma),
                                                  self.blur_order)
        return out

    def to_json(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def split_json(cls, d: dict, default: UNetConfig) -> tuple[UNetConfig, dict]:
        """Split an outer config's flat JSON dict into (the U-Net's settings, the other keys).

        Settings missing from `d` take `default`'s values, except `blur_order`: files written
        before it existed were trained with the order-0 (local mean) blur, so it reads as 0.
        """
        names = {f.name for f in dataclasses.fields(cls)}
        own = {k: v for k, v in d.items() if k in names}
        own.setdefault("blur_order", 0)
        return (dataclasses.replace(default, **own),
                {k: v for k, v in d.items() if k not in names})


# The shipped model's U-Net (wrinkle_jax/assets/enhancer.npz, MODEL_CARD.md): width 16 (the
# width study's choice), a global residual on the unsharp-masked input (sigma 16 texels, a
# learned per-material gain starting at 1) with the residual high-passed at 8 texels.
RECIPE_UNET = UNetConfig(width=16, residual=True, residual_base="unsharp", unsharp_sigma=16.0,
                         unsharp_amount=1.0, residual_highpass=8.0, blur_order=1)


class CINUNet(nn.Module):
    """Material-conditioned U-Net (see the module docstring).

    Attributes:
      config: the architecture settings (`UNetConfig`: width, residual base, detail space,
        noise, up-sampling; see there). The module has no copies of them, so a config and the
        module built from it cannot disagree.
      num_materials: number of materials the CIN tables hold.
      norm: the conditional normalization layer factory (called with num_materials).
      dtype: computation dtype of the "xla" convolutions (parameters stay float32).
      conv_impl: "xla", "im2col_bf16" (fast on CPUs with bfloat16 dot units), "im2col_f32",
        "winograd_bf16", "winograd_f32" or "auto" (see the module docstring); the parameters
        are the same for every form.
    """

    config: UNetConfig = UNetConfig()
    num_materials: int = 5
    norm: Callable[..., nn.Module] = CIN
    dtype: jnp.dtype = jnp.float32
    conv_impl: str = "xla"

    @nn.compact
    def __call__(self, x, material, origins=None, blur_weights=None):
        """Enhance patches.

        Args:
          x: (N, H, W, 3) float, RGB form of normal-map patches in [0, 1]; H and W divisible
            by 16 (128 in the paper).
          material: (N,) int material ids (see `wrinkle_jax.MATERIALS`).
          origins: (N, 2) int (row, col) texel position of each patch in its UV layout, for
            the texel noise (`noise_channels` > 0); None puts every patch at (0, 0).
          blur_weights: None, or `config.blur_weights` of the patches' masks (computed once
            when the masks repeat; the same result, without the blurs' mask passes).
        Returns:
          (N, H, W, 3) float32 enhanced patches in the same RGB form (not clipped).
        """
        if x.shape[1] % 16 or x.shape[2] % 16:
            raise ValueError(f"patch size must be divisible by 16, got {x.shape[1:3]}")
        cfg = self.config
        material = jnp.asarray(material, jnp.int32).reshape(x.shape[0])
        x = x.astype(jnp.float32)
        mask = sharpen.mask_from_rgb(x)  # one mask for detail, high-pass and unsharp base
        bw = {} if blur_weights is None else blur_weights
        if cfg.detail_sigma > 0:
            d, large, branch = detail.decompose(x * 2.0 - 1.0, mask, cfg.detail_sigma,
                                                weights=bw.get("detail"))
            x = (d + 1.0) * 0.5 * mask
        h = x
        if cfg.input_norm == "imagenet":
            h = (h - jnp.asarray(IMAGENET_MEAN)) / jnp.asarray(IMAGENET_STD)
        elif cfg.input_norm != "none":
            raise ValueError(f"unknown input_norm {cfg.input_norm!r}")
        if cfg.noise_channels > 0:
            if origins is None:
                origins = jnp.zeros((x.shape[0], 2), jnp.int32)
            noise = texel_noise(origins, x.shape[1], x.shape[2], cfg.noise_channels,
                                scale=cfg.noise_scale)
            h = jnp.concatenate([h, noise * mask], axis=-1)
        impl = hostcpu.resolve_conv_impl(self.conv_impl, cfg.width)
        if impl not in CONV_IMPLS:
            raise ValueError(f"unknown conv_impl {self.conv_impl!r}; expected one of "
                             f"{', '.join(CONV_IMPL_CHOICES)}")
        compute = CONV_IMPLS[impl]
        norm = self.norm
        if compute is None:
            conv = functools.partial(nn.Conv, kernel_size=(3, 3), padding=((1, 1), (1, 1)),
                                     dtype=self.dtype)
            # PyTorch ConvTranspose2d(k=4, s=2, p=1) == a conv of the 2x-dilated input with
            # padding k - 1 - p = 2 on each side (kernel stored flipped; see from_torch).
            deconv = functools.partial(nn.ConvTranspose, kernel_size=(4, 4), strides=(2, 2),
                                       padding=((2, 2), (2, 2)), dtype=self.dtype)
        else:
            wino = impl.startswith("winograd")
            conv = functools.partial(FastConv, kernel_size=3, compute_dtype=compute,
                                     winograd=wino)
            deconv = functools.partial(FastConv, kernel_size=4, transpose=True,
                                       compute_dtype=compute, winograd=wino)
            if norm is CIN:
                norm = functools.partial(CIN, fused=True)
        skips = []
        for level in range(NUM_LEVELS):
            layer = conv
            if level == 0 and compute is not None:
                # The raw 3-channel image: bfloat16 would round its fine detail to 8 bits (the
                # largest single error source); float32 costs little here (K = 27).
                layer = functools.partial(conv, compute_dtype=jnp.float32)
            h = nn.relu(layer(cfg.width * 2**level, name=f"enc{level + 1}")(h))
            skips.append(h)
            h = nn.max_pool(h, (2, 2), strides=(2, 2)) if compute is None else _max_pool2(h)
        if cfg.upsample in ("nearest", "bilinear"):
            deconv = _ResizeConv(conv, cfg.upsample)
        elif cfg.upsample != "transpose":
            raise ValueError(f"unknown upsample {cfg.upsample!r}; expected transpose, "
                             "nearest or bilinear")
        for level in reversed(range(NUM_LEVELS)):
            h = deconv(cfg.width * 2**level, name=f"dec{NUM_LEVELS - level}")(h)
            h = h + skips[level]
            h = norm(num_materials=self.num_materials, name=f"cin{NUM_LEVELS - level}")(
                h, material)
            h = nn.relu(h)
        if compute is not None:  # 1% of the FLOPs: keep the output's last rounding float32
            conv = functools.partial(conv, compute_dtype=jnp.float32)
        out = conv(3, name="out")(h).astype(jnp.float32)
        if cfg.output_norm == "imagenet":
            out = out * jnp.asarray(IMAGENET_STD) + jnp.asarray(IMAGENET_MEAN)
        elif cfg.output_norm != "none":
            raise ValueError(f"unknown output_norm {cfg.output_norm!r}")
        if cfg.residual:
            base = x
            base_low = None  # the unsharp base's blur, when blurred with the high-pass's
            if cfg.residual_highpass > 0:
                if cfg.shares_blur():
                    # Same mask and radius: one blur of both fields shares the mask's moments.
                    low = sharpen.masked_blur(jnp.concatenate([out, x * 2.0 - 1.0], axis=-1),
                                              mask, cfg.residual_highpass, cfg.blur_order,
                                              weights=bw.get("highpass"))
                    low, base_low = low[..., :3], low[..., 3:]
                else:
                    low = sharpen.masked_blur(out, mask, cfg.residual_highpass,
                                              cfg.blur_order, weights=bw.get("highpass"))
                out = out - low
            if cfg.residual_base == "unsharp":
                gain = self.param("unsharp_amount",
                                  nn.initializers.constant(cfg.unsharp_amount),
                                  (self.num_materials,), jnp.float32)
                if base_low is None and "unsharp" in bw:
                    base_low = sharpen.masked_blur(base * 2.0 - 1.0, mask, cfg.unsharp_sigma,
                                                   cfg.blur_order, weights=bw["unsharp"])
                base = sharpen.unsharp_rgb(base, cfg.unsharp_sigma, gain[material], mask,
                                          cfg.blur_order, blurred=base_low)
            elif cfg.residual_base != "input":
                raise ValueError(f"unknown residual_base {cfg.residual_base!r}")
            out = base + cfg.residual_gain * out  # exact at gain 1
        if cfg.detail_sigma > 0:
            out = detail.from_detail_rgb(out, large, branch, mask)
        return out


class _ResizeConv:
    """Factory with the transposed conv's call signature: fixed 2x up-sampling (`upsample2`,
    "nearest" or "bilinear"), then `conv` (a 3x3 "same" conv factory):
    ``_ResizeConv(conv, kind)(features, name=...)(x)``."""

    def __init__(self, conv, kind: str):
        self.conv, self.kind = conv, kind

    def __call__(self, features: int, name: str):
        layer = self.conv(features, name=name)
        return lambda x: layer(upsample2(x, self.kind))


def upsample2(x, kind: str = "bilinear"):
    """(N, H, W, C) -> (N, 2H, 2W, C). "nearest" repeats each texel into a 2x2 block;
    "bilinear" interpolates at the new texel centres (weights 3/4, 1/4 of the two nearest
    old texels per axis, edges clamped), whose response falls to zero towards the 2-texel
    period smoothly, so a following conv sees no block edges to turn into a checkerboard."""
    if kind == "nearest":
        return jnp.repeat(jnp.repeat(x, 2, axis=1), 2, axis=2)
    if kind != "bilinear":
        raise ValueError(f"unknown up-sampling {kind!r}")
    for axis in (1, 2):
        n = x.shape[axis]
        first = jax.lax.slice_in_dim(x, 0, 1, axis=axis)
        last = jax.lax.slice_in_dim(x, n - 1, n, axis=axis)
        xp = jnp.concatenate([first, x, last], axis=axis)
        mid = jax.lax.slice_in_dim(xp, 1, n + 1, axis=axis)
        even = 0.25 * jax.lax.slice_in_dim(xp, 0, n, axis=axis) + 0.75 * mid
        odd = 0.75 * mid + 0.25 * jax.lax.slice_in_dim(xp, 2, n + 2, axis=axis)
        x = jnp.stack([even, odd], axis=axis + 1)
        shape = list(x.shape)
        x = x.reshape(shape[:axis] + [2 * n] + shape[axis + 2:])
    return x


def texel_noise(origins, height: int, width: int, channels: int, seed: int = 0,
                scale: int = 1):
    """Fixed per-texel noise: a hash of each texel's absolute (row, col) and the channel.

    The same texel of a UV layout gets the same values in every frame and in every patch that
    covers it, so noise-driven detail neither flickers nor disagrees between overlapping
    patches.

    Args:
      origins: (N, 2) int (row, col) of each patch's top-left texel in the layout.
      height, width, channels: patch size and number of noise channels.
      seed: selects another noise field.
      scale: lattice spacing in texels. 1: independent values per texel. s > 1: independent
        values at the texels whose absolute row and column are multiples of s, bilinearly
        interpolated in between (value noise), rescaled to unit variance on average.
    Returns:
      (N, height, width, channels) float32 with zero mean and unit variance (uniform for
      scale 1).
    """
    if scale < 1:
        raise ValueError(f"noise scale must be >= 1 texel, got {scale}")
    o = jnp.asarray(origins).astype(jnp.int32)
    r = o[:, 0, None] + jnp.arange(height, dtype=jnp.int32)  # (N, H) absolute rows
    c = o[:, 1, None] + jnp.arange(width, dtype=jnp.int32)
    if scale == 1:
        return _lattice_values(r, c, channels, seed)
    r0, c0 = r // scale, c // scale  # floor division: origins may be negative near borders
    tr = ((r - r0 * scale).astype(jnp.float32) / scale)[:, :, None, None]
    tc = ((c - c0 * scale).astype(jnp.float32) / scale)[:, None, :, None]
    v00 = _lattice_values(r0, c0, channels, seed)
    v01 = _lattice_values(r0, c0 + 1, channels, seed)
    v10 = _lattice_values(r0 + 1, c0, channels, seed)
    v11 = _lattice_values(r0 + 1, c0 + 1, channels, seed)
    v = ((1 - tr) * ((1 - tc) * v00 + tc * v01) + tr * ((1 - tc) * v10 + tc * v11))
    # Interpolation lowers the variance by mean_t[(1-t)^2 + t^2] per axis over the s phases.
    t = np.arange(scale) / scale
    shrink = float(np.mean((1 - t) ** 2 + t**2)) ** 2
    return v * np.float32(1.0 / np.sqrt(shrink))


def _lattice_values(rows, cols, channels: int, seed: int):
    """rows (N, H), cols (N, W) int lattice coordinates -> (N, H, W, channels) float32 hash
    values, uniform in [-sqrt 3, sqrt 3) (zero mean, unit variance)."""
    r = rows.astype(jnp.uint32)[:, :, None, None]
    c = cols.astype(jnp.uint32)[:, None, :, None]
    k = jnp.arange(channels, dtype=jnp.uint32)[None, None, None, :] + jnp.uint32(seed * 977 + 1)
    # Integer mixing (multiply-xorshift, "lowbias32"); uint32 arithmetic wraps modulo 2^32.
    v = r * jnp.uint32(0x8DA6B343) ^ c * jnp.uint32(0xD8163841) ^ k * jnp.uint32(0xCB1AB31F)
    v = v ^ (v >> 16)
    v = v * jnp.uint32(0x7FEB352D)
    v = v ^ (v >> 15)
    v = v * jnp.uint32(0x846CA68B)
    v = v ^ (v >> 16)
    u = (v >> 8).astype(jnp.float32) * (1.0 / 2**24)  # [0, 1), 24 bits
    return (u - 0.5) * np.float32(np.sqrt(12.0))


@jax.custom_vjp
def _max_pool2(x):
    """2x2 stride-2 max-pool of (N, H, W, C): the same values as `nn.max_pool`.

    Forward: the maximum of the four strided views, elementwise (the reshape-and-reduce form
    made the shipped network's forward 2-7 % slower: 3 alternating process pairs, session 44).
    Gradient: elementwise too (XLA:CPU's reduce-window/select-and-scatter gradient is ~5x
    slower), shared equally among tied maxima as `jnp.max`'s (ties only occur at ReLU zeros,
    whose gradient is 0 anyway); written out because the strided views' own gradient is
    slower. Reverse mode only, as the fast convolutions it runs with (`custom_vjp`).
    """
    top = jnp.maximum(x[:, 0::2, 0::2], x[:, 0::2, 1::2])
    return jnp.maximum(top, jnp.maximum(x[:, 1::2, 0::2], x[:, 1::2, 1::2]))


def _max_pool2_fwd(x):
    y = _max_pool2(x)
    return y, (x, y)


def _max_pool2_bwd(res, g):
    x, y = res
    n, h, w, c = x.shape
    hit = (x.reshape(n, h // 2, 2, w // 2, 2, c) == y[:, :, None, :, None, :]).astype(g.dtype)
    share = hit / jnp.sum(hit, axis=(2, 4), keepdims=True)
    return ((share * g[:, :, None, :, None, :]).reshape(x.shape),)


_max_pool2.defvjp(_max_pool2_fwd, _max_pool2_bwd)


class FastConv(nn.Module):
    """A 3x3 "same" conv or a 4x4 stride-2 (PyTorch padding 1) transposed conv through
    `wrinkle_jax.nn.fastconv`, with exactly `nn.Conv`'s / `nn.ConvTranspose`'s parameters
    (`kernel` (k, k, C, O) HWIO, `bias` (O,), same initializers and init order).

    Attributes:
      features: output channels O.
      kernel_size: 3 (conv) or 4 (transposed conv).
      transpose: transposed conv (kernel_size 4 only).
      compute_dtype: dot operand dtype (accumulation is float32).
      winograd: the `wrinkle_jax.nn.winograd` form where `winograd.use_winograd` says it pays
        (same parameters and result up to rounding).
    """

    features: int
    kernel_size: int = 3
    transpose: bool = False
    compute_dtype: jnp.dtype = jnp.bfloat16
    winograd: bool = False

    @nn.compact
    def __call__(self, x):
        """x: (N, H, W, C) -> float32 (N, H, W, O), or (N, 2H, 2W, O) when transposed."""
        if (self.kernel_size, self.transpose) not in ((3, False), (4, True)):
            raise ValueError("FastConv supports a 3x3 conv or a 4x4 transposed conv, got "
                             f"kernel_size={self.kernel_size}, transpose={self.transpose}")
        k = self.kernel_size
        kernel = self.param("kernel", nn.initializers.lecun_normal(),
                            (k, k, x.shape[-1], self.features), jnp.float32)
        bias = self.param("bias", nn.initializers.zeros_init(), (self.features,), jnp.float32)
        ops = winograd.layer_ops(x, self.features, self.winograd)
        if self.transpose:
            return ops.conv_transpose4x4s2(x, kernel, bias, compute_dtype=self.compute_dtype)
        return ops.conv3x3(x, kernel, bias, compute_dtype=self.compute_dtype)


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
