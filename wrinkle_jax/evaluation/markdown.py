"""Building a markdown report from stored result files: a line collector that remembers which
results were missing (with the command that makes them) and which machines produced them, plus
heading demotion and a small plotting helper.

Used by `experiments/report.py` (REPORT.md); nothing here knows which results exist.
"""

from __future__ import annotations

import json
import re
from collections.abc import Callable, Mapping
from pathlib import Path

from wrinkle_jax.evaluation import suite


class Report:
    """Markdown lines, the missing results and the machines seen, collected section by section.

    Args:
      results: the folder the result paths given to `load` are relative to.
      commands: result name -> the command that produces it (named when it is missing).
    """

    def __init__(self, results: Path, commands: Mapping[str, str] | None = None):
        self.results = Path(results)
        self.known_commands = dict(commands or {})
        self.lines: list[str] = []
        self.missing: list[tuple[str, str]] = []
        self.machines: dict[str, dict] = {}
        self.commands: dict[str, str] = {}
        self._loaded: dict[str, dict | None] = {}

    def add(self, *lines: str) -> None:
        self.lines.extend(lines)

    def load(self, name: str, rel: str) -> dict | None:
        """JSON at `<results>/<rel>`, remembering its command and machine; None if missing.
        Read once per report (sections share results)."""
        if rel not in self._loaded:
            self._loaded[rel] = self._read(name, rel)
        return self._loaded[rel]

    def _read(self, name: str, rel: str) -> dict | None:
        path = self.results / rel
        known = self.known_commands.get(name)
        if not path.exists():
            self.missing.append((name, known or "no script yet"))
            return None
        try:
            data = json.loads(path.read_text())
        except (OSError, json.JSONDecodeError) as err:
            self.missing.append((name, f"{known} (unreadable: {err})"))
            return None
        if isinstance(data, dict):
            self.commands[name] = data.get("command", known or "?")
            if isinstance(data.get("machine"), dict):
                self.machines[name] = data["machine"]
        return data

    def not_run(self, what: str, name: str, why: str = "") -> None:
        cmd = self.known_commands.get(name)
        how = f"Command: `{cmd}`." if cmd else "No script yet."
        self.add(f"**Not run yet**: {what}. {how}" + (f" {why}" if why else ""), "")

    def image(self, rel: str, alt: str) -> None:
        """Link an image under `<results>` (relative to REPORT.md) if it exists."""
        if (self.results / rel).exists():
            self.add(f"![{alt}]({rel})", "")


def demote(markdown: str, levels: int = 1) -> str:
    """Push every markdown heading down `levels` levels (embed a script's table.md)."""
    return re.sub(r"^(#+) ", lambda m: "#" * (len(m.group(1)) + levels) + " ", markdown,
                  flags=re.M)


def ci(d: Mapping | None) -> str:
    """A paired difference (`stats.paired_difference` form) as "median [lo, hi]"; "" if empty."""
    if not d or not d.get("n"):
        return ""
    lo, hi = d["median_diff_ci"]
    return f"{d['median_diff']:+.1f} [{lo:+.1f}, {hi:+.1f}]"


def plot(path: Path, draw: Callable, xlabel: str, ylabel: str, title: str) -> None:
    """A 5.2 x 3.6 inch figure drawn by `draw(ax)`, saved as `path` (parents made)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5.2, 3.6))
    draw(ax)
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_title(title, fontsize=10)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    suite.save_figure(fig, path, dpi=100)


def label_points(ax, xs, ys, labels) -> None:
    """Markers at (xs, ys), each annotated with its label."""
    ax.plot(xs, ys, "o")
    for x, y, t in zip(xs, ys, labels, strict=True):
        ax.annotate(t, (x, y), textcoords="offset points", xytext=(4, 4), fontsize=8)
