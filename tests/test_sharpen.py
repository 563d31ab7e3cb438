"""Tests for wrinkle_jax.sharpen: the JAX unsharp mask against the OpenCV baseline, its
invariants and gradients, and the U-Net's unsharp residual base."""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from wrinkle_jax import evaluation, sharpen
from wrinkle_jax.nn import unet


def _folds(n=3, size=32, seed=0):
    """Random folds with ripples as RGB-form unit normals, inside a disc mask (so the mask's
    border crosses rows and columns at every angle)."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:size, 0:size] / size
    out = []
    for _ in range(n):
        a, b, c = rng.uniform(1, 4, 3)
        gx = 0.6 * np.sin(2 * np.pi * a * x + rng.uniform(0, 6)) + 0.2 * np.sin(2 * np.pi * 7 * y)
        gy = 0.6 * np.cos(2 * np.pi * b * y) + 0.2 * np.sin(2 * np.pi * c * (x + y))
        nrm = np.stack([-gx, -gy, np.ones_like(gx)], -1)
        out.append((nrm / np.linalg.norm(nrm, axis=-1, keepdims=True) + 1) / 2)
    disc = ((x - 0.45) ** 2 + (y - 0.5) ** 2 < 0.4**2).astype(np.float32)
    mask = np.broadcast_to(disc[None, ..., None], (n, size, size, 1)).copy()
    return (np.asarray(out, np.float32) * mask).astype(np.float32), mask


def test_gaussian_kernel_normalized_and_symmetric():
    for sigma in (0.7, 2.0, 8.0):
        g = sharpen.gaussian_kernel(sigma)
        assert len(g) == 2 * np.ceil(3 * sigma) + 1
        np.testing.assert_allclose(g.sum(), 1.0, rtol=1e-6)
        np.testing.assert_array_equal(g, g[::-1])


@pytest.mark.parametrize("order", [0, 1])
@pytest.mark.parametrize("sigma,amount", [(1.0, 0.5), (2.0, 1.0), (8.0, 2.0)])
def test_matches_opencv_baseline(sigma, amount, order):
    x, m = _folds()
    want = evaluation.unsharp_mask(x, m, sigma, amount, order)
    got = np.asarray(sharpen.unsharp_rgb(x, sigma, amount, m, order))
    np.testing.assert_allclose(got, want, atol=5e-5)
    # The inferred mask is the true one (background 0, normals never all-zero in RGB form).
    got_inferred = np.asarray(sharpen.unsharp_rgb(x, sigma, amount, order=order))
    np.testing.assert_allclose(got_inferred, want, atol=5e-5)


def _ramp(size=48):
    """A field linear in both texel coordinates, (1, size, size, 3), and a disc mask whose
    border cuts it at every angle, plus a one-texel-wide diagonal strip mask."""
    y, x = np.mgrid[0:size, 0:size].astype(np.float32)
    field = np.stack([0.3 + 0.01 * x, -0.2 + 0.012 * y, 0.5 - 0.004 * x + 0.006 * y], -1)[None]
    disc = ((x - 20) ** 2 + (y - 26) ** 2 < 17**2).astype(np.float32)[None, ..., None]
    strip = (np.abs(x - y) < 0.5).astype(np.float32)[None, ..., None]
    return field.astype(np.float32), disc, strip


def test_local_plane_blur_keeps_linear_fields_up_to_the_border():
    """Order 1 is exact on a linear field everywhere inside the mask (the ridge costs ~0.1 % of
    the slope); order 0 lags it along the border: the spurious ramp that unsharp masking
    amplifies on flat tilted panels."""
    field, disc, strip = _ramp()
    inside = disc[..., 0] > 0
    err1 = np.abs(np.asarray(sharpen.masked_blur(field, disc, 6.0, 1)) - field)[inside]
    err0 = np.abs(np.asarray(sharpen.masked_blur(field, disc, 6.0, 0)) - field)[inside]
    assert err1.max() < 2e-3 * np.abs(field).max()
    assert err0.max() > 20 * err1.max()
    # A one-texel-wide diagonal strip: the slope across it is undetermined (the ridge makes the
    # fit fall back), the one along it is exact: the field is still kept, and all is finite.
    got = np.asarray(sharpen.masked_blur(field, strip, 6.0, 1))
    assert np.all(np.isfinite(got))
    on = strip[..., 0] > 0
    np.testing.assert_allclose(got[on], field[on], atol=2e-3)
    assert np.all(got[~on] == 0)
    with pytest.raises(ValueError, match="order"):
        sharpen.masked_blur(field, disc, 6.0, order=2)


def test_per_patch_amount_and_identity_at_zero():
    x, m = _folds(n=2)
    both = np.asarray(sharpen.unsharp_rgb(x, 2.0, jnp.array([0.0, 1.5]), m, 1))
    np.testing.assert_allclose(both[0], x[0], atol=1e-6)  # amount 0: unchanged
    np.testing.assert_allclose(both[1],
                               np.asarray(sharpen.unsharp_rgb(x[1:], 2.0, 1.5, m[1:], 1))[0],
                               atol=1e-6)


def test_constant_field_is_fixed_and_background_stays_zero():
    m = np.zeros((1, 24, 24, 1), np.float32)
    m[:, 3:17, 5:20] = 1
    n = np.array([0.3, -0.2, 0.9])
    x = ((n / np.linalg.norm(n) + 1) / 2 * m).astype(np.float32)
    out = np.asarray(sharpen.unsharp_rgb(x, 4.0, 3.0, m, 1))
    # The normalized-convolution blur of a constant is that constant up to the mask's border:
    # the background never bleeds in, so sharpening changes nothing.
    np.testing.assert_allclose(out, x, atol=1e-5)
    assert np.all(out[m[..., 0] == 0] == 0)


def test_sharpening_adds_detail():
    x, m = _folds()
    out = np.asarray(sharpen.unsharp_rgb(x, 2.0, 1.0, m))
    inside = m[..., 0] > 0

    def grad_energy(a):
        d = np.abs(np.diff(a, axis=2)).sum(-1)
        return d[inside[:, :, 1:] & inside[:, :, :-1]].mean()

    assert grad_energy(out) > 1.2 * grad_energy(x)


@pytest.mark.parametrize("order", [0, 1])
def test_gradient_matches_finite_differences(order):
    x, m = _folds(n=1, size=24)
    w = jnp.asarray(np.random.default_rng(1).normal(size=x.shape), jnp.float32)

    # Jitted (an op-by-op backward pass compiles each of its primitives separately).
    @jax.jit
    def f(amount, xx):
        return jnp.sum(w * sharpen.unsharp_rgb(xx, 2.0, amount, m, order))

    g_a, g_x = jax.jit(jax.grad(f, argnums=(0, 1)))(jnp.float32(0.8), jnp.asarray(x))
    h = 1e-2
    fd = (f(jnp.float32(0.8 + h), x) - f(jnp.float32(0.8 - h), x)) / (2 * h)
    np.testing.assert_allclose(float(g_a), float(fd), rtol=2e-2)
    assert np.all(np.isfinite(np.asarray(g_x)))
    # A directional derivative with respect to the input, inside the mask.
    d = jnp.asarray(np.random.default_rng(2).normal(size=x.shape) * m * 1e-3, jnp.float32)
    fd_x = (f(jnp.float32(0.8), x + d) - f(jnp.float32(0.8), x - d)) / 2
    np.testing.assert_allclose(float(jnp.sum(g_x * d)), float(fd_x), rtol=5e-2)


def test_unet_unsharp_base_starts_as_unsharp_mask():
    x, m = _folds(n=2)
    model = unet.UNetConfig(width=4, residual=True, residual_base="unsharp", unsharp_sigma=2.0,
                            unsharp_amount=1.5).module(3)
    params = unet.init_params(model, jax.random.key(0, impl="rbg"), 32)
    assert params["unsharp_amount"].shape == (3,)
    params = {**params, "out": jax.tree.map(jnp.zeros_like, params["out"])}
    apply = jax.jit(model.apply)  # one program for both calls (op by op: every primitive)
    got = np.asarray(apply({"params": params}, x, jnp.array([0, 2])))
    np.testing.assert_allclose(got, np.asarray(sharpen.unsharp_rgb(x, 2.0, 1.5)), atol=1e-6)
    # The per-material gain is a live parameter: material 2's gain to 0 gives back its input.
    params["unsharp_amount"] = params["unsharp_amount"].at[2].set(0.0)
    got = np.asarray(apply({"params": params}, x, jnp.array([0, 2])))
    np.testing.assert_allclose(got[1], x[1], atol=1e-6)
    # Raised while tracing: eval_shape traces init without running it (op by op, every
    # parameter draw before the check compiles on its own).
    with pytest.raises(ValueError, match="residual_base"):
        jax.eval_shape(unet.CINUNet(unet.UNetConfig(width=4, residual=True,
                                                    residual_base="blur")).init,
                       jax.random.key(0, impl="rbg"), x, jnp.array([0, 0]))


# The width-4, 2-material U-Nets on an unsharp base below have the same parameters whatever
# their blur radii and high-pass (neither adds one): one compiled init makes them all.
_init_unsharp_unet = jax.jit(lambda key: unet.init_params(
    unet.UNetConfig(width=4, residual=True, residual_base="unsharp").module(2), key, 32))


def _unsharp_params(seed):
    return _init_unsharp_unet(jax.random.key(seed, impl="rbg"))


def test_highpassed_residual_cannot_shift_orientation():
    """A constant residual (the output conv's bias alone) tilts every normal of a patch; the
    high-passed residual removes it exactly, while detail still passes."""
    x, _ = _folds(n=2)
    cfg = unet.UNetConfig(width=4, residual=True, residual_base="unsharp", unsharp_sigma=2.0)
    plain = cfg.module(2)
    hp = dataclasses.replace(cfg, residual_highpass=4.0).module(2)
    params = _unsharp_params(0)
    bias = jnp.array([0.3, -0.2, 0.1])
    params = {**params, "out": {"kernel": jnp.zeros_like(params["out"]["kernel"]),
                                "bias": bias}}
    base = np.asarray(sharpen.unsharp_rgb(x, 2.0, 1.0))
    m = np.asarray(sharpen.mask_from_rgb(x))
    # Jitted, one program per network for both parameter sets (op by op, every primitive).
    plain_apply, hp_apply = (jax.jit(functools.partial(net.apply, x=x, material=jnp.array([0, 1])))
                             for net in (plain, hp))
    got_plain = np.asarray(plain_apply({"params": params}))
    got_hp = np.asarray(hp_apply({"params": params}))
    np.testing.assert_allclose(got_plain, base + np.asarray(bias), atol=1e-6)
    np.testing.assert_allclose(got_hp * m, base, atol=1e-5)
    # Random weights: the residual is not zero, and its masked mean is far below the plain one
    # (order 1's border extrapolation keeps a little more of a random field's mean than
    # order 0's local mean would: ~12 % here against the plain residual).
    params = _unsharp_params(1)
    r_plain = np.asarray(plain_apply({"params": params})) - base
    r_hp = (np.asarray(hp_apply({"params": params})) - base) * m
    assert np.abs(r_hp).mean() > 1e-3
    mean_hp = np.abs(r_hp.sum((1, 2)) / m.sum((1, 2))).max()
    mean_plain = np.abs((r_plain * m).sum((1, 2)) / m.sum((1, 2))).max()
    assert mean_hp < 0.2 * mean_plain


def _random_masked(shape, seed):
    """Random values on random blob masks (holes, islands, one-texel strips, an empty patch),
    with a soft-edged weight on one patch."""
    rng = np.random.default_rng(seed)
    n, h, w, c = shape
    y, x = np.mgrid[0:h, 0:w]
    masks = []
    for i in range(n):
        cy, cx, r = rng.uniform(0, h), rng.uniform(0, w), rng.uniform(0.2, 0.8) * max(h, w)
        m = ((y - cy) ** 2 + (x - cx) ** 2 < r**2) & (rng.uniform(size=(h, w)) > 0.05)
        m |= np.abs(x - y - i) < 0.5  # a one-texel diagonal strip
        masks.append(m)
    mask = np.asarray(masks, np.float32)[..., None]
    mask[-1] = 0.0  # nothing to blur
    if n > 2:
        mask[1] *= rng.uniform(0.5, 1.0, (h, w, 1)).astype(np.float32)
    vals = rng.normal(size=shape).astype(np.float32)
    return jnp.asarray(vals), jnp.asarray(mask)


@pytest.mark.parametrize("order", [0, 1])
@pytest.mark.parametrize("shape,sigma", [((4, 32, 32, 3), 2.0), ((3, 48, 40, 2), 6.0),
                                         ((3, 128, 128, 3), 8.0), ((2, 128, 128, 6), 16.0)])
def test_shared_moment_blur_matches_the_reference_formula(shape, sigma, order):
    """The blur with shared moment passes equals the original formula to float32 rounding, on
    random values and masks, for non-square patches and kernels wider than the patch."""
    n, mask = _random_masked(shape, seed=int(sigma) + order)
    got = np.asarray(sharpen.masked_blur(n, mask, sigma, order))
    want = np.asarray(sharpen.masked_blur_reference(n, mask, sigma, order))
    assert np.all(np.isfinite(got))
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-5 * np.abs(want).max())
    assert np.all(got[-1] == 0)  # the empty patch


def test_shared_moment_blur_gradient_matches_the_reference(enable_x64):
    """Reverse-mode gradients (values and mask) of the new form equal the original formula's,
    and a directional finite difference agrees. In float64: both forms are jitted, and in
    float32 XLA's fusion of the new form rounds one soft-mask border texel of its mask
    gradient 1.2e-3 (relative) away from the reference, which says nothing about the formula."""
    n, mask = (np.asarray(a, np.float64) for a in _random_masked((3, 40, 40, 3), seed=5))
    w = np.random.default_rng(6).normal(size=n.shape)

    def loss(blur, nn_, mm):
        return jnp.sum(w * blur(nn_, mm, 5.0, 1))

    ref = functools.partial(loss, sharpen.masked_blur_reference)
    new = functools.partial(loss, sharpen.masked_blur)
    gn_new, gm_new = jax.grad(new, argnums=(0, 1))(n, mask)
    gn_ref, gm_ref = jax.jit(jax.grad(ref, argnums=(0, 1)))(n, mask)
    assert gn_new.dtype == gm_new.dtype == jnp.float64
    np.testing.assert_allclose(gn_new, gn_ref, rtol=1e-9, atol=1e-11 * np.abs(gn_ref).max())
    np.testing.assert_allclose(gm_new, gm_ref, rtol=1e-9, atol=1e-11 * np.abs(gm_ref).max())
    d = np.random.default_rng(7).normal(size=n.shape) * 1e-3
    fd = (new(n + d, mask) - new(n - d, mask)) / 2
    np.testing.assert_allclose(float(jnp.sum(gn_new * d)), float(fd), rtol=1e-6)


@pytest.fixture
def fresh_jit_caches():
    """Jitted callers of `masked_blur` (`unsharp_rgb`) keep the trace of the blur they first
    saw: a test that patches it clears their caches before (so its patch is traced) and after
    (so no later test in the worker runs the patched trace, with its closed-over tracer).
    Only theirs: clearing every cache would make the worker's later tests compile again."""
    sharpen.unsharp_rgb.clear_cache()
    yield
    sharpen.unsharp_rgb.clear_cache()


@pytest.mark.parametrize("highpass,unsharp_sigma", [(2.0, 4.0), (4.0, 4.0)])
def test_unet_blurs_match_the_reference_formula(monkeypatch, fresh_jit_caches, highpass,
                                                unsharp_sigma):
    """The U-Net forward (high-passed residual on an unsharp base; equal radii share one blur
    call, different ones do not) and its parameter gradient equal those of the original blur
    formula to float32 rounding, on random masked inputs and random weights."""
    x, m = _folds(n=3)
    x = x * np.asarray(_random_masked((3, 32, 32, 1), seed=9)[1])  # ragged masks
    model = unet.UNetConfig(width=4, residual=True, residual_base="unsharp",
                            unsharp_sigma=unsharp_sigma, residual_highpass=highpass).module(2)
    params = _unsharp_params(3)
    rng = np.random.default_rng(4)
    params = {**params, "out": jax.tree.map(
        lambda a: jnp.asarray(rng.normal(size=a.shape) * 0.1, jnp.float32), params["out"])}
    mat = jnp.array([0, 1, 1])
    wts = jnp.asarray(rng.normal(size=x.shape), jnp.float32)

    # One jitted program for forward and gradient of both blur forms (op-by-op dispatch of a
    # U-Net and its backward pass costs far more CPU than compiling it; the U-Net's forward
    # and backward are most of a compile, so they are compiled once, not once per form).
    # Every blur the U-Net makes goes through `use_reference`: a traced flag selects the
    # form (`lax.cond` runs only the selected branch), so the two runs below execute the same
    # network code and differ only in the blur.
    blur = sharpen.masked_blur
    flag = []

    def either(n, mask_, sigma, order=1, weights=None):
        return jax.lax.cond(flag[0], lambda a, b: sharpen.masked_blur_reference(a, b, sigma,
                                                                                 order),
                            lambda a, b: blur(a, b, sigma, order, weights), n, mask_)

    monkeypatch.setattr(sharpen, "masked_blur", either)

    @jax.jit
    def loss_and_grad(p, use_reference):
        flag[:] = [use_reference]  # read while tracing

        def loss(q):
            out = model.apply({"params": q}, x, mat)
            return jnp.sum(wts * out), out

        return jax.value_and_grad(loss, has_aux=True)(p)

    (_, got), g_got = loss_and_grad(params, False)
    (_, want), g_want = loss_and_grad(params, True)
    assert float(jnp.abs(got - x).max()) > 1e-2  # the residual is not trivial
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=2e-6)
    # Tolerance on the whole gradient's scale: biases feeding instance normalization have a
    # zero gradient, so their computed values are rounding noise of either form.
    scale = max(float(jnp.abs(b).max()) for b in jax.tree.leaves(g_want))
    for a, b in zip(jax.tree.leaves(g_got), jax.tree.leaves(g_want), strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-3, atol=1e-4 * scale)


