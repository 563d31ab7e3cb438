"""Garment IO: Wavefront OBJ files, garment sequences (a folder of OBJ frames, an `.npz` bundle,
or a PC2 point cache with a template OBJ), binary PLY meshes, and a frame-by-frame `.npz`
writer. Every reader validates and raises `GarmentError` naming the file; every writer is
atomic (temporary file + rename).
"""

from __future__ import annotations

import dataclasses
import io
import json
import os
import re
from pathlib import Path

import numpy as np

from wrinkle_jax.fileio import atomic_write_bytes, atomic_write_text
from wrinkle_jax.mesh import Garment, GarmentError, make_garment

# --------------------------------------------------------------------------------------------
# OBJ IO
# --------------------------------------------------------------------------------------------

_PANEL_NAME = re.compile(r"^panel_(\d+)$")


def load_obj(path: str | os.PathLike) -> Garment:
    """Read a Wavefront OBJ with UVs into a `Garment`.

    Polygons are fan-triangulated; `v/vt`, `v/vt/vn` and negative (relative) indices are
    supported; normals are ignored (we recompute them). Groups (`g`/`o`) become panels: names
    `panel_<k>` map back to id k (so `save_obj` round-trips), other names get ids in order of
    first appearance. Without any group, `panels` is None.

    Raises:
      GarmentError: naming the file, if it is unreadable, has faces without UVs, or bad indices.
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8", errors="replace")
    except OSError as e:
        raise GarmentError(f"{path}: cannot read OBJ file ({e.strerror})") from None
    verts: list[list[float]] = []
    uvs: list[list[float]] = []
    faces: list[tuple[int, int, int]] = []
    uv_faces: list[tuple[int, int, int]] = []
    face_group: list[int] = []
    group_ids: dict[str, int] = {}
    current_group = -1
    face_line: list[int] = []  # the line of each triangle, for messages
    missing_uv_line = 0
    for lineno, line in enumerate(text.splitlines(), 1):
        if not line or line[0] == "#":
            continue
        parts = line.split()
        if not parts:
            continue
        tag = parts[0]
        try:
            if tag == "v":
                verts.append([float(parts[1]), float(parts[2]), float(parts[3])])
            elif tag == "vt":
                uvs.append([float(parts[1]), float(parts[2])])
            elif tag == "f":
                vi, ti = [], []
                for tok in parts[1:]:
                    fields = tok.split("/")
                    vi.append(_obj_index(int(fields[0]), len(verts), path, lineno, "vertex"))
                    if len(fields) > 1 and fields[1]:
                        ti.append(_obj_index(int(fields[1]), len(uvs), path, lineno, "UV"))
                if len(vi) < 3:
                    raise GarmentError(f"{path}:{lineno}: a face needs at least 3 vertices")
                if len(ti) != len(vi):
                    missing_uv_line = missing_uv_line or lineno
                    ti = [0] * len(vi)
                for k in range(1, len(vi) - 1):
                    faces.append((vi[0], vi[k], vi[k + 1]))
                    uv_faces.append((ti[0], ti[k], ti[k + 1]))
                    face_group.append(current_group)
                    face_line.append(lineno)
            elif tag in ("g", "o"):
                name = " ".join(parts[1:]) or "default"
                if name not in group_ids:
                    m = _PANEL_NAME.match(name)
                    group_ids[name] = int(m.group(1)) if m else len(group_ids)
                current_group = group_ids[name]
        except GarmentError:
            raise
        except (ValueError, IndexError):
            raise GarmentError(
                f"{path}:{lineno}: malformed '{tag}' line: {line.strip()!r}"
            ) from None
    if not faces:
        raise GarmentError(f"{path}: no faces found")
    if missing_uv_line or not uvs:
        where = f" (first at line {missing_uv_line})" if missing_uv_line else ""
        raise GarmentError(f"{path}: faces without UV coordinates{where}; a UV layout is required")
    _check_obj_range(np.asarray(faces, np.int64), len(verts), face_line, path, "vertex")
    _check_obj_range(np.asarray(uv_faces, np.int64), len(uvs), face_line, path, "UV")
    panels = None
    if group_ids:
        panels = np.asarray(face_group, dtype=np.int32)
        panels[panels < 0] = 0
    return make_garment(
        np.asarray(verts, np.float32).reshape(-1, 3),
        np.asarray(faces, np.int64),
        np.asarray(uvs, np.float32).reshape(-1, 2),
        np.asarray(uv_faces, np.int64),
        panels,
        source=str(path),
    )


def _obj_index(k: int, count: int, path: Path, lineno: int, what: str) -> int:
    """0-based index of OBJ index `k` (1-based, or negative: relative to the `count` read so
    far); 0 and relative indices before the first element are errors naming the line."""
    if k == 0:
        raise GarmentError(f"{path}:{lineno}: {what} index 0 is invalid (OBJ indices start at 1)")
    if k < 0 and count + k < 0:
        raise GarmentError(f"{path}:{lineno}: relative {what} index {k} points before the first "
                           f"{what} ({count} read so far)")
    return k - 1 if k > 0 else count + k


def _check_obj_range(faces: np.ndarray, count: int, face_line: list[int], path: Path,
                     what: str) -> None:
    """Raise naming the first face line whose 1-based `what` index exceeds `count`."""
    bad = np.flatnonzero((faces >= count).any(1)) if faces.size else []
    if len(bad):
        i = int(bad[0])
        plural = {"vertex": "vertices"}.get(what, what + "s")
        raise GarmentError(f"{path}:{face_line[i]}: {what} index {int(faces[i].max()) + 1} is "
                           f"out of range (the file has {count} {plural}: indices 1 to {count})")


def save_obj(path: str | os.PathLike, garment: Garment, vertices=None) -> None:
    """Write a garment as OBJ with `v`, `vt` and `f v/vt` lines (seams preserved).

    Args:
      path: output file; written atomically (temporary file + rename).
      garment: topology and UVs.
      vertices: optional (V, 3) positions replacing `garment.vertices` (e.g. one frame).
    """
    ObjWriter(garment)(path, vertices)


class ObjWriter:
    """`save_obj` for many frames of one garment: the `vt` and `f` lines, the same in every
    frame, are formatted once (two thirds of the lines of a triangle mesh), so each frame only
    formats its `v` lines. The files are byte-identical to `save_obj`'s.

        write = ObjWriter(garment)
        for t, v in enumerate(frames):
            write(f"frame_{t:05d}.obj", v)
    """

    def __init__(self, garment: Garment):
        self.garment = garment
        self._topology: str | None = None  # formatted at the first write, after its checks

    def _format_topology(self) -> str:
        garment = self.garment
        f = np.asarray(garment.faces, dtype=np.int64) + 1
        uv = np.asarray(garment.uvs, dtype=np.float64)
        uf = np.asarray(garment.uv_faces, dtype=np.int64) + 1
        chunks = [_format_rows("vt ", uv, "%.7g %.7g")]
        # Interleave (v, vt) per corner: "f v0/t0 v1/t1 v2/t2".
        corners = np.stack([f, uf], axis=2).reshape(-1, 6)
        face_fmt = "f %d/%d %d/%d %d/%d"
        if garment.panels is None:
            chunks.append(_format_rows("", corners, face_fmt))
        else:
            panels = np.asarray(garment.panels)
            # A new group line wherever the panel id changes along the face order (order kept).
            starts = np.flatnonzero(np.r_[True, panels[1:] != panels[:-1]])
            ends = np.r_[starts[1:], len(panels)]
            for s, e in zip(starts, ends, strict=True):
                chunks.append(f"g panel_{int(panels[s])}\n")
                chunks.append(_format_rows("", corners[s:e], face_fmt))
        return "".join(chunks)

    def __call__(self, path: str | os.PathLike, vertices=None) -> None:
        """Write one frame: (V, 3) `vertices` (default the garment's own) to `path`,
        atomically."""
        g = self.garment
        v = np.asarray(g.vertices if vertices is None else vertices, dtype=np.float64)
        if v.shape != (g.num_vertices, 3):
            raise GarmentError(f"{path}: vertices shape {v.shape} does not match the garment "
                               "topology")
        if self._topology is None:
            self._topology = self._format_topology()
        atomic_write_text(path, "".join(["# wrinkle-jax garment\n",
                                         _format_rows("v ", v, "%.7g %.7g %.7g"),
                                         self._topology]))


def _format_rows(prefix: str, a: np.ndarray, fmt: str) -> str:
    """Rows of `a` formatted with `fmt` (NumPy's C-level formatting), one line each."""
    if len(a) == 0:
        return ""
    buf = io.StringIO()
    np.savetxt(buf, a, fmt=prefix + fmt)
    return buf.getvalue()


# --------------------------------------------------------------------------------------------
# Sequences
# --------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class GarmentSequence:
    """An animation of one garment: shared topology and UVs, per-frame positions.

    Attributes:
      frames: (T, V, 3) float32, meters.
      garment: topology and UVs (its `vertices` are the first frame unless given otherwise).
      fps: frames per second.
      metadata: JSON-serializable dict (material, scene config, source, ...).
    """

    frames: np.ndarray
    garment: Garment
    fps: float = 30.0
    metadata: dict = dataclasses.field(default_factory=dict)

    def __len__(self) -> int:
        return int(self.frames.shape[0])


def make_sequence(frames, garment: Garment, fps: float = 30.0, metadata=None,
                  source: str = "<sequence>") -> GarmentSequence:
    """Validate and build a `GarmentSequence` (frames must match the garment's vertex count)."""
    frames = np.asarray(frames, dtype=np.float32)
    if frames.ndim != 3 or frames.shape[2] != 3:
        raise GarmentError(f"{source}: frames must have shape (T, V, 3), got {frames.shape}")
    if frames.shape[0] == 0:
        raise GarmentError(f"{source}: the sequence has no frames")
    if frames.shape[1] != garment.num_vertices:
        raise GarmentError(
            f"{source}: frames have {frames.shape[1]} vertices but the garment has "
            f"{garment.num_vertices}"
        )
    bad = ~np.isfinite(frames).all(axis=(1, 2))
    if bad.any():
        raise GarmentError(f"{source}: frame {int(np.flatnonzero(bad)[0])} has non-finite vertices")
    if not (np.isfinite(fps) and fps > 0):
        raise GarmentError(f"{source}: fps must be positive, got {fps}")
    return GarmentSequence(frames, garment, float(fps), dict(metadata or {}))


def _natural_key(name: str):
    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", name)]


def load_sequence(path: str | os.PathLike, fps: float = 30.0,
                  template: str | os.PathLike | Garment | None = None) -> GarmentSequence:
    """Load a sequence from an `.npz` bundle, a folder of per-frame OBJ files, a PC2 point
    cache (with a `template` OBJ giving topology and UVs, see `load_pc2`) or one OBJ file (a
    one-frame sequence).

    A folder's OBJs are ordered naturally (`f2.obj` before `f10.obj`) and must share topology
    (faces, UV faces) with the first; `fps` applies to folders, PC2 caches and OBJ files
    (`.npz` stores its own).

    Raises:
      GarmentError: naming the offending file (unreadable, missing keys, mismatched topology,
        non-finite vertices).
    """
    path = Path(path)
    if path.is_dir():
        files = sorted((p for p in path.iterdir() if p.suffix.lower() == ".obj"),
                       key=lambda p: _natural_key(p.name))
        if not files:
            raise GarmentError(f"{path}: no .obj frames in this folder")
        first = load_obj(files[0])
        frames = [np.asarray(first.vertices)]
        for p in files[1:]:
            g = load_obj(p)
            if g.num_vertices != first.num_vertices or not np.array_equal(g.faces, first.faces):
                raise GarmentError(
                    f"{p}: topology differs from the first frame {files[0].name} "
                    f"({g.num_vertices} vs {first.num_vertices} vertices)"
                )
            frames.append(np.asarray(g.vertices))
        return make_sequence(np.stack(frames), first, fps,
                             {"source": str(path), "files": [p.name for p in files]}, str(path))
    suffix = path.suffix.lower()
    if suffix == ".pc2":
        if template is None:
            raise GarmentError(f"{path}: a PC2 point cache needs a template OBJ with the "
                               f"topology and UVs")
        return load_pc2(path, template, fps, mmap=True)  # frames read on access
    if suffix == ".obj":
        g = load_obj(path)
        return make_sequence(np.asarray(g.vertices)[None], g, fps, {"source": str(path)},
                             str(path))
    if suffix != ".npz":
        raise GarmentError(f"{path}: expected a folder of OBJ frames, an .npz sequence, a .pc2 "
                           f"point cache or an .obj file")
    try:
        with np.load(path, allow_pickle=False) as z:
            data = {k: z[k] for k in z.files}
    except FileNotFoundError:
        raise GarmentError(f"{path}: no such file") from None
    except Exception as e:  # zipfile / format errors: report them as a bad file
        raise GarmentError(f"{path}: not a readable .npz sequence ({e})") from None
    missing = [k for k in ("frames", "faces", "uvs", "uv_faces") if k not in data]
    if missing:
        raise GarmentError(f"{path}: missing arrays {missing} in the sequence bundle")
    meta = {}
    if "metadata" in data:
        try:
            meta = json.loads(str(data["metadata"]))
        except json.JSONDecodeError:
            raise GarmentError(f"{path}: metadata is not valid JSON") from None
    frames = np.asarray(data["frames"], np.float32)
    if frames.ndim != 3 or frames.shape[0] == 0:
        raise GarmentError(f"{path}: frames must have shape (T, V, 3), got {frames.shape}")
    garment = make_garment(frames[0], data["faces"], data["uvs"], data["uv_faces"],
                           data.get("panels"), source=str(path))
    seq_fps = float(data["fps"]) if "fps" in data else fps
    return make_sequence(frames, garment, seq_fps, meta, str(path))


def save_sequence(path: str | os.PathLike, seq: GarmentSequence, **extra_arrays) -> None:
    """Write a sequence as an `.npz` bundle (atomically).

    Keys: frames (T,V,3) float32, faces, uvs, uv_faces, panels (if any), fps, metadata (JSON
    string), plus any `extra_arrays` (e.g. collider tracks).
    """
    path = Path(path)
    if path.suffix.lower() != ".npz":
        raise GarmentError(f"{path}: sequence bundles must end in .npz")
    g = seq.garment
    arrays = dict(
        frames=np.asarray(seq.frames, np.float32),
        faces=np.asarray(g.faces, np.int32),
        uvs=np.asarray(g.uvs, np.float32),
        uv_faces=np.asarray(g.uv_faces, np.int32),
        fps=np.float64(seq.fps),
        metadata=np.str_(json.dumps(seq.metadata)),
        **{k: np.asarray(v) for k, v in extra_arrays.items()},
    )
    if g.panels is not None:
        arrays["panels"] = np.asarray(g.panels, np.int32)
    buf = io.BytesIO()
    np.savez_compressed(buf, **arrays)
    atomic_write_bytes(path, buf.getvalue())


def save_obj_sequence(folder: str | os.PathLike, seq: GarmentSequence,
                      prefix: str = "frame_") -> list[Path]:
    """Write one OBJ per frame (`frame_00000.obj`, ...) into `folder`; returns the paths."""
    folder = Path(folder)
    if folder.exists() and not folder.is_dir():
        raise GarmentError(f"{folder}: exists and is not a folder")
    folder.mkdir(parents=True, exist_ok=True)
    digits = max(5, len(str(len(seq) - 1)))
    paths = []
    write = ObjWriter(seq.garment)
    for t in range(len(seq)):
        p = folder / f"{prefix}{t:0{digits}d}.obj"
        write(p, seq.frames[t])
        paths.append(p)
    return paths


# --------------------------------------------------------------------------------------------
# PC2 point caches (Blender, Maya, 3ds Max, Houdini) with a template OBJ
# --------------------------------------------------------------------------------------------

_PC2_SIGNATURE = b"POINTCACHE2\0"
# Little-endian header: signature, version, points, start frame, sample rate, samples.
_PC2_HEADER = np.dtype([("signature", "S12"), ("version", "<i4"), ("num_points", "<i4"),
                        ("start_frame", "<f4"), ("sample_rate", "<f4"),
                        ("num_samples", "<i4")])


@dataclasses.dataclass(frozen=True)
class PointCache:
    """A PC2 point cache: per-sample positions and the header's timing fields.

    Attributes:
      frames: (T, V, 3) float32 positions (a read-only memmap when read with ``mmap=True``).
      start_frame: frame number of the first sample.
      sample_rate: frames between samples (1.0: one sample per frame).
    """

    frames: np.ndarray
    start_frame: float = 0.0
    sample_rate: float = 1.0


def read_pc2(path: str | os.PathLike, mmap: bool = True) -> PointCache:
    """Read a PC2 point cache (12-byte "POINTCACHE2\\0" signature, int32 version 1, int32
    points, float32 start frame, float32 sample rate, int32 samples, then float32 xyz per point
    per sample, little-endian).

    Args:
      mmap: map the positions instead of reading them (frames are then read on access, so a
        long cache costs no memory until used).
    Raises:
      GarmentError: naming the file, if it is unreadable, not a PC2 file, or truncated.
    """
    path = Path(path)
    try:
        with open(path, "rb") as fh:
            raw = fh.read(_PC2_HEADER.itemsize)
        size = path.stat().st_size
    except OSError as e:
        raise GarmentError(f"{path}: cannot read PC2 file ({e.strerror})") from None
    if len(raw) < _PC2_HEADER.itemsize or not raw.startswith(_PC2_SIGNATURE):
        raise GarmentError(f"{path}: not a PC2 point cache (no POINTCACHE2 signature)")
    head = np.frombuffer(raw, _PC2_HEADER)[0]
    version, points, samples = int(head["version"]), int(head["num_points"]), \
        int(head["num_samples"])
    if version != 1:
        raise GarmentError(f"{path}: unsupported PC2 version {version} (expected 1)")
    if points <= 0 or samples <= 0:
        raise GarmentError(f"{path}: PC2 cache has {points} points and {samples} samples")
    need = _PC2_HEADER.itemsize + 12 * points * samples
    if size < need:
        raise GarmentError(f"{path}: truncated PC2 cache ({size} bytes, the header announces "
                           f"{samples} samples of {points} points = {need} bytes)")
    shape = (samples, points, 3)
    if mmap:
        frames = np.memmap(path, np.dtype("<f4"), "r", _PC2_HEADER.itemsize, shape)
    else:
        frames = np.fromfile(path, np.dtype("<f4"), samples * points * 3,
                             offset=_PC2_HEADER.itemsize).reshape(shape)
    return PointCache(frames, float(head["start_frame"]), float(head["sample_rate"]))


def save_pc2(path: str | os.PathLike, frames, start_frame: float = 0.0,
             sample_rate: float = 1.0) -> None:
    """Write (T, V, 3) positions as a PC2 point cache (atomically; float32 little-endian)."""
    f = np.asarray(frames, np.dtype("<f4"))
    if f.ndim != 3 or f.shape[2] != 3 or f.shape[0] == 0:
        raise GarmentError(f"{path}: PC2 frames must have shape (T, V, 3), got {f.shape}")
    head = np.array([(_PC2_SIGNATURE, 1, f.shape[1], start_frame, sample_rate, f.shape[0])],
                    _PC2_HEADER)
    atomic_write_bytes(path, head.tobytes() + np.ascontiguousarray(f).tobytes())


def load_pc2(path: str | os.PathLike, template: str | os.PathLike | Garment,
             fps: float = 30.0, mmap: bool = False) -> GarmentSequence:
    """A sequence from a PC2 point cache and a template OBJ (topology and UVs).

    The cache's points are the template's vertices, in order (how Blender and Maya export
    them). `fps` is the rate of the frames (PC2 stores none); with a sample rate s the
    sequence's fps is fps / s.

    Raises:
      GarmentError: naming the file: unreadable cache or template, a point count that differs
        from the template's vertex count, non-finite positions.
    """
    path = Path(path)
    garment = template if isinstance(template, Garment) else load_obj(template)
    cache = read_pc2(path, mmap=mmap)
    if cache.frames.shape[1] != garment.num_vertices:
        name = "the template" if isinstance(template, Garment) else Path(template).name
        raise GarmentError(f"{path}: the cache has {cache.frames.shape[1]} points but {name} "
                           f"has {garment.num_vertices} vertices (different topology)")
    rate = cache.sample_rate if cache.sample_rate > 0 else 1.0
    meta = {"source": str(path), "start_frame": cache.start_frame, "sample_rate": rate}
    return make_sequence(cache.frames, garment.replace(vertices=np.asarray(cache.frames[0],
                                                                           np.float32)),
                         fps / rate, meta, str(path))


# --------------------------------------------------------------------------------------------
# PLY (binary) and streamed sequence bundles
# --------------------------------------------------------------------------------------------


def save_ply(path: str | os.PathLike, vertices, faces) -> None:
    """Write a triangle mesh as binary little-endian PLY (float32 xyz, int32 faces; atomically).

    PLY keeps one attribute set per vertex, so the UV layout (per face corner, with seams) is
    not written; use OBJ for that.
    """
    v = np.asarray(vertices, np.dtype("<f4"))
    f = np.asarray(faces, np.int64)
    if v.ndim != 2 or v.shape[1] != 3 or f.ndim != 2 or f.shape[1] != 3:
        raise GarmentError(f"{path}: expected (V, 3) vertices and (F, 3) faces, got {v.shape} "
                           f"and {f.shape}")
    header = ("ply\nformat binary_little_endian 1.0\ncomment wrinkle-jax\n"
              f"element vertex {len(v)}\nproperty float x\nproperty float y\nproperty float z\n"
              f"element face {len(f)}\nproperty list uchar int vertex_indices\nend_header\n")
    rows = np.zeros(len(f), np.dtype([("n", "u1"), ("idx", "<i4", (3,))]))
    rows["n"] = 3
    rows["idx"] = f
    atomic_write_bytes(path, header.encode("ascii") + v.tobytes() + rows.tobytes())


class SequenceWriter:
    """Write a sequence bundle (`.npz`, readable by `load_sequence`) one frame at a time.

    Frames go to a temporary `.npy` memmap beside `path`; `close` packs it with the topology
    into the `.npz` (streamed, uncompressed, fixed zip timestamps: the same frames give the
    same bytes) and renames it into place, so memory stays one frame and no partial bundle is
    ever visible. Use as a context manager; an exception discards everything.
    """

    def __init__(self, path: str | os.PathLike, garment: Garment, num_frames: int,
                 fps: float = 30.0, metadata: dict | None = None):
        self.path = Path(path)
        if self.path.suffix.lower() != ".npz":
            raise GarmentError(f"{self.path}: sequence bundles must end in .npz")
        self.garment = garment
        self.num_frames = int(num_frames)
        self.fps = float(fps)
        self.metadata = dict(metadata or {})
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._tmp = self.path.with_name(f".{self.path.name}.frames.npy")
        self._frames = np.lib.format.open_memmap(
            self._tmp, "w+", np.float32, (self.num_frames, garment.num_vertices, 3))
        self._written = np.zeros(self.num_frames, bool)

    def write(self, t: int, vertices) -> None:
        """Store frame `t` (0 <= t < num_frames) of (V, 3) positions, meters."""
        self._frames[t] = np.asarray(vertices, np.float32)
        self._written[t] = True

    def close(self) -> Path:
        """Pack the bundle and rename it into place (every frame must have been written)."""
        import zipfile

        if not self._written.all():
            missing = int(np.flatnonzero(~self._written)[0])
            self.abort()
            raise GarmentError(f"{self.path}: frame {missing} was never written")
        self._frames.flush()
        g = self.garment
        arrays = dict(frames=self._frames, faces=np.asarray(g.faces, np.int32),
                      uvs=np.asarray(g.uvs, np.float32),
                      uv_faces=np.asarray(g.uv_faces, np.int32), fps=np.float64(self.fps),
                      metadata=np.str_(json.dumps(self.metadata)))
        if g.panels is not None:
            arrays["panels"] = np.asarray(g.panels, np.int32)
        tmp_zip = self.path.with_name(f".{self.path.name}.tmp")
        try:
            with zipfile.ZipFile(tmp_zip, "w", zipfile.ZIP_STORED, allowZip64=True) as zf:
                for name, arr in arrays.items():
                    info = zipfile.ZipInfo(f"{name}.npy", date_time=(1980, 1, 1, 0, 0, 0))
                    info.external_attr = 0o644 << 16
                    with zf.open(info, "w", force_zip64=True) as fh:
                        np.lib.format.write_array(fh, np.asanyarray(arr), allow_pickle=False)
            os.replace(tmp_zip, self.path)
        finally:
            if tmp_zip.exists():
                tmp_zip.unlink()
            self._release()
        return self.path

    def abort(self) -> None:
        """Discard the frames written so far (no bundle is created)."""
        self._release()

    def _release(self) -> None:
        self._frames = None
        if self._tmp.exists():
            self._tmp.unlink()

    def __enter__(self) -> SequenceWriter:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is not None:
            self.abort()
        elif self._frames is not None:
            self.close()
