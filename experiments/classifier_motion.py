"""Material from motion (issue 25): feature study, calibrated classifier, held-out report.

    nice -n 5 python -m experiments.classifier_motion [--train-data data/sequences]
        [--heldout-data data/classifier_sequences] [--cache data/classifier_motion]
        [--out experiments/results/classifier] [--ship]

One command regenerates everything (after `experiments.classifier_sequences` has simulated the
held-out coarse sequences): when the simulator's fabrics change, re-simulate and rerun this.

1. Features (`classifier.motion`), cached per sequence under --cache (delete to recompute):
   training = the coarse seed-0 sequences of the training scenes and the validation garment
   (tabard_dance2); held-out = the seed-1 coarse sequences of --heldout-data; skinned = each
   held-out sequence's first frame carried rigidly by the body (`motion.follow_body_rigidly`);
   real LBS = the `experiments.make_lbs_sequences` files in --lbs-data, when present.
2. Selection by leave-one-training-GARMENT-out cross-validation only (`classifier.folds`: all
   scenes of a garment leave together, so the skirt's and the apron's second dance never stay
   in training while the first is validated; `--folds scene` gives sessions 17-22's
   leave-one-scene-out): each feature family alone, all together and all but one, times three
   L2 weights and three prediction clips (`MotionConfig.clip`: off, 3, 2 standard
   deviations); the pick maximizes CV per-sequence accuracy (ties: lower CV NLL). Held-out
   numbers are printed for every candidate but never read by the choice.
3. Calibration on the pick's out-of-fold predictions: temperature (sequence level), abstain
   threshold (lowest confidence whose CV answers are >= 90 % right), novelty limit (twice the
   largest out-of-fold novelty of a training sequence).
4. Final model on all training windows; report on held-out and skinned sequences:
   `report.json`, `motion_*.png`, and the table printed for the README.
"""

from __future__ import annotations

import argparse
import dataclasses
import itertools
import json
import time
from pathlib import Path

import numpy as np

from wrinkle_jax import MATERIALS
from wrinkle_jax.classifier import calibrated as cal
from wrinkle_jax.classifier import drape, motion
from wrinkle_jax.classifier import folds as cv_folds
from wrinkle_jax.fileio import atomic_write_text
from wrinkle_jax.sim import scenes

ROOT = Path(__file__).resolve().parents[1]
L2S = (1e-3, 1e-2, 1e-1)
CLIPS = (0.0, 3.0, 2.0)  # MotionConfig.clip candidates (0: off)


def candidate_families() -> list[tuple[str, ...]]:
    """Each family alone; then all motion families, and all but one, each without and with
    the normal-map family (``drape``, session 22), so session 21's candidates stay a subset."""
    fams = motion.FAMILIES
    base = tuple(f for f in fams if f != "drape")
    out = [(f,) for f in fams]
    for s in [base] + [tuple(g for g in base if g != f) for f in base]:
        out += [s, s + ("drape",)]
    return out


def _seq_features(path: Path, cfg: cal.MotionConfig, skinned: bool = False) -> np.ndarray:
    with np.load(path) as z:
        arrays = {k: z[k] for k in z.files if k != "metadata"}
    topo = motion.make_topology(arrays["faces"], arrays["uvs"], arrays["uv_faces"])
    frames = arrays["frames"]
    if skinned:
        frames = motion.follow_body_rigidly(frames[0], arrays["capsule_ends"])
    plan = drape.make_plan(arrays["faces"], arrays["uvs"], arrays["uv_faces"], frames[0])
    return motion.sequence_features(frames, motion.reference_track(arrays), topo,
                                    float(arrays["fps"]), cfg.window, cfg.stride,
                                    arrays.get("capsule_ends"), drape_plan=plan)


def lbs_entries(lbs_root: Path | None, cfg) -> list[dict]:
    """Features of real skinned sequences (`experiments.make_lbs_sequences`: *.npz with
    capsule_ends); label -1 (no fabric). Not cached: a few small files."""
    out = []
    for p in sorted(lbs_root.glob("*.npz")) if lbs_root and lbs_root.is_dir() else []:
        out.append({"split": "lbs", "scene": p.stem, "material": None, "label": -1,
                    "features": _seq_features(p, cfg)})
    return out


