"""Material by analysis-by-synthesis (issue 25, session 23): re-simulate each input garment with
the five fabrics on the input's own body and pin tracks, compare motion features.

    nice -n 5 python -m experiments.classifier_synthesis --stage synth --variant main
    nice -n 5 python -m experiments.classifier_synthesis --stage synth --variant heavy_soft \
        --scenes skirt_dance apron_dance ...          # model-mismatch syntheses (subset)
    nice -n 5 python -m experiments.classifier_synthesis --stage report

1. `synth` (resumable; one file per input under --cache/<variant>/<split>/<scene>/<material>.npz
   holding the input's and the five syntheses' window features, the seconds and the position
   RMS of each synthesis against the input): inputs = the training scenes' coarse seed-0
   sequences (and the validation garment) and the held-out seed-1 sequences; the first
   --frames frames after a --settle-frame settle from the input's frame 0.
   Variants (`VARIANTS`; what the synthesis library assumes; the inputs are the data set's
   files, 80 substeps + self-collision, except `jitter`):
     main        20 substeps, no self-collision (a solver MISMATCH with the inputs)
     s80         80 substeps, no self-collision (the pick of session 23's CV)
     matched     the input's own solver settings from its metadata (80 + self-collision)
     heavy_soft, light_stiff (and s80_...): fabrics' mass per area x1.25 and stretch/bending
                 stiffness x0.8, or x0.8 and x1.25
     jitter      inputs re-simulated on a mesh of another lattice jitter (`--stage inputs`),
                 synthesized like s80
2. `report`: every choice (synthesis pipeline among `PIPELINES`, feature families,
   aggregation, weights, temperature, abstain thresholds, novelty limit) from
   leave-one-garment-out CV on the training inputs; with --heldout the held-out numbers are
   computed once at the end with the chosen settings and printed; the mismatch table scores
   each variant's syntheses of training inputs out of fold with its base pipeline's
   classifier (`BASE`); with --heldout also each variant's held-out syntheses with its base
   pipeline's final classifier (`heldout_variants`, per garment). Writes
   --out/synthesis_report.json. The held-out inputs are --heldout-data's files of
   --heldout-seed, cached and scored as split --heldout-split (seed 1: "heldout"; session
   24b's fresh seed 2: "fresh").
3. `export --model-out F`: the CV pick as a `synthesis_model.SynthesisClassifier`;
   `check --model-out F --check-inputs scene/material ...`: its `classify` on training input
   files against the study's distances (--out/synthesis_export_check.json).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import subprocess
import time
from pathlib import Path

import numpy as np

from wrinkle_jax import MATERIALS
from wrinkle_jax.classifier import calibrated as cal
from wrinkle_jax.classifier import drape, motion, synthesis_model
from wrinkle_jax.classifier import folds as cv_folds
from wrinkle_jax.classifier import synthesis as syn
from wrinkle_jax.classifier.synthesis_study import Distance, check_inputs, load_entries
from wrinkle_jax.classifier.synthesis_study import load_npz as _load
from wrinkle_jax.evaluation.suite import portable_path
from wrinkle_jax.fileio import atomic_write_text
from wrinkle_jax.sim import scenes

ROOT = Path(__file__).resolve().parents[1]
# variant -> solver substeps ("meta": the input file's own settings, self-collision included;
# else no self-collision), fabric mass per area and stiffness factors.
VARIANTS = {"main": (20, 1.0, 1.0), "s80": (80, 1.0, 1.0), "matched": ("meta", 1.0, 1.0),
            "heavy_soft": (20, 1.25, 0.8), "light_stiff": (20, 0.8, 1.25),
            "s80_heavy_soft": (80, 1.25, 0.8), "s80_light_stiff": (80, 0.8, 1.25),
            "jitter": (80, 1.0, 1.0)}
# Variants whose INPUTS differ from the data set's: "jitter" reads inputs simulated on a mesh of
# another lattice jitter (`--stage inputs`, <cache>/inputs_jitter; 80 substeps +
# self-collision like the data set, --frames frames), synthesized like s80.
JITTER_SEED = 1
# The synthesis pipelines the report chooses between by CV (each needs all training inputs);
# a pipeline's fabric-mismatch variants are named <pipeline>_heavy_soft / _light_stiff
# ("main": heavy_soft / light_stiff).
PIPELINES = ("main", "s80", "matched")
# The pipeline whose classifier (distance and calibration, chosen by its own CV) scores each
# variant in the mismatch table.
BASE = {"main": "main", "heavy_soft": "main", "light_stiff": "main", "s80": "s80",
        "s80_heavy_soft": "s80", "s80_light_stiff": "s80", "jitter": "s80", "matched": "s80"}
# Held-out garments that no training scene has (skirt_walk is the training flared skirt).
UNSEEN = ("dress_dance", "dress_walk", "cape_dance", "cape_walk")


def jobs(train_root: Path, heldout_root: Path, scene_filter=None, heldout_seed: int = 1,
         heldout_split: str = "heldout") -> list[tuple]:
    """(split, scene, material, file) of every input: the training scenes' coarse seed-0 files
    (split "train") and the held-out cells' coarse files of `heldout_seed` under
    `heldout_root` (split `heldout_split`: "heldout" = seed 1, read in sessions 23-24;
    "fresh" = seed 2, session 24b)."""
    out = []
    for sc in scenes.TRAINING_SCENES + scenes.VAL_SCENES:
        for m in MATERIALS:
            out.append(("train", sc, m, train_root / sc / f"{m}_coarse_s0.npz"))
    for d in sorted(p for p in heldout_root.iterdir() if p.is_dir()):
        for m in MATERIALS:
            out.append((heldout_split, d.name, m, d / f"{m}_coarse_s{heldout_seed}.npz"))
    out = [j for j in out if j[3].exists()]
    if scene_filter:
        out = [j for j in out if j[1] in scene_filter]
    return out


def synth_config(variant: str, meta: dict, frames: int, settle: int) -> syn.SynthesisConfig:
    substeps = VARIANTS[variant][0]
    if substeps == "meta":
        return syn.config_from_metadata(meta, frames=frames, settle_frames=settle)
    return syn.SynthesisConfig(frames=frames, settle_frames=settle, substeps=substeps)


def synth_one(src: Path, dst: Path, variant: str, frames: int, settle: int) -> None:
    arrays = _load(src)
    meta = json.loads(str(arrays["metadata"]))
    cfg = synth_config(variant, meta, frames, settle)
    _, density, stiffness = VARIANTS[variant]
    fabrics = {m: syn.scaled_fabric(m, density, stiffness) for m in MATERIALS}
    plan = drape.make_plan(arrays["faces"], arrays["uvs"], arrays["uv_faces"],
                           arrays["frames"][0])
    t0 = time.perf_counter()
    model = syn.build_model(arrays)
    feats, rms, secs = [], [], []
    for m in MATERIALS:
        t1 = time.perf_counter()
        x = syn.synthesize(arrays, fabrics[m], cfg, model)
        secs.append(time.perf_counter() - t1)
        rms.append(float(np.sqrt(((x - arrays["frames"][:frames]) ** 2).sum(-1).mean())))
        feats.append(syn.window_features(arrays, x, drape_plan=plan))
    sim_s = time.perf_counter() - t0
    t1 = time.perf_counter()
    inp = syn.window_features(arrays, arrays["frames"][:frames], drape_plan=plan)
    skinned = inp  # no body (the sheet): no skinned stand-in
    if "capsule_ends" in arrays:
        rigid = motion.follow_body_rigidly(arrays["frames"][0], arrays["capsule_ends"][:frames])
        skinned = syn.window_features(arrays, rigid, drape_plan=plan)
    feat_s = time.perf_counter() - t1
    dst.parent.mkdir(parents=True, exist_ok=True)
    tmp = dst.with_suffix(".tmp.npz")
    np.savez(tmp, input=inp, skinned=skinned, synth=np.stack(feats), rms=np.array(rms),
             synth_seconds=np.array(secs), total_seconds=np.array(sim_s + feat_s),
             config=np.array(json.dumps(dataclasses.asdict(cfg), default=str)))
    tmp.replace(dst)


def stage_inputs(args) -> None:
    """Simulate training inputs on a mesh of lattice jitter JITTER_SEED (the data set's seed
    0 motion, its coarse solver) into <cache>/inputs_jitter/<scene>/<material>_coarse_s0.npz."""
    for sc in args.scenes or ():
        setup = scenes.setup_scene(sc, "coarse", args.frames, seed=0, mesh_seed=JITTER_SEED)
        substeps, contacts = scenes.dataset_solver(sc, "coarse")
        for m in MATERIALS:
            dst = Path(args.cache) / "inputs_jitter" / sc / f"{m}_coarse_s0.npz"
            if dst.exists():
                continue
            t0 = time.perf_counter()
            seq = scenes.simulate(sc, m, "coarse", frames=args.frames, seed=0,
                                  substeps=substeps, setup=setup, self_collision=contacts)
            dst.parent.mkdir(parents=True, exist_ok=True)
            scenes.save_simulation(dst, seq)
            print(f"input jitter {sc} {m}: {time.perf_counter() - t0:.1f} s", flush=True)


def stage_synth(args) -> None:
    train_root = Path(args.cache) / "inputs_jitter" if args.variant == "jitter" \
        else Path(args.train_data)
    todo = jobs(train_root, Path(args.heldout_data), args.scenes, args.heldout_seed,
                args.heldout_split)
    if args.split:
        todo = [j for j in todo if j[0] == args.split]
    for split, sc, m, src in todo:
        dst = Path(args.cache) / args.variant / split / sc / f"{m}.npz"
        if dst.exists():
            continue
        t0 = time.perf_counter()
        synth_one(src, dst, args.variant, args.frames, args.settle)
        print(f"{args.variant} {split} {sc} {m}: {time.perf_counter() - t0:.1f} s", flush=True)


# --------------------------------------------------------------------------------------------
# Report
# --------------------------------------------------------------------------------------------


def candidates() -> list[dict]:
    """The study's candidates: feature families (all; all motion; each alone; all but one
    motion family) x aggregation (`synthesis.mean_squares`) with uniform weights, and all
    families with weights fitted by a conditional logit (three L2 weights)."""
    fams = motion.FAMILIES
    base = tuple(f for f in fams if f != "drape")
    sets = [fams, base] + [(f,) for f in fams] + [tuple(g for g in fams if g != f)
                                                   for f in base]
    out = [{"families": list(f), "agg": a, "l2": None} for f in sets
           for a in ("window", "mean")]
    out += [{"families": list(fams), "agg": a, "l2": l2} for a in ("window", "mean")
            for l2 in (1e-2, 1e-1, 1.0)]
    return out


def out_of_fold(train, spec, targets, key="input") -> np.ndarray:
    """(len(targets), M) distances of each target input by the `Distance` fitted on the
    training inputs of the other garments (leave-one-garment-out folds)."""
    folds = cv_folds.leave_one_garment_out(sorted({e["scene"] for e in train}))
    d = np.full((len(targets), len(MATERIALS)), np.nan)
    for f in folds:
        idx = [i for i, e in enumerate(targets) if e["scene"] in f.validate]
        if idx:
            dist = Distance(spec, [e for e in train if e["scene"] in f.train])
            d[idx] = dist([targets[i] for i in idx], key)
    return d


def cross_validate(train, spec) -> dict:
    d = out_of_fold(train, spec, train)
    labels = np.array([e["label"] for e in train])
    return {"d": d, "labels": labels,
            "names": [f"{e['scene']}/{e['material']}" for e in train],
            "seq_acc": float(np.mean(d.argmin(1) == labels))}


def group_idx(labels) -> np.ndarray:
    names = sorted(set(cal.GROUPS.values()))
    return np.array([names.index(cal.GROUPS[MATERIALS[int(i)]]) for i in labels])


def group_probs(p) -> np.ndarray:
    names = sorted(set(cal.GROUPS.values()))
    out = np.zeros((len(p), len(names)))
    for k, m in enumerate(MATERIALS):
        out[:, names.index(cal.GROUPS[m])] += p[:, k]
    return out


def summarize(d, labels, cal_: dict, names=None) -> dict:
    p = syn.scores_to_probs(d, cal_["T"])
    conf, pred = p.max(1), p.argmax(1)
    novel = d.min(1) > cal_["novelty_limit"]
    answer = (conf >= cal_["threshold"]) & ~novel
    gp = group_probs(p)
    gans = (gp.max(1) >= cal_["group_threshold"]) & ~novel
    out = {"n": int(len(d)), "seq_acc": float(np.mean(pred == labels)),
           "coverage": float(answer.mean()), "answered": int(answer.sum()),
           "acc_where_answers": float(np.mean(pred[answer] == labels[answer]))
           if answer.any() else None,
           "group_acc": float(np.mean(gp.argmax(1) == group_idx(labels))),
           "group_coverage": float(gans.mean()),
           "group_acc_where_answers": float(np.mean(gp.argmax(1)[gans] ==
                                                    group_idx(labels)[gans]))
           if gans.any() else None,
           "ece": cal.reliability(p, labels)[3], "nll": cal.nll(p, labels),
           "confusion": np.bincount(labels * 5 + pred, minlength=25).reshape(5, 5).tolist()}
    if names is not None:
        out["per_sequence"] = [
            {"sequence": n, "true": MATERIALS[int(y)], "pred": MATERIALS[int(k)],
             "answered": bool(a), "novel": bool(v), "min_distance": float(dd.min()),
             "probs": {m: round(float(q), 4) for m, q in zip(MATERIALS, pp, strict=True)}}
            for n, y, k, a, v, dd, pp in zip(names, labels, pred, answer, novel, d, p,
                                             strict=True)]
    return out


def per_garment(summary: dict) -> dict:
    """{scene: n, right (argmax), answered, right_where_answers} from `summarize`'s
    per_sequence rows ("scene/material" names)."""
    out: dict[str, dict] = {}
    for r in summary["per_sequence"]:
        g = out.setdefault(r["sequence"].split("/")[0], {"n": 0, "right": 0, "answered": 0,
                                                          "right_where_answers": 0})
        ok = r["pred"] == r["true"]
        g["n"] += 1
        g["right"] += int(ok)
        g["answered"] += int(r["answered"])
        g["right_where_answers"] += int(ok and r["answered"])
    return out


def score_variant(dist: Distance, calib: dict, entries: list[dict]) -> dict:
    """A variant's inputs (e.g. its held-out syntheses) scored by a FIXED classifier: the
    distance `dist` (fitted on the base pipeline's training syntheses) and its calibration;
    all inputs, the unseen garments (`UNSEEN`), per garment, and (when the entries carry
    them) their skinned stand-ins against the same syntheses."""
    out = {}
    for name, sel in (("all", entries), ("unseen_garments",
                                         [e for e in entries if e["scene"] in UNSEEN])):
        if sel:
            out[name] = summarize(dist(sel), np.array([e["label"] for e in sel]), calib,
                                  [f"{e['scene']}/{e['material']}" for e in sel])
    if "all" in out:
        out["per_garment"] = per_garment(out["all"])
    if entries and all("skinned" in e for e in entries):
        d = dist(entries, key="skinned")
        s = summarize(d, np.array([e["label"] for e in entries]), calib)
        out["skinned"] = {"n": s["n"], "answered": s["answered"],
                          "group_answered": int(round(s["group_coverage"] * s["n"])),
                          "min_distance_range": [float(d.min(1).min()), float(d.min(1).max())],
                          "max_confidence": float(syn.scores_to_probs(d, calib["T"]).max())}
    return out


def rule_s24(base: dict, variant: dict) -> dict:
    """Session 24's decision rule (synthesis_rule_s24.txt) on two `summarize` results for the
    same inputs: the variant is picked iff its per-sequence accuracy >= the base's and its
    answers are not fewer than the base's minus one."""
    acc = variant["seq_acc"] >= base["seq_acc"] - 1e-12
    cov = variant["answered"] >= base["answered"] - 1
    return {"accuracy_not_lower": bool(acc), "coverage_within_one": bool(cov),
            "variant_picked": bool(acc and cov)}


def calibrated_pick(rows, train):
    """A pipeline's pick (CV accuracy, ties by NLL), its CV and its calibration: temperature,
    abstain threshold, group threshold, novelty limit (2 x the largest out-of-fold
    nearest-synthesis distance)."""
    best = max(rows, key=lambda r: (r["cv_seq_acc"], -r["cv_nll"]))
    spec = {k: best[k] for k in ("families", "agg", "l2")}
    cv = cross_validate(train, spec)
    T = cal.fit_temperature(-cv["d"], cv["labels"])
    p = syn.scores_to_probs(cv["d"], T)
    gp = group_probs(p)
    calib = {"T": T, "threshold": cal.choose_threshold(p.max(1), p.argmax(1) == cv["labels"]),
             "group_threshold": cal.choose_threshold(gp.max(1),
                                                     gp.argmax(1) == group_idx(cv["labels"])),
             "novelty_limit": 2.0 * float(cv["d"].min(1).max())}
    return spec, cv, calib


def cv_pipelines(cache: Path, quiet: bool = False):
    """Session 23's CV over `PIPELINES` on the training inputs: (candidate rows, each
    pipeline's training entries, each pipeline's `calibrated_pick`, the best row)."""
    rows, trains = [], {}
    for pipe in PIPELINES:
        train = [e for e in load_entries(cache, pipe) if e["split"] == "train"]
        if len(train) < len(scenes.TRAINING_SCENES + scenes.VAL_SCENES) * len(MATERIALS):
            print(f"pipeline {pipe}: {len(train)} training inputs, incomplete; skipped")
            continue
        trains[pipe] = train
        for spec in candidates():
            cv = cross_validate(train, spec)
            t = cal.fit_temperature(-cv["d"], cv["labels"])
            p = syn.scores_to_probs(cv["d"], t)
            rows.append({"pipeline": pipe, **spec, "cv_seq_acc": cv["seq_acc"],
                         "cv_nll": cal.nll(p, cv["labels"]), "T": t})
            if not quiet:
                print(f"  {pipe:5s} {'+'.join(spec['families']):62s} {spec['agg']:6s} "
                      f"l2 {spec['l2']} CV {cv['seq_acc']:.2f} NLL {rows[-1]['cv_nll']:.3f}",
                      flush=True)
    picks = {q: calibrated_pick([r for r in rows if r["pipeline"] == q], trains[q])
             for q in trains}
    best = max(rows, key=lambda r: (r["cv_seq_acc"], -r["cv_nll"]))
    return rows, trains, picks, best


def stage_report(args) -> None:
    cache = Path(args.cache)
    rows, trains, picks, best = cv_pipelines(cache)
    pipe = best["pipeline"]
    spec, cv, calib = picks[pipe]
    train = trains[pipe]
    print("pick", json.dumps(best), json.dumps(calib), flush=True)
    res = {"pick": best, "calibration": calib, "candidates": rows,
           "cv": summarize(cv["d"], cv["labels"], calib, cv["names"]),
           "per_pipeline": {q: {"spec": sp, "calibration": cb,
                                "cv": summarize(c["d"], c["labels"], cb)}
                            for q, (sp, c, cb) in picks.items()}}
    # Skinned stand-ins of the training inputs that have a body, out of fold.
    bodied = [e for e in train if e["scene"] != "sheet_balls_wind"]
    d = out_of_fold(train, spec, bodied, key="skinned")
    p = syn.scores_to_probs(d, calib["T"])
    res["skinned_cv"] = {"n": len(bodied), "answered": int(
        ((p.max(1) >= calib["threshold"]) & (d.min(1) <= calib["novelty_limit"])).sum()),
        "min_distance_range": [float(d.min(1).min()), float(d.min(1).max())]}
    # Final distance on all training inputs; the held-out set, computed once, printed.
    dist = Distance(spec, train)
    # Without --heldout the held-out inputs are not read at all (development runs).
    held = [e for e in load_entries(cache, pipe) if e["split"] == args.heldout_split] \
        if args.heldout else []
    scored = score_variant(dist, calib, held)
    for name, key in (("heldout", "all"), ("heldout_unseen_garments", "unseen_garments")):
        if key in scored:
            res[name] = scored[key]
    if "skinned" in scored:
        res["skinned"] = {**scored["skinned"], "novelty_limit": calib["novelty_limit"]}
    # Model mismatch: the chosen classifier (its distance fitted out of fold on the chosen
    # pipeline's training syntheses, its calibration) on the syntheses of other variants, for
    # the same training inputs; and the calibration-free nearest synthesis by position RMS.
    res["mismatch"] = {}
    for v in VARIANTS:
        base = BASE[v]
        if base not in picks:
            continue
        b_spec, b_cv, b_cal = picks[base]
        pos = {n: i for i, n in enumerate(b_cv["names"])}
        ents = [e for e in load_entries(cache, v) if e["split"] == "train"]
        ents = [e for e in ents if f"{e['scene']}/{e['material']}" in pos]
        if not ents:
            continue
        labels = np.array([e["label"] for e in ents])
        d_base = b_cv["d"][[pos[f"{e['scene']}/{e['material']}"] for e in ents]]
        d_v = out_of_fold(trains[base], b_spec, ents)
        rms = np.stack([e["rms"] for e in ents])
        res["mismatch"][v] = {
            "solver_substeps_density_stiffness": list(VARIANTS[v]), "base": base,
            "scenes": sorted({e["scene"] for e in ents}), "n": len(ents),
            "base_on_same_inputs": summarize(d_base, labels, b_cal),
            "variant": summarize(d_v, labels, b_cal),
            "nearest_by_position_acc": float(np.mean(rms.argmin(1) == labels)),
            "rms_true_fabric_m": float(np.median(rms[np.arange(len(ents)), labels])),
            "rms_other_fabrics_m": float(np.median(
                [np.delete(r, y).mean() for r, y in zip(rms, labels, strict=True)])),
            "synth_seconds_per_input": float(np.median([e["synth_seconds"].sum()
                                                        for e in ents])),
            "total_seconds_per_input": float(np.median([e["total_seconds"] for e in ents]))}
        res["mismatch"][v]["rule_s24"] = rule_s24(res["mismatch"][v]["base_on_same_inputs"],
                                                  res["mismatch"][v]["variant"])
    # Held-out syntheses of every variant, scored by its base pipeline's final classifier
    # (distance fitted on all of the base's training syntheses, the base's calibration).
    res["heldout_variants"] = {}
    for v in VARIANTS if args.heldout else ():
        base = BASE[v]
        ents = [e for e in load_entries(cache, v) if e["split"] == args.heldout_split]
        if base in picks and ents:
            b_spec, _, b_cal = picks[base]
            res["heldout_variants"][v] = {"base": base, **score_variant(
                Distance(b_spec, trains[base]), b_cal, ents),
                "synth_seconds_per_input": float(np.median([e["synth_seconds"].sum()
                                                            for e in ents])),
                "total_seconds_per_input": float(np.median([e["total_seconds"]
                                                            for e in ents]))}
    res["heldout_split"] = args.heldout_split if args.heldout else None
    # For comparison only (never a choice): each pipeline's held-out syntheses scored by its OWN
    # CV-chosen classifier (distance fitted on all its training syntheses, its calibration).
    res["heldout_per_pipeline"] = {}
    for q in picks if args.heldout else ():
        ents = [e for e in load_entries(cache, q) if e["split"] == args.heldout_split]
        if ents:
            q_spec, _, q_cal = picks[q]
            res["heldout_per_pipeline"][q] = score_variant(Distance(q_spec, trains[q]), q_cal,
                                                           ents)
    out = Path(args.out) / "synthesis_report.json"
    atomic_write_text(out, json.dumps(res, indent=1, default=float))
    for q, r in res["per_pipeline"].items():
        print("pipeline", q, json.dumps(r["spec"]), json.dumps(r["calibration"]),
              json.dumps({k: v for k, v in r["cv"].items() if k != "confusion"}))
    for k in ("cv", "heldout", "heldout_unseen_garments"):
        if k in res:
            r = {q: v for q, v in res[k].items() if q not in ("per_sequence",)}
            print(k, json.dumps(r), flush=True)
    print("skinned", json.dumps(res.get("skinned")), json.dumps(res["skinned_cv"]))
    for v, r in res["mismatch"].items():
        print("mismatch", v, json.dumps({
            "n": r["n"], "base": r["base"],
            "base_acc": r["base_on_same_inputs"]["seq_acc"],
            "variant_acc": r["variant"]["seq_acc"], "variant_cov": r["variant"]["coverage"],
            "variant_where": r["variant"]["acc_where_answers"],
            "variant_group": r["variant"]["group_acc"],
            "nearest_pos": r["nearest_by_position_acc"], "rms_true": r["rms_true_fabric_m"],
            "rms_other": r["rms_other_fabrics_m"], "synth_s": r["synth_seconds_per_input"],
            "total_s": r["total_seconds_per_input"]}), flush=True)
    for v, r in res["mismatch"].items():
        print("rule_s24", v, json.dumps(r["rule_s24"]))
    for v, r in res["heldout_variants"].items():
        a = r["all"]
        print("heldout_variant", v, json.dumps({
            "base": r["base"], "n": a["n"], "seq_acc": a["seq_acc"], "coverage": a["coverage"],
            "where": a["acc_where_answers"], "group": a["group_acc"], "ece": a["ece"],
            "nll": a["nll"], "per_garment": r["per_garment"], "confusion": a["confusion"],
            "total_s": r["total_seconds_per_input"], "skinned": r.get("skinned")}),
              flush=True)
    print(f"wrote {out}")


def stage_export(args) -> None:
    """The CV pick as a `synthesis_model.SynthesisClassifier` (distance fitted on ALL training
    inputs of the picked pipeline, its CV calibration) written to --model-out."""
    if not args.model_out:
        raise SystemExit("--stage export needs --model-out PATH")
    rows, trains, picks, best = cv_pipelines(Path(args.cache), quiet=True)
    pipe = best["pipeline"]
    spec, cv, calib = picks[pipe]
    dist = Distance(spec, trains[pipe])
    substeps, density, stiffness = VARIANTS[pipe]
    if (density, stiffness) != (1.0, 1.0):
        raise SystemExit(f"pipeline {pipe} perturbs the fabrics; not exportable")
    try:
        commit = subprocess.run(["git", "rev-parse", "HEAD"], cwd=ROOT, capture_output=True,
                                text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        commit = None
    meta = {"source": "experiments/classifier_synthesis.py --stage export (issue 25)",
            "pipeline": pipe, "spec": spec, "calibration": calib,
            "cv": {k: v for k, v in summarize(cv["d"], cv["labels"], calib).items()
                   if k != "confusion"},
            "cv_per_pipeline": {q: {"spec": sp, "cv_seq_acc": c["seq_acc"]}
                                for q, (sp, c, _) in picks.items()},
            "training_inputs": len(trains[pipe]),
            "date": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()), "commit": commit}
    clf = synthesis_model.from_study(
        spec, dist.scale, dist.w, calib,
        solver="input" if substeps == "meta" else "fixed",
        substeps=syn.SynthesisConfig().substeps if substeps == "meta" else int(substeps),
        frames=args.frames, settle_frames=args.settle, meta=meta)
    path = synthesis_model.save(args.model_out, clf)
    print(f"wrote {path} ({path.stat().st_size} bytes): {pipe} {json.dumps(spec)} "
          f"{json.dumps(calib)}", flush=True)


def stage_check(args) -> None:
    """Consistency of an exported classifier (--model-out) with the study: run
    `synthesis_model.classify` on training input files (--check-inputs scene/material ...) and
    compare the distances it implies (nearest distance + T * log-probability ratios) with the
    study's `Distance` (fitted on all training inputs of the classifier's pipeline) on the cached
    features of the same inputs."""
    clf = synthesis_model.load(args.model_out)
    pipe = clf.meta["pipeline"]
    train = [e for e in load_entries(Path(args.cache), pipe) if e["split"] == "train"]
    dist = Distance(clf.meta["spec"], train)
    rows = []
    for name, e, row in check_inputs(clf, dist, train, args.check_inputs, args.train_data, 0):
        ref = np.asarray(row["reference_distances"])
        study = summarize(ref[None], np.array([e["label"]]), clf.meta["calibration"])
        rows.append({"input": name, **row,
                     "study": {"pred": MATERIALS[int(ref.argmin())],
                               "answered": bool(study["answered"])}})
        print("check", json.dumps(rows[-1]), flush=True)
    out = Path(args.out) / "synthesis_export_check.json"
    model = portable_path(args.model_out)
    atomic_write_text(out, json.dumps({"model": model, "rows": rows}, indent=1))
    print(f"wrote {out}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--stage", choices=("inputs", "synth", "report", "export", "check"),
                    required=True)
    ap.add_argument("--variant", choices=tuple(VARIANTS), default="main")
    ap.add_argument("--scenes", nargs="*", default=None)
    ap.add_argument("--split", default=None,
                    help="only this split: train, or the held-out split (--heldout-split)")
    ap.add_argument("--train-data", default=str(ROOT / "data" / "sequences"))
    ap.add_argument("--heldout-data", default=str(ROOT / "data" / "classifier_sequences"))
    ap.add_argument("--heldout-seed", type=int, default=1,
                    help="seed of the held-out files (<cell>/<material>_coarse_s<seed>.npz)")
    ap.add_argument("--heldout-split", default="heldout",
                    help="cache split name of those held-out inputs (seed 1: heldout; "
                         "seed 2: fresh); the report's --heldout scores this split")
    ap.add_argument("--cache", default=str(ROOT / "data" / "classifier_synthesis"))
    ap.add_argument("--out", default=str(ROOT / "experiments" / "results" / "classifier"))
    ap.add_argument("--heldout", action="store_true",
                    help="also score the held-out inputs (once, at the end; without it the "
                         "report reads the training inputs only)")
    ap.add_argument("--model-out", default=None,
                    help="--stage export: where to write the synthesis classifier (.npz)")
    ap.add_argument("--check-inputs", nargs="*", default=(),
                    help="--stage check: training inputs as scene/material")
    ap.add_argument("--frames", type=int, default=64)
    ap.add_argument("--settle", type=int, default=12)
    args = ap.parse_args(argv)
    {"inputs": stage_inputs, "synth": stage_synth, "report": stage_report,
     "export": stage_export, "check": stage_check}[args.stage](args)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
