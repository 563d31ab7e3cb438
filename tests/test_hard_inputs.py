"""Hard inputs for the `wrinkle-jax` command: every one gets a one-line error (or a correct
result), the documented exit code, no traceback and no partial, empty or hidden output.

Each case runs `cli.main` in-process on a tiny sheet (16 x 12 cm, 72 faces) with a tiny random
enhancer (width 4, 32-texel patches, 4 mm texels), except the signal cases, which need a
subprocess. Failing cases must fail within 10 s, before any compile.
"""

from __future__ import annotations

import dataclasses
import json
import os
import signal
import stat
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from wrinkle_jax import cli, meshio, normalmap, outdir, primitives, validate

ROOT = Path(__file__).resolve().parents[1]
DEMO = ROOT / "wrinkle_jax" / "assets" / "demo_skirt.npz"
FAIL_WITHIN_S = 10.0


def _sheet(n: int = 6):
    return primitives.grid_sheet(n, n, size=(0.16, 0.12))


def _frames(g, count: int = 3) -> np.ndarray:
    v = np.asarray(g.vertices)
    return np.stack([v + [0, 0, 0.01 * np.sin(t)] * np.sin(40 * v[:, :1])
                     for t in range(count)]).astype(np.float32)


def _save_npz(path, g, frames=None, material="wool_melton", scale=1.0, **arrays):
    """A sequence bundle of `g` (frames scaled by `scale`, e.g. 1000 for millimetres)."""
    frames = _frames(g) if frames is None else frames
    meta = {"material": material} if material else {}
    data = dict(frames=frames * np.float32(scale), faces=g.faces, uvs=g.uvs,
                uv_faces=g.uv_faces, metadata=np.str_(json.dumps(meta)))
    data.update(arrays)
    np.savez(path, **{k: v for k, v in data.items() if v is not None})
    return path


@pytest.fixture(scope="module")
def root(tmp_path_factory, model):
    from wrinkle_jax import enhancer

    root = tmp_path_factory.mktemp("hard")
    g = _sheet()
    _save_npz(root / "seq.npz", g)
    # Long enough that a signal sent once the output folder exists arrives mid-run: the
    # 3-frame sequence could finish first (seen once on a fresh clone, exit 0 instead of 143).
    _save_npz(root / "long.npz", g, frames=_frames(g, 600))
    # The session's tiny enhancer (conftest `model`: width 4, 32-texel patches, 4 mm texels).
    enhancer.save_enhancer(root / "model.npz", model.params, model.config, meta={"name": "tiny"})
    meshio.save_obj(root / "sheet.obj", g)
    return root


def _run(root, work, argv, *, source="seq.npz", command="enhance"):
    """`cli.main` on `work`/out; returns (exit code, stdout, stderr, seconds)."""
    args = [command, *([str(root / source)] if source else []), "--out", str(work / "out")]
    if command == "enhance":
        args += ["--model", str(root / "model.npz"), "--batch", "4", "--no-previews",
                 "--no-lift"]
    t0 = time.perf_counter()
    try:
        code = cli.main(args + list(argv))
    except SystemExit as e:  # argparse usage errors
        code = e.code
    return code, time.perf_counter() - t0


def _assert_failed_cleanly(capsys, work, code, expected_code, fragments, seconds,
                           before=None):
    captured = capsys.readouterr()
    assert code == expected_code, captured.err
    err = captured.err.strip()
    assert "Traceback" not in captured.err
    assert len(err.splitlines()) == 1, err  # one line
    assert err.startswith(("wrinkle-jax enhance: error: ", "wrinkle-jax bake: error: ")), err
    for fragment in fragments:
        assert fragment in err, (fragment, err)
    # Nothing new next to the output: no partial, empty or hidden temporary folder.
    assert sorted(p.name for p in work.iterdir()) == (before or []), list(work.iterdir())
    assert seconds < FAIL_WITHIN_S


# ------------------------------------------------------------------ inputs that fail cleanly


def _obj(text):
    def make(d):
        (d / "bad.obj").write_text(text)
        return "bad.obj"
    return make