@pytest.mark.parametrize("order", [0, 1])
def test_blur_weights_computed_once_serve_every_field_on_the_mask(order):
    """`blur_weights` of a mask, passed to several blurs of different fields on it, give each
    field's own blur; weights of the other order are refused."""
    n, mask = _random_masked((3, 40, 36, 4), seed=9 + order)
    weights = sharpen.blur_weights(mask, 5.0, order)
    assert weights.shape == ((3 if order else 1), 40, 3, 36)
    for field in (n[..., :1], n[..., 1:], 2.0 * n + 1.0):
        want = np.asarray(sharpen.masked_blur_reference(field, mask, 5.0, order))
        got = np.asarray(sharpen.masked_blur(field, mask, 5.0, order, weights=weights))
        np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-5 * np.abs(want).max())
        inside = np.asarray(sharpen.masked_blur(field, mask, 5.0, order))
        np.testing.assert_allclose(got, inside, rtol=1e-6, atol=1e-7 * np.abs(inside).max())
    with pytest.raises(ValueError, match="do not fit order"):
        sharpen.masked_blur(n, mask, 5.0, 1 - order, weights=weights)
    for bad in (lambda: sharpen.masked_blur(n, mask, 5.0, 2, weights=weights),
                lambda: sharpen.blur_weights(mask, 5.0, 2)):
        with pytest.raises(ValueError, match="order must be 0 or 1"):
            bad()
