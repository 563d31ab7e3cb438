"""Tests for wrinkle_jax.evaluation: the improvement score on patches and the baselines."""

from __future__ import annotations

import numpy as np

from wrinkle_jax import evaluation


def _patches(n=3, size=32, seed=0, detail=0.3):
    """Smooth folds plus optional fine ripples, as RGB-form unit normals, half-masked."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:size, 0:size] / size
    out = []
    for _ in range(n):
        a, b = rng.uniform(1, 3, 2)
        gx = 0.5 * np.sin(2 * np.pi * a * x) + detail * np.sin(2 * np.pi * 9 * y + rng.uniform())
        gy = 0.5 * np.cos(2 * np.pi * b * y)
        nrm = np.stack([-gx, -gy, np.ones_like(gx)], -1)
        nrm /= np.linalg.norm(nrm, axis=-1, keepdims=True)
        out.append((nrm + 1) / 2)
    mask = np.zeros((n, size, size, 1), np.float32)
    mask[:, :, : size * 3 // 4] = 1
    return np.asarray(out, np.float32) * mask, mask


def _detail(rgb, mask):
    m = (mask[..., 0] > 0)
    d = np.linalg.norm(np.diff(rgb, axis=2), axis=-1)
    return d[m[:, :, 1:] & m[:, :, :-1]].mean()


def _unit_inside_zero_outside(rgb, mask):
    m = mask[..., 0] > 0
    np.testing.assert_allclose(np.linalg.norm(rgb[m] * 2 - 1, axis=-1), 1.0, atol=1e-5)
    assert not rgb[~m].any()


def test_scores_of_identity_and_target(tiny_vgg):
    smooth, mask = _patches(detail=0.0)
    target, _ = _patches(detail=0.3)
    ident = evaluation.score_patches(tiny_vgg, smooth, smooth, target, mask, batch_size=2)
    assert ident["valid"].all()
    np.testing.assert_allclose(ident["improvement_signed"], 0.0, atol=1e-3)
    perfect = evaluation.score_patches(tiny_vgg, smooth, target, target, mask, batch_size=2)
    np.testing.assert_allclose(perfect["improvement_signed"], 100.0, atol=1e-3)
    # Worse than the input: the paper's |.| form is positive, the signed form negative.
    noisy = np.clip(smooth + 0.3 * np.random.default_rng(1).standard_normal(smooth.shape), 0, 1)
    worse = evaluation.score_patches(tiny_vgg, smooth, noisy.astype(np.float32) * mask, target,
                                     mask, batch_size=2)
    bad = worse["loss_output"] > worse["loss_input"]
    assert bad.any()
    assert (worse["improvement_signed"][bad] < 0).all() and (worse["improvement"][bad] > 0).all()
    s = evaluation.summarize(perfect, np.array(["a", "a", "b"]))
    assert s["a"]["n"] == 2 and s["b"]["n"] == 1 and abs(s["all"]["signed_mean"] - 100) < 1e-3


def test_unsharp_mask_sharpens_and_stays_unit():
    x, mask = _patches(detail=0.1)
    np.testing.assert_allclose(evaluation.unsharp_mask(x, mask, amount=0.0), x, atol=1e-6)
    sharp = evaluation.unsharp_mask(x, mask, sigma=2.0, amount=1.5)
    _unit_inside_zero_outside(sharp, mask)
    assert _detail(sharp, mask) > 1.2 * _detail(x, mask)


def test_resample_smooths_and_ignores_background():
    x, mask = _patches(detail=0.4)
    down_up = evaluation.resample(x, mask, factor=4.0)
    _unit_inside_zero_outside(down_up, mask)
    assert _detail(down_up, mask) < 0.8 * _detail(x, mask)
    # Garbage in the background must not change anything inside the mask.
    junk = x + (1 - mask) * np.random.default_rng(2).uniform(size=x.shape).astype(np.float32)
    np.testing.assert_allclose(evaluation.resample(junk, mask, factor=4.0), down_up, atol=1e-6)
    np.testing.assert_allclose(evaluation.unsharp_mask(junk, mask), evaluation.unsharp_mask(
        x, mask), atol=1e-6)


def _rotate_y(rgb, mask, deg):
    a = np.deg2rad(deg)
    q = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
    n = (rgb.astype(np.float64) * 2 - 1) @ q.T
    return (((n + 1) / 2) * mask).astype(np.float32)


def test_detail_score_ignores_large_scale_divergence(tiny_vgg):
    """The oracle 'input's large scale + the target's detail' scores ~100 on the detail-only
    score, whatever the large-scale divergence; on the object-space score it does not."""
    smooth, mask = _patches(detail=0.0, size=48)
    wrinkled, _ = _patches(detail=0.3, size=48)
    target = _rotate_y(wrinkled, mask, 35.0)  # the fine sim, tilted away from the coarse one
    inp = smooth
    oracle = wrinkled  # the same detail on the input's own large scale
    sigma = 3.0
    det = evaluation.score_patches(tiny_vgg, inp, oracle, target, mask, batch_size=3,
                                   detail_sigma=sigma)
    obj = evaluation.score_patches(tiny_vgg, inp, oracle, target, mask, batch_size=3)
    assert det["valid"].all()
    assert np.all(det["improvement_signed"] > 90), det["improvement_signed"]
    assert np.all(obj["improvement_signed"] < 60), obj["improvement_signed"]
    # Detail maps of the three share the input's branch and are unit normals inside the mask.
    for x in evaluation.detail_triplet(inp, oracle, target, mask, sigma):
        _unit_inside_zero_outside(x, mask)
    # The target's own tilt is gone: the angle of each detail normal to +z (twist-free, the
    # z channel) equals the untilted map's; only a small twist about z remains.
    _, _, d_t = evaluation.detail_triplet(inp, oracle, target, mask, sigma)
    _, _, d_w = evaluation.detail_triplet(inp, oracle, wrinkled, mask, sigma)
    np.testing.assert_allclose(d_t[..., 2], d_w[..., 2], atol=2e-5)
    assert np.abs(d_t - d_w).max() < 0.05


def test_paired_difference_and_bootstrap():
    rng = np.random.default_rng(0)
    b = rng.normal(10, 50, 400)
    a = b + 7 + rng.normal(0, 1, 400)
    got = evaluation.paired_difference(a, b)
    assert got["n"] == 400 and got["win_rate"] > 0.99
    lo, hi = got["median_diff_ci"]
    assert lo < got["median_diff"] < hi and 6 < lo and hi < 8
    # Pairing matters: the medians' own spread is far wider than the paired interval.
    assert abs(got["median_a"] - got["median_b"] - 7) < 10
    valid = np.zeros(400, bool)
    valid[:10] = True
    assert evaluation.paired_difference(a, b, valid)["n"] == 10
    assert evaluation.paired_difference(a[:0], b[:0])["n"] == 0
    assert np.isnan(evaluation.bootstrap_ci([])[0])


def _ripple_rgb(wavelength, amp=0.1, size=64):
    x = np.arange(size)
    nx = amp * np.sin(2 * np.pi * x / wavelength)
    n = np.zeros((1, size, size, 3))
    n[..., 0] = nx[None, None, :]
    n[..., 2] = 1
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    return ((n + 1) / 2).astype(np.float32)


def test_band_rms_puts_each_wavelength_in_its_band():
    mask = np.ones((1, 64, 64, 1), np.float32)
    fine = evaluation.band_rms(_ripple_rgb(4.0), mask)     # 8 mm at 2 mm texels
    mid = evaluation.band_rms(_ripple_rgb(16.0), mask)     # 32 mm
    amp_rms = 0.1 / np.sqrt(2)
    assert fine["lt16mm"][0] > 0.8 * amp_rms and fine["16_64mm"][0] < 0.2 * amp_rms
    assert mid["16_64mm"][0] > 0.6 * amp_rms and mid["lt16mm"][0] < 0.2 * amp_rms


def test_checker_rms_sees_the_two_texel_checkerboard_only():
    mask = np.ones((1, 32, 32, 1), np.float32)
    smooth = _ripple_rgb(16.0, size=32)
    n = smooth * 2 - 1
    i, j = np.mgrid[0:32, 0:32]
    n[..., 0] += 0.02 * (-1.0) ** (i + j)
    checker = ((n / np.linalg.norm(n, axis=-1, keepdims=True) + 1) / 2).astype(np.float32)
    assert evaluation.checker_rms(smooth, mask)[0] < 2e-3
    np.testing.assert_allclose(evaluation.checker_rms(checker, mask)[0], 0.02, rtol=0.1)
