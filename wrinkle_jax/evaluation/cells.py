"""The evaluation tables' cells: a garment in a material doing a motion.

Which scene config a (garment, motion) cell uses, where its simulated sequences live and
simulating the missing ones (resumable, atomic writes), and evaluating every cell of a table
while reusing stored cells method by method (`run_cells`). Vertices are meters; times seconds.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
import zipfile
from collections.abc import Callable, Iterable
from pathlib import Path

import numpy as np

from wrinkle_jax import meshio
from wrinkle_jax.evaluation.suite import SEQUENCES, TABLE1_SEQUENCES, eta_text
from wrinkle_jax.fileio import NPZ_READ_ERRORS
from wrinkle_jax.sim import scenes, selfcollision

__all__ = ["GARMENTS", "GARMENT_BASE_SCENE", "GARMENT_SHORT", "MOTIONS", "SEEN_GARMENT",
           "SEEN_MOTION", "TABLE_MATERIALS", "TEST_SEED", "UNSEEN_GARMENT", "Cell",
           "add_sequence_args", "cell_sequences", "find_or_simulate", "load_first_frames",
           "merge_methods", "merge_timings", "run_cells", "scene_for", "sequence_file",
           "stored_frames", "stored_matches", "table_cells"]

# The scene each garment's cells are derived from (its pins, attachment and pre-roll).
GARMENT_BASE_SCENE = {"flared_skirt": "skirt_dance", "dress": "dress_dance", "cape": "cape_walk"}
GARMENT_SHORT = {"flared_skirt": "skirt", "dress": "dress", "cape": "cape"}
# The held-out data sets' scenes whose garment training never saw (the model card's groups).
UNSEEN_GARMENT = {"dress_dance", "cape_walk"}


def scene_for(garment: str, motion: str) -> scenes.SceneConfig:
    """The scene of a (garment, motion) cell: an existing `scenes.SCENES` entry when one has
    exactly this garment and motion (so its files are reused), else the garment's base scene
    (`GARMENT_BASE_SCENE`: pins, attachment, pre-roll) with the motion replaced, named
    "<short garment>_<motion>" (e.g. dress_walk, cape_dance)."""
    for sc in scenes.SCENES.values():
        if sc.garment == garment and sc.motion == motion:
            return sc
    if garment not in GARMENT_BASE_SCENE:
        raise scenes.SceneError(f"no base scene for garment {garment!r}; expected one of "
                                f"{', '.join(GARMENT_BASE_SCENE)}")
    base = scenes.get_scene(GARMENT_BASE_SCENE[garment])
    return dataclasses.replace(base, name=f"{GARMENT_SHORT[garment]}_{motion}", motion=motion,
                               test_only=True, description=f"{garment}, {motion} "
                               f"(derived from {base.name} for the evaluation suite)")


def sequence_file(root: Path, scene: str, material: str, resolution: str, seed: int) -> Path:
    """`<root>/<scene>/<material>_<resolution>_s<seed>.npz` (experiments.make_sequences)."""
    return Path(root) / scene / f"{material}_{resolution}_s{seed}.npz"


def stored_frames(path: Path) -> int:
    """Number of frames in a sequence `.npz` (read from the array header, not decompressed)."""
    with zipfile.ZipFile(path) as zf, zf.open("frames.npy") as fh:
        version = np.lib.format.read_magic(fh)
        read = (np.lib.format.read_array_header_1_0 if version == (1, 0)
                else np.lib.format.read_array_header_2_0)
        shape, _, _ = read(fh)
    return int(shape[0])


def stored_matches(path: Path, config: scenes.SceneConfig, material: str, seed: int,
                   frames: int, solver: tuple | None = None) -> bool:
    """Whether a stored simulation is this scene config, material and seed with >= frames,
    and, when `solver` = (substeps, SelfCollisionConfig or None) is given, was simulated with
    those settings (metadata "substeps" and "self_collision", read by
    `sim.selfcollision.recorded_config`)."""
    try:
        if stored_frames(path) < frames:
            return False
        with np.load(path, allow_pickle=False) as z:
            meta = json.loads(str(z["metadata"]))
    except NPZ_READ_ERRORS:
        return False
    same = (meta.get("scene_config") == config.to_json() and meta.get("material") == material
            and int(meta.get("seed", -1)) == seed)
    if solver is None or not same:
        return same
    substeps, self_collision = solver
    try:
        recorded = selfcollision.recorded_config(meta.get("self_collision"))
    except ValueError:  # a setting this code does not know: another recipe
        return False
    return meta.get("substeps") == substeps and recorded == self_collision


def find_or_simulate(config: scenes.SceneConfig, material: str, resolution: str, seed: int,
                     frames: int, reuse_roots: Iterable[Path], out_root: Path,
                     log: Callable[[str], None] = print) -> tuple[Path, dict]:
    """The path of a stored simulation of (config, material, resolution, seed) with at least
    `frames` frames, simulated with the data set's solver settings (`scenes.dataset_solver`:
    substeps, self-collision): the first match under `reuse_roots`, else `out_root`, else a
    new simulation with those settings written to `out_root` (atomically, so an interrupted
    run leaves no partial file and a rerun resumes). A file of other settings is never
    reused, so a table never mixes coarse inputs of two solver recipes.

    Returns:
      (path, info): info = {"source": "reused" | "simulated", "sim_s": wall seconds or 0}.
    """
    solver = scenes.dataset_solver(config, resolution)
    for root in (*reuse_roots, out_root):
        p = sequence_file(root, config.name, material, resolution, seed)
        if p.exists() and stored_matches(p, config, material, seed, frames, solver):
            return p, {"source": "reused", "sim_s": 0.0}
    p = sequence_file(out_root, config.name, material, resolution, seed)
    log(f"simulating {config.name} {material} {resolution} seed {seed}, {frames} frames -> {p}")
    t0 = time.perf_counter()
    seq = scenes.simulate(config, material, resolution, frames=frames, seed=seed,
                          substeps=solver[0], self_collision=solver[1])
    scenes.save_simulation(p, seq)
    wall = time.perf_counter() - t0
    log(f"  done in {wall:.0f} s ({seq.metadata['ms_per_frame']:.0f} ms/frame)")
    return p, {"source": "simulated", "sim_s": wall}


# Table 1's cells (paper Table 1: Dress A seen, Dress B and C unseen; Motion 1 seen, 2 unseen).
GARMENTS = ("flared_skirt", "dress", "cape")  # the first is seen in training
TABLE_MATERIALS = ("silk_charmeuse", "denim_light")
MOTIONS = ("dance", "walk")  # the first is seen in training
SEEN_GARMENT, SEEN_MOTION = GARMENTS[0], MOTIONS[0]
TEST_SEED = scenes.TEST_SEED  # training scenes use seed 0: an unseen performance of every motion


@dataclasses.dataclass(frozen=True)
class Cell:
    """One sequence pair of Table 1: a garment in a material doing a motion."""

    garment: str
    motion: str
    material: str

    @property
    def scene(self) -> scenes.SceneConfig:
        return scene_for(self.garment, self.motion)

    @property
    def key(self) -> str:
        return f"{self.scene.name}/{self.material}"

    @property
    def kind(self) -> str:
        """'seen garment, seen motion' | 'seen garment, unseen motion' | 'unseen garment'."""
        if self.garment != SEEN_GARMENT:
            return "unseen garment"
        return "seen garment, " + ("seen motion" if self.motion == SEEN_MOTION
                                   else "unseen motion")

    @property
    def patch_seed(self) -> list[int]:
        """Stable seed entropy of the cell's patch draws (Python's hash() is salted per
        process); with the sampling seed and the frame it fixes Table 1's patches, which
        Table 2 and the stride ablation reuse."""
        return [int.from_bytes(self.key.encode(), "little") % (2**32)]


def table_cells(garments=GARMENTS, materials=TABLE_MATERIALS, motions=MOTIONS) -> list[Cell]:
    """Cells in table order: material, then motion, then garment."""
    return [Cell(g, mo, ma) for ma in materials for mo in motions for g in garments]


def cell_sequences(cell: Cell, frames: int, seed: int = TEST_SEED,
                   reuse_roots: Iterable[Path] = (SEQUENCES,), out_root: Path = TABLE1_SEQUENCES,
                   log: Callable[[str], None] = print) -> dict:
    """Paths of the fine and the coarse simulation of a cell (simulated if missing).

    Returns:
      {"fine": Path, "coarse": Path, "fine_info": {...}, "coarse_info": {...}} (see
      `find_or_simulate`).
    """
    out = {}
    for res in ("fine", "coarse"):
        p, info = find_or_simulate(cell.scene, cell.material, res, seed, frames, reuse_roots,
                                   out_root, log)
        out[res], out[f"{res}_info"] = p, info
    return out


def merge_methods(old: dict, new: dict, order: list[str]) -> dict:
    """Union of two per-method maps (`new` wins), methods in `order`, then any others stored."""
    both = {**old, **new}
    return {k: both[k] for k in [*order, *[k for k in both if k not in order]]}


def merge_timings(old: dict, new: dict, summed: Iterable[str]) -> dict:
    """A stored cell's timings plus a rescoring run's: per-method seconds merged, `summed`
    counters (seconds, VGG passes) added, everything else kept from `old`."""
    out = {**old, "methods_s": {**old.get("methods_s", {}), **new["methods_s"]}}
    for k in summed:
        out[k] = old.get(k, 0) + new.get(k, 0)
    return out


def run_cells(cells: list[Cell], methods: dict, sources: dict[str, str] | None, *,
              path_of: Callable[[Cell], Path], fingerprint_of: Callable[[Cell], dict],
              load: Callable, save: Callable, evaluate: Callable, merge: Callable,
              field: str, units: Callable[[list[str]], int], unit: str,
              fresh: bool = False, log: Callable[[str], None] = print) -> dict[str, dict]:
    """Evaluate (or reload) every cell of a table, reusing stored cells method by method.

    A stored cell (`load(path, fingerprint)` -> dict with `field`, "sources", "legacy",
    "timings", or None) is reused for every method whose stored source equals `sources[name]`
    (default: the name); the other methods are evaluated on the same patches
    (`evaluate(cell, names, progress)`), merged in (`merge(old, new, order)`, ValueError when
    the patches differ: then every method is evaluated again) and the cell saved
    (`save(path, result, fingerprint, sources)`). Legacy files (written before sources were
    stored) are rewritten in place when fully reused. Progress: `progress(k, what=None)` adds
    k of a cell's `units(names)` work units (named `unit`) and logs an ETA.

    Returns:
      cell key -> result with `field` restricted to `methods` (timings also hold "cell_s").
    """
    sources = {k: k for k in methods} if sources is None else sources
    cached = {c.key: None if fresh else load(path_of(c), fingerprint_of(c)) for c in cells}

    def missing(c):
        got = cached[c.key]
        if got is None:
            return list(methods)
        return [m for m in methods if m not in got[field] or got["sources"].get(m) != sources[m]]

    todo = {c.key: missing(c) for c in cells}
    total = sum(units(v) for v in todo.values() if v)
    done = [0]
    t_start = time.perf_counter()
    results = {}
    for i, cell in enumerate(cells):
        tag = f"[{i + 1}/{len(cells)}] {cell.key}"
        path, old, names = path_of(cell), cached[cell.key], todo[cell.key]
        if not names:
            log(f"{tag}: reusing {path}")
            if old["legacy"]:  # upgrade the file in place (sources stored from now on)
                save(path, old, fingerprint_of(cell), old["sources"])
            results[cell.key] = {**old, field: {k: old[field][k] for k in methods}}
            continue
        first, n_units = done[0], units(names)

        def progress(k, what=None, tag=tag, first=first, n_units=n_units):
            done[0] += k
            elapsed = time.perf_counter() - t_start
            log(f"{tag}: {what + ', ' if what else ''}{done[0] - first}/{n_units} {unit}, "
                f"{elapsed / 60:.1f} min, {eta_text(done[0], total, elapsed)}")

        if old is not None:
            log(f"{tag}: adding {', '.join(names)} to the stored cell")
        t0 = time.perf_counter()
        res = evaluate(cell, names, progress)
        if old is not None:
            try:
                res = merge(old, res, list(methods))
                res["timings"]["cell_s"] = (old["timings"].get("cell_s", 0.0)
                                            + time.perf_counter() - t0)
            except ValueError:
                log(f"{tag}: the stored patches differ; evaluating every method again")
                res, old = evaluate(cell, list(methods), None), None
        if old is None:
            res["timings"]["cell_s"] = time.perf_counter() - t0
        save(path, res, fingerprint_of(cell), {**({} if old is None else old["sources"]),
                                              **sources})
        results[cell.key] = {**res, field: {k: res[field][k] for k in methods}}
    return results


def load_first_frames(path: Path, frames: int) -> meshio.GarmentSequence:
    """Load a sequence and keep its first `frames` frames (error if it has fewer)."""
    seq = meshio.load_sequence(path)
    if len(seq) < frames:
        raise ValueError(f"{path}: {len(seq)} frames, {frames} needed")
    return dataclasses.replace(seq, frames=np.ascontiguousarray(seq.frames[:frames]))


def add_sequence_args(ap: argparse.ArgumentParser) -> None:
    """The flags that choose the evaluation cells and where their simulations live (shared by
    Tables 1 and 2, the stride ablation and the flicker study)."""
    ap.add_argument("--garments", default=",".join(GARMENTS))
    ap.add_argument("--materials", default=",".join(TABLE_MATERIALS))
    ap.add_argument("--motions", default=",".join(MOTIONS))
    ap.add_argument("--sequences", default=str(SEQUENCES),
                    help="folder of existing simulations to reuse")
    ap.add_argument("--sim-out", default=str(TABLE1_SEQUENCES),
                    help="folder for the simulations made here (shared by the suite)")
