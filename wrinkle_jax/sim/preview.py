"""Quick preview images of simulated frames (matplotlib, NumPy; not for hot paths).

`render_frame(ax, vertices, faces, ...)` draws a Lambert-shaded mesh with the painter's
algorithm under an orthographic camera (azimuth/elevation in degrees), plus optional capsules
and spheres as grey silhouettes. `save_comparison(path, rows)` writes a grid of such views and
baked normal maps (fine vs coarse side by side).
"""

from __future__ import annotations

import numpy as np


def _camera(azim: float, elev: float):
    a, e = np.radians(azim), np.radians(elev)
    fwd = np.array([np.cos(e) * np.sin(a), -np.cos(e) * np.cos(a), np.sin(e)])  # to the viewer
    right = np.array([np.cos(a), np.sin(a), 0.0])
    up = np.cross(fwd, right)
    return right, up, fwd


def render_frame(ax, vertices, faces, azim: float = 20.0, elev: float = 10.0, capsules=None,
                 capsule_radii=None, spheres=None, sphere_radii=None, color=(0.55, 0.7, 0.95)):
    """Draw one frame on a matplotlib axis (orthographic, painter's algorithm).

    Args:
      vertices: (V, 3) m; faces: (F, 3).
      capsules: optional (C, 2, 3) ends with capsule_radii (C,); spheres: (S, 3) with radii.
    """
    from matplotlib.collections import PolyCollection

    right, up, fwd = _camera(azim, elev)
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces)
    p = v[f]
    n = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    light = np.array([0.3, -0.6, 0.75])
    light /= np.linalg.norm(light)
    # Two-sided shading; the back side is tinted so folds read clearly.
    facing = n @ fwd
    shade = 0.25 + 0.75 * np.abs(n @ light)
    base = np.where(facing[:, None] >= 0, np.asarray(color), np.asarray(color) * [1.0, 0.8, 0.7])
    rgb = np.clip(base * shade[:, None], 0, 1)
    items = [(p @ right, p @ up, (p @ fwd).mean(1), rgb)]
    if capsules is not None:
        c = np.asarray(capsules, np.float64)
        r = np.asarray(capsule_radii, np.float64)
        t = np.linspace(0, 1, 6)
        pts = c[:, None, 0] + t[None, :, None] * (c[:, None, 1] - c[:, None, 0])
        items.append(("caps", pts.reshape(-1, 3), np.repeat(r, len(t))))
    if spheres is not None:
        items.append(("caps", np.asarray(spheres, np.float64), np.asarray(sphere_radii)))
    polys, depth, colors = [], [], []
    x2, y2, d, rgb = items[0]
    polys.extend(np.stack([x2, y2], -1))
    depth.extend(d)
    colors.extend(rgb)
    ang = np.linspace(0, 2 * np.pi, 16, endpoint=False)
    for it in items[1:]:
        _, centers, radii = it
        for cen, rad in zip(centers, radii, strict=True):
            cx, cy = cen @ right, cen @ up
            polys.append(np.stack([cx + rad * np.cos(ang), cy + rad * np.sin(ang)], -1))
            depth.append(cen @ fwd)
            colors.append((0.75, 0.72, 0.7))
    order = np.argsort(depth)
    pc = PolyCollection([polys[i] for i in order], facecolors=[colors[i] for i in order],
                        edgecolors="none", antialiased=False)
    ax.add_collection(pc)
    allxy = np.concatenate([np.asarray(q) for q in polys])
    lo, hi = allxy.min(0), allxy.max(0)
    span = float((hi - lo).max()) * 0.55 + 1e-6
    mid = (lo + hi) / 2
    ax.set_xlim(mid[0] - span, mid[0] + span)
    ax.set_ylim(mid[1] - span, mid[1] + span)
    ax.set_aspect("equal")
    ax.axis("off")


def save_comparison(path, panels, titles, dpi: int = 80, ncols: int | None = None):
    """Save a grid of panels: each a callable(ax) drawing one view or image; PNG, atomically."""
    import io

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from wrinkle_jax.fileio import atomic_write_bytes

    ncols = ncols or len(panels)
    nrows = (len(panels) + ncols - 1) // ncols
    fig, axes = plt.subplots(nrows, ncols, figsize=(3.2 * ncols, 3.4 * nrows), squeeze=False)
    for ax in axes.reshape(-1):
        ax.axis("off")
    for ax, draw, title in zip(axes.reshape(-1), panels, titles, strict=False):
        draw(ax)
        ax.set_title(title, fontsize=8)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi)
    plt.close(fig)
    atomic_write_bytes(path, buf.getvalue())
