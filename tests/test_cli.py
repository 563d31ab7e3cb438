"""Tests for the `wrinkle-jax` command: demo, bake, exit codes and error messages."""

from __future__ import annotations

import json

import numpy as np
import pytest

from wrinkle_jax import cli, meshio, normalmap, primitives


def test_demo_writes_normal_maps_and_report(tmp_path, capsys):
    out = tmp_path / "demo"
    assert cli.main(["demo", "--out", str(out), "--texel-size", "0.006"]) == 0
    report = json.loads((out / "report.json").read_text())
    assert report["frames"] == 12 and len(report["outputs"]) == 12
    assert report["timings"]["bake_ms_per_frame"] > 0
    n, mask = normalmap.load_normal_map_png(out / "normal_map_00000.png")
    assert list(n.shape[:2]) == report["map_shape"]
    assert mask.sum() == report["covered_texels"] > 0
    m = mask[..., 0] > 0
    np.testing.assert_allclose(np.linalg.norm(n[m], axis=-1), 1.0, atol=1e-4)
    # Frames differ (the skirt moves).
    n5, _ = normalmap.load_normal_map_png(out / "normal_map_00005.png")
    assert np.abs(n5 - n)[m].max() > 0.05
    assert "bake_ms_per_frame" in capsys.readouterr().out


def test_bake_obj_and_frame_range(tmp_path):
    g = primitives.grid_sheet(6, 6, size=(0.2, 0.2))
    meshio.save_obj(tmp_path / "sheet.obj", g)
    assert cli.main(["bake", str(tmp_path / "sheet.obj"), "--out", str(tmp_path / "o")]) == 0
    assert (tmp_path / "o" / "normal_map_00000.png").exists()
    seq = meshio.make_sequence(np.repeat(g.vertices[None], 5, 0), g)
    meshio.save_sequence(tmp_path / "s.npz", seq)
    assert cli.main(["bake", str(tmp_path / "s.npz"), "--out", str(tmp_path / "r"),
                     "--frames", "1:3", "--batch", "4"]) == 0
    assert sorted(p.name for p in (tmp_path / "r").iterdir()) == [
        "normal_map_00001.png", "normal_map_00002.png"]


def test_bad_inputs_exit_nonzero_with_a_message(tmp_path, capsys):
    bad = tmp_path / "nouv.obj"
    bad.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    assert cli.main(["bake", str(bad), "--out", str(tmp_path / "o")]) == 1
    err = capsys.readouterr().err
    assert "nouv.obj" in err and "UV" in err
    assert not (tmp_path / "o").exists()  # no partial output

    g = primitives.grid_sheet(2, 2)
    meshio.save_obj(tmp_path / "ok.obj", g)
    (tmp_path / "file").write_text("x")
    assert cli.main(["bake", str(tmp_path / "ok.obj"), "--out", str(tmp_path / "file")]) == 1
    assert "not a folder" in capsys.readouterr().err

    with pytest.raises(SystemExit) as info:
        cli.main(["bake"])
    assert info.value.code == 2
    with pytest.raises(SystemExit) as info:
        cli.main(["frobnicate"])
    assert info.value.code == 2


def test_help_on_every_command(capsys):
    for argv in (["--help"], ["demo", "--help"], ["bake", "--help"]):
        with pytest.raises(SystemExit) as info:
            cli.main(argv)
        assert info.value.code == 0
    assert "--texel-size" in capsys.readouterr().out
