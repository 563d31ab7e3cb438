"""Tests for the `wrinkle-jax` command: demo, bake, exit codes and error messages."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest

from wrinkle_jax import cli, meshio, normalmap, primitives


def test_demo_writes_normal_maps_and_report(tmp_path, capsys, monkeypatch):
    # Without a shipped model the demo bakes only, and says so.
    monkeypatch.setattr(cli, "_shipped_model_path", lambda: tmp_path / "no_model.npz")
    out = tmp_path / "demo"
    assert cli.main(["demo", "--out", str(out), "--texel-size", "0.006", "--json"]) == 0
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
    captured = capsys.readouterr()
    assert "bake_ms_per_frame" in captured.out
    assert "no shipped enhancer model" in captured.err and "only the bake" in report["note"]


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
        "normal_map_00001.png", "normal_map_00002.png", "report.json"]
    report = json.loads((tmp_path / "r" / "report.json").read_text())
    assert report["frame_indices"] == [1, 2] and report["outputs"][0] == "normal_map_00001.png"


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
    for argv in (["--help"], ["demo", "--help"], ["bake", "--help"], ["enhance", "--help"],
                 ["train-enhancer", "--help"]):
        with pytest.raises(SystemExit) as info:
            cli.main(argv)
        assert info.value.code == 0
    out = capsys.readouterr().out
    # train-enhancer's help lists the recipe's flags (wrinkle_jax.recipe) and the run options
    assert "--texel-size" in out and "--detail-sigma" in out and "--init-from" in out


# ---------------------------------------------------------------- enhance


def _tiny_model(path, model):
    """The session's tiny enhancer (conftest `model`) as a model file."""
    from wrinkle_jax import enhancer

    enhancer.save_enhancer(path, model.params, model.config, meta={"name": "tiny"})
    return path


@pytest.fixture(scope="module")
def inputs(tmp_path_factory, model):
    """A tiny 3-frame sheet as .npz, OBJ folder and PC2 + template, and a tiny model."""
    root = tmp_path_factory.mktemp("inputs")
    g = primitives.grid_sheet(6, 6, size=(0.16, 0.12))
    v = np.asarray(g.vertices)
    frames = np.stack([v + [0, 0, 0.01 * np.sin(t)] * np.sin(40 * v[:, :1]) for t in range(3)])
    seq = meshio.make_sequence(frames.astype(np.float32), g)
    meshio.save_sequence(root / "seq.npz", seq)
    meshio.save_obj_sequence(root / "objs", seq)
    meshio.save_obj(root / "template.obj", g)
    meshio.save_pc2(root / "seq.pc2", seq.frames)
    return {"root": root, "seq": seq, "model": _tiny_model(root / "model.npz", model)}


def _enhance(inputs, out, *extra, source="seq.npz"):
    return cli.main(["enhance", str(inputs["root"] / source), "--out", str(out), "--model",
                     str(inputs["model"]), "--batch", "4", "--no-previews", *extra])


def _files(folder):
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*"))
            if p.is_file()}


def test_enhance_writes_maps_meshes_npz_and_report(inputs, tmp_path, capsys):
    out = tmp_path / "out"
    assert _enhance(inputs, out, "--material", "wool_melton") == 0
    report = json.loads((out / "report.json").read_text())
    assert report["material"] == "wool_melton" and report["material_source"] == "flag"
    assert report["frames"] == 3 and report["lift"] is True
    assert report["patches"]["per_frame"] > 0 and report["patches"]["batch_size"] == 4
    for stage in ("bake", "tile", "network", "merge", "lift", "write", "compile"):
        assert report["timings_s"][stage] >= 0 and stage in report["timings_s"]
    assert report["ms_per_frame"]["network"] > 0
    files = _files(out)
    assert [k for k in files if k.startswith("normal_maps/")] == [
        f"normal_maps/normal_map_{t:05d}.png" for t in range(3)]
    assert [k for k in files if k.startswith("meshes/")] == [
        f"meshes/frame_{t:05d}.obj" for t in range(3)]
    detailed = meshio.load_sequence(out / "detailed.npz")
    assert detailed.frames.shape == (3, report["detailed_vertices"], 3)
    assert np.isfinite(detailed.frames).all()
    last = meshio.load_obj(out / "meshes" / "frame_00002.obj")
    np.testing.assert_allclose(last.vertices, detailed.frames[2], atol=1e-6)
    n, mask = normalmap.load_normal_map_png(out / "normal_maps" / "normal_map_00001.png")
    assert list(n.shape[:2]) == report["map_shape"] and mask.sum() == report["covered_texels"]
    # No temporary sibling folders are left behind.
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]
    captured = capsys.readouterr()
    assert captured.out == ""  # quiet: the JSON report is in the folder only
    assert "material wool_melton (flag)" in captured.err and len(captured.err.splitlines()) < 12

    # Running again (into the same folder) gives identical files; only timings differ.
    assert _enhance(inputs, out, "--material", "wool_melton") == 0
    again = _files(out)
    assert again.keys() == files.keys()
    for k in files:
        if k != "report.json":
            assert again[k] == files[k], k
    r2 = json.loads(again["report.json"])
    assert {k: v for k, v in r2.items() if k != "timings_s" and k != "ms_per_frame"} == {
        k: v for k, v in report.items() if k != "timings_s" and k != "ms_per_frame"}


