"""The import graph: the library never imports the experiments, an experiment script imports
no other script, and the library's module-level imports have no cycles.

Static (the `ast` of every file; nothing is imported), so it runs in well under a second.
"""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

# Scripts that may import each other: none. (The last chain, per_layer_ratios -> short_runs ->
# train_default, ended when the recipe's flags moved to `wrinkle_jax.recipe`, the held-out
# patch set to `evaluation.patchsets.take` and the run's outputs to `train.enhance_batch`.)
ALLOWED_SCRIPT_IMPORTS: set[str] = set()


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _modules(package: str) -> dict[str, Path]:
    return {_module_name(p): p for p in sorted((ROOT / package).rglob("*.py"))
            if "results" not in p.relative_to(ROOT).parts}


def _is_package(name: str, modules: dict[str, Path]) -> bool:
    return modules.get(name, Path()).name == "__init__.py"


def _imports(name: str, path: Path, modules: dict[str, Path], top_level_only: bool
             ) -> set[str]:
    """Absolute names a module imports (resolved to modules in `modules` where they are one;
    `from P import x` gives P.x when that is a module, else P)."""
    tree = ast.parse(path.read_text(), str(path))
    nodes = tree.body if top_level_only else list(ast.walk(tree))
    package = name if _is_package(name, modules) else name.rpartition(".")[0]
    out = set()
    for node in nodes:
        if isinstance(node, ast.Import):
            out.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")
                anchor = anchor[:len(anchor) - (node.level - 1)]
                base = ".".join([*anchor, *([base] if base else [])])
            for a in node.names:
                sub = f"{base}.{a.name}"
                out.add(sub if sub in modules else base)
    return out


def test_the_library_never_imports_the_experiments():
    lib = _modules("wrinkle_jax")
    bad = {name: sorted(i for i in _imports(name, p, lib, False)
                        if i == "experiments" or i.startswith("experiments."))
           for name, p in lib.items()}
    assert not {k: v for k, v in bad.items() if v}


def _script_imports(scripts: dict[str, Path]) -> dict[str, list[str]]:
    """{script: the `experiments` modules it imports (anywhere in the file)} outside the
    allow-list."""
    bad = {}
    for name, p in scripts.items():
        me = name.rpartition(".")[2]
        for i in sorted(_imports(name, p, scripts, False)):
            if i == "experiments" or i.startswith("experiments."):
                other = i.rpartition(".")[2]
                if not (me in ALLOWED_SCRIPT_IMPORTS and other in ALLOWED_SCRIPT_IMPORTS):
                    bad.setdefault(name, []).append(i)
    return bad


def test_experiment_scripts_import_no_other_script():
    bad = _script_imports(_modules("experiments"))
    assert not bad, f"experiments import other experiments (move the code to wrinkle_jax): {bad}"


def test_the_script_check_sees_every_import_form(tmp_path):
    """`from experiments import x`, `import experiments.x` inside a function and
    `from experiments.x import f` are all found; a library import is not."""
    files = {"a": "from experiments import b\n",
             "b": "def f():\n    import experiments.c\n",
             "c": "from experiments.a import f\nfrom wrinkle_jax import recipe\n",
             "d": "from wrinkle_jax import train\n"}
    scripts = {}
    for stem, text in files.items():
        (tmp_path / f"{stem}.py").write_text(text)
        scripts[f"experiments.{stem}"] = tmp_path / f"{stem}.py"
    assert _script_imports(scripts) == {"experiments.a": ["experiments.b"],
                                        "experiments.b": ["experiments.c"],
                                        "experiments.c": ["experiments.a"]}


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan)."""
    index, low, stack, on, out = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in graph.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def test_the_library_has_no_module_level_import_cycles():
    lib = _modules("wrinkle_jax")
    graph = {}
    for name, p in lib.items():
        deps = set()
        for i in _imports(name, p, lib, True):
            # A module's own packages are already importing when it runs: not an edge.
            if i in lib and not (name == i or name.startswith(i + ".")):
                deps.add(i)
        graph[name] = deps
    assert not _cycles(graph)


def test_the_cycle_finder_sees_a_cycle():
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
