"""Winograd (Toom-Cook) forms of the U-Net's 3x3 conv and 4x4 stride-2 transposed conv: fewer
multiplications per output than `fastconv`'s im2col, for inference on CPU.

Why: the im2col forms already run their bfloat16 dots near this machine's rate (250-360
GFLOP/s on 2 cores at width 64, AVX512-BF16), so only fewer multiplications make the U-Net
faster. The same holds in float32 on a CPU without bfloat16 units ("winograd_f32" in
`nn.unet`; AVX2-only EPYC, width 64, batch 8: 35-46 against im2col's 61-72 ms/patch). A
Winograd F(m, r) correlation computes m outputs of an r-tap filter from alpha = m + r - 1
inputs with alpha products instead of m r (Lavin & Gray 2016, "Fast Algorithms for
Convolutional Neural Networks"); in 2D, tiles of m x m outputs take alpha^2 products:
  * `conv3x3`: F(2 x 2, 3 x 3), 16 products per 4 outputs instead of 36 (2.25x fewer);
  * `conv_transpose4x4s2`: every output phase of the 4x4 stride-2 transposed conv is a 2 x 2
    correlation of the same input windows (`fastconv._phase_kernel`), so all four phases are
    one F(3 x 3, 2 x 2) correlation with 4 O outputs: 16 products per 9 windows instead of 36
    (2.25x fewer).
Each layer: the input tiles' transform (sums of shifted, strided views: one fused loop), then
alpha^2 independent dots (rows = tiles, contraction = channels) in the compute dtype with float32
accumulation, then the output transform and the interleaving of the m x m tiles. Larger tiles
(F(4 x 4, 3 x 3)) were measured at 2.1 % relative RMS error in bfloat16 and no faster; F(2, 3)
and F(3, 2) use the points 0, 1, -1 (transform coefficients 0, +-1, +-1/2), whose error is
1.5x the im2col form's (about 3.5e-3 against 2.3e-3 relative RMS per layer, measured).

Where it pays: the transforms move alpha^2 / m^2 (4 or 1.8) values per output and channel in
float32, so at few channels they cost more than the saved products. `use_winograd` holds the
rule measured on this machine (`benchmarks/bench_winograd.py`): both channel counts at
least `MIN_CHANNELS` and an input of at least `MIN_SIDE` x `MIN_SIDE` texels.

Gradients (reverse mode, `jax.custom_vjp`): the input gradient of either layer is itself a
correlation (a 3x3 conv of the output gradient with the flipped, transposed kernel; a 2x2
correlation of the space-to-depth output gradient, see `fastconv`), computed by the same
Winograd forms; the kernel gradient is `fastconv`'s im2col one, its patches recomputed from
the saved input (and dropped by XLA when unused, as for a frozen VGG in a loss).
Shapes: NHWC activations, HWIO kernels as `fastconv`.
"""

from __future__ import annotations

import functools
import sys

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from numpy.polynomial import polynomial as npoly

from wrinkle_jax.nn import fastconv

__all__ = ["MIN_CHANNELS", "MIN_SIDE", "conv3x3", "conv_transpose4x4s2", "layer_ops",
           "toom_cook", "use_winograd"]

# Measured rule (see the module docstring): the Winograd form is used for a layer whose input
# and output channels are both >= MIN_CHANNELS and whose input is >= MIN_SIDE texels per side.
MIN_CHANNELS = 64
MIN_SIDE = 16


