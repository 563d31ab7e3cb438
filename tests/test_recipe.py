"""`experiments.train_default` is thin over `train.RECIPE`, and the experiments' imports form no
cycle (per_layer_ratios -> short_runs -> train_default -> per_layer_ratios used to)."""

from __future__ import annotations

import argparse
import ast
import dataclasses
from pathlib import Path

from wrinkle_jax import enhancer, train
from wrinkle_jax.nn import unet

ROOT = Path(__file__).resolve().parents[1]


def _parse(argv):
    from experiments import train_default

    ap = argparse.ArgumentParser()
    train_default.add_recipe_args(ap)
    return train_default.config_from_args(ap.parse_args(argv))


def test_recipe_is_the_shipped_models_and_the_flags_default_to_it():
    assert _parse([]) == train.RECIPE
    assert train.RECIPE.unet == unet.RECIPE_UNET
    shipped = enhancer.load_enhancer().meta["train_config"]
    assert train.TrainConfig.from_json(shipped) == train.RECIPE
    assert enhancer.load_enhancer().config.unet == unet.RECIPE_UNET


def test_the_detail_recipe_command_line_sets_exactly_its_flags():
    argv = ("--detail-sigma 8 --noise-channels 4 --noise-scale 4 --upsample bilinear "
            "--residual-base unsharp --unsharp-sigma 16 --unsharp-amount 1 "
            "--residual-highpass 16 --style-layers relu1_2,relu2_1,relu3_1,relu4_1 "
            "--relative-floor 300 --w-s 10 --w-c 0.1 --width 16 --lr 2e-4").split()
    got = _parse(argv)
    net = dataclasses.replace(unet.RECIPE_UNET, detail_sigma=8.0, noise_channels=4,
                              noise_scale=4, upsample="bilinear", residual_highpass=16.0)
    assert got == dataclasses.replace(
        train.RECIPE, unet=net, relative_floor=300.0,
        style_layers=("relu1_2", "relu2_1", "relu3_1", "relu4_1"))
    # ... which is the committed detail model's training config, as that run wrote it
    meta = enhancer.load_enhancer(ROOT / "experiments/results/fidelity/detail_bilinear.npz").meta
    saved = train.TrainConfig.from_json(meta["train_config"])
    assert saved.unet == got.unet and saved.style_layers == got.style_layers
    assert _parse(["--relative-floor", "0"]).relative_floor is None


def _experiment_imports(path: Path) -> set[str]:
    """Names of the `experiments` modules a script imports (at top level or in functions)."""
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module == "experiments":
            found |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom) and (node.module or "").startswith("experiments."):
            found.add(node.module.split(".")[1])
        elif isinstance(node, ast.Import):
            found |= {a.name.split(".")[1] for a in node.names
                      if a.name.startswith("experiments.")}
    return found


def test_experiments_import_graph_has_no_cycle():
    scripts = {p.stem: p for p in (ROOT / "experiments").glob("*.py") if p.stem != "__init__"}
    graph = {name: _experiment_imports(p) & set(scripts) for name, p in scripts.items()}
    assert "train_default" in graph["short_runs"]  # the graph is read (not empty)
    state: dict[str, int] = {}

    def visit(node, path):
        state[node] = 1
        for nxt in sorted(graph[node]):
            assert state.get(nxt) != 1, " -> ".join([*path, node, nxt])
            if nxt not in state:
                visit(nxt, [*path, node])
        state[node] = 2

    for name in sorted(graph):
        if name not in state:
            visit(name, [])

