"""Camera and light of the preview renderer (`render`): a look-at camera, a camera fitted to a
whole sequence so views do not jump, and a directional plus ambient light.

World units are meters. Camera frame: x right, y up, z towards the viewer; depth is the
distance along the viewing direction (positive in front of the camera); pixel (row r, col c)
has its center at continuous coordinates (x, y) = (c + 0.5, r + 0.5). `render` re-exports every
name here (old import paths keep working).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

__all__ = ["Camera", "Light", "RenderError", "fit_camera"]


class RenderError(ValueError):
    """Invalid rendering input or an output that cannot be written (the message says which)."""


# --------------------------------------------------------------------------------------------
# Camera and light
# --------------------------------------------------------------------------------------------


def _unit(v, what: str) -> np.ndarray:
    v = np.asarray(v, np.float64)
    n = float(np.linalg.norm(v))
    if not (np.isfinite(n) and n > 0):
        raise RenderError(f"{what} must be a finite non-zero vector, got {tuple(v)}")
    return v / n


@dataclasses.dataclass(frozen=True)
class Camera:
    """A look-at camera (static, hashable).

    Attributes:
      eye: camera position, meters.
      target: the point looked at, meters.
      up: approximate up direction (orthogonalized against the viewing direction).
      projection: "perspective" or "orthographic".
      fov: vertical field of view in degrees (perspective).
      ortho_height: meters of the scene spanned by the image height (orthographic).
      near: triangles with a vertex at depth < near (meters) are not drawn.
    """

    eye: tuple[float, float, float]
    target: tuple[float, float, float] = (0.0, 0.0, 0.0)
    up: tuple[float, float, float] = (0.0, 0.0, 1.0)
    projection: str = "perspective"
    fov: float = 30.0
    ortho_height: float = 1.0
    near: float = 1e-3

    def __post_init__(self):
        for name in ("eye", "target", "up"):
            object.__setattr__(self, name, tuple(float(x) for x in getattr(self, name)))
        if self.projection not in ("perspective", "orthographic"):
            raise RenderError(f"projection must be 'perspective' or 'orthographic', "
                              f"got {self.projection!r}")
        if not 0.0 < self.fov < 180.0:
            raise RenderError(f"fov must be in (0, 180) degrees, got {self.fov}")
        if not self.ortho_height > 0:
            raise RenderError(f"ortho_height must be positive, got {self.ortho_height}")

    @property
    def perspective(self) -> bool:
        return self.projection == "perspective"

    def basis(self) -> np.ndarray:
        """(3, 3) rows: right, up, back (= towards the viewer), world coordinates."""
        back = _unit(np.subtract(self.eye, self.target), "eye - target")
        right = np.cross(_unit(self.up, "up"), back)
        if np.linalg.norm(right) < 1e-9:
            raise RenderError(f"camera up {self.up} is parallel to the viewing direction")
        right /= np.linalg.norm(right)
        return np.stack([right, np.cross(back, right), back])

    def focal(self, height: int) -> float:
        """Pixels per unit of (lateral offset / depth) for a perspective image `height` tall."""
        return 0.5 * height / math.tan(math.radians(self.fov) / 2)

    def project(self, points, height: int, width: int) -> np.ndarray:
        """World points (N, 3) meters -> (N, 3) float64: pixel x, pixel y, depth (meters)."""
        p = np.asarray(points, np.float64) - np.asarray(self.eye)
        cam = p @ self.basis().T
        depth = -cam[:, 2]
        if self.perspective:
            scale = self.focal(height) / np.where(depth > 0, depth, 1.0)
            scale = scale[:, None]
        else:
            scale = height / self.ortho_height
        xy = cam[:, :2] * scale
        return np.stack([0.5 * width + xy[:, 0], 0.5 * height - xy[:, 1], depth], axis=1)


def fit_camera(points, *, azimuth: float = 20.0, elevation: float = 10.0,
               up=(0.0, 0.0, 1.0), front=(0.0, -1.0, 0.0), projection: str = "perspective",
               fov: float = 30.0, margin: float = 1.05, aspect: float = 1.0) -> Camera:
    """A camera that frames every point, e.g. all frames of a sequence (views do not jump).

    The sphere about the center of the points' bounding box that holds every point is fitted
    into the image (whatever the viewing direction); the camera
    looks at the box center from the direction `front` turned by `azimuth` about `up` and
    raised by `elevation`.

    Args:
      points: (..., 3) meters, e.g. (T, V, 3) frames or a (2, 3) bounding box.
      azimuth, elevation: viewing direction in degrees.
      up: the world's up axis (the bundled garments are z-up). front: the direction from the
        garment towards the viewer at azimuth 0 (perpendicular to `up`).
      projection, fov: as in `Camera`. margin: >= 1, extra room around the sphere.
      aspect: image width / height the camera is fitted for.
    Returns:
      Camera.
    """
    p = np.asarray(points, np.float64).reshape(-1, 3)
    if p.size == 0 or not np.isfinite(p).all():
        raise RenderError("fit_camera needs at least one point and only finite coordinates")
    center = (p.min(0) + p.max(0)) / 2
    # The smallest sphere about the box center holding every point (tighter than the box's).
    radius = max(float(np.sqrt(((p - center) ** 2).sum(1).max())), 1e-6) * margin
    u = _unit(up, "up")
    f = np.asarray(front, np.float64)
    f = _unit(f - (f @ u) * u, "front (perpendicular to up)")
    a, e = math.radians(azimuth), math.radians(elevation)
    side = np.cross(u, f)
    direction = math.cos(e) * (math.cos(a) * f + math.sin(a) * side) + math.sin(e) * u
    # Half the narrower field of view must see the whole sphere.
    half_v = math.radians(fov) / 2
    half = min(half_v, math.atan(math.tan(half_v) * aspect))
    distance = radius / math.sin(half)
    eye = center + distance * direction
    ortho_height = 2 * radius / min(1.0, aspect)
    return Camera(eye=tuple(eye), target=tuple(center), up=tuple(u), projection=projection,
                  fov=fov, ortho_height=ortho_height, near=1e-3 * distance)


@dataclasses.dataclass(frozen=True)
class Light:
    """A directional light plus ambient light (static, hashable).

    Pixel intensity = ambient + diffuse * max(0, n . l), times the albedo.

    Attributes:
      direction: towards the light (normalized internally); in the camera frame (x right,
        y up, z towards the viewer) when `camera_frame`, else in world coordinates.
      ambient, diffuse: intensities.
      camera_frame: the light moves with the camera (the default: every view is lit alike).
    """

    direction: tuple[float, float, float] = (-0.35, 0.45, 1.0)
    ambient: float = 0.22
    diffuse: float = 0.78
    camera_frame: bool = True

    def world_direction(self, camera: Camera) -> np.ndarray:
        """(3,) unit vector towards the light, world coordinates."""
        d = _unit(self.direction, "light direction")
        return d @ camera.basis() if self.camera_frame else d
