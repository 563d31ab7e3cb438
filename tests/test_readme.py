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
    import numpy as np

    maps, detailed = np.asarray(scope["maps"]), np.asarray(scope["detailed"])
    assert maps.shape[0] == 12 and detailed.shape == maps[0].shape
    # The network sees the RGB form in [0, 1], zero off the garment, as in training.
    tiles = np.asarray(scope["tiles"])
    assert tiles.min() >= 0.0 and tiles.max() <= 1.0 and tiles.mean() > 0.2
    inside = np.asarray(scope["plan"].mask)[..., 0] > 0
    # The enhanced map is unit-norm on the garment and differs from the coarse map there
    # (new detail), without flipping normals.
    np.testing.assert_allclose(np.linalg.norm(detailed[inside], axis=-1), 1.0, atol=1e-4)
    cos = np.sum(detailed[inside] * maps[0][inside], -1)
    assert np.percentile(np.arccos(np.clip(cos, -1, 1)), 99) > np.deg2rad(2.0)
    assert np.median(cos) > np.cos(np.deg2rad(30.0))
    from wrinkle_jax import normalmap

    back, mask = normalmap.load_normal_map_png(tmp_path / "frame0.png")
    assert (mask[..., 0] > 0).sum() == inside.sum()


def test_readme_layout_names_every_module_and_only_existing_files():
    """The layout section is the newcomer's map: every library module, subpackage, benchmark
    and experiment script is in it, and every file it names exists."""
    text = (ROOT / "README.md").read_text()
    section = text[text.index("## Layout"):]
    block = re.search(r"```\n(.*?)```", section, re.S).group(1)
    words = set(re.findall(r"[A-Za-z_][\w/]*(?:\.py|\.npz|\.md|/)?", block))
    package = ROOT / "wrinkle_jax"
    for path in package.glob("*.py"):
        if path.name != "__init__.py":
            assert path.name in words, f"{path.name} is not in the README layout"
    for path in package.iterdir():
        if path.is_dir() and (path / "__init__.py").is_file():
            assert any(w.startswith(f"{path.name}/") for w in words), (
                f"{path.name}/ is not in the README layout")
    for folder in ("benchmarks", "experiments"):
        for path in (ROOT / folder).glob("*.py"):
            if path.name != "__init__.py":
                assert path.stem in words, f"{folder}/{path.name} is not in the README layout"
    library = {p.name for p in package.rglob("*") if p.is_file()}
    for word in words:
        if word.endswith((".py", ".npz", ".md")):
            found = ((package / word).is_file() if "/" in word else
                     word in library or (ROOT / "tests" / word).is_file()
                     or (ROOT / "experiments" / "results" / word).is_file())
        elif word.endswith("/"):
            found = any((base / word).is_dir() for base in (package, ROOT, ROOT / "experiments"))
        else:
            continue
        assert found, f"the README layout names {word}, which does not exist"
