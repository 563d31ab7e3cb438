"""The README's Python example runs as written (from the repository root)."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_readme_python_example_runs(tmp_path, monkeypatch):
    text = (ROOT / "README.md").read_text()
    blocks = re.findall(r"```python\n(.*?)```", text, re.S)
    assert blocks, "the README has no Python example"
    monkeypatch.chdir(ROOT)
    code = blocks[0].replace('"frame0.png"', repr(str(tmp_path / "frame0.png")))
    scope: dict = {}
    exec(compile(code, "README.md", "exec"), scope)
    assert scope["maps"].shape[0] == 12
    assert scope["merged"].shape == scope["maps"][0].shape
    assert (tmp_path / "frame0.png").exists()
    assert scope["detailed"].shape == scope["tiles"].shape