def toom_cook(m: int, r: int, points) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Transform matrices of the Winograd correlation F(m, r) on the finite `points` plus
    infinity: y = AT @ ((G @ g) * (BT @ d)) is the correlation y[i] = sum_k d[i + k] g[k],
    i < m, of an input d (alpha,) and a filter g (r,), alpha = m + r - 1.

    Args:
      m: outputs per tile; r: filter taps; points: alpha - 1 distinct finite points.
    Returns:
      (AT (m, alpha), G (alpha, r), BT (alpha, alpha)) float64.
    """
    alpha = m + r - 1
    pts = [float(p) for p in points]
    if len(pts) != alpha - 1 or len(set(pts)) != len(pts):
        raise ValueError(f"F({m}, {r}) needs {alpha - 1} distinct finite points, got {points}")
    at, g, bt = np.zeros((m, alpha)), np.zeros((alpha, r)), np.zeros((alpha, alpha))
    for j, p in enumerate(pts):
        others = [q for q in pts if q != p]
        at[:, j] = p ** np.arange(m)
        g[j] = p ** np.arange(r) / np.prod([p - q for q in others])
        bt[j, :alpha - 1] = npoly.polyfromroots(others)  # Lagrange numerator, rising powers
    at[m - 1, alpha - 1] = g[alpha - 1, r - 1] = 1.0  # the point at infinity
    bt[alpha - 1] = npoly.polyfromroots(pts)
    return at, g, bt


F23 = toom_cook(2, 3, (0, 1, -1))  # the 3x3 conv: 2 x 2 output tiles
F32 = toom_cook(3, 2, (0, 1, -1))  # the transposed conv's 2x2 phase windows: 3 x 3 tiles


def use_winograd(c_in: int, c_out: int, side: int) -> bool:
    """The measured rule: Winograd for a layer of c_in -> c_out channels on a `side`-texel
    input (the smaller of H and W)."""
    return min(c_in, c_out) >= MIN_CHANNELS and side >= MIN_SIDE


def layer_ops(x, c_out: int, enabled: bool = True):
    """The module whose `conv3x3` / `conv_transpose4x4s2` runs a layer of input x
    (N, H, W, C) and c_out output channels: this one where `enabled` and the rule picks the
    layer, else `fastconv` (same signatures)."""
    picked = enabled and use_winograd(x.shape[-1], c_out, min(x.shape[1], x.shape[2]))
    return sys.modules[__name__] if picked else fastconv


def _lin(parts, coefs):
    """sum_k coefs[k] parts[k] over the non-zero coefficients (+-1 without a multiply)."""
    out = None
    for c, p in zip(coefs, parts, strict=True):
        if c == 0:
            continue
        term = p if c == 1 else -p if c == -1 else float(c) * p
        out = term if out is None else out + term
    return out


def _input_tiles(xp, bt, m: int, th: int, tw: int):
    """BT d BT^T of every alpha x alpha input tile (stride m) of xp (N, Hp, Wp, C) float32:
    alpha^2 arrays (N, th, tw, C), index u alpha + v."""
    a = bt.shape[0]
    rows = [xp[:, k:k + m * (th - 1) + 1:m] for k in range(a)]
    rt = [_lin(rows, bt[u]) for u in range(a)]
    out = []
    for u in range(a):
        cols = [rt[u][:, :, k:k + m * (tw - 1) + 1:m] for k in range(a)]
        out.extend(_lin(cols, bt[v]) for v in range(a))
    return out


def _kernel_tiles(kernel, g):
    """G k G^T of a (r, r, C, O) kernel: alpha^2 arrays (C, O), index u alpha + v."""
    a, r = g.shape
    rows = [_lin([kernel[i] for i in range(r)], g[u]) for u in range(a)]   # (r, C, O) each
    return [_lin([rows[u][j] for j in range(r)], g[v]) for u in range(a) for v in range(a)]


def _output_tiles(products, at, n: int, th: int, tw: int, o: int):
    """AT M AT^T of the alpha^2 products (N, th, tw, O) float32, interleaved into
    (N, th m, tw m, O)."""
    m, a = at.shape
    grid = [products[u * a:(u + 1) * a] for u in range(a)]
    rows = [[_lin([grid[u][v] for u in range(a)], at[p]) for v in range(a)] for p in range(m)]
    tiles = [[_lin(rows[p], at[q]) for q in range(m)] for p in range(m)]
    y = jnp.stack([jnp.stack(tiles[p], axis=3) for p in range(m)], axis=2)  # (N, th, m, tw, m, O)
    return y.reshape(n, th * m, tw * m, o)


def _correlate(xp, kernel, transform, th: int, tw: int, dtype):
    """Valid 2D correlation of xp (N, Hp, Wp, C) with kernel (r, r, C, O) on th x tw output
    tiles of m x m: (N, th m, tw m, O) float32. Dots in `dtype` with float32 accumulation."""
    at, g, bt = (np.asarray(t, np.float32) for t in transform)
    m = at.shape[0]
    n, o = xp.shape[0], kernel.shape[-1]
    tiles = _input_tiles(xp.astype(jnp.float32), bt, m, th, tw)
    # Materialize the transformed tiles and the products once: fused into their consumers,
    # XLA:CPU re-derives them per use (measured 2-3x slower layers).
    tiles = lax.optimization_barrier([t.astype(dtype) for t in tiles])
    kern = _kernel_tiles(kernel.astype(jnp.float32), g)
    products = [lax.dot_general(t, k.astype(dtype), (((3,), (0,)), ((), ())),
                                preferred_element_type=jnp.float32)
                for t, k in zip(tiles, kern, strict=True)]
    products = lax.optimization_barrier(products)
    return _output_tiles(products, at, n, th, tw, o)


def _conv3x3_forward(x, kernel, padding: str, dtype):
    _, h, w, _ = x.shape
    th, tw = -(-h // 2), -(-w // 2)
    if padding == "REFLECT":
        x = jnp.pad(x, ((0, 0), (1, 1), (1, 1), (0, 0)), mode="reflect")
        lo = 0
    else:
        lo = 1
    # Rows m th + 2 in all; the extra zero rows/columns only reach discarded outputs.
    xp = jnp.pad(x, ((0, 0), (lo, 2 * th + 2 - lo - x.shape[1]),
                     (lo, 2 * tw + 2 - lo - x.shape[2]), (0, 0)))
    return _correlate(xp, kernel, F23, th, tw, dtype)[:, :h, :w]


def _deconv_forward(x, kernel, dtype):
    n, h, w, c = x.shape
    o = kernel.shape[-1]
    # The (h + 1) x (w + 1) windows of x zero-padded by 1 give every phase
    # (`fastconv._deconv_forward`); tiles of 3 windows need 3 th + 1 padded rows.
    th, tw = -(-(h + 1) // 3), -(-(w + 1) // 3)
    xp = jnp.pad(x, ((0, 0), (1, 3 * th - h), (1, 3 * tw - w), (0, 0)))
    phases = fastconv._phase_kernel(kernel).reshape(2, 2, c, 4 * o)
    z = _correlate(xp, phases, F32, th, tw, dtype)[:, :h + 1, :w + 1]
    return fastconv._depth_to_space(z.reshape(n, h + 1, w + 1, 2, 2, o), h, w)


@functools.partial(jax.custom_vjp, nondiff_argnums=(2, 3))
def _conv3x3(x, kernel, padding, compute):
    return _conv3x3_forward(x, kernel, padding, fastconv._DTYPES[compute])


def _conv3x3_fwd(x, kernel, padding, compute):
    return _conv3x3(x, kernel, padding, compute), (x, kernel)


def _kernel_grad(fn, x, kernel, g):
    """The kernel gradient of the im2col form `fn(x, kernel)` (its forward's patches are
    recomputed; XLA drops all of it when the caller does not use the kernel gradient, e.g.
    the frozen VGG of a loss)."""
    _, vjp = jax.vjp(lambda k: fn(x, k), kernel)
    return vjp(g)[0]


def _conv3x3_bwd(padding, compute, res, g):
    x, kernel = res
    dt = fastconv._DTYPES[compute]
    _, h, w, _ = x.shape
    k_in = fastconv._flip_transpose(kernel)  # the input gradient is a 3x3 conv of g with it
    if padding == "ZERO":
        dx = _conv3x3_forward(g, k_in, "ZERO", dt)
    else:  # full correlation onto the reflection-padded input, then its adjoint
        th, tw = -(-(h + 2) // 2), -(-(w + 2) // 2)
        gp = jnp.pad(g, ((0, 0), (2, 2 * th - h), (2, 2 * tw - w), (0, 0)))
        dx = fastconv._reflect_pad_adjoint(_correlate(gp, k_in, F23, th, tw, dt)[:, :h + 2,
                                                                                 :w + 2])
    dk = _kernel_grad(functools.partial(fastconv.conv3x3, compute_dtype=compute,
                                        padding=padding), x, kernel, g)
    return dx.astype(x.dtype), dk


_conv3x3.defvjp(_conv3x3_fwd, _conv3x3_bwd)


@functools.partial(jax.custom_vjp, nondiff_argnums=(2,))
def _deconv(x, kernel, compute):
    return _deconv_forward(x, kernel, fastconv._DTYPES[compute])


def _deconv_fwd(x, kernel, compute):
    return _deconv(x, kernel, compute), (x, kernel)


def _deconv_bwd(compute, res, g):
    x, kernel = res
    dt = fastconv._DTYPES[compute]
    _, h, w, _ = x.shape
    c, o = kernel.shape[2:]
    # The input gradient: a 2x2 valid correlation of the space-to-depth output gradient
    # (N, H+1, W+1, 4 O) with `fastconv._grad_kernel` (`fastconv._deconv_bwd`), by F(3, 2).
    s2d = fastconv._space_to_depth_padded(g.astype(jnp.float32))
    th, tw = -(-h // 3), -(-w // 3)
    sp = jnp.pad(s2d, ((0, 0), (0, 3 * th + 1 - (h + 1)), (0, 3 * tw + 1 - (w + 1)), (0, 0)))
    k_in = fastconv._grad_kernel(kernel).reshape(2, 2, 4 * o, c)
    dx = _correlate(sp, k_in, F32, th, tw, dt)[:, :h, :w]
    dk = _kernel_grad(functools.partial(fastconv.conv_transpose4x4s2, compute_dtype=compute),
                      x, kernel, g)
    return dx.astype(x.dtype), dk


_deconv.defvjp(_deconv_fwd, _deconv_bwd)


def conv3x3(x, kernel, bias=None, *, compute_dtype=jnp.bfloat16, padding="ZERO"):
    """`fastconv.conv3x3` (3x3 stride-1 "same" cross-correlation) by F(2 x 2, 3 x 3).

    Args:
      x: (N, H, W, C) float; any H, W >= 1.
      kernel: (3, 3, C, O) float32 HWIO.
      bias: optional (O,) float32.
      compute_dtype: dot operand dtype (`jnp.bfloat16` fast, `jnp.float32` exact to float32
        rounding); transforms and accumulation are float32.
      padding: "ZERO" or "REFLECT".
    Returns:
      (N, H, W, O) float32.

    Example:
      >>> x = jnp.ones((1, 8, 8, 4)); k = jnp.ones((3, 3, 4, 5)) / 36
      >>> y = jax.jit(conv3x3)(x, k)            # interior 1, corner 4/9, to bfloat16 rounding
      >>> y.shape, round(float(y[0, 4, 4, 0]), 2), round(float(y[0, 0, 0, 0]), 2)
      ((1, 8, 8, 5), 1.0, 0.44)
    """
    fastconv._check_layer(x, kernel, 3, padding)
    y = _conv3x3(x, kernel, padding, fastconv._dtype_name(compute_dtype))
    return y if bias is None else y + bias.astype(jnp.float32)


def conv_transpose4x4s2(x, kernel, bias=None, *, compute_dtype=jnp.bfloat16):
    """`fastconv.conv_transpose4x4s2` (PyTorch `ConvTranspose2d(4, stride 2, padding 1)`,
    Flax kernel layout) by F(3 x 3, 2 x 2) on its four phases.

    Args:
      x: (N, H, W, C) float. kernel: (4, 4, C, O) float32. bias: optional (O,).
      compute_dtype: dot operand dtype; transforms and accumulation are float32.
    Returns:
      (N, 2H, 2W, O) float32.
    """
    fastconv._check_layer(x, kernel, 4)
    y = _deconv(x, kernel, fastconv._dtype_name(compute_dtype))
    return y if bias is None else y + bias.astype(jnp.float32)
