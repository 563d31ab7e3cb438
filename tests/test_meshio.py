"""Tests for wrinkle_jax.meshio: OBJ and sequence round trips, clear errors, atomic writes."""

from __future__ import annotations

import json

import numpy as np
import pytest

from wrinkle_jax import meshio, primitives
from wrinkle_jax.mesh import GarmentError


def test_obj_round_trip_keeps_seams_and_panels(cube, tmp_path):
    p = tmp_path / "cube.obj"
    meshio.save_obj(p, cube)
    back = meshio.load_obj(p)
    np.testing.assert_allclose(back.vertices, cube.vertices, atol=1e-6)
    np.testing.assert_allclose(back.uvs, cube.uvs, atol=1e-6)
    np.testing.assert_array_equal(back.faces, cube.faces)
    np.testing.assert_array_equal(back.uv_faces, cube.uv_faces)
    np.testing.assert_array_equal(back.panels, cube.panels)
    # Seams survive: more UV vertices than 3D vertices, welded 3D stays closed.
    assert len(back.uvs) > back.num_vertices


def test_obj_round_trip_with_replacement_vertices(skirt, tmp_path):
    p = tmp_path / "frame.obj"
    moved = skirt.vertices + np.float32(0.25)
    meshio.save_obj(p, skirt, moved)
    np.testing.assert_allclose(meshio.load_obj(p).vertices, moved, atol=1e-6)
    with pytest.raises(GarmentError, match="does not match"):
        meshio.save_obj(p, skirt, moved[:-1])


def test_a_shape_error_is_raised_before_the_topology_is_formatted(skirt, tmp_path, monkeypatch):
    def never(*a, **k):
        raise AssertionError("formatted the topology for a write that fails its check")

    write = meshio.ObjWriter(skirt)  # formats nothing yet
    monkeypatch.setattr(meshio, "_format_rows", never)
    with pytest.raises(GarmentError, match="does not match"):
        write(tmp_path / "bad.obj", skirt.vertices[:-1])
    with pytest.raises(GarmentError, match="does not match"):
        meshio.save_obj(tmp_path / "bad.obj", skirt, skirt.vertices[:-1])
    assert not (tmp_path / "bad.obj").exists()


def test_obj_writer_formats_the_topology_once_and_writes_each_frame(cube, tmp_path):
    """One `ObjWriter` for many frames: each file round-trips to its frame with the garment's
    UVs, seams and panels, and the frames' files differ only in their `v` lines (the writer's
    topology text is reused, not re-derived from a frame)."""
    write = meshio.ObjWriter(cube)
    frames = [cube.vertices, cube.vertices * np.float32(1.5) + np.float32(0.1)]
    for t, v in enumerate(frames):
        write(tmp_path / f"f{t}.obj", v)
        back = meshio.load_obj(tmp_path / f"f{t}.obj")
        np.testing.assert_allclose(back.vertices, v, atol=1e-6)
        np.testing.assert_array_equal(back.faces, cube.faces)
        np.testing.assert_array_equal(back.uv_faces, cube.uv_faces)
        np.testing.assert_array_equal(back.panels, cube.panels)
    lines = [(tmp_path / f"f{t}.obj").read_text().splitlines() for t in (0, 1)]
    differ = [a for a, b in zip(*lines, strict=True) if a != b]
    assert differ and all(a.startswith("v ") for a in differ)
    assert (tmp_path / "f0.obj").read_bytes() == _saved(tmp_path / "s.obj", cube, frames[0])
    with pytest.raises(GarmentError, match="does not match"):
        write(tmp_path / "bad.obj", frames[0][:-1])


def _saved(path, garment, vertices) -> bytes:
    meshio.save_obj(path, garment, vertices)
    return path.read_bytes()


def test_obj_parser_polygons_negative_indices_and_normals(tmp_path):
    p = tmp_path / "quad.obj"
    p.write_text(
        "# a quad with normals and relative indices\n"
        "o sheet\n"
        "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\n"
        "vt 0 0\nvt 1 0\nvt 1 1\nvt 0 1\n"
        "vn 0 0 1\n"
        "f -4/-4/1 -3/-3/1 -2/-2/1 -1/-1/1\n"
    )
    g = meshio.load_obj(p)
    np.testing.assert_array_equal(g.faces, [[0, 1, 2], [0, 2, 3]])
    np.testing.assert_array_equal(g.uv_faces, [[0, 1, 2], [0, 2, 3]])
    np.testing.assert_array_equal(g.panels, [0, 0])


