"""Procedural garments with known geometry: sheets, cylinder panels, sphere caps and a
seamed cube. Used by tests (closed-form normals), benchmarks and the demo.

All return validated `Garment`s (NumPy arrays) in meters, with UVs in meters of the unrolled
surface wherever the surface is developable (so one UV unit is one meter of cloth). Two
benchmark inputs live here too, so every benchmark times the same case: the wrinkled-sheet
lifting case (`wrinkled_sheet_case`) and wavy normal-map patches (`wavy_normal_maps`).
"""

from __future__ import annotations

import numpy as np

from wrinkle_jax import subdivision
from wrinkle_jax.mesh import Garment, make_garment, unique_rows


def _grid_faces(nx: int, ny: int, alternate: bool = True) -> np.ndarray:
    """Triangles of an (ny+1) x (nx+1) vertex grid (row-major), counter-clockwise in (x, y).

    With `alternate`, the diagonal direction alternates per cell (a "union jack"-free but
    symmetric pattern), so one-rings are point-symmetric in the interior.
    """
    j, i = np.meshgrid(np.arange(ny), np.arange(nx), indexing="ij")
    a = j * (nx + 1) + i
    b, c, d = a + 1, a + nx + 1, a + nx + 2  # b right, c up, d up-right
    flip = ((i + j) % 2 == 1) if alternate else np.zeros_like(a, bool)
    t1 = np.where(flip[..., None], np.stack([a, b, c], -1), np.stack([a, b, d], -1))
    t2 = np.where(flip[..., None], np.stack([b, d, c], -1), np.stack([a, d, c], -1))
    return np.stack([t1, t2], axis=2).reshape(-1, 3).astype(np.int32)


def grid_sheet(nx: int = 32, ny: int = 32, size=(1.0, 1.0), height_fn=None, jitter: float = 0.0,
               seed: int = 0, alternate: bool = True) -> Garment:
    """A rectangular sheet in the z = 0 plane (optionally displaced by a height field).

    Args:
      nx, ny: cells along x and y.
      size: (width, height) in meters.
      height_fn: optional f(x, y) -> z (arrays, meters) displacing the sheet along +z.
      jitter: random in-plane offset of interior vertices, as a fraction of the cell size
        (applied to positions and UVs alike, so the UV layout stays isometric).
      seed: NumPy seed for the jitter.
      alternate: alternate diagonal directions (symmetric one-rings on the regular grid).
    Returns:
      Garment with (nx+1)(ny+1) vertices; UVs = (x, y) in meters; normals along +z when flat.
    """
    xs = np.linspace(0.0, size[0], nx + 1)
    ys = np.linspace(0.0, size[1], ny + 1)
    x, y = np.meshgrid(xs, ys, indexing="xy")
    if jitter > 0:
        rng = np.random.default_rng(seed)
        hx, hy = size[0] / nx, size[1] / ny
        interior = np.zeros_like(x, bool)
        interior[1:-1, 1:-1] = True
        x = x + interior * rng.uniform(-jitter, jitter, x.shape) * hx
        y = y + interior * rng.uniform(-jitter, jitter, y.shape) * hy
    z = np.zeros_like(x) if height_fn is None else height_fn(x, y)
    v = np.stack([x, y, z], -1).reshape(-1, 3)
    uv = v[:, :2].copy()
    f = _grid_faces(nx, ny, alternate)
    return make_garment(v, f, uv, f, source="grid_sheet")


