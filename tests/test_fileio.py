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


def _npz_bytes(compressed: bool) -> bytes:
    import io
    import json

    import numpy as np

    buf = io.BytesIO()
    save = np.savez_compressed if compressed else np.savez
    save(buf, a=np.arange(3000, dtype=np.float32).reshape(30, 100),
         meta=np.frombuffer(json.dumps({"format": "x"}).encode(), np.uint8))
    return buf.getvalue()


def _read_like_a_loader(path):
    import json

    import numpy as np

    with np.load(path, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    json.loads(bytes(arrays.pop("meta")).decode())
    return arrays["a"]


def _deflate_start(data: bytes, member: str) -> int:
    """Offset of `member`'s compressed bytes in the zip `data` (after its local header)."""
    import io
    import struct
    import zipfile

    info = zipfile.ZipFile(io.BytesIO(data)).getinfo(member)
    name_len, extra_len = struct.unpack("<HH", data[info.header_offset + 26:
                                                   info.header_offset + 30])
    return info.header_offset + 30 + name_len + extra_len


# NumPy evaluates a damaged .npy header as a Python literal, which may warn about its escapes.
@pytest.mark.filterwarnings("ignore::DeprecationWarning", "ignore::SyntaxWarning")
@pytest.mark.parametrize("compressed", [False, True])
def test_every_damaged_npz_raises_one_of_the_read_errors(tmp_path, compressed):
    """Cut short anywhere, or one byte flipped in either end (the first member's zip and .npy
    headers; the central directory): reading fails only with `NPZ_READ_ERRORS` (an error
    outside it fails this test), or reads (flips in unused fields)."""
    data = _npz_bytes(compressed)
    path = tmp_path / "f.npz"
    path.write_bytes(data)
    assert _read_like_a_loader(path).shape == (30, 100)  # the intact file reads
    damaged = [data[:cut] for cut in range(0, len(data), 97)]  # also the empty file
    for pos in [*range(200), *range(len(data) - 200, len(data))]:
        for bits in (0xFF, 0x01):
            b = bytearray(data)
            b[pos] ^= bits
            damaged.append(bytes(b))
    raised = set()
    for d in damaged:
        path.write_bytes(d)
        try:
            _read_like_a_loader(path)
        except fileio.NPZ_READ_ERRORS as e:
            raised.add(type(e).__name__)
    # The sweep reaches the exotic ones (zipfile's encrypted-flag and method errors, NumPy's
    # header parsing), not only BadZipFile.
    assert {"BadZipFile", "RuntimeError", "NotImplementedError", "TokenError"} <= raised, raised
    for missing in (tmp_path / "none.npz", tmp_path):  # no file; a folder
        with pytest.raises(fileio.NPZ_READ_ERRORS):
            _read_like_a_loader(missing)


def test_a_damaged_compressed_member_raises_zlib_error_which_is_a_read_error(tmp_path):
    import zlib

    data = bytearray(_npz_bytes(True))
    start = _deflate_start(bytes(data), "a.npy")
    data[start] = 0xFF  # deflate block type 3: reserved, invalid
    path = tmp_path / "f.npz"
    path.write_bytes(bytes(data))
    with pytest.raises(zlib.error):
        _read_like_a_loader(path)
    assert issubclass(zlib.error, fileio.NPZ_READ_ERRORS)


def test_model_files_with_a_damaged_member_are_reported_as_unreadable(tmp_path):
    """modelfile.write stores compressed members (enhancer files): a damaged member is the
    reader's error naming the file, not a zlib.error from inside NumPy."""
    import numpy as np

    from wrinkle_jax import modelfile

    class Unreadable(Exception):
        pass

    path = tmp_path / "m.npz"
    w = np.arange(4000, dtype=np.float32)
    modelfile.write(path, {"w": w}, {"c": 1}, {"m": 2}, "test-format/1")
    arrays, config, meta = modelfile.read(path, "test", "test-format/1", Unreadable)
    np.testing.assert_array_equal(arrays["w"], w)
    assert config == {"c": 1} and meta["m"] == 2
    data = bytearray(path.read_bytes())
    data[_deflate_start(bytes(data), "w.npy")] = 0xFF
    path.write_bytes(bytes(data))
    with pytest.raises(Unreadable, match="m.npz: not a readable test file"):
        modelfile.read(path, "test", "test-format/1", Unreadable)


def test_a_claim_excludes_other_holders_and_dies_with_its_process(tmp_path):
    """`claim` is an flock: a second claim (another open file, here or in another process)
    is refused while one is held, the file goes when the block ends, and a killed holder
    leaves nothing stale behind."""
    import subprocess
    import sys

    from wrinkle_jax.fileio import claim

    path = tmp_path / "sub" / "job.lock"
    with claim(path) as first:
        assert first and path.exists()
        with claim(path) as second:
            assert not second
        assert path.exists()  # the refused claim leaves the holder's file
    assert not path.exists()
    with claim(path) as again:
        assert again
    holder = subprocess.Popen(
        [sys.executable, "-c", "import sys, time\nfrom wrinkle_jax.fileio import claim\n"
         f"with claim({str(path)!r}) as ok:\n    print(ok, flush=True)\n    time.sleep(60)"],
        stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "True"
        with claim(path) as mine:
            assert not mine
    finally:
        holder.kill()
        holder.wait()
    assert path.exists()  # killed inside its block: the file stays, the lock does not
    with claim(path) as mine:
        assert mine
    assert not path.exists()
