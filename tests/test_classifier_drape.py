"""classifier.drape: normal-map band statistics of coarse frames (the ``drape`` family)."""

import numpy as np
import pytest

from wrinkle_jax.classifier import drape, motion

TEXEL = 0.01


def _corrugated(amp_slope, wavelength, size=160, phase=0.0):
    """Unit normals of z = A sin(k x) on a size x size grid of TEXEL texels (slope A k), a
    full mask, and the texel centers' x (meters)."""
    x = (np.arange(size) + 0.5) * TEXEL
    k = 2 * np.pi / wavelength
    nx = -amp_slope * np.cos(k * x + phase)
    n = np.stack(np.broadcast_arrays(nx[None, :], 0.0 * x[:, None], 1.0 + 0 * nx[None, :]),
                 axis=-1).astype(np.float64)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    return n, np.ones((size, size)), x


def _rot_z(n, angle):
    c, s = np.cos(angle), np.sin(angle)
    r = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return n @ r.T


def test_bands_match_the_gaussian_response_of_a_sine():
    """Band b of cos(kx) is (exp(-k^2 s_b^2 / 2) - exp(-k^2 s_b+1^2 / 2)) cos(kx) away from
    the edges: the difference-of-Gaussians response of each octave."""
    slope, lam = 0.05, 0.25
    n, m, x = _corrugated(slope, lam)
    bands, support, _ = drape.frame_bands(n, m, TEXEL)
    k = 2 * np.pi / lam
    g = [np.exp(-0.5 * (k * s) ** 2) for s in drape.SIGMAS_M]
    inner = slice(50, 110)                          # 3 largest sigmas from every edge
    for b in range(3):
        want = -slope * (g[b] - g[b + 1]) * np.cos(k * x[inner])
        got = bands[b][inner, inner, 0]
        assert np.abs(got - want[None, :]).max() < 0.04 * slope, b
        assert np.all(bands[b][inner, inner, 1] == 0.0)
        assert np.abs(bands[b][inner, inner, 2]).max() < slope ** 2 / 4  # n_z: 2nd order
    # The 25 cm fold sits in the middle octave (sigma 40-80 mm), not in the finest one.
    e = [float((bb[inner, inner] ** 2).sum(-1).mean()) for bb in bands]
    assert e[1] > 2 * e[0] and e[1] > 2 * e[2]
    assert support.all() is not True and support[inner, inner].all()


def test_fold_wavelength_of_a_sine():
    for lam in (0.08, 0.2):
        x = (np.arange(300) + 0.5) * TEXEL
        band = np.zeros((300, 300, 3))
        band[..., 0] = 0.1 * np.sin(2 * np.pi * x / lam)[None, :]
        got = drape.fold_wavelength(band, np.ones((300, 300), bool), TEXEL)
        # Central differences read sin(k h) / h for k: a 1 % effect at 8 texels per fold.
        want = lam * (2 * np.pi * TEXEL / lam) / np.sin(2 * np.pi * TEXEL / lam)
        assert got == pytest.approx(want, rel=0.01)


def test_flat_sheets_and_hang():
    size = 60
    flat = np.zeros((size, size, 3))
    flat[..., 2] = 1.0
    st = drape.frame_stats(np.stack([flat, flat]), np.ones((size, size)), TEXEL)
    assert np.all(st[:, :3] < np.log(1e-7))            # no fold energy
    assert np.all(st[:, 3:6] < 0.5 * np.log(1e-7))     # nothing moves
    assert st[:, 7] == pytest.approx(1.0)               # lies flat: |n_z| = 1
    wall = np.zeros((size, size, 3))
    wall[..., 0] = 1.0
    assert drape.frame_stats(wall[None], np.ones((size, size)), TEXEL)[0, 7] == \
        pytest.approx(0.0, abs=1e-12)                   # hangs straight down


def test_invariant_to_rotation_about_vertical_and_rates_scale_with_time():
    maps = np.stack([_corrugated(0.2, 0.15, size=80, phase=p)[0] for p in (0.0, 0.4, 0.9)])
    m = np.ones((80, 80))
    m[:, :10] = 0.0                                      # a garment edge
    st = drape.frame_stats(maps, m, TEXEL, dt=0.1)
    rot = drape.frame_stats(_rot_z(maps, 1.3), m, TEXEL, dt=0.1)
    np.testing.assert_allclose(rot, st, rtol=1e-9, atol=1e-9)
    # Band rates are RMS change per second: twice the time step, half the rate.
    slow = drape.frame_stats(maps, m, TEXEL, dt=0.2)
    np.testing.assert_allclose(slow[:, 3:6], st[:, 3:6] - np.log(2.0), atol=2e-4)  # floor
    np.testing.assert_allclose(slow[:, [0, 1, 2, 6, 7]], st[:, [0, 1, 2, 6, 7]])
    assert np.all(st[:2, 3:6] > np.log(1e-3))           # the fold moves: rates above the floor


