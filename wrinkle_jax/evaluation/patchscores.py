"""Scoring methods on aligned patches of the evaluation cells (paper Table 1's measurement).

Per cell (a fine and a coarse simulation of one garment, material and motion), `evaluate_cell`
bakes both on one grid, draws patches (`Sampling`), runs every method on them and keeps each
method's style loss against the fine map (`gram.method_losses`; scores by
`scores.scores_from_losses`). A cell's losses are stored (`save_cell`, `load_cell`) with the
fingerprint of its patches and the source of every method, so a rerun (`run`) scores only
methods it has not stored. `add_cell_args` and `setup_from_args` are the flags and the setup
the table scripts share (model, cells, sequences, baselines). Vertices are meters; patches
(N, S, S, 3) in the RGB form with (N, S, S, 1) masks; times seconds.
"""

from __future__ import annotations

import dataclasses
import io
import json
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from wrinkle_jax import MATERIALS, evaluation, material_index, patches
from wrinkle_jax import enhancer as enhancer_lib
from wrinkle_jax.evaluation import cells as cell_lib
from wrinkle_jax.evaluation import gram, patchsets, suite
from wrinkle_jax.evaluation import methods as method_lib
from wrinkle_jax.fileio import NPZ_READ_ERRORS, atomic_write_bytes

__all__ = ["CELL_KEYS", "MODEL", "WRONG", "Sampling", "Setup", "add_cell_args", "cell_part",
           "cell_path", "cell_scores", "evaluate_cell", "frames_text", "legacy_sources",
           "load_cell", "merge_cell", "pooled_scores", "run", "same_patches", "save_cell",
           "setup_from_args", "summary"]

MODEL = "model"
WRONG = "model, wrong material"


@dataclasses.dataclass(frozen=True)
class Sampling:
    """Which patches are scored (static).

    Attributes:
      frames: frames used per sequence (the first `frames`).
      frame_stride: score every k-th of them (frame 0, k, 2k, ...).
      patches_per_frame: patches drawn per scored frame (all candidates if fewer).
      patch_size, texel_size: from the model (texels; meters per texel).
      grid_stride: candidate grid step, texels (None: half a patch).
      min_coverage: minimum fraction of texels covered by both meshes in a candidate patch.
      seed: seeds the patch draw (with the cell and the frame index).
      score_batch: patches per VGG call.
    """

    frames: int = 200
    frame_stride: int = 10
    patches_per_frame: int = 8
    patch_size: int = 128
    texel_size: float = 0.002
    grid_stride: int | None = None
    min_coverage: float = 0.5
    seed: int = 0
    score_batch: int = 8

    @property
    def frame_indices(self) -> list[int]:
        return list(range(0, self.frames, self.frame_stride))


