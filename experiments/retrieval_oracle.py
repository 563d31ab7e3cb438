"""Can real fine wrinkles, retrieved from the training data, replace the coarse map's detail?

    python -m experiments.retrieval_oracle [--bank 64] [--queries 32]

Validation data only (the tabard, `valgarment`; the bank is the TRAIN split). Per material, a
bank of `--bank` fully covered training patches (evenly spaced) with the detail maps of their
coarse input and fine target (`wrinkle_jax.detail`, sigma 8 texels) and their VGG Grams
(`evaluation.gram.flat_grams`), and the `fidelity val` queries (`--queries` evenly spaced
tabard patches per material). Each method puts one bank patch's FINE detail on the query's
coarse large scale (`detail.from_detail_rgb`) and is scored with the detail-only score
against the query's fine patch, paired against the per-material unsharp base:

  oracle_bank     the bank patch whose fine Gram is closest to the query's TARGET (uses the
                  target: the ceiling of any retrieval from this bank)
  knn1            the bank patch whose COARSE Gram is closest to the query's coarse one
  knnK_medoid     among the K nearest by coarse Gram, the fine patch with the least summed
                  Gram loss to the other K fines (the texture minimising the expected loss)
  uncond_medoid   the material's most typical fine texture (medoid of the whole bank)
  random          a random bank patch

Writes `experiments/results/fidelity/retrieval_oracle.json`.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from wrinkle_jax import MATERIALS, data, detail, evaluation
from wrinkle_jax.evaluation import gram, suite
from wrinkle_jax.evaluation import methods as method_lib
from wrinkle_jax.nn import vgg

OUT = suite.RESULTS / "fidelity" / "retrieval_oracle.json"
SIGMA = detail.DEFAULT_SIGMA
KS = (5, 20)


def _medoid(cand: np.ndarray, d_fine: np.ndarray) -> int:
    sub = d_fine[np.ix_(cand, cand)]
    return int(cand[sub.sum(1).argmin()])


def material_choices(vgg_params, bank: dict, query: dict, rng) -> tuple[dict, np.ndarray]:
    """Bank indices chosen per method for each query, and the bank's fine detail maps."""
    b_in, b_tg, b_m = bank["input"], bank["target"], bank["mask"]
    bd_in = np.asarray(detail.to_detail_rgb(b_in, b_m, SIGMA))
    bd_tg = np.asarray(detail.to_detail_rgb(b_tg, b_m, SIGMA))
    g_bin, g_btg = (gram.flat_grams(vgg_params, x, b_m) for x in (bd_in, bd_tg))
    qd_in, qd_tg = (np.asarray(x) for x in detail.on_reference_branch_rgb(
        query["input"], (query["target"],), query["mask"], SIGMA))
    g_qin, g_qtg = (gram.flat_grams(vgg_params, x, query["mask"]) for x in (qd_in, qd_tg))
    d_fine = gram.pairwise_losses(g_btg, g_btg)
    order = np.argsort(gram.pairwise_losses(g_qin, g_bin), axis=1)
    n = len(query["input"])
    choice = {"oracle_bank": gram.pairwise_losses(g_qtg, g_btg).argmin(1),
              "knn1": order[:, 0]}
    for k in KS:
        choice[f"knn{k}_medoid"] = np.asarray([_medoid(order[i, :k], d_fine) for i in range(n)])
    choice["uncond_medoid"] = np.full(n, _medoid(np.arange(len(b_in)), d_fine))
    choice["random"] = rng.integers(0, len(b_in), n)
    return choice, bd_tg


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", default=str(suite.ROOT / "data" / "pairs"))
    ap.add_argument("--bank", type=int, default=64, help="bank patches per material")
    ap.add_argument("--queries", type=int, default=32, help="tabard patches per material")
    ap.add_argument("--out", default=str(OUT))
    args = ap.parse_args(argv)
    vgg_params = vgg.load_vgg19()
    train = data.PatchDataset(args.data, "train")
    val = data.PatchDataset(args.data, "valgarment")
    settings = method_lib.material_unsharp_settings()
    rng = np.random.default_rng(0)
    scores: dict[str, list] = {}
    t0 = time.time()
    for mid, mat in enumerate(MATERIALS):
        rows = np.flatnonzero(val.materials == mid)
        query = val.get(rows[np.unique(np.linspace(0, len(rows) - 1, args.queries)
                                       .round().astype(int))])
        brows = np.flatnonzero(train.materials == mid)
        cand = train.get(brows[np.linspace(0, len(brows) - 1, min(len(brows), 4 * args.bank))
                               .round().astype(int)])
        full = np.flatnonzero(cand["mask"].mean(axis=(1, 2, 3)) > 0.99)
        full = full[np.linspace(0, len(full) - 1, min(args.bank, len(full))).round().astype(int)]
        bank = {k: cand[k][full] for k in ("input", "target", "mask")}
        choice, bd_tg = material_choices(vgg_params, bank, query, rng)
        m = query["mask"]
        _, large, branch = detail.decompose(query["input"] * 2.0 - 1.0, m, SIGMA)
        outs = {"unsharp_material": evaluation.unsharp_mask(query["input"], m, *settings[mid],
                                                            order=1)}
        outs.update({k: detail.from_detail_rgb(bd_tg[c], large, branch, m)
                     for k, c in choice.items()})
        outs = {k: np.asarray(v, np.float32) * m for k, v in outs.items()}
        d_in, d_tgt, *d_outs = (np.asarray(x) for x in detail.on_reference_branch_rgb(
            query["input"], (query["target"], *outs.values()), m, SIGMA))
        losses = gram.method_losses(vgg_params, d_in, d_tgt, m,
                                    dict(zip(outs, d_outs, strict=True)))
        for k in outs:
            sc = evaluation.scores_from_losses(losses["input"], losses[k])
            scores.setdefault(k, []).append(np.where(sc["valid"], sc["improvement_signed"],
                                                     np.nan))
        print(f"{mat}: bank {len(full)}, " + ", ".join(
            f"{k} {np.nanmedian(v[-1]):+.1f}" for k, v in scores.items())
            + f" ({time.time() - t0:.0f} s)", flush=True)
    cat = {k: np.concatenate(v) for k, v in scores.items()}
    base = cat["unsharp_material"]
    got = {"split": "valgarment", "bank_per_material": args.bank,
           "queries_per_material": args.queries, "detail_sigma": SIGMA, "methods": {}}
    for k, v in cat.items():
        entry = {"median": float(np.nanmedian(v)), "mean": float(np.nanmean(v))}
        if k != "unsharp_material":
            ok = np.isfinite(v) & np.isfinite(base)
            entry["vs_unsharp_material"] = evaluation.paired_difference(
                np.nan_to_num(v), np.nan_to_num(base), ok)
        got["methods"][k] = entry
        pd = entry.get("vs_unsharp_material")
        print(f"{k}: median {entry['median']:+.1f} (mean {entry['mean']:+.1f})"
              + (f", paired {pd['median_diff']:+.1f} [{pd['median_diff_ci'][0]:+.1f}, "
                 f"{pd['median_diff_ci'][1]:+.1f}]" if pd else ""), flush=True)
    suite.write_json(args.out, got)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
