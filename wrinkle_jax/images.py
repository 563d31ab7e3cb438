"""Images at the edges of the preview renderer (`render`): float [0, 1] to uint8, a normal map
for viewing, and atomic PNG and streamed MP4 output (OpenCV).

Images are float32 (H, W, 3) RGB in [0, 1] inside `render`, uint8 RGB here. `render`
re-exports every name here (old import paths keep working).
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Iterable
from pathlib import Path

import cv2
import numpy as np

from wrinkle_jax import fileio
from wrinkle_jax.camera import RenderError

__all__ = ["normal_map_image", "to_uint8", "write_mp4", "write_png"]


def to_uint8(image) -> np.ndarray:
    """Float [0, 1] (or uint8) image -> uint8, rounded; NaNs become 0."""
    x = np.asarray(image)
    if x.dtype == np.uint8:
        return x
    x = np.nan_to_num(x.astype(np.float64), nan=0.0)
    return np.round(np.clip(x, 0.0, 1.0) * 255.0).astype(np.uint8)


def normal_map_image(rgb_map, mask=None, background=(0.5, 0.5, 0.5)) -> np.ndarray:
    """A normal map for viewing: its RGB form on a flat background.

    Args:
      rgb_map: (H, W, 3) the RGB form (n + 1) / 2 in [0, 1] (pass `normalmap.to_rgb(n)` for a
        map of unit normals n in [-1, 1]).
      mask: optional (H, W) or (H, W, 1) in [0, 1]; texels outside get `background`.
      background: RGB in [0, 1].
    Returns:
      (H, W, 3) uint8 RGB.
    """
    rgb = np.asarray(rgb_map, np.float64)
    if rgb.ndim != 3 or rgb.shape[2] != 3:
        raise RenderError(f"normal_map_image expects (H, W, 3), got shape {rgb.shape}")
    if mask is not None:
        m = np.clip(np.asarray(mask, np.float64).reshape(rgb.shape[0], rgb.shape[1], 1), 0, 1)
        rgb = rgb * m + np.asarray(background, np.float64) * (1 - m)
    return to_uint8(rgb)


def _as_rgb8(image, what: str) -> np.ndarray:
    img = to_uint8(image)
    if img.ndim == 2:
        img = np.repeat(img[..., None], 3, axis=2)
    if img.ndim != 3 or img.shape[2] != 3 or img.shape[0] < 1 or img.shape[1] < 1:
        raise RenderError(f"{what}: expected an (H, W, 3) RGB image, got shape {img.shape}")
    return img


def write_png(path: str | os.PathLike, image) -> None:
    """Write an RGB image ((H, W, 3) uint8, or float in [0, 1]) as an 8-bit PNG, atomically."""
    from wrinkle_jax.fileio import atomic_write_bytes

    img = _as_rgb8(image, str(path))
    ok, buf = cv2.imencode(".png", np.ascontiguousarray(img[..., ::-1]))  # OpenCV wants BGR
    if not ok:
        raise RenderError(f"{path}: PNG encoding failed")
    atomic_write_bytes(path, buf.tobytes())


def write_mp4(path: str | os.PathLike, frames: Iterable, fps: float = 24.0) -> int:
    """Stream RGB frames into an MP4 file (OpenCV, codec 'mp4v'), atomically.

    Frames are encoded as they arrive (a generator is never materialized). The first frame
    fixes the size; every frame must match it. The video is written to a temporary file in
    the same folder and renamed when complete: a failure leaves no partial file.

    Args:
      path: output file (.mp4). frames: iterable of (H, W, 3) uint8 RGB (or float in [0, 1]).
      fps: frames per second (> 0).
    Returns:
      The number of frames written.
    Raises:
      RenderError: no frames, a frame of another size, or OpenCV cannot open the writer.
    """
    path = Path(path)
    if not fps > 0:
        raise RenderError(f"{path}: fps must be positive, got {fps}")
    if path.is_dir():
        raise RenderError(f"{path}: is a directory, cannot write a video there")
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp.mp4", dir=path.parent)
    os.close(fd)
    writer = None
    count = 0
    shape = None
    try:
        for frame in frames:
            img = _as_rgb8(frame, f"{path}: frame {count}")
            if writer is None:
                shape = img.shape
                writer = cv2.VideoWriter(tmp, cv2.VideoWriter_fourcc(*"mp4v"), float(fps),
                                         (shape[1], shape[0]))
                if not writer.isOpened():
                    raise RenderError(f"{path}: OpenCV cannot open an MP4 writer (codec "
                                      f"'mp4v', {shape[1]}x{shape[0]}); this OpenCV build "
                                      f"may lack FFmpeg video support")
            elif img.shape != shape:
                raise RenderError(f"{path}: frame {count} has shape {img.shape}, the first "
                                  f"frame {shape}")
            writer.write(np.ascontiguousarray(img[..., ::-1]))
            count += 1
        if writer is None:
            raise RenderError(f"{path}: no frames to write")
        writer.release()
        writer = None
        if os.path.getsize(tmp) == 0:
            raise RenderError(f"{path}: OpenCV wrote an empty video")
        os.chmod(tmp, 0o666 & ~fileio._UMASK)  # a new file's mode, as open() would give
        os.replace(tmp, path)
    finally:
        if writer is not None:
            writer.release()
        if os.path.exists(tmp):
            os.unlink(tmp)
    return count