def test_enhance_inputs_formats_and_options(inputs, tmp_path):
    # PC2 + template, PLY output, a frame range, no lift.
    out = tmp_path / "pc2"
    assert _enhance(inputs, out, "--material", "silk_chiffon", "--template",
                    str(inputs["root"] / "template.obj"), "--format", "ply", "--frames", "1:3",
                    source="seq.pc2") == 0
    import trimesh

    report = json.loads((out / "report.json").read_text())
    assert report["frame_indices"] == [1, 2]
    tm = trimesh.load(out / "meshes" / "frame_00002.ply", process=False)
    assert len(tm.vertices) == report["detailed_vertices"]
    assert np.isfinite(np.asarray(tm.vertices)).all()
    # An OBJ folder with --no-lift writes maps only; the same maps as from the .npz.
    out2 = tmp_path / "objs"
    assert _enhance(inputs, out2, "--material", "silk_chiffon", "--no-lift", "--frames", "1:3",
                    source="objs") == 0
    assert not (out2 / "meshes").exists() and not (out2 / "detailed.npz").exists()
    for t in (1, 2):
        name = f"normal_maps/normal_map_{t:05d}.png"
        a, _ = normalmap.load_normal_map_png(out / name)
        b, _ = normalmap.load_normal_map_png(out2 / name)
        np.testing.assert_allclose(a, b, atol=1e-4)  # OBJ text rounds the vertices


