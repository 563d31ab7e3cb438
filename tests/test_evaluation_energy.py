"""Tests for evaluation.energy: analytic stretches, texel maps, band energy, matched gains."""

from __future__ import annotations

import numpy as np
import pytest

from wrinkle_jax import normalmap
from wrinkle_jax.evaluation import energy
from wrinkle_jax.mesh import make_garment


def _square(n: int = 4, size: float = 0.1):
    """A flat n x n grid of squares (2 triangles each) in the UV plane, UVs in meters."""
    g = np.linspace(0.0, size, n + 1)
    uv = np.stack(np.meshgrid(g, g, indexing="xy"), -1).reshape(-1, 2)
    faces = []
    for r in range(n):
        for c in range(n):
            a, b, d, e = r * (n + 1) + c, r * (n + 1) + c + 1, (r + 1) * (n + 1) + c, \
                (r + 1) * (n + 1) + c + 1
            faces += [[a, b, e], [a, e, d]]
    faces = np.asarray(faces, np.int32)
    verts = np.concatenate([uv, np.zeros((len(uv), 1))], 1)
    return make_garment(verts, faces, uv, faces)


def test_principal_stretches_match_the_linear_map_and_ignore_rotation():
    gar = _square()
    uv = np.asarray(gar.uvs, np.float64)
    a = np.array([[1.2, 0.3], [0.0, 0.7], [0.1, -0.2]])  # any 3 x 2 map
    want = np.sort(np.linalg.svd(a, compute_uv=False))
    s = energy.principal_stretches(uv @ a.T, gar)
    np.testing.assert_allclose(s, np.broadcast_to(want, s.shape), rtol=1e-10)
    q, _ = np.linalg.qr(np.random.default_rng(0).normal(size=(3, 3)))
    s_rot = energy.principal_stretches(uv @ a.T @ q.T + [1.0, -2.0, 0.5], gar)
    np.testing.assert_allclose(s_rot, s, rtol=1e-10)
    # The rest shape is unstretched; a uniform 0.9 compression reads 0.9 on both axes.
    np.testing.assert_allclose(energy.principal_stretches(gar.vertices, gar), 1.0, atol=1e-6)
    squeezed = np.asarray(gar.vertices, np.float64) * 0.9
    np.testing.assert_allclose(energy.principal_stretches(squeezed, gar), 0.9, atol=1e-6)


def test_face_values_land_on_their_faces_texels():
    gar = _square(n=2)
    plan = normalmap.make_plan(gar, texel_size=0.002)
    values = np.arange(gar.num_faces, dtype=np.float64) + 1.0
    m = energy.face_values_to_texels(plan, values, fill=-1.0)
    covered = np.asarray(plan.mask)[..., 0] > 0
    assert covered.sum() == plan.num_covered
    assert (m[~covered] == -1.0).all()
    # Every face covers the same UV area, so each value holds ~1/F of the covered texels.
    counts = np.array([(m == v).sum() for v in values])
    assert counts.sum() == covered.sum()
    np.testing.assert_allclose(counts / counts.sum(), 1.0 / gar.num_faces, atol=0.02)


def _wave(wavelength: float, amp: float, size: int = 96):
    """An RGB-form detail map tilting x by amp * sin(2 pi col / wavelength)."""
    col = np.arange(size)[None, :].repeat(size, 0).astype(np.float64)
    x = amp * np.sin(2 * np.pi * col / wavelength)
    n = np.stack([x, np.zeros_like(x), np.sqrt(1 - x ** 2)], -1)
    return (n + 1) / 2, np.ones((size, size, 1))


def test_local_band_energy_scales_with_amplitude_and_picks_the_band():
    flat, mask = _wave(16.0, 0.0)
    assert np.abs(energy.local_band_energy(flat, mask)).max() < 1e-20
    small = energy.local_band_energy(*_wave(16.0, 0.05))
    big = energy.local_band_energy(*_wave(16.0, 0.10))
    c = slice(30, 66)
    np.testing.assert_allclose(big[c, c], 4.0 * small[c, c], rtol=1e-9)
    # A 16-texel (32 mm) wave is a 16-64 mm wrinkle; a 3-texel one is below 16 mm.
    fine = _wave(3.0, 0.05)
    assert energy.local_band_energy(*_wave(16.0, 0.05))[c, c].mean() > \
        5 * energy.local_band_energy(*fine)[c, c].mean()
    assert energy.local_band_energy(*fine, band="lt16mm")[c, c].mean() > \
        5 * energy.local_band_energy(*_wave(16.0, 0.05), band="lt16mm")[c, c].mean()


def test_matched_gain_choice_is_the_closest_in_log():
    band_out = np.array([[0.0, 0.01, 0.02, 0.04],
                         [0.01, 0.02, 0.04, 0.08]])
    np.testing.assert_array_equal(energy.matched_gain_choice(band_out, [0.021, 0.05]), [2, 2])
    # log distance: 0.03 is closer to 0.04 (ratio 1.33) than to 0.02 (1.5).
    assert energy.matched_gain_choice(band_out[:1], [0.03])[0] == 3
    # A zero level picks the zero output, not an error.
    assert energy.matched_gain_choice(band_out[:1], [0.0])[0] == 0


@pytest.mark.parametrize("sigma", [2.0, 8.0])
def test_masked_smooth_keeps_constants_and_ignores_outside(sigma):
    x = np.full((40, 40), 3.0)
    mask = np.zeros((40, 40))
    mask[5:30, 8:35] = 1.0
    x[mask == 0] = 100.0  # must not leak in
    out = energy.masked_smooth(x, mask, sigma)
    np.testing.assert_allclose(out[mask > 0], 3.0, rtol=1e-9)


def test_gain_sweep_gain_zero_is_the_input_and_energy_grows_with_gain():
    rgb, mask = _wave(16.0, 0.05, size=64)
    rgb, mask = rgb[None].astype(np.float32), mask[None].astype(np.float32)
    target, _ = _wave(16.0, 0.15, size=64)
    sw = energy.gain_sweep(rgb, target[None].astype(np.float32), mask, 8.0, (0.0, 1.0, 2.0),
                           8.0)
    np.testing.assert_allclose(sw["outputs"][0], rgb, atol=1e-6)
    b = sw["band_out"][0]
    assert b.shape == (3,) and b[0] < b[1] < b[2]
    # The target's wave is 3x the input's: its band energy is above every output's but the
    # largest, and the matched choice is the strongest gain.
    assert sw["band_target"][0] > b[1]
    assert energy.matched_gain_choice(sw["band_out"], sw["band_target"])[0] == 2
    assert len(sw["details"]) == 2 + 3
