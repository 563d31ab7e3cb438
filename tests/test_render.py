"""Tests for wrinkle_jax.render: analytic coverage, z-buffer, Lambert, perspective, normal-map
shading, preview panels and PNG/MP4 output."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
import trimesh

from wrinkle_jax import normalmap, primitives, render
from wrinkle_jax.render import Camera, Light, RenderError

WHITE = (1.0, 1.0, 1.0)
BLACK = (0.0, 0.0, 0.0)
# Pure Lambert: the pixel value is max(0, n . l) exactly.
LAMBERT = Light(direction=(0.0, 0.0, 1.0), ambient=0.0, diffuse=1.0, camera_frame=False)


def _quad(x0=-0.5, x1=0.5, y0=-0.5, y1=0.5, z=0.0):
    """A counter-clockwise rectangle in a z = const plane: (4, 3) vertices, (2, 3) faces."""
    v = np.array([[x0, y0, z], [x1, y0, z], [x1, y1, z], [x0, y1, z]], np.float64)
    return v, np.array([[0, 1, 2], [0, 2, 3]])


def _front_ortho(height=2.0, **kw):
    """Orthographic camera on the +z axis looking at the origin, y up."""
    return Camera(eye=(0.0, 0.0, 5.0), target=(0.0, 0.0, 0.0), up=(0.0, 1.0, 0.0),
                  projection="orthographic", ortho_height=height, **kw)


def _covered(img, background=WHITE):
    return np.any(np.abs(img - np.asarray(background, np.float32)) > 1e-6, axis=-1)


# ---------------------------------------------------------------- coverage and orientation


@pytest.mark.parametrize("shape", [(100, 100), (80, 120)])
def test_orthographic_unit_square_covers_the_expected_pixels(shape):
    h, w = shape
    v, f = _quad()
    cam = _front_ortho(2.0)                            # the image height spans 2 m
    side = h / 2                                       # pixels per meter = the square's side
    frags = render.rasterize(cam, v, f, h, w)
    rows, cols = np.nonzero(frags.covered)
    assert abs(len(rows) - side * side) <= side        # +-1 pixel row
    assert abs((rows.max() - rows.min() + 1) - side) <= 1
    assert abs((cols.max() - cols.min() + 1) - side) <= 1
    assert abs((rows.mean() + 0.5) - h / 2) < 0.6 and abs((cols.mean() + 0.5) - w / 2) < 0.6
    # No pixel is drawn twice or missed on the shared diagonal: the square is solid.
    assert frags.covered[rows.min():rows.max() + 1, cols.min():cols.max() + 1].all()
    np.testing.assert_allclose(frags.depth[frags.covered], 5.0, rtol=1e-6)
    assert np.isinf(frags.depth[~frags.covered]).all()
    assert (frags.face[~frags.covered] == -1).all()


def test_image_axes_point_right_and_up():
    # A square in the +x, +y quadrant lands in the top-right quarter of the image.
    v, f = _quad(0.2, 0.8, 0.2, 0.8)
    frags = render.rasterize(_front_ortho(2.0), v, f, 100, 100)
    rows, cols = np.nonzero(frags.covered)
    assert rows.max() < 50 and cols.min() >= 50
    # Barycentrics interpolate the corners back to the pixel's world position.
    world = np.einsum("hwk,hwkd->hwd", frags.bary, v[f][frags.face])[frags.covered]
    expect_x = (cols + 0.5 - 50) / 50
    expect_y = (50 - (rows + 0.5)) / 50
    np.testing.assert_allclose(world[:, 0], expect_x, atol=1e-5)
    np.testing.assert_allclose(world[:, 1], expect_y, atol=1e-5)


def test_triangles_outside_or_behind_the_camera_are_not_drawn():
    v, f = _quad(5.0, 6.0, 5.0, 6.0)                   # off screen
    assert not render.rasterize(_front_ortho(2.0), v, f, 40, 40).covered.any()
    v, f = _quad(z=8.0)                                # behind the eye (z = 5)
    cam = Camera(eye=(0, 0, 5), up=(0, 1, 0), projection="perspective", fov=60)
    assert not render.rasterize(cam, v, f, 40, 40).covered.any()


# ---------------------------------------------------------------- z-buffer


@pytest.mark.parametrize("projection", ["orthographic", "perspective"])
@pytest.mark.parametrize("near_first", [True, False])
def test_nearer_triangle_hides_the_farther_one_whatever_the_order(projection, near_first):
    near_v, _ = _quad(-0.3, 0.3, -0.3, 0.3, z=0.5)
    far_v, _ = _quad(-0.6, 0.6, -0.6, 0.6, z=-0.5)
    tri = np.array([[0, 1, 2], [0, 2, 3]])
    blocks = [near_v, far_v] if near_first else [far_v, near_v]
    v = np.concatenate(blocks)
    f = np.concatenate([tri, tri + 4])
    near_faces = {0, 1} if near_first else {2, 3}
    cam = Camera(eye=(0, 0, 5), up=(0, 1, 0), projection=projection, fov=15, ortho_height=2)
    frags = render.rasterize(cam, v, f, 64, 64)
    center = frags.face[24:40, 24:40]
    assert set(np.unique(center)) <= near_faces
    np.testing.assert_allclose(frags.depth[24:40, 24:40], 4.5, rtol=1e-5)
    # The far quad still shows around the near one.
    ring = frags.face[frags.covered & (frags.depth > 5.0)]
    assert len(ring) > 0 and not (set(np.unique(ring)) & near_faces)


def test_image_does_not_depend_on_face_order_or_chunking(monkeypatch):
    s = trimesh.creation.icosphere(subdivisions=3)       # back faces must all be hidden
    v, f = np.asarray(s.vertices), np.asarray(s.faces)
    cam = render.fit_camera(v, azimuth=30, elevation=20)
    ref = render.render_mesh(v, f, cam, 64)
    perm = np.random.default_rng(0).permutation(len(f))
    np.testing.assert_allclose(render.render_mesh(v, f[perm], cam, 64), ref, atol=1e-5)
    frags = render.rasterize(cam, v, f, 64, 64)
    monkeypatch.setattr(render, "_CHUNK_CANDIDATES", 50)  # many chunks, some of one triangle
    small = render.rasterize(cam, v, f, 64, 64)
    np.testing.assert_array_equal(small.face, frags.face)
    np.testing.assert_array_equal(small.depth, frags.depth)


def test_interpenetrating_triangles_resolve_per_pixel():
    # Two planes crossing along x = 0: left of it one is nearer, right of it the other.
    a = np.array([[-1, -1, -0.5], [1, -1, 0.5], [1, 1, 0.5], [-1, 1, -0.5]], float)
    b = a * np.array([1, 1, -1])
    v = np.concatenate([a, b])
    f = np.array([[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7]])
    frags = render.rasterize(_front_ortho(2.5), v, f, 50, 50)
    row = frags.face[25]
    assert set(row[5:20]) <= {2, 3} and set(row[30:45]) <= {0, 1}


# ---------------------------------------------------------------- shading


@pytest.mark.parametrize("angle", [0.0, 30.0, 60.0, 85.0, 120.0])
def test_lambert_intensity_is_the_clamped_cosine(angle):
    t = math.radians(angle)
    light = Light(direction=(math.sin(t), 0.0, math.cos(t)), ambient=0.0, diffuse=1.0,
                  camera_frame=False)
    v, f = _quad()
    for smooth in (True, False):
        img = render.render_mesh(v, f, _front_ortho(2.0), 40, light=light, color=WHITE,
                                 background=BLACK, smooth=smooth, supersample=1)
        inside = img[12:28, 12:28]
        np.testing.assert_allclose(inside, max(0.0, math.cos(t)), atol=1e-6)


def test_ambient_and_albedo_scale_the_light():
    v, f = _quad()
    light = Light(direction=(0.0, 0.6, 0.8), ambient=0.25, diffuse=0.5, camera_frame=False)
    img = render.render_mesh(v, f, _front_ortho(2.0), 40, light=light, color=(1.0, 0.5, 0.2),
                             supersample=1)
    np.testing.assert_allclose(img[20, 20], np.array([1.0, 0.5, 0.2]) * (0.25 + 0.5 * 0.8),
                               atol=1e-6)


def test_camera_frame_light_follows_the_camera():
    # A headlight (towards the viewer) lights a facing quad fully from any viewpoint.
    v, f = _quad()
    head = Light(direction=(0.0, 0.0, 1.0), ambient=0.0, diffuse=1.0, camera_frame=True)
    for eye in [(0, 0, 5), (3, 0, 4), (0, -4, 3)]:
        cam = Camera(eye=eye, up=(0, 1, 0) if eye[1] == 0 else (0, 0, 1), fov=30)
        img = render.render_mesh(v, f, cam, 48, light=head, color=WHITE, background=BLACK,
                                 supersample=1)
        expect = np.dot(_unit(eye), (0, 0, 1))
        np.testing.assert_allclose(img[24, 24], expect, atol=1e-5)


def _unit(x):
    x = np.asarray(x, float)
    return x / np.linalg.norm(x)


def test_two_sided_shading_lights_the_back_of_a_sheet():
    v, f = _quad()
    f_back = f[:, ::-1]                                  # normal along -z, seen from +z
    light = Light(direction=(0.0, 0.0, 1.0), ambient=0.1, diffuse=0.9, camera_frame=False)
    cam = _front_ortho(2.0)
    kw = dict(light=light, color=WHITE, background=BLACK, supersample=1)
    one = render.render_mesh(v, f_back, cam, 40, two_sided=False, **kw)
    two = render.render_mesh(v, f_back, cam, 40, two_sided=True, **kw)
    np.testing.assert_allclose(one[20, 20], 0.1, atol=1e-6)      # ambient only
    np.testing.assert_allclose(two[20, 20], 1.0, atol=1e-6)


def test_smooth_shading_interpolates_and_flat_shading_does_not():
    s = trimesh.creation.icosphere(subdivisions=1)     # coarse: facets are visible
    v, f = np.asarray(s.vertices), np.asarray(s.faces)
    cam = render.fit_camera(v, elevation=0)
    kw = dict(light=LAMBERT, color=WHITE, background=BLACK, supersample=1)
    flat = render.render_mesh(v, f, cam, 64, smooth=False, **kw)
    smooth = render.render_mesh(v, f, cam, 64, smooth=True, **kw)
    frags = render.rasterize(cam, v, f, 64, 64)
    # Flat: one value per face; smooth: varies within faces.
    per_face_spread = [np.ptp(flat[..., 0][frags.face == k]) for k in np.unique(frags.face)
                       if k >= 0 and (frags.face == k).sum() > 10]
    assert max(per_face_spread) < 1e-5
    assert len(np.unique(np.round(smooth[frags.covered, 0], 4))) > 3 * len(per_face_spread)


# ---------------------------------------------------------------- perspective


def test_sphere_silhouette_matches_the_pinhole_formula():
    radius, dist, fov, size = 1.0, 2.5, 60.0, 201
    s = trimesh.creation.icosphere(subdivisions=4, radius=radius)
    cam = Camera(eye=(0.0, 0.0, dist), up=(0.0, 1.0, 0.0), fov=fov)
    frags = render.rasterize(cam, np.asarray(s.vertices), np.asarray(s.faces), size, size)
    measured = math.sqrt(frags.covered.sum() / math.pi)
    focal = 0.5 * size / math.tan(math.radians(fov) / 2)
    expect = focal * radius / math.sqrt(dist**2 - radius**2)  # tangent cone, not f R / d
    assert abs(measured - expect) / expect < 0.01
    assert abs(measured - focal * radius / dist) / expect > 0.05
    # The nearest point is at depth dist - radius, in the center.
    c = size // 2
    np.testing.assert_allclose(frags.depth[c, c], dist - radius, rtol=2e-3)


def test_perspective_depth_and_barycentrics_are_perspective_correct():
    # A plane tilted in depth: depth and interpolated world points follow the pixel rays.
    v = np.array([[-1, -1, -1.5], [1, -1, 0.5], [1, 1, 0.5], [-1, 1, -1.5]], float)
    f = np.array([[0, 1, 2], [0, 2, 3]])
    size, fov = 64, 50.0
    cam = Camera(eye=(0.0, 0.0, 3.0), up=(0.0, 1.0, 0.0), fov=fov)
    frags = render.rasterize(cam, v, f, size, size)
    rows, cols = np.nonzero(frags.covered)
    focal = cam.focal(size)
    ray = np.stack([(cols + 0.5 - size / 2) / focal, (size / 2 - rows - 0.5) / focal,
                    -np.ones(len(rows))], -1)                    # depth-1 ray (camera = world)
    normal = np.array([-1.0, 0.0, 1.0])                          # plane: z = x - 0.5
    t = (-0.5 - normal @ np.array([0, 0, 3.0])) / (ray @ normal)
    np.testing.assert_allclose(frags.depth[rows, cols], t, rtol=1e-5)
    world = np.einsum("nk,nkd->nd", frags.bary[rows, cols], v[f][frags.face[rows, cols]])
    np.testing.assert_allclose(world, np.array([0, 0, 3.0]) + t[:, None] * ray, atol=1e-5)


def test_fit_camera_frames_every_point_of_a_sequence():
    rng = np.random.default_rng(0)
    frames = rng.normal(size=(5, 200, 3)) * [0.3, 0.2, 0.5] + rng.normal(size=(5, 1, 3))
    for projection in ("perspective", "orthographic"):
        for aspect in (1.0, 2.0, 0.5):
            cam = render.fit_camera(frames, projection=projection, aspect=aspect, azimuth=35,
                                    elevation=25)
            h = 100
            w = int(h * aspect)
            for frame in frames:
                p = cam.project(frame, h, w)
                assert (p[:, 0] >= 0).all() and (p[:, 0] <= w).all()
                assert (p[:, 1] >= 0).all() and (p[:, 1] <= h).all()
                assert (p[:, 2] > cam.near).all()


# ---------------------------------------------------------------- normal maps


@pytest.fixture(scope="module")
def sheet_map():
    g = primitives.grid_sheet(6, 6, size=(0.4, 0.4))
    layout = normalmap.layout_for(g, texel_size=0.01)
    mask = np.asarray(normalmap.make_plan(g, texel_size=0.01).mask)
    cam = Camera(eye=(0.2, 0.2, 2.0), target=(0.2, 0.2, 0.0), up=(0, 1, 0), fov=20)
    return g, layout, mask, cam


def _render_sheet(g, cam, **kw):
    return render.render_mesh(g.vertices, g.faces, cam, 48, color=WHITE, background=BLACK,
                              supersample=1, **kw)


def test_constant_geometric_normal_map_gives_the_plain_image(sheet_map):
    g, layout, mask, cam = sheet_map
    light = Light(direction=(0.3, 0.4, 1.0), camera_frame=False)
    plain = _render_sheet(g, cam, light=light)
    nmap = np.zeros((layout.height, layout.width, 3), np.float32)
    nmap[..., 2] = 1.0
    mapped = _render_sheet(g, cam, light=light, normal_map=nmap, uvs=g.uvs, uv_faces=g.uv_faces,
                           layout=layout, mask=mask)
    np.testing.assert_allclose(mapped, plain, atol=1e-6)


def test_normal_map_tilts_the_shading_where_it_is_painted(sheet_map):
    g, layout, mask, cam = sheet_map
    # Tilt the normals of the map's left half (u < 0.2 m, i.e. world x < 0.2) by 60 degrees.
    nmap = np.zeros((layout.height, layout.width, 3), np.float32)
    nmap[..., 2] = 1.0
    left = layout.width // 2 - 4
    nmap[:, :left] = [math.sin(math.radians(60)), 0.0, math.cos(math.radians(60))]
    img = _render_sheet(g, cam, light=LAMBERT, normal_map=nmap, uvs=g.uvs, uv_faces=g.uv_faces,
                        layout=layout, mask=mask)
    frags = render.rasterize(cam, g.vertices, g.faces, 48, 48)
    world_x = np.einsum("hwk,hwk->hw", frags.bary, g.vertices[g.faces][frags.face][..., 0])
    cov = frags.covered
    far_left = cov & (world_x < 0.1)
    far_right = cov & (world_x > 0.25)
    np.testing.assert_allclose(img[far_left, 0], 0.5, atol=1e-3)    # cos 60
    np.testing.assert_allclose(img[far_right, 0], 1.0, atol=1e-6)


def test_masked_out_texels_fall_back_to_the_geometric_normal(sheet_map):
    g, layout, mask, cam = sheet_map
    garbage = np.zeros((layout.height, layout.width, 3), np.float32)
    garbage[..., 0] = 1.0                                         # sideways everywhere
    img = _render_sheet(g, cam, light=LAMBERT, normal_map=garbage, uvs=g.uvs,
                        uv_faces=g.uv_faces, layout=layout, mask=np.zeros_like(mask))
    plain = _render_sheet(g, cam, light=LAMBERT)
    np.testing.assert_allclose(img, plain, atol=1e-6)


def test_normal_map_shading_needs_the_layout(sheet_map):
    g, layout, mask, cam = sheet_map
    nmap = np.zeros((layout.height, layout.width, 3), np.float32)
    with pytest.raises(RenderError, match="layout"):
        _render_sheet(g, cam, normal_map=nmap, uvs=g.uvs, uv_faces=g.uv_faces)


def test_normal_map_image_paints_the_background():
    rgb = np.full((4, 5, 3), 0.25, np.float32)
    mask = np.zeros((4, 5, 1), np.float32)
    mask[1:3, 1:4] = 1
    img = render.normal_map_image(rgb, mask, background=(1.0, 0.0, 0.0))
    assert img.dtype == np.uint8 and img.shape == (4, 5, 3)
    np.testing.assert_array_equal(img[2, 2], [64, 64, 64])
    np.testing.assert_array_equal(img[0, 0], [255, 0, 0])


# ---------------------------------------------------------------- antialiasing, panels


def test_supersampling_blends_edges_only():
    v, f = _quad(-0.53, 0.47, -0.51, 0.49)
    kw = dict(light=LAMBERT, color=WHITE, background=BLACK)
    hard = render.render_mesh(v, f, _front_ortho(2.0), 50, supersample=1, **kw)
    soft = render.render_mesh(v, f, _front_ortho(2.0), 50, supersample=4, **kw)
    assert set(np.unique(hard)) <= {0.0, 1.0}
    partial = (soft[..., 0] > 0.01) & (soft[..., 0] < 0.99)
    assert partial.sum() > 20
    # Coverage is preserved on average (area of the quad in pixels: 25 x 25).
    np.testing.assert_allclose(soft[..., 0].sum(), 625.0, rtol=0.02)


def test_preview_panel_shows_three_labelled_views():
    g = primitives.grid_sheet(8, 8, size=(0.4, 0.4),
                              height_fn=lambda x, y: 0.03 * np.sin(12 * x))
    plan = normalmap.make_plan(g, texel_size=0.01)
    nmap = np.zeros(plan.shape + (3,), np.float32)
    nmap[..., 0] = 0.7
    nmap[..., 2] = 0.7
    cam = render.fit_camera(g.vertices, elevation=50)
    lifted = g.vertices + [0, 0, 0.02]
    panel = render.preview_panel(g.vertices, g.faces, nmap, lifted, g.faces, g.uvs, g.uv_faces,
                                 camera=cam, size=64, layout=plan.layout, mask=plan.mask)
    assert panel.shape == (64, 192, 3) and panel.dtype == np.uint8
    left, mid, right = panel[:, :64], panel[:, 64:128], panel[:, 128:]
    body = slice(20, 64)                                 # below the labels
    assert np.abs(left[body].astype(int) - mid[body]).max() > 30   # the map changes shading
    assert (left[:8] < 100).any()                        # a dark label in the corner
    assert (right[body] < 250).any()
    empty = render.preview_panel(g.vertices, g.faces, None, None, None, g.uvs, g.uv_faces,
                                 camera=cam, size=64)
    assert empty.shape == (64, 192, 3)
    assert (empty[20:, 64:] == 255).all()                # blank middle and right views


# ---------------------------------------------------------------- files


def test_write_png_keeps_rgb_order(tmp_path):
    img = np.zeros((6, 7, 3), np.uint8)
    img[..., 0] = 200                                    # red
    render.write_png(tmp_path / "a.png", img)
    back = cv2.imread(str(tmp_path / "a.png"), cv2.IMREAD_UNCHANGED)
    np.testing.assert_array_equal(back[..., ::-1], img)
    with pytest.raises(RenderError):
        render.write_png(tmp_path / "b.png", np.zeros((4, 4, 2)))
    assert not (tmp_path / "b.png").exists()


def test_write_mp4_streams_readable_frames(tmp_path):
    n, h, w = 7, 48, 64
    colors = np.linspace(30, 220, n).astype(np.uint8)
    produced = []

    def frames():
        for c in colors:
            produced.append(int(c))
            yield np.full((h, w, 3), c, np.uint8)

    path = tmp_path / "out" / "video.mp4"
    assert render.write_mp4(path, frames(), fps=10) == n
    assert len(produced) == n
    cap = cv2.VideoCapture(str(path))
    read = []
    while True:
        ok, frame = cap.read()
        if not ok:
            break
        read.append(frame)
    cap.release()
    assert len(read) == n
    assert read[0].shape == (h, w, 3)
    np.testing.assert_allclose([f.mean() for f in read], colors, atol=6)
    assert sorted(p.name for p in path.parent.iterdir()) == ["video.mp4"]  # no temporaries


@pytest.mark.parametrize("umask", [0o022, 0o077])
def test_write_mp4_file_mode_follows_the_umask(tmp_path, monkeypatch, umask):
    from wrinkle_jax import fileio

    monkeypatch.setattr(fileio, "_UMASK", umask)
    path = tmp_path / "v.mp4"
    render.write_mp4(path, [np.zeros((16, 16, 3), np.uint8)] * 2, fps=5)
    assert path.stat().st_mode & 0o777 == 0o666 & ~umask


def test_write_mp4_rejects_bad_frames_and_leaves_nothing(tmp_path):
    path = tmp_path / "bad.mp4"
    frames = [np.zeros((16, 16, 3), np.uint8), np.zeros((16, 20, 3), np.uint8)]
    with pytest.raises(RenderError, match="frame 1"):
        render.write_mp4(path, frames, fps=5)
    with pytest.raises(RenderError, match="no frames"):
        render.write_mp4(path, [], fps=5)
    assert list(tmp_path.iterdir()) == []


def test_write_mp4_reports_an_unopenable_writer(tmp_path, monkeypatch):
    class Closed:
        def __init__(self, *args):
            pass

        def isOpened(self):  # noqa: N802 (OpenCV's name)
            return False

        def release(self):
            pass

    monkeypatch.setattr(render.cv2, "VideoWriter", Closed)
    with pytest.raises(RenderError, match="cannot open an MP4 writer"):
        render.write_mp4(tmp_path / "x.mp4", [np.zeros((8, 8, 3), np.uint8)], fps=5)
    assert list(tmp_path.iterdir()) == []


def test_bad_input_is_named():
    v, f = _quad()
    with pytest.raises(RenderError, match="non-finite"):
        render.rasterize(_front_ortho(), v * np.nan, f, 8, 8)
    with pytest.raises(RenderError, match="face indices"):
        render.rasterize(_front_ortho(), v, f + 10, 8, 8)
    with pytest.raises(RenderError, match="projection"):
        Camera(eye=(0, 0, 1), projection="fisheye")
    with pytest.raises(RenderError, match="parallel"):
        Camera(eye=(0, 0, 1), up=(0, 0, 1)).basis()