QUAD = "v 0 0 0\nv 0.2 0 0\nv 0.2 0.2 0\nv 0 0.2 0\nvt 0 0\nvt 1 0\nvt 1 1\nvt 0 1\n"


def _npz_case(**kw):
    def make(d):
        g = kw.pop("garment", None) or _sheet()
        _save_npz(d / "in.npz", g, **kw)
        return "in.npz"
    return make


def _nan(d):
    f = _frames(_sheet())
    f[1, 3, 2] = np.nan
    return _npz_case(frames=f)(d)


def _inf(d):
    f = _frames(_sheet())
    f[2, 0, 0] = np.inf
    return _npz_case(frames=f)(d)


def _topology(d):
    (d / "objs").mkdir()
    meshio.save_obj(d / "objs" / "f0.obj", _sheet())
    meshio.save_obj(d / "objs" / "f1.obj", _sheet(5))
    return "objs"


def _missing_keys(d):
    g = _sheet()
    np.savez(d / "in.npz", frames=_frames(g), faces=g.faces)
    return "in.npz"


def _random_bytes(d):
    (d / "in.npz").write_bytes(np.random.default_rng(0).bytes(300))
    return "in.npz"


def _degenerate(fraction_faces: int):
    """The sheet with its first `fraction_faces` faces collapsed to zero area (one vertex
    repeated), UVs untouched."""
    def make(d):
        g = _sheet()
        f = np.array(g.faces)
        f[:fraction_faces, 2] = f[:fraction_faces, 1]
        uf = np.array(g.uv_faces)
        g2 = g.replace(faces=f, uv_faces=uf)
        _save_npz(d / "in.npz", g2)
        return "in.npz"
    return make


def _one_point(d):
    g = _sheet()
    f = np.zeros_like(_frames(g)) + 0.5
    return _npz_case(frames=f)(d)


def _flat_uvs(d):
    g = _sheet()
    g2 = g.replace(uvs=np.zeros_like(np.asarray(g.uvs)))
    _save_npz(d / "in.npz", g2)
    return "in.npz"


def _pc2_mismatch(d):
    meshio.save_pc2(d / "in.pc2", _frames(_sheet(5)))
    meshio.save_obj(d / "t.obj", _sheet())
    return "in.pc2"


def _empty_folder(d):
    (d / "objs").mkdir()
    return "objs"