def cylinder_panel(radius: float = 0.2, height: float = 0.5, angle: float = np.pi,
                   n_theta: int = 48, n_h: int = 24) -> Garment:
    """An open cylindrical panel around the z axis with its UVs unrolled isometrically.

    Vertices at (r cos t, r sin t, z) for t in [0, angle], z in [0, height]; UV = (r t, z).
    Outward normals are (cos t, sin t, 0).
    """
    t = np.linspace(0.0, angle, n_theta + 1)
    z = np.linspace(0.0, height, n_h + 1)
    tt, zz = np.meshgrid(t, z, indexing="xy")
    v = np.stack([radius * np.cos(tt), radius * np.sin(tt), zz], -1).reshape(-1, 3)
    uv = np.stack([radius * tt, zz], -1).reshape(-1, 2)
    f = _grid_faces(n_theta, n_h)
    # Grid faces are counter-clockwise in (t, z); (d/dt x d/dz) points outward.
    return make_garment(v, f, uv, f, source="cylinder_panel")


def sphere_cap(radius: float = 0.3, max_polar: float = 1.0, n_rings: int = 16,
               n_segments: int = 48) -> Garment:
    """A spherical cap around +z (polar angle <= max_polar radians), outward normals.

    UVs are the azimuthal-equidistant map (r * polar) * (cos az, sin az), which preserves
    radial distances (a disc). The exact normal at a point is its position / radius.
    """
    polar = np.linspace(0.0, max_polar, n_rings + 1)[1:]
    az = np.linspace(0.0, 2 * np.pi, n_segments, endpoint=False)
    pp, aa = np.meshgrid(polar, az, indexing="ij")
    ring = np.stack([np.sin(pp) * np.cos(aa), np.sin(pp) * np.sin(aa), np.cos(pp)], -1)
    v = np.concatenate([[[0.0, 0.0, 1.0]], ring.reshape(-1, 3)]) * radius
    uvr = radius * np.concatenate([[0.0], pp.reshape(-1)])
    ua = np.concatenate([[0.0], aa.reshape(-1)])
    uv = np.stack([uvr * np.cos(ua), uvr * np.sin(ua)], -1)
    faces = []
    s = n_segments
    for k in range(s):  # the fan around the pole
        faces.append([0, 1 + k, 1 + (k + 1) % s])
    for r in range(n_rings - 1):
        for k in range(s):
            a = 1 + r * s + k
            b = 1 + r * s + (k + 1) % s
            c = a + s
            d = b + s
            faces += [[a, c, d], [a, d, b]]
    f = np.asarray(faces, np.int32)
    return make_garment(v, f, uv, f, source="sphere_cap")


def uv_cube(size: float = 0.4, n: int = 8, gap: float = 0.05) -> Garment:
    """A closed cube (welded in 3D) whose six faces are separate UV panels (seams everywhere).

    The six panels are laid out in a 3 x 2 atlas with `gap` meters between them; panel k is
    the face whose outward normal is +x, -x, +y, -y, +z, -z for k = 0..5.
    """
    h = size / 2
    g = np.linspace(-h, h, n + 1)
    a, b = np.meshgrid(g, g, indexing="xy")
    grid_f = _grid_faces(n, n)
    verts, uvs, faces, panels = [], [], [], []
    for k in range(6):
        ax = k // 2
        # Build a right-handed in-plane frame (e1, e2) with e1 x e2 = outward normal.
        normal = np.zeros(3)
        normal[ax] = 1.0 if k % 2 == 0 else -1.0
        e1 = np.zeros(3)
        e1[(ax + 1) % 3] = 1.0
        e2 = np.cross(normal, e1)
        p = normal * h + a[..., None] * e1 + b[..., None] * e2
        base = len(verts) * (n + 1) ** 2
        verts.append(p.reshape(-1, 3))
        col, row = k % 3, k // 3
        off = np.array([col * (size + gap), row * (size + gap)])
        uvs.append(np.stack([a + h, b + h], -1).reshape(-1, 2) + off)
        faces.append(grid_f + base)
        panels.append(np.full(len(grid_f), k))
    v = np.concatenate(verts)
    uv = np.concatenate(uvs)
    uf = np.concatenate(faces)
    # Weld coincident corners/edges in 3D while the UV faces keep the per-panel copies.
    key = np.round(v / (size / n) * 4).astype(np.int64)
    _, first, inv = unique_rows(key, return_index=True, return_inverse=True)
    order = np.argsort(first)
    remap = np.empty_like(order)
    remap[order] = np.arange(len(order))
    welded = v[first[order]]
    f = remap[inv.reshape(-1)][uf]
    return make_garment(welded, f, uv, uf, np.concatenate(panels), source="uv_cube")