def evaluate_cell(fine, coarse, material: str, methods: dict[str, Callable], vgg_params,
                  sampling: Sampling, cell_seed=(0,),
                  progress: Callable[[int], None] | None = None) -> dict:
    """Score every method on the same aligned patches of one fine/coarse sequence pair.

    Args:
      fine, coarse: `GarmentSequence`s of the same pattern, scene, material and seed (frames
        (T, V, 3) meters; T >= max(sampling.frame_indices) + 1).
      material: material name (passed to the model method through `PatchSet.material_id`).
      methods: name -> (PatchSet) -> (K, S, S, 3) RGB-form outputs.
      vgg_params: `vgg.load_vgg19()` (or a small VGG in tests).
      sampling: `Sampling`.
      cell_seed: extra seed entropy for the patch draw (e.g. the cell).
      progress: called with 1 after each scored frame.
    Returns:
      {"frame": (N,) int32 frame of every patch, "origin": (N, 2) int32, "coverage": (N,),
       "loss_input": (N,), "loss": {name: (N,)}, "n_candidates": int,
       "timings": {"bake_s", "methods_s": {name: s}, "score_s", "vgg_passes"}}.
    """
    size = sampling.patch_size
    stride = size // 2 if sampling.grid_stride is None else sampling.grid_stride
    pair = patchsets.aligned_pair(fine.garment, coarse.garment, sampling.texel_size)
    mask = np.asarray(patches.pad_to_patch(pair.mask, size)[0])
    cand, cov = patchsets.candidate_origins(mask, size, stride, sampling.min_coverage)
    if not len(cand):
        raise ValueError(f"no {size}x{size} patch reaches {sampling.min_coverage:.0%} coverage "
                         "by both meshes")
    cov_of = {tuple(o): c for o, c in zip(cand.tolist(), cov.tolist(), strict=True)}
    mid = material_index(material)
    frames, origins, covs = [], [], []
    loss_in, loss = [], {k: [] for k in methods}
    timings = {"bake_s": 0.0, "methods_s": {k: 0.0 for k in methods}, "score_s": 0.0}
    counter: dict = {}
    for t in sampling.frame_indices:
        sel = patchsets.choose_origins(cand, sampling.patches_per_frame,
                                       (sampling.seed, *cell_seed, t))
        t0 = time.perf_counter()
        ps = patchsets.aligned_patches(pair, fine.frames[t], coarse.frames[t], sel, size, mid)
        timings["bake_s"] += time.perf_counter() - t0
        outs = {}
        for name, fn in methods.items():
            t0 = time.perf_counter()
            outs[name] = fn(ps)
            timings["methods_s"][name] += time.perf_counter() - t0
        t0 = time.perf_counter()
        got = gram.method_losses(vgg_params, ps.input, ps.target, ps.mask, outs,
                                 batch_size=sampling.score_batch, counter=counter)
        timings["score_s"] += time.perf_counter() - t0
        loss_in.append(got["input"])
        for k in methods:
            loss[k].append(got[k])
        frames += [t] * len(sel)
        origins.append(sel)
        covs += [cov_of[tuple(o)] for o in sel.tolist()]
        if progress is not None:
            progress(1)
    timings["vgg_passes"] = counter.get("vgg_passes", 0)
    return {"frame": np.asarray(frames, np.int32), "origin": np.concatenate(origins),
            "coverage": np.asarray(covs, np.float32), "loss_input": np.concatenate(loss_in),
            "loss": {k: np.concatenate(v) for k, v in loss.items()},
            "n_candidates": int(len(cand)), "timings": timings}


def summary(scores: dict) -> dict:
    """`evaluation.summarize(scores)["all"]` plus the medians of both scores."""
    out = evaluation.summarize(scores)["all"]
    v = scores["valid"]
    if v.any():
        out["improvement_median"] = float(np.median(scores["improvement"][v]))
        out["signed_median"] = float(np.median(scores["improvement_signed"][v]))
    return out


def cell_scores(cell_result: dict) -> dict[str, dict]:
    """Per-method score dicts (`evaluation.scores_from_losses``) of one evaluated cell."""
    return {k: evaluation.scores_from_losses(cell_result["loss_input"], v)
            for k, v in cell_result["loss"].items()}


def paired_against(pooled: dict[str, dict], methods, references, seed: int = 0) -> dict:
    """Each method's signed per-patch score against each reference on the same patches
    (`evaluation.paired_difference`: median of the differences with a 95 % bootstrap interval,
    means beside), over the patches valid for both. pooled: `pooled_scores` output; names
    missing from it are skipped. Returns {method: {reference: paired difference}}."""
    out = {}
    for m in methods:
        if m not in pooled:
            continue
        out[m] = {}
        for r in references:
            if r in pooled and r != m:
                a, b = pooled[m], pooled[r]
                out[m][r] = evaluation.paired_difference(
                    a["improvement_signed"], b["improvement_signed"], a["valid"] & b["valid"],
                    seed=seed)
    return out


