"""Fast CPU forms of the U-Net's and VGG's operators: im2col + one bfloat16 dot per layer.

Why: XLA:CPU runs float32 convolutions at roughly 40-80 GFLOP/s and converts bfloat16
convolutions back to float32, but a bfloat16 `dot_general` with float32 accumulation
(`preferred_element_type=float32`) runs on the AVX512-BF16 units at several times that rate.
So every convolution here is rewritten as *patch extraction by slicing* (shifted views of the
padded input concatenated along channels -- no gather) followed by **one** dot whose
contraction is the trailing, contiguous axis of an NHWC array:

* `conv3x3` -- 3x3, stride 1, "same" size, zero or reflection padding (U-Net encoder and
  output convs; VGG19's convs). Patches `(N, H, W, 9 C)` with tap order `(dy, dx, c)` times the
  HWIO kernel reshaped to `(9 C, O)`. When the output has few channels (`2 O < C`, e.g. the
  U-Net's final 3-channel conv) the dot runs first, `(N, H, W, C) @ (C, 9 O)`, and the nine
  shifted partial outputs are summed ("output-side" form): it moves 9 O instead of 9 C values
  per pixel.
* `conv_transpose4x4s2` -- PyTorch `ConvTranspose2d(k=4, s=2, p=1)` (the U-Net decoder), by
  sub-pixel phases. Output pixel `(2m + dy, 2n + dx)` only sees a 2 x 2 window of the input, and
  all four phases share the same windows: with `xp` the input zero-padded by 1, the 2 x 2 window
  at `(s, r)` (`s, r = 0..H`) produces phase `(dy, dx)` of output `(s - dy, r - dx)`. So one
  dot `(N, H+1, W+1, 4 C) @ (4 C, 4 O)` -- no zero taps -- gives every phase, and depth-to-space
  with a one-pixel shift per phase assembles the output. Exact for k=4, s=2, p=1.
* `instance_norm` -- conditional instance norm fused into one pass: per (sample, channel)
  mean and E[x^2] in one reduction, scale and shift folded into one multiply-add, optional
  ReLU.

Gradients: the two convolutions carry a `jax.custom_vjp` whose backward pass uses the same
fast form -- the input gradient of a 3x3 conv is a 3x3 conv of the output gradient with the
flipped, transposed kernel; the input gradient of the transposed conv is a 2x2 conv of the
space-to-depth output gradient; the kernel gradients are one dot each, `patches^T @ g` -- all
in the compute dtype with float32 accumulation. (`custom_vjp`: reverse mode only; `jax.jvp`
through these operators is not supported.)

Precision (`compute_dtype`): `jnp.bfloat16` rounds the dot operands (activations, kernel,
output gradient) to 8 significant bits: relative rounding error at most 2**-8, RMS about
1.6e-3 per operand, so ~2.3e-3 per product; products and sums are float32. An output is a sum
of K products with independent errors, so its error has RMS ~2.3e-3 times the output's own RMS,
independent of K -- for a layer and for its gradients (measured 2.1e-3 to 2.8e-3). The tests
bound one layer by `BF16_RTOL` = 1e-2 in RMS and by `BF16_MAX_RTOL` = 5e-2 in the maximum
(Gaussian tails over up to 1e5 outputs; measured <= 1.7e-2), both relative to the reference
output's RMS. Through the whole U-Net the errors do not compound (CIN re-normalizes after every
decoder layer): 2.5e-3 to 4.5e-3 RMS at widths 4 to 64. `compute_dtype=jnp.float32` runs the
identical index arithmetic in float32 and matches the XLA convolutions to float32 rounding
(`F32_ATOL` on O(1) data; measured ~1e-6), which is what proves the indexing exact.

XLA:CPU specifics (each measured; they decide the speed more than the FLOPs do):
* data movement (padding, shifted views, depth-to-space, space-to-depth) runs on the operands'
  bits as uint16/uint32: XLA:CPU has no bfloat16 data movement and round-trips every bf16 pad
  or slice through float32 (2-3x slower patches);
* concatenation is written as an OR of zero-padded parts (`_concat`), which XLA fuses into one
  loop; a `concatenate` of slices materializes every slice and copies it again (3-5x slower);
* arrays read by two dots (the patches, in the forward and the kernel gradient) and a
  reflection-padded input are materialized once (`optimization_barrier`): otherwise XLA
  re-derives them per consumer and stops fusing the shifted views (10x slower backward);
* a bfloat16 dot that contracts the leading axis of its first operand (`a^T b`) is run as a
  float32 dot; `(M, K) @ (K, N)` and `(M, K) @ (N, K)^T` run as bfloat16 dots. So `a^T b`
  needs `a` copied transposed, and that copy is fused with `a`'s producers into a strided loop
  (a norm's backward fused in: 6-18x slower per element than a stored array's copy). The operand
  to transpose is chosen per call site: the output gradient of the 3x3 conv, the saved input
  of the transposed conv (`_im2col_t`'s channel-major windows), never the patches;
* XLA's own transposed-convolution gradient is pathologically slow on CPU (~0.6-1 s per
  128 x 128 patch and layer at width 64) -- the main reason the plain U-Net trains slowly.

Shapes: NHWC activations, HWIO kernels exactly as `flax.linen.Conv` / `ConvTranspose` store them
(`torch_interop.from_torch_state_dict`'s layout), so parameters are interchangeable between the
XLA and the fast forms.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
from jax import lax

__all__ = [
    "BF16_MAX_RTOL",
    "BF16_RTOL",
    "F32_ATOL",
    "conv3x3",
    "conv3x3_flops",
    "conv_transpose4x4s2",
    "conv_transpose4x4s2_flops",
    "instance_norm",
]

# Error of one bfloat16 layer (or its gradient) relative to the reference output's RMS:
# RMS of the error, and its maximum (see the module docstring for the derivation).
BF16_RTOL = 1e-2
BF16_MAX_RTOL = 5e-2
# Absolute tolerance of the float32 im2col forms against XLA on O(1) data.
F32_ATOL = 1e-5

_PADDINGS = ("ZERO", "REFLECT")
_DTYPES = {"float32": jnp.float32, "bfloat16": jnp.bfloat16}


def _dtype_name(dtype) -> str:
    name = jnp.dtype(dtype if dtype is not None else jnp.float32).name
    if name not in _DTYPES:
        raise ValueError(f"compute_dtype must be float32 or bfloat16, got {name}")
    return name


def _dot(a, b):
    """Contract the last axis of `a` (..., K) with the first of `b` (K, O) -> (..., O) float32."""
    return lax.dot_general(a, b, (((a.ndim - 1,), (0,)), ((), ())),
                           preferred_element_type=jnp.float32)


def _dot_tn(a, b):
    """`a^T b` over all but the last axis: a (N, H, W, K), b (N, H, W, O) -> (K, O) float32.

    XLA:CPU copies `a` into a transposed layout first (a bfloat16 dot contracting `a`'s leading
    axes is not one it runs): callers pass as `a` the operand that is cheapest to transpose (a
    materialized array, not patches whose shifted views XLA would fuse into a slow strided copy).
    """
    dims = tuple(range(a.ndim - 1))
    return lax.dot_general(a, b, ((dims, dims), ((), ())), preferred_element_type=jnp.float32)


def _dot_tn_t(a, b):
    """`(a^T b)^T` = `b^T a` with `a` the transposed operand (see `_dot_tn`); the barrier keeps
    XLA from folding the final, kernel-sized transpose into the dot (that folded form is not a
    bfloat16 dot XLA:CPU's runtime has)."""
    return lax.optimization_barrier(_dot_tn(a, b)).T


def _residual(x):
    """Materialize `x` once for both the forward dot and the backward pass (without the barrier
    XLA:CPU re-derives the patches for each consumer and stops fusing their shifted views)."""
    return lax.optimization_barrier(x)


def _pad(x, pad, mode="ZERO"):
    """Pad H and W of (N, H, W, C) `x` by `pad` with zeros or by reflection.

    The reflected copy is materialized once (a barrier): fused into the patch loop below, XLA
    would re-derive it for every tap (~3x slower patches).
    """
    widths = ((0, 0), (pad, pad), (pad, pad), (0, 0))
    if mode == "ZERO":
        return jnp.pad(x, widths)
    return lax.optimization_barrier(jnp.pad(x, widths, mode="reflect"))


def _reflect_pad_adjoint(gp):
    """Adjoint of reflection padding by 1: (N, H+2, W+2, C) float -> (N, H, W, C); border rows
    and columns are added onto the rows/columns they mirror (1 and n-2)."""
    for axis in (1, 2):
        n = gp.shape[axis] - 2
        inner = lax.slice_in_dim(gp, 1, n + 1, axis=axis)
        widths = [(0, 0)] * gp.ndim
        widths[axis] = (1, n - 2)
        first = jnp.pad(lax.slice_in_dim(gp, 0, 1, axis=axis), widths)
        widths[axis] = (n - 2, 1)
        last = jnp.pad(lax.slice_in_dim(gp, n + 1, n + 2, axis=axis), widths)
        gp = inner + first + last
    return gp


_BITS = {2: jnp.uint16, 4: jnp.uint32}


def _check_layer(x, kernel, taps: int, padding: str = "ZERO"):
    """Raise ValueError unless `padding` is known and x (N, H, W, C) and kernel
    (taps, taps, C, O) fit the 3x3 conv (taps 3) or the transposed conv (taps 4)."""
    if padding not in _PADDINGS:
        raise ValueError(f"padding must be one of {_PADDINGS}, got {padding!r}")
    if x.ndim != 4 or kernel.shape[:2] != (taps, taps) or kernel.shape[2] != x.shape[-1]:
        name = "conv3x3" if taps == 3 else "conv_transpose4x4s2"
        raise ValueError(f"{name}: x {x.shape} and kernel {kernel.shape} do not match "
                         f"(N, H, W, C) / ({taps}, {taps}, C, O)")


def _bits(x):
    """Reinterpret float `x` as unsigned integers of the same width.

    All data movement (padding, shifted views, concatenation, depth-to-space) runs on these:
    XLA:CPU has no native bfloat16 data movement and would round-trip every bfloat16 pad or
    slice through float32 inside the fusion. Zero bits are +0.0, so zero padding is exact.
    """
    return lax.bitcast_convert_type(x, _BITS[jnp.dtype(x.dtype).itemsize])


def _concat(parts, axis=-1):
    """`jnp.concatenate(parts, axis)` of unsigned-integer arrays as ONE XLA loop fusion.

    XLA:CPU materializes every sliced operand of a concatenate and then copies them again; here
    each part is zero-padded to the full size and the parts are OR-ed (exact: exactly one part
    is non-zero at each position), which XLA fuses into a single loop.
    """
    axis = axis % parts[0].ndim
    total = sum(p.shape[axis] for p in parts)
    out, start = None, 0
    for p in parts:
        c = p.shape[axis]
        widths = [(0, 0)] * p.ndim
        widths[axis] = (start, total - start - c)
        q = jnp.pad(p, widths)
        out = q if out is None else out | q
        start += c
    return out


def _im2col(x, taps, h, w, pad=0, mode="ZERO"):
    """Patches of float `x` (N, h + taps - 1 - 2 pad, w + taps - 1 - 2 pad, C) after padding
    by `pad`: shifted views, tap order (dy, dx, c).

    Returns (N, h, w, taps * taps * C), x's dtype.
    """
    xp = _bits(x)
    if pad:
        xp = _pad(xp, pad, mode)
    cols = _concat([xp[:, a:a + h, b:b + w, :] for a in range(taps) for b in range(taps)])
    return lax.bitcast_convert_type(cols, x.dtype)


# ---------------------------------------------------------------------------------------------
# 3x3 "same" convolution.


def _output_side(c_in, c_out):
    """Few outputs: multiply first, then sum shifted partial outputs (moves 9 O, not 9 C)."""
    return 2 * c_out < c_in


def _small_input(c_in, c_out):
    """Few inputs (e.g. an RGB image): the kernel gradient uses channel-major patches of x."""
    return 9 * c_in <= c_out


def _shifted_sum(x, kernel, pad):
    """Output-side 3x3 correlation: u = x @ kernel[a, b] for all taps, then
    y[p] = sum_ab u[p + (a, b) - pad, (a, b)] (zero outside). x (N, H, W, C) -> (N, H + 2 pad - 2,
    W + 2 pad - 2, O) float32: pad=1 is the "same" conv, pad=2 the full correlation."""
    n, h, w, c = x.shape
    o = kernel.shape[-1]
    u = _dot(x, kernel.transpose(2, 0, 1, 3).reshape(c, 9 * o))
    up = _pad(u, pad).reshape(n, h + 2 * pad, w + 2 * pad, 9, o)
    ho, wo = h + 2 * pad - 2, w + 2 * pad - 2
    return sum(up[:, a:a + ho, b:b + wo, 3 * a + b, :] for a in range(3) for b in range(3))


def _im2col_t(x, taps=3, flip=False):
    """Channel-major patches of `x` (N, H, W, C) zero-padded by 1, for kernel-gradient dots
    without a transposed copy of the wide operand: (taps^2 C, N Ho Wo) with Ho = H + 3 - taps,
    rows (dy, dx, c) -- or taps (taps-1-dy, taps-1-dx) when `flip`. taps=3: the 3x3 conv's
    patches (Ho = H); taps=2: the transposed conv's 2x2 windows (Ho = H + 1). Built from the
    transposed (C, N, H, W) array, so every shifted view is a long contiguous run."""
    _, h, w, c = x.shape
    ho, wo = h + 3 - taps, w + 3 - taps
    xt = jnp.pad(jnp.transpose(_bits(x), (3, 0, 1, 2)), ((0, 0), (0, 0), (1, 1), (1, 1)))
    offsets = [(a, b) for a in range(taps) for b in range(taps)]
    if flip:
        offsets = [(taps - 1 - a, taps - 1 - b) for a, b in offsets]
    parts = [xt[None, :, :, a:a + ho, b:b + wo] for a, b in offsets]
    cols = _concat(parts, axis=0)  # (taps^2, C, N, Ho, Wo)
    return lax.bitcast_convert_type(cols, x.dtype).reshape(taps * taps * c, -1)


def _conv3x3_forward(x, kernel, padding, save=False):
    """y (N, H, W, O) float32 and the residual for the kernel gradient (materialized once when
    `save`).

    x: (N, H, W, C) and kernel (3, 3, C, O), both already in the compute dtype.
    """
    n, h, w, c = x.shape
    o = kernel.shape[-1]
    if padding == "ZERO" and _output_side(c, o):
        return _shifted_sum(x, kernel, 1), x
    patches = _im2col(x, 3, h, w, pad=1, mode=padding)
    if save and not _small_input(c, o):
        patches = _residual(patches)
    y = _dot(patches, kernel.reshape(9 * c, o))
    return y, (x if _small_input(c, o) else patches)


def _flip_transpose(kernel):
    """(3, 3, C, O) -> (3, 3, O, C) kernel of the input gradient (spatially flipped)."""
    return kernel[::-1, ::-1].transpose(0, 1, 3, 2)


@functools.partial(jax.custom_vjp, nondiff_argnums=(2, 3, 4))
def _conv3x3(x, kernel, padding, compute, x_dtype):
    del x_dtype
    dt = _DTYPES[compute]
    return _conv3x3_forward(x.astype(dt), kernel.astype(dt), padding)[0]


def _conv3x3_fwd(x, kernel, padding, compute, x_dtype):
    del x_dtype
    dt = _DTYPES[compute]
    y, residual = _conv3x3_forward(x.astype(dt), kernel.astype(dt), padding, save=True)
    return y, (residual, kernel)


def _conv3x3_bwd(padding, compute, x_dtype, res, g):
    residual, kernel = res
    dt = _DTYPES[compute]
    n, h, w, o = g.shape
    c = kernel.shape[2]
    g = g.astype(dt)
    k_in = _flip_transpose(kernel).astype(dt)
    if padding == "ZERO":
        # dx[q] = sum_ab g[q - (a, b) + 1] @ kernel[a, b]^T: a same conv with the flipped kernel.
        dx = _conv3x3_forward(g, k_in, "ZERO")[0]
    else:
        # Full correlation onto the padded input, then the adjoint of the reflection padding.
        if _output_side(o, c):
            dxp = _shifted_sum(g, k_in, 2)
        else:
            dxp = _dot(_im2col(g, 3, h + 2, w + 2, pad=2), k_in.reshape(9 * o, c))
        dx = _reflect_pad_adjoint(dxp)
    if padding == "ZERO" and _output_side(c, o):
        # dk[a, b] = sum_q x[q]^T g[q + 1 - (a, b)]: channel-major patches of g, taps flipped.
        dk = _dot(_im2col_t(g, flip=True), residual.reshape(-1, c))  # (9 O, C)
        dk = dk.reshape(3, 3, o, c).transpose(0, 1, 3, 2)
    elif _small_input(c, o):
        if padding == "ZERO":
            cols = _im2col_t(residual)
        else:  # reflection: channel-major patches of the (small) padded input
            cols = _im2col(residual, 3, h, w, pad=1, mode=padding).reshape(-1, 9 * c).T
        dk = _dot(cols, g.reshape(-1, o)).reshape(3, 3, c, o)
    else:
        dk = _dot_tn_t(g, residual).reshape(3, 3, c, o)  # transposes g, not the patches
    return dx.astype(x_dtype), dk.astype(kernel.dtype)


_conv3x3.defvjp(_conv3x3_fwd, _conv3x3_bwd)


def conv3x3(x, kernel, bias=None, *, compute_dtype=jnp.bfloat16, padding="ZERO"):
    """3x3 stride-1 convolution with output size = input size (cross-correlation, like
    `lax.conv_general_dilated` / `flax.linen.Conv(padding=1)` / PyTorch `Conv2d(padding=1)`).

    Args:
      x: (N, H, W, C) float activations.
      kernel: (3, 3, C, O) float32 HWIO kernel.
      bias: optional (O,) float32.
      compute_dtype: dtype of the dot operands (`jnp.bfloat16` fast, `jnp.float32` exact);
        accumulation and the result are float32.
      padding: "ZERO" or "REFLECT" (reflection-pad by 1, as the Gatys VGG19 does).

    Returns:
      (N, H, W, O) float32.

    Example:
      >>> x = jnp.ones((1, 8, 8, 4)); k = jnp.ones((3, 3, 4, 5)) / 36
      >>> y = jax.jit(conv3x3)(x, k)            # interior 1, corner 4/9, to bfloat16 rounding
      >>> y.shape, float(y[0, 4, 4, 0]), float(y[0, 0, 0, 0])
      ((1, 8, 8, 5), 1.001953125, 0.4453125)
    """
    _check_layer(x, kernel, 3, padding)
    y = _conv3x3(x, kernel, padding, _dtype_name(compute_dtype), jnp.dtype(x.dtype).name)
    return y if bias is None else y + bias.astype(jnp.float32)


def conv3x3_flops(h, w, c_in, c_out, batch=1) -> int:
    """Multiply-adds x 2 of a 3x3 same convolution."""
    return 2 * batch * h * w * 9 * c_in * c_out


# ---------------------------------------------------------------------------------------------
# 4x4 stride-2 transposed convolution (PyTorch padding 1) by sub-pixel phases.


def _phase_kernel(kernel):
    """(4, 4, C, O) Flax ConvTranspose kernel -> (4 C, 4 O) with rows (ty, tx, c), cols
    (dy, dx, o): tap t of the 2x2 window feeds phase d through kernel index d + 2 t."""
    c, o = kernel.shape[2:]
    return kernel.reshape(2, 2, 2, 2, c, o).transpose(0, 2, 4, 1, 3, 5).reshape(4 * c, 4 * o)


def _grad_kernel(kernel):
    """(4, 4, C, O) -> (16 O, C), rows (ty, tx, py, px, o): the 2x2 conv on the space-to-depth
    output gradient that gives the input gradient (kernel index 3 - 2 t - p)."""
    c, o = kernel.shape[2:]
    k = kernel[::-1, ::-1].reshape(2, 2, 2, 2, c, o)  # (ty, py, tx, px, c, o)
    return k.transpose(0, 2, 1, 3, 5, 4).reshape(16 * o, c)


def _depth_to_space(z, h, w):
    """z (N, H+1, W+1, 2, 2, O) phase outputs per window -> (N, 2H, 2W, O), y[2m + dy, 2n + dx]
    = z[m + dy, n + dx, dy, dx] (one fused loop: zero-padded phases OR-ed, as `_concat`)."""
    n, o = z.shape[0], z.shape[-1]
    zb = _bits(z)
    out = None
    for dy in range(2):
        for dx in range(2):
            p = zb[:, dy:dy + h, dx:dx + w, dy, dx, :][:, :, None, :, None, :]
            q = jnp.pad(p, ((0, 0), (0, 0), (dy, 1 - dy), (0, 0), (dx, 1 - dx), (0, 0)))
            out = q if out is None else out | q
    return lax.bitcast_convert_type(out, z.dtype).reshape(n, 2 * h, 2 * w, o)


def _space_to_depth_padded(g):
    """g (N, 2H, 2W, O) -> S (N, H+1, W+1, 4 O), S[s, r, (py, px, o)] = gp[2s + py, 2r + px]
    with gp = g zero-padded by 1."""
    n, h2, w2, o = g.shape
    h, w = h2 // 2, w2 // 2
    gp = _pad(_bits(g), 1).reshape(n, h + 1, 2, w + 1, 2, o)
    s = gp.transpose(0, 1, 3, 2, 4, 5).reshape(n, h + 1, w + 1, 4 * o)
    return lax.bitcast_convert_type(s, g.dtype)


def _deconv_forward(x, kernel):
    n, h, w, c = x.shape
    o = kernel.shape[-1]
    patches = _im2col(x, 2, h + 1, w + 1, pad=1)  # (N, H+1, W+1, 4 C)
    z = _dot(patches, _phase_kernel(kernel)).reshape(n, h + 1, w + 1, 2, 2, o)
    return _depth_to_space(z, h, w)


@functools.partial(jax.custom_vjp, nondiff_argnums=(2, 3))
def _deconv(x, kernel, compute, x_dtype):
    del x_dtype
    dt = _DTYPES[compute]
    return _deconv_forward(x.astype(dt), kernel.astype(dt))


def _deconv_fwd(x, kernel, compute, x_dtype):
    del x_dtype
    dt = _DTYPES[compute]
    xd = x.astype(dt)
    return _deconv_forward(xd, kernel.astype(dt)), (xd, kernel)


def _deconv_bwd(compute, x_dtype, res, g):
    x, kernel = res
    dt = _DTYPES[compute]
    n, h2, w2, o = g.shape
    h, w, c = h2 // 2, w2 // 2, kernel.shape[2]
    s = _space_to_depth_padded(g.astype(dt))  # (N, H+1, W+1, 4 O); phase (dy,dx) = (1-py,1-px)
    dx = _dot(_im2col(s, 2, h, w), _grad_kernel(kernel).astype(dt))
    # The kernel gradient patches^T s: its transposed operand is the channel-major windows of
    # the saved input (a plain transpose of x), not s: s is usually fused with the layer's
    # output gradient (a norm's backward, a Winograd output's interleave), and a transposed
    # copy of that fusion is a strided loop ~6x slower per element (measured).
    dk = _dot(_im2col_t(x, taps=2), s.reshape(-1, 4 * o))
    dk = dk.reshape(2, 2, c, 2, 2, o)  # (ty, tx, c, py, px, o)
    dk = dk[:, :, :, ::-1, ::-1].transpose(0, 3, 1, 4, 2, 5).reshape(4, 4, c, o)
    return dx.astype(x_dtype), dk.astype(kernel.dtype)


_deconv.defvjp(_deconv_fwd, _deconv_bwd)


def conv_transpose4x4s2(x, kernel, bias=None, *, compute_dtype=jnp.bfloat16):
    """PyTorch `ConvTranspose2d(kernel_size=4, stride=2, padding=1)`: (H, W) -> (2H, 2W).

    The kernel is in the `flax.linen.ConvTranspose` layout the U-Net stores: HWIO and spatially
    flipped relative to PyTorch's `(in, out, kH, kW)` weight (see
    `torch_interop.from_torch_state_dict`); i.e. this equals
    `nn.ConvTranspose(O, (4, 4), strides=(2, 2), padding=((2, 2), (2, 2)))`.

    Args:
      x: (N, H, W, C) float.
      kernel: (4, 4, C, O) float32.
      bias: optional (O,) float32.
      compute_dtype: dot operand dtype (`jnp.bfloat16` or `jnp.float32`); accumulation float32.

    Returns:
      (N, 2H, 2W, O) float32.
    """
    _check_layer(x, kernel, 4)
    y = _deconv(x, kernel, _dtype_name(compute_dtype), jnp.dtype(x.dtype).name)
    return y if bias is None else y + bias.astype(jnp.float32)


def conv_transpose4x4s2_flops(h, w, c_in, c_out, batch=1) -> int:
    """Useful multiply-adds x 2 (each output pixel sees 2 x 2 input pixels): input (h, w)."""
    return 2 * batch * (2 * h) * (2 * w) * 4 * c_in * c_out


# ---------------------------------------------------------------------------------------------
# Fused (conditional) instance normalization.


def instance_norm(x, scale, shift, eps=1e-5, relu=False, out_dtype=jnp.float32):
    """`relu?((x - mean) / sqrt(var + eps) * scale + shift)` over (H, W), in one pass.

    Biased variance, as PyTorch's InstanceNorm2d, computed as `max(E[x^2] - mean^2, 0)` from
    one fused float32 reduction of x and x^2, then `x * a + (shift - mean * a)` with
    `a = scale / sqrt(var + eps)` in one elementwise pass. The one-pass variance costs
    ~1e-6 * (mean / std)^2 of relative accuracy (8e-4 at |mean| / std = 30): negligible for the
    U-Net's post-deconv + skip activations, whose |mean| / std is O(1) (the fast U-Net matches the
    two-pass form to ~1e-6 in float32); `eps` keeps a constant patch finite (output = shift up
    to ~1e-7 * |x| / sqrt(eps), finite gradients). (Centering about a pivot pixel first would
    remove the bound but costs XLA:CPU an extra pass: ~2.5x slower.)

    Args:
      x: (N, H, W, C) float.
      scale, shift: (N, C) per-sample affine (CIN: the material's rows) or (C,).
      eps: variance guard.
      relu: apply ReLU (fused into the same elementwise pass).
      out_dtype: result dtype.

    Returns:
      (N, H, W, C) `out_dtype`.
    """
    x = x.astype(jnp.float32)
    mean = jnp.mean(x, axis=(1, 2), keepdims=True)
    mean_sq = jnp.mean(x * x, axis=(1, 2), keepdims=True)
    var = jnp.maximum(mean_sq - mean * mean, 0.0)
    scale = jnp.asarray(scale, jnp.float32)
    shift = jnp.asarray(shift, jnp.float32)
    if scale.ndim == 2:
        scale, shift = scale[:, None, None, :], shift[:, None, None, :]
    a = scale * lax.rsqrt(var + eps)
    y = x * a + (shift - mean * a)
    if relu:
        y = jnp.maximum(y, 0.0)
    return y.astype(out_dtype)