def flared_skirt(waist_radius: float = 0.12, hem_radius: float = 0.32, length: float = 0.6,
                 n_theta: int = 64, n_s: int = 20, n_panels: int = 2) -> Garment:
    """A conical flared skirt sewn from `n_panels` identical panels (welded side seams).

    The cone's apex is above the waist on the +z axis; the skirt hangs from z = 0 down, with
    `length` the slant length (waist to hem along the cloth), in meters. Each panel's UVs are
    its exact unrolling (an annular sector, in meters), the pattern a tailor would cut, so 3D
    and UV lengths agree at rest. Vertices are a (n_s + 1) x n_theta grid (ring-major,
    periodic in theta); UV copies are split at the seams.
    """
    if n_theta % n_panels:
        raise ValueError("n_theta must be a multiple of n_panels")
    if not length > hem_radius - waist_radius > 0:
        raise ValueError("need 0 < hem_radius - waist_radius < length (the slant length)")
    slant = length  # measured along the cloth, waist to hem
    height = np.sqrt(length**2 - (hem_radius - waist_radius) ** 2)
    s = np.linspace(0.0, 1.0, n_s + 1)
    radius = waist_radius + (hem_radius - waist_radius) * s
    theta = np.linspace(0.0, 2 * np.pi, n_theta, endpoint=False)
    rr, tt = np.meshgrid(radius, theta, indexing="ij")
    zz = np.repeat((-height * s)[:, None], n_theta, axis=1)
    v = np.stack([rr * np.cos(tt), rr * np.sin(tt), zz], -1).reshape(-1, 3)
    # Unrolling: distance from the apex rho, sector angle phi = theta * (radius / rho).
    sin_half = (hem_radius - waist_radius) / slant
    rho0 = waist_radius / sin_half
    per = n_theta // n_panels
    faces, uv_faces, uvs, panels = [], [], [], []
    cols = np.arange(per + 1)
    for p in range(n_panels):
        rho = rho0 + slant * s
        phi = (cols * 2 * np.pi / n_theta) * sin_half
        pr, pp = np.meshgrid(rho, phi - phi.mean(), indexing="ij")
        # Panels side by side in UV, with a 5 cm gap; v up = towards the waist.
        off = p * (2 * rho[-1] * np.sin(phi[-1] / 2) + 0.05)
        uv = np.stack([pr * np.sin(pp) + off, -pr * np.cos(pp)], -1).reshape(-1, 2)
        base = sum(len(u) for u in uvs)
        uvs.append(uv)
        j, i = np.meshgrid(np.arange(n_s), np.arange(per), indexing="ij")
        a_uv = base + j * (per + 1) + i
        b_uv, c_uv, d_uv = a_uv + 1, a_uv + per + 1, a_uv + per + 2
        col3 = (p * per + i) % n_theta
        col3n = (p * per + i + 1) % n_theta
        a3, b3 = j * n_theta + col3, j * n_theta + col3n
        c3, d3 = a3 + n_theta, b3 + n_theta
        # Ring index grows downward; order corners so normals point outward.
        faces.append(np.stack([np.stack([a3, c3, b3], -1), np.stack([b3, c3, d3], -1)], 2))
        uv_faces.append(np.stack([np.stack([a_uv, c_uv, b_uv], -1),
                                  np.stack([b_uv, c_uv, d_uv], -1)], 2))
        panels.append(np.full(2 * n_s * per, p))
    f = np.concatenate([x.reshape(-1, 3) for x in faces])
    uf = np.concatenate([x.reshape(-1, 3) for x in uv_faces])
    return make_garment(v, f, np.concatenate(uvs), uf, np.concatenate(panels),
                        source="flared_skirt")


