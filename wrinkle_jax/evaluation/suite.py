"""Plumbing shared by the evaluation scripts in `experiments/`: the project's folders, results
files (JSON written atomically, machine information, file digests, portable paths), progress
text, figures and argument parsers.

The folders are those of the project checkout this package is in (`ROOT`): the scripts' default
inputs (`SEQUENCES`) and outputs (`RESULTS`).
"""

from __future__ import annotations

import argparse
import functools
import io
import json
import math
import os
import platform
import sys
from pathlib import Path

import cv2
import jax
import numpy as np

from wrinkle_jax import enhancer as enhancer_lib
from wrinkle_jax import hostcpu
from wrinkle_jax.fileio import atomic_write_bytes, atomic_write_text, sha256_file

__all__ = ["MODEL_CARD_RESULTS", "RESULTS", "ROOT", "SEQUENCES", "TABLE1_SEQUENCES", "eta_text",
           "file_digest", "load_model_or_usage_error", "machine_info", "portable_path",
           "save_figure", "script_parser", "write_json"]

ROOT = Path(__file__).resolve().parents[2]
SEQUENCES = ROOT / "data" / "sequences"  # experiments.make_sequences output
TABLE1_SEQUENCES = ROOT / "data" / "table1_sequences"  # sequences simulated for the suite
RESULTS = ROOT / "experiments" / "results"
MODEL_CARD_RESULTS = RESULTS / "model_card" / "results.json"


def machine_info() -> dict:
    """Platform, CPU (model, the flags that decide XLA's code, `hostcpu.describe`), CPU count,
    1-minute load average and library versions (JSON-ready)."""
    try:
        load = round(os.getloadavg()[0], 2)
    except OSError:
        load = None
    return {"platform": platform.platform(), "processor": platform.processor() or None,
            **hostcpu.describe(), "cpu_count": os.cpu_count(), "load_avg_1min": load,
            "python": sys.version.split()[0], "jax": jax.__version__,
            "jax_backend": jax.default_backend(), "numpy": np.__version__,
            "opencv": cv2.__version__}


def file_digest(path: str | os.PathLike) -> str:
    """'sha256:<first 16 hex digits>' of a file's bytes: identifies a model or a simulation
    across clones (its mtime does not). Remembered per (path, mtime, size) within a process:
    the tables ask for each sequence's digest when they look for a stored cell and again
    when they store it."""
    st = os.stat(path)
    return _digest(str(Path(path).resolve()), st.st_mtime_ns, st.st_size)


@functools.lru_cache(maxsize=512)
def _digest(path: str, mtime_ns: int, size: int) -> str:
    del mtime_ns, size  # the cache key: a rewritten file is hashed again
    return "sha256:" + sha256_file(path)[:16]


def portable_path(path: str | os.PathLike) -> str:
    """`path` relative to the project root when it lies under it (fingerprints then survive a
    clone to another folder), else absolute."""
    p = Path(path).resolve()
    try:
        return str(p.relative_to(ROOT))
    except ValueError:
        return str(p)


def write_json(path: str | os.PathLike, obj) -> None:
    """Write `obj` as indented JSON, atomically (NaN written as null)."""
    atomic_write_text(path, json.dumps(_jsonable(obj), indent=1) + "\n")


def _jsonable(x):
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [_jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return _jsonable(x.tolist())
    if isinstance(x, np.generic):
        return _jsonable(x.item())
    if isinstance(x, float) and not math.isfinite(x):
        return None
    return x


def eta_text(done: float, total: float, elapsed_s: float) -> str:
    """'ETA 12.3 min' from the work done so far (any unit) and the seconds it took."""
    if done <= 0:
        return "ETA ?"
    return f"ETA {elapsed_s / done * max(total - done, 0.0) / 60:.1f} min"


def script_parser(doc: str) -> argparse.ArgumentParser:
    """An argument parser whose description is the docstring's first paragraph and whose
    epilog is the rest of it (the scripts' usage and method notes)."""
    return argparse.ArgumentParser(description=" ".join(doc.split("\n\n")[0].split()),
                                   formatter_class=argparse.RawDescriptionHelpFormatter,
                                   epilog="\n".join(doc.splitlines()[1:]))


def load_model_or_usage_error(ap: argparse.ArgumentParser, path) -> enhancer_lib.Enhancer:
    """The enhancer at `path`, or a usage error (exit 2) naming the file and the `--model` flag."""
    try:
        return enhancer_lib.load_enhancer(path)
    except enhancer_lib.EnhancerError as e:
        ap.error(f"{e}; pass --model PATH (e.g. outputs/candidates/enhancer_w32_relative.npz)")


def save_figure(fig, path, dpi: int) -> None:
    """Write a matplotlib figure as PNG atomically and close it."""
    import matplotlib.pyplot as plt

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi)
    plt.close(fig)
    atomic_write_bytes(path, buf.getvalue())
