"""Shared pieces of the evaluation scripts (`experiments.table1`, `.temporal`, `.timing`).

    sequences   which scene config a (garment, motion) cell uses, where its simulated sequences
                live, and simulating the missing ones (resumable, atomic writes)
    alignment   baking a coarse and a fine simulation of the same pattern onto ONE pixel grid,
                so that a patch origin means the same cloth in both maps
    scoring     the improvement score of several methods on the same patches, with the VGG
                Gram matrices of the input and the target computed once and reused by every
                method (`method_losses` + `scores_from_losses` == `evaluation.score_patches`)
    flicker     mean angular change of a normal map between consecutive frames
    results     machine information and atomic JSON writing

Conventions (as in the library): normal maps are float32 (H, W, 3) unit vectors in [-1, 1];
patches are in the RGB form (n + 1) / 2 in [0, 1], NHWC, with a (N, S, S, 1) float32 {0, 1}
mask; vertices are meters; times are seconds unless a name says ms.
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import io
import json
import math
import os
import platform
import sys
import time
import zipfile
from collections.abc import Callable, Iterable
from pathlib import Path

import cv2
import jax
import jax.numpy as jnp
import numpy as np

from wrinkle_jax import MATERIALS, evaluation, material_index, meshio
from wrinkle_jax import enhancer as enhancer_lib
from wrinkle_jax.fileio import atomic_write_bytes, atomic_write_text
from wrinkle_jax.nn import losses, vgg
from wrinkle_jax.sim import scenes

ROOT = Path(__file__).resolve().parents[1]
SEQUENCES = ROOT / "data" / "sequences"  # experiments.make_sequences output
TABLE1_SEQUENCES = ROOT / "data" / "table1_sequences"  # sequences simulated for the suite
RESULTS = ROOT / "experiments" / "results"
MODEL_CARD_RESULTS = RESULTS / "model_card" / "results.json"

# The scene each garment's cells are derived from (its pins, attachment and pre-roll).
GARMENT_BASE_SCENE = {"flared_skirt": "skirt_dance", "dress": "dress_dance", "cape": "cape_walk"}
GARMENT_SHORT = {"flared_skirt": "skirt", "dress": "dress", "cape": "cape"}
# Unsharp masking when no sweep result exists (the model card's sweep best on training patches).
DEFAULT_UNSHARP = (8.0, 1.0)


# --------------------------------------------------------------------------------------------
# Results
# --------------------------------------------------------------------------------------------


def machine_info() -> dict:
    """Platform, CPU count, 1-minute load average and library versions (JSON-ready)."""
    try:
        load = round(os.getloadavg()[0], 2)
    except OSError:
        load = None
    return {"platform": platform.platform(), "processor": platform.processor() or None,
            "cpu_count": os.cpu_count(), "load_avg_1min": load,
            "python": sys.version.split()[0], "jax": jax.__version__,
            "jax_backend": jax.default_backend(), "numpy": np.__version__,
            "opencv": cv2.__version__}


def file_digest(path: str | os.PathLike) -> str:
    """'sha256:<first 16 hex digits>' of a file's bytes: identifies a model across clones (its
    mtime does not)."""
    import hashlib

    return "sha256:" + hashlib.sha256(Path(path).read_bytes()).hexdigest()[:16]


def portable_path(path: str | os.PathLike) -> str:
    """`path` relative to the project root when it lies under it (fingerprints then survive a
    clone to another folder), else absolute."""
    p = Path(path).resolve()
    try:
        return str(p.relative_to(ROOT))
    except ValueError:
        return str(p)


def model_methods(specs: list[str], batch_size: int) -> tuple[dict, dict]:
    """Extra models as methods, from "NAME=PATH" specs (e.g. a trained baseline).

    A one-material model (e.g. the PatchGAN baseline's "any") is told material 0; others the
    patch set's material by name. Returns (methods, sources): name -> method, and name -> a
    source string (file digest) that identifies its outputs.
    """
    methods, sources = {}, {}
    for spec in specs:
        name, sep, path = spec.partition("=")
        if not sep or not name or not path:
            raise ValueError(f"expected NAME=PATH, got {spec!r}")
        enh = enhancer_lib.load_enhancer(path)
        if len(enh.config.materials) == 1:
            def material_of(_):
                return 0
        else:
            def material_of(i, enh=enh):
                return enh.config.material_id(MATERIALS[i])
        methods[name] = enhancer_method(enh, batch_size=batch_size, material_of=material_of)
        sources[name] = f"model {file_digest(path)}"
    return methods, sources


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


# --------------------------------------------------------------------------------------------
# Sequences
# --------------------------------------------------------------------------------------------


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
                   frames: int) -> bool:
    """Whether a stored simulation is this scene config, material and seed with >= frames."""
    try:
        if stored_frames(path) < frames:
            return False
        with np.load(path, allow_pickle=False) as z:
            meta = json.loads(str(z["metadata"]))
    except (OSError, KeyError, ValueError, zipfile.BadZipFile):
        return False
    return (meta.get("scene_config") == config.to_json() and meta.get("material") == material
            and int(meta.get("seed", -1)) == seed)


def find_or_simulate(config: scenes.SceneConfig, material: str, resolution: str, seed: int,
                     frames: int, reuse_roots: Iterable[Path], out_root: Path,
                     log: Callable[[str], None] = print) -> tuple[Path, dict]:
    """The path of a stored simulation of (config, material, resolution, seed) with at least
    `frames` frames: the first match under `reuse_roots`, else `out_root`, else a new
    simulation written to `out_root` (atomically, so an interrupted run leaves no partial
    file and a rerun resumes).

    Returns:
      (path, info): info = {"source": "reused" | "simulated", "sim_s": wall seconds or 0}.
    """
    for root in (*reuse_roots, out_root):
        p = sequence_file(root, config.name, material, resolution, seed)
        if p.exists() and stored_matches(p, config, material, seed, frames):
            return p, {"source": "reused", "sim_s": 0.0}
    p = sequence_file(out_root, config.name, material, resolution, seed)
    log(f"simulating {config.name} {material} {resolution} seed {seed}, {frames} frames -> {p}")
    t0 = time.perf_counter()
    seq = scenes.simulate(config, material, resolution, frames=frames, seed=seed)
    scenes.save_simulation(p, seq)
    wall = time.perf_counter() - t0
    log(f"  done in {wall:.0f} s ({seq.metadata['ms_per_frame']:.0f} ms/frame)")
    return p, {"source": "simulated", "sim_s": wall}


# Table 1's cells (paper Table 1: Dress A seen, Dress B and C unseen; Motion 1 seen, 2 unseen).
GARMENTS = ("flared_skirt", "dress", "cape")  # the first is seen in training
TABLE_MATERIALS = ("silk_charmeuse", "denim_light")
MOTIONS = ("dance", "walk")  # the first is seen in training
SEEN_GARMENT, SEEN_MOTION = GARMENTS[0], MOTIONS[0]
TEST_SEED = 1  # training scenes use seed 0: seed 1 is an unseen performance of every motion


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


# Alignment lives in the library (`wrinkle_jax.evaluation.patchsets`); the names stay
# importable from here.
from wrinkle_jax.evaluation.patchsets import (  # noqa: E402,F401
    AlignedPair,
    PatchSet,
    aligned_pair,
    aligned_patches,
    bake_map,
    candidate_origins,
    choose_origins,
    cut,
    shared_layout,
)

# --------------------------------------------------------------------------------------------
# Methods
# --------------------------------------------------------------------------------------------


def unsharp_setting(path: Path = MODEL_CARD_RESULTS, order: int = 1
                    ) -> tuple[float, float, str]:
    """(sigma texels, amount, source) of the unsharp-mask baseline with masked-blur `order`:
    the best entry of that order in the model card's "unsharp_sweep" (mean signed improvement
    on training patches; keys without "order=" are order 0, from before it existed) if that
    file has one, else `DEFAULT_UNSHARP`."""
    try:
        sweep = json.loads(Path(path).read_text())["unsharp_sweep"]
        parsed = {key: dict(part.split("=") for part in key.split(",")) for key in sweep}
        mine = [key for key, kv in parsed.items() if int(kv.get("order", 0)) == order]
        best = max(mine, key=sweep.get)
        kv = parsed[best]
        return (float(kv["sigma"]), float(kv["amount"]),
                f"{portable_path(path)}: unsharp_sweep best {best}")
    except (OSError, KeyError, ValueError, json.JSONDecodeError):
        s, a = DEFAULT_UNSHARP
        return s, a, (f"default order={order},sigma={s:g},amount={a:g} "
                      f"(no sweep in {portable_path(path)})")


def enhancer_method(enh: enhancer_lib.Enhancer, batch_size: int = 16,
                    timings: dict | None = None,
                    material_of: Callable[[int], int] | None = None
                    ) -> Callable[[PatchSet], np.ndarray]:
    """The model as a method: (PatchSet) -> (K, S, S, 3) RGB-form outputs, unit normals inside
    the mask and zero outside (as the baselines).

    `material_of` maps the patch set's `material_id` to the id the model is told (default:
    itself); the wrong-material ablation (paper Fig. 10) passes another material's id.

    One jitted apply with a fixed batch shape (the last batch padded), compiled here (seconds
    in `timings["compile_s"]`), so calls time the network only; `timings` accumulates
    "network_s" and "network_patches".
    """
    apply = enhancer_lib.make_apply(enh)
    timings = {} if timings is None else timings
    size = enh.config.patch_size
    noise = bool(enh.config.noise_channels)  # texel-noise models read the patch origins
    t0 = time.perf_counter()
    apply(enh.params, jnp.zeros((batch_size, size, size, 3), jnp.float32),
          jnp.zeros((batch_size,), jnp.int32),
          *((jnp.zeros((batch_size, 2), jnp.int32),) if noise else ())).block_until_ready()
    timings["compile_s"] = time.perf_counter() - t0

    def run(p: PatchSet) -> np.ndarray:
        mid = p.material_id if material_of is None else material_of(p.material_id)
        return enhancer_lib.enhance_patches(apply, enh.params, p.input, mid, p.mask,
                                            batch_size, timings,
                                            origins=p.origins if noise else None)

    return run


def wrong_material(material_id: int, materials=TABLE_MATERIALS) -> int:
    """The id (in `wrinkle_jax.MATERIALS`) of the table material that is not `material_id`'s:
    silk_charmeuse <-> denim_light, the lightest and stiffest of the table's materials. A
    material outside `materials` maps to the first of them."""
    ids = [material_index(m) for m in materials]
    others = [i for i in ids if i != material_id]
    if not others:
        raise ValueError("need at least two distinct materials")
    return others[0]


def baseline_methods(settings: dict[int, tuple[float, float]]
                     ) -> dict[str, Callable[[PatchSet], np.ndarray]]:
    """The non-learned methods, each (PatchSet) -> (K, S, S, 3) outputs (RGB form, masked).

    settings: masked-blur order -> (sigma, amount) of an unsharp-mask baseline (one entry per
    order, e.g. from `unsharp_setting`).
    """
    def unsharp(order, sigma, amount):
        return lambda p: evaluation.unsharp_mask(p.input, p.mask, sigma, amount, order)

    return {
        "identity": lambda p: evaluation.identity(p.input, p.mask),
        **{f"unsharp order {o} (sigma={s:g},amount={a:g})": unsharp(o, s, a)
           for o, (s, a) in sorted(settings.items())},
        "bicubic x2 down/up": lambda p: evaluation.resample(p.input, p.mask, 2.0),
        "lanczos x2 down/up": lambda p: evaluation.resample(p.input, p.mask, 2.0,
                                                            up=cv2.INTER_LANCZOS4),
    }


# --------------------------------------------------------------------------------------------
# Scoring with shared Gram matrices
# --------------------------------------------------------------------------------------------


@functools.lru_cache(maxsize=8)
def _gram_fn(layers: tuple[str, ...], pool: str):
    def fn(vgg_params, images, mask):
        feats = vgg.features(vgg_params, images, layers=layers, pool=pool)
        levels = losses.mask_pyramid(mask, max(vgg.layer_level(n) for n in layers) + 1)
        return {n: losses.gram(feats[n], levels[vgg.layer_level(n)], normalize=True)
                for n in layers}
    return jax.jit(fn)


@jax.jit
def _gram_loss(grams_a: dict, grams_b: dict):
    """sum_l ||G_l(a)/R_l - G_l(b)/R_l||_F^2 / 4, per sample (N,): `losses.style_loss` with unit
    layer weights, from precomputed normalized Gram matrices."""
    total = 0.0
    for name in sorted(grams_a):
        d = grams_a[name] - grams_b[name]
        total = total + jnp.sum(d * d, axis=(1, 2)) / 4.0
    return total


def gram_matrices(vgg_params, images, mask, layers=evaluation.EVAL_LAYERS, pool: str = "avg"):
    """Normalized masked Gram matrices G_l / R_l of a batch: dict layer -> (N, C_l, C_l).

    images: (N, S, S, 3) RGB form; mask: (N, S, S, 1). One jitted VGG pass (compiled per
    batch shape: pass fixed-size batches).
    """
    return _gram_fn(tuple(layers), pool)(vgg_params, jnp.asarray(images, jnp.float32),
                                         jnp.asarray(mask, jnp.float32))


def method_losses(vgg_params, inp, target, mask, outputs: dict[str, np.ndarray],
                  layers=evaluation.EVAL_LAYERS, pool: str = "avg", batch_size: int = 16,
                  counter: dict | None = None) -> dict[str, np.ndarray]:
    """Style losses against the target of the input and of every method's output.

    The target's and the input's Gram matrices are computed once per batch and shared by all
    methods; an output equal to the input (identity) reuses the input's. VGG passes per patch:
    2 + (number of outputs that differ from the input), against 3 per method for
    `evaluation.score_patches`.

    Args:
      inp, target: (N, S, S, 3) RGB form; mask: (N, S, S, 1); outputs: name -> (N, S, S, 3).
      counter: optional dict; "vgg_passes" accumulates image-batches run through VGG.
    Returns:
      {"input": L(N) (N,), <name>: L(N*) (N,) for every output} float32.
    """
    n = len(inp)
    counter = {} if counter is None else counter
    parts: dict[str, list] = {"input": [], **{k: [] for k in outputs}}

    def grams(x, idx):
        counter["vgg_passes"] = counter.get("vgg_passes", 0) + 1
        return gram_matrices(vgg_params, np.asarray(x)[idx], np.asarray(mask)[idx], layers, pool)

    for s in range(0, n, batch_size):
        k = min(batch_size, n - s)
        idx = np.resize(np.arange(s, s + k), batch_size)  # fixed shape: one compile
        g_t = grams(target, idx)
        g_i = grams(inp, idx)
        loss_in = _gram_loss(g_i, g_t)
        parts["input"].append(np.asarray(loss_in)[:k])
        for name, out in outputs.items():
            if np.array_equal(np.asarray(out)[s:s + k], np.asarray(inp)[s:s + k]):
                loss = loss_in
            else:
                loss = _gram_loss(grams(out, idx), g_t)
            parts[name].append(np.asarray(loss)[:k])
    return {k: (np.concatenate(v) if v else np.zeros(0, np.float32)).astype(np.float32)
            for k, v in parts.items()}


# The same computation as `evaluation.score_patches` uses (one implementation).
scores_from_losses = evaluation.scores_from_losses


def script_parser(doc: str) -> argparse.ArgumentParser:
    """An argument parser whose description is the docstring's first paragraph and whose
    epilog is the rest of it (the scripts' usage and method notes)."""
    return argparse.ArgumentParser(description=" ".join(doc.split("\n\n")[0].split()),
                                   formatter_class=argparse.RawDescriptionHelpFormatter,
                                   epilog="\n".join(doc.splitlines()[1:]))


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


# --------------------------------------------------------------------------------------------
# Flicker
# --------------------------------------------------------------------------------------------


def series_stats(x: np.ndarray) -> dict:
    """mean, std, median, p95, max of a 1-D series (JSON-ready floats)."""
    x = np.asarray(x, np.float64)
    if not len(x):
        return {"n": 0}
    return {"n": int(len(x)), "mean": float(x.mean()), "std": float(x.std()),
            "median": float(np.median(x)), "p95": float(np.percentile(x, 95)),
            "max": float(x.max())}