# (id, make input in a folder -> its name, extra argv, exit code, message fragments)
FAILING = [
    ("no UVs", _obj("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n"), [], 1,
     ["bad.obj", "without UV coordinates"]),
    ("empty OBJ", _obj(""), [], 1, ["bad.obj", "no faces"]),
    ("random text OBJ", _obj("v nonsense here\n"), [], 1, ["bad.obj:1", "malformed 'v'"]),
    ("random bytes npz", _random_bytes, [], 1, ["in.npz", "not a readable .npz"]),
    ("NaN vertex", _nan, [], 1, ["in.npz", "frame 1 has non-finite vertices"]),
    ("inf vertex", _inf, [], 1, ["in.npz", "frame 2 has non-finite vertices"]),
    ("face index out of range", _obj(QUAD + "f 1/1 2/2 9/3\n"), [], 1,
     ["bad.obj:9", "vertex index 9 is out of range", "indices 1 to 4"]),
    ("UV index out of range", _obj(QUAD + "f 1/1 2/2 3/7\n"), [], 1,
     ["bad.obj:9", "UV index 7 is out of range"]),
    ("face index 0", _obj(QUAD + "f 0/1 1/2 2/3\n"), [], 1,
     ["bad.obj:9", "vertex index 0 is invalid", "start at 1"]),
    ("mismatched frame topology", _topology, [], 1, ["f1.obj", "topology differs"]),
    ("missing npz keys", _missing_keys, [], 1, ["in.npz", "missing arrays", "uvs"]),
    ("folder without OBJ", _empty_folder, [], 1, ["objs", "no .obj frames"]),
    ("PC2 without template", lambda d: (meshio.save_pc2(d / "in.pc2", _frames(_sheet())),
                                        "in.pc2")[1], [], 1, ["in.pc2", "template"]),
    ("PC2 point count", _pc2_mismatch, ["--template", "{d}/t.obj"], 1,
     ["in.pc2", "the cache has 36 points but t.obj has 49 vertices"]),
    ("millimetres", _npz_case(scale=1000.0), [], 1,
     ["in.npz", "200 units across", "centimetres (--units cm) or millimetres (--units mm)"]),
    ("centimetres", _npz_case(scale=100.0), [], 1,
     ["in.npz", "20 units across", "probably in centimetres (--units cm)"]),
    ("x0.1", _npz_case(scale=0.1), [], 1, ["in.npz", "0.02 units across", "too small",
                                           "--scale 100"]),
    ("x0.001", _npz_case(scale=0.001), [], 1, ["in.npz", "too small", "--scale 10000"]),
    ("x30", _npz_case(scale=30.0), [], 1, ["in.npz", "6 units across", "too large",
                                           "--scale 0.1"]),
    # The bundled skirt (1.1 m across) as a user would scale it by mistake; the old code spent
    # minutes and gigabytes in set-up on x10 and crashed or silently made a tiny map on x0.001.
    ("skirt x10", lambda d: str(DEMO), ["--scale", "10"], 1,
     ["demo_skirt.npz (scaled by 10)", "11.06 units across", "too large",
      "centimetres (--units cm)"]),
    ("skirt x0.001", lambda d: str(DEMO), ["--scale", "0.001"], 1,
     ["demo_skirt.npz", "0.001106 units across", "too small", "--scale 1000"]),
    ("map over budget", None, ["--texel-size", "0.00002"], 1,
     ["seq.npz", "M texels", "larger --texel-size"]),
    ("zero-area faces", _degenerate(10), ["--material", "wool_melton"], 1,
     ["in.npz", "10 of 72 zero-area or sliver faces", "first: face 1", "degenerate"]),
    ("all vertices on one point", _one_point, [], 1, ["in.npz", "zero 3D area"]),
    ("zero-area UV layout", _flat_uvs, [], 1, ["in.npz", "UV layout has zero area"]),
    ("unknown material", None, ["--material", "tweed"], 2,
     ["unknown material 'tweed'", "silk_charmeuse"]),
    ("no stored material", _npz_case(material=None), [], 2,
     ["in.npz stores no material", "--material NAME", "denim_light"]),
    ("auto without classifier", None, ["--material", "auto"], 2,
     ["no material classifier is available", "--material NAME"]),
    ("frames past the end", None, ["--frames", "2:40"], 2,
     ["wrinkle-jax enhance: error: --frames 2:40", "stop 40 is outside the 3-frame"]),
    ("frames start past the end", None, ["--frames", "5:"], 2, ["start 5 is outside"]),
    ("frames reversed", None, ["--frames", "2:1"], 2, ["selects no frame of the 3-frame"]),
    ("frames negative outside", None, ["--frames=-4:"], 2, ["start -4 is outside"]),
    ("frames malformed", None, ["--frames", "a:b"], 2, ["--frames must look like A:B"]),
    ("frames step 0", None, ["--frames", "0:2:0"], 2, ["step must not be 0"]),
    ("single frame outside", None, ["--frames", "3"], 2, ["frame 3 is outside"]),
    ("stride 0", None, ["--stride", "0"], 2, ["--stride must be >= 1, got 0"]),
    ("batch 0", None, ["--batch", "0"], 2, ["--batch must be >= 1"]),
    ("units and scale", None, ["--units", "mm", "--scale", "2"], 2, ["not both"]),
    ("negative scale", None, ["--scale", "-1"], 2, ["--scale must be a positive number"]),
    ("texel size 0", None, ["--texel-size", "0"], 2, ["--texel-size must be positive"]),
    ("missing input", lambda d: "nope.npz", [], 1, ["nope.npz", "no such file"]),
    ("corrupt model", None, ["--model", "{d}/bad_model.npz"], 1, ["bad_model.npz"]),
    ("open body", None, ["--body", "{root}/sheet.obj"], 1, ["sheet.obj", "closed"]),
]


@pytest.mark.parametrize("name, make, argv, code, fragments", FAILING,
                         ids=[c[0] for c in FAILING])
