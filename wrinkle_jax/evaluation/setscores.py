"""Sets of patches without correspondence, cell by cell (paper Table 2's measurement): the
records `experiments.table2` keeps of a cell, their files, and the means and table over cells.

A cell's record holds the frames and origins of its sets a (coarse input patches; every b, a
method's output on a, shares them) and c (fine patches at other frames), the layer scales of
the Gram features, and per method the `sets.compare_sets` numbers C1, C2, DR and DR_signed in
both `SPACES` (the 2D spectral embedding, float32 (N_a + N_b + N_c, 2), and the full feature
space); C1, C2 are Chamfer distances of scaled Gram features (dimensionless), DR in percent.
A stored record (`save_cell`, `load_cell`) carries the fingerprint of its sets and the source
of each method, so a rerun scores only methods it has not stored (`merge_records`).
"""

from __future__ import annotations

import io
import json
import time
from collections.abc import Iterable
from pathlib import Path

import numpy as np

from wrinkle_jax.evaluation import cells as cell_lib
from wrinkle_jax.evaluation import patchscores
from wrinkle_jax.evaluation import sets as set_lib
from wrinkle_jax.evaluation.patchscores import MODEL
from wrinkle_jax.fileio import atomic_write_bytes

__all__ = ["CELL_KEYS", "GROUPS", "SPACES", "c_frame_indices", "cell_path", "cell_record",
           "group_of", "load_cell", "mean_scores", "merge_records", "save_cell",
           "table_markdown"]

SPACES = ("embedded", "full")
GROUPS = ("seen garment", "unseen garment")


def c_frame_indices(frame_indices: Iterable[int], frames: int, frame_stride: int) -> list[int]:
    """Frames of set (c), one per scored frame t: t + frame_stride // 2, or t - frame_stride // 2
    where that is not below `frames`. With scored frames 0, k, 2k, ... (k = frame_stride >= 2)
    none of them is a scored frame.

    Raises:
      ValueError: frame_stride < 2, or a frame with neither neighbour in [0, frames).
    """
    half = int(frame_stride) // 2
    if half < 1:
        raise ValueError("the frame stride must be >= 2: set (c) uses the frames between the "
                         "scored ones")
    out = []
    for t in frame_indices:
        tc = t + half if t + half < frames else t - half
        if tc < 0:
            raise ValueError(f"no frame {half} away from frame {t} within {frames} frames")
        out.append(int(tc))
    return out


def cell_record(res: dict) -> dict:
    """What is kept of an evaluated cell: sampling, scales, timings and per method
    `compare_sets` (embedding as float32), without the distance matrices.

    Args:
      res: `experiments.table2.evaluate_cell`'s result: "frame", "origin" ((N_a,) int32,
        (N_a, 2)), "frame_c", "origin_c" (the same for c), "scales", "d2_ref" ((N_a + N_c,)*2
        scaled squared distances of a then c), "d2_method" ({name: (N_a, N_a + N_c + N_a)}),
        "n_candidates", "timings" (seconds).
    Returns:
      the same without "d2_ref" and "d2_method", with "methods": {name: `compare_sets` dict}
      and "timings" plus "compare_s".
    """
    n_a = len(res["frame"])
    methods = {}
    t0 = time.perf_counter()
    for name, blk in res["d2_method"].items():
        got = set_lib.compare_sets(*set_lib.union_sq_dists(res["d2_ref"], blk, n_a))
        got["embedding"] = got["embedding"].astype(np.float32)
        methods[name] = got
    timings = dict(res["timings"], compare_s=time.perf_counter() - t0)
    return {"frame": res["frame"], "origin": res["origin"], "frame_c": res["frame_c"],
            "origin_c": res["origin_c"], "scales": res["scales"],
            "n_candidates": res["n_candidates"], "timings": timings, "methods": methods}


# --------------------------------------------------------------------------------------------
# Cell files (resume)
# --------------------------------------------------------------------------------------------


def cell_path(out: Path, cell: cell_lib.Cell) -> Path:
    """Where a cell's record is stored under a Table 2 output folder `out`."""
    return out / "cells" / f"{cell.scene.name}__{cell.material}.npz"


# What defines a cell's sets a and c and their features; each method's numbers carry a source.
CELL_KEYS = ("sampling", "sequences", "simulations", "metric")


def save_cell(path: Path, record: dict, fingerprint: dict, sources: dict[str, str]) -> None:
    """Store one cell record (arrays + JSON numbers, fingerprint and every method's source),
    atomically."""
    names = list(record["methods"])
    numbers = {k: {s: record["methods"][k][s] for s in SPACES} for k in names}
    arrays = {k: record[k] for k in ("frame", "origin", "frame_c", "origin_c")}
    arrays["methods"] = np.array(names)
    arrays["embeddings"] = np.stack([record["methods"][k]["embedding"] for k in names])
    arrays["meta"] = np.str_(json.dumps(  # NaN stays NaN (json reads it back)
        {"fingerprint": fingerprint, "sources": {k: sources[k] for k in names},
         "numbers": numbers, "scales": record["scales"],
         "n_candidates": record["n_candidates"], "timings": record["timings"]}))
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    atomic_write_bytes(path, buf.getvalue())


