"""The plain-`.npz` model-file format shared by the enhancer and the material classifier.

A file holds named float arrays (parameter pytrees flattened to "a/b/c" keys), plus
``config.json`` and ``meta.json`` stored as uint8 bytes of JSON -- no pickle, readable with
`np.load(allow_pickle=False)`. ``meta["format"]`` names the kind and version of the file.

The calibrated classifiers (`classifier.calibrated`, `classifier.synthesis_model`) use a
second, "headed" layout (`write_headed` / `read_headed`): named arrays plus one ``head``
array, the uint8 bytes of a JSON object whose first key is ``format``; stored uncompressed.
"""

from __future__ import annotations

import io
import json
import os
from pathlib import Path
from typing import Any

import jax
import numpy as np

from wrinkle_jax.fileio import NPZ_READ_ERRORS, atomic_write_bytes


def flatten(tree, leaf_fn=np.asarray) -> dict[str, Any]:
    """Nested dict pytree -> {"a/b/c": leaf_fn(leaf)}."""
    flat = {}
    for path, leaf in jax.tree_util.tree_flatten_with_path(tree)[0]:
        flat["/".join(str(getattr(p, "key", p)) for p in path)] = leaf_fn(leaf)
    return flat


def unflatten(flat: dict[str, Any]) -> dict:
    """{"a/b/c": x} -> nested dicts (inverse of `flatten`)."""
    tree: dict = {}
    for keys, value in flat.items():
        node = tree
        *parents, leaf = keys.split("/")
        for part in parents:
            node = node.setdefault(part, {})
        node[leaf] = value
    return tree


def cast_params(params, dtype, path: Path, error_cls) -> dict[str, np.ndarray]:
    """Flattened parameters cast to `dtype`, under "params/" keys.

    Raises:
      error_cls: naming the file and the parameter, if a value does not fit `dtype`.
    """
    out = {}
    for k, v in flatten(params).items():
        with np.errstate(over="ignore"):
            cast = v.astype(dtype)
        if not np.all(np.isfinite(cast)):
            raise error_cls(f"{path}: parameter {k} does not fit {np.dtype(dtype).name}")
        out[f"params/{k}"] = cast
    return out


def write(path: str | os.PathLike, arrays: dict[str, np.ndarray], config: dict, meta: dict,
          fmt: str) -> Path:
    """Write `arrays` + config + meta (with ``format = fmt``) to `path` atomically."""
    path = Path(path)
    arrays = dict(arrays)
    arrays["config.json"] = np.frombuffer(json.dumps(config).encode(), np.uint8)
    arrays["meta.json"] = np.frombuffer(json.dumps({"format": fmt, **meta}, indent=1).encode(),
                                        np.uint8)
    buf = io.BytesIO()
    np.savez_compressed(buf, **arrays)
    atomic_write_bytes(path, buf.getvalue())
    return path


def read(path: Path, kind: str, fmt: str, error_cls) -> tuple[dict, dict, dict]:
    """(arrays, config dict, meta dict) of a model file of `kind` ("enhancer", ...).

    Raises:
      error_cls: naming the file, if it is unreadable or of another format.
    """
    try:
        with np.load(path, allow_pickle=False) as z:
            files = {k: z[k] for k in z.files}
        config = json.loads(bytes(files.pop("config.json")).decode())
        meta = json.loads(bytes(files.pop("meta.json")).decode())
    except NPZ_READ_ERRORS as e:
        raise error_cls(f"{path}: not a readable {kind} file ({e})") from None
    if meta.get("format") != fmt:
        raise error_cls(f"{path}: unknown format {meta.get('format')!r}")
    return files, config, meta


HEAD = "head"


def write_headed(path: str | os.PathLike, fmt: str, arrays: dict) -> Path:
    """Write a headed file atomically: `arrays` (name -> array, written in this order) whose
    `HEAD` entry is a JSON-able dict, stored with ``format = fmt`` as its first key."""
    path = Path(path)
    out = {k: (np.frombuffer(json.dumps({"format": fmt, **v}).encode(), np.uint8)
               if k == HEAD else v) for k, v in arrays.items()}
    buf = io.BytesIO()
    np.savez(buf, **out)
    atomic_write_bytes(path, buf.getvalue())
    return path


def head_format(head: np.ndarray) -> str | None:
    """The ``format`` named by a `HEAD` array, or None (not a JSON object naming one)."""
    try:
        obj = json.loads(bytes(head).decode())
    except (ValueError, TypeError):
        return None
    return obj.get("format") if isinstance(obj, dict) else None


def read_headed(path: str | os.PathLike, fmt: str, what: str, error_cls, build):
    """``build(head, arrays)`` for the headed file at `path`: head = its JSON object without
    ``format``, arrays = its other members as stored.

    Raises:
      error_cls: naming the file and `what` ("motion classifier", ...): missing, or unreadable,
        of another format, or refused by `build` (KeyError, ValueError, TypeError).
    """
    path = Path(path)
    if not path.is_file():
        raise error_cls(f"{path}: no such {what} file")
    try:
        with np.load(path, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
        head = json.loads(bytes(arrays.pop(HEAD)).decode())
    except NPZ_READ_ERRORS as e:
        raise error_cls(f"{path}: not a readable {what} ({e})") from None
    # Only what a foreign or damaged file's contents cause: an error of build's own code
    # (RuntimeError, ...) stays itself.
    try:
        got = head.get("format") if isinstance(head, dict) else None
        if got != fmt:
            raise ValueError(f"format {got!r}, expected {fmt!r}")
        del head["format"]
        return build(head, arrays)
    except (KeyError, ValueError, TypeError) as e:
        raise error_cls(f"{path}: not a readable {what} ({e})") from None


def float32_params(files: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """The "params/..." arrays of a file, as float32, keyed without the prefix."""
    return {k[len("params/"):]: v.astype(np.float32) for k, v in files.items()
            if k.startswith("params/")}
