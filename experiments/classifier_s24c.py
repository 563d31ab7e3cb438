"""Issue 25, session 24c: configuration C as a saved classifier, and its consistency check.

C = the exported s80 classifier (synthesis_classifier_s24.npz: session 23's CV pick) with
solver "input" (each input re-simulated with its own metadata's solver settings, i.e. the
`matched` synthesis) instead of "fixed"; nothing else changes (synthesis_rule_s24c.txt).

    python -m experiments.classifier_s24c --stage make     # writes synthesis_classifier_s24c.npz
    python -m experiments.classifier_s24c --stage check --inputs cape_dance/silk_charmeuse
    python -m experiments.classifier_s24c --stage windows \
        --out experiments/results/classifier/s24c_seed3   # accuracy vs windows, reliability

`check` runs `synthesis_model.classify` with C on seed-3 input files and compares the distances it
implies (nearest distance + T x log-probability ratios) with the study's scoring of the same
inputs: `Distance` of the s80 spec fitted on the s80 training syntheses, applied to the cached
`matched` features of split fresh3 (what the report's `heldout_variants.matched` scores).
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import json
import subprocess
from pathlib import Path

import numpy as np

from wrinkle_jax import MATERIALS
from wrinkle_jax.classifier import calibrated as cal
from wrinkle_jax.classifier import synthesis_model
from wrinkle_jax.classifier.synthesis_study import Distance, check_inputs, load_entries
from wrinkle_jax.evaluation.suite import portable_path
from wrinkle_jax.fileio import atomic_write_text

ROOT = Path(__file__).resolve().parents[1]
RES = ROOT / "experiments" / "results" / "classifier"
S80 = RES / "synthesis_classifier_s24.npz"
C_PATH = RES / "synthesis_classifier_s24c.npz"


def stage_make(args) -> None:
    clf = synthesis_model.load(S80)
    meta = dict(clf.meta)
    meta["configuration"] = ("C (session 24c): the s80 classifier of synthesis_classifier_s24.npz "
                             "unchanged, solver 'input' (matched synthesis: the input's own "
                             "solver settings from its metadata)")
    meta["rule"] = "experiments/results/classifier/synthesis_rule_s24c.txt"
    meta["derived_from"] = {"file": str(S80.relative_to(ROOT)), "commit": clf.meta.get("commit"),
                            "solver": clf.solver}
    rep = Path(args.report)
    if rep.exists():
        r = json.loads(rep.read_text())["heldout_variants"]["matched"]
        a = r["all"]
        meta["seed3"] = {k: a[k] for k in ("n", "seq_acc", "coverage", "acc_where_answers",
                                           "group_acc", "ece", "nll")}
        meta["seed3"]["skinned"] = r.get("skinned")
        meta["seed3"]["report"] = str(rep.relative_to(ROOT))
    meta["date"] = datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds")
    meta["commit_s24c"] = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT,
                                         capture_output=True, text=True).stdout.strip()
    c = dataclasses.replace(clf, solver="input", meta=meta)
    out = synthesis_model.save(args.model_out or C_PATH, c)
    print("wrote", out, out.stat().st_size, "bytes")


def stage_check(args) -> None:
    clf = synthesis_model.load(args.model_out or C_PATH)
    assert clf.solver == "input"
    cache = Path(args.cache)
    train = [e for e in load_entries(cache, "s80") if e["split"] == "train"]
    dist = Distance(clf.meta["spec"], train)
    held = [e for e in load_entries(cache, "matched") if e["split"] == args.split]
    rows = []
    for name, _, row in check_inputs(clf, dist, held, args.inputs, args.data, args.seed):
        rows.append({"input": name, **row})
        print("check", json.dumps(rows[-1]), flush=True)
    out = Path(args.out) / "synthesis_export_check.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    model = portable_path(args.model_out or C_PATH)
    atomic_write_text(out, json.dumps({"model": model, "rows": rows}, indent=1))
    print(f"wrote {out}")


def stage_windows(args) -> None:
    """Descriptive, after the ship decision (no choice depends on it): C's answers on the
    cached matched features of `--split` using only the first k of the 3 windows (k x 16 + 16
    frames compared), and C's reliability table and diagram on the full windows."""
    clf = synthesis_model.load(args.model_out or C_PATH)
    held = [e for e in load_entries(Path(args.cache), "matched") if e["split"] == args.split]
    labels = np.array([e["label"] for e in held])
    rows = []
    for k in range(1, min(len(e["input"]) for e in held) + 1):
        res = [synthesis_model.decide(clf, clf.distances(e["input"][:k], e["synth"][:, :k]), k)
               for e in held]
        pred = np.array([MATERIALS.index(max(r.scores, key=r.scores.get)) for r in res])
        ans = np.array([not r.abstained for r in res])
        rows.append({"windows": k, "frames_compared": clf.window + (k - 1) * clf.stride,
                     "seq_acc": float(np.mean(pred == labels)), "coverage": float(ans.mean()),
                     "acc_where_answers": float(np.mean(pred[ans] == labels[ans]))
                     if ans.any() else None})
        print("windows", json.dumps(rows[-1]), flush=True)
    probs = np.array([[r.scores[m] for m in MATERIALS] for r in res])
    counts, conf, acc, ece = cal.reliability(probs, labels)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out / "windows_and_reliability.json", json.dumps(
        {"split": args.split, "n": len(held), "by_windows": rows,
         "reliability": {"counts": counts.tolist(), "mean_confidence": conf.tolist(),
                         "accuracy": acc.tolist(), "ece": ece}}, indent=1, default=float))
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(4, 4))
    ok = counts > 0
    ax.plot([0, 1], [0, 1], "k:", lw=1)
    ax.plot(conf[ok], acc[ok], "o-")
    for c, a, n in zip(conf[ok], acc[ok], counts[ok], strict=True):
        ax.annotate(str(n), (c, a), textcoords="offset points", xytext=(4, -10), fontsize=8)
    ax.set(xlabel="confidence (max p)", ylabel="accuracy", xlim=(0, 1), ylim=(0, 1.05),
           title=f"shipped classifier, {args.split}: ECE {ece:.2f}")
    fig.tight_layout()
    fig.savefig(out / "reliability.png", dpi=100)
    print(f"wrote {out}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--stage", choices=("make", "check", "windows"), required=True)
    ap.add_argument("--model-out", default=None)
    ap.add_argument("--report", default=str(RES / "s24c_seed3" / "synthesis_report.json"))
    ap.add_argument("--cache", default=str(ROOT / "data" / "classifier_synthesis"))
    ap.add_argument("--data", default=str(ROOT / "data" / "classifier_sequences_s3"))
    ap.add_argument("--seed", type=int, default=3)
    ap.add_argument("--split", default="fresh3")
    ap.add_argument("--inputs", nargs="*", default=("cape_dance/silk_charmeuse",))
    ap.add_argument("--out", default=str(RES / "s24c_export_check"))
    args = ap.parse_args(argv)
    {"make": stage_make, "check": stage_check, "windows": stage_windows}[args.stage](args)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