def sim_settings(path: Path) -> str:
    """The solver settings a simulated sequence was made with, as a short key: substeps and
    self-collision, e.g. "sub80_sc" (from the file's metadata; "sub?" when not recorded)."""
    with np.load(path) as z:
        meta = json.loads(str(z["metadata"])) if "metadata" in z.files else {}
    contacts = "_sc" if meta.get("self_collision") else ""
    return f"sub{meta.get('substeps', '?')}{contacts}"


def build_cache(train_root: Path, heldout_root: Path, cache: Path, cfg) -> list[dict]:
    """Window features of every sequence, cached as
    <cache>/d<dim>_<settings>/<split>/<scene>/<material>.npy (`sim_settings`).

    Raises:
      SystemExit: the sequences were simulated with different solver settings (training and
        held-out must match, or the classifier would read the solver instead of the fabric).
    """
    jobs = []
    for sc in scenes.TRAINING_SCENES + scenes.VAL_SCENES:
        for m in MATERIALS:
            jobs.append(("train", sc, m, train_root / sc / f"{m}_coarse_s0.npz", False))
    for d in sorted(p for p in heldout_root.iterdir() if p.is_dir()):
        for m in MATERIALS:
            p = d / f"{m}_coarse_s1.npz"
            jobs.append(("heldout", d.name, m, p, False))
            jobs.append(("skinned", d.name, m, p, True))
    for j in jobs:
        if not j[3].exists():
            print(f"missing {j[3]}", flush=True)
    jobs = [j for j in jobs if j[3].exists()]
    settings = {src: sim_settings(src) for _, _, _, src, _ in jobs}
    if len(set(settings.values())) > 1:
        counts = {k: list(settings.values()).count(k) for k in sorted(set(settings.values()))}
        raise SystemExit(f"sequences simulated with different solver settings {counts}; "
                         "re-simulate them alike (experiments.classifier_sequences, "
                         "experiments.make_coarse_training_sequences)")
    entries = []
    for split, sc, m, src, skinned in jobs:
        dst = cache / f"d{motion.FEATURE_DIM}_{settings[src]}" / split / sc / f"{m}.npy"
        if not dst.exists():
            t0 = time.perf_counter()
            f = _seq_features(src, cfg, skinned)
            dst.parent.mkdir(parents=True, exist_ok=True)
            np.save(dst, f)
            print(f"{split} {sc} {m}: {f.shape} {time.perf_counter() - t0:.1f} s", flush=True)
        entries.append({"split": split, "scene": sc, "material": m, "settings": settings[src],
                        "label": MATERIALS.index(m), "features": np.load(dst)})
    return entries


def _stack(entries):
    x = np.concatenate([e["features"] for e in entries])
    y = np.concatenate([np.full(len(e["features"]), e["label"]) for e in entries])
    return x, y


def make_folds(train: list[dict], by: str = "garment") -> list[cv_folds.Fold]:
    """The CV folds of the training sequences: one per garment (default; garments from the
    scene definitions) or, with by="scene", one per scene (sessions 17-22)."""
    names = sorted({e["scene"] for e in train})
    if by == "garment":
        return cv_folds.leave_one_garment_out(names)
    if by == "scene":
        return cv_folds.leave_one_scene_out(names)
    raise ValueError(f"by must be 'garment' or 'scene', got {by!r}")