def pooled_scores(results: list[dict]) -> dict[str, dict]:
    """Scores of several cells pooled patch by patch (each cell's eps kept)."""
    per = [cell_scores(r) for r in results]
    return {k: {f: np.concatenate([p[k][f] for p in per]) for f in per[0][k]} for k in per[0]}


# --------------------------------------------------------------------------------------------
# Cell files (resume)
# --------------------------------------------------------------------------------------------


def cell_path(out: Path, cell: cell_lib.Cell) -> Path:
    return out / "cells" / f"{cell.scene.name}__{cell.material}.npz"


# What defines a cell's patches (sampling, sequence files and their contents); each method's
# losses are tagged with a source string instead, so a rerun with another method set scores
# only the new methods.
CELL_KEYS = ("sampling", "sequences", "simulations")


def same_patches(stored: dict, wanted: dict, path: Path,
                 keys: tuple[str, ...] = CELL_KEYS) -> bool | None:
    """Whether the cell stored at `path` with fingerprint `stored` has `wanted`'s patches:
    True; False; or None for a cell stored before the simulations' digests were recorded
    that agrees in every other key and is newer than both sequence files it names (so it was
    scored from these files: reuse it, and store it again with the digests). A sequence
    simulated again after the cell was scored makes it False."""
    a, b = cell_part(stored, keys), cell_part(wanted, keys)
    if a == b:
        return True
    if ("simulations" not in keys or a.get("simulations") is not None
            or not isinstance(b.get("sequences"), dict)):
        return False
    if {**a, "simulations": b.get("simulations")} != b:
        return False
    files = [suite.ROOT / p for p in b["sequences"].values()]  # portable: root-relative
    try:
        newest = max(f.stat().st_mtime for f in files)
        return None if path.stat().st_mtime > newest else False
    except OSError:
        return False


def save_cell(path: Path, result: dict, fingerprint: dict, sources: dict[str, str]) -> None:
    """Store one evaluated cell atomically: arrays, the JSON fingerprint of its patches and
    the source of every method's losses (`sources`: name -> string)."""
    arrays = {"frame": result["frame"], "origin": result["origin"],
              "coverage": result["coverage"], "loss_input": result["loss_input"],
              "methods": np.array(list(result["loss"])),
              "losses": np.stack([result["loss"][k] for k in result["loss"]]),
              "meta": np.str_(json.dumps({"fingerprint": fingerprint,
                                          "sources": {k: sources[k] for k in result["loss"]},
                                          "n_candidates": result["n_candidates"],
                                          "timings": result["timings"]}))}
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    atomic_write_bytes(path, buf.getvalue())


def cell_part(fingerprint: dict, keys: tuple[str, ...] = CELL_KEYS) -> dict:
    """The part of a fingerprint that defines the patches, with portable sequence paths."""
    fp = json.loads(json.dumps({k: fingerprint.get(k) for k in keys}))
    if isinstance(fp.get("sequences"), dict):
        fp["sequences"] = {k: suite.portable_path(v) for k, v in fp["sequences"].items()}
    return fp


def legacy_sources(fingerprint: dict, methods: list[str]) -> dict[str, str]:
    """Sources of a cell file written before sources were stored (model methods named by the
    model file's path and mtime): the model's digest if that file is unchanged since."""
    model = fingerprint.get("model")
    src = None
    if model and Path(model).exists() and Path(model).stat().st_mtime == fingerprint.get(
            "model_mtime"):
        src = f"model {suite.file_digest(model)}"
    out = {}
    for m in methods:
        if m == MODEL:
            out[m] = src or "unknown model"
        elif m == WRONG:
            out[m] = f"{src} wrong material" if src else "unknown model"
        else:
            out[m] = m
    return out