@pytest.mark.parametrize(
    "text, message",
    [
        ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n", "without UV"),
        ("v 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\nf 1/1 2/1 3/1\nf 1 2 3\n", "line 6"),
        ("v 0 0 0\nv 1 0 nan\nv 0 1 0\nvt 0 0\nf 1/1 2/1 3/1\n", "non-finite vertex"),
        ("v 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\nf 1/1 2/1 9/1\n",
         r"obj:5: vertex index 9 is out of range \(the file has 3 vertices: indices 1 to 3\)"),
        ("v 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\nf 1/1 2/1 3/2\n", "obj:5: UV index 2 is out"),
        ("v 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\nf 0/1 1/1 2/1\n", "obj:5: vertex index 0 is inv"),
        ("v 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\nf -4/1 1/1 2/1\n", "obj:5: relative vertex"),
        ("v 0 0\n", "obj:1: malformed .v. line"),
        ("v 0 0 0\n", "no faces"),
    ],
)
def test_obj_errors_name_file_and_problem(tmp_path, text, message):
    p = tmp_path / "bad.obj"
    p.write_text(text)
    with pytest.raises(GarmentError, match=message) as info:
        meshio.load_obj(p)
    assert "bad.obj" in str(info.value)


def test_missing_obj_file(tmp_path):
    with pytest.raises(GarmentError, match="cannot read"):
        meshio.load_obj(tmp_path / "nope.obj")


def _sequence(garment, t=5, seed=0):
    rng = np.random.default_rng(seed)
    frames = garment.vertices[None] + 0.01 * rng.normal(size=(t, garment.num_vertices, 3))
    return meshio.make_sequence(frames, garment, fps=24.0, metadata={"material": "denim_light"})


def test_npz_sequence_round_trip(skirt, tmp_path):
    seq = _sequence(skirt)
    p = tmp_path / "seq.npz"
    meshio.save_sequence(p, seq, balls=np.zeros((5, 2, 3), np.float32))
    back = meshio.load_sequence(p)
    np.testing.assert_array_equal(back.frames, seq.frames)
    np.testing.assert_array_equal(back.garment.uv_faces, skirt.uv_faces)
    np.testing.assert_array_equal(back.garment.panels, skirt.panels)
    assert back.fps == 24.0 and back.metadata == {"material": "denim_light"}
    assert len(back) == 5
    with np.load(p) as z:
        assert z["balls"].shape == (5, 2, 3)
        json.loads(str(z["metadata"]))


def test_obj_folder_sequence_round_trip_natural_order(sheet, tmp_path):
    seq = _sequence(sheet, t=12)
    paths = meshio.save_obj_sequence(tmp_path / "frames", seq, prefix="f")
    # Rename to unpadded numbers: natural sort must still order f2 before f10.
    for i, p in enumerate(paths):
        p.rename(p.with_name(f"f{i}.obj"))
    back = meshio.load_sequence(tmp_path / "frames", fps=12)
    np.testing.assert_allclose(back.frames, seq.frames, atol=1e-6)
    assert back.fps == 12


def test_folder_sequence_rejects_mismatched_topology(sheet, tmp_path):
    d = tmp_path / "frames"
    d.mkdir()
    meshio.save_obj(d / "a0.obj", sheet)
    meshio.save_obj(d / "a1.obj", primitives.grid_sheet(4, 4))
    with pytest.raises(GarmentError, match="a1.obj: topology differs"):
        meshio.load_sequence(d)


def test_sequence_errors(sheet, tmp_path):
    with pytest.raises(GarmentError, match="vertices but the garment has"):
        meshio.make_sequence(np.zeros((2, 3, 3)), sheet)
    frames = np.repeat(sheet.vertices[None], 3, 0)
    frames[2, 1, 0] = np.inf
    with pytest.raises(GarmentError, match="frame 2 has non-finite"):
        meshio.make_sequence(frames, sheet)
    bad = tmp_path / "corrupt.npz"
    bad.write_bytes(b"PK\x03\x04 definitely not a zip")
    with pytest.raises(GarmentError, match="corrupt.npz: not a readable"):
        meshio.load_sequence(bad)
    partial = tmp_path / "partial.npz"
    np.savez(partial, frames=frames[:1])
    with pytest.raises(GarmentError, match="missing arrays"):
        meshio.load_sequence(partial)
    with pytest.raises(GarmentError, match="no .obj frames"):
        meshio.load_sequence(tmp_path)
    with pytest.raises(GarmentError, match="must end in .npz"):
        meshio.save_sequence(tmp_path / "x.bin", _sequence(sheet))


def test_writes_are_atomic(sheet, tmp_path, monkeypatch):
    p = tmp_path / "out.obj"
    meshio.save_obj(p, sheet)
    before = p.read_bytes()

    def boom(*args, **kwargs):
        raise RuntimeError("disk full")

    monkeypatch.setattr("os.replace", boom)
    with pytest.raises(RuntimeError):
        meshio.save_obj(p, sheet, sheet.vertices * 2)
    assert p.read_bytes() == before  # old file intact
    assert sorted(x.name for x in tmp_path.iterdir()) == ["out.obj"]  # no temp left behind


