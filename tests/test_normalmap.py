"""Tests for wrinkle_jax.normalmap: analytic bakes, seams, gradients, sampling, downsampling, IO."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from wrinkle_jax import mesh, normalmap, primitives
from wrinkle_jax.mesh import Garment, make_garment

bake = normalmap.bake


def _angle_deg(a, b):
    a = a / np.maximum(np.linalg.norm(a, axis=-1, keepdims=True), 1e-12)
    b = b / np.maximum(np.linalg.norm(b, axis=-1, keepdims=True), 1e-12)
    return np.degrees(np.arccos(np.clip((a * b).sum(-1), -1.0, 1.0)))


def _texel_uvs(plan):
    """UV coordinates of every texel center (H, W, 2)."""
    lay = plan.layout
    h, w = plan.shape
    x, y = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5, indexing="xy")
    u = (x - lay.margin) / lay.pixels_per_uv + lay.u_min
    v = lay.v_max - (y - lay.margin) / lay.pixels_per_uv
    return np.stack([u, v], -1)


# ---------------------------------------------------------------- analytic surfaces


def test_plane_bakes_constant_normal_and_covers_its_area():
    g = primitives.grid_sheet(9, 7, size=(0.3, 0.2), jitter=0.3, seed=1)
    plan = normalmap.make_plan(g, texel_size=0.002, gutter=3)
    n = np.asarray(bake(plan, jnp.asarray(g.vertices)))
    m = np.asarray(plan.mask)[..., 0] > 0
    np.testing.assert_allclose(n[m], np.tile([0, 0, 1.0], (m.sum(), 1)), atol=1e-6)
    # A texel is texel_size meters wide: the covered count is area / texel^2.
    np.testing.assert_allclose(m.sum(), 0.3 * 0.2 / 0.002**2, rtol=0.02)
    # Background (beyond the gutter) is exactly zero; gutter texels are unit normals.
    planned = np.asarray(plan.index_map) < len(plan.texel_tri)
    assert (np.abs(n[~planned]) == 0).all()
    np.testing.assert_allclose(np.linalg.norm(n[planned & ~m], axis=-1), 1.0, atol=1e-6)


def test_cylinder_panel_matches_closed_form_normals():
    r = 0.2
    g = primitives.cylinder_panel(radius=r, height=0.3, angle=np.pi, n_theta=96, n_h=12)
    plan = normalmap.make_plan(g, texel_size=0.003)
    n = np.asarray(bake(plan, jnp.asarray(g.vertices)))
    m = np.asarray(plan.mask)[..., 0] > 0
    theta = _texel_uvs(plan)[..., 0] / r
    exact = np.stack([np.cos(theta), np.sin(theta), np.zeros_like(theta)], -1)
    err = _angle_deg(n, exact)
    # Away from the open sides (one facet wide), smooth shading is accurate to O(h^2); at the
    # sides a vertex normal sees faces on one side only and tilts by about half a facet angle.
    inner = m & (theta > np.pi / 96) & (theta < np.pi - np.pi / 96)
    assert err[inner].max() < 0.05, err[inner].max()
    assert err[m].max() < 0.5 * 180 / 96, err[m].max()
    # Flat shading is visibly worse (half the facet angle, 180/96/2 ~ 0.94 deg at worst).
    flat = np.asarray(bake(plan, jnp.asarray(g.vertices), smooth=False))
    assert _angle_deg(flat[m], exact[m]).max() > 0.8


def test_sphere_cap_matches_closed_form_normals():
    r = 0.3
    g = primitives.sphere_cap(radius=r, max_polar=1.0, n_rings=40, n_segments=120)
    plan = normalmap.make_plan(g, texel_size=0.003)
    n = np.asarray(bake(plan, jnp.asarray(g.vertices)))
    m = np.asarray(plan.mask)[..., 0] > 0
    uv = _texel_uvs(plan)
    polar = np.linalg.norm(uv, axis=-1) / r
    az = np.arctan2(uv[..., 1], uv[..., 0])
    exact = np.stack([np.sin(polar) * np.cos(az), np.sin(polar) * np.sin(az), np.cos(polar)], -1)
    err = _angle_deg(n[m], exact[m])
    assert np.median(err) < 0.1 and err.max() < 1.0, (np.median(err), err.max())


def test_baked_map_equals_vertex_normals_at_vertex_uvs(skirt):
    frame = skirt.vertices * np.array([1.0, 0.8, 1.0], np.float32)  # squash: varied normals
    plan = normalmap.make_plan(skirt, texel_size=0.002)
    n = bake(plan, jnp.asarray(frame))
    at_vertices = normalmap.sample_at_vertices(n, skirt, plan.layout)
    vn = np.asarray(mesh.vertex_normals(jnp.asarray(frame), jnp.asarray(skirt.faces)))
    err = _angle_deg(np.asarray(at_vertices), vn)
    assert err.max() < 1.0, err.max()
    # Per UV copy too (no seam averaging): every corner's UV samples its vertex's normal.
    per_uv = np.asarray(normalmap.sample(n, jnp.asarray(skirt.uvs), plan.layout))
    uv_to_v = np.zeros(len(skirt.uvs), int)
    uv_to_v[skirt.uv_faces.reshape(-1)] = skirt.faces.reshape(-1)
    assert _angle_deg(per_uv, vn[uv_to_v]).max() < 1.0


# ---------------------------------------------------------------- seams and gutters


@pytest.mark.parametrize("gutter", [0, 3])
def test_cube_seams_do_not_bleed_background(cube, gutter):
    plan = normalmap.make_plan(cube, texel_size=0.005, gutter=gutter)
    n = bake(plan, jnp.asarray(cube.vertices))
    m = np.asarray(plan.mask)[..., 0] > 0
    np.testing.assert_allclose(np.linalg.norm(np.asarray(n)[m], axis=-1), 1.0, atol=1e-5)
    # Raw bilinear samples at every UV vertex, panel borders and corners included.
    raw = np.asarray(normalmap.sample(n, jnp.asarray(cube.uvs), plan.layout, renormalize=False))
    length = np.linalg.norm(raw, axis=-1)
    if gutter:
        assert length.min() > 0.97, length.min()
        uv_to_v = np.zeros(len(cube.uvs), int)
        uv_to_v[cube.uv_faces.reshape(-1)] = cube.faces.reshape(-1)
        vn = np.asarray(mesh.vertex_normals(jnp.asarray(cube.vertices), jnp.asarray(cube.faces)))
        assert _angle_deg(raw, vn[uv_to_v]).max() < 12.0
    else:
        assert length.min() < 0.6  # without a gutter, border samples read background


def test_each_cube_panel_faces_its_axis(cube):
    plan = normalmap.make_plan(cube, texel_size=0.004)
    # Flat shading: smooth vertex normals are rounded over a whole cell next to each cube edge.
    n = np.asarray(bake(plan, jnp.asarray(cube.vertices), smooth=False)).reshape(-1, 3)
    k = plan.num_covered
    pixels, panel = np.asarray(plan.texel_pixel)[:k], cube.panels[np.asarray(plan.texel_tri)[:k]]
    axes = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1.0]])
    for p in range(6):
        err = _angle_deg(n[pixels[panel == p]], axes[p][None])
        assert np.median(err) < 1e-3, (p, np.median(err))


# ---------------------------------------------------------------- hard cases


def test_degenerate_and_flipped_uv_triangles():
    v = np.array([[0, 0, 0], [0.1, 0, 0], [0.1, 0.1, 0], [0, 0.1, 0], [0.2, 0, 0.01]], np.float32)
    f = np.array([[0, 1, 2], [0, 2, 3], [1, 4, 2]])
    uv = np.array([[0, 0], [0.1, 0], [0.1, 0.1], [0, 0.1], [0.2, 0.05], [0.2, 0.05]], np.float32)
    # Face 2's UVs are collinear (zero area): it covers nothing but must not break anything.
    uf = np.array([[0, 1, 2], [0, 2, 3], [4, 5, 5]])
    g = make_garment(v, f, uv, uf)
    plan = normalmap.make_plan(g, texel_size=0.005)
    assert 2 not in np.asarray(plan.texel_tri)[: plan.num_covered]
    np.testing.assert_array_equal(np.asarray(plan.mask).reshape(-1)[plan.texel_pixel],
                                  np.arange(len(plan.texel_pixel)) < plan.num_covered)
    n = np.asarray(bake(plan, jnp.asarray(v)))
    assert np.isfinite(n).all()
    np.testing.assert_allclose(np.asarray(plan.mask).sum(), 0.1 * 0.1 / 0.005**2, rtol=0.05)

    # Mirroring the UV layout flips every UV triangle's orientation: same coverage, same map.
    # The mirrored layout maps pixel x to W - x exactly, so the map must mirror column-wise.
    mirrored = g.replace(uvs=uv * np.array([-1.0, 1.0], np.float32))
    lay = plan.layout
    width_uv = (lay.width - 2 * lay.margin) / lay.pixels_per_uv
    plan_m = normalmap.make_plan(mirrored, layout=dataclasses.replace(
        lay, u_min=-(lay.u_min + width_uv)))
    n_m = np.asarray(bake(plan_m, jnp.asarray(v)))
    assert plan_m.num_covered == plan.num_covered
    np.testing.assert_allclose(n_m[:, ::-1], n, atol=1e-6)


def test_empty_mask_does_not_crash():
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32)
    uv = np.array([[0, 0], [0.0001, 0], [0.0002, 0]], np.float32)  # collinear: zero UV area
    g = Garment(v, np.array([[0, 1, 2]], np.int32), uv, np.array([[0, 1, 2]], np.int32))
    layout = normalmap.UVLayout(1000.0, 0.0, 0.0, 4, 12, 12, 0.001)
    plan = normalmap.make_plan(g, layout=layout)
    assert plan.num_covered == 0 and len(plan.texel_tri) == 0
    n = bake(plan, jnp.asarray(v))
    assert n.shape == (12, 12, 3) and not np.asarray(n).any()
    with pytest.raises(mesh.GarmentError, match="zero area"):
        normalmap.make_plan(g)  # no texel size can be derived from zero UV area


def test_layout_reuse_aligns_coarse_and_fine(skirt):
    fine = primitives.flared_skirt(n_theta=96, n_s=24)
    layout = normalmap.layout_for(skirt, texel_size=0.004, meters_per_uv=1.0)
    p_coarse = normalmap.make_plan(skirt, layout=layout)
    p_fine = normalmap.make_plan(fine, layout=layout)
    assert p_coarse.shape == p_fine.shape
    overlap = (np.asarray(p_coarse.mask) * np.asarray(p_fine.mask)).sum()
    assert overlap / max(p_coarse.num_covered, p_fine.num_covered) > 0.97


# ---------------------------------------------------------------- transforms


def test_bake_vmap_equals_loop(skirt):
    plan = normalmap.make_plan(skirt, texel_size=0.006)
    # NumPy noise: an op-by-op jax.random draw compiles a threefry program of its shape.
    noise = np.random.default_rng(1).standard_normal((3, skirt.num_vertices, 3))
    frames = jnp.asarray(skirt.vertices + 0.01 * noise, jnp.float32)
    batched = normalmap.bake_frames(plan, frames)
    for t in range(3):
        np.testing.assert_allclose(batched[t], bake(plan, frames[t]), atol=1e-6)


def test_bake_gradient_matches_finite_differences(enable_x64):
    g = primitives.grid_sheet(4, 4, size=(0.1, 0.1),
                              height_fn=lambda x, y: 0.02 * np.sin(40 * x) * np.cos(30 * y))
    plan = normalmap.make_plan(g, texel_size=0.004)
    v0 = jnp.asarray(g.vertices, jnp.float64)
    w = jnp.asarray(np.random.default_rng(1).standard_normal((*plan.shape, 3)), jnp.float64)

    def f(v):
        return jnp.sum(w * normalmap.bake(plan, v))

    grad = np.asarray(jax.jit(jax.grad(f))(v0))
    assert np.abs(grad).max() > 0
    rng = np.random.default_rng(0)
    eps = 1e-6
    for _ in range(12):
        i, c = rng.integers(g.num_vertices), rng.integers(3)
        d = jnp.zeros_like(v0).at[i, c].set(eps)
        fd = (f(v0 + d) - f(v0 - d)) / (2 * eps)
        np.testing.assert_allclose(grad[i, c], fd, rtol=1e-5, atol=1e-8)


def test_sample_is_bilinear_and_differentiable():
    layout = normalmap.UVLayout(1.0, 0.0, 4.0, 0, 4, 4, 1.0)  # one texel per UV unit
    img = jnp.arange(48, dtype=jnp.float32).reshape(4, 4, 3)
    # Texel (row 1, col 2) has its center at pixel (2.5, 1.5), i.e. uv (2.5, 2.5).
    out = normalmap.sample(img, jnp.array([[2.5, 2.5], [3.0, 2.5], [3.0, 2.0]]), layout,
                           renormalize=False)
    np.testing.assert_allclose(out[0], img[1, 2])
    np.testing.assert_allclose(out[1], 0.5 * (img[1, 2] + img[1, 3]))
    np.testing.assert_allclose(out[2], 0.25 * (img[1, 2] + img[1, 3] + img[2, 2] + img[2, 3]))
    g = jax.grad(lambda m: normalmap.sample(m, jnp.array([[3.0, 2.0]]), layout,
                                            renormalize=False).sum())(img)
    np.testing.assert_allclose(np.asarray(g)[1:3, 2:4].sum(), 3.0)


def test_downsample_like_coarse():
    # Wrinkles of 12.6 mm wavelength (8 texels) on a 0.3 m fold; 2 mm mesh cells.
    g = primitives.grid_sheet(75, 75, size=(0.15, 0.15),
                              height_fn=lambda x, y: 5e-4 * np.sin(500 * x) + 0.01 * np.sin(20 * y))
    plan = normalmap.make_plan(g, texel_size=0.0015, gutter=0)
    n = bake(plan, jnp.asarray(g.vertices))
    mask = jnp.asarray(plan.mask)
    # Garbage in the background must not leak into the garment.
    polluted = jnp.where(mask > 0, n, jnp.array([1.0, 0.0, 0.0]))
    down = jax.jit(normalmap.downsample_like_coarse, static_argnames="factor")
    out = np.asarray(down(polluted, mask, factor=3.0))
    clean = np.asarray(down(n, mask, factor=3.0))
    np.testing.assert_allclose(out, clean, atol=1e-6)
    m = np.asarray(mask)[..., 0] > 0
    np.testing.assert_allclose(np.linalg.norm(out[m], axis=-1), 1.0, atol=1e-5)
    assert not out[~m].any()

    def detail(x):  # mean |Laplacian| of the map inside the mask, away from the border
        lap = 4 * x[1:-1, 1:-1] - x[:-2, 1:-1] - x[2:, 1:-1] - x[1:-1, :-2] - x[1:-1, 2:]
        inner = m[1:-1, 1:-1] & m[:-2, 1:-1] & m[2:, 1:-1] & m[1:-1, :-2] & m[1:-1, 2:]
        return np.abs(lap[inner]).mean()

    n = np.asarray(n)
    assert detail(out) < 0.6 * detail(n)  # fine wrinkles are smoothed out
    # ... while the large fold survives: the y-component correlates with the original.
    corr = np.corrcoef(out[m][:, 1], n[m][:, 1])[0, 1]
    assert corr > 0.95
    np.testing.assert_allclose(down(n, mask, factor=1.0), n * np.asarray(mask), atol=0)


# ---------------------------------------------------------------- IO


def test_png_round_trip_16_bit(skirt, tmp_path):
    plan = normalmap.make_plan(skirt, texel_size=0.006)
    n = np.asarray(bake(plan, jnp.asarray(skirt.vertices)))
    p = tmp_path / "map.png"
    normalmap.save_normal_map_png(p, n, plan.mask)
    back, mask = normalmap.load_normal_map_png(p, renormalize=False)
    np.testing.assert_array_equal(mask, np.asarray(plan.mask))
    m = mask[..., 0] > 0
    assert np.abs(back[m] - n[m]).max() < 2.0 / 65535 + 1e-7  # 16-bit quantization
    renorm, _ = normalmap.load_normal_map_png(p)
    np.testing.assert_allclose(np.linalg.norm(renorm[m], axis=-1), 1.0, atol=1e-6)
    normalmap.save_mask_png(tmp_path / "mask.png", plan.mask)
    np.testing.assert_array_equal(normalmap.load_mask_png(tmp_path / "mask.png"), plan.mask)


def test_png_errors(tmp_path):
    bad = tmp_path / "bad.png"
    bad.write_bytes(b"\x89PNG not really")
    with pytest.raises(normalmap.NormalMapError, match="bad.png: not a readable PNG"):
        normalmap.load_normal_map_png(bad)
    with pytest.raises(normalmap.NormalMapError, match="missing.png: cannot read"):
        normalmap.load_normal_map_png(tmp_path / "missing.png")
    with pytest.raises(normalmap.NormalMapError, match="non-finite"):
        normalmap.save_normal_map_png(tmp_path / "x.png", np.full((2, 2, 3), np.nan))
    assert not (tmp_path / "x.png").exists()