def load_cell(path: Path, fingerprint: dict) -> dict | None:
    """A stored cell if it exists and its patches are this fingerprint's, else None.

    The result also holds "sources" (name -> source of its losses) and "legacy" (True for a
    file written before sources were stored)."""
    z = read_cell_file(path)
    if z is None:
        return None
    # A file of another layout (missing keys, lengths that disagree) is recomputed.
    try:
        meta = json.loads(str(z["meta"]))
        same = same_patches(meta["fingerprint"], fingerprint, path)
        if same is False:
            return None
        names = z["methods"].tolist()
        legacy = "sources" not in meta or same is None
        sources = (legacy_sources(meta["fingerprint"], names) if "sources" not in meta
                   else meta["sources"])
        return {"frame": z["frame"], "origin": z["origin"], "coverage": z["coverage"],
                "loss_input": z["loss_input"],
                "loss": dict(zip(names, z["losses"], strict=True)),
                "n_candidates": meta["n_candidates"], "timings": meta["timings"],
                "sources": sources, "legacy": legacy}
    except (KeyError, ValueError, TypeError):
        return None


def read_cell_file(path: Path) -> dict[str, np.ndarray] | None:
    """Every member of a stored cell file (name -> array), or None if it is missing or damaged
    (`fileio.NPZ_READ_ERRORS`: the cell is then recomputed)."""
    try:
        with np.load(path, allow_pickle=False) as z:
            return {k: z[k] for k in z.files}
    except NPZ_READ_ERRORS:
        return None


def cell_simulations(cell_dir: Path) -> dict[str, dict | None]:
    """The simulation digests each stored cell file (`<cell_dir>/*.npz`, Table 1/2 form) was
    scored on: {file stem: {"fine": digest, "coarse": digest}, or None where the file records
    none (written before the digests were kept) or cannot be read}."""
    out = {}
    for path in sorted(Path(cell_dir).glob("*.npz")):
        z = read_cell_file(path)
        try:
            out[path.stem] = json.loads(str(z["meta"]))["fingerprint"].get("simulations")
        except (TypeError, KeyError, ValueError):  # unreadable, or no meta / fingerprint
            out[path.stem] = None
    return out


def same_simulations(reference_dir: Path, cell_dir: Path) -> dict[str, list[str]]:
    """Which cells of `cell_dir` were scored on the same simulations as the cell of the same
    name in `reference_dir`: {"same", "different", "unrecorded" (either side records no
    digests), "unmatched" (no such cell in the reference)}, each a sorted list of stems."""
    ref, got = cell_simulations(reference_dir), cell_simulations(cell_dir)
    out = {"same": [], "different": [], "unrecorded": [], "unmatched": []}
    for stem, sims in got.items():
        if stem not in ref:
            out["unmatched"].append(stem)
        elif sims is None or ref[stem] is None:
            out["unrecorded"].append(stem)
        else:
            out["same" if sims == ref[stem] else "different"].append(stem)
    return out


def merge_cell(cached: dict, new: dict, order: list[str]) -> dict:
    """A stored cell plus newly scored methods on the same patches (`new` from
    `evaluate_cell` with only those methods); methods in `order`, then any others stored.

    Raises:
      ValueError: the patches or the input's losses differ (the sequences changed).
    """
    if (not np.array_equal(cached["frame"], new["frame"])
            or not np.array_equal(cached["origin"], new["origin"])
            or not np.allclose(cached["loss_input"], new["loss_input"], rtol=1e-4)):
        raise ValueError("stored cell and rescored methods are not on the same patches")
    loss = cell_lib.merge_methods(cached["loss"], new["loss"], order)
    timings = cell_lib.merge_timings(cached["timings"], new["timings"], ("score_s", "vgg_passes"))
    return {**cached, "loss": loss, "timings": timings}


def frames_text(idx: list[int]) -> str:
    """'0, 10, 20, ..., 190' (or the whole list when short)."""
    if len(idx) <= 4:
        return ", ".join(map(str, idx))
    return f"{idx[0]}, {idx[1]}, {idx[2]}, ..., {idx[-1]}"