# ---------------------------------------------------------------- PC2, PLY, streamed bundles


def _moving(sheet, count=3):
    return np.stack([np.asarray(sheet.vertices) + 0.01 * t for t in range(count)]).astype(
        np.float32)


def test_pc2_round_trip_and_header(sheet, tmp_path):
    import struct

    frames = _moving(sheet)
    p = tmp_path / "anim.pc2"
    meshio.save_pc2(p, frames, start_frame=5.0, sample_rate=0.5)
    raw = p.read_bytes()
    assert raw[:12] == b"POINTCACHE2\0"
    assert struct.unpack("<iiffi", raw[12:32]) == (1, sheet.num_vertices, 5.0, 0.5, 3)
    assert len(raw) == 32 + frames.size * 4
    for mmap in (True, False):
        cache = meshio.read_pc2(p, mmap=mmap)
        np.testing.assert_array_equal(cache.frames, frames)
        assert (cache.start_frame, cache.sample_rate) == (5.0, 0.5)
    meshio.save_obj(tmp_path / "template.obj", sheet)
    seq = meshio.load_sequence(p, fps=24, template=tmp_path / "template.obj")
    np.testing.assert_array_equal(seq.frames, frames)
    np.testing.assert_array_equal(seq.garment.uv_faces, sheet.uv_faces)
    assert seq.fps == 48.0  # a sample every half frame


def test_pc2_errors_name_the_file(sheet, tmp_path):
    p = tmp_path / "anim.pc2"
    meshio.save_pc2(p, _moving(sheet))
    with pytest.raises(GarmentError, match="needs a template"):
        meshio.load_sequence(p)
    with pytest.raises(GarmentError, match="anim.pc2: the cache has .* points but"):
        meshio.load_pc2(p, primitives.grid_sheet(3, 3))
    p.write_bytes(p.read_bytes()[:-4])
    with pytest.raises(GarmentError, match="anim.pc2: truncated"):
        meshio.read_pc2(p)
    (tmp_path / "x.pc2").write_bytes(b"not a cache at all, really not" * 2)
    with pytest.raises(GarmentError, match="x.pc2: not a PC2"):
        meshio.read_pc2(tmp_path / "x.pc2")
    frames = _moving(sheet)
    frames[1, 0, 0] = np.nan
    meshio.save_pc2(tmp_path / "nan.pc2", frames)
    with pytest.raises(GarmentError, match="frame 1 has non-finite"):
        meshio.load_pc2(tmp_path / "nan.pc2", sheet)


def test_ply_is_readable_by_trimesh(sheet, tmp_path):
    import trimesh

    p = tmp_path / "m.ply"
    meshio.save_ply(p, sheet.vertices, sheet.faces)
    tm = trimesh.load(p, process=False)
    np.testing.assert_array_equal(np.asarray(tm.vertices, np.float32), sheet.vertices)
    np.testing.assert_array_equal(np.asarray(tm.faces), sheet.faces)
    with pytest.raises(GarmentError, match="expected"):
        meshio.save_ply(p, sheet.vertices[:, :2], sheet.faces)


def test_single_obj_is_a_one_frame_sequence(sheet, tmp_path):
    meshio.save_obj(tmp_path / "a.obj", sheet)
    seq = meshio.load_sequence(tmp_path / "a.obj")
    assert seq.frames.shape == (1, sheet.num_vertices, 3)


def test_sequence_writer_streams_a_loadable_deterministic_bundle(sheet, tmp_path):
    frames = _moving(sheet, 4)
    paths = []
    for name in ("a.npz", "b.npz"):
        with meshio.SequenceWriter(tmp_path / name, sheet, 4, fps=12, metadata={"k": 1}) as w:
            for t in (2, 0, 3, 1):  # any order
                w.write(t, frames[t])
        paths.append(tmp_path / name)
    back = meshio.load_sequence(paths[0])
    np.testing.assert_array_equal(back.frames, frames)
    assert back.fps == 12 and back.metadata == {"k": 1}
    assert paths[0].read_bytes() == paths[1].read_bytes()  # fixed zip timestamps
    # A failure inside the block, or a missing frame, leaves no bundle and no temporary file.
    with pytest.raises(RuntimeError):
        with meshio.SequenceWriter(tmp_path / "c.npz", sheet, 2) as w:
            w.write(0, frames[0])
            raise RuntimeError("boom")
    w = meshio.SequenceWriter(tmp_path / "d.npz", sheet, 2)
    w.write(0, frames[0])
    with pytest.raises(GarmentError, match="frame 1 was never written"):
        w.close()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.npz", "b.npz"]
