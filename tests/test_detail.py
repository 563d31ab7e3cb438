"""The detail representation: exact inverse, orthogonality, flat panels to +z, equivariance,
both branches, and finite gradients near the pole."""

import doctest

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from wrinkle_jax import detail


def _unit(v):
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _random_normals(seed, shape=(2, 16, 16)):
    return _unit(np.random.default_rng(seed).normal(size=(*shape, 3))).astype(np.float32)


def _rot_y(deg):
    a = np.deg2rad(deg)
    return np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]],
                    np.float32)


def _rot_z(deg):
    a = np.deg2rad(deg)
    return np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]],
                    np.float32)


def _wrinkled(size=64, wavelength=8.0, amp=0.6):
    """Normals of z = h(x), h = a sin(2 pi x / wavelength) (texel units): a flat panel with
    parallel wrinkles, facing +z."""
    x = np.arange(size, dtype=np.float32)
    slope = amp * 2 * np.pi / wavelength * np.cos(2 * np.pi * x / wavelength)
    n = np.zeros((1, size, size, 3), np.float32)
    n[..., 0] = -slope[None, None, :]
    n[..., 2] = 1.0
    return _unit(n).astype(np.float32)


@pytest.mark.parametrize("branch", [1.0, -1.0])
def test_from_detail_inverts_to_detail_and_preserves_angles(branch):
    n, m = _random_normals(0), _random_normals(1)
    large = _random_normals(2)
    # Keep L off the branch's pole (the guard makes R inexact within ~2.6 degrees of it).
    large[..., 2] = np.abs(large[..., 2]) * branch
    large = _unit(large + np.array([0, 0, 0.3 * branch], np.float32)).astype(np.float32)
    b = jnp.full((2,), branch)
    d = detail.to_detail(n, large, b)
    np.testing.assert_allclose(detail.from_detail(d, large, b), n, atol=2e-5)
    np.testing.assert_allclose(np.linalg.norm(d, axis=-1), 1.0, atol=2e-5)
    # A rotation keeps dot products between vectors at the same texel.
    dm = detail.to_detail(m, large, b)
    np.testing.assert_allclose(np.sum(d * dm, -1), np.sum(n * m, -1), atol=3e-5)
    # ... and takes the large scale itself to +z.
    np.testing.assert_allclose(detail.to_detail(large, large, b)[..., 2], 1.0, atol=2e-5)


@pytest.mark.parametrize("direction", [(1, 0, 0), (0, 0, -1), (0.3, -0.8, -0.5), (0, 0, 1)])
def test_flat_panel_becomes_plus_z_in_any_orientation(direction):
    n = np.broadcast_to(_unit(np.asarray(direction, np.float32)), (1, 24, 24, 3))
    mask = np.ones((1, 24, 24, 1), np.float32)
    mask[:, :5] = 0  # a border: the first-order blur keeps the panel's normal up to it
    d = np.asarray(detail.to_detail_rgb((n + 1) / 2, mask, sigma=4.0))
    inside = mask[..., 0] > 0
    np.testing.assert_allclose(d[inside], np.broadcast_to([0.5, 0.5, 1.0], d[inside].shape),
                               atol=1e-4)
    assert np.all(d[~inside] == 0)


def test_global_tilt_leaves_the_detail_unchanged():
    n = _wrinkled()
    mask = np.ones(n.shape[:-1] + (1,), np.float32)
    q = _rot_y(50.0)  # L = q z: the minimal rotation back is q^T, so no twist
    d0 = detail.decompose(n, mask, 6.0)[0]
    d1 = detail.decompose(n @ q.T, mask, 6.0)[0]
    np.testing.assert_allclose(d1, d0, atol=2e-3)
    # The wrinkles survive (the low-pass at sigma 6 removes < 1 % of an 8-texel wave).
    np.testing.assert_allclose(d0[0, 16:48, 16:48], n[0, 16:48, 16:48], atol=2e-2)


def test_rotation_about_z_twists_the_detail_alike():
    n = _wrinkled() @ _rot_y(30.0).T
    mask = np.ones(n.shape[:-1] + (1,), np.float32)
    q = _rot_z(70.0)
    d0 = detail.decompose(n, mask, 6.0)[0]
    d1 = detail.decompose(n @ q.T, mask, 6.0)[0]
    np.testing.assert_allclose(d1, d0 @ q.T, atol=2e-5)