def run(cells: list[cell_lib.Cell], sequences: dict, methods: dict, vgg_params, sampling: Sampling,
        out: Path, fingerprint_of: Callable[[cell_lib.Cell], dict], fresh: bool = False,
        log: Callable[[str], None] = print, sources: dict[str, str] | None = None
        ) -> dict[str, dict]:
    """Evaluate (or reload from `<out>/cells/`) every cell, printing progress and an ETA.

    Stored cells are reused method by method (`evaluation.cells.run_cells`): a method whose stored
    source equals `sources[name]` (default: the name) is not rescored; a new one costs 2 VGG
    passes per patch (the input and target Grams) plus its own.

    Returns:
      cell key -> `evaluate_cell` result restricted to `methods` (timings also hold "cell_s").
    """
    def evaluate(cell, names, progress):
        fine = cell_lib.load_first_frames(sequences[cell.key]["fine"], sampling.frames)
        coarse = cell_lib.load_first_frames(sequences[cell.key]["coarse"], sampling.frames)
        res = evaluate_cell(fine, coarse, cell.material, {k: methods[k] for k in names},
                            vgg_params, sampling, cell.patch_seed, progress)
        sig = {k: round(float(np.mean(s["improvement_signed"][s["valid"]])), 1)
               for k, s in cell_scores(res).items() if s["valid"].any()}
        log(f"{cell.key}: signed means {sig}")
        return res

    return cell_lib.run_cells(cells, methods, sources, path_of=lambda c: cell_path(out, c),
                              fingerprint_of=fingerprint_of, load=load_cell, save=save_cell,
                              evaluate=evaluate, merge=merge_cell, field="loss",
                              units=lambda names: len(sampling.frame_indices), unit="frames",
                              fresh=fresh, log=log)


# --------------------------------------------------------------------------------------------
# Setup shared with Table 2 and the stride ablation
# --------------------------------------------------------------------------------------------


def add_cell_args(ap, out_default: Path, frame_stride_help: str = "score every k-th frame"
                  ) -> None:
    """The flags that choose the model, the cells, their sequences and the patch sampling."""
    ap.add_argument("--model", default=str(enhancer_lib.DEFAULT_PATH),
                    help="enhancer .npz (default: the shipped model)")
    ap.add_argument("--frames", type=int, default=200, help="frames per sequence")
    ap.add_argument("--frame-stride", type=int, default=10, help=frame_stride_help)
    ap.add_argument("--patches-per-frame", type=int, default=8)
    ap.add_argument("--min-coverage", type=float, default=0.5,
                    help="minimum fraction of patch texels covered by both meshes")
    ap.add_argument("--seed", type=int, default=0, help="seed of the patch draw")
    cell_lib.add_sequence_args(ap)
    ap.add_argument("--out", default=str(out_default))
    ap.add_argument("--fresh", action="store_true", help="ignore stored cells and recompute")
    ap.add_argument("--extra", action="append", default=[], metavar="NAME=PATH",
                    help="also evaluate this enhancer file as method NAME (repeatable; e.g. "
                         "patchgan=experiments/results/patchgan/patchgan.npz)")


