"""The `wrinkle-jax` help: the light parser (one sub-command built in full, placeholders for the
rest, so `wrinkle-jax --help` imports no JAX) must say what the full parser says."""

from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path

import pytest

from wrinkle_jax import cli

ROOT = Path(__file__).resolve().parents[1]


def _subparsers(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    (action,) = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    return dict(action.choices)


COMMANDS = sorted(_subparsers(cli.build_parser()))


def test_every_command_is_listed():
    # The placeholders (`_OTHER_HELP`) stand for these; a new one must be checked below too.
    assert set(cli._OTHER_HELP) <= set(COMMANDS)
    assert {"demo", "enhance", "bake", "simulate", "classify", "train-classifier"} <= set(
        COMMANDS)


@pytest.mark.parametrize("command", ["", "frobnicate", *COMMANDS])
def test_light_parser_top_level_help_is_the_full_one(command):
    """`main` builds `build_parser(<first positional>)`: "" for `wrinkle-jax --help`, an unknown
    name for a usage error, or one sub-command. Its top-level help (the sub-command list with
    each help line) must be the full parser's, so a placeholder help line that drifts from
    what sim/command.py or classifier/cli.py registers fails here."""
    assert cli.build_parser(command).format_help() == cli.build_parser().format_help()


@pytest.mark.parametrize("command", COMMANDS)
def test_command_help_shows_its_real_options(command, capsys):
    """`wrinkle-jax COMMAND --help` prints the sub-command's full help, as the full parser
    builds it (its options, not a placeholder's empty list)."""
    full = _subparsers(cli.build_parser())[command]
    with pytest.raises(SystemExit) as info:
        cli.main([command, "--help"])
    assert info.value.code == 0
    out = capsys.readouterr().out
    assert out == full.format_help()
    # Every option the full parser registers is named (guards against both being empty).
    options = [s for a in full._actions for s in a.option_strings if s not in ("-h", "--help")]
    if command != "assets":  # assets has only a nested sub-command (fetch)
        assert options
    for s in options:
        assert s in out


def test_top_level_help_and_usage_errors_import_no_jax():
    code = ("import sys\n"
            "from wrinkle_jax import cli\n"
            "for argv in (['--help'], ['frobnicate']):\n"
            "    try:\n"
            "        cli.main(argv)\n"
            "    except SystemExit as e:\n"
            "        print(e.code, file=sys.stderr)\n"
            "print(sorted(m for m in ('jax', 'flax') if m in sys.modules))\n")
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True, cwd=ROOT)
    assert run.stdout.strip().split("\n")[-1] == "[]"
    codes = [line for line in run.stderr.split("\n") if line in ("0", "2")]
    assert codes == ["0", "2"]
    assert "simulate" in run.stdout and "classify" in run.stdout