def _bad_cases(inputs, tmp_path):
    """(name, argv, expected exit code, message fragments) for every bad input."""
    root = inputs["root"]
    g = primitives.grid_sheet(6, 6, size=(0.16, 0.12))
    nouv = tmp_path / "nouv"
    nouv.mkdir()
    meshio.save_obj(nouv / "f0.obj", g)
    (nouv / "f1.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    seq = inputs["seq"]
    frames = np.array(seq.frames)
    frames[1, 3, 2] = np.nan
    nan = tmp_path / "nan.npz"
    np.savez(nan, frames=frames, faces=g.faces, uvs=g.uvs, uv_faces=g.uv_faces)
    topo = tmp_path / "topo"
    topo.mkdir()
    meshio.save_obj(topo / "f0.obj", g)
    meshio.save_obj(topo / "f1.obj", primitives.grid_sheet(5, 5))
    bad_model = tmp_path / "bad_model.npz"
    bad_model.write_bytes(b"PK\x03\x04 not an enhancer")
    a_file = tmp_path / "a_file"
    a_file.write_text("x")
    npz = str(root / "seq.npz")
    model = ["--model", str(inputs["model"])]
    return [
        ("missing UVs", [str(nouv), *model], 1, ["f1.obj", "UV"]),
        ("non-finite", [str(nan), *model], 1, ["nan.npz", "non-finite"]),
        ("topology", [str(topo), *model], 1, ["f1.obj", "topology"]),
        ("material", [npz, *model, "--material", "tweed"], 2, ["unknown material 'tweed'"]),
        ("checkpoint", [npz, "--model", str(bad_model)], 1, ["bad_model.npz", "enhancer"]),
        ("out is a file", [npz, *model], 1, ["a_file", "not a folder"]),
        ("pc2 without template", [str(root / "seq.pc2"), *model], 1, ["seq.pc2", "template"]),
        ("missing input", [str(tmp_path / "nope.npz"), *model], 1, ["nope.npz"]),
        ("open body", [npz, *model, "--body", str(root / "template.obj")], 1,
         ["template.obj", "closed"]),
    ]


def test_enhance_bad_inputs_exit_nonzero_and_leave_nothing(inputs, tmp_path, capsys):
    for name, argv, code, fragments in _bad_cases(inputs, tmp_path):
        out = tmp_path / ("a_file" if name == "out is a file" else "out")
        before = sorted(p.name for p in tmp_path.iterdir())
        argv = ["enhance", *argv, "--out", str(out), "--batch", "4", "--no-previews"]
        if "--material" not in argv:
            argv += ["--material", "wool_melton"]
        assert cli.main(argv) == code, name
        err = capsys.readouterr().err
        for fragment in fragments:
            assert fragment in err, (name, err)
        assert sorted(p.name for p in tmp_path.iterdir()) == before, name  # no partial output


def test_enhance_failure_midway_leaves_no_partial_output(inputs, tmp_path, monkeypatch, capsys):
    calls = []

    def failing_save(path, *args, **kwargs):
        calls.append(path)
        if len(calls) == 2:
            raise OSError(28, "No space left on device")
        return original(path, *args, **kwargs)

    original = normalmap.save_normal_map_png
    monkeypatch.setattr(normalmap, "save_normal_map_png", failing_save)
    assert _enhance(inputs, tmp_path / "out", "--material", "wool_melton") == 1
    assert "No space left" in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []


def test_enhance_auto_material_without_classifier_fails_clearly(inputs, tmp_path, monkeypatch,
                                                                capsys):
    from wrinkle_jax.classifier import calibrated, synthesis_model

    monkeypatch.setattr(calibrated, "MOTION_PATH", tmp_path / "no_classifier.npz")
    monkeypatch.setattr(synthesis_model, "SYNTHESIS_PATH", tmp_path / "no_synthesis.npz")
    assert _enhance(inputs, tmp_path / "out", "--material", "auto") == 2
    err = capsys.readouterr().err
    assert "no material classifier is available" in err and "--material NAME" in err
    assert list(tmp_path.iterdir()) == []


def test_demo_runs_the_pipeline_with_a_shipped_model(inputs, tmp_path, monkeypatch, capsys):
    from wrinkle_jax import classifier

    monkeypatch.setattr(cli, "_shipped_model_path", lambda: inputs["model"])
    # No classifier is needed: the material defaults to the one stored in the sequence.
    monkeypatch.setattr(classifier, "DEFAULT_PATH", tmp_path / "no_classifier.npz")
    out = tmp_path / "demo"
    assert cli.main(["demo", "--out", str(out), "--frames", "0:1", "--no-lift",
                     "--no-previews", "--batch", "4"]) == 0
    report = json.loads((out / "report.json").read_text())
    assert report["command"] == "demo" and report["frames"] == 1
    assert report["material"] == "silk_charmeuse"  # the demo sequence's own material
    assert report["material_source"] == "stored" and report["notes"] == []
    assert report["input"] == "wrinkle_jax/assets/demo_skirt.npz"  # no machine path
    assert report["model"]["path"] == str(inputs["model"])  # a user's path, as given
    assert (out / "normal_maps" / "normal_map_00000.png").exists()
    assert "silk_charmeuse (stored)" in capsys.readouterr().err


def test_use_fast_compile_adds_the_flag_only_when_it_can_and_may():
    env = {"XLA_FLAGS": "--xla_force_host_platform_device_count=2"}
    assert cli.use_fast_compile(env, backend_started=False)
    assert env["XLA_FLAGS"] == f"--xla_force_host_platform_device_count=2 {cli.FAST_COMPILE_FLAG}"
    assert not cli.use_fast_compile(env, backend_started=False)  # once
    env = {}
    assert cli.use_fast_compile(env, backend_started=False)
    assert env == {"XLA_FLAGS": cli.FAST_COMPILE_FLAG}
    for env in ({"XLA_FLAGS": "--xla_cpu_use_fusion_emitters=true"},  # the user's choice
                {"WRINKLE_JAX_XLA_DEFAULTS": "1"}):
        before = dict(env)
        assert not cli.use_fast_compile(env, backend_started=False) and env == before
    env = {}
    assert not cli.use_fast_compile(env, backend_started=True) and env == {}  # too late


def test_the_command_process_runs_with_the_flag(tmp_path):
    # `python -m wrinkle_jax.cli` is main() without arguments: a fresh process whose backend
    # has not started; --help exits before any compile.
    env = {k: v for k, v in os.environ.items() if k not in ("XLA_FLAGS",
                                                            "WRINKLE_JAX_XLA_DEFAULTS")}
    code = ("import os, sys\nfrom wrinkle_jax import cli\nsys.argv = ['wrinkle-jax', '--version']\n"
            "try:\n    cli.main()\nexcept SystemExit:\n    pass\n"
            "print(os.environ.get('XLA_FLAGS'))")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env,
                         cwd=tmp_path, timeout=120)
    assert res.returncode == 0, res.stderr[-2000:]
    assert res.stdout.strip().splitlines()[-1] == cli.FAST_COMPILE_FLAG