def test_window_features_average_the_baked_frames_inside():
    stats = np.tile(np.arange(75.0)[:, None], (1, drape.DIM))
    w = drape.window_features(stats, np.array([0, 16, 268]), 32, frame_step=4)
    # window [16, 48) holds baked frames 16, 20, ..., 44 = rows 4..11; rates: pairs 4..10
    np.testing.assert_allclose(w[1, :3], 7.5)
    np.testing.assert_allclose(w[1, 3:6], 7.0)
    np.testing.assert_allclose(w[2, 6:], np.mean(np.arange(67, 75)))
    with pytest.raises(ValueError, match="no baked frame"):
        drape.window_features(stats, np.array([1]), 3, frame_step=4)


def test_sequence_features_drape_slice_is_invariant_and_zero_without_a_plan():
    """Through the real bake: a folded hanging sheet, translated and turned about the
    vertical with its body, gives the same drape features; no plan gives zeros."""
    nx, nz = 13, 13
    u, v = np.meshgrid(np.arange(nx) * 0.03, np.arange(nz) * 0.03)
    uv = np.stack([u.ravel(), v.ravel()], 1)
    q = np.arange(nx * nz).reshape(nz, nx)
    a, b, c, d = q[:-1, :-1].ravel(), q[:-1, 1:].ravel(), q[1:, 1:].ravel(), q[1:, :-1].ravel()
    faces = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    t = np.arange(36) / 30.0
    fold = 0.03 * np.sin(2 * np.pi * uv[None, :, 0] / 0.18 + 3.0 * t[:, None])
    frames = np.stack([np.broadcast_to(uv[:, 0], fold.shape), fold,
                       np.broadcast_to(uv[:, 1], fold.shape)], -1)
    ref = np.zeros((len(t), 3))
    topo = motion.make_topology(faces, uv, faces)
    sl = motion.family_slices()["drape"]
    plan = drape.make_plan(faces, uv, faces, frames[0])
    f0 = motion.sequence_features(frames, ref, topo, 30.0, 32, 4, drape_plan=plan)[:, sl]
    c_, s_ = np.cos(0.7), np.sin(0.7)
    r = np.array([[c_, -s_, 0.0], [s_, c_, 0.0], [0.0, 0.0, 1.0]])
    shift = np.array([0.4, -1.0, 0.2])
    moved = frames @ r.T + shift
    f1 = motion.sequence_features(moved, ref @ r.T + shift, topo, 30.0, 32, 4,
                                  drape_plan=drape.make_plan(faces, uv, faces, moved[0]))[:, sl]
    assert f0.shape == (2, drape.DIM) and np.all(np.isfinite(f0))
    # The same as the per-frame statistics of every FRAME_STEP-th baked frame, FRAME_STEP / fps
    # seconds apart, averaged per window.
    maps = drape.bake_every(plan, frames)
    assert maps.shape[0] == len(frames[::drape.FRAME_STEP]) == 9
    st = drape.frame_stats(maps, np.asarray(plan.mask), TEXEL, drape.FRAME_STEP / 30.0)
    np.testing.assert_allclose(f0, drape.window_features(st, np.array([0, 4]), 32), atol=1e-5)
    np.testing.assert_allclose(f1, f0, atol=2e-4)
    assert f0[0, 7] < 0.3                                 # hangs: normals nearly horizontal
    assert np.all(motion.sequence_features(frames, ref, topo, 30.0, 32, 4)[:, sl] == 0.0)


def test_band_rate_of_a_travelling_fold():
    """A fold B cos(k x + w t) sampled every dt changes by 2 sin(w dt / 2) |B| per step, so
    log rate - log RMS band = log(2 sin(w dt / 2) / dt), with dt = FRAME_STEP / fps."""
    x = (np.arange(120) + 0.5) * TEXEL
    w, fps = 3.0, 30.0
    maps = []
    for t in np.arange(0, 33, drape.FRAME_STEP) / fps:
        n = np.zeros((120, 120, 3))
        n[..., 0] = 0.1 * np.cos(2 * np.pi * x / 0.2 + w * t)[None, :]
        n[..., 2] = 1.0
        maps.append(n / np.linalg.norm(n, axis=-1, keepdims=True))
    st = drape.frame_stats(np.stack(maps), np.ones((120, 120)), TEXEL, drape.FRAME_STEP / fps)
    dt = drape.FRAME_STEP / fps
    want = np.log(2 * np.sin(w * dt / 2) / dt)
    np.testing.assert_allclose(st[:-1, 3:5] - 0.5 * st[:-1, 0:2], want, atol=0.05)
