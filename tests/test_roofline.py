"""roofline: the dots read from optimized HLO, their FLOPs and their replay alone."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from wrinkle_jax import roofline
from wrinkle_jax.nn import fastconv, winograd


def _dots(fn, *args):
    return roofline.program_dots(jax.jit(fn).lower(*args).compile())


def test_matmul_shapes_and_flops():
    a, b = jnp.ones((64, 32)), jnp.ones((32, 16))
    (d,) = _dots(lambda x, y: x @ y, a, b)
    assert (d.lhs_shape, d.rhs_shape, d.out_shape) == ((64, 32), (32, 16), (64, 16))
    assert (d.lhs_dtype, d.out_dtype) == ("f32", "f32")
    assert d.flops == 2 * 64 * 32 * 16 and not d.in_loop


def test_batched_dot_reads_batch_dims():
    a, b = jnp.ones((3, 8, 5)), jnp.ones((3, 5, 7))
    (d,) = _dots(lambda x, y: jnp.einsum("bij,bjk->bik", x, y), a, b)
    assert d.lhs_batch == (0,) and d.rhs_batch == (0,)
    assert d.flops == 2 * 3 * 8 * 5 * 7


def test_conv_forms_flops_match_their_counts():
    """The im2col conv's one dot carries exactly conv3x3_flops; the Winograd form's 16 dots
    carry 16 / 36 of it on a tile-aligned input."""
    x, k = jnp.ones((2, 16, 16, 64)), jnp.ones((3, 3, 64, 64))
    direct = fastconv.conv3x3_flops(16, 16, 64, 64, 2)
    im2col = _dots(lambda a, b: fastconv.conv3x3(a, b), x, k)
    wino = _dots(lambda a, b: winograd.conv3x3(a, b), x, k)
    assert len(im2col) == 1 and roofline.dots_flops(im2col) == direct
    assert len(wino) == 16 and roofline.dots_flops(wino) * 36 == direct * 16
    (d, count), = roofline.unique_dots(wino)
    assert count == 16 and d.lhs_dtype == "bf16" and d.out_dtype == "f32"


def test_dead_dots_are_not_counted():
    """The gradient of a conv w.r.t. input and kernel runs two dots: the forward product the
    custom VJP traces is dead and XLA drops it."""
    x, k = jnp.ones((2, 16, 16, 8)), jnp.ones((3, 3, 8, 4))
    grads = jax.grad(lambda a, b: fastconv.conv3x3(a, b).sum(), argnums=(0, 1))
    dots = _dots(grads, x, k)
    assert len(dots) == 2
    assert roofline.dots_flops(dots) == 2 * fastconv.conv3x3_flops(16, 16, 8, 4, 2)


def test_dot_in_a_loop_is_flagged():
    def f(x, w, n):
        return jax.lax.fori_loop(0, n, lambda i, v: jnp.tanh(v @ w), x)

    dots = _dots(f, jnp.ones((8, 8)), jnp.ones((8, 8)), 3)
    assert dots and all(d.in_loop for d in dots)


@pytest.mark.parametrize("lhs_layout", [(1, 0), (0, 1)])
def test_replay_computes_the_logical_product(lhs_layout):
    """The replayed dot stores each operand as the program does (layout (0, 1): column-major,
    i.e. a row-major array of the transposed shape) and still computes the logical product:
    checked against NumPy on the operands read back in logical order."""
    d = roofline.Dot((6, 4), (4, 5), (6, 5), lhs_layout, (1, 0), "f32", "f32", "f32", (1,), (0,))
    run, (p, q) = roofline.dot_runner(d)
    order = list(reversed(lhs_layout))  # physical axes, major to minor
    assert p.shape == tuple(d.lhs_shape[i] for i in order)
    lhs = np.transpose(np.asarray(p), np.argsort(order))  # back to the logical (6, 4)
    out = np.asarray(run(p, q))
    assert out.shape == d.out_shape
    np.testing.assert_allclose(out, lhs @ np.asarray(q), rtol=1e-5, atol=1e-5)
    assert roofline.operand_bytes(d) == 4 * (24 + 20)


def test_replay_of_a_program_dot_runs():
    a, b = jnp.ones((48, 24)), jnp.ones((48, 16))
    (d,) = _dots(lambda x, y: x.T @ y, a, b)
    run, ops = roofline.dot_runner(d)
    assert np.asarray(run(*ops)).shape == d.out_shape == (24, 16)


def test_layout_maps_logical_dims():
    shape, dims = roofline._physical((3, 5), (0, 1), (1,))
    assert shape == (5, 3) and dims == (0,)
