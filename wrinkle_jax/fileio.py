"""Where files go and how they are written: the user cache folder, atomic file writes
(readers never see a partial output file, and a failed write leaves nothing behind), and the
errors a damaged `.npz` raises when it is read."""

from __future__ import annotations

import contextlib
import fcntl
import hashlib
import os
import subprocess
import tempfile
import tokenize
import zipfile
import zlib
from collections.abc import Iterator
from pathlib import Path
from typing import BinaryIO

# What reading a damaged or foreign `.npz` raises (np.load, its members, decoding their
# bytes), seen in a sweep of single-byte flips over both ends of plain and compressed files
# (tests/test_fileio.py): OSError (missing, a folder, no permission; a bad zip header),
# EOFError (empty or cut short), zipfile.BadZipFile (cut short, a bad CRC), zlib.error (a
# damaged compressed member: np.savez_compressed files such as model files and sequences),
# KeyError (a missing member), ValueError (object arrays without pickle, bad .npy headers, bad
# JSON or UTF-8), TypeError (a member of another type than the reader expects), SyntaxError and
# tokenize.TokenError (NumPy parses a damaged .npy header dict), RuntimeError and
# NotImplementedError (zipfile: a damaged flag or method field reads as encrypted or as an
# unknown compression). Loaders catch these and raise their own error naming the file.
NPZ_READ_ERRORS = (OSError, EOFError, zipfile.BadZipFile, zlib.error, KeyError, ValueError,
                   TypeError, SyntaxError, tokenize.TokenError, RuntimeError,
                   NotImplementedError)

# Read once at import: os.umask can only be read by setting it, which races with threads.
_UMASK = os.umask(0o022)
os.umask(_UMASK)


def user_cache_dir() -> Path:
    """The user cache folder (need not exist yet), read from the environment at each call.

    `$WRINKLE_JAX_CACHE` if set (and non-empty), else `$XDG_CACHE_HOME/wrinkle-jax`, else
    `~/.cache/wrinkle-jax`.
    """
    explicit = os.environ.get("WRINKLE_JAX_CACHE")
    if explicit:
        return Path(explicit)
    xdg = os.environ.get("XDG_CACHE_HOME")
    return (Path(xdg) if xdg else Path.home() / ".cache") / "wrinkle-jax"


def atomic_write_text(path: str | os.PathLike, text: str) -> None:
    """Write text to `path` via a temporary file in the same folder and `os.replace`."""
    atomic_write_bytes(path, text.encode("utf-8"))


def atomic_write_bytes(path: str | os.PathLike, data: bytes, *, fsync: bool = False) -> None:
    """Write bytes to `path` atomically: readers never see a partial file.

    Args:
      fsync: flush the data to disk before the rename, so that a crash or power loss cannot
        leave an empty or truncated file under `path` (for cache entries that are read back
        without being rewritten; costs a disk sync per call).
    """
    with atomic_open(path, fsync=fsync) as fh:
        fh.write(data)


@contextlib.contextmanager
def atomic_open(path: str | os.PathLike, *, fsync: bool = False) -> Iterator[BinaryIO]:
    """A binary file to write that replaces `path` only when the block ends without error
    (a temporary file in the same folder, then `os.replace`; on error it is removed and
    `path` is left as it was). The file gets the mode `open()` would give a new one,
    0o666 minus the umask (not `mkstemp`'s 0o600). `fsync`: as in `atomic_write_bytes`."""
    path = Path(path)
    if path.is_dir():
        raise IsADirectoryError(f"{path}: is a directory, cannot write a file there")
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as fh:
            yield fh
            if fsync:
                fh.flush()
                os.fsync(fh.fileno())
        os.chmod(tmp, 0o666 & ~_UMASK)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def sha256_file(path: str | os.PathLike) -> str:
    """The SHA-256 of a file's bytes (hex), read in 4 MiB blocks (a 100 MB sequence file in
    ~0.3 s): what a derived file records of its sources, to tell when they changed."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(1 << 22):
            h.update(block)
    return h.hexdigest()


def git_commit(root: str | os.PathLike) -> str | None:
    """The short HEAD commit of the git checkout at `root`, or None (no git, not a checkout)."""
    try:
        return subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True,
                              text=True, check=True, cwd=root).stdout.strip() or None
    except (OSError, subprocess.CalledProcessError):
        return None


@contextlib.contextmanager
def claim(path: str | os.PathLike) -> Iterator[bool]:
    """Claim a piece of work among processes sharing a folder: yields True if this process
    holds the claim on `path` for the block, False if another process holds it.

    An exclusive `flock` on the file `path` (created if needed, removed when the block
    ends): the kernel drops it when its process dies, so a killed run leaves no stale claim.
    Local file systems only (flock is advisory and per host).
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    while True:
        fd = os.open(path, os.O_CREAT | os.O_RDWR, 0o666)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            yield False
            return
        try:
            same = os.fstat(fd).st_ino == os.stat(path).st_ino
        except FileNotFoundError:
            same = False
        if same:
            break
        # The holder removed the file between our open and lock: that inode is gone, retry.
        os.close(fd)
    try:
        yield True
    finally:
        with contextlib.suppress(FileNotFoundError):
            path.unlink()  # still under the lock, so no one holds the removed inode
        os.close(fd)


def claim_output(out: str | os.PathLike, path: str | os.PathLike):
    """`claim` the writing of `path`, a file under the folder `out`, among runs sharing that
    folder: the claim file is `<out>/.partial/<path relative to out>.lock`, beside the runs'
    checkpoints and out of the way of globs over the outputs."""
    out, path = Path(out), Path(path)
    rel = path.relative_to(out)
    return claim(out / ".partial" / rel.parent / (rel.name + ".lock"))