def test_bad_input_fails_with_one_line_and_no_output(root, tmp_path, capsys, monkeypatch, name,
                                                     make, argv, code, fragments):
    from wrinkle_jax.classifier import calibrated, synthesis_model

    monkeypatch.setattr(calibrated, "MOTION_PATH", tmp_path / "no_classifier.npz")
    monkeypatch.setattr(synthesis_model, "SYNTHESIS_PATH", tmp_path / "no_synthesis.npz")
    inputs = tmp_path / "inputs"
    inputs.mkdir()
    (inputs / "bad_model.npz").write_bytes(b"PK\x03\x04 not an enhancer")
    work = tmp_path / "work"
    work.mkdir()
    source = "seq.npz" if make is None else str(inputs / make(inputs))
    argv = [a.format(d=inputs, root=root) for a in argv]
    result, seconds = _run(root, work, argv, source=source)
    _assert_failed_cleanly(capsys, work, result, code, fragments, seconds)


def test_bake_refuses_millimetres_too(root, tmp_path, capsys):
    _save_npz(tmp_path / "mm.npz", _sheet(), scale=1000.0)
    work = tmp_path / "work"
    work.mkdir()
    code, seconds = _run(root, work, [], source=str(tmp_path / "mm.npz"), command="bake")
    _assert_failed_cleanly(capsys, work, code, 1, ["wrinkle-jax bake: error:", "--units mm"],
                           seconds)


# ------------------------------------------------------------------ output folders


def test_output_path_is_a_file(root, tmp_path, capsys):
    (tmp_path / "out").write_text("mine")
    code, seconds = _run(root, tmp_path, [])
    _assert_failed_cleanly(capsys, tmp_path, code, 1, ["out: output path exists and is not a "
                                                       "folder"], seconds, before=["out"])
    assert (tmp_path / "out").read_text() == "mine"


def test_folder_with_user_files_is_refused_then_replaced_with_force(root, tmp_path, capsys):
    out = tmp_path / "out"
    assert _run(root, tmp_path, [])[0] == 0
    capsys.readouterr()
    (out / "notes.txt").write_text("my notes")
    (out / "renders").mkdir()
    (out / "renders" / "a.png").write_bytes(b"png")
    listing = sorted(str(p.relative_to(out)) for p in out.rglob("*"))
    code, seconds = _run(root, tmp_path, [])
    _assert_failed_cleanly(capsys, tmp_path, code, 1,
                           ["holds files wrinkle-jax did not write (notes.txt, renders/)",
                            "--force"], seconds, before=["out"])
    assert sorted(str(p.relative_to(out)) for p in out.rglob("*")) == listing  # untouched
    assert (out / "notes.txt").read_text() == "my notes"
    assert _run(root, tmp_path, ["--force"])[0] == 0
    assert not (out / "notes.txt").exists() and (out / "report.json").is_file()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]


def test_rerun_keeps_the_folder_permissions_and_a_new_folder_is_not_0700(root, tmp_path):
    out = tmp_path / "out"
    assert _run(root, tmp_path, [])[0] == 0
    assert stat.S_IMODE(out.stat().st_mode) == 0o777 & ~outdir._UMASK
    os.chmod(out, 0o751)
    assert _run(root, tmp_path, [])[0] == 0
    assert stat.S_IMODE(out.stat().st_mode) == 0o751
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]


def test_unwritable_target_fails_cleanly(root, tmp_path, capsys, monkeypatch):
    # Tests may run as root, for whom chmod 0o555 does not stop writes: fail the mkdtemp.
    def denied(*args, **kwargs):
        raise PermissionError(13, "Permission denied")

    monkeypatch.setattr(outdir.tempfile, "mkdtemp", denied)
    work = tmp_path / "ro"
    work.mkdir()
    code, seconds = _run(root, work, [])
    _assert_failed_cleanly(capsys, work, code, 1, ["cannot create the output folder",
                                                   "Permission denied"], seconds)


