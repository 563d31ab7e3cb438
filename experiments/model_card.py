"""Held-out scores of the shipped enhancer against the non-learned baselines (model card data).

    python -m experiments.model_card [--model wrinkle_jax/assets/enhancer.npz] [--n 480]

Patches: the held-out split of `data/patches` (`experiments.make_dataset`): the test-only
scenes dress_dance (unseen garment), cape_walk (unseen garment and motion) and skirt_walk
(seen garment, unseen motion), all five materials, input = the fine map downsampled to the
coarse particle distance, target = the fine map; plus `--n-seen` patches of the training split
(seen garments and motions: training data, for reference). Methods on the same patches:

  * identity (the input unchanged: improvement 0 by definition);
  * unsharp mask, the best (sigma, amount) of a small sweep on TRAINING patches;
  * bicubic down/up-sampling by 2 and Lanczos down/up-sampling by 2;
  * the model.

Score: `evaluation.score_patches` (paper's improvement score on relu1_2..relu5_1, plus the
signed form). Writes `experiments/results/model_card/results.json` and `table.md`.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import cv2
import jax.numpy as jnp
import numpy as np

from wrinkle_jax import MATERIALS, data, enhancer, evaluation
from wrinkle_jax.nn import vgg

ROOT = Path(__file__).resolve().parents[1]
UNSEEN_GARMENT = {"dress_dance", "cape_walk"}
SWEEP = [(s, a) for s in (1.0, 2.0, 4.0, 8.0) for a in (0.5, 1.0, 2.0, 4.0)]


def take(ds: data.PatchDataset, n: int) -> dict:
    idx = np.unique(np.linspace(0, len(ds) - 1, min(n, len(ds))).round().astype(int))
    b = ds.get(idx)
    b["scene"] = np.array([ds.entries[j]["scene"] for j in ds.sequence_of[idx]])
    return b


def run_model(enh: enhancer.Enhancer, batch: dict, size: int = 16) -> tuple[np.ndarray, float]:
    apply = enhancer.make_apply(enh)
    n = len(batch["input"])
    outs, t_net = [], 0.0
    for s in range(0, n, size):
        idx = np.resize(np.arange(s, min(s + size, n)), size)
        x, m = jnp.asarray(batch["input"][idx]), jnp.asarray(batch["material"][idx])
        if s == 0:
            apply(enh.params, x, m).block_until_ready()  # compile outside the timing
        t0 = time.perf_counter()
        o = np.asarray(apply(enh.params, x, m))
        t_net += time.perf_counter() - t0
        outs.append(o[:min(size, n - s)])
    out = np.concatenate(outs) * 2 - 1
    out = out / np.maximum(np.linalg.norm(out, axis=-1, keepdims=True), 1e-8)
    return ((out + 1) * 0.5 * batch["mask"]).astype(np.float32), 1e3 * t_net / n


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--model", default=str(enhancer.DEFAULT_PATH))
    ap.add_argument("--data", default=str(ROOT / "data" / "patches"))
    ap.add_argument("--n", type=int, default=480)
    ap.add_argument("--n-seen", type=int, default=160)
    ap.add_argument("--n-tune", type=int, default=48)
    ap.add_argument("--out", default=str(ROOT / "experiments" / "results" / "model_card"))
    args = ap.parse_args(argv)
    out_dir = Path(args.out)
    out_dir.mkdir(parents=True, exist_ok=True)
    vgg_params = vgg.load_vgg19()
    enh = enhancer.load_enhancer(args.model)
    held = take(data.PatchDataset(args.data, "heldout"), args.n)
    seen = take(data.PatchDataset(args.data, "train"), args.n_seen)

    # Unsharp-mask parameters chosen on training patches (a different, disjoint subset).
    tune = take(data.PatchDataset(args.data, "train"), args.n_tune)
    sweep = {}
    for s, a in SWEEP:
        sc = evaluation.score_patches(vgg_params, tune["input"],
                                      evaluation.unsharp_mask(tune["input"], tune["mask"], s, a),
                                      tune["target"], tune["mask"])
        sweep[f"sigma={s:g},amount={a:g}"] = float(sc["improvement_signed"][sc["valid"]].mean())
    best = max(sweep, key=sweep.get)
    s_best, a_best = SWEEP[list(sweep).index(best)]

    methods = {
        "identity": lambda b: evaluation.identity(b["input"], b["mask"]),
        f"unsharp ({best})": lambda b: evaluation.unsharp_mask(b["input"], b["mask"], s_best,
                                                               a_best),
        "bicubic x2 down/up": lambda b: evaluation.resample(b["input"], b["mask"], 2.0),
        "lanczos x2 down/up": lambda b: evaluation.resample(b["input"], b["mask"], 2.0,
                                                            up=cv2.INTER_LANCZOS4),
    }
    results = {"model": str(args.model), "model_meta": enh.meta, "unsharp_sweep": sweep,
               "n_heldout": len(held["input"]), "n_seen": len(seen["input"]), "methods": {}}
    for split, batch in (("heldout", held), ("seen", seen)):
        groups = np.array([
            f"{'unseen garment' if sc in UNSEEN_GARMENT else 'seen garment'}|{sc}|"
            f"{MATERIALS[m]}" for sc, m in zip(batch["scene"], batch["material"], strict=True)])
        outs = {name: fn(batch) for name, fn in methods.items()}
        outs["model"], ms = run_model(enh, batch)
        for name, o in outs.items():
            sc = evaluation.score_patches(vgg_params, batch["input"], o, batch["target"],
                                          batch["mask"])
            kind = np.array([g.split("|")[0] for g in groups])
            scene = np.array([g.split("|")[1] for g in groups])
            mat = np.array([g.split("|")[2] for g in groups])
            entry = results["methods"].setdefault(name, {})
            entry[split] = {"all": evaluation.summarize(sc)["all"],
                            "by_kind": evaluation.summarize(sc, kind),
                            "by_scene": evaluation.summarize(sc, scene),
                            "by_material": evaluation.summarize(sc, mat)}
            if name == "model":
                entry[split]["net_ms_per_patch"] = round(ms, 2)
        print(split, {k: round(v[split]["all"]["signed_mean"], 2)
                      for k, v in results["methods"].items()}, flush=True)
    (out_dir / "results.json").write_text(json.dumps(results, indent=1) + "\n")

    def cell(d):
        return (f"{d['improvement_mean']:.1f} ± {d['improvement_std']:.1f} "
                f"({d['signed_mean']:+.1f})") if d.get("n") else "-"

    lines = ["Improvement score, paper form |.| mean ± std (signed mean in brackets; higher is "
             "better, 0 = unchanged input).", "",
             "| method | unseen garments | seen garment, unseen motion | seen (training data) |",
             "|---|---|---|---|"]
    for name, r in results["methods"].items():
        kinds = r["heldout"]["by_kind"]
        lines.append(f"| {name} | {cell(kinds.get('unseen garment', {}))} | "
                     f"{cell(kinds.get('seen garment', {}))} | {cell(r['seen']['all'])} |")
    lines += ["", "Model, held-out patches by material:", "", "| material | n | score |",
              "|---|---|---|"]
    for mat, d in results["methods"]["model"]["heldout"]["by_material"].items():
        if mat != "all":
            lines.append(f"| {mat} | {d['n']} | {cell(d)} |")
    lines += ["", "Model, held-out patches by scene:", "", "| scene | n | score |", "|---|---|---|"]
    for sc_name, d in results["methods"]["model"]["heldout"]["by_scene"].items():
        if sc_name != "all":
            lines.append(f"| {sc_name} | {d['n']} | {cell(d)} |")
    (out_dir / "table.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))



if __name__ == "__main__":
    main()