def draped_height(x, y):
    """The wrinkled sheet's coarse shape z(x, y), meters: a 3 cm drape (x, y in meters)."""
    return 0.03 * np.sin(2 * np.pi * x / 0.8) * np.cos(2 * np.pi * y / 1.1)


def wrinkled_height(x, y):
    """`draped_height` plus two crossing wrinkle trains (10 and 13 cm wavelength, fixed
    directions, 3-5 mm amplitude), blended smoothly across the sheet; meters."""
    amp = 0.005 * (0.6 + 0.4 * np.cos(2 * np.pi * y / 0.9))
    mix = 0.5 + 0.5 * np.sin(2 * np.pi * x / 1.3) * np.cos(2 * np.pi * y / 1.7)
    a = np.sin(2 * np.pi / 0.10 * (x * np.cos(0.5) + y * np.sin(0.5)))
    b = np.sin(2 * np.pi / 0.13 * (x * np.cos(2.0) + y * np.sin(2.0)) + 1.0)
    return draped_height(x, y) + amp * (mix * a + (1 - mix) * b)


def wrinkled_sheet_case(cells: int) -> dict:
    """The lifting benchmark's case: a (cells // 4)-cell grid on `draped_height`, side
    cells x 10 mm, subdivided twice by midpoints (10 mm edges when 4 divides cells), and the
    normals of `wrinkled_height` at its vertices.

    Returns:
      {"coarse": the grid `Garment`, "fine": the subdivided `Garment` (its first Vc vertices
       are the coarse ones), "normals": (V, 3) float32 unit target normals (central
       differences of the analytic field), "ideal": (V, 3) float32 the wrinkled surface at the
       fine vertices' (x, y)}.
    """
    side = cells * 0.01
    coarse = grid_sheet(cells // 4, cells // 4, size=(side, side), height_fn=draped_height)
    fine = subdivision.build(coarse, 2).garment(coarse)
    x = np.asarray(fine.vertices[:, 0], np.float64)
    y = np.asarray(fine.vertices[:, 1], np.float64)
    d = 1e-6  # central differences of an analytic field: ~1e-10 truncation error
    hx = (wrinkled_height(x + d, y) - wrinkled_height(x - d, y)) / (2 * d)
    hy = (wrinkled_height(x, y + d) - wrinkled_height(x, y - d)) / (2 * d)
    n = np.stack([-hx, -hy, np.ones_like(hx)], 1)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    return {"coarse": coarse, "fine": fine, "normals": n.astype(np.float32),
            "ideal": np.stack([x, y, wrinkled_height(x, y)], 1).astype(np.float32)}


def wavy_normal_maps(rng: np.random.Generator, batch: int, size: int,
                     waves: int = 8) -> np.ndarray:
    """Wrinkle-like normal-map patches: normals of random height fields, each a sum of `waves`
    sinusoids with amplitudes 0.002-0.01 patch widths and wave numbers drawn from N(0, 12)
    cycles per patch width.

    Returns:
      (batch, size, size, 3) float32, RGB form ((n + 1) / 2) in [0, 1].
    """
    yy, xx = np.mgrid[0:size, 0:size].astype(np.float32) / size
    out = np.empty((batch, size, size, 3), np.float32)
    for i in range(batch):
        hx = np.zeros((size, size), np.float32)
        hy = np.zeros((size, size), np.float32)
        for _ in range(waves):
            kx, ky = rng.normal(0, 12, 2)
            amp, phase = rng.uniform(0.002, 0.01), rng.uniform(0, 2 * np.pi)
            c = amp * 2 * np.pi * np.cos(2 * np.pi * (kx * xx + ky * yy) + phase)
            hx += kx * c
            hy += ky * c
        n = np.stack([-hx, -hy, np.ones_like(hx)], -1)
        out[i] = (n / np.linalg.norm(n, axis=-1, keepdims=True) + 1) / 2
    return out