@dataclasses.dataclass
class Setup:
    """What a table script evaluates: model, sampling, cells, their sequence files, methods.

    Attributes:
      enh: the model; sampling: `Sampling`; cells: `evaluation.cells.Cell`s.
      sequences: cell key -> `evaluation.cells.cell_sequences` (fine/coarse paths and info).
      sim_s: seconds spent finding or simulating the sequences.
      methods: name -> (PatchSet) -> outputs; sources: name -> source of its outputs.
      unsharp: blur order -> (sigma, amount, source); net_timings: the model's timings.
    """

    enh: enhancer_lib.Enhancer
    sampling: Sampling
    cells: list
    sequences: dict
    sim_s: float
    methods: dict
    sources: dict
    unsharp: dict
    net_timings: dict

    @property
    def unsharp_text(self) -> str:
        return "; ".join(f"order {o}: {u[2]}" for o, u in self.unsharp.items())

    def record(self, model_path) -> dict:
        """The results' header both tables write: the model (portable path, config, flat meta),
        the methods, their output sources and the unsharp settings."""
        return {
            "model": suite.portable_path(model_path), "model_config": self.enh.config.to_json(),
            "model_meta": {k: v for k, v in self.enh.meta.items()
                           if not isinstance(v, dict | list)},
            "methods": list(self.methods), "method_sources": self.sources,
            "unsharp": {f"order {o}": {"sigma": u[0], "amount": u[1], "source": u[2]}
                        for o, u in self.unsharp.items()}}

    def fingerprint_of(self, cell: cell_lib.Cell, **extra) -> dict:
        """What defines the cell's patches: sampling, sequence files (portable) and their
        contents' digests (a sequence simulated again at the same path is another cell),
        `extra`."""
        files = {r: self.sequences[cell.key][r] for r in ("fine", "coarse")}
        return {"sampling": dataclasses.asdict(self.sampling), **extra,
                "sequences": {r: suite.portable_path(p) for r, p in files.items()},
                "simulations": {r: suite.file_digest(p) for r, p in files.items()}}


def setup_from_args(ap, args, min_frame_stride: int = 1, wrong_material: bool = False,
                    with_methods: bool = True) -> Setup:
    """Validate the `add_cell_args` flags, load the model, find or simulate the sequences and
    build the methods: the baselines, the model (and its wrong-material twin), --extra."""
    if args.frames < 1 or args.patches_per_frame < 1:
        ap.error("--frames and --patches-per-frame must be >= 1")
    if args.frame_stride < min_frame_stride:
        ap.error(f"--frame-stride must be >= {min_frame_stride}")
    for name in args.materials.split(","):
        if name not in MATERIALS:
            ap.error(f"unknown material {name!r}")
    enh = suite.load_model_or_usage_error(ap, args.model)
    sampling = Sampling(frames=args.frames, frame_stride=args.frame_stride,
                        patches_per_frame=args.patches_per_frame,
                        patch_size=enh.config.patch_size, texel_size=enh.config.texel_size,
                        min_coverage=args.min_coverage, seed=args.seed,
                        score_batch=min(args.patches_per_frame, 16))
    cells = cell_lib.table_cells(args.garments.split(","), args.materials.split(","),
                                 args.motions.split(","))
    t0 = time.perf_counter()  # simulate what is missing (resumable)
    sequences = {c.key: cell_lib.cell_sequences(c, args.frames, cell_lib.TEST_SEED,
                                                (Path(args.sequences),), Path(args.sim_out))
                 for c in cells}
    sim_s = time.perf_counter() - t0
    methods, sources, unsharp, net_timings = {}, {}, {}, {}
    if with_methods:
        unsharp = {o: method_lib.unsharp_setting(order=o) for o in (0, 1)}
        methods = method_lib.baseline_methods({o: u[:2] for o, u in unsharp.items()})
        methods[MODEL] = method_lib.enhancer_method(enh, batch_size=sampling.score_batch,
                                                    timings=net_timings)
        model_src = f"model {suite.file_digest(args.model)}"
        sources = {k: k for k in methods} | {MODEL: model_src}
        if wrong_material:
            # Paper Fig. 10: the right patches, the other table material's CIN parameters.
            methods[WRONG] = method_lib.enhancer_method(enh, batch_size=sampling.score_batch,
                                                        material_of=method_lib.wrong_material)
            sources[WRONG] = f"{model_src} wrong material"
        try:
            extra, extra_src = method_lib.model_methods(args.extra, sampling.score_batch)
        except (ValueError, enhancer_lib.EnhancerError) as err:
            ap.error(f"--extra: {err}")
        methods.update(extra)
        sources.update(extra_src)
    return Setup(enh, sampling, cells, sequences, sim_s, methods, sources, unsharp,
                 net_timings)
