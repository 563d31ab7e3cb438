"""Reading MPFB2 asset files: the error type shared by the character modules and a checked
JSON reader.

Contract:
  * Every bad character asset raises `CharacterError` (a `ValueError`) whose message names the
    file and the problem.
  * `read_json(path)` returns the parsed JSON, or raises `CharacterError` for an unreadable
    file or invalid JSON.
"""

from __future__ import annotations

import json
from pathlib import Path


class CharacterError(ValueError):
    """Invalid or unsupported character asset (the message names the file and the problem)."""


def read_json(path: Path):
    """Parsed JSON of `path` (CharacterError naming the file if unreadable or invalid)."""
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except OSError as e:
        raise CharacterError(f"{path}: cannot read ({e.strerror})") from None
    except json.JSONDecodeError as e:
        raise CharacterError(f"{path}: invalid JSON ({e.msg} at line {e.lineno})") from None