def test_branch_follows_the_mean_large_scale_and_is_shared_when_given():
    up = np.broadcast_to(np.float32([0, 0.6, 0.8]), (1, 16, 16, 3))
    down = np.broadcast_to(np.float32([0, 0.6, -0.8]), (1, 16, 16, 3))
    n = np.concatenate([up, down])
    mask = np.ones((2, 16, 16, 1), np.float32)
    _, large, branch = detail.decompose(n, mask, 4.0)
    np.testing.assert_array_equal(branch, [1.0, -1.0])
    d_own = detail.to_detail_rgb((n + 1) / 2, mask, 4.0)
    d_shared = detail.to_detail_rgb((n + 1) / 2, mask, 4.0, branch=np.float32([-1, 1]))
    # Either branch takes a smooth field to +z; only the twist of the detail differs.
    np.testing.assert_allclose(d_own[..., 2], 1.0, atol=1e-5)
    np.testing.assert_allclose(d_shared[..., 2], 1.0, atol=1e-5)


def test_round_trip_through_the_rgb_forms():
    n = _wrinkled(32) @ _rot_y(120.0).T  # mostly facing -z: branch -1
    mask = np.ones(n.shape[:-1] + (1,), np.float32)
    x = (n + 1) / 2
    d, large, branch = detail.decompose(n, mask, 4.0)
    assert float(branch[0]) == -1.0
    back = detail.from_detail_rgb((d + 1) / 2, large, branch, mask)
    np.testing.assert_allclose(back, x, atol=2e-5)


def test_gradients_are_finite_and_match_finite_differences():
    jax.config.update("jax_enable_x64", True)
    try:
        n = (_wrinkled(32) @ _rot_y(175.0).T).astype(np.float64)  # near -z: branch -1
        mask = np.ones(n.shape[:-1] + (1,))
        w = np.random.default_rng(3).normal(size=n.shape)

        # Jitted (an op-by-op backward pass compiles each of its primitives separately).
        @jax.jit
        def f(x):
            return jnp.sum(detail.to_detail_rgb(x, mask, 4.0) * w)

        x = (n + 1) / 2
        g = jax.jit(jax.grad(f))(x)
        assert np.all(np.isfinite(g))
        v = np.random.default_rng(4).normal(size=x.shape)
        h = 1e-6
        fd = (f(x + h * v) - f(x - h * v)) / (2 * h)
        np.testing.assert_allclose(np.sum(g * v), fd, rtol=1e-5)
    finally:
        jax.config.update("jax_enable_x64", False)


def test_transplant_carries_the_donors_detail_onto_the_large_scale():
    wrinkled = _wrinkled(32)
    mask = np.ones(wrinkled.shape[:-1] + (1,), np.float32)
    x = (wrinkled @ _rot_y(60.0).T + 1) / 2          # the wrinkles on a tilted panel
    donor = (wrinkled @ _rot_z(90.0).T @ _rot_y(-35.0).T + 1) / 2  # twisted, other tilt
    # A map given its own detail is itself.
    np.testing.assert_allclose(detail.transplant_rgb(x, x, mask, mask, 4.0), x, atol=2e-5)
    # The donor's detail, not x's: the result's detail is the donor's (its twist included),
    # whatever the donor's own large-scale orientation.
    out = detail.transplant_rgb(x, donor, mask, mask, 4.0)
    d_out = np.asarray(detail.to_detail_rgb(out, mask, 4.0))
    d_donor = np.asarray(detail.to_detail_rgb(donor, mask, 4.0))
    d_x = np.asarray(detail.to_detail_rgb(x, mask, 4.0))
    inner = (slice(None), slice(8, -8), slice(8, -8))
    err = np.abs(d_out - d_donor)[inner].max()
    assert err < 0.02, err
    assert np.abs(d_x - d_donor)[inner].max() > 0.1  # 5x the bound: the test tells them apart
    # Where the donor has no garment, only x's large scale remains (detail +z).
    half = mask.copy()
    half[:, :, 16:] = 0.0
    out = detail.transplant_rgb(x, donor, mask, half, 4.0)
    _, large, _ = detail.decompose(x * 2.0 - 1.0, mask, 4.0)
    np.testing.assert_allclose(np.asarray(out)[:, :, 16:],
                               ((np.asarray(large) + 1) / 2)[:, :, 16:],
                               atol=2e-5)


def test_module_example():
    assert doctest.testmod(detail, raise_on_error=False).failed == 0