def cross_validate(train: list[dict], config: cal.MotionConfig,
                   folds: list[cv_folds.Fold] | None = None) -> dict:
    """Out-of-fold mean window log-probs, window accuracy and novelty of every training
    sequence; folds default to `make_folds` (leave one garment out)."""
    folds = make_folds(train) if folds is None else folds
    mean_lp, labels, nov, win_ok, names = [], [], [], [], []
    for fold in folds:
        fit_on = [e for e in train if e["scene"] in fold.train]
        if {e["scene"] for e in fit_on} & set(fold.validate):
            raise ValueError(f"fold {fold.group}: a scene is both fitted and validated")
        model = cal.fit(*_stack(fit_on), config)
        for e in (e for e in train if e["scene"] in fold.validate):
            lp = cal.window_log_probs(model, e["features"])
            mean_lp.append(lp.mean(0))
            win_ok.append(lp.argmax(1) == e["label"])
            labels.append(e["label"])
            nov.append(cal.novelty(model, e["features"]))
            names.append(f"{e['scene']}/{e['material']}")
    mean_lp, labels = np.array(mean_lp), np.array(labels)
    return {"mean_lp": mean_lp, "labels": labels, "novelty": np.array(nov), "names": names,
            "seq_acc": float(np.mean(mean_lp.argmax(1) == labels)),
            "win_acc": float(np.mean(np.concatenate(win_ok)))}


def best_per_set(rows: list[dict]) -> list[dict]:
    """For each feature set, its candidate (L2, clip) of highest CV accuracy, ties by lower CV
    NLL (the study's own rule); the held-out column rides along, unread."""
    best: dict[tuple, dict] = {}
    for r in rows:
        k = tuple(r["families"])
        if k not in best or ((r["cv_seq_acc"], -r["cv_nll"])
                             > (best[k]["cv_seq_acc"], -best[k]["cv_nll"])):
            best[k] = r
    return list(best.values())


def per_fold_accuracy(cv: dict, folds: list[cv_folds.Fold]) -> dict:
    """Left-out group -> out-of-fold per-sequence accuracy of its sequences."""
    group = {s: f.group for f in folds for s in f.validate}
    ok = cv["mean_lp"].argmax(1) == cv["labels"]
    out: dict[str, list] = {}
    for name, good in zip(cv["names"], ok, strict=True):
        out.setdefault(group[name.split("/")[0]], []).append(bool(good))
    return {g: float(np.mean(v)) for g, v in out.items()}


def _nan_none(a) -> list:
    """Empty reliability bins are NaN; JSON gets null."""
    return [None if not np.isfinite(v) else float(v) for v in np.asarray(a, float)]


def group_of(idx) -> np.ndarray:
    return np.array([cal.GROUPS[MATERIALS[i]] for i in np.asarray(idx)])


def evaluate(model: cal.MotionClassifier, entries: list[dict]) -> dict:
    """Per-sequence results and summary numbers of a set of sequences."""
    rows = []
    for e in entries:
        r = cal.classify_features(model, e["features"])
        probs = np.array([r.scores[m] for m in MATERIALS])
        rows.append({"scene": e["scene"], "material": e["material"], "label": e["label"],
                     "pred": int(probs.argmax()), "confidence": r.confidence,
                     "abstained": r.abstained, "reason": r.reason, "novelty": r.novelty,
                     "probs": probs.tolist(), "group": r.group,
                     "group_confidence": r.group_confidence})
    g_ans = np.array([r["group"] is not None for r in rows])
    g_ok = np.array([r["group"] == cal.GROUPS[r["material"]] for r in rows])
    y = np.array([r["label"] for r in rows])
    p = np.array([r["pred"] for r in rows])
    ans = ~np.array([r["abstained"] for r in rows])
    probs = np.array([r["probs"] for r in rows])
    gy, gp = group_of(y), group_of(p)
    conf = np.zeros((5, 5), int)
    np.add.at(conf, (y, p), 1)
    counts, mconf, macc, ece = cal.reliability(probs, y)
    return {
        "n": len(rows), "accuracy_all": float(np.mean(p == y)),
        "coverage": float(ans.mean()),
        "accuracy_answered": float(np.mean(p[ans] == y[ans])) if ans.any() else None,
        "group_accuracy_all": float(np.mean(gp == gy)),
        "group_accuracy_answered": float(np.mean(gp[ans] == gy[ans])) if ans.any() else None,
        "group_level_coverage": float(g_ans.mean()),
        "group_level_accuracy_answered": float(g_ok[g_ans].mean()) if g_ans.any() else None,
        "ece": ece, "nll": cal.nll(probs, y), "confusion": conf.tolist(),
        "reliability": {"counts": counts.tolist(), "confidence": _nan_none(mconf),
                        "accuracy": _nan_none(macc)},
        "sequences": rows}


