"""Tests for scoring with shared Gram matrices (`wrinkle_jax.evaluation.gram`)."""

from __future__ import annotations

import numpy as np
from evaluation_fixtures import PATCH  # tests/ is on sys.path

from wrinkle_jax import evaluation
from wrinkle_jax.evaluation import gram


def _rgb_patches(n=3, size=PATCH, seed=0, detail=0.3):
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:size, 0:size] / size
    out = []
    for _ in range(n):
        a, b = rng.uniform(1, 3, 2)
        gx = 0.5 * np.sin(2 * np.pi * a * x) + detail * np.sin(2 * np.pi * 7 * y + rng.uniform())
        gy = 0.5 * np.cos(2 * np.pi * b * y)
        nrm = np.stack([-gx, -gy, np.ones_like(gx)], -1)
        out.append((nrm / np.linalg.norm(nrm, axis=-1, keepdims=True) + 1) / 2)
    mask = np.zeros((n, size, size, 1), np.float32)
    mask[:, :, : size * 3 // 4] = 1
    return np.asarray(out, np.float32) * mask, mask


def test_method_losses_equal_score_patches_and_share_the_input_and_target_passes(tiny_vgg):
    inp, mask = _rgb_patches(5, detail=0.0)
    target, _ = _rgb_patches(5, seed=1, detail=0.4)
    noisy = np.clip(inp + 0.2 * np.random.default_rng(2).standard_normal(inp.shape), 0, 1)
    outputs = {"identity": evaluation.identity(inp, mask),
               "noisy": (noisy * mask).astype(np.float32),
               "unsharp": evaluation.unsharp_mask(inp, mask, 2.0, 1.0),
               "oracle": target}
    counter = {}
    got = gram.method_losses(tiny_vgg, inp, target, mask, outputs, batch_size=2, counter=counter)
    # 3 batches (2 + 2 + 1 padded): target and input once each, identity reuses the input.
    assert counter["vgg_passes"] == 3 * (2 + 3)
    for name, out in outputs.items():
        ref = evaluation.score_patches(tiny_vgg, inp, out, target, mask, batch_size=2)
        sc = evaluation.scores_from_losses(got["input"], got[name])
        np.testing.assert_allclose(sc["loss_input"], ref["loss_input"], rtol=1e-5)
        np.testing.assert_allclose(sc["loss_output"], ref["loss_output"], rtol=1e-5, atol=1e-12)
        np.testing.assert_allclose(sc["improvement_signed"], ref["improvement_signed"],
                                   rtol=1e-4, atol=1e-3)
        np.testing.assert_array_equal(sc["valid"], ref["valid"])
    ident = evaluation.scores_from_losses(got["input"], got["identity"])
    oracle = evaluation.scores_from_losses(got["input"], got["oracle"])
    assert ident["valid"].all()
    np.testing.assert_array_equal(ident["improvement"], 0.0)
    np.testing.assert_allclose(oracle["improvement_signed"], 100.0, atol=1e-3)


def test_pairwise_losses_equal_method_losses_for_every_pair(tiny_vgg):
    a, mask = _rgb_patches(3, detail=0.2)
    b, _ = _rgb_patches(4, seed=3, detail=0.5)
    mb = np.resize(mask, (4, *mask.shape[1:]))
    ga = gram.flat_grams(tiny_vgg, a, mask, batch_size=2)
    gb = gram.flat_grams(tiny_vgg, b, mb, batch_size=2)
    d = gram.pairwise_losses(ga, gb)
    assert d.shape == (3, 4)
    for j in range(4):  # column j: every a against target b[j]
        tgt = np.repeat(b[j:j + 1], 3, 0)
        ref = gram.method_losses(tiny_vgg, a, tgt, mask, {"a": a}, batch_size=2)["input"]
        np.testing.assert_allclose(d[:, j], ref, rtol=1e-4, atol=1e-6 * ref.max())
    # self-distances vanish up to the float32 cancellation of |a|^2 + |a|^2 - 2 a.a
    np.testing.assert_allclose(np.diag(gram.pairwise_losses(ga, ga)), 0.0,
                               atol=1e-5 * d.max())
