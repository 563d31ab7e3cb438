"""wrinkle_jax.fileio's atomic writes: all or nothing, and the mode `open()` would give."""

from __future__ import annotations

import os
import stat

import pytest

from wrinkle_jax import fileio


def _mode(path) -> int:
    return stat.S_IMODE(os.stat(path).st_mode)


def test_the_umask_is_the_process_umask():
    mask = os.umask(0o022)
    os.umask(mask)
    assert fileio._UMASK == mask


@pytest.mark.parametrize("umask", [0o022, 0o002, 0o077])
def test_atomic_writes_honour_the_umask(tmp_path, monkeypatch, umask):
    monkeypatch.setattr(fileio, "_UMASK", umask)
    fileio.atomic_write_text(tmp_path / "a.txt", "x")
    fileio.atomic_write_bytes(tmp_path / "sub" / "b.bin", b"y", fsync=True)
    with fileio.atomic_open(tmp_path / "c.bin") as fh:
        fh.write(b"z")
    for name in ("a.txt", "sub/b.bin", "c.bin"):
        assert _mode(tmp_path / name) == 0o666 & ~umask
    assert (tmp_path / "c.bin").read_bytes() == b"z"


def test_a_failed_write_leaves_the_old_file_and_no_temporary(tmp_path):
    path = tmp_path / "f.bin"
    fileio.atomic_write_bytes(path, b"old")
    with pytest.raises(RuntimeError), fileio.atomic_open(path) as fh:
        fh.write(b"partial")
        raise RuntimeError("disk full")
    assert path.read_bytes() == b"old" and os.listdir(tmp_path) == ["f.bin"]
    with pytest.raises(IsADirectoryError, match="is a directory"):
        fileio.atomic_write_bytes(tmp_path, b"x")