def test_disk_full_midway_leaves_nothing_not_even_new_parent_folders(root, tmp_path, capsys,
                                                                    monkeypatch):
    original = normalmap.save_normal_map_png
    calls = []

    def failing(path, *args, **kwargs):
        calls.append(path)
        if len(calls) == 2:
            raise OSError(28, "No space left on device")
        return original(path, *args, **kwargs)

    monkeypatch.setattr(normalmap, "save_normal_map_png", failing)
    args = ["enhance", str(root / "seq.npz"), "--out", str(tmp_path / "a" / "b" / "out"),
            "--model", str(root / "model.npz"), "--batch", "4", "--no-previews", "--no-lift"]
    assert cli.main(args) == 1
    err = capsys.readouterr().err
    assert "No space left" in err and "Traceback" not in err
    assert list(tmp_path.iterdir()) == []  # neither out nor the parents a/ and a/b/


@pytest.mark.parametrize("sig, code, word", [(signal.SIGTERM, 143, "terminated"),
                                             (signal.SIGINT, 130, "interrupted")])
def test_signal_removes_the_temporary_folder(root, tmp_path, sig, code, word):
    env = {**os.environ, "PYTHONPATH": str(ROOT), "JAX_PLATFORMS": "cpu"}
    # A shell's background job may inherit SIGINT as ignored (Python then keeps ignoring it):
    # install Python's usual Ctrl-C handler before running the command.
    run = ("import signal, sys; signal.signal(signal.SIGINT, signal.default_int_handler); "
           "from wrinkle_jax.cli import main; sys.exit(main(sys.argv[1:]))")
    proc = subprocess.Popen(
        [sys.executable, "-c", run, "enhance", str(root / "long.npz"), "--out",
         str(tmp_path / "out"), "--model", str(root / "model.npz"), "--batch", "4",
         "--no-previews"], cwd=tmp_path, env=env, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 60
        while not list(tmp_path.glob(".out.*.tmp")) and proc.poll() is None:
            assert time.monotonic() < deadline, "the run never started"
            time.sleep(0.02)
        assert proc.poll() is None, proc.stderr.read()
        proc.send_signal(sig)
        # Python runs the handler once XLA returns from a compile: minutes on a loaded machine.
        _, err = proc.communicate(timeout=300)
    finally:  # never leave the run behind when an assertion or the timeout fires
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == code, err
    assert "Traceback" not in err
    assert err.strip().splitlines()[-1] == f"wrinkle-jax enhance: {word}; no output written"
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("sig, exc", [(signal.SIGINT, KeyboardInterrupt),
                                      (signal.SIGTERM, outdir.Terminated)])
def test_a_signal_right_after_the_temporary_folder_appears_still_removes_it(
        tmp_path, monkeypatch, sig, exc):
    # The race the subprocess test above can hit on a loaded machine: the signal arrives once
    # mkdtemp has made the folder but before staged_folder holds its name. Sent from inside
    # mkdtemp, it must not leave the folder behind (fails if creation is not signal-safe).
    real = outdir.tempfile.mkdtemp

    def mkdtemp_then_signal(*args, **kwargs):
        path = real(*args, **kwargs)
        os.kill(os.getpid(), sig)
        return path

    monkeypatch.setattr(outdir.tempfile, "mkdtemp", mkdtemp_then_signal)
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        with pytest.raises(exc), outdir.terminate_as_exception():
            with outdir.staged_folder(tmp_path / "a" / "out"):
                pass
    finally:
        signal.signal(signal.SIGINT, previous)
    assert list(tmp_path.iterdir()) == []  # neither the temporary folder nor a/


@pytest.mark.parametrize("sig, exc", [(signal.SIGTERM, outdir.Terminated),
                                      (signal.SIGINT, KeyboardInterrupt)])
def test_a_signal_whose_exception_c_code_turned_into_another_error_is_still_reported(sig, exc):
    # NumPy's structured-array comparison turned a Ctrl-C inside np.unique(axis=0) into a
    # TypeError (a CLI run interrupted during subdivision exited 1 with a traceback). Here the
    # handler's exception is replaced the same way; the block still raises the signal's.
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        with pytest.raises(exc) as got, outdir.terminate_as_exception():
            try:
                signal.raise_signal(sig)
            except (KeyboardInterrupt, outdir.Terminated):
                raise TypeError("Cannot compare structured arrays") from None
        assert isinstance(got.value.__cause__, TypeError)
        # Without a signal, errors pass through unchanged.
        with pytest.raises(TypeError), outdir.terminate_as_exception():
            raise TypeError("a plain error")
        assert signal.getsignal(signal.SIGINT) is signal.default_int_handler  # restored
    finally:
        signal.signal(signal.SIGINT, previous)


# ------------------------------------------------------------------ inputs that now work


def _report(tmp_path) -> dict:
    return json.loads((tmp_path / "out" / "report.json").read_text())


def test_negative_frames_select_the_last_ones(root, tmp_path, capsys):
    code, _ = _run(root, tmp_path, ["--frames=-2:"])
    assert code == 0
    assert _report(tmp_path)["frame_indices"] == [1, 2]
    assert sorted(p.name for p in (tmp_path / "out" / "normal_maps").iterdir()) == [
        "normal_map_00001.png", "normal_map_00002.png"]
    assert _run(root, tmp_path, ["--frames", "::2"])[0] == 0
    assert _report(tmp_path)["frame_indices"] == [0, 2]


def test_millimetres_with_units_give_the_same_maps_as_meters(root, tmp_path, capsys):
    # Not a whole number of texels across, so float rounding of the unit conversion cannot
    # change the map size.
    g = primitives.grid_sheet(6, 6, size=(0.157, 0.121))
    _save_npz(tmp_path / "m.npz", g)
    _save_npz(tmp_path / "mm.npz", g, scale=1000.0)
    assert _run(root, tmp_path, [], source=str(tmp_path / "m.npz"))[0] == 0
    meters = normalmap.load_normal_map_png(tmp_path / "out" / "normal_maps" /
                                           "normal_map_00001.png")[0]
    (tmp_path / "ref").mkdir()
    os.replace(tmp_path / "out", tmp_path / "ref" / "out")
    assert _run(root, tmp_path, ["--units", "mm"], source=str(tmp_path / "mm.npz"))[0] == 0
    mm = normalmap.load_normal_map_png(tmp_path / "out" / "normal_maps" /
                                       "normal_map_00001.png")[0]
    np.testing.assert_allclose(mm, meters, atol=2e-3)
    assert _report(tmp_path)["budget"]["map_shape"] == list(mm.shape[:2])


def test_few_degenerate_faces_warn_with_the_count(root, tmp_path, capsys):
    g = primitives.grid_sheet(12, 12, size=(0.16, 0.12))  # 288 faces
    f = np.array(g.faces)
    f[7, 2] = f[7, 1]
    _save_npz(tmp_path / "in.npz", dataclasses.replace(g, faces=f))
    code, _ = _run(root, tmp_path, ["--texel-size", "0.004"], source=str(tmp_path / "in.npz"),
                   command="bake")
    assert code == 0
    err = capsys.readouterr().err
    assert "warning: " in err and "1 of 288 zero-area or sliver faces in 3D (first: face 8)" in err
    assert _report(tmp_path)["warnings"] == [line.split("warning: ", 1)[1]
                                             for line in err.splitlines() if "warning" in line]


def test_garment_smaller_than_a_patch_warns(root, tmp_path, capsys):
    g = primitives.grid_sheet(6, 6, size=(0.1, 0.08))  # 25 x 20 texels < one 32-texel patch
    _save_npz(tmp_path / "in.npz", g)
    assert _run(root, tmp_path, [], source=str(tmp_path / "in.npz"))[0] == 0
    err = capsys.readouterr().err
    assert "warning:" in err and "less than one 32-texel patch" in err and "--units" in err


def test_quiet_by_default_json_on_request(root, tmp_path, capsys):
    assert _run(root, tmp_path, [])[0] == 0
    captured = capsys.readouterr()
    assert captured.out == "" and "Traceback" not in captured.err
    assert 2 <= len(captured.err.strip().splitlines()) <= 10  # one screen
    assert "material wool_melton (stored)" in captured.err
    assert _run(root, tmp_path, ["--json"])[0] == 0
    printed = json.loads(capsys.readouterr().out)
    assert printed == _report(tmp_path)


def test_help_lists_the_materials(capsys):
    from wrinkle_jax import MATERIALS

    for command in ("enhance", "demo"):
        with pytest.raises(SystemExit) as info:
            cli.main([command, "--help"])
        assert info.value.code == 0
        text = " ".join(capsys.readouterr().out.split())
        assert all(m in text for m in MATERIALS)
        assert "--units" in text or command == "demo"


def test_report_paths_are_package_relative_for_package_files():
    from wrinkle_jax import enhancer

    assert outdir.display_path(enhancer.DEFAULT_PATH) == "wrinkle_jax/assets/enhancer.npz"
    assert outdir.display_path(Path("some/where.npz")) == "some/where.npz"


def test_parse_frames_is_python_slicing_without_clipping():
    n = 20
    for spec in ("3:7", "-3:", ":-1", "::3", "-5:-2", "1:20:4", "19:-20:-2", "-20:20"):
        python = range(n)[slice(*[int(x) if x else None for x in spec.split(":")])]
        assert list(validate.parse_frames(spec, n)) == list(python), spec
    assert list(validate.parse_frames(None, n)) == list(range(n))
    assert list(validate.parse_frames("-1", n)) == [19]
    assert list(validate.parse_frames("7:2:-1", n)) == [7, 6, 5, 4, 3]
    for spec in ("17:40", "-21:", "20:", "3:3"):
        with pytest.raises(validate.UsageError):
            validate.parse_frames(spec, n)


def test_layout_names_zero_3d_area_and_zero_uv_area_apart():
    from wrinkle_jax.mesh import GarmentError

    g = _sheet()
    with pytest.raises(GarmentError, match="zero 3D area"):
        normalmap.make_plan(g.replace(vertices=np.zeros_like(np.asarray(g.vertices))))
    with pytest.raises(GarmentError, match="UV layout has zero area"):
        normalmap.make_plan(g.replace(uvs=np.zeros_like(np.asarray(g.uvs))))


def test_bake_never_writes_into_a_folder_with_user_files(root, tmp_path, capsys):
    out = tmp_path / "out"
    out.mkdir()
    (out / "mine.txt").write_text("x")
    code, seconds = _run(root, tmp_path, ["--texel-size", "0.004"], command="bake")
    _assert_failed_cleanly(capsys, tmp_path, code, 1, ["wrinkle-jax bake: error:", "mine.txt",
                                                       "--force"], seconds, before=["out"])
    assert sorted(p.name for p in out.iterdir()) == ["mine.txt"]  # nothing added or lost
    (out / "mine.txt").unlink()
    assert _run(root, tmp_path, ["--texel-size", "0.004"], command="bake")[0] == 0
    assert _run(root, tmp_path, ["--texel-size", "0.004", "--frames", "1"],
                command="bake")[0] == 0  # a previous bake is replaced, not merged into
    assert sorted(p.name for p in out.iterdir()) == ["normal_map_00001.png", "report.json"]


def test_choose_material_reports_where_the_material_came_from(tmp_path, monkeypatch):
    from wrinkle_jax import MATERIALS
    from wrinkle_jax.classifier import calibrated, synthesis_model

    choose = validate.choose_material
    assert choose(None, "knit_terry", MATERIALS, "s.npz") == ("knit_terry", "stored")
    assert choose("wool_melton", "knit_terry", MATERIALS, "s.npz") == ("wool_melton", "flag")
    with pytest.raises(validate.UsageError, match="s.npz stores the unknown material 'tweed'"):
        choose(None, "tweed", MATERIALS, "s.npz")
    with pytest.raises(validate.UsageError, match="s.npz stores no material.*--material NAME"):
        choose(None, None, MATERIALS, "s.npz")
    monkeypatch.setattr(calibrated, "MOTION_PATH", tmp_path / "none.npz")
    monkeypatch.setattr(synthesis_model, "SYNTHESIS_PATH", tmp_path / "no_synthesis.npz")
    with pytest.raises(validate.UsageError, match="no material classifier is available"):
        choose("auto", "knit_terry", MATERIALS, "s.npz")
    (tmp_path / "none.npz").write_bytes(b"")  # a classifier file exists: classify
    assert choose("auto", "knit_terry", MATERIALS, "s.npz") == ("auto", "classified")