def load_cell(path: Path, fingerprint: dict) -> dict | None:
    """A stored cell record if it exists and its sets a and c are this fingerprint's, else None
    (with "sources" and "legacy" as `evaluation.patchscores.load_cell`)."""
    z = patchscores.read_cell_file(path)
    if z is None:
        return None
    # A file of another layout (missing keys, lengths that disagree) is recomputed.
    try:
        meta = json.loads(str(z["meta"]))
        same = patchscores.same_patches(meta["fingerprint"], fingerprint, path, CELL_KEYS)
        if same is False:
            return None
        names = z["methods"].tolist()
        legacy = "sources" not in meta or same is None
        methods = {name: {**meta["numbers"][name], "embedding": emb}
                   for name, emb in zip(names, z["embeddings"], strict=True)}
        return {"frame": z["frame"], "origin": z["origin"], "frame_c": z["frame_c"],
                "origin_c": z["origin_c"], "scales": meta["scales"],
                "n_candidates": meta["n_candidates"], "timings": meta["timings"],
                "methods": methods, "legacy": legacy,
                "sources": (patchscores.legacy_sources(meta["fingerprint"], names)
                            if "sources" not in meta else meta["sources"])}
    except (KeyError, ValueError, TypeError):
        return None


def merge_records(old: dict, new: dict, order: list[str]) -> dict:
    """A stored cell record plus newly computed methods on the same sets a and c.

    Raises:
      ValueError: the sets or their layer scales differ (the sequences changed).
    """
    same = all(np.array_equal(old[k], new[k]) for k in ("frame", "origin", "frame_c",
                                                         "origin_c"))
    scales_ok = set(old["scales"]) == set(new["scales"]) and all(
        np.isclose(old["scales"][k], new["scales"][k], rtol=1e-4) for k in old["scales"])
    if not (same and scales_ok):
        raise ValueError("stored cell and new methods are not on the same sets a and c")
    methods = cell_lib.merge_methods(old["methods"], new["methods"], order)
    timings = cell_lib.merge_timings(old["timings"], new["timings"],
                                     ("features_s", "distances_s", "compare_s", "vgg_passes"))
    return {**old, "methods": methods, "timings": timings}


# --------------------------------------------------------------------------------------------
# Means over cells, the table
# --------------------------------------------------------------------------------------------


def group_of(cell: cell_lib.Cell) -> str:
    """The cell's group in `GROUPS`: the seen garment's cells, or the unseen garments'."""
    return GROUPS[0] if cell.garment == cell_lib.SEEN_GARMENT else GROUPS[1]


def mean_scores(records: list[dict]) -> dict:
    """Per method and space, the means over cells of C1, C2, DR and DR_signed (NaN-skipping),
    with the number of cells: {name: {space: {"c1", "c2", "dr", "dr_signed", "n_cells"}}}."""
    out = {}
    for name in records[0]["methods"]:
        out[name] = {}
        for space in SPACES:
            vals = {k: np.array([r["methods"][name][space][k] for r in records], np.float64)
                    for k in ("c1", "c2", "dr", "dr_signed")}
            ok = np.isfinite(vals["dr_signed"])
            out[name][space] = {k: float(v[ok].mean()) if ok.any() else float("nan")
                                for k, v in vals.items()}
            out[name][space]["n_cells"] = int(ok.sum())
    return out


def _fmt(d: dict, paper: bool = False) -> str:
    if not np.isfinite(d.get("dr_signed", float("nan"))):
        return "-"
    if paper:
        return f"{d['c1']:.3f} / {d['c2']:.3f} / {d['dr']:.1f} ({d['dr_signed']:+.1f})"
    return f"{d['c1']:.3f} / {d['c2']:.3f} / {d['dr_signed']:+.1f}"


def table_markdown(results: dict) -> str:
    """table.md: the paper's layout for the model (rows material x motion, columns garments) in
    both spaces; then every method per cell and the group means, in both spaces."""
    cells = results["cells"]
    cfg = results["config"]
    lines = [f"# Table 2: Chamfer distances to fine-simulation patches (model "
             f"`{results['model']}`)", "", results["sampling_text"], "",
             "C1 = CD(a, c), C2 = CD(b, c); DR = 100 |C1 - C2| / C1 (the paper's), signed "
             "DR = 100 (C1 - C2) / C1 (> 0: b is closer to the fine patches than the input).",
             ""]
    for space in SPACES:
        where = ("2D spectral embedding (the paper's)" if space == "embedded"
                 else "full Gram feature space")
        lines += [f"## Model, {where}: C1 / C2 / DR (signed DR)", "",
                  "| material | motion | " + " | ".join(
                      f"{g} ({'seen' if g == cell_lib.SEEN_GARMENT else 'unseen'})"
                      for g in cfg["garments"]) + " |",
                  "|---|---|" + "---|" * len(cfg["garments"])]
        for ma in cfg["materials"]:
            for mo in cfg["motions"]:
                row = [ma, f"{mo} ({'seen' if mo == cell_lib.SEEN_MOTION else 'unseen'})"]
                for g in cfg["garments"]:
                    key = cell_lib.Cell(g, mo, ma).key
                    row.append(_fmt(cells[key]["methods"][MODEL][space], paper=True)
                               if key in cells else "-")
                lines.append("| " + " | ".join(row) + " |")
        lines.append("")
    for space in SPACES:
        where = "2D spectral embedding" if space == "embedded" else "full Gram feature space"
        lines += [f"## All methods, {where}: C1 / C2 / signed DR", "",
                  "| cell | kind | " + " | ".join(results["methods"]) + " |",
                  "|---|---|" + "---|" * len(results["methods"])]
        for key, c in cells.items():
            lines.append(f"| {key} | {c['kind']} | " + " | ".join(
                _fmt(c["methods"][m][space]) for m in results["methods"]) + " |")
        for group, means in [*results["by_group"].items(), ("all", results["all"])]:
            n = means[MODEL][space]["n_cells"] if MODEL in means else ""
            lines.append(f"| mean, {group} | {n} cells | " + " | ".join(
                _fmt(means[m][space]) for m in results["methods"]) + " |")
        lines.append("")
    return "\n".join(lines)