def accuracy_vs_windows(model, entries, max_k: int | None = None) -> dict:
    """Accuracy (all and answered) and coverage when only k consecutive windows vote,
    averaged over every start position."""
    n = min(len(e["features"]) for e in entries)
    out = {}
    for k in range(1, (max_k or n) + 1):
        ok, ans, ok_ans = [], [], []
        for e in entries:
            for s in range(0, len(e["features"]) - k + 1):
                r = cal.classify_features(model, e["features"][s:s + k])
                pred = max(r.scores, key=r.scores.get)
                good = MATERIALS.index(pred) == e["label"]
                ok.append(good)
                ans.append(not r.abstained)
                if not r.abstained:
                    ok_ans.append(good)
        out[k] = {"accuracy_all": float(np.mean(ok)), "coverage": float(np.mean(ans)),
                  "accuracy_answered": float(np.mean(ok_ans)) if ok_ans else None}
    return out


def plots(out: Path, res: dict, cv_rel, curve: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 2, figsize=(9, 4))
    for a, (name, rel) in zip(ax, (("CV (training scenes, out of fold)", cv_rel),
                                  ("held-out", res["heldout"]["reliability"])), strict=True):
        conf = np.array([np.nan if v is None else v for v in rel["confidence"]])
        acc = np.array([np.nan if v is None else v for v in rel["accuracy"]])
        cnt = np.array(rel["counts"])
        centers = (np.arange(10) + 0.5) / 10
        a.bar(centers, np.nan_to_num(acc), width=0.09, alpha=0.6, label="accuracy")
        a.plot(conf, acc, "o", label="(mean conf, accuracy)")
        a.plot([0, 1], [0, 1], "k--", lw=1)
        for c, v, k in zip(centers, np.nan_to_num(acc), cnt, strict=True):
            if k:
                a.text(c, v + 0.02, str(k), ha="center", fontsize=7)
        a.set_title(name, fontsize=9)
        a.set_xlabel("top-class confidence")
        a.set_ylabel("accuracy")
        a.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out / "motion_reliability.png", dpi=90)
    plt.close(fig)

    fig, ax = plt.subplots(1, 2, figsize=(8, 3.6))
    for a, key, title in ((ax[0], "heldout", "held-out"), (ax[1], "skinned", "skinned (LBS)")):
        c = np.array(res[key]["confusion"])
        a.imshow(c, cmap="Blues")
        for i, j in itertools.product(range(5), range(5)):
            a.text(j, i, str(c[i, j]), ha="center", va="center", fontsize=8)
        short = [m.replace("silk_", "s_").replace("_light", "").replace("_melton", "")
                 .replace("_terry", "") for m in MATERIALS]
        a.set_xticks(range(5), short, rotation=45, fontsize=7)
        a.set_yticks(range(5), short, fontsize=7)
        a.set_xlabel("predicted (argmax, abstentions included)")
        a.set_ylabel("true")
        a.set_title(title, fontsize=9)
    fig.tight_layout()
    fig.savefig(out / "motion_confusion.png", dpi=90)
    plt.close(fig)

    ks = sorted(curve, key=int)
    fig, a = plt.subplots(figsize=(5, 3.5))
    a.plot(ks, [curve[k]["accuracy_all"] for k in ks], label="accuracy (all)")
    a.plot(ks, [curve[k]["accuracy_answered"] or np.nan for k in ks],
           label="accuracy where it answers")
    a.plot(ks, [curve[k]["coverage"] for k in ks], label="coverage")
    a.axhline(0.2, color="gray", ls=":", lw=1)
    a.set_xlabel("voted windows (32 frames each, stride 16)")
    a.set_ylim(0, 1.02)
    a.legend(fontsize=7)
    a.set_title("held-out sequences", fontsize=9)
    fig.tight_layout()
    fig.savefig(out / "motion_accuracy_vs_windows.png", dpi=90)
    plt.close(fig)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--train-data", default=str(ROOT / "data" / "sequences"))
    ap.add_argument("--heldout-data", default=str(ROOT / "data" / "classifier_sequences"))
    ap.add_argument("--cache", default=str(ROOT / "data" / "classifier_motion"))
    ap.add_argument("--out", default=str(ROOT / "experiments" / "results" / "classifier"))
    ap.add_argument("--lbs-data", default=str(ROOT / "data" / "lbs"),
                    help="folder of skinned sequences (experiments.make_lbs_sequences) to "
                    "report on; skipped when absent")
    ap.add_argument("--model-out", default=None, metavar="PATH",
                    help="also write the fitted model here (for inspection; not shipped)")
    ap.add_argument("--folds", choices=("garment", "scene"), default="garment",
                    help="cross-validation leaves out one garment (all its scenes; default) "
                    "or one scene (sessions 17-22)")
    ap.add_argument("--ship", action="store_true",
                    help=f"write {cal.MOTION_PATH.name} to wrinkle_jax/assets (only when the "
                    "targets hold)")
    args = ap.parse_args(argv)
    base = cal.MotionConfig()
    entries = build_cache(Path(args.train_data), Path(args.heldout_data), Path(args.cache),
                          base)
    train = [e for e in entries if e["split"] == "train"]
    heldout = [e for e in entries if e["split"] == "heldout"]
    skinned = [e for e in entries if e["split"] == "skinned"]
    print(f"{len(train)} training, {len(heldout)} held-out, {len(skinned)} skinned sequences")
    folds = make_folds(train, args.folds)
    for f in folds:
        print(f"fold {f.group}: validate {', '.join(f.validate)}")

    # Selection: CV numbers only; the held-out column is printed for the record.
    cands = []
    for fams, l2, clip in itertools.product(candidate_families(), L2S, CLIPS):
        cfg = dataclasses.replace(base, families=fams, l2=l2, clip=clip)
        cv = cross_validate(train, cfg, folds)
        t = cal.fit_temperature(cv["mean_lp"], cv["labels"])
        cv_nll = cal.nll(cal.sequence_probs(cv["mean_lp"], t), cv["labels"])
        model = cal.fit(*_stack(train), cfg)
        ho = np.array([cal.window_log_probs(model, e["features"]).mean(0) for e in heldout])
        ho_acc = float(np.mean(ho.argmax(1) == [e["label"] for e in heldout]))
        row = {"families": list(fams), "l2": l2, "clip": clip, "cv_seq_acc": cv["seq_acc"],
               "cv_win_acc": cv["win_acc"], "cv_nll": cv_nll, "heldout_seq_acc": ho_acc}
        cands.append((row, cfg, cv))
        print(json.dumps(row), flush=True)
    for r in best_per_set([c[0] for c in cands]):
        print(f"best of set {'+'.join(r['families'])}: L2 {r['l2']} clip {r['clip']} CV "
              f"{r['cv_seq_acc']:.2f} (window {r['cv_win_acc']:.2f}, NLL {r['cv_nll']:.2f}) "
              f"held-out {r['heldout_seq_acc']:.2f}")
    row, cfg, cv = max(cands, key=lambda c: (c[0]["cv_seq_acc"], -c[0]["cv_nll"]))
    print("pick:", json.dumps(row))

    # Calibration on the pick's out-of-fold predictions.
    temp = cal.fit_temperature(cv["mean_lp"], cv["labels"])
    cv_probs = cal.sequence_probs(cv["mean_lp"], temp)
    conf = cv_probs.max(1)
    ok = cv_probs.argmax(1) == cv["labels"]
    threshold = cal.choose_threshold(conf, ok, 0.9)
    novelty_limit = 2.0 * float(cv["novelty"].max())
    cv_groups = [cal.group_scores(dict(zip(MATERIALS, p, strict=True))) for p in cv_probs]
    g_conf = np.array([max(g.values()) for g in cv_groups])
    g_ok = np.array([max(g, key=g.get) == cal.GROUPS[MATERIALS[y]]
                     for g, y in zip(cv_groups, cv["labels"], strict=True)])
    group_threshold = cal.choose_threshold(g_conf, g_ok, 0.9)
    model = cal.fit(*_stack(train), cfg)._replace(temperature=temp, threshold=threshold,
                                                   novelty_limit=novelty_limit,
                                                   group_threshold=group_threshold)
    cv_counts, cv_conf, cv_acc, cv_ece = cal.reliability(cv_probs, cv["labels"])
    _, _, _, cv_ece_t1 = cal.reliability(cal.sequence_probs(cv["mean_lp"], 1.0), cv["labels"])
    cv_ans = conf >= threshold
    g_ans = g_conf >= group_threshold
    res = {"cv_folds": {"by": args.folds,
                        "folds": [{"group": f.group, "validate": list(f.validate)}
                                  for f in folds]},
           "config": dataclasses.asdict(cfg), "temperature": temp, "threshold": threshold,
           "novelty_limit": novelty_limit, "group_threshold": group_threshold,
           "cv": {"seq_acc": cv["seq_acc"], "win_acc": cv["win_acc"], "ece": cv_ece,
                  "ece_temperature_1": cv_ece_t1,
                  "nll": cal.nll(cv_probs, cv["labels"]),
                  "nll_temperature_1": cal.nll(cal.sequence_probs(cv["mean_lp"], 1.0),
                                               cv["labels"]),
                  "coverage": float(cv_ans.mean()),
                  "accuracy_answered": float(ok[cv_ans].mean()) if cv_ans.any() else None,
                  "group_accuracy": float(np.mean(group_of(cv_probs.argmax(1))
                                                  == group_of(cv["labels"]))),
                  "max_novelty": float(cv["novelty"].max()),
                  "per_fold": per_fold_accuracy(cv, folds),
                  "group_level_coverage": float(g_ans.mean()),
                  "group_level_accuracy_answered": float(g_ok[g_ans].mean()) if g_ans.any()
                  else None},
           "candidates": [c[0] for c in cands],
           "best_per_set": best_per_set([c[0] for c in cands]),
           "heldout": evaluate(model, heldout), "skinned": evaluate(model, skinned)}
    curve = accuracy_vs_windows(model, heldout)
    res["heldout_vs_windows"] = curve
    res["simulation"] = entries[0]["settings"] if entries else None  # one setting (build_cache)
    res["lbs"] = []
    for e in lbs_entries(Path(args.lbs_data), base):
        r = cal.classify_features(model, e["features"])
        res["lbs"].append({"sequence": e["scene"], "abstained": r.abstained, "reason": r.reason,
                           "novelty": r.novelty, "argmax": max(r.scores, key=r.scores.get),
                           "confidence": r.confidence})
        print("lbs", json.dumps(res["lbs"][-1]))
    if args.model_out:
        cal.save(args.model_out, model, {"selection": row, "note": "not shipped"})
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    plots(out, res, {"counts": cv_counts.tolist(), "confidence": _nan_none(cv_conf),
                     "accuracy": _nan_none(cv_acc)}, curve)
    atomic_write_text(out / "motion_report.json", json.dumps(res, indent=1) + "\n")
    h, s = res["heldout"], res["skinned"]
    print(json.dumps({k: res["cv"][k] for k in res["cv"]}, indent=1))
    for name, r in (("heldout", h), ("skinned", s)):
        print(name, {k: r[k] for k in ("n", "accuracy_all", "coverage", "accuracy_answered",
                                       "group_accuracy_all", "group_accuracy_answered",
                                       "group_level_coverage", "group_level_accuracy_answered",
                                       "ece", "nll")})
    print("temperature", temp, "threshold", threshold, "group_threshold", group_threshold,
          "novelty_limit", novelty_limit)
    targets = (h["coverage"] >= 0.5 and (h["accuracy_answered"] or 0) >= 0.9
               and (h["group_accuracy_answered"] or 0) >= 0.9 and s["coverage"] == 0.0)
    print("targets hold:", targets)
    if args.ship:
        if not targets:
            print("not shipping: the targets do not hold")
        else:
            cal.save(cal.MOTION_PATH, model, {"selection": row, "trained_on": "coarse s0 of "
                                              + ", ".join(sorted({e['scene'] for e in train}))})
            print("wrote", cal.MOTION_PATH)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
