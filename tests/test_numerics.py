"""Tests for `wrinkle_jax.numerics.to_device` and the set-up code that uses it (issue 22: in a
fresh notebook kernel every eager jnp op compiles an XLA program, 20-40 ms each)."""

from __future__ import annotations

import contextlib

import jax
import jax.numpy as jnp
import numpy as np

from wrinkle_jax import bodies, lift, normalmap, primitives
from wrinkle_jax.numerics import to_device


@contextlib.contextmanager
def _compiles():
    """Collect the names of the XLA programs compiled inside the block."""
    names = []

    def listener(event, duration, **kw):
        if event == "/jax/core/compile/backend_compile_duration":
            names.append(kw.get("fun_name"))

    jax.monitoring.register_event_duration_secs_listener(listener)
    try:
        yield names
    finally:
        jax.monitoring.unregister_event_duration_listener(listener)


def test_to_device_returns_what_jnp_asarray_returns():
    rng = np.random.default_rng(0)
    leaves = [rng.normal(size=(3, 7)), rng.integers(0, 9, (5,)), np.array([True, False]),
              rng.normal(size=(2, 3)).astype(np.float16), np.float32(2.5)]
    got = to_device({"a": leaves[:3], "b": tuple(leaves[3:])})
    assert isinstance(got, dict) and isinstance(got["b"], tuple)
    for x, y in zip(leaves, jax.tree.leaves(got), strict=True):
        want = jnp.asarray(x)
        assert isinstance(y, jax.Array)
        assert (y.dtype, y.shape, y.weak_type) == (want.dtype, want.shape, want.weak_type)
        np.testing.assert_array_equal(np.asarray(y), np.asarray(want))
    # With a dtype: the host cast rounds like XLA's convert.
    x = rng.normal(size=(4, 3)) * 1e3
    y, want = to_device(x, np.float32), jnp.asarray(x, jnp.float32)
    assert y.dtype == want.dtype and not y.weak_type
    np.testing.assert_array_equal(np.asarray(y), np.asarray(want))


def test_set_up_functions_compile_nothing():
    # Odd sizes: shapes no other test has compiled a one-op program for.
    sheet = primitives.grid_sheet(3, 7, size=(0.06, 0.14))
    with _compiles() as names:
        plan = normalmap.make_plan(sheet, texel_size=0.0037)
        topology = lift.lift_topology(sheet.faces, sheet.num_vertices)
        body = bodies.primitive_body(spheres=([[0.0, 0.0, 0.1]] * 3, 0.05))
        to_device(np.zeros((13, 3), np.float64), np.float32)
    assert names == []
    assert all(isinstance(a, jax.Array) for a in jax.tree.leaves((plan, topology, body)))


def test_three_component_forms_match_the_general_ones():
    """dot3 / norm3 / normalize3 (multiply-adds, for speed on CPU) against jnp.sum, safe_norm
    and normalize: the same values, zero vectors giving 0 with finite gradients."""
    from wrinkle_jax.numerics import dot3, norm3, normalize, normalize3, safe_norm

    rng = np.random.default_rng(5)
    a = jnp.asarray(rng.normal(size=(4, 7, 3)), jnp.float32).at[0, 0].set(0.0)
    b = jnp.asarray(rng.normal(size=(4, 7, 3)), jnp.float32)
    np.testing.assert_allclose(dot3(a, b), jnp.sum(a * b, -1), rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(norm3(a), safe_norm(a), rtol=1e-6)
    np.testing.assert_allclose(normalize3(a), normalize(a), rtol=1e-6, atol=1e-7)
    assert float(norm3(a)[0, 0]) == 0.0 and not np.asarray(normalize3(a)[0, 0]).any()
    for f in (norm3, lambda x: normalize3(x)[..., 0]):
        g = jax.grad(lambda x, f=f: jnp.sum(f(x)))(a)
        assert np.isfinite(np.asarray(g)).all()
        assert not np.asarray(g[0, 0]).any()
